"""What a run shows in the Prefect UI: names from the dataset are shown as text."""

from __future__ import annotations

from pathlib import Path

import pytest

from facecap.flows.ui import capture_markdown, markdown_text


def test_capture_and_folder_names_cannot_add_links_images_or_html():
    report = {"subject": "[click](https://evil.example)", "capture": "<img src=x onerror=alert(1)>",
              "computed": 1, "cached": 0, "wall_seconds": 1.0,
              "figures": {"scale": {"sigma_pct": 4.0, "used": ["landmarks"],
                                    "dropped": [{"name": "iris", "reason": "![a](b)"}]}}}
    page = capture_markdown(report, Path("/out/`code` **bold**"), [])
    assert "<img" not in page and "](" not in page and "`code`" not in page
    assert "**bold**" not in page
    # The names are all there, as text.
    assert "click" in page and "evil" in page and "onerror=alert" in page
    assert markdown_text("O'Brien") == "O'Brien"  # an apostrophe is shown as one


def test_the_summary_says_how_smooth_the_face_is():
    report = {"subject": "s", "capture": "c", "computed": 1, "cached": 0, "wall_seconds": 1.0,
              "figures": {"roughness": {"edges": 46220, "bent_share_pct": 3.75,
                                        "median_bend_deg": 2.87, "p90_bend_deg": 11.4,
                                        "bent_deg": 20.0}}}
    page = capture_markdown(report, Path("/out"), [])
    shown = page.replace("\\", "")  # as the markdown renders: its escapes go
    assert "3.8 % of the face's edges bent over 20°, median bend 2.9°" in shown
    assert "1 artifact computed" in shown  # one artifact, not "1 artifacts"
    # A mesh with no face edge measured (another template) shows no line rather than None.
    report["figures"]["roughness"]["bent_share_pct"] = None
    assert "bent over" not in capture_markdown(report, Path("/out"), [])


@pytest.mark.slow
def test_a_forgotten_subjects_ui_pages_are_deleted_and_no_one_elses():
    import asyncio

    from prefect import flow
    from prefect.artifacts import create_markdown_artifact
    from prefect.client.orchestration import get_client
    from prefect.testing.utilities import prefect_test_harness

    from facecap.flows.ui import artifact_keys, forget_artifacts

    async def keys_on_server() -> list[str]:
        async with get_client() as client:
            return sorted(a.key for a in await client.read_artifacts())

    @flow
    def publish(labels: list[str]) -> None:
        for label in labels:
            for key in artifact_keys(label):
                create_markdown_artifact("a face", key=key, description=f"{label}: a page")

    @flow
    def publish_legacy(labels: list[str]) -> None:
        # Earlier versions: the ASCII slug alone, which "Alice/take1" and "alice/take1" share.
        for label in labels:
            create_markdown_artifact("a face", key="capture-alice-take1",
                                     description=f"{label}: results and previews")

    with prefect_test_harness(server_startup_timeout=120):
        # Names whose transliterations meet alice's keep their own pages.
        others = ["bob/take1", "Alice/take1", "alice-take/1", "alice/take-2"]
        publish(["alice/take1", "alice/take1", "alice/take 2", *others])
        publish_legacy(["alice/take1", "Alice/take1"])
        # Three pages per publication (table, results, link), two of alice/take1, and one
        # legacy page.
        assert forget_artifacts(["alice/take1", "alice/take 2"]) == 3 * 3 + 1
        assert asyncio.run(keys_on_server()) == sorted(
            ["capture-alice-take1", *(k for label in others for k in artifact_keys(label))])


STAGE_NAMES = ["keyframes", "poses", "frames", "landmarks", "coarse", "views", "depth",
               "fusion", "fitting", "evaluation"]


def test_the_progress_bar_sends_every_stage_and_the_maps_at_most_so_often(monkeypatch):
    """Each update is a call to the API: the depth maps' updates within a stage are sent at
    most once a second (40 reused maps would be 40 calls), a stage's end always (the UI is
    never left at an earlier stage)."""
    import prefect.artifacts

    from facecap.flows.capture import _RunProgress

    shown = []
    monkeypatch.setattr(prefect.artifacts, "create_progress_artifact", lambda *a, **k: "id")
    monkeypatch.setattr(prefect.artifacts, "update_progress_artifact",
                        lambda _id, percent, description: shown.append(description))
    monkeypatch.setattr(_RunProgress, "EVERY_S", 3600.0)
    progress = _RunProgress("s/c", STAGE_NAMES)
    for name in STAGE_NAMES:
        for i in range(1, 40):
            progress.update(f"{name} map {i} of 40", i / 40, every_s=progress.EVERY_S)
        progress.stage_done(name)
    assert len(shown) == len(STAGE_NAMES) and "(10 of 10 stages)" in shown[-1]


def test_the_progress_bar_follows_the_work_in_whole_percents(monkeypatch):
    """The depth maps and the poses are most of a capture's time: with the poses done and
    17 of 40 depth maps made, the bar is near half way, not at 80 % as when each stage was an
    equal share; it shows whole percents and ends at 100."""
    import prefect.artifacts

    from facecap.flows.capture import _RunProgress

    shown = []
    monkeypatch.setattr(prefect.artifacts, "create_progress_artifact", lambda *a, **k: "id")
    monkeypatch.setattr(prefect.artifacts, "update_progress_artifact",
                        lambda _id, percent, description: shown.append(percent))
    progress = _RunProgress("s/c", STAGE_NAMES)
    stages = STAGE_NAMES
    for name in stages[:6]:
        progress.stage_done(name)
    progress.update("depth map 17 of 40", 17 / 40)
    assert 40 <= shown[-1] <= 60, shown
    for name in stages[6:]:
        progress.stage_done(name)
    assert shown[-1] == 100
    assert all(p == int(p) for p in shown) and shown == sorted(shown)
