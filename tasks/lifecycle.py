"""The lifecycle of what the service keeps about a face: artifacts pruned by age or because
no result names them, and everything derived from one subject's captures forgotten.

Artifacts are content-addressed and name the keys they were made from (their manifest's
``inputs``), so "derived from" is a walk down those links: a subject's videos, photos and
scan are input artifacts, and every stage artifact made from them, directly or not, holds
their face or numbers measured on it.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from facecap.tasks.outputs import (
    RECORD_NAME,
    ResultWriter,
    check_output_place,
    remove_results,
)
from facecap.tasks.own_files import NAME_MAX, OwnFileError, read_json
from facecap.tasks.runner import key_lock, unleased
from facecap.tasks.store import ArtifactStore, CorruptArtifactError, input_key
from facecap.tasks.store.base import redact
from facecap.tasks.store.keys import KEY_PATTERN
from facecap_core.dataset import SUMMARY_NAMES
from facecap_core.errors import InputError


@dataclass
class Removal:
    """What a prune or a forget removed (or, with ``dry_run``, would remove)."""

    artifacts: list[str] = field(default_factory=list)
    folders: list[Path] = field(default_factory=list)
    history_entries: int = 0
    captures: list[str] = field(default_factory=list)
    """``subject/capture`` of each capture forgotten (their UI pages go too)."""
    in_use: list[str] = field(default_factory=list)
    """Artifacts kept because a run in progress holds them (see :func:`facecap.tasks.runner.lease`)."""
    damaged: dict[str, str] = field(default_factory=dict)
    """Artifacts a prune kept because their manifest cannot be read (so neither can their
    age): their key and the one-line problem, which says what to do."""
    files: list[Path] = field(default_factory=list)
    """The files of the results folders removed: those a results record there names with
    the content facecap wrote (:func:`facecap.tasks.outputs.remove_results`)."""
    kept: list[Path] = field(default_factory=list)
    """What the results folders hold that facecap cannot prove it wrote: it stays."""


def _made_from(manifests: dict) -> dict[str, set[str]]:
    """Each stored artifact's input keys (its manifest's ``inputs``)."""
    return {key: set(manifest.inputs.values()) for key, manifest in manifests.items()}


def _manifests(store: ArtifactStore) -> dict:
    """Every stored artifact's manifest, read once per command."""
    return {key: store.manifest(key) for key in store.keys()}


def _dated_manifests(store: ArtifactStore) -> tuple[dict, dict[str, str]]:
    """The manifests a prune can read (and so date), and why each of the others cannot be
    read: one damaged manifest must neither stop a prune nor be removed as old."""
    manifests, damaged = {}, {}
    for key in store.keys():
        try:
            manifests[key] = store.manifest(key)
        except CorruptArtifactError as exc:
            damaged[key] = str(exc)
    return manifests, damaged


def _down(made_from: dict[str, set[str]], keys: set[str]) -> set[str]:
    found = keys & set(made_from)
    grew = True
    while grew:  # artifacts name their inputs, not their readers: walk until nothing is added
        new = {key for key, inputs in made_from.items() if key not in found and inputs & found}
        found |= new
        grew = bool(new)
    return found


def _up(made_from: dict[str, set[str]], keys: set[str]) -> set[str]:
    found, frontier = set(), keys & set(made_from)
    while frontier:  # up the inputs: what each artifact was made from
        found |= frontier
        frontier = {k for key in frontier for k in made_from[key] if k in made_from} - found
    return found


def derived(store: ArtifactStore, keys: set[str]) -> set[str]:
    """The stored artifacts among ``keys`` and every stored artifact made from them."""
    return _down(_made_from(_manifests(store)), keys)


def prune(store: ArtifactStore, before: datetime, dry_run: bool = False) -> Removal:
    """Remove the artifacts committed before ``before`` and every artifact made from them."""
    manifests, damaged = _dated_manifests(store)
    old = {key for key, m in manifests.items() if m.created_at < before}
    removal = Removal(artifacts=sorted(_down(_made_from(manifests), old)), damaged=damaged)
    if not dry_run:
        _delete(store, removal)
    return removal


