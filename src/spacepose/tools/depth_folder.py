"""Depth image folders: one depth image per frame (:mod:`spacepose.tools.depth_io`) and an
intrinsics file (:mod:`spacepose.tools.intrinsics_io`), or one given explicitly.

Frames are the images sorted by name, with ``timestamps.txt`` when present, or, in TUM RGB-D's
layout, the ``timestamp path`` lines of ``depth.txt`` (``#`` comments ignored; the paths
relative to the folder).
"""

from __future__ import annotations

import os
import re
from collections import Counter
from decimal import Decimal
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from spacepose.core.depth import DepthCamera
from spacepose.errors import ConfigError, InputError, SpaceposeError
from spacepose.tools.cloud_io import DEPTH_SUFFIXES
from spacepose.tools.depth_io import image_size, read_depth_image
from spacepose.tools.intrinsics_io import find_intrinsics, read_intrinsics
from spacepose.tools.npy_io import npy_shape
from spacepose.tools.text_io import check_timing, data_number, read_text

# A depth folder's frames may also be NumPy arrays; elsewhere a ``.npy`` is a point cloud.
FOLDER_DEPTH_SUFFIXES: tuple[str, ...] = (*DEPTH_SUFFIXES, ".npy")
# Suffixes of one format: a folder's images are all of one.
_FORMATS = {".tif": ".tiff"}
TUM_DEPTH_LIST = "depth.txt"
# Metres per stored unit of TUM RGB-D's 16-bit depth images (5000 per metre).
TUM_DEPTH_SCALE = 0.0002


def folder_camera(
    root: Path, intrinsics: str | Path | None, camera: DepthCamera | None
) -> tuple[DepthCamera | None, Path | None]:
    """The camera of a depth folder (or of a depth image's folder) and its file: ``camera``
    read from the ``intrinsics`` given, else the folder's own intrinsics file (None, None
    without either). Every reader of depth images takes its camera here, so a given file and
    the folder's own are weighed alike (a depth folder's frames, ``register``'s images).

    Raises
    ------
    InputError
        Both are there and differ: the given file won without a word, the folder's own
        calibration (the one recorded with its images) ignored. As for two intrinsics files
        in one folder, the user keeps one.
    ConfigError
        An intrinsics file is invalid.
    """
    given = None if intrinsics is None else Path(intrinsics)
    found = find_intrinsics(root)
    if found is None:
        return camera, given
    try:
        own = read_intrinsics(found)
    except ConfigError as exc:
        if camera is None:
            raise
        # The user gave intrinsics, perhaps for this very reason: say why theirs are refused.
        raise InputError(
            f"--intrinsics {intrinsics} is given beside the folder's {found.name}, which "
            f"cannot be read ({exc}): keep one",
            root,
        ) from None
    if camera is None:
        return own, found
    differ = [
        f"{name} {getattr(camera, name)} vs {getattr(own, name)}"
        for name in type(own).model_fields
        if getattr(camera, name) != getattr(own, name)
    ]
    if differ:
        raise InputError(
            f"--intrinsics {intrinsics} and the folder's {found.name} differ "
            f"({', '.join(differ[:3])}{', ...' if len(differ) > 3 else ''}): keep one "
            f"(move {found.name} out, or leave out --intrinsics)",
            root,
        )
    return camera, given


def is_depth_folder(root: str | Path) -> bool:
    """Whether a folder is read as depth images: it holds ``depth.txt`` or an intrinsics file."""
    return (Path(root) / TUM_DEPTH_LIST).is_file() or find_intrinsics(root) is not None


# A number in a frame's name: digits, and a fraction after a dot between digits (TUM times).
_NUMBER = re.compile(r"(\d+(?:\.\d+)?)")


