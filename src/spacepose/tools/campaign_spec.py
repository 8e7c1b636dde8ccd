"""The spec of a campaign: its config, the checks of its grid, and the cases it expands to.

A campaign is described by a :class:`CampaignConfig` (read by :func:`load_campaign_config` from
YAML or JSON). Its grid is checked as it is read: the four :data:`REQUIRED_AXES`, one type per
axis, no duplicates, and only the axes and values (names, numeric bounds) that the case runner
of its ``case_kind`` accepts, so that no case fails in a worker on a value the file holds. Its
cases are the Cartesian product of the axes (:func:`expand_grid`); each is identified by
:func:`case_id`, a short hash of its sorted parameters, so a resumed run recognises finished
cases whatever the order of the grid.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import (
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    StrictStr,
    field_validator,
    model_validator,
)

from spacepose.core.config import StageConfig, load_config
from spacepose.errors import ConfigError
from spacepose.tools.campaign_cases import CaseRunner, Scalar, get_runner

REQUIRED_AXES: tuple[str, ...] = ("scenario", "noise_scale", "method", "seed")
# Columns the campaign adds itself; neither an axis nor a metric may take these names.
RESERVED_COLUMNS: tuple[str, ...] = ("case_id", "error", "time_s")
# Keys of a summary record; an axis of that name would be overwritten there.
_SUMMARY_KEYS: tuple[str, ...] = ("metric", "n", "n_failed", "mean", "std", "median", "p95")
NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
# Cases of one campaign: each takes a second or more, so a million run for days on a cluster.
MOST_CASES = 1_000_000


# --------------------------------------------------------------------------------------------
# Config and cases
# --------------------------------------------------------------------------------------------


class CampaignConfig(StageConfig):
    """A Monte Carlo campaign.

    Attributes
    ----------
    name
        Campaign name (stored with the results; a folder holds one campaign).
    grid
        Axis name -> list of values. ``scenario``, ``noise_scale``, ``method`` and ``seed`` are
        required; a runner may accept extra axes (e.g. ``frames``). Every axis is non-empty,
        without duplicates, of one type (numbers mixing int and float become float).
    out
        Output folder (relative paths are taken from the current directory).
    case_kind
        Name of the registered case runner.
    workers
        Worker processes of the local Dask cluster.
    threads_per_worker
        Threads per worker process (cases run concurrently in a worker).
    connect_timeout_s
        How long to wait for an external scheduler (``--scheduler``).
    """

    name: str = Field("campaign", min_length=1)
    grid: dict[str, list[StrictBool | StrictInt | StrictFloat | StrictStr]]
    out: Path = Path("runs/campaign")
    case_kind: str = "registration"
    workers: int = Field(2, ge=1)
    threads_per_worker: int = Field(1, ge=1)
    connect_timeout_s: float = Field(10.0, gt=0)

    @field_validator("grid", mode="before")
    @classmethod
    def _plain_values(cls, grid: object) -> object:
        # Said here in one line: pydantic tried each scalar type in turn and listed all four
        # failures ("grid.noise_scale.0.bool: ...; .int: ...; .float: ...; .str: ...").
        if not isinstance(grid, dict):
            return grid
        for axis, values in grid.items():
            for value in values if isinstance(values, list) else ():
                if isinstance(value, list | dict):
                    raise ValueError(f"{axis}: {value!r} is no single value (a list in a list?)")
                if isinstance(value, float) and not math.isfinite(value):
                    raise ValueError(f"{axis}: {value!r} is not a finite number")
        return grid

    @field_validator("grid")
    @classmethod
    def _check_grid(cls, grid: dict[str, list[Scalar]]) -> dict[str, list[Scalar]]:
        missing = [axis for axis in REQUIRED_AXES if axis not in grid]
        if missing:
            raise ValueError(f"missing axis {', '.join(missing)} (required: {REQUIRED_AXES})")
        grid = {axis: _check_axis(axis, values) for axis, values in grid.items()}
        cases = math.prod(len(values) for values in grid.values())
        if cases > MOST_CASES:
            # 3000 seeds by 3000 noise scales were taken, and the run built the list of its
            # 9 million cases before the first one, for hours.
            sizes = " x ".join(f"{len(v)} {axis}" for axis, v in grid.items())
            raise ValueError(f"{sizes} make {cases:,} cases, more than {MOST_CASES:,}")
        return grid

    @model_validator(mode="after")
    def _check_runner(self) -> CampaignConfig:
        # ConfigError is a ValueError, so pydantic reports it as this field's error.
        runner = get_runner(self.case_kind)
        for axis, allowed in runner.choices.items():
            unknown = [v for v in self.grid.get(axis, ()) if v not in allowed]
            if unknown:
                raise ValueError(
                    f"unknown {axis} {', '.join(map(repr, unknown))} for case_kind "
                    f"{self.case_kind!r}; choose from: {', '.join(map(str, allowed))}"
                )
        for axis, bound in runner.bounds.items():
            problem = bound.problem(axis, self.grid.get(axis, ()))
            if problem is not None:
                raise ValueError(f"{problem} for case_kind {self.case_kind!r}")
        problem = _scenario_problem(runner, self.grid)
        if problem is not None:
            raise ValueError(f"{problem} (for case_kind {self.case_kind!r})")
        extra = [a for a in self.grid if a not in REQUIRED_AXES and a not in runner.extra_axes]
        if extra:
            raise ValueError(
                f"axis {', '.join(map(repr, extra))} is not used by case_kind {self.case_kind!r} "
                f"(it accepts: {', '.join(REQUIRED_AXES + runner.extra_axes)})"
            )
        return self


def _scenario_problem(runner: CaseRunner, grid: dict[str, list[Scalar]]) -> str | None:
    """Why a combination of the grid's values makes no scenario (None: each makes one): a
    noise_scale whose noise overflows, frames beyond the simulator's bound. Each such case
    failed in a worker, every one of them, after the campaign had started."""
    if runner.scenario is None:
        return None
    axes = [axis for axis in runner.scenario_axes if axis in grid]
    for values in itertools.product(*(grid[axis] for axis in axes)):
        params = dict(zip(axes, values, strict=True))
        try:
            runner.scenario(params)
        except ConfigError as exc:
            where = ", ".join(f"{axis} {value!r}" for axis, value in params.items())
            return f"grid: {where}: {exc}"
    return None


def _check_axis(axis: str, values: list[Scalar]) -> list[Scalar]:
    """Validate one grid axis; int/float mixtures become float so a column has one type."""
    if not NAME_RE.match(axis) or axis in RESERVED_COLUMNS + _SUMMARY_KEYS:
        raise ValueError(
            f"axis name {axis!r} must be an identifier other than "
            f"{', '.join(RESERVED_COLUMNS + _SUMMARY_KEYS)}"
        )
    if not values:
        raise ValueError(f"axis {axis!r} is empty")
    kinds = {bool if isinstance(v, bool) else str if isinstance(v, str) else float for v in values}
    if len(kinds) > 1:
        raise ValueError(f"axis {axis!r} mixes value types: {values}")
    # noise_scale is always float, so 1 and 1.0 give one case id across config edits.
    if float in kinds and (axis == "noise_scale" or any(isinstance(v, float) for v in values)):
        values = [float(v) for v in values]
    if any(isinstance(v, float) and not math.isfinite(v) for v in values):
        raise ValueError(f"axis {axis!r} has a non-finite value: {values}")
    # The results table stores integers in 64 bits: a larger one ran every case, then ended
    # the campaign in pyarrow's OverflowError traceback (and every resume after it).
    if any(type(v) is int and not -(2**63) <= v < 2**63 for v in values):
        raise ValueError(f"axis {axis!r} has an integer beyond 64 bits: {values}")
    if len(set(values)) != len(values):
        raise ValueError(f"axis {axis!r} has duplicate values: {values}")
    # The simulator and the perturbation draw from default_rng([seed, ...]): no negative seed.
    if axis == "seed" and not all(
        isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in values
    ):
        raise ValueError(f"seeds must be integers >= 0, got {values}")
    if axis == "noise_scale" and not (float in kinds and all(v >= 0 for v in values)):
        raise ValueError(f"noise_scale values must be numbers >= 0, got {values}")
    if axis in ("scenario", "method") and kinds != {str}:
        raise ValueError(f"{axis} values must be names (strings), got {values}")
    return values


def load_campaign_config(
    path: str | Path, *, workers: int | None = None, out: str | Path | None = None
) -> CampaignConfig:
    """Read a campaign YAML/JSON file; ``workers`` and ``out`` override the file's values."""
    config = load_config(CampaignConfig, path)
    update: dict[str, Any] = {}
    if workers is not None:
        if workers < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        update["workers"] = workers
    if out is not None:
        update["out"] = Path(out)
    return config.model_copy(update=update)


@dataclass(frozen=True)
class Case:
    """One point of the grid: its parameters and their hash."""

    case_id: str
    params: dict[str, Scalar]


def case_id(params: Mapping[str, Scalar]) -> str:
    """Stable 12-hex-digit identifier of a parameter set (independent of key order)."""
    canonical = json.dumps(dict(params), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()[:12]


def expand_grid(grid: Mapping[str, Sequence[Scalar]]) -> list[Case]:
    """All cases of the grid (Cartesian product of the axes), sorted by ``case_id``."""
    axes = list(grid)
    cases = []
    for values in itertools.product(*(grid[a] for a in axes)):
        params = dict(zip(axes, values, strict=True))
        cases.append(Case(case_id(params), params))
    return sorted(cases, key=lambda c: c.case_id)
