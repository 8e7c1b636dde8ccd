"""Bad inputs found by a third hostile round: each ends in one line naming the file and the
problem (or a warning naming it), never a traceback, a hang or a silently wrong result."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from spacepose.cli import main
from spacepose.errors import FileFormatError
from spacepose.tools.runs import read_run

# /proc/self/mem is a regular file whose first page no read can reach (EIO), even for root, as
# a file without read permission is for anyone else.
_UNREADABLE = Path("/proc/self/mem")
needs_proc = pytest.mark.skipif(not _UNREADABLE.is_file(), reason="needs Linux's /proc")


def _cli_error(capsys) -> str:
    """The CLI's stderr, checked to be one ``error:`` line without a traceback."""
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    assert err.startswith("error:"), err
    return err


def _orbit_run(root: Path) -> Path:
    """The smallest orbit run folder that :func:`read_run` reads up to its truth.csv."""
    (root / "frames").mkdir(parents=True)
    (root / "frames" / "000000.ply").write_bytes(b"")
    (root / "scenario.json").write_text(json.dumps({"scenario": "orbit"}))
    (root / "groundtruth.tum").write_text("0 0 0 0 0 0 0 1\n")
    (root / "model.ply").write_bytes(b"")
    (root / "model.obj").write_bytes(b"")
    (root / "truth.csv").write_text("")
    return root


# -- a run's own files that the system refuses to read ----------------------------------------


@needs_proc
@pytest.mark.parametrize("name", ["scenario.json", "truth.csv"])
def test_a_run_file_the_system_refuses_is_named(tmp_path, capsys, name):
    """read_run read scenario.json and truth.csv with Path.read_text: an OSError of the read
    ended as 'error: Input/output error', naming no file."""
    run = _orbit_run(tmp_path / "run")
    (run / name).unlink()
    (run / name).symlink_to(_UNREADABLE)
    with pytest.raises(FileFormatError) as exc:
        read_run(run)
    assert str(run / name) in str(exc.value) and "Input/output error" in str(exc.value)
    assert main(["navigate", str(run), "--out", str(tmp_path / "nav.csv")]) == 1
    err = _cli_error(capsys)
    assert str(run / name) in err and "cannot read" in err


# -- trajectories -----------------------------------------------------------------------------


def test_two_truth_poses_at_one_time_name_the_time_as_a_number(tmp_path, capsys):
    """The time was printed as numpy's repr: 't = np.float64(2.0)'."""
    est, gt = tmp_path / "est.tum", tmp_path / "gt.tum"
    est.write_text("".join(f"{k} 0 0 1 0 0 0 1\n" for k in range(4)))
    gt.write_text(est.read_text() + "2 0.5 0 1 0 0 0 1\n")
    assert main(["evaluate", str(est), str(gt)]) == 1
    err = _cli_error(capsys)
    assert str(gt) in err and "two ground-truth poses at t = 2.0:" in err
    assert "np." not in err
