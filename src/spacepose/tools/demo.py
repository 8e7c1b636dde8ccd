"""The whole story in one call (``make demo``): simulate, track, navigate, score, report.

Steps, each writing into one folder:

1. simulate the lab run (Li et al.) and the orbit run (Yu et al.);
2. track the lab run with ICP, GICP and J-ICP (model-free, methods.md §0);
3. navigate the orbit run with the rectangle-based EKF, with no prior (the lost-in-space start
   on the run's model; the scenario's measured process noise and chaser-attitude σ, as
   experiment yu-y4 does);
4. score both against the ground truth: Li's Table 2 layout and Yu's Y4 errors;
5. run the two quick experiments whose figures the report shows (normal consistency L1,
   coarse registration against noise L2);
6. write the HTML report.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.table import Table

from spacepose.core.metrics import evaluate, navigation_errors
from spacepose.core.navigation import NavigationConfig
from spacepose.core.sim import scenario_config, simulate
from spacepose.errors import InputError
from spacepose.tools.experiments import ExperimentOptions, run_experiment
from spacepose.tools.experiments.li import AXES, METHODS, PAPER_TABLE2
from spacepose.tools.experiments.yu_nav import navigation_config
from spacepose.tools.navigation_io import navigate_run
from spacepose.tools.navigation_io import output_paths as navigation_output_paths
from spacepose.tools.report import build_report
from spacepose.tools.runs import read_run, write_run
from spacepose.tools.text_io import strict_json
from spacepose.tools.tracking_io import output_paths, track_folder, tracker_config
from spacepose.tools.trajectory_io import read_tum

# Yu et al. 2019 (methods.md §2.5, Y4): accuracy the paper reports after convergence, per axis.
PAPER_Y4 = {
    "position (mm)": (1.4, 3.2, 1.4),
    "velocity (mm/s)": (0.01, 0.01, 0.01),
    "attitude (deg)": (0.1, 0.1, 0.1),
    "angular rate (deg/s)": (0.01, 0.01, 0.01),
    "centre-of-mass offset (mm)": (1.0, 1.0, 1.0),
}
_NAV_ROWS = {
    "position": "position (mm)",
    "velocity": "velocity (mm/s)",
    "attitude": "attitude (deg)",
    "angular rate": "angular rate (deg/s)",
    "centre-of-mass offset": "centre-of-mass offset (mm)",
}


@dataclass(frozen=True)
class DemoResult:
    """Tables and paths of one demo run.

    Attributes
    ----------
    li_table
        Method -> axis -> (mean, std) of the absolute per-frame errors (mm, deg).
    yu_table
        State group -> RMS per axis over the second half of the orbit run (display units).
    report
        The HTML report.
    seconds
        Step name -> wall time.
    """

    li_table: dict[str, dict[str, tuple[float, float]]]
    yu_table: dict[str, list[float]]
    report: Path
    seconds: dict[str, float]


def run_demo(
    out: str | Path,
    *,
    orbit_frames: int = 600,
    seed: int = 0,
    workers: int = -1,
    log: Callable[[str], None] = print,
) -> DemoResult:
    """Run every step of the demo into ``out`` and return the two tables.

    Parameters
    ----------
    out
        Folder for the runs (``lab/``, ``orbit/``), the experiments and ``report.html``.
    orbit_frames
        Length of the orbit run (600 in Yu et al.'s scenario).
    seed
        Seed of both simulations and the experiments.
    workers
        Threads for neighbour searches.
    log
        Receives one line per step.
    """
    root = Path(out)
    _check_out_folder(root)
    seconds: dict[str, float] = {}

    def step(name: str, fn: Callable[[], Any]) -> Any:
        start = time.perf_counter()
        log(f"{name} ...")
        value = fn()
        seconds[name] = time.perf_counter() - start
        log(f"{name}: {seconds[name]:.1f} s")
        return value

    lab_dir, orbit_dir = root / "lab", root / "orbit"
    # The demo's own results of an earlier demo go first: the new runs' frames are not theirs.
    earlier = [p for m in METHODS for p in output_paths(lab_dir / "tracks" / f"{m}.tum")]
    for path in [*earlier, *navigation_output_paths(orbit_dir / "nav.csv")]:
        path.unlink(missing_ok=True)
    step("simulate lab", lambda: write_run(lab_dir, simulate(scenario_config("lab", seed=seed))))
    step(
        "simulate orbit",
        lambda: write_run(
            orbit_dir, simulate(scenario_config("orbit", seed=seed, frames=orbit_frames))
        ),
    )
    for method in METHODS:
        step(
            f"track lab ({method})",
            lambda m=method: track_folder(
                lab_dir, lab_dir / "tracks" / f"{m}.tum", tracker_config(method=m), workers=workers
            ),
        )
    nav_config = navigation_config(read_run(orbit_dir).scenario, NavigationConfig())
    step("navigate orbit", lambda: navigate_run(orbit_dir, orbit_dir / "nav.csv", nav_config))
    li_table = _li_table(lab_dir)
    yu_table = _yu_table(orbit_dir)
    options = ExperimentOptions(seed=seed, quick=True, workers=workers)
    for name in ("li-l1", "li-l2"):
        step(
            f"experiment {name}",
            lambda n=name: run_experiment(n, root / "experiments" / n, options),
        )
    (root / "tables.json").write_text(
        strict_json({"li_table2": li_table, "yu_y4_rms": yu_table, "seconds": seconds}, indent=1)
    )
    report = step("report", lambda: build_report(root))
    return DemoResult(li_table, yu_table, report, seconds)


def _check_out_folder(root: Path) -> None:
    """Refuse an ``--out`` that is (or lies under) a regular file: the demo failed after its
    first simulation on "FILE/lab/tracks/point_to_point.tum: Not a directory".

    Raises
    ------
    InputError
        One line naming ``root``: it is a file, or lies under one.
    """
    existing = root
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        where = "is a file, not a folder" if existing == root else f"lies under {existing}, a file"
        raise InputError(
            f"--out {where}: the demo writes its runs and report.html into a folder", root
        )


def _li_table(lab_dir: Path) -> dict[str, dict[str, tuple[float, float]]]:
    gt = read_tum(lab_dir / "groundtruth.tum")
    table = {}
    for method in METHODS:
        est = read_tum(lab_dir / "tracks" / f"{method}.tum")
        d = evaluate(est, gt, rebase_first=True).to_dict()
        table[method] = {a: (d["mean"][a], d["std"][a]) for a in AXES}
    return table


def _yu_table(orbit_dir: Path) -> dict[str, list[float]]:
    def columns(path: Path) -> dict[str, np.ndarray]:
        header = path.read_text().splitlines()[0].split(",")
        data = np.genfromtxt(path, delimiter=",", skip_header=1, dtype=float)
        return {c: data[:, i] for i, c in enumerate(header) if c != "status"}

    errors = navigation_errors(columns(orbit_dir / "nav.csv"), columns(orbit_dir / "truth.csv"))
    return {_NAV_ROWS[k]: v for k, v in errors.rms(0.5).items() if k in _NAV_ROWS}


def li_rich_table(li_table: dict[str, dict[str, tuple[float, float]]]) -> Table:
    """Li et al.'s Table 2 layout: mean (std) per axis and method, the paper's J-ICP beside."""
    table = Table(title="Lab run (Li et al. Table 2): mean (std) of |error|")
    table.add_column("error")
    for method in METHODS:
        table.add_column(method.upper().replace("JICP", "J-ICP"), justify="right")
    table.add_column("paper J-ICP", justify="right", style="dim")
    for axis in AXES:
        name, unit = axis.rsplit("_", 1)
        cells = [f"{li_table[m][axis][0]:.3f} ({li_table[m][axis][1]:.3f})" for m in METHODS]
        paper = PAPER_TABLE2["jicp"][axis]
        table.add_row(f"{name} ({unit})", *cells, f"{paper[0]:.3f} ({paper[1]:.3f})")
    return table


def yu_rich_table(yu_table: dict[str, list[float]]) -> Table:
    """Yu et al.'s Y4 errors: RMS per axis over the second half, the paper's accuracy beside."""
    table = Table(title="Orbit run (Yu et al. Y4): RMS error over the second half")
    for col in ("state", "x", "y", "z", "paper (x, y, z)"):
        table.add_column(col, justify="left" if col == "state" else "right")
    for name, rms in yu_table.items():
        paper = ", ".join(f"{v:g}" for v in PAPER_Y4[name])
        table.add_row(name, *(f"{v:.4g}" for v in rms), f"< {paper}")
    return table
