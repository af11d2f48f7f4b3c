"""Every ``FACECAP_*`` environment variable facecap reads, in one validated model.

Whoever runs facecap sets these (a shell, a worker's container, a test): where its files go,
which store and models it uses, what a served run may touch and cost. They are not part of a
run's config, so that a run of a shared service cannot change them. Each field is the variable
``FACECAP_<FIELD>`` (``max_frames``: ``FACECAP_MAX_FRAMES``); ``docs/deploy.md`` lists them.

One rule for every variable: an empty value is the same as an unset one (the default), so a
compose file or a shell that passes an empty value never means "the current folder". Paths
expand ``~``. A bad value raises :class:`~facecap_core.errors.InputError` naming the variable.

Read them with :func:`settings`, never with ``os.environ``.
"""

from __future__ import annotations

import os
import re
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlsplit

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict, SettingsError

from facecap_core.config import MAX_FRAMES
from facecap_core.errors import InputError

ENV_PREFIX = "FACECAP_"
FAULT_SPEC = re.compile(r"[\w-]+(:[1-9][0-9]*(:(exit|interrupt|oserror))?)?")
"""``STAGE[:N[:HOW]]`` of :attr:`FacecapSettings.fault`."""


def default_home() -> Path:
    """``~/.cache/facecap``, the folder of facecap's own files when FACECAP_HOME is unset."""
    return Path.home() / ".cache" / "facecap"


MAX_TIMEOUT_S = 30 * 24 * 3600.0
"""The longest time limit a run takes (30 days): the clocks and Prefect's timers that keep
a limit work with seconds of that order, not with 1e308."""


