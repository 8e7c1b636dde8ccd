"""Output files: refuse a location that cannot be written before any work is done.

A run that registers, tracks or navigates for minutes and then fails to write its result loses
the work; so every command that writes checks its outputs first (:func:`check_writable`).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
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
