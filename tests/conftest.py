"""Fixtures shared by the test files: seeded random data with known ground truth."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from spacepose.core import se3
from spacepose.core.trajectory import Trajectory


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh seeded generator per test, so tests do not depend on their order."""
    return np.random.default_rng(12345)


@pytest.fixture
def random_trajectory(rng: np.random.Generator) -> Trajectory:
    """20 random poses (rotations up to ~π, translations ~1 m) at 10 Hz from t = 1.7e9 s."""
    poses = np.stack([se3.exp(rng.normal(size=6)) for _ in range(20)])
    return Trajectory(1.7e9 + 0.1 * np.arange(20), poses)


@pytest.fixture
def bare_orbit_run() -> Callable[..., Path]:
    """Makes the smallest orbit run folder that ``read_run`` reads up to its truth.csv (its
    frame, model and truth files empty unless ``truth`` is given): ``make(root, truth=b"")``."""

    def make(root: Path, truth: bytes = b"") -> Path:
        (root / "frames").mkdir(parents=True)
        (root / "frames" / "000000.ply").write_bytes(b"")
        (root / "scenario.json").write_text(json.dumps({"scenario": "orbit"}))
        (root / "groundtruth.tum").write_text("0 0 0 0 0 0 0 1\n")
        (root / "model.ply").write_bytes(b"")
        (root / "model.obj").write_bytes(b"")
        (root / "truth.csv").write_bytes(truth)
        return root

    return make
