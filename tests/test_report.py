"""The HTML report: built from a synthetic run, checked for content and in headless Chromium."""

import base64
import csv
import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.cli import main
from spacepose.core import se3
from spacepose.core.trajectory import Trajectory
from spacepose.errors import InputError
from spacepose.tools import plots
from spacepose.tools.cloud_io import write_cloud
from spacepose.tools.report import build_report
from spacepose.tools.trajectory_io import read_tum, write_tum

NAV_STATE = (
    "rho_x rho_y rho_z v_x v_y v_z qx qy qz qw w_x w_y w_z k_x k_y k_z com_x com_y com_z".split()
)
NAV_SIGMA = [f"sig_{c}" for c in NAV_STATE if not c.startswith("q")] + [
    "sig_att_x",
    "sig_att_y",
    "sig_att_z",
]


def _write_csv(path: Path, header: list[str], rows: list[list[object]]) -> None:
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)


def _make_run(root: Path) -> dict[str, float]:
    """A lab-like run (ground truth, two tracks, health) and an orbit-like one (truth, nav)."""
    rng = np.random.default_rng(3)
    lab = root / "lab"
    lab.mkdir(parents=True)
    (lab / "scenario.json").write_text(json.dumps({"scenario": "lab", "seed": 3}))
    # One noisy planar frame, enough for the mpp-MLS before/after view.
    grid = np.stack(np.meshgrid(np.linspace(-0.1, 0.1, 40), np.linspace(-0.1, 0.1, 40)), -1)
    plane = np.c_[grid.reshape(-1, 2), np.full(1600, 1.2) + rng.normal(0, 1e-3, 1600)]
    write_cloud(lab / "frames" / "000000.ply", plane)
    t = np.arange(10.0)
    gt = np.stack(
        [
            se3.make_transform(Rotation.from_euler("y", k, degrees=True), [0.01 * k, 0, 1.2])
            for k in t
        ]
    )
    write_tum(lab / "groundtruth.tum", Trajectory(t, gt))
    offset = se3.make_transform(np.eye(3), [0.002, 0.0, 0.0])  # a constant 2 mm x error
    write_tum(lab / "tracks" / "icp.tum", Trajectory(t, offset @ gt))
    write_tum(lab / "tracks" / "gicp.tum", Trajectory(t, gt))
    _write_csv(
        lab / "tracks" / "icp.health.csv",
        ["frame", "timestamp", "status"],
        [[i, ti, "ok" if i != 4 else "lost"] for i, ti in enumerate(t)],
    )
    orbit = root / "orbit"
    orbit.mkdir()
    (orbit / "scenario.json").write_text(json.dumps({"scenario": "orbit", "seed": 3}))
    truth_rows, nav_rows = [], []
    for ti in t:
        q = Rotation.from_rotvec([0.0, 0.0, 0.01 * ti]).as_quat()
        truth = [25.0, 0, 0, 0, 0, 0, *q, 0, 0, 0.01, -0.2, 0.4, -0.25, 0.02, -0.03, 0.05]
        nav = list(truth)
        nav[0] += 0.003  # 3 mm of position error in x
        truth_rows.append([ti, *truth])
        nav_rows.append([ti, *nav, *np.full(len(NAV_SIGMA), 1e-3), 2, "ok"])
    _write_csv(orbit / "truth.csv", ["t", *NAV_STATE], truth_rows)
    _write_csv(orbit / "nav.csv", ["t", *NAV_STATE, *NAV_SIGMA, "n_rect", "status"], nav_rows)
    exp = root / "experiments" / "li-l1"
    exp.mkdir(parents=True)
    (exp / "table.json").write_text(json.dumps({"share_below_20deg": {"raw": 0.2, "mls": 0.85}}))
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot(rng.normal(size=10))
    fig.savefig(exp / "histogram.png")
    plt.close(fig)
    return {"icp_x_mm": 2.0, "nav_rho_x_mm": 3.0}