def prune_unreferenced(store: ArtifactStore, results: list[Path], before: datetime,
                       dry_run: bool = False) -> Removal:
    """Remove the artifacts committed before ``before`` that no run report under the
    ``results`` folders names, directly or as what a named artifact was made from (what a
    rerun of those captures would reuse stays).

    ``before`` spares the artifacts of runs still in progress: they are named by a report
    only when their run ends."""
    for folder in results:
        if Path(folder).exists() and not Path(folder).is_dir():
            raise InputError(f"the results folder {folder} is a file; give the --out folders "
                             "whose results keep their artifacts")
        if not Path(folder).is_dir():
            raise InputError(f"results folder not found: {folder}; give the --out folders "
                             "whose results keep their artifacts")
        _check_reports_readable(Path(folder))  # a damaged report first: it names the file
        if next(_run_reports(Path(folder)), None) is None:  # a wrong folder keeps nothing
            raise InputError(f"{folder} holds no facecap results (no report.json under it); "
                             "give the results folder the runs wrote (--out)")
    manifests, damaged = _dated_manifests(store)
    named = set().union(*(_reported_keys(Path(folder))[0] for folder in results))
    keep = _up(_made_from(manifests), named)
    removal = Removal(artifacts=sorted(
        key for key, m in manifests.items() if key not in keep and m.created_at < before),
        damaged=damaged)
    if not dry_run:
        _delete(store, removal)
    return removal


def _check_reports_readable(folder: Path) -> None:
    """Refuse, before anything is deleted, a results folder with a ``report.json`` that cannot
    be read or is no JSON: the artifacts of the run it may report would be pruned as
    unreferenced. A link or a folder of that name is none of facecap's (its writer writes
    neither) and is passed over, as is JSON that names no stages (a file of the user's)."""
    for path in folder.rglob("report.json"):
        if path.is_symlink() or not path.is_file():
            continue
        try:
            read_json(path)
        except OSError as exc:
            raise InputError(f"the run report {path} cannot be read ({exc.strerror}); make it "
                             "readable or move it out of the results folder, then prune again "
                             "(nothing was removed)") from None
        except OwnFileError as exc:  # not UTF-8, not JSON, nested or grown past facecap's
            raise InputError(f"the run report {path} is damaged ({exc.problem}): the "
                             "artifacts of its run could not be kept; restore it or move it out "
                             "of the results folder, then prune again (nothing was removed)"
                             ) from None


def _delete(store: ArtifactStore, removal: Removal) -> None:
    """Delete the removal's artifacts, each under its key's lock (a run computing one of
    them finishes its commit first, and a later run computes it again); one that a run in
    progress reads or made is kept (moved to ``removal.in_use``): the run would fail or
    hand out results whose artifacts are gone."""

    kept = []
    for key in removal.artifacts:
        # The lease first, without waiting: a run computing the key holds its lease too, so
        # a leased key is never waited for, and the lock below waits only for another prune.
        with unleased(store, key) as free:
            if not free:
                kept.append(key)
                continue
            with key_lock(store, key):
                store.delete(key)
    removal.artifacts = [key for key in removal.artifacts if key not in kept]
    removal.in_use = kept


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


def _run_reports(folder: Path, paths: Iterable[Path] | None = None) -> Iterator[dict]:
    """The run reports under a results folder (or among ``paths``): each ``report.json``
    whose ``stages`` name each stage's artifact key. Other files of that name are passed
    over."""
    for path in folder.rglob("report.json") if paths is None else paths:
        if path.name != "report.json":
            continue
        try:
            doc = read_json(path)  # a FIFO, a link, a JSON bomb: no report of facecap's
            keys = [row["key"] for row in doc["stages"].values()]
        except (OSError, OwnFileError, KeyError, TypeError, AttributeError):
            continue
        if keys and all(isinstance(key, str) for key in keys):
            yield doc


def report_keys(doc: dict) -> tuple[str | None, list[str]]:
    """The artifact keys a run report names: its page's
    (:func:`facecap.pages.stored.store_page`; None without one), and its stages' with its
    page's parts' (:func:`facecap.pages.stored.keep_parts`, what a rerun's page reuses),
    leaving out whatever is not a key (a results folder is anyone's to write)."""
    def key(row, field: str = "key") -> str | None:
        value = row.get(field) if isinstance(row, dict) else None
        return value if isinstance(value, str) and KEY_PATTERN.fullmatch(value) else None

    stages = doc.get("stages") if isinstance(doc.get("stages"), dict) else {}
    made = [k for k in (*map(key, stages.values()), key(doc.get("page"), "parts")) if k]
    return key(doc.get("page")), made


def _reported_keys(folder: Path, paths: Iterable[Path] | None = None
                   ) -> tuple[set[str], set[str], set[str]]:
    """The artifact keys named by the run reports under a results folder (or among
    ``paths``), the stores the reports say the runs used and the runs' ``subject/capture``
    labels (their UI pages)."""
    keys, stores, labels = set(), set(), set()
    for doc in _run_reports(folder, paths):
        page, stages = report_keys(doc)
        keys |= {*stages, *([page] if page else [])}
        if doc.get("store"):
            stores.add(str(doc["store"]))
        if doc.get("subject") and doc.get("capture"):
            labels.add(f"{doc['subject']}/{doc['capture']}")
    return keys, stores, labels


