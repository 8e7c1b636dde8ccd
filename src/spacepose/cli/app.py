"""The typer application object and the one error handler of the command line."""

from __future__ import annotations

import sys

import typer
from rich.console import Console

from spacepose.errors import SpaceposeError

app = typer.Typer(
    name="spacepose",
    help="Pose and tumbling motion of non-cooperative space targets from 3D point clouds.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)


@app.callback()
def _root() -> None:
    """Pose and tumbling-motion estimation of non-cooperative space targets from 3D point clouds."""


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; a :class:`SpaceposeError` becomes one line on stderr and exit code 1.

    Parameters
    ----------
    argv
        Arguments without the program name; ``sys.argv[1:]`` when omitted.
    """
    try:
        result = app(args=argv, prog_name="spacepose", standalone_mode=False)
    except SpaceposeError as exc:
        # The message goes out as plain text: file names and "spacepose[peers]" hold brackets
        # that rich would read as markup.
        err_console.print("[bold red]error:[/] ", end="")
        err_console.print(str(exc), markup=False, highlight=False, soft_wrap=True)
        return 1
    except typer.Abort:
        err_console.print("aborted")
        return 130
    except typer.Exit as exc:
        return exc.exit_code
    except typer.TyperException as exc:  # usage errors: unknown option, missing argument
        exc.show(file=sys.stderr)
        return getattr(exc, "exit_code", 2)
    return result if isinstance(result, int) else 0
