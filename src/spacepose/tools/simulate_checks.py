"""What `simulate` says of the run it wrote: a target frame that is not the mesh file's own,
and an orbit target with no rectangle catalogue to navigate on."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from spacepose.core.sim.simulation import Simulation
from spacepose.errors import SpaceposeWarning


def warn_if_model_moved(model: Path, mesh: Any, scale: float) -> None:
    """Warn when the run's target frame is not ``model``'s own: the mesh is centred on its
    bounding box (and sized or aligned by the grid), the run's ``model.ply`` and ``model.obj``
    are in that frame, and a track against the file itself was off by the shift (an
    asymmetric mesh: 566 mm of ATE, every frame `ok`) without a word. A generated spacecraft
    (``random:K``) has no file to be tracked against."""
    from spacepose.core.sim.mesh_files import load_mesh
    from spacepose.core.sim.random_targets import generated_seed

    if generated_seed(str(model)) is not None:
        return
    own = load_mesh(model, scale=scale, center=False).mesh
    shift = mesh.bounds.mean(axis=0) - own.bounds.mean(axis=0) + 0.0  # no "-0" said
    same_size = np.allclose(np.sort(mesh.extents), np.sort(own.extents), rtol=1e-9)
    if np.linalg.norm(shift) <= 1e-9 * np.linalg.norm(own.extents) and same_size:
        return
    how = f"moved by ({shift[0]:.4g}, {shift[1]:.4g}, {shift[2]:.4g}) m"
    how += "" if same_size else ", and sized or turned"
    warnings.warn(
        SpaceposeWarning(
            f"the run's target frame is the mesh {how}: track against the run's model.ply or "
            "model.obj, not this file",
            model,
        ),
        stacklevel=2,
    )


def warn_if_no_catalogue(sim: Simulation, out: Path) -> None:
    """Warn when an orbit run's target has no rectangle catalogue (a mesh file, or a generated
    spacecraft): `navigate` with its default measurements then refused the run ("the rectangle
    catalogue is empty") after `simulate` had said nothing."""
    if sim.name == "orbit" and not sim.extras.get("rectangles"):
        problem = (
            "the target has no rectangle catalogue (a mesh's faces are not listed): navigate "
            "this run with --measurements registration"
        )
        warnings.warn(SpaceposeWarning(problem, out), stacklevel=2)
