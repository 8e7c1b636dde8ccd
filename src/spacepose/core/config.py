"""Configuration models: one per stage, defaults in code, unknown options rejected.

Every stage's config derives from :class:`StageConfig`. A pipeline config nests stage configs;
:func:`load_config` reads a YAML or JSON file into any such model. Every validation failure,
whether from a file or from ``XConfig(field=value)`` in code, is a one-line
:class:`~spacepose.errors.ConfigError` naming the model, the offending field and, for a file, the
file; a file that does not parse is named with the line and column of the problem
(:func:`parse_problem`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from types import UnionType
from typing import Annotated, Any, Literal, TypeVar, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator

from spacepose.errors import ConfigError


class StageConfig(BaseModel):
    """Base of every config model: immutable, unknown keys and non-finite floats are an error.

    Constructing one with a bad value (``TrackerConfig(voxel_size=-1)``, an unknown keyword,
    ``inf`` or ``nan`` for a float) raises :class:`~spacepose.errors.ConfigError` naming the
    model and the field, not pydantic's ``ValidationError``. A bound that may be absent is
    ``None``, never ``inf``: the effective config is written as JSON, which has no infinity.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_boolean_numbers(cls, value: Any, info: ValidationInfo) -> Any:
        # The other way round too: pydantic reads ``use_mls: 1`` as true; a switch is a yes/no.
        is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if is_number and cls.model_fields[info.field_name].annotation is bool:
            raise ValueError(f"{value!r} is a number, not a yes/no (write true or false)")
        return refuse_text_number(cls, refuse_boolean(cls, value, info), info)

    def __init__(self, /, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise config_error(type(self), exc, data=data) from None

    @classmethod
    def model_validate(cls, obj: Any, **kwargs: Any) -> StageConfig:  # type: ignore[override]
        """Pydantic's ``model_validate``; a failure is a :class:`ConfigError`."""
        try:
            return super().model_validate(obj, **kwargs)
        except ValidationError as exc:
            raise config_error(cls, exc, data=obj) from None


C = TypeVar("C", bound=BaseModel)


def _admits(annotation: Any, leaf: Callable[[Any], bool], kind: type, through: tuple) -> bool:
    """Whether a field annotated ``annotation`` may hold a value of ``kind``: a ``leaf`` type,
    a ``Literal`` with one, or any member of the ``through`` generics (unions; containers)."""
    if leaf(annotation):
        return True
    origin, args = get_origin(annotation), get_args(annotation)
    if origin is Annotated:
        return _admits(args[0], leaf, kind, through)
    if origin is Literal:
        return any(isinstance(a, kind) for a in args)
    if origin in through:
        return any(_admits(a, leaf, kind, through) for a in args if a is not Ellipsis)
    return False


def admits_boolean(annotation: Any) -> bool:
    """Whether a field annotated ``annotation`` may hold ``True`` / ``False`` (a container
    admits one when any of its element types does)."""
    return _admits(
        annotation, lambda a: a is bool or a is Any, bool, (Union, UnionType, tuple, list)
    )


def holds_boolean(value: Any) -> bool:
    """Whether ``value`` is a boolean or a list / tuple holding one at any depth (a number
    read from a file as ``true`` is a slip: numpy and pydantic would take it for 1)."""
    if isinstance(value, (list, tuple)):
        return any(holds_boolean(v) for v in value)
    return isinstance(value, bool)


def refuse_boolean(model: type[BaseModel], value: Any, info: ValidationInfo) -> Any:
    """``value`` unchanged, unless it is or holds a boolean for a field that takes none.

    Pydantic reads ``true`` as 1 for a number field: in a file, ``ok_condition: true`` or a side
    ``a: yes`` (YAML 1.1) or a centre ``[true, 0, 0]`` is a slip, never the number one.
    """
    if holds_boolean(value) and not admits_boolean(model.model_fields[info.field_name].annotation):
        raise ValueError(f"{str(value).lower()} is a yes/no, not a value of this field")
    return value


def admits_text(annotation: Any) -> bool:
    """Whether a field annotated ``annotation`` may be given as text (a name, a path, a choice
    of words), or hold text (a container of them)."""

    def text(a: Any) -> bool:
        return a in (Path, Any) or (isinstance(a, type) and issubclass(a, str))

    return _admits(annotation, text, str, (Union, UnionType, tuple, list))


def refuse_text_number(model: type[BaseModel], value: Any, info: ValidationInfo) -> Any:
    """``value`` unchanged, unless it is text for a field that takes no text.

    Pydantic reads ``"0.5"`` as 0.5 for a number field: in a file, ``gate: "0.5"`` is a value
    quoted by mistake (or a unit written in: ``"5 mm"``), not a number the user meant as text.
    """
    if not holds_text(value) or admits_text(model.model_fields[info.field_name].annotation):
        return value
    if isinstance(value, str):
        raise ValueError(f"{value!r} is text, not a value of this field (write it unquoted)")
    # A list of numbers quoted ("30", "30") was read as the numbers without a word.
    raise ValueError(f"{value!r} holds text, not values of this field (write them unquoted)")


def holds_text(value: Any) -> bool:
    """Whether ``value`` is text or a list / tuple holding text at any depth (a number quoted
    in a file: pydantic and numpy would read ``"1.8"`` as 1.8)."""
    if isinstance(value, (list, tuple)):
        return any(holds_text(v) for v in value)
    return isinstance(value, str)


def config_error(
    model: type[BaseModel],
    exc: ValidationError,
    source: str | Path | None = None,
    data: object = None,
) -> ConfigError:
    """One-line :class:`ConfigError` listing every field ``exc`` rejects, as ``field: problem``.

    A nested StageConfig's own ConfigError (pydantic wraps it as a value error of the outer
    field) is unwrapped, so the line reads ``icp.max_iterations: ...``, not the inner message
    inside the outer one. The (field, problem) pairs are kept as ``error.problems``. When
    every key of ``data`` (the mapping validated) is unknown, the line says so once.
    """
    problems: list[tuple[str, str]] = []
    for err in exc.errors():
        loc = [str(p) for p in err["loc"]]
        nested = getattr((err.get("ctx") or {}).get("error"), "problems", None)
        if nested:
            problems += [(".".join(filter(None, [*loc, field])), msg) for field, msg in nested]
        else:
            # Pydantic prefixes a validator's own words with "Value error, ".
            problems.append((".".join(loc), err["msg"].removeprefix("Value error, ")))
    where = f"{source}: " if source else ""
    listed = "; ".join(f"{field}: {msg}" if field else msg for field, msg in problems)
    extra = [field for field, msg in problems if msg == "Extra inputs are not permitted"]
    keys = {str(k) for k in data} if isinstance(data, dict) else set()
    if len(extra) >= 3 and keys and keys == set(extra):
        # Every key unknown (a tracker config given to navigate listed 30 of them, one by one).
        named = ", ".join(extra[:4]) + (", ..." if len(extra) > 4 else "")
        error = ConfigError(
            f"{where}none of its keys ({named}) is a {config_name(model)}'s: a config of "
            "another command?"
        )
        error.problems = problems
        return error
    error = ConfigError(f"{where}invalid {config_name(model)}: {listed}")
    error.problems = problems
    return error


def config_name(model: type[BaseModel]) -> str:
    """A config model's name in words, as a user knows it: ``TrackerConfig`` -> "tracker
    config", ``FPFHConfig`` -> "FPFH config", ``LostInSpaceConfig`` -> "lost in space config"
    (the class names read as code in a one-line error)."""
    words = re.sub(r"(?<=[a-z])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", " ", model.__name__).split()
    return " ".join(w if w.isupper() and len(w) > 1 else w.lower() for w in words)


def validate_config(model: type[C], data: dict | None, source: str | Path | None = None) -> C:
    """Build ``model`` from a mapping; a validation failure becomes one readable ConfigError."""
    key = _non_string_key(data)
    if key is not None:
        # YAML reads "yes:", "1:" or "null:" as a boolean, number or None: pydantic's
        # "keywords must be strings" TypeError escaped as a traceback.
        where, bad = key
        problem = f"invalid {config_name(model)}: the key {bad!r}{where} is not a name"
        raise ConfigError(f"{source}: {problem}" if source else problem)
    try:
        return model.model_validate(data or {})
    except ValidationError as exc:
        raise config_error(model, exc, source, data) from None
    except ConfigError as exc:  # a StageConfig's own error, without the file
        raise ConfigError(f"{source}: {exc}" if source else str(exc)) from None


def stage_config(config: Any, model: type[C], name: str = "config") -> C:
    """``config`` as a ``model``: an instance as it is, a dict of its fields validated (as
    :class:`~spacepose.core.tracker.Tracker` takes one), anything else refused.

    The check at the top of every one-call function that takes a stage config: a dict or None
    passed there ended in ``AttributeError: 'dict' object has no attribute ...`` deep inside.

    Raises
    ------
    ConfigError
        ``config`` is neither a ``model`` nor a dict, or the dict is not a valid ``model``.
    """
    if isinstance(config, model):
        return config
    if isinstance(config, dict):
        return validate_config(model, config)
    raise ConfigError(
        f"{name} must be a {model.__name__} (or a dict of its fields), got {type(config).__name__}"
    )


def _non_string_key(data: Any, path: str = "") -> tuple[str, Any] | None:
    """``(" under a.b", key)`` of the first key of a nested mapping that is not a string, or
    None."""
    if isinstance(data, dict):
        for key, value in data.items():
            if not isinstance(key, str):
                return (f" under {path}" if path else ""), key
            found = _non_string_key(value, f"{path}.{key}" if path else key)
            if found is not None:
                return found
    elif isinstance(data, list):
        for i, value in enumerate(data):
            found = _non_string_key(value, f"{path}[{i}]")
            if found is not None:
                return found
    return None


def parse_problem(exc: Exception) -> str:
    """``line L:C: problem`` of a YAML or JSON parse error, on one line.

    PyYAML's message spans several lines (the context, the offending line and a caret); this
    keeps the position of the problem and the problem itself, and the context in brackets.
    """
    if isinstance(exc, json.JSONDecodeError):
        return f"line {exc.lineno}:{exc.colno}: {exc.msg}"
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None)
    if problem is None:
        return " ".join(str(exc).split())
    where = f"line {mark.line + 1}:{mark.column + 1}: " if mark is not None else ""
    context = getattr(exc, "context", None)
    return f"{where}{problem}" + (f" ({context})" if context else "")


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a mapping that gives a key twice."""


def _unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> Any:
    # PyYAML keeps the last of two equal keys without a word: a config's first value of a
    # knob would be ignored silently.
    seen: set[Any] = set()
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":  # "<<: *base" merges, as it may
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            twice = key in seen
            seen.add(key)
        except TypeError:  # an unhashable key: construct_mapping says so
            break
        if twice:
            problem = f"the key {key!r} is given twice"
            raise yaml.constructor.ConstructorError(None, None, problem, key_node.start_mark)
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)
# Numbers as YAML 1.2's core schema reads them, not YAML 1.1's, which PyYAML follows: 1.1 reads
# 1e5 as text, 010 as 8 (octal), 1:30 as 90 (base 60) and 1_000 as 1000. Here 1e5 is a number,
# 010 is 10, and 1:30 and 1_000 are text, which a config then refuses as a number given as
# text (refuse_text_number) instead of reading a value the user did not write.
_INT, _FLOAT = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
_UniqueKeyLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in (_INT, _FLOAT)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_UniqueKeyLoader.add_implicit_resolver(
    _INT, re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"), list("-+0123456789")
)
_UniqueKeyLoader.add_implicit_resolver(
    _FLOAT,
    re.compile(
        r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
        r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
    ),
    list("-+.0123456789"),
)


def _core_int(loader: _UniqueKeyLoader, node: yaml.ScalarNode) -> int:
    """An integer as YAML 1.2 writes it: decimal (leading zeros too), 0o octal, 0x hex."""
    text = loader.construct_scalar(node)
    if text[:2] in ("0o", "0x"):
        return int(text[2:], 8 if text[1] == "o" else 16)
    return int(text, 10)


_UniqueKeyLoader.add_constructor(_INT, _core_int)


def _unique_pairs(text: str) -> Any:
    """``object_pairs_hook`` of :func:`json.loads` refusing an object that gives a key twice."""

    def hook(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        keys = [k for k, _ in pairs]
        twice = next((k for k in keys if keys.count(k) > 1), None)
        if twice is not None:
            at = max(text.rfind(json.dumps(twice)), 0)
            raise json.JSONDecodeError(f"the key {twice!r} is given twice", text, at)
        return dict(pairs)

    return hook


def load_structured(text: str, kind: str) -> Any:
    """``json.loads`` (``kind == "json"``) or ``yaml.safe_load`` of ``text``, refusing a key
    given twice in one mapping.

    Both parsers recurse once per level of nesting, so ``[[[[…`` a few thousand deep ends in a
    RecursionError; it is raised as the parser's own error (``nested too deeply``), which every
    reader already turns into one line naming its file. So is the ValueError of an integer
    too long for Python's int() (over 4,300 digits), and so are YAML aliases that stand for a
    structure without end or a hundred times the file's characters in values.
    """
    try:
        if kind == "json":
            return json.loads(text, object_pairs_hook=_unique_pairs(text))
        data = yaml.load(text, Loader=_UniqueKeyLoader)
    except RecursionError:
        if kind == "json":
            raise json.JSONDecodeError("nested too deeply", text, 0) from None
        raise yaml.YAMLError("nested too deeply") from None
    except ValueError as exc:
        if isinstance(exc, json.JSONDecodeError):
            raise
        # Python's int() refuses an integer of more than 4,300 digits, inside either parser.
        what = "a number of more digits than can be read" if "digits" in str(exc) else str(exc)
        if kind == "json":
            raise json.JSONDecodeError(what, text, 0) from None
        raise yaml.YAMLError(what) from None
    # An alias shares its anchor's value, so a few lines can stand for a structure without end
    # (an anchor inside itself: `a: &a [*a]`) or of 10⁹ values (aliases of aliases), which
    # every later walk over the values (key checks, validation) would follow for ever.
    if not _expands_within(data, _VALUES_PER_CHARACTER * len(text) + 1000):
        raise yaml.YAMLError(
            "its aliases stand for a structure without end or far larger than the file "
            "(an anchor used inside itself, or aliases of aliases)"
        )
    return data


# Values a YAML text may stand for through its aliases, per character: a config written out
# has fewer than one; a file that reuses a block by alias a few times stays far below this.
_VALUES_PER_CHARACTER = 100


def _expands_within(data: Any, budget: int) -> bool:
    """Whether ``data``, its shared values counted each time they occur, holds at most
    ``budget`` values (a cyclic structure holds infinitely many)."""
    stack, count = [data], 0
    while stack:
        item = stack.pop()
        count += 1
        if count > budget:
            return False
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, list | tuple):
            stack.extend(item)
    return True


def parse_structured(text: str, source: str | Path, kind: str | None = None) -> Any:
    """Parse ``text`` as JSON (``kind == "json"`` or a ``.json`` source) or else YAML.

    Raises
    ------
    ConfigError
        One line: ``source: not valid YAML: line L:C: problem``.
    """
    kind = kind or ("json" if Path(source).suffix.lower() == ".json" else "yaml")
    try:
        return load_structured(text, kind)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"{source}: not valid {kind.upper()}: {parse_problem(exc)}") from None


def not_text(exc: UnicodeDecodeError) -> str:
    """``not UTF-8 text (byte 0xff at offset 0)``: the problem of a file that does not decode."""
    return f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})"


def not_a_file(path: Path) -> str | None:
    """Why ``path`` is not a regular file to read, or None when it is one (a pipe or device
    named as an input would block a read for ever)."""
    if path.is_file():
        return None
    if path.is_dir():
        return "a folder, not a file"
    if path.is_symlink() and not path.exists():
        return "a broken link"
    if path.exists():
        return "not a regular file (a pipe or a device?)"
    return "no such file"


def read_config_text(path: Path, what: str) -> str:
    """The UTF-8 text of a config-like file (``what``: ``"config"``, ``"the rectangle
    catalogue"``).

    Raises
    ------
    ConfigError
        ``path: cannot read WHAT: problem``: not a regular file, refused by the system, or
        not UTF-8 text.
    """
    problem = not_a_file(path)
    try:
        if problem is None:
            return path.read_text()
    except OSError as exc:
        problem = exc.strerror or str(exc)
    except UnicodeDecodeError as exc:
        problem = not_text(exc)
    raise ConfigError(f"{path}: cannot read {what}: {problem}") from None


def read_mapping(path: str | Path) -> dict | None:
    """The mapping a YAML (``.yaml``/``.yml``) or JSON config file holds (None: empty file).

    Raises
    ------
    ConfigError
        One line naming the file: unreadable, not UTF-8, not valid YAML / JSON, or not a
        mapping.
    """
    path = Path(path)
    data = parse_structured(read_config_text(path, "config"), path)
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must hold a mapping, got {type(data).__name__}")
    return data


def load_config(model: type[C], path: str | Path) -> C:
    """Read a YAML (``.yaml``/``.yml``) or JSON config file into ``model``."""
    return validate_config(model, read_mapping(path), path)


def dump_config(config: BaseModel, path: str | Path) -> Path:
    """Write the effective config (every value, defaults included) as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(config.model_dump(mode="json"), indent=2) + "\n")
    return path
