"""Round 26 of bad inputs (navigation runs broken on purpose): a filter whose model does not
fit the data refuses what it sees, and says so."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from spacepose.core.nav_result import NavRow
from spacepose.errors import SpaceposeWarning
from spacepose.tools.navigation_reasons import warn_if_mostly_predicted


def _rows(updated: int, gated: int, idle: int) -> list[NavRow]:
    """A start, then frames that updated, frames whose rectangles the gate refused (a coarse
    pose was measured) and frames with nothing to update with."""
    coarse = np.eye(4)
    rows = [NavRow(0.0, None, None, 0, "init")]
    rows += [NavRow(1.0 + k, None, None, 1, "update") for k in range(updated)]
    rows += [NavRow(500.0 + k, None, None, 0, "predict", coarse) for k in range(gated)]
    rows += [NavRow(900.0 + k, None, None, 0, "predict") for k in range(idle)]
    return rows


@pytest.mark.parametrize(
    ("updated", "gated", "idle", "warned"),
    [
        (100, 78, 17, True),  # a mean motion twice the run's: 95 of 195 frames updated nothing
        (178, 0, 17, False),  # a sound orbit run: faces seen edge-on leave 9 % to prediction
        (120, 0, 73, True),  # a third of the frames without measurements
    ],
)
def test_a_filter_that_updates_on_few_frames_says_so(tmp_path, updated, gated, idle, warned):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_if_mostly_predicted(_rows(updated, gated, idle), tmp_path / "nav.csv")
    said = [str(w.message) for w in caught if issubclass(w.category, SpaceposeWarning)]
    assert bool(said) is warned
    if warned:
        assert f"{gated + idle} of {updated + gated + idle} frames" in said[0]
        assert f"({gated} of them with rectangles the gate refused)" in said[0]
