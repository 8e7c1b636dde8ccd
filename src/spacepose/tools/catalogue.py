"""Read and check a target's rectangle catalogue (methods.md §2.2) from scenario.json or YAML.

Accepted layouts (JSON or YAML): a list of entries; a mapping with a ``rectangles`` list (a
user file); a scenario file with ``target.rectangles`` (what ``spacepose simulate`` writes) or a
top-level ``rectangles``. Each entry is ``{name, center, R_model_plane, a, b}`` in the model
frame B', metres (see :class:`spacepose.core.rectangles.CatalogueEntry`).

Faces of equal size are legal: a box's opposite faces, a panel's two sides, a mock-up's two
equal wings. Their sides alone do not name them (:func:`size_classes` lists which entries share
a size); a predicted pose, or the lost-in-space start, does. What is refused is the same face
listed twice: two entries whose sides lie within the summed recognition tolerances of each
other, whose outward normals are less than 90° apart and whose centres lie within the summed
tolerances of their long sides, so that no pose could ever tell them apart.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import ValidationError
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from spacepose.core.cloud import MAX_ABS_COORDINATE
from spacepose.core.rectangles import CatalogueEntry, RectangleConfig, side_tolerance
from spacepose.core.structured_text import parse_structured, read_config_text
from spacepose.errors import ConfigError, SpaceposeWarning

# Longest side (m) of a catalogued face read without a warning: the ISS's truss, 109 m, is
# the largest structure in orbit.
_LONGEST_SIDE_M = 200.0

__all__ = [
    "CatalogueEntry",
    "check_distinguishable",
    "load_catalogue",
    "parse_catalogue",
    "size_classes",
]


def _entries_of(data: Any, source: str) -> list:
    """The list of entries inside any accepted layout."""
    if isinstance(data, list):
        return data
    if isinstance(data, dict):
        target = data.get("target")
        if isinstance(target, dict) and "rectangles" in target:
            return _entries_of(target["rectangles"], source)
        if "rectangles" in data:
            if not isinstance(data["rectangles"], list):  # "no catalogue found" beside the key
                kind = "a mapping" if isinstance(data["rectangles"], dict) else "no list"
                raise ConfigError(f"{source}: rectangles must be a list of entries, got {kind}")
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
        that is not orthonormal with det +1, a non-finite centre or side), duplicate names, an
        empty catalogue, or two entries that are the same face (:func:`check_distinguishable`).

    Warns
    -----
    SpaceposeWarning
        A side longer than any spacecraft's face (200 m): millimetres, not metres.
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
            entry = CatalogueEntry.model_validate(item)
        except ValidationError as exc:
            problems = "; ".join(_entry_problem(err) for err in exc.errors())
            raise ConfigError(f"{source}: rectangle {label}: {problems}") from None
        # The model takes inf for a float (and the sides' gt=0 lets +inf through); a face at
        # infinity or of infinite size is no face.
        # Beyond a cloud's largest coordinate the squares overflow (numpy's bare warning).
        infinite = [
            k
            for k in ("center", "a", "b")
            if not np.all(np.abs(getattr(entry, k)) <= MAX_ABS_COORDINATE)
        ]
        if infinite:
            raise ConfigError(
                f"{source}: rectangle {label}: "
                + "; ".join(
                    f"{k}: must be finite and at most {MAX_ABS_COORDINATE:.3g} m, "
                    f"got {getattr(entry, k)}"
                    for k in infinite
                )
            )
        entries.append(entry)
    names = [e.name for e in entries]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ConfigError(f"{source}: duplicate rectangle names: {', '.join(duplicates)}")
    check_distinguishable(entries, config, source)
    _warn_if_not_metres(entries, source)
    return entries


def _warn_if_not_metres(entries: Sequence[CatalogueEntry], source: str) -> None:
    """Warn (naming ``source``) when a rectangle's long side is longer than any spacecraft's
    face (:data:`_LONGEST_SIDE_M`): sides in millimetres, which no measured face then matches,
    and every frame is navigated as one without a rectangle, without a word why."""
    longest = max(entries, key=lambda e: e.b)
    if longest.b > _LONGEST_SIDE_M:
        problem = (
            f"rectangle {longest.name!r} is {longest.a:g} x {longest.b:g} m, larger than any "
            "spacecraft's face: sides in millimetres? the catalogue is in metres"
        )
        warnings.warn(SpaceposeWarning(problem, source), stacklevel=3)


def _same_size(
    entries: Sequence[CatalogueEntry], config: RectangleConfig
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """(n, n) whether two entries' sides both lie within the summed tolerances; tol(b) (n,)."""
    a = np.array([e.a for e in entries])
    b = np.array([e.b for e in entries])
    tol_a = np.array([side_tolerance(v, config) for v in a])
    tol_b = np.array([side_tolerance(v, config) for v in b])
    close = (np.abs(a[:, None] - a[None]) <= tol_a[:, None] + tol_a[None]) & (
        np.abs(b[:, None] - b[None]) <= tol_b[:, None] + tol_b[None]
    )
    return close, tol_b


