"""What a capture run shows in the Prefect UI: a stage table, a markdown page with preview
images (embedded as data URIs, so the browser needs no access to the store), a link to the
results, and an event that automations can react to."""

from __future__ import annotations

import asyncio
import base64
import hashlib
import html
import logging
import re
import shutil
import unicodedata
from pathlib import Path

import cv2
import numpy as np
from prefect.artifacts import (
    create_link_artifact,
    create_markdown_artifact,
    create_table_artifact,
)
from prefect.client.orchestration import get_client
from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey
from prefect.events import emit_event

from facecap.pages.dataset import dataset_name, store_dataset_page
from facecap.pages.figures import figure_rows, run_summary
from facecap.pages.stored import PAGE_NAME, RESULTS_LINK_SECONDS, stored_link
from facecap.tasks.lifecycle import report_keys
from facecap.tasks.store import open_store
from facecap_core.evaluation import mesh_render
from facecap_core.meshio import load_mesh
from facecap_core.template import Template, head_frame

_log = logging.getLogger(__name__)


def _slug(text: str) -> str:
    # Artifact keys: lowercase ASCII letters, digits and dashes only, which many names share
    # ("ann/lee-1" and "ann-lee/1", "Bob" and "bob", "Zoë" and "Zoe"): a hash of the exact
    # name keeps every capture's pages apart (and facecap forget from deleting another's).

    plain = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode()
    out = "".join(c if c.isalnum() else "-" for c in plain.lower())
    slug = "-".join(p for p in out.split("-") if p)[:71] or "capture"
    return f"{slug}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


def markdown_text(text: object) -> str:
    """Text shown as itself in the UI's markdown: a capture or folder name cannot add a link,
    an image, HTML or formatting to the page (names come from whoever fills the dataset)."""

    return re.sub(r"([\\`*_{}\[\]()#+\-.!|>~])", r"\\\1", html.escape(str(text), quote=False))


