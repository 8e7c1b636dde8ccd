"""The cells of the robustness grid (:mod:`spacepose.tools.experiments.robustness`): its axes,
one run's coordinates and scenario, and the runs an experiment's options select, each checked
before any runs.

Selecting cells: ``"target=lab,range=1.2+25,seed=0"`` (``+`` separates values; an axis not named
spans the grid, or with ``quick`` takes the default cell's value), or a YAML / JSON file holding
any subset of :class:`RobustnessGrid`'s fields. ``quick`` alone runs the default cell (lab,
1.2 m, ×1, constant, none) and seven variants, six changing one axis and the wall alone at 3 m,
8 frames each.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from pydantic import Field, NonNegativeInt

import spacepose
from spacepose.core.config import StageConfig, load_config, validate_config
from spacepose.core.sim import LabConfig, grid_scenario
from spacepose.core.sim.grid import CLUTTERS, MOTIONS, motion_fields
from spacepose.core.sim.random_targets import generated_seed
from spacepose.errors import ConfigError

MODELS_DIR = Path(spacepose.__file__).resolve().parents[2] / "data" / "models"
TARGETS = {"hubble": "hubble_model_kit.obj", "panels": "satellite_panels.obj"}
AXES = ("target", "range", "noise", "motion", "clutter", "seed")
# The axes whose values are numbers (read so from a command line's text).
_NUMERIC = ("range", "noise", "seed")
QUICK_FRAMES = 8
# Quick subset: the default cell and one variant per axis; the wall alone at 3 m, where the
# mock-up holds 1 % of the cells that the wall's spacing sizes.
QUICK_VARIANTS: tuple[dict[str, Any], ...] = (
    {"target": "hubble"},
    {"target": "panels"},
    {"range": 25.0},
    {"noise": 3.0},
    {"motion": "tumbling-5"},
    {"clutter": "wall-table"},
    {"clutter": "wall", "range": 3.0},
)


class RobustnessGrid(StageConfig):
    """The axes of the robustness grid (the full grid by default) and the frames of a run."""

    target: list[str] = Field(["lab", "hubble", "panels"], min_length=1)
    range: list[float] = Field([0.5, 1.2, 3.0, 6.0, 25.0], min_length=1)
    noise: list[float] = Field([1.0, 3.0], min_length=1)
    motion: list[str] = Field(list(MOTIONS), min_length=1)
    # The wall alone (a third clutter) is an option, not in the full grid of the README.
    clutter: list[str] = Field(["none", "wall-table"], min_length=1)
    seed: list[NonNegativeInt] = Field([0, 1, 2, 3, 4], min_length=1)
    frames: int = Field(30, ge=2, description="Frames per run.")


@dataclass(frozen=True)
class Cell:
    """One run of the grid: a cell's coordinates and a seed."""

    target: str = "lab"
    range: float = 1.2
    noise: float = 1.0
    motion: str = "constant"
    clutter: str = "none"
    seed: int = 0

    @property
    def key(self) -> tuple[Any, ...]:
        """The coordinates without the seed (the runs a table row averages)."""
        return (self.target, self.range, self.noise, self.motion, self.clutter)

    @property
    def label(self) -> str:
        return f"{self.target} {self.range:g} m x{self.noise:g} {self.motion} {self.clutter}"


def mesh_path(target: str) -> str:
    """``"lab"`` or ``"random:K"`` (a generated spacecraft), or the mesh file of a target name
    of :data:`TARGETS` or path."""
    if target == "lab" or generated_seed(target) is not None:
        return target
    path = MODELS_DIR / TARGETS[target] if target in TARGETS else Path(target)
    if not path.exists():
        # Said as missing: "not a mesh file" sent a user looking at a file that is not there.
        raise ConfigError(f"{path}: robustness target {target!r}: no such mesh file")
    if not path.is_file():
        raise ConfigError(f"{path}: robustness target {target!r} is not a mesh file")
    return str(path)


def _meaning(axis: str, value: object) -> object:
    """What a cell's value on ``axis`` runs: a motion's scenario fields (``tumbling-5`` and
    ``tumbling-5.0`` are one), the value itself for the rest and for an unknown motion (which
    :func:`check_cells` names with its source)."""
    if axis != "motion":
        return value
    try:
        return motion_fields(str(value))
    except ConfigError:
        return value


def _number(name: str, text: str) -> float:
    """A numeric axis's value as a number (a seed's ``2`` as 2.0 too: the grid takes a whole
    float as its int).

    Raises
    ------
    ConfigError
        ``text`` reads as no number.
    """
    try:
        return float(text)
    except ValueError:
        raise ConfigError(f"--cells {name}={text}: {text!r} is not a number") from None


def parse_cells(spec: str) -> dict[str, list[str] | list[float]]:
    """``"target=lab,range=1.2+25"`` -> ``{"target": ["lab"], "range": [1.2, 25.0]}``: the
    numbers of the numeric axes read here (a config file's quoted number is refused, and a
    command line's are all text).

    Raises
    ------
    ConfigError
        An item that is not ``AXIS=VALUE[+VALUE...]``, an axis named twice, a numeric axis's
        value that is no number, or no item at all.
    """
    axes: dict[str, list[str] | list[float]] = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        name, sep, values = item.partition("=")
        name = name.strip()
        if not sep or name not in AXES or not values.strip():
            raise ConfigError(
                f"--cells {item!r}: write AXIS=VALUE[+VALUE...] with AXIS one of {', '.join(AXES)}"
            )
        if name in axes:
            raise ConfigError(f"--cells: axis {name} is named twice; join its values with +")
        written = [v.strip() for v in values.split("+")]
        if not all(written):
            # "range=1+" or "range=+": a value left out, said with what was typed.
            raise ConfigError(f"--cells {item!r}: an empty value between the + signs")
        axes[name] = [_number(name, v) for v in written] if name in _NUMERIC else written
    if not axes:
        raise ConfigError(f"--cells {spec!r} names no cells; write AXIS=VALUE[+VALUE...]")
    return axes