def _name_order(path: Path) -> tuple[tuple[str | Decimal, ...], str]:
    """Sort key of a frame's name: the numbers of its stem (the name less its suffix) by value,
    a number being digits with, after a dot that follows a digit, a fraction (``frame5``
    before ``frame10``, ``1.25`` before ``1.5``, ``0`` before ``0.5``, ``scan.2`` before
    ``scan.10``); the same order as the names' where the numbers are zero-padded. Names of
    equal value (``frame1``, ``frame01``) follow as text, so the order never rests on the
    folder's."""
    stem = path.name[: len(path.name) - len(path.suffix)]
    chunks: list[str | Decimal] = _NUMBER.split(stem)
    # Text and numbers alternate, so a position always compares like with like.
    for i in range(1, len(chunks), 2):
        chunks[i] = Decimal(chunks[i])
    return tuple(chunks), path.name


def frame_entries(root: Path, suffixes: tuple[str, ...]) -> tuple[Path, ...]:
    """A folder's entries named as frames (a suffix of ``suffixes``, any case), sorted by name
    with its numbers by value (:func:`_name_order`).

    Not only regular files: a folder or a broken link named as a frame is a frame that cannot
    be read (reported lost), not one to skip and shift the rest. Hidden entries (a leading
    dot: macOS's ``._000000.ply`` resource forks, editors' swap files) are not frames.

    Raises
    ------
    InputError
        Two entries share a name but for the suffix.
    """
    entries = tuple(
        sorted(
            (
                p
                for p in root.iterdir()
                if p.suffix.lower() in suffixes and not p.name.startswith(".")
            ),
            key=_name_order,
        )
    )
    # Two files of one frame name (000001.ply and 000001.npy) would both be tracked, and every
    # later frame numbered, and timed, one too far.
    seen: dict[str, Path] = {}
    for p in entries:
        if p.stem in seen:
            raise InputError(
                f"{seen[p.stem].name} and {p.name} are one frame name twice: keep one", root
            )
        seen[p.stem] = p
    return entries


def depth_files(root: str | Path) -> tuple[Path, ...]:
    """The depth images of a folder, sorted by name.

    Raises
    ------
    InputError
        The folder holds no image with a suffix of :data:`FOLDER_DEPTH_SUFFIXES`, images of
        more than one format, or its first ``.npy`` is an (N, 3) or (N, 6) point array.
    """
    root = Path(root)
    paths = frame_entries(root, FOLDER_DEPTH_SUFFIXES)
    if not paths:
        raise InputError(
            f"no depth images ({', '.join(FOLDER_DEPTH_SUFFIXES)}) in the folder", root
        )
    formats = Counter(_FORMATS.get(p.suffix.lower(), p.suffix.lower()) for p in paths)
    if len(formats) > 1:
        # One depth_scale reads every image: a renderer's EXR in metres beside 16-bit PNGs in
        # millimetres came out a thousand times too near, frame for frame.
        listed = ", ".join(f"{n} {suffix}" for suffix, n in formats.most_common())
        raise InputError(
            f"the folder mixes depth formats ({listed}), which one camera's depth_scale cannot "
            "all read: keep the frames of one format",
            root,
        )
    arrays = [p for p in paths if p.suffix.lower() == ".npy"]
    shape = npy_shape(arrays[0]) if arrays else None
    if shape is not None and len(shape) == 2 and shape[1] in (3, 6):
        # No depth map is 3 or 6 pixels wide: these are point clouds, given intrinsics.
        raise InputError(
            f"{arrays[0].name} holds points, an {shape} array, not a depth map: a folder of "
            "point clouds needs no intrinsics",
            root,
        )
    return paths


