"""Bad inputs found by a fifth hostile round: each ends in one line naming the file and the
problem (or a warning naming it), never a traceback, a hang or a silently wrong result."""

from __future__ import annotations

import gc
import warnings
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.errors import FileFormatError, InputError
from spacepose.tools.cloud_io import read_cloud
from spacepose.tools.depth_io import write_depth_image
from spacepose.tools.register import register_files

INTRINSICS = "fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\n"


def _cli_error(capsys) -> str:
    """The CLI's stderr, checked to be one ``error:`` line without a traceback."""
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    assert err.startswith("error:"), err
    return err


def _refused(capsys, error: type, message: str, read, argv: list[str]) -> None:
    """``read()`` raises ``error`` with ``message``, and the CLI run ``argv`` ends in that one
    line."""
    with pytest.raises(error) as exc:
        read()
    assert str(exc.value) == message
    assert main(argv) == 1
    assert _cli_error(capsys) == f"error: {message}"


def _depth_pair(root: Path, intrinsics: str | None = INTRINSICS) -> tuple[Path, Path]:
    """Two 32 x 24 depth maps of a curved surface about 1.2 m away (seeded noise), and an
    intrinsics file beside them."""
    rng = np.random.default_rng(5)
    root.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[:24, :32]
    surface = 1.2 + 0.01 * xx + 0.005 * yy + 0.0004 * (xx - 16) ** 2 + 0.0006 * (yy - 12) ** 2
    paths = []
    for k in range(2):
        path = root / f"{k:06d}.png"
        write_depth_image(path, surface + 0.002 * k + rng.normal(scale=1e-4, size=surface.shape))
        paths.append(path)
    if intrinsics is not None:
        (root / "intrinsics.yaml").write_text(intrinsics)
    return paths[0], paths[1]


# -- register: --intrinsics beside a depth image's own file ---------------------------------------


def test_register_intrinsics_that_differ_from_the_images_own_are_refused(tmp_path, capsys):
    """--intrinsics given for a depth image with an intrinsics.yaml beside it won without a
    word (the image's own calibration ignored); depth folders refuse it, register now too."""
    source, target = _depth_pair(tmp_path / "depth")
    given = tmp_path / "given.yaml"
    given.write_text(INTRINSICS.replace("fx: 30", "fx: 40"))
    message = (
        f"{source.parent}: --intrinsics {given} and the folder's intrinsics.yaml differ "
        "(fx 40.0 vs 30.0): keep one (move intrinsics.yaml out, or leave out --intrinsics)"
    )
    argv = ["register", str(source), str(target), "--intrinsics", str(given)]
    _refused(
        capsys, InputError, message, lambda: register_files(source, target, intrinsics=given), argv
    )


# The pair's geometry (a shallow bowl seen by 768 pixels) is not the point: its degeneracy
# warning is left out.
@pytest.mark.filterwarnings("ignore::spacepose.errors.SpaceposeWarning")
def test_register_intrinsics_equal_to_the_images_own_are_accepted(tmp_path):
    """The same calibration given twice (here as JSON beside the folder's YAML) is no
    conflict."""
    source, target = _depth_pair(tmp_path / "depth")
    given = tmp_path / "given.json"
    given.write_text('{"fx": 30, "fy": 30, "cx": 15.5, "cy": 11.5}')
    outcome = register_files(source, target, intrinsics=given)
    assert outcome.n_source > 3