def png_data_uri(path: Path, max_width: int = 960) -> str:
    """A PNG as a data URI, downscaled to ``max_width`` so the artifact stays small."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        return ""
    if image.shape[1] > max_width:
        h = int(round(image.shape[0] * max_width / image.shape[1]))
        image = cv2.resize(image, (max_width, h), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".png", image)
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode() if ok else ""


def mesh_preview(results: dict[str, Path], target: Path) -> Path | None:
    """Render ``target`` from a run's results (name -> file, as :func:`facecap.flows.capture._export`
    staged them): the accuracy heat map (metric protocol) when a scan was given, otherwise
    the mesh in its own colours turned to face the viewer; None without a mesh."""


    if "heatmap_metric.png" in results:
        shutil.copyfile(results["heatmap_metric.png"], target)
        return target
    if "mesh.ply" not in results:
        return None
    mesh = load_mesh(results["mesh.ply"], "mesh")
    vertices = np.asarray(mesh.vertices, float)
    template = Template.default()
    framed = vertices
    if len(vertices) == len(template.vertices):
        # The reconstruction's world frame is the cameras'; turn the face to the viewer.
        R, origin = head_frame(vertices[template.landmarks])
        vertices = (vertices - origin) @ R.T
        framed = vertices[template.regions["face"]]
    # Only colours the file holds: trimesh gives an uncoloured mesh a default grey.
    colours = mesh.visual.vertex_colors[:, :3] if mesh.visual.kind == "vertex" else None
    return mesh_render(vertices, mesh.faces, target, colours, size=320, framed=framed)


def stage_rows(report: dict) -> list[dict]:
    return [{"stage": name, "cached": info["cached"], "seconds": info["seconds"],
             "cpu_seconds": info["cpu_seconds"], "artifact": info["key"]}
            for name, info in report["stages"].items()]


def capture_markdown(report: dict, out: Path, images: list[tuple[str, Path]]) -> str:
    lines = [f"# {markdown_text(report['subject'])} / {markdown_text(report['capture'])}", "",
             f"{run_summary(report)}. Results in {markdown_text(out)}.", ""]
    lines += [f"- {label}: {markdown_text(text)}" for _, label, text in figure_rows(report)]
    for title, path in images:
        uri = png_data_uri(path)
        if uri:
            lines += ["", f"## {title}", "", f"![{title}]({uri})"]
    return "\n".join(lines)


def artifact_keys(label: str) -> list[str]:
    """The keys of the UI artifacts a capture run publishes (every version shares them):
    the stage table, the results page and the link to the results."""
    key = _slug(label)
    return [f"stages-{key}", f"capture-{key}", f"results-{key}"]


def page_link(store, key: str | None, folder: Path) -> tuple[str, str]:
    """``(link, where)`` to a page: a link that opens stored page ``key`` from the Prefect UI
    (:func:`stored_link`), else the ``file://`` address of ``index.html`` in ``folder``,
    which a browser opens only when typed in."""

    link = stored_link(store, key, PAGE_NAME)
    if link:
        return link, f"its page, for {RESULTS_LINK_SECONDS // 3600} h"
    return ((Path(folder).resolve() / PAGE_NAME).as_uri(),
            "its page on the worker's disk: set FACECAP_PAGES_URL and run `facecap pages` "
            "for a link that opens from here")


def results_link(report: dict, out: Path) -> tuple[str, str]:
    """``(link, where)`` to a capture run's page (:mod:`facecap.pages.capture`): :func:`page_link` to
    the page its report names, or to ``index.html`` in the output folder."""

    page, _ = report_keys(report)
    store = open_store(report["store"]) if page else None
    return page_link(store, page, out)


def _legacy_keys(label: str) -> list[str]:
    """The keys earlier versions published under: an ASCII name without the hash (names
    that transliterate alike shared them, so their artifacts are told apart by the
    description, which names the capture); they published no link."""
    key = _slug(label).rsplit("-", 1)[0]
    return [f"stages-{key}", f"capture-{key}"]


def _describes(description: str | None, label: str) -> bool:
    return bool(description) and (description.startswith(f"{label}: ")
                                  or description.startswith(f"stages of {label}: "))


def forget_artifacts(labels: list[str]) -> int:
    """Delete every version of the UI artifacts of these captures (``subject/capture``) from
    the Prefect server the runs reported to; returns how many went."""


    keys = [k for label in labels for k in artifact_keys(label)]
    legacy = {k: label for label in labels for k in _legacy_keys(label)}
    if not keys:
        return 0

    async def delete() -> int:
        deleted = 0
        async with get_client() as client:
            while found := await client.read_artifacts(
                    artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=keys)), limit=200):
                for artifact in found:
                    await client.delete_artifact(artifact.id)
                deleted += len(found)
            offset = 0
            while found := await client.read_artifacts(
                    artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=list(legacy))),
                    limit=200, offset=offset):
                ours = [a for a in found if _describes(a.description, legacy[a.key])]
                for artifact in ours:
                    await client.delete_artifact(artifact.id)
                deleted += len(ours)
                offset += len(found) - len(ours)
        return deleted

    return asyncio.run(delete())


def publish_capture(report: dict, out: Path, label: str, results: dict[str, Path]) -> None:
    """The run's UI artifacts (stage table, results page with its previews, link) and its
    completion event; the previews are read from ``results`` (name -> this run's file), never
    from the output folder, which may hold anything."""

    key = _slug(label)
    stages_key, capture_key, results_key = artifact_keys(label)
    create_table_artifact(stage_rows(report), key=stages_key,
                          description=f"stages of {label}: computed or reused, seconds")
    images = []
    if "preview.png" in results:
        scored = "heatmap_metric.png" in results
        images.append(("Accuracy (metric)" if scored else "Mesh", results["preview.png"]))
    if "heatmap_similarity.png" in results:
        images.append(("Accuracy (similarity)", results["heatmap_similarity.png"]))
    create_markdown_artifact(capture_markdown(report, out, images), key=capture_key,
                             description=f"{label}: results and previews")
    link, where = results_link(report, out)
    create_link_artifact(link, link_text=f"results of {markdown_text(label)}",
                         key=results_key, description=f"{label}: results ({where})")
    emit_event(event="facecap.capture.completed",
               resource={"prefect.resource.id": f"facecap.capture.{key}",
                         "prefect.resource.name": label},
               payload={"out": str(out), "computed": report["computed"],
                        "cached": report["cached"], "figures": report.get("figures", {})})


def dataset_link_key(out: Path) -> str:
    """The key of the UI link to the dataset page of results folder ``out``."""
    return f"dataset-{_slug(str(Path(out).resolve()))}"


def publish_dataset_page(out: Path, store: str) -> None:
    """Link the Prefect UI to the dataset page of ``out`` (just rewritten): a copy kept in
    the store whose links open the captures' pages (:func:`facecap.pages.dataset.
    store_dataset_page`), for :data:`RESULTS_LINK_SECONDS`; else the page on disk."""


    st = open_store(store)
    try:
        key = store_dataset_page(Path(out), st)
    except Exception as exc:  # noqa: BLE001 - the dataset's results are made: a link is not worth failing for
        _log.warning("the dataset page of %s was not kept in the store: %s", out, exc)
        key = None
    link, where = page_link(st, key, out)
    name = dataset_name(Path(out))
    create_link_artifact(link, link_text=f"results of {markdown_text(name)}",
                         key=dataset_link_key(out), description=f"dataset {name}: ({where})")
