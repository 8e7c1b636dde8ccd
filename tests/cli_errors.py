"""What the bad-input tests check of a command that refused its input."""

from __future__ import annotations

import pytest


def error_line(capsys: pytest.CaptureFixture[str]) -> str:
    """The command's stderr, checked to be one ``error:`` line: no traceback, no warning."""
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith("error: "), err
    return err
