"""The lifecycle of what the service keeps about a face: artifacts pruned by age or because
no result names them, and everything derived from one subject's captures forgotten.

Artifacts are content-addressed and name the keys they were made from (their manifest's
``inputs``), so "derived from" is a walk down those links: a subject's videos, photos and
scan are input artifacts, and every stage artifact made from them, directly or not, holds
their face or numbers measured on it.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from facecap_core.dataset import inside
from facecap_core.errors import InputError
from tasks.store import ArtifactStore, input_key


@dataclass
class Removal:
    """What a prune or a forget removed (or, with ``dry_run``, would remove)."""

    artifacts: list[str] = field(default_factory=list)
    folders: list[Path] = field(default_factory=list)
    history_entries: int = 0
    captures: list[str] = field(default_factory=list)
    """``subject/capture`` of each capture forgotten (their UI pages go too)."""


def derived(store: ArtifactStore, keys: set[str]) -> set[str]:
    """The stored artifacts among ``keys`` and every stored artifact made from them."""
    inputs = {key: set(store.manifest(key).inputs.values()) for key in store.keys()}
    found = keys & set(inputs)
    grew = True
    while grew:  # artifacts name their inputs, not their readers: walk until nothing is added
        new = {key for key, made_from in inputs.items() if key not in found and made_from & found}
        found |= new
        grew = bool(new)
    return found


def prune(store: ArtifactStore, before: datetime, dry_run: bool = False) -> Removal:
    """Remove the artifacts committed before ``before`` and every artifact made from them."""
    old = {key for key in store.keys()
           if datetime.fromisoformat(store.manifest(key).created) < before}
    removal = Removal(artifacts=sorted(derived(store, old)))
    if not dry_run:
        for key in removal.artifacts:
            store.delete(key)
    return removal


def referenced(store: ArtifactStore, results: list[Path]) -> set[str]:
    """The artifacts that the run reports under the ``results`` folders name, and every
    artifact they were made from (what a rerun of those captures would reuse)."""
    named = set()
    for folder in results:
        named |= _reported_keys(Path(folder))
    inputs = {key: set(store.manifest(key).inputs.values()) for key in store.keys()}
    found, frontier = set(), named & set(inputs)
    while frontier:  # up the inputs: what each kept artifact was made from
        found |= frontier
        frontier = {k for key in frontier for k in inputs[key] if k in inputs} - found
    return found


def prune_unreferenced(store: ArtifactStore, results: list[Path], before: datetime,
                       dry_run: bool = False) -> Removal:
    """Remove the artifacts committed before ``before`` that no run report under the
    ``results`` folders names, directly or as what a named artifact was made from.

    ``before`` spares the artifacts of runs still in progress: they are named by a report
    only when their run ends."""
    for folder in results:
        if not Path(folder).is_dir():
            raise InputError(f"results folder not found: {folder}; give the --out folders "
                             "whose results keep their artifacts")
    keep = referenced(store, results)
    removal = Removal(artifacts=sorted(
        key for key in set(store.keys()) - keep
        if datetime.fromisoformat(store.manifest(key).created) < before))
    if not dry_run:
        for key in removal.artifacts:
            store.delete(key)
    return removal


def _subject_inputs(root: Path, subject: str) -> set[str]:
    """Keys of the subject's raw inputs: every capture (video or photo folder) and scan file."""
    folder = root / subject
    if not folder.is_dir():
        return set()
    return {input_key(path) for path in sorted(folder.iterdir())
            if not path.name.startswith(".") and (path.is_file() or path.is_dir())}


def _capture_labels(subject: str, root: Path | None, results: Path | None) -> list[str]:
    """``subject/capture`` of the subject's captures in the dataset and the results folder."""
    names = set()
    if root is not None and (Path(root) / subject).is_dir():
        names |= {p.stem if p.is_file() else p.name for p in (Path(root) / subject).iterdir()
                  if not p.name.startswith(".") and not p.name.startswith(("scan.",
                                                                            "scan_landmarks."))}
    if results is not None and results.is_dir():
        names |= {p.name for p in results.iterdir() if p.is_dir()}
    return sorted(f"{subject}/{name}" for name in names)


def _reported_keys(folder: Path) -> set[str]:
    """The artifact keys named by the run reports under a subject's results folder."""
    keys = set()
    for report in folder.rglob("report.json"):
        try:
            keys |= {row["key"] for row in json.loads(report.read_text())["stages"].values()}
        except (OSError, ValueError, KeyError, TypeError):
            continue  # not a facecap report: its folder is removed all the same
    return keys


def _forget_history(out: Path, subject: str, dry_run: bool) -> int:
    """Drop the subject's captures from the nightly evaluation history; returns how many
    entries went."""
    removed = 0
    for path in sorted((out / "evaluations").glob("*.json")):
        try:
            doc = json.loads(path.read_text())
            captures = doc["captures"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        names = [name for name in captures if name.split("/", 1)[0] == subject]
        if not names:
            continue
        removed += len(names)
        for name in names:
            del captures[name]
        doc["regressions"] = [r for r in doc.get("regressions", [])
                              if str(r.get("capture", "")).split("/", 1)[0] != subject]
        if not dry_run:
            path.write_text(json.dumps(doc, indent=1))
    return removed


def forget(store: ArtifactStore, subject: str, root: Path | None, out: Path | None,
           dry_run: bool = False) -> Removal:
    """Remove every artifact derived from ``subject``'s captures and scan (found through the
    dataset folder ``root`` and the run reports under ``out/<subject>``), the subject's
    results folder and its entries in the evaluation history."""
    if not subject or subject in (".", "..") or "/" in subject or "\\" in subject:
        raise InputError(f"{subject!r} is not a subject name; give the name of a folder in "
                         "the dataset, such as 'alice'")
    seeds: set[str] = set()
    removal = Removal()
    if root is not None:
        seeds |= _subject_inputs(Path(root), subject)
    results = Path(out) / subject if out is not None else None
    if results is not None and results.is_dir():
        inside(Path(out), results, "results folder")  # a link out of OUT is not followed
        seeds |= _reported_keys(results)
        removal.folders.append(results)
    if not seeds and not removal.folders:
        raise InputError(f"nothing of subject {subject!r} was found (no {subject}/ in the "
                         "dataset folder or the results folder); check the name, --root and "
                         "--out")
    removal.artifacts = sorted(derived(store, seeds))
    removal.captures = _capture_labels(subject, root, results)
    if out is not None:
        removal.history_entries = _forget_history(Path(out), subject, dry_run)
    if not dry_run:
        for key in removal.artifacts:
            store.delete(key)
        for folder in removal.folders:
            shutil.rmtree(folder)
    return removal
