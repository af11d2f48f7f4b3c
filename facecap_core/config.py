"""Typed configuration, the machinery: the strict base model of every stage's settings,
one-line validation errors, YAML in and out.

Each stage declares its own settings model in its module (``KeyframeConfig`` in
``facecap_core/keyframes.py``, ``DepthMapConfig`` in ``facecap_core/mvs/depth.py``, ...);
:mod:`facecap_core.pipeline` assembles them into the :class:`PipelineConfig` of a run.
Every tunable has a docstring; unknown keys and out-of-range values are rejected with a
message that names the field.
"""

from __future__ import annotations

import re
import stat
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar, get_args

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    ValidationError,
    ValidationInfo,
    field_validator,
)
from pydantic_core import PydanticCustomError

from facecap_core.errors import InputError

MAX_LEVELS = 32
"""Most levels of a stiffness schedule: each level is a sparse solve of the whole template,
and a schedule longer than this is a mistake, not a setting (the default has 6)."""
MAX_CONFIG_BYTES = 256 * 1024
"""Largest config file read: every setting with a comment fits in a few kilobytes."""
MAX_FRAMES = 100_000
"""Most frames any setting may ask a capture to have (about 7 minutes at 240 fps)."""
KEY_NEUTRAL = "key_neutral"
"""A setting's metadata (``Field(..., json_schema_extra={KEY_NEUTRAL: value})``): the value
at which the stage does what it did before the setting existed. At that value the setting is
left out of the stage's artifact key (``facecap.tasks.graph.config_data``), so adding it
does not make every store compute that stage, and all after it, again. Only a field that
holds a value, or a settings model directly, is looked at (not a list of models); the entry
also shows in the settings' JSON schema, where validators ignore it."""


class StrictModel(BaseModel):
    """Base: unknown keys are errors, values are validated on assignment too, and NaN or
    infinite numbers are refused (they pass every ``gt``/``le`` bound they meet in a list
    or an unbounded field)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False,
                              use_attribute_docstrings=True)

    @field_validator("*", mode="before")
    @classmethod
    def _no_boolean_for_a_number(cls, value: Any, info: ValidationInfo) -> Any:
        """``true`` is no number, but pydantic's lax mode takes it as 1 (and YAML reads
        ``yes`` and ``on`` as ``true``). Strict mode would refuse it, and also the strings
        and lists that YAML and flow parameters give for paths and tuples."""
        items = value if isinstance(value, list | tuple) else (value,)
        if any(isinstance(v, bool) for v in items) and _is_numeric(
                cls.model_fields[info.field_name].annotation):
            raise PydanticCustomError("bool_for_number", "Input should be a number, not a "
                                      "boolean (true/false, yes/no, on/off)")
        return value


@lru_cache
def _is_numeric(annotation: Any) -> bool:
    """Whether a field's type holds numbers (``int``, ``float | None``, ``list[float]``,
    ``tuple[int, int]``) and no bool (a ``Literal`` of numbers lists values, not types:
    pydantic itself refuses ``true`` there)."""
    types, todo = set(), [annotation]
    while todo:
        t = todo.pop()
        types.add(t)
        todo.extend(get_args(t))
    return bool(types & {int, float}) and bool not in types




M = TypeVar("M", bound=BaseModel)


def validation_message(exc: ValidationError) -> str:
    """One line naming each bad field and why."""
    parts = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err["loc"]) or "config"
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)


def build(model: type[M], values: dict, source: str = "config") -> M:
    """Validate ``values`` into ``model``; bad values raise one-line :class:`InputError`."""
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        raise InputError(f"invalid {source}: {validation_message(exc)}; correct or remove "
                         "these settings") from None


class ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader without a YAML 1.1 surprise: ``1:30`` is a string, not the
    base-60 integer 90 (nor ``1:30.5`` a float), so that a number field refuses it."""


# The implicit int and float resolvers of PyYAML's resolver.py, without their base-60 forms;
# every other resolver as SafeLoader has it.
ConfigLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers
            if tag not in ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:int",
    re.compile(r"""^(?:[-+]?0b[0-1_]+
                   |[-+]?0[0-7_]+
                   |[-+]?(?:0|[1-9][0-9_]*)
                   |[-+]?0x[0-9a-fA-F_]+)$""", re.X),
    list("-+0123456789"))
ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+][0-9]+)?
                   |\.[0-9][0-9_]*(?:[eE][-+][0-9]+)?
                   |[-+]?\.(?:inf|Inf|INF)
                   |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


