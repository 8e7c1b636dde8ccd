"""OpenEXR depth maps, as renderers (Blender's depth pass, game engines) write them, through the
``OpenEXR`` bindings.

A depth EXR holds float (16- or 32-bit) depths in one channel: the only channel, or the one
channel named as depth (``Z``, ``depth``, ``distance``; after a layer's name, as Blender's
multilayer files spell ``ViewLayer.Depth.Z``), or three equal ``R``, ``G``, ``B`` channels (a
depth saved as a grey image). Any other set of channels is refused with its names, so that a
colour image is never read as depths.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from spacepose.errors import FileFormatError

EXR_SUFFIX = ".exr"
# Channel names (the last part, case-insensitive) that hold depth.
_DEPTH_NAMES = ("z", "depth", "distance")


def read_exr_depth(path: Path) -> NDArray[np.float32]:
    """The (H, W) float32 depth channel of an OpenEXR file (module docstring).

    Raises
    ------
    FileFormatError
        Not an EXR the library opens, or no channel that is depth alone.
    """
    import OpenEXR

    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = {name: part.pixels for name, part in exr.channels().items()}
    except RuntimeError as exc:  # the library's one error for a missing or corrupt file
        problem = "file not found" if not path.exists() else f"cannot decode the image: {exc}"
        raise FileFormatError(" ".join(problem.split()), path) from None
    name = _depth_channel(channels, path)
    values = np.asarray(channels[name])
    if values.ndim != 2 or values.dtype.kind != "f":
        raise FileFormatError(
            f"channel {name!r} holds {values.dtype} of shape {values.shape}, not float depths",
            path,
        )
    return values.astype(np.float32, copy=False)


def _depth_channel(channels: dict[str, NDArray], path: Path) -> str:
    """The name of the channel that holds the depths."""
    if len(channels) == 1:
        return next(iter(channels))
    named = [n for n in channels if n.rsplit(".", 1)[-1].lower() in _DEPTH_NAMES]
    if len(named) == 1:
        return named[0]
    grey = [n for n in ("R", "G", "B") if n in channels]
    if len(grey) == 3 and set(channels) <= {"R", "G", "B", "A"}:
        if all(np.array_equal(channels["R"], channels[n], equal_nan=True) for n in "GB"):
            return "R"
    raise FileFormatError(
        f"channels {', '.join(sorted(channels))}: none is depth alone (one channel, one named "
        "Z or depth, or equal R, G, B)",
        path,
    )


def exr_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an EXR from its header, None if it does not open."""
    import OpenEXR

    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            (x0, y0), (x1, y1) = exr.header()["dataWindow"]
    except (RuntimeError, KeyError, TypeError, ValueError):
        return None
    return int(x1 - x0 + 1), int(y1 - y0 + 1)


def write_exr_depth(path: Path, values: NDArray) -> None:
    """Write (H, W) depths as one float32 channel ``Z`` (ZIP-compressed scanlines)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Z": np.ascontiguousarray(values, dtype=np.float32)}) as exr:
        exr.write(str(path))