def test_report_holds_the_tables_and_every_figure(tmp_path: Path) -> None:
    expected = _make_run(tmp_path / "demo")
    out = build_report(tmp_path / "demo")
    page = out.read_text()
    # Tracking table: icp row shows the 2 mm x error, gicp is exact.
    icp_row = re.search(r"<tr><td>icp</td><td>([\d.]+) \(", page)
    assert icp_row and float(icp_row.group(1)) == pytest.approx(expected["icp_x_mm"], abs=1e-3)
    assert re.search(r"<tr><td>gicp</td><td>0.000 \(0.000\)", page)
    # Navigation table: 3 mm RMS on rho_x over the second half.
    nav_row = re.search(r"<tr><td>position \(mm\)</td><td>([\d.]+)</td>", page)
    assert nav_row and float(nav_row.group(1)) == pytest.approx(expected["nav_rho_x_mm"], rel=1e-6)
    # Figures: mpp-MLS view, error curves, health, 6 navigation groups, the experiment's own PNG;
    # all decodable.
    uris = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert "mpp-MLS before / after" in page
    assert len(uris) == 1 + 1 + 1 + 6 + 1
    for uri in uris:
        image = mpimg.imread(__import__("io").BytesIO(base64.b64decode(uri)), format="png")
        assert image.shape[0] > 50 and image.shape[1] > 50
    assert "share_below_20deg" in page and "<script" not in page


def test_a_lost_frames_prediction_is_not_scored_in_the_report(tmp_path: Path) -> None:
    """The tracker writes a lost frame's pose as the motion model's guess so no frame goes
    missing; its health table marks it. Scored, a guess 0.5 m off moved the icp row's x mean
    from 2 mm to 52 mm; the report leaves it out, as `evaluate` does, and says so."""
    expected = _make_run(tmp_path / "demo")
    tracks = tmp_path / "demo" / "lab" / "tracks"
    t = np.arange(10.0)
    gt = np.stack(
        [
            se3.make_transform(
                Rotation.from_euler("y", k, degrees=True), [0.01 * k + 0.002, 0, 1.2]
            )
            for k in t
        ]
    )
    gt[4, 0, 3] += 0.5  # frame 4, lost in icp.health.csv: a prediction 0.5 m off
    write_tum(tracks / "icp.tum", Trajectory(t, gt))
    page = build_report(tmp_path / "demo").read_text()
    icp_row = re.search(r"<tr><td>icp</td><td>([\d.]+) \(([\d.]+)\)", page)
    assert icp_row and float(icp_row.group(1)) == pytest.approx(expected["icp_x_mm"], abs=1e-3)
    assert float(icp_row.group(2)) == pytest.approx(0.0, abs=1e-3)
    assert "icp: 1 frame(s) lost in icp.health.csv left out" in page


def test_a_track_in_millimetres_is_noted_in_the_report_as_evaluate_warns(tmp_path: Path) -> None:
    """A track written in millimetres scored 1,200 mm of ATE in the report without a word,
    where `evaluate` warns that the two are a unit's factor apart."""
    _make_run(tmp_path / "demo")
    tracks = tmp_path / "demo" / "lab" / "tracks"
    gicp = read_tum(tracks / "gicp.tum")
    in_mm = gicp.poses.copy()
    in_mm[:, :3, 3] *= 1e3
    write_tum(tracks / "gicp.tum", Trajectory(gicp.timestamps, in_mm))
    page = html.unescape(build_report(tmp_path / "demo").read_text())
    note = re.search(r"gicp: [^<]*times as far[^<]*are both in metres\?", page)
    assert note, page[-3000:]


def test_report_cli_and_errors(tmp_path: Path, capsys) -> None:
    _make_run(tmp_path / "demo")
    assert main(["report", str(tmp_path / "demo"), "--out", str(tmp_path / "r.html")]) == 0
    assert (tmp_path / "r.html").stat().st_size > 10_000
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="nothing to report"):
        build_report(tmp_path / "empty")
    assert main(["report", str(tmp_path / "missing")]) == 1
    assert "not a folder" in capsys.readouterr().err


def test_report_finds_nav_csv_named_as_the_readme_names_it(tmp_path: Path) -> None:
    expected = _make_run(tmp_path / "demo")
    orbit = tmp_path / "demo" / "orbit"
    (orbit / "nav.csv").rename(orbit / "NAV.csv")
    page = build_report(tmp_path / "demo").read_text()
    nav_row = re.search(r"<tr><td>position \(mm\)</td><td>([\d.]+)</td>", page)
    assert nav_row and float(nav_row.group(1)) == pytest.approx(expected["nav_rho_x_mm"], rel=1e-6)


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def _run_chromium(page: Path, profile: Path) -> tuple[str, str]:
    cmd = [
        _chromium(),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile}",
        "--enable-logging=stderr",
        "--v=0",
        "--virtual-time-budget=5000",
        "--dump-dom",
        page.resolve().as_uri(),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    return done.stdout, done.stderr