def cell_scenario(cell: Cell, frames: int) -> LabConfig:
    """The scenario config of one run of the grid (:func:`~spacepose.core.sim.grid_scenario`)."""
    return grid_scenario(
        target=mesh_path(cell.target),
        range_m=cell.range,
        noise_scale=cell.noise,
        motion=cell.motion,
        clutter=cell.clutter,
        seed=cell.seed,
        frames=frames,
    )


def cell_problem(cell: Cell) -> str | None:
    """What keeps a run from simulating (None: nothing), naming the axis and its value.

    Builds the run's scenario config (no simulation), so a whole grid is checked in
    milliseconds; the range must also lie within the range of the sensor the scenario picks,
    or the target's frames would be empty.
    """
    try:
        generated = generated_seed(cell.target) is not None
    except ConfigError as exc:
        return str(exc)
    known = generated or cell.target == "lab" or cell.target in TARGETS
    if not known and not Path(cell.target).is_file():
        return (
            f"unknown target {cell.target!r}; choose lab, {', '.join(TARGETS)}, random:K or a "
            "mesh file"
        )
    if not (math.isfinite(cell.range) and cell.range > 0):
        return f"range {cell.range:g} is not a positive number of metres"
    if not (math.isfinite(cell.noise) and cell.noise >= 0):
        return f"noise {cell.noise:g} is not a factor >= 0 of the sensor's sigma"
    if cell.clutter not in CLUTTERS:
        return f"unknown clutter {cell.clutter!r}; choose {', '.join(CLUTTERS)}"
    try:
        motion_fields(cell.motion)
    except ConfigError as exc:  # an unknown name, told as such rather than as the cell's
        return str(exc)
    try:
        config = cell_scenario(cell, 2)
    except ConfigError as exc:
        return f"cell {cell.label} seed {cell.seed}: {exc}"
    sensor = config.sensor
    if not sensor.min_range <= cell.range <= sensor.max_range:
        return (
            f"range {cell.range:g} m is outside the {sensor.min_range:g}-{sensor.max_range:g} m "
            f"that the {sensor.model} sees"
        )
    return None


def check_cells(runs: Sequence[Cell], source: str) -> None:
    """Check every run before any starts (:func:`cell_problem`), so that a bad value ends the
    experiment at once instead of as an error record among the results.

    Raises
    ------
    ConfigError
        ``source: `` and the first problem found.
    """
    for cell in dict.fromkeys(runs):
        problem = cell_problem(cell)
        if problem is not None:
            raise ConfigError(f"{source}: {problem}")


def is_cells_file(cells: str) -> bool:
    """Whether a ``cells`` option names a YAML / JSON file (else it is a selection string)."""
    return Path(cells).suffix.lower() in (".yaml", ".yml", ".json")


def select_cells(
    cells: str | None, quick: bool, frames: int | None, seed: int = 0
) -> tuple[list[Cell], int]:
    """The runs and the frames per run an experiment's options ask for (module notes).

    Raises
    ------
    ConfigError
        A bad selection or cells file (an empty one included), or a run that cannot simulate
        (:func:`check_cells`).
    """
    source = "--cells"
    # With --quick the axes a selection leaves out keep the quick cell's one value (a file's
    # too: it ran the whole grid on the axes it did not name, 500 runs for "target: [lab]").
    base = {} if not quick else {a: [v] for a, v in asdict(Cell(seed=seed)).items()}
    base |= {"frames": QUICK_FRAMES} if quick else {}
    if cells is not None and is_cells_file(cells):
        source = cells
        grid = load_config(RobustnessGrid, cells)
        # An empty file would otherwise mean the whole grid, hours of runs nobody asked for;
        # so would one of frames alone (1,500 runs for "frames: 5").
        if not grid.model_fields_set & set(AXES):
            raise ConfigError(f"{cells}: holds no cells; set any of {', '.join(AXES)}")
        named = {a: getattr(grid, a) for a in grid.model_fields_set}
        grid = validate_config(RobustnessGrid, base | named, source=source)
    elif cells is not None:
        grid = validate_config(RobustnessGrid, base | parse_cells(cells), source=source)
    elif quick:
        default = Cell(seed=seed)
        runs = [default, *(replace(default, **variant) for variant in QUICK_VARIANTS)]
        check_cells(runs, "--seed")
        return runs, frames or QUICK_FRAMES
    else:
        grid = RobustnessGrid()
    for axis in AXES:
        values = getattr(grid, axis)
        # A motion by what it means: tumbling-5 and tumbling-5.0 ran the same cells twice.
        meant = [_meaning(axis, v) for v in values]
        twice = next((v for k, v in enumerate(values) if meant[k] in meant[:k]), None)
        if twice is not None:  # the same runs again, reported as more seeds with no spread
            raise ConfigError(f"{source}: {axis} {twice} is named twice")
    runs = [Cell(*values) for values in itertools.product(*(getattr(grid, a) for a in AXES))]
    check_cells(runs, source)
    return runs, frames or grid.frames