def _same_store(a: str, b: str) -> bool:
    if "://" in a or "://" in b:
        return a.rstrip("/") == b.rstrip("/")
    return Path(a).expanduser().resolve() == Path(b).expanduser().resolve()


def _of(subject: str, name: object) -> bool:
    return str(name).split("/", 1)[0] == subject


def _without(subject: str, doc):
    """A summary the runs write into OUT (an evaluation, ``dataset.json``,
    ``consistency.json``) without the subject's entries."""
    def rows(items: list) -> list:
        return [r for r in items if not (isinstance(r, dict) and r.get("subject") == subject)]

    if isinstance(doc, list):  # consistency.json
        return rows(doc)
    if not isinstance(doc, dict):
        return doc
    doc = dict(doc)
    for key in ("captures", "carried", "failed"):
        if isinstance(doc.get(key), dict):
            doc[key] = {n: v for n, v in doc[key].items() if not _of(subject, n)}
    for key in ("done", "skipped"):
        if isinstance(doc.get(key), list):
            doc[key] = [n for n in doc[key] if not _of(subject, n)]
    if isinstance(doc.get("regressions"), list):
        doc["regressions"] = [r for r in doc["regressions"]
                              if not (isinstance(r, dict) and _of(subject, r.get("capture")))]
    if isinstance(doc.get("consistency"), list):
        doc["consistency"] = rows(doc["consistency"])
    return doc


def _forget_summaries(out: Path, subject: str) -> tuple[dict[str, bytes], int, list[Path]]:
    """The evaluation history and the dataset summaries without the subject's captures
    (each changed file's name relative to ``out`` and its new content), how many history
    entries go, and the summaries that cannot be read (kept as they are)."""
    removed, rewritten, unreadable = 0, {}, []
    history = sorted((out / "evaluations").glob("*.json"))
    for path in [*history, out / "dataset.json", out / "consistency.json"]:
        try:
            doc = read_json(path)
        except FileNotFoundError:
            continue
        except (OSError, OwnFileError):
            # A FIFO, a link, a JSON bomb or a damaged file is no summary facecap can
            # rewrite: it is kept and listed with what else the user must look at, and the
            # forget goes on. Refusing would hold every subject's erasure (faces in the
            # store, results) hostage to one planted file; what it holds, if anything of
            # the subject, is for the user to judge, as with any file facecap did not write.
            unreadable.append(path)
            continue
        kept = _without(subject, doc)
        if kept == doc:
            continue
        if path in history and isinstance(doc, dict) and isinstance(doc.get("captures"), dict):
            removed += len(doc["captures"]) - len(kept["captures"])
        rewritten[path.relative_to(out).as_posix()] = json.dumps(kept, indent=1).encode()
    return rewritten, removed, unreadable


def _check_places(out: Path, root: Path | None, subject: str, store: ArtifactStore) -> None:
    """Refuse a results folder that cannot be one: the file system's root, the dataset
    folder, a folder in the store or facecap's own, one whose subject folder is in the
    dataset folder or holds it."""
    try:
        target = Path(out).resolve()
        dataset = Path(root).resolve() if root is not None else None
    except (OSError, RuntimeError):
        raise InputError(f"the results folder {out} cannot be looked up (a link that leads "
                         "back to itself?); give the folder the runs wrote (--out)") from None
    if target == Path(target.anchor):
        raise InputError(f"--out {out} is the root of the file system, not a results folder; "
                         "give the folder the runs wrote (--out); nothing was removed")
    url = str(store.url)
    check_output_place(out, None if "://" in url and not url.startswith("file://") else url,
                       (root,))
    if dataset is not None:
        results = target / subject
        if results == dataset or dataset in results.parents or results in dataset.parents:
            raise InputError(f"{Path(out) / subject} is in the dataset folder {root} or holds "
                             "it: its captures are no results; give the folder the runs wrote "
                             "(--out); nothing was removed")