@pytest.mark.skipif(_chromium() is None, reason="needs Debian's chromium (installed by .ci/run)")
def test_report_renders_in_headless_chromium_without_console_errors(tmp_path: Path) -> None:
    _make_run(tmp_path / "demo")
    report = build_report(tmp_path / "demo")
    dom, log = _run_chromium(report, tmp_path / "profile-a")
    assert "spacepose report" in dom
    assert re.findall(r"CONSOLE[^\n]*", log) == []
    # The checker page is the report plus a script that counts decoded images; its own log line
    # is the only console output allowed.
    checker = tmp_path / "checker.html"
    script = (
        "<script>window.addEventListener('load', () => { const im = [...document.images];"
        " console.log('IMGCHECK ' + im.length + ' ' +"
        " im.filter(i => i.complete && i.naturalWidth > 0).length); });</script>"
    )
    checker.write_text(report.read_text().replace("</body>", script + "</body>"))
    _, log = _run_chromium(checker, tmp_path / "profile-b")
    counts = re.search(r"IMGCHECK (\d+) (\d+)", log)
    assert counts, log[-2000:]
    assert int(counts.group(1)) == 10 and counts.group(1) == counts.group(2)


def test_report_skips_corrupt_files_names_them_and_builds_the_rest(tmp_path: Path, capsys) -> None:
    expected = _make_run(tmp_path / "demo")
    root = tmp_path / "demo"
    (root / "lab" / "scenario.json").write_text('{"scenario": "lab",')
    (root / "bench.json").write_text("[1, 2")
    (root / "experiments" / "li-l1" / "table.json").write_text("{oops}")
    _write_csv(root / "lab" / "tracks" / "icp.health.csv", ["frame", "timestamp"], [[0, 0.0]])
    # A folder named as a figure aborted the whole report ("Is a directory"); a health table
    # longer than the ground truth dropped every track's timeline, blaming groundtruth.tum.
    (root / "experiments" / "li-l1" / "broken.png").mkdir()
    _write_csv(
        root / "lab" / "tracks" / "gicp.health.csv",
        ["frame", "timestamp", "status"],
        [[i, float(i), "ok"] for i in range(12)],
    )
    assert main(["report", str(root)]) == 0
    out, err = capsys.readouterr()
    page = (root / "report.html").read_text()
    # Every bad file is named once on stderr, one line each, and listed in the page.
    bad = {
        "lab/scenario.json": "not valid JSON: line 1:20: Expecting property name",
        "bench.json": "not valid JSON: line 1:6: Expecting ',' delimiter",
        "experiments/li-l1/table.json": "not valid JSON: line 1:2: Expecting property name",
        "lab/tracks/icp.health.csv": "CSV file has no status column",
        "experiments/li-l1/broken.png": "Is a directory",
        "lab/tracks/gicp.health.csv": "12 rows for 10 ground-truth frames",
    }
    lines = err.strip().splitlines()
    assert len(lines) == len(bad) and "Traceback" not in err
    for name, reason in bad.items():
        assert sum(f"{root / name}: left out of the report: {reason}" in ln for ln in lines) == 1
        assert f"<td>{name}</td><td>{html.escape(reason)}" in page
    # The rest is all there: both tracks scored, navigation, the experiment's figure.
    icp_row = re.search(r"<tr><td>icp</td><td>([\d.]+) \(", page)
    assert icp_row and float(icp_row.group(1)) == pytest.approx(expected["icp_x_mm"], abs=1e-3)
    nav_row = re.search(r"<tr><td>position \(mm\)</td><td>([\d.]+)</td>", page)
    assert nav_row and float(nav_row.group(1)) == pytest.approx(expected["nav_rho_x_mm"], rel=1e-6)
    assert "histogram" in page and "health flags" not in page
    assert "report written" in out


