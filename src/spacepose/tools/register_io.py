"""The files of ``spacepose register``: two clouds (or depth images) and an initial transform
read, :func:`~spacepose.tools.register.register` run on them, the JSON summary written.

A depth image is read into its camera's sensor frame through the intrinsics given or beside it;
a fit that leaves directions free, or that holds little of the source, is warned of by name of
the pair.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import holds_boolean, holds_text
from spacepose.core.structured_text import load_structured, parse_problem
from spacepose.errors import FileFormatError, InputError, RegistrationError, SpaceposeWarning
from spacepose.tools.cloud_io import DEPTH_SUFFIXES, read_sensor_cloud
from spacepose.tools.depth_folder import folder_camera
from spacepose.tools.depth_io import read_depth_cloud
from spacepose.tools.intrinsics_io import check_camera, read_intrinsics
from spacepose.tools.outputs import check_spares_inputs, check_text_name, check_writable
from spacepose.tools.register import RegisterConfig, RegisterResult, register
from spacepose.tools.text_io import read_text
from spacepose.tools.trajectory_io import nearest_rotations

# Below this share of the source within the last gate a fit is more likely wrong than partial:
# the real LiDAR pair's scans overlap at 0.90, a 90° local minimum of a cloud on itself 0.39.
_LOW_FITNESS = 0.5


def read_transform(path: str | Path) -> NDArray[np.float64]:
    """A 4×4 transform from a text file (16 numbers apart by blanks or commas; ``#`` starts a
    comment), or a JSON file (``.json``, any case, or any name whose text opens with ``{`` or
    ``[``) holding the matrix (4 rows, or 16 numbers) or a mapping with ``T_target_source``
    (e.g. an earlier ``--out``)."""
    path = Path(path)
    text = read_text(path, "the transform")
    expected = "expected 16 numbers (a 4x4 matrix) or JSON with T_target_source"
    problem = None
    try:
        # register's own --out is JSON whatever its name (result.txt): told by its first
        # character, it was "expected ... JSON with T_target_source" though it held one.
        if path.suffix.lower() == ".json" or text.lstrip()[:1] in ("{", "["):
            data = load_structured(text, "json")
            # A bare matrix is the transform as the key's is: refused, it was "expected" the
            # 4x4 matrix it held.
            values = data["T_target_source"] if isinstance(data, dict) else data
            if holds_text(values):  # numpy would read "0.5" as 0.5, where configs refuse it
                problem = "text where a number goes (write it unquoted)"
        else:
            # '#' comments, as in the T_target_source.txt small_gicp ships and hand-written
            # files, and commas, as numpy.savetxt(delimiter=",") writes: "expected 16
            # numbers" of a file that held them.
            body = " ".join(line.split("#", 1)[0] for line in text.splitlines())
            values = body.replace(",", " ").split()
        if holds_boolean(values):  # numpy would read true as 1
            problem = "a yes/no where a number goes"
        T = np.asarray(values, dtype=np.float64).reshape(4, 4)
    except json.JSONDecodeError as exc:  # where the JSON breaks, not only what was expected
        raise FileFormatError(f"{expected}: not valid JSON: {parse_problem(exc)}", path) from None
    except (ValueError, KeyError, TypeError):
        raise FileFormatError(expected, path) from None
    if problem is not None:
        raise FileFormatError(f"{expected}: {problem}", path)
    if np.isfinite(T).all():
        # Written by hand to 4 decimals (0.8660 for cos 30°) a rotation is off orthonormal by
        # ~1e-4, beyond as_transform's 1e-6: read as the rotation it rounds, as KITTI files are.
        T[:3, :3] = nearest_rotations(T[None, :3, :3])[0]
    try:
        return se3.as_transform(T, "init transform")
    except InputError as exc:
        raise InputError(str(exc), path) from None


def register_files(
    source_path: str | Path,
    target_path: str | Path,
    init_path: str | Path | None = None,
    config: RegisterConfig = RegisterConfig(),
    out: str | Path | None = None,
    workers: int = -1,
    intrinsics: str | Path | None = None,
) -> RegisterResult:
    """Read two cloud files, :func:`register` them and optionally write the JSON summary.

    A depth image (16-bit PNG or TIFF) is read through ``intrinsics`` (or the
    ``intrinsics.yaml`` / ``.json`` beside it) into the camera's sensor frame; ``intrinsics``
    given for two point clouds, or beside an image's own intrinsics file that differs, is
    refused (InputError), not ignored.
    """
    depth_inputs = [
        p for p in (source_path, target_path) if Path(p).suffix.lower() in DEPTH_SUFFIXES
    ]
    if intrinsics is not None and not depth_inputs:
        # Ignored, they would let the user believe the clouds were read through them.
        raise InputError(
            f"intrinsics apply to depth images ({', '.join(DEPTH_SUFFIXES)}), and neither "
            f"{Path(source_path).name} nor {Path(target_path).name} is one: leave out --intrinsics",
            intrinsics,
        )
    if out is not None:
        check_writable(out)
        given = (source_path, target_path, init_path, intrinsics)
        check_spares_inputs([out], [p for p in given if p is not None])
        check_text_name(out, "a JSON result", "name it .json")
    source = _read_input(source_path, intrinsics)
    target = _read_input(target_path, intrinsics)
    init = None if init_path is None else read_transform(init_path)
    pair = f"{source_path} onto {target_path}"
    try:
        outcome = register(source, target, init, config, workers)
    except RegistrationError as exc:  # say which pair failed
        gap = 0.0 if init is None else _box_gap(source.transformed(init).points, target.points)
        if gap > 0:  # the initial transform moved the source clear of the target: the cause
            raise InputError(
                f"the initial transform (--init) moves {source_path} {gap:.3g} m clear of "
                f"{target_path} (their bounding boxes do not meet), and registration failed: "
                f"{exc}",
                init_path,
            ) from None
        raise RegistrationError(f"{pair}: {exc}") from None
    except InputError as exc:
        if exc.source is not None:  # one cloud's own problem, already named
            raise
        # The pair's geometry (two lines, two planes sliding in each other): name both files.
        raise type(exc)(exc.reason, pair) from None
    if outcome.degeneracy.degenerate:
        warnings.warn(SpaceposeWarning(outcome.degeneracy.summary(), pair), stacklevel=2)
    if outcome.result.fitness < _LOW_FITNESS:  # its σ describes the fit, not whether it is right
        warnings.warn(
            SpaceposeWarning(
                f"only {100 * outcome.result.fitness:.0f} % of the source lies within "
                f"{outcome.gates[-1]:.3g} m of the target: a local minimum, or clouds that "
                "overlap little? (the covariance assumes the fit is the right one)",
                pair,
            ),
            stacklevel=2,
        )
    if out is not None:
        summary = {"source": str(source_path), "target": str(target_path), **outcome.to_dict()}
        summary["config"] = config.model_dump(mode="json")
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(summary, indent=2) + "\n")
    return outcome


def _box_gap(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """The distance (m) between the bounding boxes of two (N, 3) clouds; 0 where they meet."""
    apart = np.maximum(a.min(axis=0) - b.max(axis=0), b.min(axis=0) - a.max(axis=0))
    return float(np.linalg.norm(np.maximum(apart, 0.0)))


def _read_input(path: str | Path, intrinsics: str | Path | None) -> PointCloud:
    """A cloud file, or a depth image with its camera's intrinsics.

    Raises
    ------
    InputError
        A depth image without intrinsics, or ``intrinsics`` given that differ from the
        intrinsics file beside it (:func:`~spacepose.tools.depth_folder.folder_camera`).
    """
    path = Path(path)
    if path.suffix.lower() not in DEPTH_SUFFIXES:
        return read_sensor_cloud(path)
    given = None if intrinsics is None else read_intrinsics(intrinsics)
    # As for a depth folder: intrinsics given beside the image's own file that differ are
    # refused (the given file won without a word, the image's own calibration ignored).
    camera, source = folder_camera(path.parent, intrinsics, given)
    if camera is None:
        raise InputError("a depth image needs --intrinsics (or intrinsics.yaml beside it)", path)
    # As a depth folder's are: a sized camera's principal point and lens checked at its size.
    check_camera(camera, source or path)
    return read_depth_cloud(path, camera)
