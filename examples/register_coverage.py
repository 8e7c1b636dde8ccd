"""How well ``spacepose register``'s covariance covers its error, on pairs with a known transform.

Run from the repository's root: ``.venv/bin/python examples/register_coverage.py``. Each pair is
two views of a mesh from a camera 3 sizes away (each view: 5,000 points of the side the camera
sees, moved along their rays by Gaussian range noise), the source moved by a seeded transform
(3° and 2 % of the size per axis, 1 σ). Each row: per axis, the RMS over the seeds of the error
over σ (1 for a σ that fits), and the share of pairs within 3σ on every axis, for the
registration's information form alone and for the covariance ``register`` reports.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.tools.register import RegisterConfig, register

MODELS = Path(__file__).resolve().parents[1] / "data" / "models"
SEEDS = 20
# (mesh, size m, range noise m, method)
CASES = [
    ("satellite_panels", 2.0, 0.0005, "gicp"),
    ("satellite_panels", 2.0, 0.005, "gicp"),
    ("hubble_model_kit", 2.0, 0.01, "gicp"),
    ("hubble_model_kit", 0.5, 0.001, "gicp"),
    ("hubble_model_kit", 2.0, 0.01, "point_to_plane"),
]


def scaled_mesh(name: str, size: float) -> trimesh.Trimesh:
    """The mesh ``name`` of data/models, centred, its largest extent ``size`` (m)."""
    mesh = trimesh.load(MODELS / f"{name}.obj", force="mesh")
    mesh.apply_translation(-mesh.centroid)
    mesh.apply_scale(size / mesh.extents.max())
    return mesh


def noisy_view(mesh: trimesh.Trimesh, seed: int, noise: float) -> np.ndarray:
    """(5000, 3) points of the side of ``mesh`` a camera 3 sizes along -z sees, each moved
    along its ray by Gaussian noise of σ ``noise`` (m)."""
    points, faces = trimesh.sample.sample_surface(mesh, 20_000, seed=seed)
    camera = np.array([0.0, 0.0, -3.0 * mesh.extents.max()])
    points = points[np.einsum("ij,ij->i", mesh.face_normals[faces], camera - points) > 0][:5000]
    ray = (points - camera) / np.linalg.norm(points - camera, axis=1)[:, None]
    return points + np.random.default_rng(seed).normal(0.0, noise, (len(points), 1)) * ray


def squared_z(
    mesh: trimesh.Trimesh, noise: float, seeds: int, method: str = "gicp"
) -> tuple[np.ndarray, np.ndarray]:
    """(seeds, 6) squared error over σ per axis (rx ry rz tx ty tz) of each pair: with the
    information form alone, and with the reported covariance."""
    size = mesh.extents.max()
    information, reported = [], []
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        rotation = Rotation.from_rotvec(rng.normal(0.0, np.radians(3.0), 3)).as_matrix()
        T = se3.make_transform(rotation, rng.normal(0.0, 0.02 * size, 3))
        source = se3.transform_points(se3.invert(T), noisy_view(mesh, 2 * seed + 1, noise))
        config = RegisterConfig(method=method)
        out = register(source, noisy_view(mesh, 2 * seed, noise), config=config, workers=2)
        d = se3.log(out.result.T_target_source @ se3.invert(T))
        own = out.result.covariance(sigma=1.0 if method == "gicp" else None)
        information.append(d**2 / np.diag(own))
        reported.append(d**2 / np.diag(out.covariance))
    return np.array(information), np.array(reported)


def main() -> None:
    print(
        "| target | size m | noise mm | method | covariance | RMS error/σ rx ry rz tx ty tz "
        "| within 3σ |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, size, noise, method in CASES:
        z2s = squared_z(scaled_mesh(name, size), noise, SEEDS, method)
        for label, z2 in zip(("information", "reported"), z2s, strict=True):
            rms = " ".join(f"{v:.2f}" for v in np.sqrt(z2.mean(axis=0)))
            within = np.mean(np.all(z2 < 9.0, axis=1))
            print(
                f"| {name} | {size} | {1e3 * noise:g} | {method} | {label} | {rms} "
                f"| {100 * within:.0f} % |"
            )


if __name__ == "__main__":
    main()
