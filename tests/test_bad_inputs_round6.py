"""Bad inputs found by a sixth hostile round: each ends in one line naming the file and the
problem, never a traceback, a hang, lost output or a silently wrong result."""

from __future__ import annotations

import pytest

from spacepose.cli import main
from test_bad_inputs_round4 import _cli_error

# -- simulate: --no-turntable without --background ------------------------------------------------


@pytest.mark.parametrize("scenario", ["lab", "orbit"])
def test_no_turntable_without_background_is_refused(tmp_path, capsys, scenario):
    """The turntable belongs to --background's scene: without it --no-turntable was ignored
    (exit 0, the scene the user meant to change left as it was)."""
    out = tmp_path / "run"
    assert main(["simulate", scenario, "--frames", "2", "--no-turntable", "--out", str(out)]) == 1
    assert _cli_error(capsys) == (
        "error: --no-turntable leaves the turntable out of --background's scene, and "
        "--background is not given: add --background (a wall alone), or leave out --no-turntable"
    )
    assert not out.exists()
