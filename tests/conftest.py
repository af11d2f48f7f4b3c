"""Shared fixtures: the ICT Face Model the tests render and fit."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from facecap_core.assets import ICT_MODEL_ENV, default_ict_model


@pytest.fixture(scope="session")
def ict_model() -> Path:
    """``$FACECAP_ICT_MODEL`` when set (e.g. the full 100-mode model), else the trimmed model
    that ships in the package. Never a skip: a missing model fails the tests that need it."""
    path = default_ict_model()
    if not path.is_file():
        source = (f"${ICT_MODEL_ENV}" if os.environ.get(ICT_MODEL_ENV)
                  else "the packaged model (build it with tools/trim_ict_model.py)")
        pytest.fail(f"ICT Face Model not found at {path} ({source})", pytrace=False)
    return path
