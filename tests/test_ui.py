"""What a run shows in the Prefect UI: names from the dataset are shown as text."""

from __future__ import annotations

from pathlib import Path

from flows.ui import capture_markdown


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