class FacecapSettings(BaseSettings):
    """The ``FACECAP_*`` environment of this process, validated."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX, use_attribute_docstrings=True,
        env_ignore_empty=True,  # an empty value means the default, for every variable
        extra="ignore",  # the stack's own FACECAP_ variables are compose's and prefect.yaml's
        frozen=True,  # one instance is shared by every caller (see settings())
        allow_inf_nan=False,  # an infinite limit or timeout is a typo, not a setting
    )

    home: Path = Field(default_factory=default_home)
    """Folder of facecap's own files: downloaded assets (``assets/``, ``downloads/``), the
    default store (``store/``), copies of remote artifacts (``store-cache/``), locks of a
    remote store (``locks/``), scratch space (``work/``), crash logs (``logs/``); made if
    missing, refused if it is a file or a folder facecap may not write in. Default
    ``~/.cache/facecap``."""
    store: str | None = None
    """Artifact store: a folder or ``s3://bucket/prefix``. A served run uses this one and may
    name no other. Default ``$FACECAP_HOME/store``."""
    input_roots: Annotated[tuple[Path, ...], NoDecode] = ()
    """Folders (``:``-separated) a served run may read inputs from. Default none: a run from a
    deployment reads nothing; ``facecap serve`` sets its ``--root``."""
    output_root: Path | None = None
    """Folder a served run may write results under. Default none: a run from a deployment
    writes nothing; ``facecap serve`` sets its ``--out``."""
    ict_model: Path | None = None
    """ICT Face Model ``.npz`` used when none is given (e.g. the full 100-mode model). Default:
    the trimmed model in the package (``facecap_core/data/``); ear training needs one set."""
    ear_models: Path | None = None
    """Folder holding the ear model files (``ear_detector.svm``, ``ear_predictor.dat``,
    ``ear_contour.json``), e.g. a fresh ``facecap train-ears`` run. Default: the models in the
    package (``facecap_core/landmarks/models/``)."""
    # The input limits: the largest capture a run accepts, checked before any compute
    # (flows.capture.preflight). The defaults admit any phone capture (a 10-minute 4K video
    # at 60 fps is 36,000 frames and about 4 GB).
    max_file_mb: float = Field(8192.0, gt=0)
    """Largest video file (a photo folder: all its photos) a run accepts, in MiB: checked
    before the file is opened, and the store holds a copy of it. Default 8192."""
    max_duration_s: float = Field(600.0, gt=0)
    """Longest video a run accepts, in seconds (an ear-to-ear sweep takes 10 to 30). Default
    600."""
    max_frames: int = Field(36_000, ge=2, le=10 * MAX_FRAMES)
    """Most frames of a video, or photos in a folder, a run accepts: the keyframe stage
    decodes every one. Default 36000 (10 minutes at 60 fps)."""
    max_side_px: int = Field(8192, ge=120, le=65536)
    """Longest image side a run accepts, in pixels; the keyframes are kept at full
    resolution. Default 8192 (8K)."""
    capture_timeout_s: float = Field(21600.0, gt=0, le=MAX_TIMEOUT_S)
    """The longest a capture flow run may take, in seconds, before it ends Failed: its
    stages keep it, and Prefect's own limit on the run follows a minute later. Default
    21600 (6 hours)."""
    stage_timeout_s: float = Field(7200.0, gt=0, le=MAX_TIMEOUT_S)
    """The longest one stage may take, in seconds, before the run ends Failed; the depth
    maps together count as one stage. Default 7200 (2 hours)."""
    alert_webhook: str | None = None
    """Webhook URL ``facecap alerts`` sends the service's alerts to (regressions, failed
    runs; ``deploy/alerts.py``). Default unset: ``facecap alerts`` needs ``--webhook``."""
    evaluation_timeout_s: float = Field(21600.0, gt=0, le=MAX_TIMEOUT_S)
    """The longest a dataset evaluation run (the nightly one) may take, in seconds, before
    it ends Failed: a hung night must not make the later ones skip. Default 21600 (6 hours)."""
    pages_url: str | None = None
    """Address at which ``facecap pages`` (or ``facecap serve``) serves a local store's
    results pages over HTTP, as the Prefect UI's browser reaches it, e.g.
    ``http://facecap-host:4280``: a run links its UI page to its results page there, by a link
    that lasts a day. Default unset: ``facecap serve`` sets it to its own page server; a run
    elsewhere links to its output folder (a ``file://`` address a web page cannot open). An S3
    store needs none: its links are S3's own."""
    fault: str | None = None
    """Fault injection for the robustness tests, ``STAGE[:N[:HOW]]``: the N-th computation
    (default 1) of STAGE in a process fails before its commit; HOW is ``exit`` (default),
    ``interrupt`` or ``oserror`` (``facecap.tasks.runner.inject_fault``). Default unset: no fault.
    Never set it outside a test."""

    @field_validator("input_roots", mode="before")
    @classmethod
    def _split_roots(cls, value: Any) -> Any:
        # Colon-separated like PATH; empty entries (a trailing ':') name no folder.
        if isinstance(value, str):
            return tuple(part for part in value.split(os.pathsep) if part)
        return value

    @field_validator("home", "ict_model", "ear_models", "output_root")
    @classmethod
    def _expand_path(cls, value: Path | None) -> Path | None:
        return value.expanduser() if value is not None else None

    @field_validator("home")
    @classmethod
    def _check_home(cls, value: Path) -> Path:
        # Every command writes below it (assets, store, locks, scratch, crash logs): a file
        # or a folder it may not write in is named here, with its variable, rather than by
        # the traceback of the first folder made under it.
        problem = folder_problem(value)
        if problem:
            raise ValueError(problem)
        return value

    @field_validator("input_roots")
    @classmethod
    def _expand_roots(cls, value: tuple[Path, ...]) -> tuple[Path, ...]:
        return tuple(root.expanduser() for root in value)

    @field_validator("store")
    @classmethod
    def _expand_store(cls, value: str | None) -> str | None:
        if value is None or "://" in value:
            return value
        return os.path.expanduser(value)

    @field_validator("pages_url")
    @classmethod
    def _check_pages_url(cls, value: str | None) -> str | None:
        if value is None:
            return value
        parts = urlsplit(value)
        if parts.scheme not in ("http", "https") or not parts.hostname or parts.query \
                or parts.fragment or parts.username or parts.password:
            raise ValueError("expected the address of the page server, "
                             "http(s)://HOST[:PORT][/PATH], with no query or credentials")
        return value.rstrip("/")

    @field_validator("fault")
    @classmethod
    def _check_fault(cls, value: str | None) -> str | None:
        if value is not None and not FAULT_SPEC.fullmatch(value):
            raise ValueError("expected STAGE[:N[:HOW]], N a positive count and HOW one of "
                             "exit, interrupt, oserror")
        return value


def folder_problem(path: Path) -> str | None:
    """Why ``path`` cannot be a folder facecap writes in (it, or the nearest of its parents
    that exists, is not a folder or not writable), or None. A folder still to be made is
    fine."""
    existing = next(p for p in (path, *path.parents) if p.exists() or p.is_symlink())
    inside = "" if existing == path else f"{path} cannot be made: "
    if not existing.is_dir():
        return f"{inside}{existing} is {'a file, ' if existing.is_file() else ''}not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"{inside}{existing} is a folder facecap may not write in"
    return None


REMEDIES = {"home": "set FACECAP_HOME to a writable folder, or unset it for the default "
                    "(~/.cache/facecap)"}
"""What to do about a bad value, where more can be said than "correct it"."""


def time_limit(field: str) -> float:
    """A flow's time limit (``capture_timeout_s``, ``evaluation_timeout_s``), read when the
    flow's module is imported (a worker imports it for each flow run). A bad FACECAP_* value
    must not make that import fail: the default stands in, and the run itself reports the
    value at its first check."""
    try:
        return getattr(settings(), field)
    except InputError:
        return FacecapSettings.model_fields[field].default


def env_name(field: str) -> str:
    """The environment variable of a settings field: ``max_frames`` -> ``FACECAP_MAX_FRAMES``."""
    return ENV_PREFIX + field.upper()


def settings() -> FacecapSettings:
    """The settings of the current environment; a bad value raises a one-line InputError."""
    return _settings_of(_relevant_environ())


def _relevant_environ() -> tuple[tuple[str, str], ...]:
    # What the settings depend on: the FACECAP_* variables (any case: pydantic-settings
    # matches names case-insensitively) and HOME, which the default of FACECAP_HOME expands.
    return tuple(sorted((name, value) for name, value in os.environ.items()
                        if name.upper().startswith(ENV_PREFIX) or name == "HOME"))


@lru_cache(maxsize=8)
def _settings_of(environ: tuple[tuple[str, str], ...]) -> FacecapSettings:
    # Keyed on the relevant variables, so a changed environment (a test, facecap serve's
    # defaults) is read again, while repeated calls in one run cost a dictionary scan.
    del environ  # the key only: the settings read os.environ, which it was taken from
    try:
        return FacecapSettings()
    except ValidationError as exc:
        raise InputError("; ".join(_problem(error) for error in exc.errors())) from None
    except SettingsError as exc:  # a value the source could not even parse
        raise InputError(f"cannot read the {ENV_PREFIX}* environment ({exc}); correct the "
                         "variable or unset it") from None


def _problem(error: dict) -> str:
    """One bad variable: its name, value, why, and what to do."""
    field = str(error["loc"][0])
    value = _shorten(str(error.get("input", "")))
    # A validator's own message without pydantic's "Value error, " in front of it.
    reason = str(error["ctx"]["error"]) if error["type"] == "value_error" else error["msg"]
    reason = reason[:1].lower() + reason[1:]
    default = FacecapSettings.model_fields[field].get_default(call_default_factory=True)
    shown = f" ({default:g})" if isinstance(default, int | float) else ""
    remedy = REMEDIES.get(field, f"correct it or unset it for the default{shown}")
    return f"invalid {env_name(field)}={value!r} in the environment: {reason}; {remedy}"


def _shorten(text: str, limit: int = 80) -> str:
    return text if len(text) <= limit else text[:limit - 3] + "..."
