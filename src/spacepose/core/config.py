"""Configuration models: one per stage, defaults in code, unknown options rejected.

Every stage's config derives from :class:`StageConfig`. A pipeline config nests stage configs;
:func:`load_config` reads a YAML or JSON file into any such model and turns validation failures
into :class:`~spacepose.errors.ConfigError` naming the file and the offending option.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from spacepose.errors import ConfigError


class StageConfig(BaseModel):
    """Base of every config model: immutable, unknown keys are an error."""

    model_config = ConfigDict(extra="forbid", frozen=True)


C = TypeVar("C", bound=BaseModel)


def validate_config(model: type[C], data: dict | None, source: str | Path | None = None) -> C:
    """Build ``model`` from a mapping; a validation failure becomes one readable ConfigError."""
    try:
        return model.model_validate(data or {})
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc']) or '<root>'}: {err['msg']}"
            for err in exc.errors()
        )
        where = f"{source}: " if source else ""
        raise ConfigError(f"{where}invalid {model.__name__}: {problems}") from None


def load_config(model: type[C], path: str | Path) -> C:
    """Read a YAML (``.yaml``/``.yml``) or JSON config file into ``model``."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config: {exc.strerror}") from None
    try:
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: not valid {path.suffix.lstrip('.') or 'YAML'}: {exc}") from None
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must hold a mapping, got {type(data).__name__}")
    return validate_config(model, data, path)


def dump_config(config: BaseModel, path: str | Path) -> Path:
    """Write the effective config (every value, defaults included) as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(config.model_dump(mode="json"), indent=2) + "\n")
    return path
