"""Shared fixtures: the ICT Face Model copy in ../shared and small synthetic captures."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ICT_MODEL = ROOT.parent / "shared" / "data" / "ict_face_model" / "ict_face_model.npz"


@pytest.fixture(scope="session")
def ict_model() -> Path:
    if not ICT_MODEL.is_file():
        pytest.skip(f"ICT Face Model not found at {ICT_MODEL}")
    return ICT_MODEL