def plan_forget(store: ArtifactStore, subject: str, root: Path | None,
                out: Path | None) -> Removal:
    """What forgetting ``subject`` removes: every artifact derived from the subject's
    captures and scan (found through the dataset folder ``root`` and the run reports under
    ``out/<subject>``, with what those were made from, and the copies of the results' meshes
    the nightly evaluation stored), the subject's results folder and UI pages. Removes
    nothing; refuses what it cannot do safely."""
    if (not subject or subject in (".", "..") or "/" in subject or "\\" in subject
            or subject.startswith(".") or "\x00" in subject):
        raise InputError(f"{subject!r} is not a subject name; give the name of a folder in "
                         "the dataset, such as 'alice'")
    if len(os.fsencode(subject)) > NAME_MAX:  # no folder has it: the look-up would fail
        raise InputError(f"the subject name {subject[:24]!r}... is {len(os.fsencode(subject))} "
                         f"bytes long, longer than a folder name can be ({NAME_MAX}); give the "
                         "name of a folder in the dataset")
    if subject in SUMMARY_NAMES:
        raise InputError(f"{subject!r} is a summary the dataset and evaluation runs write, not "
                         "a subject; give the name of a subject's folder")
    seeds: set[str] = set()
    removal = Removal()
    made_from = _made_from(_manifests(store))
    if root is not None:
        if not Path(root).is_dir():
            raise InputError(f"dataset folder not found: {root}; check the path (--root)")
        seeds |= _subject_inputs(Path(root), subject)
    if out is not None:
        _check_places(Path(out), root, subject, store)
    results = Path(out) / subject if out is not None else None
    labels: set[str] = set()
    if results is not None and (results.exists() or results.is_symlink()):
        if results.is_symlink() or results.resolve() != Path(out).resolve() / subject:
            raise InputError(f"{results} is a link; a subject's results folder must be a "
                             "plain folder of the results folder (remove the link)")
        if not results.is_dir():
            raise InputError(f"{results} is a file, not a subject's results folder; check the "
                             "name and --out")
        # Only what facecap can prove it wrote there: the files its records name, as written.
        removal.files, removal.kept = remove_results(results, dry_run=True)
        # A record is facecap's own file: remove_results takes every one it finds.
        if removal.kept and not any(f.name == RECORD_NAME for f in removal.files):
            raise InputError(
                f"{results} holds no record of a facecap result, so nothing in it can be shown "
                "to be facecap's (results written before facecap kept records, or files of "
                "your own): remove what you no longer want from it yourself, then run forget "
                "again; nothing was removed")
        reported, stores, labels = _reported_keys(results, removal.files)
        others = [u for u in stores if not _same_store(u, str(store.url))]
        if reported and not reported & set(made_from) and others:
            raise InputError(
                f"none of the {len(reported)} artifacts the reports under {results} name is in "
                f"the store {store.shown_url}; the runs used "
                f"{', '.join(redact(u) for u in sorted(others))}: give that "
                "store (--store); nothing was removed")
        seeds |= _up(made_from, reported)  # the video and scan they were made from
        seeds |= {input_key(mesh) for mesh in removal.files
                  if mesh.name == "mesh.ply"}  # the nightly's copies
        removal.folders.append(results)
    if not seeds and not removal.folders:
        raise InputError(f"nothing of subject {subject!r} was found (no {subject}/ in the "
                         "dataset folder or the results folder); check the name, --root and "
                         "--out")
    removal.artifacts = sorted(_down(made_from, seeds))
    removal.captures = sorted(set(_capture_labels(subject, root, results)) | labels)
    return removal


def forget(store: ArtifactStore, subject: str, root: Path | None, out: Path | None,
           dry_run: bool = False) -> Removal:
    """Remove what :func:`plan_forget` finds (see :func:`remove`)."""
    return remove(store, plan_forget(store, subject, root, out), subject, out, dry_run)


def remove(store: ArtifactStore, removal: Removal, subject: str, out: Path | None,
           dry_run: bool = False, results: dict[str, bytes] | None = None,
           first: Callable[[], None] | None = None) -> Removal:
    """Carry out a :func:`plan_forget`: the subject's entries dropped from the evaluation
    history and the dataset summaries, ``results`` (more files of ``out`` to write, such as
    the dataset page without the subject), then ``first`` (the UI's pages, which live on the
    Prefect server), the artifacts and what facecap wrote in the results folders.

    Everything that can fail is done before anything is removed: the rewritten files are
    made and staged in ``out`` first (a damaged summary, a folder that cannot be written
    stop the forget there), and put in place once the subject's data is gone."""
    rewritten, removal.history_entries, unreadable = (_forget_summaries(Path(out), subject)
                                                      if out is not None else ({}, 0, []))
    if dry_run:
        removal.kept += unreadable
        return removal
    rewritten.update(results or {})
    with contextlib.ExitStack() as stack:
        writer = stack.enter_context(ResultWriter(out)) if rewritten else None
        for name, data in rewritten.items():
            writer.add(name, data)
        if first is not None:
            first()
        _delete(store, removal)
        removal.files, removal.kept = [], []
        for folder in removal.folders:
            files, kept = remove_results(folder)
            removal.files += files
            removal.kept += kept
        if writer is not None:
            writer.commit()
    removal.kept += unreadable
    return removal
