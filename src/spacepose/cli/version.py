"""``spacepose version``."""

from spacepose.cli.app import app, console


@app.command()
def version() -> None:
    """Print the package version."""
    from spacepose import __version__

    console.print(__version__)
