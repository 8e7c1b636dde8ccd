"""Bad inputs found by a third hostile round: each ends in one line naming the file and the
problem (or a warning naming it), never a traceback, a hang or a silently wrong result."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.catalogue import load_catalogue
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.depth_folder import read_tum_depth_list
from spacepose.tools.frames import open_frames, read_frame_cloud, read_timestamps
from spacepose.tools.register_io import read_transform
from spacepose.tools.runs import read_run
from spacepose.tools.text_io import timing_problem

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


# -- a run's own files that the system refuses to read ----------------------------------------


@needs_proc
@pytest.mark.parametrize("name", ["scenario.json", "truth.csv"])
def test_a_run_file_the_system_refuses_is_named(tmp_path, capsys, name, bare_orbit_run):
    """read_run read scenario.json and truth.csv with Path.read_text: an OSError of the read
    ended as 'error: Input/output error', naming no file."""
    run = bare_orbit_run(tmp_path / "run")
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


def test_a_quaternion_too_long_to_square_is_read_as_its_rotation(tmp_path, capsys):
    """A quaternion of 1e200 components overflowed its length: numpy's bare RuntimeWarning,
    then the pose refused as 'not a rigid transform' though it is a rotation (as one of any
    other length, read with a warning naming the line)."""
    q = [0.1, -0.2, 0.3, 0.9] / np.linalg.norm([0.1, -0.2, 0.3, 0.9])

    def tum(scale: float) -> str:
        long = " ".join(f"{v * scale:.17g}" for v in q)  # the second pose's quaternion
        unit = " ".join(f"{v:.17g}" for v in q)
        return f"0 0.1 0 1 {unit}\n1 0.2 0 1 {long}\n2 0.3 0 1 {unit}\n"

    gt, est = tmp_path / "gt.tum", tmp_path / "est.tum"
    gt.write_text(tum(1e200))
    est.write_text(tum(1.0))
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    captured = capsys.readouterr()
    warnings = captured.err.strip().splitlines()
    assert warnings == [
        f"warning: {gt}: 1 quaternions are not of unit length (line 2: 1e+200); read as "
        "their rotations"
    ], warnings
    assert json.loads(captured.out)["ate_rotation_rmse_deg"] == pytest.approx(0.0, abs=1e-6)


# -- frame times in another unit ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("stamps", "words"),
    [
        # nanoseconds from the start at 30 Hz: navigate integrated the orbit a year a frame
        ([round(k * 1e9 / 30) for k in range(4)], "3.333e+07 s apart (median), more than an hour"),
        ([1_700_000_000_000 + 33 * k for k in range(4)], "a time of 1.7e+12 s is past"),  # ms
        ([1.7e18 + 3.3e7 * k for k in range(4)], "a time of 1.7e+18 s is past"),  # epoch ns
    ],
)
def test_frame_times_in_another_unit_than_seconds_are_refused(tmp_path, capsys, stamps, words):
    """timestamps.txt and depth.txt in nanoseconds were read as seconds without a word:
    tracked a year a frame, and navigate, integrating the orbit over each such step, never
    ended (the ten-second run was stopped after five minutes)."""
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(300, 3)) * 0.1 + [0.0, 0.0, 1.0]
    for k in range(4):
        write_cloud(tmp_path / f"{k:06d}.ply", cloud)
    stamps_file = tmp_path / "timestamps.txt"
    stamps_file.write_text("".join(f"{t}\n" for t in stamps))
    with pytest.raises(InputError) as exc:
        read_timestamps(stamps_file, 4)
    assert str(stamps_file) in str(exc.value) and words in str(exc.value)
    assert "times are seconds" in str(exc.value)
    assert main(["track", str(tmp_path), "--out", str(tmp_path / "o" / "e.tum")]) == 1
    err = _cli_error(capsys)
    assert str(stamps_file) in err and words in err
    depth_list = tmp_path / "depth.txt"
    depth_list.write_text("".join(f"{t} {k:06d}.png\n" for k, t in enumerate(stamps)))
    with pytest.raises(InputError) as exc:
        read_tum_depth_list(depth_list)
    assert str(depth_list) in str(exc.value) and words in str(exc.value)


def test_seconds_since_the_epoch_and_slow_frames_still_read():
    """The unit check leaves real seconds alone: epoch times, and a frame a minute."""
    assert timing_problem(1.7e9 + np.arange(5) / 30) is None
    assert timing_problem(60.0 * np.arange(5)) is None
    assert timing_problem([5.0]) is None


# -- cloud frames in another unit than metres ---------------------------------------------------


def test_cloud_frames_in_kilometres_are_warned_about(tmp_path):
    """A folder of clouds in kilometres (a target 1.2 m away written as 0.0012) was tracked
    as a scene a thousandth of its size without a word; a depth map in such a unit was
    warned about, a cloud file was not."""
    rng = np.random.default_rng(0)
    box = rng.uniform(-0.2, 0.2, size=(400, 3)) + np.array([0.0, 0.0, 1.2])
    for k in range(2):
        write_cloud(tmp_path / f"{k:06d}.ply", box * 1e-3, dtype="float64")
    frames = open_frames(tmp_path)
    with pytest.warns(SpaceposeWarning, match="nearer than any sensor ranges") as caught:
        clouds = [frame.cloud for frame in frames]
    assert all(cloud is not None for cloud in clouds)  # read, as a millimetre file is
    messages = [str(w.message) for w in caught if isinstance(w.message, SpaceposeWarning)]
    assert len(messages) == 2 and str(tmp_path / "000000.ply") in messages[0]
    assert "mm from the sensor (median)" in messages[0] and "kilometres" in messages[0]
    # The same cloud in metres reads without a word.
    write_cloud(tmp_path / "000001.ply", box)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_frame_cloud(tmp_path / "000001.ply")


def test_one_pose_scored_rebased_says_its_zero_errors_measure_nothing(tmp_path, capsys):
    """A one-pose estimate rebased on its first pose scored 0 mm and 0 deg, exit 0, without a
    word, however far off it was. It then said so with exit 0 still, which passed an estimate
    in nanoseconds against a truth in seconds (one pose on the truth's times) as perfect: an
    error now, saying why the other poses were left out."""
    est, gt = tmp_path / "est.tum", tmp_path / "gt.tum"
    est.write_text("0 0 0 0 0 0 0 1\n")
    gt.write_text("0 3 -2 7 0.6 0 0 0.8\n")
    assert main(["evaluate", str(est), str(gt), "--rebase-first", "--json"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert f"error: {est}: one pose scored: rebased on itself" in captured.err
    ns = tmp_path / "ns.tum"
    ns.write_text("".join(f"{k * 10**9} {k} 0 0 0 0 0 1\n" for k in range(6)))
    gt.write_text("".join(f"{k} {k} 0 0 0 0 0 1\n" for k in range(6)))
    assert main(["evaluate", str(ns), str(gt), "--rebase-first"]) == 1
    err = capsys.readouterr().err
    assert "5 of 6 estimated poses lie outside gt.tum's times" in err and "one pose" in err
    est.write_text("0 0 0 0 0 0 0 1\n")
    gt.write_text("0 3 -2 7 0.6 0 0 0.8\n")
    # report scores a track as evaluate does, and says so too.
    (tmp_path / "scenario.json").write_text("{}")
    est.rename(tmp_path / "est_track.tum")
    gt.rename(tmp_path / "groundtruth.tum")
    assert main(["report", str(tmp_path), "--out", str(tmp_path / "r.html")]) == 0
    assert "every error is zero whatever the estimate" in (tmp_path / "r.html").read_text()


# -- file names that look like rich markup --------------------------------------------------------


def test_file_names_with_brackets_are_printed_as_they_are(tmp_path, capsys):
    """The CLI printed its results through rich markup: '[red]' vanished from the names it
    printed ('e .tum vs gt.tum') and '[/]' ended a finished command in a MarkupError
    traceback (the report written, exit code 1)."""
    (tmp_path / "run").mkdir()
    est, gt = tmp_path / "run" / "e [red].tum", tmp_path / "run" / "groundtruth.tum"
    est.write_text("0 0 0 1 0 0 0 1\n1 0.1 0 1 0 0 0 1\n")
    gt.write_text(est.read_text())
    assert main(["evaluate", str(est), str(gt)]) == 0
    assert "e [red].tum vs groundtruth.tum" in capsys.readouterr().out
    (tmp_path / "run" / "scenario.json").write_text("{}")
    out = tmp_path / "[/]" / "report.html"
    assert main(["report", str(tmp_path / "run"), "--out", str(out)]) == 0
    assert f"report written: {out}" in capsys.readouterr().out.replace("\n", "")
    assert out.is_file()


# -- depth maps -------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.uint8, np.int8])
def test_an_8_bit_depth_array_is_lost_as_an_8_bit_png_is(tmp_path, dtype):
    """An 8-bit PNG is refused as no depth map, but the same 256 levels saved as a .npy were
    back-projected as depths of 0-255 mm without a word."""
    yy, xx = np.mgrid[:24, :32]
    depth = 1000 + 10 * xx + 5 * yy  # millimetres
    for k in (0, 2):
        np.save(tmp_path / f"{k:06d}.npy", depth.astype(np.uint16))
    np.save(tmp_path / "000001.npy", (depth // 8).astype(dtype))
    (tmp_path / "intrinsics.yaml").write_text("fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\n")
    frames = list(open_frames(tmp_path))
    assert frames[0].cloud is not None and frames[2].cloud is not None
    assert frames[1].cloud is None
    assert str(tmp_path / "000001.npy") in frames[1].error
    assert "8-bit integers" in frames[1].error


# -- a rectangle catalogue in millimetres -------------------------------------------------------


def test_a_catalogue_in_millimetres_is_warned_about(tmp_path):
    """Sides of 1400 x 1800 (mm) were taken as metres: no face ever matched, and planes and
    navigate went on without a word of the unit."""
    eye = np.eye(3).tolist()
    entry = {"name": "front", "center": [0, 0, 700], "R_model_plane": eye, "a": 1400, "b": 1800}
    path = tmp_path / "catalogue.yaml"
    path.write_text(json.dumps([entry]))
    with pytest.warns(SpaceposeWarning) as caught:
        load_catalogue(path)
    message = str(caught[0].message)
    assert str(path) in message and "'front' is 1400 x 1800 m" in message
    assert "millimetres" in message
    path.write_text(json.dumps([entry | {"center": [0, 0, 0.7], "a": 1.4, "b": 1.8}]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_catalogue(path)


# -- a navigation scenario's model key ----------------------------------------------------------


@pytest.mark.parametrize(("model", "shown"), [(5, "5"), ("", "''"), ([], "[]")])
def test_a_scenario_model_that_is_no_file_name_names_the_scenario(tmp_path, capsys, model, shown):
    """A scenario's model of 5 was read as a file named '5' ('5: unknown point cloud
    extension'), an empty one as the scenario's folder ('.: a folder'): neither named the
    scenario or its key."""
    rng = np.random.default_rng(2)
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(2):
        write_cloud(frames / f"{k:06d}.ply", rng.normal(size=(300, 3)) * 0.3 + [0, 0, 20])
    entry = {"name": "front", "center": [0, 0, 0], "R_model_plane": np.eye(3).tolist()}
    scenario = tmp_path / "scenario.yaml"
    description = {"mean_motion": 0.0011, "R_O_C": np.eye(3).tolist(), "model": model}
    scenario.write_text(json.dumps(description | {"rectangles": [entry | {"a": 1, "b": 2}]}))
    out = tmp_path / "nav.csv"
    assert main(["navigate", str(frames), "--scenario", str(scenario), "--out", str(out)]) == 1
    err = _cli_error(capsys)
    problem = f"model must name a cloud file (relative to the scenario), got {shown}"
    assert err == f"error: {scenario}: {problem}"


# -- the config file given is an input too ------------------------------------------------------


@pytest.mark.parametrize("command", ["track", "navigate"])
def test_the_config_given_is_not_overwritten_by_the_effective_config(tmp_path, capsys, command):
    """track --out e.tum --config e.config.json (navigate: nav.csv, nav.config.json) wrote the
    effective config over the config it read: every default frozen into the user's file."""
    rng = np.random.default_rng(3)
    frames = tmp_path / "frames"
    frames.mkdir()
    write_cloud(frames / "000000.ply", rng.normal(size=(300, 3)) * 0.1 + [0, 0, 1])
    out = tmp_path / ("e.tum" if command == "track" else "nav.csv")
    config = out.with_suffix(".config.json")
    config.write_text("{}")
    assert main([command, str(frames), "--out", str(out), "--config", str(config)]) == 1
    err = _cli_error(capsys)
    assert err == f"error: {config}: would overwrite the input {config}: write it elsewhere"
    assert config.read_text() == "{}" and not out.exists()


# -- x y z r g b read as x y z nx ny nz ---------------------------------------------------------


@pytest.mark.parametrize("scale", [255, 1])
def test_colour_columns_are_not_read_as_normals(tmp_path, scale):
    """A headerless x y z r g b file (CloudCompare's and PCL's common layout) had its colours
    read as normals "not of unit length" and used as the surface's directions."""
    rng = np.random.default_rng(4)
    points = rng.normal(size=(400, 3)) * 0.1 + [0.0, 0.0, 1.0]
    colours = rng.integers(0, 256, size=(400, 3)) / 255 * scale
    path = tmp_path / "rgb.xyz"
    np.savetxt(path, np.c_[points, colours], fmt="%.6f")
    with pytest.raises(FileFormatError) as exc:
        read_cloud(path)
    assert str(path) in str(exc.value) and "columns 4-6 look like colours" in str(exc.value)
    # Named in a header, the colours are read past.
    named = tmp_path / "named.xyz"
    named.write_text("x y z r g b\n" + path.read_text())
    cloud = read_cloud(named)
    assert not cloud.has_normals and len(cloud) == 400
    # True normals, and one plate's long normals, stay normals.
    normals = rng.normal(size=(400, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    np.savetxt(path, np.c_[points, normals], fmt="%.9f")
    assert read_cloud(path).has_normals
    np.savetxt(path, np.c_[points, np.tile([0.0, 0.0, 5.0], (400, 1))], fmt="%.6f")
    with pytest.warns(SpaceposeWarning, match="normals are not of unit length"):
        assert read_cloud(path).has_normals


# -- simulate --out onto a file ---------------------------------------------------------------


@pytest.mark.parametrize("under", [False, True])
def test_a_run_out_onto_a_file_says_so(tmp_path, capsys, under):
    """simulate --out FILE (or FILE/run) ended in mkdir's 'FILE/frames: Not a directory'."""
    file = tmp_path / "notes.txt"
    file.write_text("keep me\n")
    out = file / "run" if under else file
    assert main(["simulate", "lab", "--out", str(out), "--frames", "1"]) == 1
    err = _cli_error(capsys)
    where = f"lies under {file}, a file" if under else "is a file"
    assert err == f"error: {out}: {where}: a run is written to a folder"
    assert file.read_text() == "keep me\n"


# -- model-free navigation on a run shorter than its batch --------------------------------------


def test_model_free_navigation_short_of_its_batch_says_so(tmp_path):
    """Model-free, the filter starts on a batch of 200 ok poses: a 6-frame run, every pose
    ok, ended in "the tracker gave no ok pose" beside a health table of ok rows."""
    from types import SimpleNamespace

    from spacepose.core.fused_navigation import FusionConfig
    from spacepose.tools.navigation_reasons import why_no_registration

    tracks = [SimpleNamespace(status=s) for s in ("ok",) * 5 + ("degraded",)]
    health = tmp_path / "nav.health.csv"
    why = why_no_registration(tracks, FusionConfig(), False, health)
    assert "a batch of 200 ok poses" in why and "the tracker gave 5 in 6 frames" in why
    assert "no ok pose" not in why
    lost = [SimpleNamespace(status="lost")] * 3
    assert "the tracker gave no ok pose" in why_no_registration(lost, FusionConfig(), False, health)


# -- a folder of clouds read as depth images ----------------------------------------------------


@pytest.mark.parametrize("given", [False, True])
def test_intrinsics_beside_cloud_frames_name_what_made_it_a_depth_folder(tmp_path, capsys, given):
    """A folder of .ply frames with a stray intrinsics.yaml (or --intrinsics) ended in "no
    depth images (.png, .tif, .tiff, .npy) in the folder", beside the clouds in it."""
    rng = np.random.default_rng(5)
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(3):
        write_cloud(frames / f"{k:06d}.ply", rng.normal(size=(200, 3)) * 0.1 + [0, 0, 1])
    intrinsics = (tmp_path if given else frames) / "intrinsics.yaml"
    intrinsics.write_text("fx: 500\nfy: 500\ncx: 319.5\ncy: 239.5\n")
    extra = ["--intrinsics", str(intrinsics)] if given else []
    assert main(["track", str(frames), "--out", str(tmp_path / "e.tum"), *extra]) == 1
    err = _cli_error(capsys)
    why = (
        "intrinsics apply to depth images"
        if given
        else "its intrinsics.yaml makes it a folder of depth images"
    )
    remedy = "leave out --intrinsics" if given else "move intrinsics.yaml out"
    clouds = "000000.ply, 000001.ply, ..."
    assert err == f"error: {frames}: {why}, and its frames are point clouds ({clouds}): {remedy}"


# -- register --init files -----------------------------------------------------------------------


def test_an_init_json_holding_the_matrix_itself_is_read(tmp_path):
    """A .json holding the 4x4 matrix (as numpy's tolist writes it) was refused as "expected
    16 numbers (a 4x4 matrix)", an earlier --out saved as RESULT.JSON read as text, and a
    JSON syntax error not located."""
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    rows = tmp_path / "rows.json"
    rows.write_text(json.dumps(T.tolist()))
    flat = tmp_path / "flat.json"
    flat.write_text(json.dumps(T.ravel().tolist()))
    upper = tmp_path / "RESULT.JSON"
    upper.write_text(json.dumps({"T_target_source": T.tolist(), "fitness": 1.0}))
    for path in (rows, flat, upper):
        np.testing.assert_array_equal(read_transform(path), T)
    broken = tmp_path / "broken.json"
    broken.write_text('{"T_target_source": [1, 2,}')
    with pytest.raises(FileFormatError) as exc:
        read_transform(broken)
    assert str(broken) in str(exc.value) and "not valid JSON: line 1:27" in str(exc.value)


# -- a European locale's text export ------------------------------------------------------------


@pytest.mark.parametrize(
    ("row", "problem"),
    [
        ("0,0126 -0,0132 1,0640", "line 1: commas and blanks both in '0,0126 -0,0132 1,0640'"),
        ("0.0126;-0.0132;1.0640", "line 1: fields separated by ';' ('0.0126;-0.0132;1.0640')"),
    ],
)
def test_decimal_commas_and_semicolons_are_named_as_such(tmp_path, row, problem):
    """Decimal commas ended in "cannot parse text point file", naming no line; ';'-separated
    rows were taken for a header, and the error pointed at line 2."""
    path = tmp_path / "frame.xyz"
    path.write_text(f"{row}\n{row}\n")
    with pytest.raises(FileFormatError) as exc:
        read_cloud(path)
    assert str(exc.value).startswith(f"{path}: {problem}")


# -- part of the normals ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "text", "given"),
    [
        ("part.xyz", "x y z nx ny\n1 2 3 0 1\n1 2 4 0 1\n1 3 3 0 1\n", "nx, ny without nz"),
        (
            "part.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nproperty float nx\nproperty float nz\nend_header\n"
            "1 2 3 0 1\n1 2 4 0 1\n1 3 3 0 1\n",
            "nx, nz without ny",
        ),
    ],
)
def test_part_of_the_normals_is_warned_about(tmp_path, name, text, given):
    """Two of the three normal components named (a header or PLY properties): the normals
    were dropped without a word."""
    path = tmp_path / name
    path.write_text(text)
    with pytest.warns(SpaceposeWarning) as caught:
        cloud = read_cloud(path)
    assert not cloud.has_normals and len(cloud) == 3
    message = str(caught[0].message)
    assert message == f"{path}: normals read as absent: {given} (a normal needs all three)"


def test_a_far_plane_before_every_return_says_so(tmp_path):
    """max_depth: 0.5 (meant as 5 m, or in other units) left every pixel beyond it: the frame
    was lost as "no return (every pixel zero or invalid)", the far plane not named."""
    yy, xx = np.mgrid[:24, :32]
    np.save(tmp_path / "000000.npy", (1000 + 10 * xx + 5 * yy).astype(np.uint16))
    intrinsics = "fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\nmax_depth: 0.5\n"
    (tmp_path / "intrinsics.yaml").write_text(intrinsics)
    frame = next(iter(open_frames(tmp_path)))
    assert frame.cloud is None
    assert frame.error == (
        f"{tmp_path / '000000.npy'}: every return lies at or beyond max_depth 0.5 m (the "
        "nearest at 1 m): a far plane in other units than metres?"
    )
    # Only no-return codes (0 and 65535) beyond it: no return, as before.
    np.save(tmp_path / "000000.npy", np.where(xx % 2, 0, 65535).astype(np.uint16))
    frame = next(iter(open_frames(tmp_path)))
    assert frame.error.endswith("depth image has no return (every pixel zero or invalid)")


# -- report: navigation tables it cannot score --------------------------------------------------


def _nav_run(root: Path, nav_rows: list[list[str]]) -> Path:
    """A run folder with a 4-row truth.csv and a nav.csv of ``nav_rows`` (NAV_COLUMNS)."""
    from spacepose.core.nav_result import NAV_COLUMNS
    from spacepose.core.sim.scenarios import TRUTH_COLUMNS

    root.mkdir()
    (root / "scenario.json").write_text('{"scenario": "orbit"}')
    truth = [[str(float(k)), "25", "0", "0", *["0"] * 3, "0", "0", "0", "1", *["0"] * 9]
             for k in range(4)]  # fmt: skip
    (root / "truth.csv").write_text(
        ",".join(TRUTH_COLUMNS) + "\n" + "".join(",".join(r) + "\n" for r in truth)
    )
    (root / "nav.csv").write_text(
        ",".join(NAV_COLUMNS) + "\n" + "".join(",".join(r) + "\n" for r in nav_rows)
    )
    return root


def _nav_row(t: float, state: bool) -> list[str]:
    values = ["25", "0", "0", *["0"] * 3, "0", "0", "0", "1", *["0"] * 9]
    return [str(t), *(values if state else ["nan"] * 19), *["0.1"] * 18, "2", "update"]


@pytest.mark.parametrize(
    ("rows", "reason"),
    [
        # Every row waiting: numpy's bare "Mean of empty slice" and matplotlib's "Axis limits
        # cannot be NaN or Inf" as the reason.
        ([_nav_row(k, False) for k in range(4)], "no frame navigated (no row holds a state)"),
        # Another run's times: scored line by line against other frames, without a word.
        ([_nav_row(k + 5, True) for k in range(4)], "row 1 is at t = 5 s, truth.csv's at 0 s"),
    ],
)
def test_report_leaves_out_a_navigation_it_cannot_score_saying_why(tmp_path, capsys, rows, reason):
    run = _nav_run(tmp_path / "run", rows)
    assert main(["report", str(run), "--out", str(tmp_path / "r.html")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warning: {run / 'nav.csv'}: left out"), err
    assert reason in err[0]


# -- timestamps.txt spelt in another case -------------------------------------------------------


def test_timestamps_named_in_another_case_time_the_frames(tmp_path, capsys):
    """Timestamps.txt (as a case-blind file system keeps it) was tracked as a sixth frame,
    lost, and the five frames timed 0, 1, 2, ... without a word."""
    rng = np.random.default_rng(6)
    for k in range(3):
        write_cloud(tmp_path / f"{k:06d}.ply", rng.normal(size=(200, 3)) * 0.1 + [0, 0, 1])
    (tmp_path / "Timestamps.txt").write_text("10\n10.5\n11\n")
    frames = open_frames(tmp_path)
    assert len(frames) == 3
    assert [frame.timestamp for frame in frames] == [10.0, 10.5, 11.0]
    # Two spellings: which times are the frames'? Refused, naming both.
    (tmp_path / "timestamps.txt").write_text("0\n1\n2\n")
    with pytest.raises(InputError) as exc:
        open_frames(tmp_path)
    assert str(exc.value) == f"{tmp_path}: holds Timestamps.txt and timestamps.txt: keep one"
