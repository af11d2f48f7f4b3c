"""JSON files that one stage writes and others read, as pydantic models.

A stage's file format is a :class:`ArtifactJson` model in the stage that writes it; the
writer and every reader go through it, so a reader cannot drift from the writer. The bytes
are those of ``json.dumps(doc, indent=1)`` of the fields the writer set, in the model's
field order (Python's float formatting, ASCII), so artifacts written through a model are
the files the stages wrote before.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, ClassVar, Self

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from facecap_core.errors import InputError

Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]
"""A point or a translation: three numbers."""
Matrix3 = Annotated[list[Vector3], Field(min_length=3, max_length=3)]
"""A rotation: three rows of three numbers."""


class ArtifactJson(BaseModel):
    """Base of an artifact's JSON: strict types (no strings or booleans for numbers), no
    unknown keys, no NaN or infinite numbers (the writers write ``null`` for a missing
    value)."""

    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False,
                              use_attribute_docstrings=True)

    file_name: ClassVar[str] = "artifact.json"
    """The file's name in its stage's folder."""
    written_by: ClassVar[str] = "the stage that writes it"
    """What to rerun when the file does not read."""

    def to_json(self) -> str:
        """The file's text: the fields that were set, in field order, indented by one."""
        return json.dumps(self.model_dump(exclude_unset=True), indent=1)

    def write(self, path: str | Path) -> Path:
        """Write the file whole or not at all (through ``<name>.part``)."""
        path = Path(path)
        part = path.with_name(path.name + ".part")
        part.write_text(self.to_json())
        part.replace(path)
        return path

    @classmethod
    def read(cls, path: str | Path) -> Self:
        """The model of the file at ``path``; :class:`InputError` naming the file and its
        first problems when it is missing, not JSON or not this format."""
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{cls.file_name} not found: {path} (run {cls.written_by} "
                             "first)")
        try:
            # json's own parser: floats read back exactly as Python wrote them.
            return cls.model_validate(json.loads(path.read_text()))
        except ValueError as exc:  # ValidationError and JSONDecodeError
            raise InputError(f"{path} is not a facecap {cls.file_name} ({_problems(exc)}); "
                             f"rerun {cls.written_by}") from None


def _problems(exc: ValueError, shown: int = 3) -> str:
    """The first problems of a validation error in one line: ``keyframes.0.R: ...``."""
    if not isinstance(exc, ValidationError):
        return f"{type(exc).__name__}: {exc}"
    errors = exc.errors(include_url=False)
    said = "; ".join(f"{'.'.join(str(p) for p in e['loc']) or 'file'}: {e['msg']}"
                     for e in errors[:shown])
    return said + (f"; and {len(errors) - shown} more" if len(errors) > shown else "")
