"""Command line: each sub-command lives in its own module and only parses and calls."""

import sys

from spacepose.cli import (  # noqa: F401  (importing a module registers its command)
    bench,
    campaign,
    demo,
    evaluate,
    experiment,
    navigate,
    planes,
    register,
    report,
    simulate,
    track,
    version,
)
from spacepose.cli.app import app, main

__all__ = ["app", "main", "run"]


def run() -> None:
    """Console-script entry point."""
    sys.exit(main())