def test_a_run_folder_named_with_bytes_that_are_not_utf8_is_reported(tmp_path: Path) -> None:
    """A folder name with a byte that is not UTF-8 (Linux allows any bytes) went into the
    figures' titles and ended the report with a TypeError from matplotlib's text; it is now
    shown with a backslash escape, and every figure is drawn."""
    root = Path(bytes(tmp_path).decode("utf-8", "surrogateescape")) / (
        b"demo\xff".decode("utf-8", "surrogateescape")
    )
    _make_run(root)
    page = build_report(root, out=tmp_path / "r.html").read_text(encoding="utf-8")
    assert "demo\\udcff" in page
    assert len(re.findall(r'src="data:image/png;base64,', page)) == 1 + 1 + 1 + 6 + 1


def test_report_refuses_to_overwrite_a_file_it_reads(tmp_path: Path, capsys) -> None:
    """``--out RUN/lab/groundtruth.tum`` replaced the run's ground truth with the page (exit 0);
    the next report or evaluate scored against HTML. A page written before is overwritten."""
    root = tmp_path / "demo"
    _make_run(root)
    gt = root / "lab" / "groundtruth.tum"
    before = gt.read_bytes()
    assert main(["report", str(root), "--out", str(gt)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"error: {gt}: would overwrite the input {gt}: write it elsewhere", err
    assert gt.read_bytes() == before
    assert main(["report", str(root)]) == 0 and main(["report", str(root)]) == 0


@pytest.mark.parametrize(
    ("truth", "scored"),
    [("lab/groundtruth.tum", "gicp.tum, icp.tum"), ("orbit/truth.csv", "nav.csv")],
)
def test_files_of_a_run_without_its_truth_are_named_not_dropped(
    tmp_path: Path, capsys, truth: str, scored: str
) -> None:
    """Without groundtruth.tum a run's tracks, and without truth.csv its nav.csv, were left out
    of the page without a word."""
    root = tmp_path / "demo"
    _make_run(root)
    (root / truth).unlink()
    assert main(["report", str(root), "--out", str(tmp_path / "r.html")]) == 0
    err = capsys.readouterr().err.strip()
    assert err == (
        f"warning: {root / truth}: left out of the report: not found, so {scored} cannot be scored"
    ), err
    assert f"{scored} cannot be scored" in (tmp_path / "r.html").read_text()


def test_an_estimate_with_repeated_times_is_noted_and_not_paired_by_line(
    tmp_path: Path, monkeypatch
) -> None:
    """`evaluate` notes estimates that share a ground-truth pose; the report scored them without
    a word, and drew its error curves by line number whenever the counts matched."""
    root = tmp_path / "demo"
    _make_run(root)
    gt = read_tum(root / "lab" / "groundtruth.tum")
    # Ten poses as the truth has, the fifth time repeated: by line, the last five would meet
    # the truth of the frame after theirs.
    t = np.r_[gt.timestamps[:5], gt.timestamps[4:9]]
    poses = np.r_[gt.poses[:5], gt.poses[4:9]]
    write_tum(root / "lab" / "tracks" / "gicp.tum", Trajectory(t, poses))
    drawn: list[str] = []
    curves = plots.pose_error_curves
    monkeypatch.setattr(
        plots, "pose_error_curves", lambda t, c, title: drawn.extend(c) or curves(t, c, title)
    )
    page = build_report(root, tmp_path / "r.html").read_text()
    note = (
        "gicp: 1 estimate(s) share a ground-truth pose with another (repeated timestamps, or a "
        "--max-dt wider than the spacing of the truth)"
    )
    assert note in page
    assert drawn == ["icp"]  # icp's times are the truth's; gicp's are not, so no curve


def test_a_run_nested_in_another_is_scored_against_its_own_truth_alone(tmp_path: Path) -> None:
    """The outer run scored the inner run's tracks, its groundtruth.tum taken for one, and its
    nav.csv against the outer truth: 15 m off, without a word (a demo written into a run)."""
    root = tmp_path / "outer"
    _make_run(root)
    inner = root / "lab" / "inner"
    shutil.copytree(root / "orbit", inner / "orbit_copy")
    shutil.copytree(root / "lab" / "tracks", inner / "tracks")
    shutil.copy(root / "lab" / "groundtruth.tum", inner / "groundtruth.tum")
    (inner / "scenario.json").write_text(json.dumps({"scenario": "lab", "seed": 4}))
    gt = read_tum(inner / "groundtruth.tum")
    far = se3.make_transform(np.eye(3), [15.0, 0.0, 0.0])
    write_tum(inner / "tracks" / "far.tum", Trajectory(gt.timestamps, far @ gt.poses))
    page = build_report(root, tmp_path / "r.html").read_text()
    sections = re.split(r"<h2>Run: ", page)
    outer = next(s for s in sections if s.startswith("lab<"))
    own = next(s for s in sections if s.startswith("lab/inner<"))
    assert "far" not in outer and "groundtruth" not in outer and "15000" not in outer
    assert "far" in own and "15000" in own


def test_a_navigation_scored_on_less_than_the_run_is_warned_about(tmp_path: Path, capsys) -> None:
    """A nav.csv of 4 rows for 10 frames was scored "over the second half" of its 4; a row the
    filter updated holding NaN was left out of the RMS; both without a word."""
    root = tmp_path / "demo"
    _make_run(root)
    nav = root / "orbit" / "nav.csv"
    lines = nav.read_text().splitlines()
    cells = lines[3].split(",")
    cells[1], cells[-1] = "nan", "update"
    nav.write_text("\n".join([*lines[:3], ",".join(cells), lines[4]]) + "\n")
    assert main(["report", str(root), "--out", str(tmp_path / "r.html")]) == 0
    err = capsys.readouterr().err
    assert f"warning: {nav}: 4 rows for the run's 10 frames: scored over those rows only" in err
    assert f"warning: {nav}: row 3 holds NaN though its status is update (1 such rows" in err


def test_figures_at_the_root_are_headed_by_its_name_and_a_bench_output_shown_once(
    tmp_path: Path,
) -> None:
    """Figures at the top of the reported folder were headed "." (the folder relative to
    itself), and a bench output beside them was dumped as JSON there as well as tabled in the
    benchmark section."""
    root = tmp_path / "campaign_7"
    root.mkdir()
    mpimg.imsave(root / "curve.png", np.zeros((4, 4)))
    bench = {"stages": {"icp": {"median_ms": 12.5, "min_ms": 11.0, "max_ms": 14.0}}}
    (root / "bench_w2.json").write_text(json.dumps(bench))
    (root / "table.json").write_text(json.dumps({"cells": 3}))
    page = build_report(root, tmp_path / "r.html").read_text()
    assert "<h3>campaign_7</h3>" in page and "<h3>.</h3>" not in page
    assert page.count("median_ms") == 0 and page.count("12.5") == 1
    assert "cells" in page


def test_a_track_named_in_capitals_is_scored(tmp_path: Path) -> None:
    """`track --out RUN/upper.TUM` wrote a track the report left out without a word (it read
    *.tum only), though the frame readers and `evaluate` take any case."""
    expected = _make_run(tmp_path / "demo")
    tracks = tmp_path / "demo" / "lab" / "tracks"
    (tracks / "icp.tum").rename(tracks / "upper.TUM")
    page = build_report(tmp_path / "demo").read_text()
    row = re.search(r"<tr><td>upper</td><td>([\d.]+) \(([\d.]+)\)", page)
    assert row and float(row.group(1)) == pytest.approx(expected["icp_x_mm"], abs=1e-3)


def test_a_track_written_w_first_is_noted_in_the_report_as_evaluate_warns(tmp_path: Path) -> None:
    """A track whose quaternions were written w first scored 160° of rotation in the report
    without the note `evaluate` gives it."""
    _make_run(tmp_path / "demo")
    tracks = tmp_path / "demo" / "lab" / "tracks"
    rows = [line.split() for line in (tracks / "gicp.tum").read_text().splitlines()]
    turned = [[t, x, y, z, qw, qx, qy, qz] for t, x, y, z, qx, qy, qz, qw in rows]
    (tracks / "wfirst.tum").write_text("\n".join(" ".join(r) for r in turned) + "\n")
    page = html.unescape(build_report(tmp_path / "demo").read_text())
    assert "wfirst: rotations" in page and "quaternions are read w first" in page
    assert "gicp: rotations" not in page
