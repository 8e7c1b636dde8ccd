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

from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator

from spacepose.core.structured_text import parse_structured, read_config_text
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


# Largest σ, or factor on one, a setting may give: squared and multiplied by another such
# square on the way to a covariance it stays finite in float64 (the EKF's and the tracker's bound).
LARGEST_SQUARED = 1e50


def square_stays_finite(value: float | None) -> float | None:
    """``value`` (a σ, or a factor on one, that a stage squares), refused as a ValueError (a
    field's error, when a validator) beyond :data:`LARGEST_SQUARED`: 1e300 ended ``navigate``
    in an OverflowError traceback, or in "measurement covariance must be finite", which named
    neither the setting nor the file."""
    if value is not None and value > LARGEST_SQUARED:
        raise ValueError(
            f"{value:g} is too large: squared, and times another square, it overflows "
            f"float64 (at most {LARGEST_SQUARED:g})"
        )
    return value


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