def size_classes(
    entries: Sequence[CatalogueEntry], config: RectangleConfig = RectangleConfig()
) -> list[list[str]]:
    """Names of the entries whose sides a measurement cannot tell apart, one list per class.

    Classes are the connected groups of entries of the same size (sides within the summed
    tolerances, :func:`spacepose.core.rectangles.side_tolerance`), in catalogue order; an entry
    alone in its class is named by its sides.
    """
    if len(entries) == 0:
        return []
    close, _ = _same_size(entries, config)
    _, labels = connected_components(csr_matrix(close), directed=False)
    order = list(dict.fromkeys(labels.tolist()))
    return [[e.name for e, lab in zip(entries, labels, strict=True) if lab == k] for k in order]


def check_distinguishable(
    entries: Sequence[CatalogueEntry],
    config: RectangleConfig = RectangleConfig(),
    source: str | Path = "catalogue",
) -> None:
    """Raise ConfigError naming the first pair of entries that are the same face listed twice.

    Entries i and j are the same face when ``|a_i − a_j| <= tol(a_i) + tol(a_j)`` and the same
    holds for b (tol from :func:`spacepose.core.rectangles.side_tolerance`), their outward
    normals are less than 90° apart and their centres lie within ``tol(b_i) + tol(b_j)``.
    Equal faces elsewhere on the target (opposite faces, two equal wings) are legal.
    """
    if len(entries) < 2:
        return
    close, tol_b = _same_size(entries, config)
    normals = np.stack([e.rotation[:, 2] for e in entries])
    centres = np.stack([e.centre for e in entries])
    # A small margin so that exactly perpendicular faces (a box's sides) count as separable.
    close &= normals @ normals.T > 1e-6
    apart = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    close &= apart <= tol_b[:, None] + tol_b[None]
    i, j = np.nonzero(np.triu(close, k=1))
    if len(i):
        ei, ej = entries[int(i[0])], entries[int(j[0])]
        raise ConfigError(
            f"{source}: rectangles {ei.name!r} ({ei.a:g} x {ei.b:g} m) and {ej.name!r} "
            f"({ej.a:g} x {ej.b:g} m) cannot be told apart: the same face twice (sizes and "
            f"centres within the tolerance, abs {config.side_tolerance_abs:g} m + rel "
            f"{config.side_tolerance_rel:g}, normals less than 90 degrees apart)"
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
        Recognition tolerances (two entries within them at the same place are one face twice).

    Raises
    ------
    ConfigError
        The file cannot be read or parsed, or :func:`parse_catalogue` rejects its content.
    """
    path = Path(path)
    text = read_config_text(path, "the rectangle catalogue")
    return parse_catalogue(parse_structured(text, path), config, path)


def _entry_problem(err: dict) -> str:
    """One of pydantic's errors of a catalogue entry as ``field: problem`` (the entry's own
    checks as their words alone: "<entry>: Value error, invalid catalogue entry: a: ..." was
    shown as it came)."""
    field = ".".join(str(p) for p in err["loc"])
    message = err["msg"].removeprefix("Value error, ").removeprefix("invalid catalogue entry: ")
    return f"{field}: {message}" if field else message