class DuplicateKeyError(yaml.YAMLError):
    """A mapping of a YAML document gives one key twice."""

    def __init__(self, key: str, line: int):
        super().__init__(f"{key} is given twice (line {line})")
        self.key, self.line = key, line


def parse_yaml(text: str) -> Any:
    """The one YAML document of ``text`` (None when empty), read by :class:`ConfigLoader`;
    a key given twice in one mapping raises :class:`DuplicateKeyError` (PyYAML would keep
    the last silently)."""
    loader = ConfigLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_unique_keys(node)
        try:
            return loader.construct_document(node)
        except (ValueError, TypeError, OverflowError) as exc:  # a scalar its resolver misread
            raise yaml.constructor.ConstructorError(None, None, str(exc)) from None
    finally:
        loader.dispose()


def _check_unique_keys(node: yaml.Node, path: tuple[str, ...] = (),
                       seen: set[int] | None = None) -> None:
    """Raise :class:`DuplicateKeyError`, naming the key's dotted path, for a key given twice
    in one mapping under ``node``."""
    seen = set() if seen is None else seen
    if id(node) in seen:  # an alias: its node is checked once (and may contain itself)
        return
    seen.add(id(node))
    if isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _check_unique_keys(item, (*path, str(i)), seen)
    elif isinstance(node, yaml.MappingNode):
        keys = set()
        for key, value in node.value:
            name = str(key.value) if isinstance(key, yaml.ScalarNode) else "?"
            # The tag tells 'iterations' and "iterations" (one key) from 1 and "1" (two);
            # a merge key (<<) brings its own mapping's keys, which the mapping may override.
            if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                if (key.tag, key.value) in keys:
                    raise DuplicateKeyError(".".join((*path, name)), key.start_mark.line + 1)
                keys.add((key.tag, key.value))
            _check_unique_keys(value, (*path, name), seen)


def _config_text(path: Path) -> str:
    """The text of a config file: a regular UTF-8 file of at most MAX_CONFIG_BYTES."""
    try:
        info = path.stat()
    except (FileNotFoundError, NotADirectoryError):
        raise InputError(f"config file not found: {path}; check the path") from None
    except OSError as exc:
        raise InputError(f"config file {path} cannot be read ({exc.strerror}); check the path "
                         "and its permissions") from None
    if stat.S_ISDIR(info.st_mode):
        raise InputError(f"config file {path} is a folder, not a file; give the path of a YAML "
                         "file")
    if not stat.S_ISREG(info.st_mode):  # a FIFO or a device: opening it could block
        raise InputError(f"config file {path} is not a regular file; give the path of a YAML "
                         "file")
    if info.st_size > MAX_CONFIG_BYTES:
        raise InputError(f"config file {path} is {info.st_size} bytes, too large to be a config "
                         f"(at most {MAX_CONFIG_BYTES}); give the settings that differ from the "
                         "defaults")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"config file {path} is not UTF-8 text (byte {exc.start} is not); "
                         "save it as UTF-8") from None
    except OSError as exc:
        raise InputError(f"config file {path} cannot be read ({exc.strerror}); check its "
                         "permissions") from None


def load_yaml(model: type[M], path: str | Path, overrides: dict | None = None) -> M:
    """Read a YAML config (``{}`` for an empty file) and apply ``overrides`` on top."""
    path = Path(path)
    text = _config_text(path)
    try:
        values = parse_yaml(text)
    except DuplicateKeyError as exc:
        raise InputError(f"config file {path} sets {exc.key} twice (the second time on line "
                         f"{exc.line}); keep one of them") from None
    except yaml.YAMLError as exc:
        raise InputError(f"config file {path} is not valid YAML ({str(exc).splitlines()[0]});"
                         " fix its syntax") from None
    except RecursionError:
        raise InputError(f"config file {path} nests too deeply to be a config; settings are "
                         "two or three levels deep, such as 'mvs: {depth: {iterations: 4}}'") from None
    values = {} if values is None else values  # an empty file; [] or 0 are not
    if not isinstance(values, dict):
        raise InputError(f"config file {path} must hold a mapping of settings, such as "
                         "'mvs: {depth: {iterations: 4}}'")
    return build(model, {**values, **(overrides or {})}, source=f"config {path}")


def dump_yaml(config: BaseModel, path: str | Path) -> Path:
    path = Path(path)
    path.write_text(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
    return path




























