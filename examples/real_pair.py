"""``spacepose register`` on small_gicp's real LiDAR pair, beside ``small_gicp.align``.

Run from the repository's root: ``.venv/bin/python examples/real_pair.py`` (small_gicp comes
with the ``peers`` extra; without it only our rows are printed). Each row: the error against
the pair's reference transform (small_gicp's test error, E = T_ref⁻¹ T_est) and the median
time of 7 calls, the contenders interleaved, on 2 threads, from the identity.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.tools.cloud_io import read_cloud
from spacepose.tools.register import RegisterConfig, register

PAIR = Path(__file__).resolve().parents[1] / "data" / "real" / "small_gicp"
REPEATS, THREADS = 7, 2


def main() -> None:
    source, target = read_cloud(PAIR / "source.ply"), read_cloud(PAIR / "target.ply")
    T_ref = np.loadtxt(PAIR / "T_target_source.txt")

    def ours(method: str) -> Callable[[], np.ndarray]:
        config = RegisterConfig(method=method)
        return lambda: (
            register(source, target, config=config, workers=THREADS).result.T_target_source
        )

    rows = {"spacepose gicp": ours("gicp"), "spacepose point_to_plane": ours("point_to_plane")}
    try:
        import small_gicp
    except ImportError:
        small_gicp = None
    if small_gicp is not None:

        def peer(kind: str) -> Callable[[], np.ndarray]:
            return lambda: (
                small_gicp.align(
                    target.points,
                    source.points,
                    registration_type=kind,
                    downsampling_resolution=0.25,
                    num_threads=THREADS,
                ).T_target_source
            )

        rows |= {"small_gicp GICP": peer("GICP"), "small_gicp PLANE_ICP": peer("PLANE_ICP")}
    times: dict[str, list[float]] = {name: [] for name in rows}
    results = {name: call() for name, call in rows.items()}  # warm-up (compilation)
    for _ in range(REPEATS):
        for name, call in rows.items():
            tic = time.perf_counter()
            results[name] = call()
            times[name].append(1e3 * (time.perf_counter() - tic))
    print("| method | error (mm) | error (deg) | median ms |")
    print("|---|---|---|---|")
    for name, T in results.items():
        E = se3.invert(T_ref) @ T
        degrees = np.degrees(Rotation.from_matrix(E[:3, :3]).magnitude())
        millimetres = 1e3 * np.linalg.norm(E[:3, 3])
        print(f"| {name} | {millimetres:.1f} | {degrees:.3f} | {np.median(times[name]):.1f} |")


if __name__ == "__main__":
    main()
