"""Round 30 of bad inputs: a lab scene beyond the sensor or overflowing the renderer, intrinsics
of a size no image has, endless benchmark repeats, campaign grids of endless or failing cases,
a comma-separated --init, GICP covariances that are none, and Kabsch pairs whose squares
overflow."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from tests.cli_errors import error_line

from spacepose.cli import main
from spacepose.errors import ConfigError, InputError


def _simulate_lab(tmp_path, *options: str) -> subprocess.CompletedProcess:
    """``simulate lab`` in its own process: numpy's warnings there are printed, not filtered."""
    out = tmp_path / "run"
    args = ["simulate", "lab", "--frames", "1", "--out", str(out), *options]
    code = f"from spacepose.cli import main; raise SystemExit(main({args!r}))"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)


def test_a_lab_range_beyond_the_sensor_is_refused_before_rendering(tmp_path):
    """--range 1e300 printed numpy's "overflow encountered in cast" and "in dot" before "lab
    frame 0: the sensor sees nothing (target inf m away ...)"."""
    done = _simulate_lab(tmp_path, "--range", "1e300")
    assert done.returncode == 1
    assert done.stderr.strip() == (
        "error: scenario lab: a range of 1e+300 m puts the whole target (reaching 0.464 m from "
        "its centre) beyond the sensor's 10 m range: it would see nothing; place it nearer"
    )
    assert not (tmp_path / "run" / "frames").exists()


def test_a_lab_target_size_that_overflows_the_renderer_names_the_option(tmp_path):
    """--target-size 1e100 printed numpy's "overflow encountered in multiply" before "the
    sensor sees nothing (target 1.2 m away ...)", naming no setting."""
    done = _simulate_lab(tmp_path, "--target-size", "1e100")
    assert done.returncode == 1
    assert done.stderr.strip() == (
        "error: scenario lab: invalid lab config: target_size_m: 1e+100 is too large: squared, "
        "and times another square, it overflows float64 (at most 1e+50)"
    )


def _depth_folder(root, intrinsics: str):
    from spacepose.tools.depth_io import write_depth_image

    root.mkdir()
    v, u = np.mgrid[:30, :40]
    for k in range(3):
        write_depth_image(root / f"{k:06d}.png", 1.0 + 0.002 * (u + k) + 0.001 * v)
    (root / "intrinsics.yaml").write_text(intrinsics)
    return root


def test_intrinsics_of_a_size_no_image_has_name_the_file_and_fields(tmp_path, capsys):
    """width 1e26 (written out whole) lost every frame, each blamed on its image ("image is
    40x30, the intrinsics say 100000000000000000000000000x30"), the intrinsics file unnamed."""
    width = 10**26
    text = f"fx: 40\nfy: 40\ncx: 19.5\ncy: 14.5\nwidth: {width}\nheight: 30\n"
    root = _depth_folder(tmp_path / "depth", text)
    assert main(["track", str(root), "--out", str(tmp_path / "est.tum")]) == 1
    assert error_line(capsys) == (
        f"error: {root / 'intrinsics.yaml'}: width {width} and height 30 are the size of no "
        "image of the folder (3 images, most 40x30): intrinsics of another camera or resolution?"
    )
    from spacepose.tools.frames import open_frames

    (root / "intrinsics.yaml").write_text(text.replace(str(width), "40"))
    assert len(open_frames(root)) == 3


def test_endless_benchmark_repeats_are_refused(tmp_path, capsys, monkeypatch):
    """--repeats 10**9 ran for ever, the timed calls of the first stage unfinished."""
    import spacepose.tools.bench as bench

    def measure(*args, **kwargs):
        raise AssertionError("the benchmark started")

    monkeypatch.setattr(bench, "_measure", measure)
    out = tmp_path / "bench.json"
    assert main(["bench", "--quick", "--out", str(out), "--repeats", str(10**9)]) == 1
    assert error_line(capsys) == (
        f"error: --repeats: {10**9} timed calls per stage would run for days: at most 100 (a "
        "stage's median steadies within a few)"
    )
    assert not out.exists()


_CAMPAIGN = (
    "case_kind: {kind}\ngrid:\n  scenario: [lab]\n  noise_scale: [{noise}]\n  method: [{method}]\n"
    "  seed: [{seeds}]\n"
)


def _campaign(tmp_path, kind="registration", noise="0.0", method="gicp", seeds="0", extra=""):
    from spacepose.tools.campaign_spec import load_campaign_config

    path = tmp_path / "campaign.yaml"
    text = _CAMPAIGN.format(kind=kind, noise=noise, method=method, seeds=seeds)
    path.write_text(text + extra)
    return path, lambda: load_campaign_config(path)


