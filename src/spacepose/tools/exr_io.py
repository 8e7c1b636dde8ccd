"""OpenEXR depth maps, as renderers (Blender's depth pass, game engines) write them, through the
``OpenEXR`` bindings.

A depth EXR holds float (16- or 32-bit) depths in one channel: the only channel, or the one
channel named as depth (``Z``, ``depth``, ``distance``; after a layer's name, as Blender's
multilayer files spell ``ViewLayer.Depth.Z``, or in any part of a multi-part file), or three
equal ``R``, ``G``, ``B`` channels (a depth saved as a grey image). Any other set of channels is
refused with its names, so that a colour image is never read as depths. What the library prints
of a damaged file is held back and quoted in the error (or the warning) naming it.
"""

from __future__ import annotations

import io
import os
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from spacepose.errors import FileFormatError, SpaceposeWarning

EXR_SUFFIX = ".exr"
# Most pixels of a display window an image is placed in (a 4K frame holds 8.3 million).
_LARGEST_IMAGE = 1 << 26
# Channel names (the last part, case-insensitive) that hold depth.
_DEPTH_NAMES = ("z", "depth", "distance")


def read_exr_depth(path: Path, kind_given: bool = False) -> NDArray[np.float32]:
    """The (H, W) float32 depth channel of an OpenEXR file (module docstring). ``kind_given``:
    the intrinsics say which depth the map holds (``depth_kind``), so a channel named
    ``distance`` is not warned of.

    Raises
    ------
    FileFormatError
        Not an EXR the library opens (a truncated file: the library's own account of it), or
        no channel that is depth alone.

    Warns
    -----
    SpaceposeWarning
        The library warned while decoding it (its message, once); or the depth channel is
        named ``distance`` and the intrinsics do not say which depth it is: read as depth
        along the boresight, a render's distances along the rays tracked 0.7-1.1° off.
    """
    if not path.exists():
        raise FileFormatError("file not found", path)
    with _quiet() as said:
        try:
            channels = _channels(path)
        except Exception as exc:  # RuntimeError, or a cut file's ValueError ("0 parts")
            problem = " ".join(str(exc).split())
            error = FileFormatError(f"cannot decode the image: {problem}", path)
        else:
            error = None
    library = said().removeprefix(f"{path}: ")
    if error is not None:
        # The library's own account of a truncated file says more than its exception.
        raise FileFormatError(f"{error.reason} ({library})", path) if library else error
    if not channels:  # a file cut after its header opens with no part
        reason = "cannot decode the image: it holds no channel (a truncated file?)"
        raise FileFormatError(f"{reason} ({library})" if library else reason, path)
    if library:
        warnings.warn(
            SpaceposeWarning(f"decoded despite OpenEXR's warning: {library}", path), stacklevel=3
        )
    name = _depth_channel(channels, path)
    if name.rsplit(".", 1)[-1].lower() == "distance" and not kind_given:
        problem = (
            f"channel {name!r} is read as depth along the boresight: if it holds the distance "
            "along each pixel's ray, set depth_kind: range in the intrinsics (depth_kind: z "
            "says it does not)"
        )
        warnings.warn(SpaceposeWarning(problem, path), stacklevel=4)
    values = np.asarray(channels[name])
    if values.ndim != 2 or values.dtype.kind != "f":
        raise FileFormatError(
            f"channel {name!r} holds {values.dtype} of shape {values.shape}, not float depths",
            path,
        )
    return values.astype(np.float32, copy=False)


def _channels(path: Path) -> dict[str, NDArray]:
    """Every channel of every part, named ``part.channel`` when the file has several parts (a
    render's beauty and depth passes): the first part alone held no depth in such a file, and
    its luminance was tracked as depths."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as exr:
        parts = exr.parts
        if len(parts) == 1:
            header = parts[0].header
            return {
                name: _on_display(channel.pixels, header)
                for name, channel in parts[0].channels.items()
            }
        return {
            f"{part.name()}.{name}": _on_display(channel.pixels, part.header)
            for part in parts
            for name, channel in part.channels.items()
        }


def _on_display(pixels: NDArray, header: dict) -> NDArray:
    """A channel's pixels where they lie in the image: a render of a region (its data window
    inside the display window) placed at the data window's origin, the rest no return (0).
    Read as the whole image, a crop of a 640×480 render was 440×380 ("the intrinsics say
    640x480"), or, without a size, every ray was off by the window's origin."""
    data, display = header.get("dataWindow"), header.get("displayWindow")
    if data is None or display is None or pixels.ndim != 2:
        return pixels
    (x0, y0), (dx0, dy0), (dx1, dy1) = data[0], display[0], display[1]
    if (x0, y0, *pixels.shape[::-1]) == (dx0, dy0, dx1 - dx0 + 1, dy1 - dy0 + 1):
        return pixels
    width, height = int(dx1 - dx0 + 1), int(dy1 - dy0 + 1)
    if width <= 0 or height <= 0 or width * height > _LARGEST_IMAGE:
        # A header's display window is only numbers: 10⁵ x 10⁵ would be 40 GB of zeros.
        raise ValueError(
            f"its display window is {width}x{height} pixels, no depth camera's image "
            f"(at most {_LARGEST_IMAGE:,} pixels read)"
        )
    image = np.zeros((height, width), dtype=pixels.dtype)
    # The overlap of the two windows, in the display image's pixels and in the data's.
    top, left = max(int(y0 - dy0), 0), max(int(x0 - dx0), 0)
    row, col = top - int(y0 - dy0), left - int(x0 - dx0)
    rows = min(image.shape[0] - top, pixels.shape[0] - row)
    cols = min(image.shape[1] - left, pixels.shape[1] - col)
    if rows > 0 and cols > 0:
        image[top : top + rows, left : left + cols] = pixels[row : row + rows, col : col + cols]
    return image


@contextmanager
def _quiet() -> Iterator[Callable[[], str]]:
    """The library prints its warnings and errors, from C++ to the process's stdout and stderr
    and from its bindings to Python's (seven lines for a truncated file): held back while it
    reads, and handed to the caller (the first line) through the function yielded."""
    held: list[str] = []
    saved = [os.dup(1), os.dup(2)]
    printed = io.StringIO()
    with tempfile.TemporaryFile() as sink:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
            for fd in (1, 2):
                os.dup2(sink.fileno(), fd)
            with redirect_stdout(printed), redirect_stderr(printed):
                yield lambda: held[0] if held else ""
        finally:
            for fd, copy in zip((1, 2), saved, strict=True):
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            text = sink.read().decode(errors="replace") + printed.getvalue()
            held.extend(line.strip() for line in text.splitlines() if line.strip())


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
        "Z, depth or distance, or equal R, G, B)",
        path,
    )


def exr_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an EXR's image (its display window) from its header, None if it
    does not open."""
    import OpenEXR

    try:
        with _quiet(), OpenEXR.File(str(path), header_only=True) as exr:
            header = exr.header()
            (x0, y0), (x1, y1) = header.get("displayWindow", header["dataWindow"])
    except (RuntimeError, KeyError, TypeError, ValueError):  # the frame's own read says why
        return None
    return int(x1 - x0 + 1), int(y1 - y0 + 1)


def write_exr_depth(path: Path, values: NDArray) -> None:
    """Write (H, W) depths as one float32 channel ``Z`` (ZIP-compressed scanlines)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Z": np.ascontiguousarray(values, dtype=np.float32)}) as exr:
        exr.write(str(path))
