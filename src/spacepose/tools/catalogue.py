"""Read and check a target's rectangle catalogue (METHODS §2.2) from scenario.json or YAML.

Accepted layouts (JSON or YAML): a list of entries; a mapping with a ``rectangles`` list (a
user file); a scenario file with ``target.rectangles`` (what ``spacepose simulate`` writes) or a
top-level ``rectangles``. Each entry is ``{name, center, R_model_plane, a, b}`` in the model
frame B', metres (see :class:`spacepose.core.rectangles.CatalogueEntry`).

A catalogue is only useful if every rectangle can be told apart from the others. Two entries
conflict when both their sides lie within the summed recognition tolerances of each other
(a measurement of one could match the other) and their outward normals are less than 90° apart
(so a predicted attitude cannot separate them either, as it does for the opposite faces of a box).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from spacepose.core.config import parse_structured
from spacepose.core.rectangles import CatalogueEntry, RectangleConfig, side_tolerance
from spacepose.errors import ConfigError

__all__ = ["CatalogueEntry", "check_distinguishable", "load_catalogue", "parse_catalogue"]


def _entries_of(data: Any, source: str) -> list:
    """The list of entries inside any accepted layout."""
    if isinstance(data, list):
        return data
    if isinstance(data, dict):
        target = data.get("target")
        if isinstance(target, dict) and "rectangles" in target:
            return _entries_of(target["rectangles"], source)
        if "rectangles" in data:
            return _entries_of(data["rectangles"], source)
    raise ConfigError(
        f"{source}: no rectangle catalogue found (expected a list, 'rectangles' or "
        "'target.rectangles')"
    )


def parse_catalogue(
    data: Any, config: RectangleConfig = RectangleConfig(), source: str | Path = "catalogue"
) -> list[CatalogueEntry]:
    """Validate catalogue data already read (a scenario dict, a list of entry dicts).

    Raises
    ------
    ConfigError
        Naming ``source`` and the entry: a malformed entry (missing field, ``a > b``, a rotation
        that is not orthonormal with det +1), duplicate names, an empty catalogue, or two entries
        that cannot be told apart (:func:`check_distinguishable`).
    """
    source = str(source)
    raw = _entries_of(data, source)
    if len(raw) == 0:
        raise ConfigError(f"{source}: the rectangle catalogue is empty")
    entries: list[CatalogueEntry] = []
    for i, item in enumerate(raw):
        label = f"entry {i}" + (
            f" ({item['name']!r})" if isinstance(item, dict) and "name" in item else ""
        )
        try:
            entries.append(CatalogueEntry.model_validate(item))
        except ValidationError as exc:
            problems = "; ".join(
                f"{'.'.join(str(p) for p in err['loc']) or '<entry>'}: {err['msg']}"
                for err in exc.errors()
            )
            raise ConfigError(f"{source}: rectangle {label}: {problems}") from None
    names = [e.name for e in entries]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ConfigError(f"{source}: duplicate rectangle names: {', '.join(duplicates)}")
    check_distinguishable(entries, config, source)
    return entries


def check_distinguishable(
    entries: Sequence[CatalogueEntry],
    config: RectangleConfig = RectangleConfig(),
    source: str | Path = "catalogue",
) -> None:
    """Raise ConfigError naming the first pair of entries that recognition cannot tell apart.

    Entries i and j conflict when ``|a_i − a_j| <= tol(a_i) + tol(a_j)`` and the same holds for
    b (tol from :func:`spacepose.core.rectangles.side_tolerance`), and their outward normals
    are less than 90° apart.
    """
    if len(entries) < 2:
        return
    a = np.array([e.a for e in entries])
    b = np.array([e.b for e in entries])
    normals = np.stack([e.rotation[:, 2] for e in entries])
    tol_a = np.array([side_tolerance(v, config) for v in a])
    tol_b = np.array([side_tolerance(v, config) for v in b])
    close = (np.abs(a[:, None] - a[None]) <= tol_a[:, None] + tol_a[None]) & (
        np.abs(b[:, None] - b[None]) <= tol_b[:, None] + tol_b[None]
    )
    # A small margin so that exactly perpendicular faces (a box's sides) count as separable.
    close &= normals @ normals.T > 1e-6
    i, j = np.nonzero(np.triu(close, k=1))
    if len(i):
        ei, ej = entries[int(i[0])], entries[int(j[0])]
        raise ConfigError(
            f"{source}: rectangles {ei.name!r} ({ei.a:g} x {ei.b:g} m) and {ej.name!r} "
            f"({ej.a:g} x {ej.b:g} m) cannot be told apart: sizes within the tolerance "
            f"(abs {config.side_tolerance_abs:g} m + rel {config.side_tolerance_rel:g}) and "
            "normals less than 90 degrees apart"
        )


def load_catalogue(
    path: str | Path, config: RectangleConfig = RectangleConfig()
) -> list[CatalogueEntry]:
    """Read a catalogue from a scenario.json or a YAML/JSON file and check it.

    Parameters
    ----------
    path
        ``.json`` is read as JSON, anything else as YAML.
    config
        Recognition tolerances the entries must be distinguishable at.

    Raises
    ------
    ConfigError
        The file cannot be read or parsed, or :func:`parse_catalogue` rejects its content.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the rectangle catalogue: {exc.strerror}") from None
    return parse_catalogue(parse_structured(text, path), config, path)