def read_tum_depth_list(path: str | Path) -> tuple[tuple[Path, ...], NDArray[np.float64]]:
    """Read TUM RGB-D's ``depth.txt``: ``timestamp relative/path.png`` per line.

    Returns
    -------
    paths, timestamps
        The image paths (relative to the list's folder) and their (N,) times, seconds.

    Raises
    ------
    InputError
        Unreadable list, a line that is not ``number path``, an image outside the list's
        folder or listed twice, a non-finite or decreasing time,
        times that are not seconds (:func:`~spacepose.tools.text_io.check_timing`), or no
        line at all.
    """
    path = Path(path)
    text = read_text(path, "the depth list")
    paths: list[Path] = []
    stamps: list[float] = []
    listed: dict[Path, int] = {}  # each image's line
    for lineno, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        parts = body.split(maxsplit=1)
        try:
            stamp = data_number(parts[0])
        except ValueError:
            stamp = float("nan")
        if len(parts) != 2 or not np.isfinite(stamp):
            raise InputError(f"line {lineno}: expected 'timestamp path', got {body!r}", path)
        inside = os.path.relpath(os.path.normpath(path.parent / parts[1]), path.parent)
        if inside.split(os.sep)[0] == os.pardir:
            # An image of another folder (another sequence's) was read as one of this one.
            raise InputError(
                f"line {lineno}: {parts[1]} lies outside the list's folder: a depth list "
                "names the images of its own sequence",
                path,
            )
        image = path.parent / parts[1]
        if image in listed:
            # One image tracked as two frames: a line pasted twice, or the wrong file named.
            raise InputError(
                f"line {lineno}: {parts[1]} is listed again (line {listed[image]}): one image is "
                "one frame",
                path,
            )
        listed[image] = lineno
        stamps.append(stamp)
        paths.append(image)
    if not paths:
        raise InputError("lists no depth image", path)
    timestamps = np.asarray(stamps, dtype=np.float64)
    check_timing(timestamps, path)
    return tuple(paths), timestamps


def integer_depths(paths: tuple[Path, ...]) -> bool:
    """Whether a folder's depth images (one format: :func:`depth_files`) hold integers, by the
    first that can be read (True when none can: each frame's own error says why). TUM RGB-D's
    5000 units per metre are a 16-bit image's unit, not a float image's."""
    for path in paths:
        try:
            return bool(np.issubdtype(read_depth_image(path).dtype, np.integer))
        except SpaceposeError:
            continue
    return True


def unlisted_images(paths: tuple[Path, ...]) -> list[Path]:
    """Depth images in the folders of a list's ``paths`` that the list leaves out (sorted): TUM
    RGB-D's ``depth.txt`` names every image of ``depth/``, and one left out was skipped
    without a word."""
    listed = {p.resolve() for p in paths}
    folders = {p.parent for p in paths if p.parent.is_dir()}
    return sorted(
        p
        for folder in folders
        for p in folder.iterdir()
        if p.suffix.lower() in FOLDER_DEPTH_SUFFIXES and p.is_file() and p.resolve() not in listed
    )


def sized_camera(camera: DepthCamera, paths: tuple[Path, ...], source: Path | None) -> DepthCamera:
    """``camera`` with the sequence's image size where its intrinsics give none: the size most
    of its images have (read from their headers). One camera makes every frame, and an image
    of another size (a frame of another stream) would be back-projected with the wrong
    principal point without a word.

    Raises
    ------
    ConfigError
        The intrinsics (``source``) give a size no image has: every frame was lost, each
        blamed on its image (width 1e26 as well), not on the intrinsics.
    """
    sizes = Counter(size for size in map(image_size, paths) if size is not None)
    if not sizes:
        return camera  # each frame's own error is reported when it is read
    (width, height), _ = sizes.most_common(1)[0]
    given = (camera.width, camera.height)
    if None not in given and given not in sizes:
        where = "the intrinsics" if source is None else source
        raise ConfigError(
            f"{where}: width {camera.width} and height {camera.height} are the size of no "
            f"image of the folder ({len(paths)} images, most {width}x{height}): intrinsics of "
            "another camera or resolution?"
        )
    size = {"width": width, "height": height}
    return camera.model_copy(update={k: v for k, v in size.items() if getattr(camera, k) is None})
