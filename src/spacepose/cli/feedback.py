"""What long commands show while they run and say when they end: a transient progress line and
the list of files they wrote."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

from spacepose.cli.app import console, err_console


@contextmanager
def working(label: str) -> Iterator[None]:
    """A spinner, ``label`` and the elapsed time on stderr while the block runs; erased after.

    On stderr so that what the command prints on stdout (JSON included) stays clean; not drawn
    at all when stderr is not a terminal.
    """
    if not err_console.is_terminal:  # rich would still end the (invisible) line with "\n"
        yield
        return
    with Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        TimeElapsedColumn(),
        console=err_console,
        transient=True,
    ) as progress:
        progress.add_task(label, total=None)
        yield


def print_written(folder: Path, since: float, stderr: bool = False) -> list[Path]:
    """List the files under ``folder`` modified at or after ``since`` (a ``time.time()``).

    On stdout, or on stderr when stdout carries something else (``--json``).

    Returns
    -------
    The files listed, sorted by path.
    """
    # File systems store modification times coarser than time.time(): allow two seconds.
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.stat().st_mtime >= since - 2.0)
    out = err_console if stderr else console
    out.print(
        f"wrote {len(files)} file(s) to {folder}/", highlight=False, markup=False, soft_wrap=True
    )
    for path in files:
        size = _size(path.stat().st_size)
        out.print(
            f"  {path.relative_to(folder)}  ({size})", highlight=False, markup=False, soft_wrap=True
        )
    return files


def _size(n_bytes: int) -> str:
    if n_bytes < 1000:
        return f"{n_bytes} B"
    return f"{n_bytes / 1e3:.1f} kB" if n_bytes < 1e6 else f"{n_bytes / 1e6:.1f} MB"
