"""Output files: refuse a location that cannot be written before any work is done.

A run that registers, tracks or navigates for minutes and then fails to write its result loses
the work; so every command that writes checks its outputs first (:func:`check_writable`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path

from spacepose.errors import InputError


def check_writable(*paths: str | Path) -> None:
    """Check that each path can be created or overwritten as a regular file.

    A path must name a file (not an existing folder or an empty name), the nearest existing
    folder above it must be a folder, its own folder must be creatable, and the file must open
    for writing (the file and folders the probe made are removed again). Root passes
    ``os.access`` everywhere, so the file itself is opened: ``/proc`` refuses it there.

    Raises
    ------
    InputError
        One line naming the path and the problem.
    """
    for raw in paths:
        path = Path(raw)
        if not str(raw).strip() or path.name in ("", ".", ".."):
            raise InputError(f"an output needs a file name, got {str(raw)!r}")
        if path.exists() and not path.is_file():
            raise InputError("output exists and is not a regular file (a folder?)", path)
        parent = path.absolute().parent
        existing = parent
        while not existing.exists():
            existing = existing.parent
        if not existing.is_dir():
            raise InputError(f"cannot write under {existing}: it is a regular file", path)
        if not os.access(existing, os.W_OK | os.X_OK):
            raise InputError(f"cannot write under {existing}: permission denied", path)
        existed = path.exists()
        try:
            parent.mkdir(parents=True, exist_ok=True)
            with path.open("a"):
                pass
        except OSError as exc:
            raise InputError(f"cannot write the output: {exc.strerror}", path) from None
        finally:
            # Leave no trace of the probe: the file and the folders made for it.
            if not existed:
                path.unlink(missing_ok=True)
            folder = parent
            while folder != existing and folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
                folder = folder.parent


def check_spares_inputs(outputs: Iterable[str | Path], inputs: Iterable[str | Path]) -> None:
    """Refuse an output that is one of the input files (the same file, through any link).

    An existing output is overwritten: written onto a run's ``groundtruth.tum`` it would
    replace the truth that a later ``evaluate`` compares with, onto a frame it destroys the
    frame before it is read.

    Raises
    ------
    InputError
        One line naming the output and the input it would overwrite.
    """
    sources = [Path(p) for p in inputs]
    for out in map(Path, outputs):
        if not out.is_file():
            continue  # a new file overwrites nothing
        for source in sources:
            if source.is_file() and os.path.samefile(out, source):
                raise InputError(f"would overwrite the input {source}: write it elsewhere", out)


def check_text_name(out: str | Path, writes: str, fix: str) -> None:
    """Refuse a text output named as data spacepose reads: a point cloud, a depth image, a mesh
    or a bag. Written so, the next run over the folder read it as a frame (lost: "not an image
    Pillow can decode") and a viewer refused it.

    Parameters
    ----------
    out
        The output file.
    writes
        What the command writes there ("a TUM trajectory").
    fix
        The name to give it instead ("name it .tum").

    Raises
    ------
    InputError
        One line naming the output, what it holds and what its suffix means.
    """
    # Imported here: the readers check their own outputs through this module.
    from spacepose.core.sim.mesh_files import MESH_SUFFIXES
    from spacepose.tools.bag_io import BAG_SUFFIXES
    from spacepose.tools.cloud_io import BINARY_CLOUD_SUFFIXES, DEPTH_SUFFIXES

    suffix = Path(out).suffix.lower()
    kinds = {
        "a point cloud": BINARY_CLOUD_SUFFIXES,
        "a depth image": (*DEPTH_SUFFIXES, ".jpg", ".jpeg", ".bmp"),
        "a mesh": MESH_SUFFIXES,
        "a bag": BAG_SUFFIXES,
    }
    for kind, suffixes in kinds.items():
        if suffix in suffixes:
            raise InputError(f"{writes} is text, and a {suffix} file is read as {kind}: {fix}", out)


def companion(out: str | Path, own_suffix: str, suffix: str) -> Path:
    """The file beside ``out`` that a command writes with it (``EST.tum`` -> ``EST.health.csv``
    for ``own_suffix`` ``.tum``): ``out``'s name less its own suffix, or its whole name when it
    has another, plus ``suffix``.

    Only the command's own suffix is taken off: taking any made ``est_0.25`` and ``est_0.5``
    share ``est_0.health.csv``, the second run's table replacing the first's.
    """
    out = Path(out)
    stem = out.name[: -len(own_suffix)] if out.suffix.lower() == own_suffix else out.name
    return out.with_name(stem + suffix)


def check_not_anothers(
    out: str | Path,
    own_suffix: str,
    marker: str,
    owner: str,
    is_theirs: Callable[[Path], bool] = Path.is_file,
) -> None:
    """Refuse ``out`` when its companions would replace another command's: a file ``marker``
    beside ``out``'s stem that ``is_theirs`` (``owner``'s alone: track's ``.cov.csv``,
    navigate's table) says the shared companions (``.config.json``, ``.health.csv``) are that
    command's. ``run.tum`` tracked and ``run.csv`` navigated shared ``run.config.json`` and
    ``run.health.csv`` without a word, and ``evaluate run.tum`` read the navigation's health
    table.

    Raises
    ------
    InputError
        One line naming the output and the other command's file.
    """
    found = companion(out, own_suffix, marker)
    if found.is_file() and is_theirs(found):
        raise InputError(
            f"its .config.json and .health.csv would replace those of {found.name} beside it "
            f"({owner}'s): name the output otherwise",
            out,
        )
