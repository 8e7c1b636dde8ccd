"""``spacepose experiment``: ends with where it wrote what; progress while long commands run."""

from __future__ import annotations

import io
import json
import time
from pathlib import Path

import pytest
from rich.console import Console

from spacepose.cli import feedback, main
from spacepose.tools import experiments

TABLE = {"rows": [{"method": m, "x_mm": 0.1 * i} for i, m in enumerate(["icp", "gicp", "jicp"])]}


@pytest.fixture
def fake_experiment(monkeypatch: pytest.MonkeyPatch):
    """A stand-in experiment that writes a table and a figure, as the real ones do."""

    def run(name: str, out_dir: Path, options: experiments.ExperimentOptions) -> dict:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "table.json").write_text(json.dumps(TABLE, indent=2))
        (out_dir / "errors.png").write_bytes(b"\x89PNG" + bytes(2000))
        return TABLE

    monkeypatch.setattr(experiments, "run_experiment", run)


def test_experiment_ends_with_the_files_it_wrote_not_its_json(
    tmp_path: Path, fake_experiment, capsys: pytest.CaptureFixture[str]
) -> None:
    stale = tmp_path / "li-l3" / "old.png"
    stale.parent.mkdir()
    stale.write_bytes(b"old")
    old = time.time() - 3600
    __import__("os").utime(stale, (old, old))
    assert main(["experiment", "li-l3", "--out", str(tmp_path)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert out.splitlines() == [
        f"wrote 2 file(s) to {tmp_path / 'li-l3'}/",
        "  errors.png  (2.0 kB)",
        f"  table.json  ({(tmp_path / 'li-l3' / 'table.json').stat().st_size} B)",
    ]


def test_experiment_json_goes_to_stdout_alone(
    tmp_path: Path, fake_experiment, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["experiment", "li-l3", "--out", str(tmp_path), "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == TABLE
    assert err.startswith(f"wrote 2 file(s) to {tmp_path / 'li-l3'}/")


def test_working_draws_a_transient_line_only_on_a_terminal(monkeypatch) -> None:
    screen = io.StringIO()
    monkeypatch.setattr(feedback, "err_console", Console(file=screen, force_terminal=True))
    with feedback.working("navigating"):
        time.sleep(0.2)
    drawn = screen.getvalue()
    assert "navigating" in drawn and "0:00:00" in drawn
    # Transient: the last thing written moves the cursor back up and clears the line.
    assert drawn.endswith("\x1b[2K") or "\x1b[2K" in drawn[-40:]
    piped = io.StringIO()
    monkeypatch.setattr(feedback, "err_console", Console(file=piped, force_terminal=False))
    with feedback.working("navigating"):
        pass
    assert piped.getvalue() == ""
