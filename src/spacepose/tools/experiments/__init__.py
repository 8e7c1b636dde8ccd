"""Reproductions of the papers' experiments (methods.md §1.7 and §2.5) on the simulator.

Each experiment is a function ``(out_dir, options) -> dict`` registered under a name such as
``li-l3`` or ``yu-y1``; it writes its tables (JSON) and figures (PNG) into ``out_dir`` and returns
the table it wrote. Modules are imported on first use so the CLI starts fast.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spacepose.errors import ConfigError, SpaceposeError
from spacepose.tools.outputs import check_writable

# Modules that register experiments when imported.
_MODULES: tuple[str, ...] = (
    "yu_geometry",
    "yu_nav",
    "li",
    "li_tracking",
    "li_global",
    "robustness",
    "fusion",
    "room",
)


@dataclass(frozen=True)
class ExperimentOptions:
    """Options every experiment accepts.

    Attributes
    ----------
    seed
        Seed of every random draw in the experiment.
    quick
        Smaller sizes and fewer repetitions, for tests and smoke runs.
    workers
        Threads for neighbour searches (-1: all cores).
    seeds
        li-l1, li-l3, fusion and room: number of seeds, from ``seed`` on (None: the
        experiment's default).
    targets
        ``fusion`` only: comma-separated targets (None: the experiment's own).
    cells, frames, frames_csv, jobs, tracker
        ``robustness`` (``frames`` also fusion and room): the grid cells to run (selection
        string or config file, None: the whole grid), frames per run (None: the experiment's
        default), whether to write every frame's scores, the processes running cells, and a
        tracker config file (YAML or JSON; None: the defaults).

    An experiment refuses any of :data:`OWN_OPTIONS` it does not read (:func:`check_options`).
    """

    seed: int = 0
    quick: bool = False
    workers: int = -1
    seeds: int | None = None
    cells: str | None = None
    frames: int | None = None
    frames_csv: bool = False
    jobs: int = 1
    tracker: str | None = None
    targets: str | None = None


Experiment = Callable[[Path, ExperimentOptions], dict[str, Any]]
_REGISTRY: dict[str, Experiment] = {}
# Options that only some experiments read; set for another one, they are an error, not ignored
# (li-l2 --frames 5 ran its own frames and said nothing).
OWN_OPTIONS: tuple[str, ...] = (
    "cells",
    "tracker",
    "targets",
    "seeds",
    "frames",
    "frames_csv",
    "jobs",
)
_USES: dict[str, tuple[str, ...]] = {}
# Most seeds a run takes: a simulation each (with its frames) over every method or target;
# 10**10 ended in a MemoryError traceback (fusion) or ran for ever (li-l1).
MOST_SEEDS = 1000
# Most frames a run takes, as the simulator's scenarios take them: robustness --frames 10**9
# failed every cell on the scenario's bound and exited 0, room's 10**12 a MemoryError traceback.
MOST_FRAMES = 1_000_000


def register(name: str, uses: tuple[str, ...] = ()) -> Callable[[Experiment], Experiment]:
    """Decorator that makes an experiment available under ``name``; ``uses``: the options of
    :data:`OWN_OPTIONS` it reads."""

    def wrap(fn: Experiment) -> Experiment:
        _REGISTRY[name] = fn
        _USES[name] = uses
        return fn

    return wrap


def check_options(name: str, options: ExperimentOptions) -> None:
    """Refuse an option of :data:`OWN_OPTIONS` that experiment ``name`` would ignore.

    Raises
    ------
    ConfigError
        ``--cells: experiment 'li-l1' does not use it (only robustness does)``; ``--seeds``
        beyond :data:`MOST_SEEDS`, ``--frames`` beyond :data:`MOST_FRAMES`.
    """
    defaults = ExperimentOptions()
    for option in OWN_OPTIONS:
        given = getattr(options, option) != getattr(defaults, option)
        if given and option not in _USES[name]:
            users = sorted(n for n, uses in _USES.items() if option in uses)
            verb = "does" if len(users) == 1 else "do"
            raise ConfigError(
                f"--{option.replace('_', '-')}: experiment {name!r} does not use it (only "
                f"{', '.join(users)} {verb})"
            )
    if options.seeds is not None and not 1 <= options.seeds <= MOST_SEEDS:
        raise ConfigError(
            f"--seeds: {options.seeds} is not a number of seeds from 1 to {MOST_SEEDS} (each is "
            "a simulation and its runs)"
        )
    if options.frames is not None and not 2 <= options.frames <= MOST_FRAMES:
        raise ConfigError(
            f"--frames: {options.frames} is not a number of frames from 2 to {MOST_FRAMES:,} (a "
            "run's frames are simulated, as simulate's --frames)"
        )


def available() -> list[str]:
    """Names of every registered experiment, sorted."""
    for module in _MODULES:
        importlib.import_module(f"spacepose.tools.experiments.{module}")
    return sorted(_REGISTRY)


def run_experiment(name: str, out_dir: str | Path, options: ExperimentOptions) -> dict[str, Any]:
    """Run the experiment ``name``, writing into ``out_dir``; returns its result table."""
    names = available()
    if name not in _REGISTRY:
        raise ConfigError(f"unknown experiment {name!r}; choose one of: {', '.join(names)}")
    check_options(name, options)
    out = Path(out_dir)
    # A file where a folder goes is named, as every command's output check does.
    check_writable(out / f"{name}.json")
    # The folders this run makes, deepest first: a run refused before it writes (a bad cell,
    # a config it cannot read) leaves no empty folders behind.
    made = [p for p in (out, *out.parents) if not p.exists()]
    out.mkdir(parents=True, exist_ok=True)
    try:
        return _REGISTRY[name](out, options)
    except SpaceposeError:
        for folder in made:
            if any(folder.iterdir()):
                break
            folder.rmdir()
        raise
