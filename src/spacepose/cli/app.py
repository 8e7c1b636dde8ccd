"""The typer application object, the one error handler and the warning printer of the CLI.

Every error ends as one line on stderr and exit code 1: a :class:`SpaceposeError` (bad input,
bad config), a file the system refuses (OSError) and a usage error alike (an unknown option or
command, a missing argument, a value that does not parse), as the README promises. A
:class:`SpaceposeWarning` is one line ``warning: FILE: problem``, and so is any other warning;
past the first few files with the same problem (every frame of a
folder in millimetres) the others are only counted, and the count printed at the end.
"""

from __future__ import annotations

import sys
import warnings
from collections import Counter

import typer
from rich.console import Console
from typer._click.exceptions import NoArgsIsHelpError, UsageError

from spacepose.errors import Interrupted, SpaceposeError, SpaceposeWarning

app = typer.Typer(
    name="spacepose",
    help="Pose and tumbling motion of non-cooperative space targets from 3D point clouds.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
# Plain text, no markup: what the commands print holds file names, and a name with brackets
# ("run [2]", "[/]") lost them on the way ("-> run .tum") or ended a finished run in rich's
# MarkupError traceback.
console = Console(markup=False)
err_console = Console(stderr=True)


@app.callback()
def _root() -> None:
    """Pose and tumbling-motion estimation of non-cooperative space targets from 3D point clouds."""


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; errors become one line on stderr and exit code 1.

    Parameters
    ----------
    argv
        Arguments without the program name; ``sys.argv[1:]`` when omitted.

    Returns
    -------
    The exit code: 0, 1 for any error in the input or on the command line, 130 when aborted.
    A bare ``spacepose`` prints the help (exit code 2, as before).
    """
    with warnings.catch_warnings(), _OneLineWarnings() as shown:
        warnings.simplefilter("always", SpaceposeWarning)
        warnings.showwarning = shown.show
        try:
            result = app(args=argv, prog_name="spacepose", standalone_mode=False)
        except Interrupted as exc:  # Ctrl-C that a command caught to close its outputs
            _fail(shown, str(exc))
            return 130
        except SpaceposeError as exc:
            return _fail(shown, str(exc))
        except typer.Abort:
            err_console.print("aborted")
            return 130
        except typer.Exit as exc:
            return exc.exit_code
        except NoArgsIsHelpError as exc:
            exc.show(file=sys.stderr)
            return exc.exit_code
        except UsageError as exc:  # unknown option or command, missing argument, bad value
            command = exc.ctx.command_path if exc.ctx is not None else "spacepose"
            return _fail(shown, f"{command}: {exc.format_message()} (see '{command} --help')")
        except typer.TyperException as exc:  # any other click error (e.g. an unreadable file)
            return _fail(shown, exc.format_message())
        except OSError as exc:  # a file the system refused (disk full, a read-only mount)
            where = f"{exc.filename}: " if exc.filename else ""
            return _fail(shown, f"{where}{exc.strerror or exc}")
    return result if isinstance(result, int) else 0


def _fail(shown: _OneLineWarnings, message: str) -> int:
    """Exit code 1 after the warnings' counts and the error line, the error last."""
    shown.flush()
    print_error(message)
    return 1


def print_error(message: str) -> None:
    """``error: message`` as one line on stderr (a multi-line message is joined)."""
    # Plain text: file names and "spacepose[peers]" hold brackets rich would read as markup.
    err_console.print("[bold red]error:[/] ", end="")
    err_console.print(_one_line(message), markup=False, highlight=False, soft_wrap=True)


def _print_warning(text: str) -> None:
    """``warning: text`` as one line on stderr (plain text, as :func:`print_error`)."""
    err_console.print("[yellow]warning:[/] ", end="")
    err_console.print(text, markup=False, highlight=False, soft_wrap=True)


def _one_line(message: str) -> str:
    text = " ".join(part.strip() for part in str(message).splitlines() if part.strip())
    # A file name that is not UTF-8 holds surrogates no terminal encodes: its bytes escaped.
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


class _OneLineWarnings:
    """Print each :class:`SpaceposeWarning` as one line, a repeated problem ``shown`` times."""

    shown = 3

    def __init__(self) -> None:
        self.repeats: Counter[tuple[type, str]] = Counter()
        # Each message once: a run folder opened three times by one command warned three times.
        self.said: set[str] = set()

    def __enter__(self) -> _OneLineWarnings:
        return self

    def show(self, message, category, filename, lineno, file=None, line=None) -> None:
        if not isinstance(message, SpaceposeWarning):
            # A library's warning (numpy on overflowing values): one line too, without the
            # source line Python's printer adds.
            _print_warning(f"{category.__name__}: {_one_line(str(message))}")
            return
        text = _one_line(str(message))
        if text in self.said:
            return
        self.said.add(text)
        key = (category, _problem(message.reason))
        self.repeats[key] += 1
        if self.repeats[key] <= self.shown:
            _print_warning(text)

    def flush(self) -> None:
        """Print how many more warnings each repeated problem had, once."""
        for (_, what), count in self.repeats.items():
            if count > self.shown:
                _print_warning(f"{count - self.shown} more with the same warning: {what}")
        self.repeats.clear()

    def __exit__(self, *exc_info: object) -> None:
        self.flush()


def _problem(reason: str) -> str:
    """A warning's problem without its figures: each file in millimetres says its own extent
    and spacing in brackets, and is still the same problem."""
    return reason.split("(")[0].split(";")[0].strip()
