"""Seventeenth hostile round, outputs: companion files that belonged to another output, and a
run folder rewritten under its earlier results."""

from __future__ import annotations

import csv

import pytest

from spacepose.cli import main
from spacepose.core.sim.scenarios import LabConfig, OrbitConfig, simulate_lab, simulate_orbit
from spacepose.errors import SpaceposeWarning
from spacepose.tools import navigation_io, tracking_io
from spacepose.tools.runs import write_run


def test_companions_keep_the_whole_name_unless_it_ends_in_the_commands_own_suffix():
    """`track --out est_0.25` and `--out est_0.5` both wrote est_0.health.csv (the last suffix
    was taken off whatever it was), and `evaluate est_0.25` read the second run's table: 5 of
    its `ok` frames were left out as lost. Only .tum (track) and .csv (navigate) are taken
    off now."""
    assert tracking_io.output_paths("w/est.tum")[1].name == "est.health.csv"
    assert tracking_io.output_paths("w/est.TUM")[4].name == "est.cov.csv"
    names = {tracking_io.output_paths(f"w/est_{v}")[1].name for v in ("0.25", "0.5")}
    assert names == {"est_0.25.health.csv", "est_0.5.health.csv"}
    assert tracking_io.output_paths("est.txt")[2].name == "est.txt.config.json"
    assert navigation_io.output_paths("nav.csv")[1].name == "nav.config.json"
    both = navigation_io.output_paths("nav_0.5", "both")
    assert [p.name for p in both] == [
        "nav_0.5",
        "nav_0.5.config.json",
        "nav_0.5.candidates.csv",
        "nav_0.5.health.csv",
        "nav_0.5.pose_noise.json",
    ]


@pytest.fixture(scope="module")
def orbit_run(tmp_path_factory):
    return write_run(
        tmp_path_factory.mktemp("orbit") / "run", simulate_orbit(OrbitConfig(frames=8))
    )


def test_track_and_navigate_do_not_share_companions(orbit_run, tmp_path, capsys):
    """`track RUN --out run.tum` then `navigate RUN --out run.csv --measurements both` replaced
    run.config.json and run.health.csv without a word, and `evaluate run.tum` then scored
    navigate's health table (the same rows and times: no check fired). Either order is now
    refused in one line naming the other command's file, before any work."""
    tum, nav = tmp_path / "run.tum", tmp_path / "run.csv"
    assert main(["track", str(orbit_run), "--out", str(tum)]) == 0
    track_config = (tmp_path / "run.config.json").read_text()
    capsys.readouterr()
    assert main(["navigate", str(orbit_run), "--out", str(nav), "--measurements", "both"]) == 1
    err = capsys.readouterr().err
    assert "run.cov.csv" in err and "track's" in err and len(err.strip().splitlines()) == 1
    assert (tmp_path / "run.config.json").read_text() == track_config and not nav.exists()

    other = tmp_path / "other"
    assert main(["navigate", str(orbit_run), "--out", str(other / "run.csv")]) == 0
    with (other / "run.csv").open() as fh:
        assert next(csv.reader(fh))[0] == "t"
    assert main(["track", str(orbit_run), "--out", str(other / "run.tum")]) == 1
    err = capsys.readouterr().err
    assert "run.csv" in err and "navigate's" in err
    assert not (other / "run.tum").exists() and not (other / "run.cov.csv").exists()
    # A CSV file that is not a navigation table leaves the track alone.
    (tmp_path / "notes" / "run.csv").parent.mkdir()
    (tmp_path / "notes" / "run.csv").write_text("a,b\n1,2\n")
    assert main(["track", str(orbit_run), "--out", str(tmp_path / "notes" / "run.tum")]) == 0


def test_a_track_not_named_tum_is_said_to_be_out_of_the_reports_reach(tmp_path, capsys):
    """`track RUN --out est.txt` wrote a track that `report RUN` never showed, without a word
    (report reads *.tum). It is written still, with a warning that says so."""
    run = write_run(tmp_path / "run", simulate_lab(LabConfig(frames=2)))
    assert main(["track", str(run), "--out", str(run / "est.txt")]) == 0
    assert "est.txt: not named .tum: spacepose report looks for" in capsys.readouterr().err
    assert (run / "est.txt.health.csv").is_file()


def test_a_run_rewritten_over_its_results_says_so_and_drops_its_own_stale_truth(tmp_path):
    """`simulate lab` into a run folder that held a track (est.tum) kept it without a word, and
    `report` scored the old track against the new truth (ATE 230 mm, 12.6°); a lab run
    written over an orbit run kept the orbit's truth.csv, and report scored the navigation in
    it. Now the earlier results are named in a warning, and simulate's own truth.csv, which a
    lab run does not have, is removed."""
    run = write_run(tmp_path / "run", simulate_orbit(OrbitConfig(frames=2)))
    assert (run / "truth.csv").is_file()
    (run / "est.tum").write_text("0 0 0 0 0 0 0 1\n")
    (run / "tracks").mkdir()
    (run / "tracks" / "a.tum").write_text("0 0 0 0 0 0 0 1\n")
    with pytest.warns(SpaceposeWarning, match=r"est\.tum, tracks/a\.tum\): they are not of"):
        write_run(run, simulate_lab(LabConfig(frames=2)))
    assert not (run / "truth.csv").exists() and (run / "est.tum").is_file()