def test_a_campaign_grid_of_endless_cases_is_refused(tmp_path):
    """3000 noise scales by 3000 seeds were taken: the run built its 9 million cases first."""
    many = ", ".join(str(k) for k in range(3000))
    path, load = _campaign(tmp_path, noise=many, seeds=many)
    with pytest.raises(ConfigError) as info:
        load()
    assert str(info.value) == (
        f"{path}: invalid campaign config: grid: 1 scenario x 3000 noise_scale x 1 method x "
        "3000 seed make 9,000,000 cases, more than 1,000,000"
    )
    path, load = _campaign(tmp_path, seeds=", ".join(str(k) for k in range(1000)))
    assert len(load().grid["seed"]) == 1000


def test_a_campaign_noise_scale_no_sensor_takes_is_refused_as_read(tmp_path):
    """noise_scale 1e300 was taken, and every case failed in a worker on the sensor's bound."""
    path, load = _campaign(tmp_path, noise="1e300")
    with pytest.raises(ConfigError) as info:
        load()
    message = str(info.value)
    assert message.startswith(
        f"{path}: invalid campaign config: grid: scenario 'lab', noise_scale 1e+300: sensor tof: "
        "invalid sensor config: noise_scale 1e+300 makes σ"
    ), message
    assert message.endswith("(for case_kind 'registration')")
    _campaign(tmp_path, noise="2.0")[1]()


def test_campaign_frames_beyond_the_simulator_are_refused_as_read(tmp_path):
    """frames 10**9 (tracking) was taken, and every case failed in a worker."""
    extra = f"  frames: [10, {10**9}]\n"
    path, load = _campaign(tmp_path, kind="tracking", method="keyframe", extra=extra)
    with pytest.raises(ConfigError) as info:
        load()
    assert str(info.value) == (
        f"{path}: invalid campaign config: grid: noise_scale 0.0, frames {10**9}: scenario lab: "
        "invalid lab config: frames: Input should be less than or equal to 1000000 (for "
        "case_kind 'tracking')"
    )
    _campaign(tmp_path, kind="tracking", method="keyframe", extra="  frames: [10]\n")[1]()


def test_a_comma_separated_init_transform_is_read(tmp_path):
    """numpy.savetxt(delimiter=",") rows were refused as "expected 16 numbers (a 4x4 matrix)
    or JSON with T_target_source", of a file that held them."""
    from spacepose.errors import FileFormatError
    from spacepose.tools.register_io import read_transform

    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    path = tmp_path / "init.csv"
    np.savetxt(path, T, delimiter=",")
    np.testing.assert_allclose(read_transform(path), T)
    path.write_text("1,0,0,0\n0,1,0,0\n0,0,1,0\n")
    with pytest.raises(FileFormatError, match=r"init\.csv: expected 16 numbers \(a 4x4 matrix\)"):
        read_transform(path)


def _plane(n: int = 300) -> np.ndarray:
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.5, 0.5, (n, 3))
    points[:, 2] = 0.2 * points[:, 0] ** 2 + 0.1 * points[:, 1] ** 2
    return points


@pytest.mark.parametrize(
    ("matrix", "problem"),
    [
        (
            [[1e-4, 1e-4, 0], [0, 1e-4, 0], [0, 0, 1e-4]],
            "matrix 0 of 300 is not symmetric (C[0, 1] 0.0001, C[1, 0] 0): no covariance",
        ),
        (
            [[1e-4, 2e-4, 0], [2e-4, 1e-4, 0], [0, 0, 1e-4]],
            "matrix 0 of 300 is not positive semidefinite (its smallest eigenvalue is -0.0001): "
            "no covariance",
        ),
    ],
    ids=["not-symmetric", "not-positive-semidefinite"],
)
def test_gicp_covariances_that_are_none_are_refused(matrix, problem):
    """Registered without a word: a lopsided matrix, or one of a negative variance."""
    from spacepose.core.gicp import gicp

    points = _plane()
    covariances = np.tile(np.asarray(matrix), (len(points), 1, 1))
    with pytest.raises(InputError) as info:
        gicp(points, points, source_covariances=covariances)
    assert str(info.value) == f"source_covariances: {problem}"
    from spacepose.core.gicp_covariances import compute_covariances

    fine = compute_covariances(points)
    assert gicp(points, points, source_covariances=fine).fitness == 1.0


def test_kabsch_pairs_whose_squares_overflow_are_refused():
    """Points of 1e200 ended in numpy's LinAlgError "SVD did not converge"."""
    from spacepose.core.registration import kabsch

    points = _plane(6)
    with pytest.raises(InputError) as info:
        kabsch(points * 1e200, points)
    assert str(info.value).startswith("kabsch: the source points reach |coordinate| ")
    assert str(info.value).endswith(
        "beyond 3.12e+144: their squares overflow float64 (wrong units or a corrupt file?)"
    )
    turn = kabsch(points * 1e100, points * 1e100)[:3, :3]  # large, its squares finite
    np.testing.assert_allclose(turn, np.eye(3), atol=1e-9)
