"""Generated spacecraft: targets no estimator default was chosen on (methods.md §3).

``random:K`` names the spacecraft that seed ``K`` draws. Each is a box bus with what real
satellites carry, every size and place drawn:

* the bus, 1.0-2.5 m along each axis;
* none, one or two solar wings (probabilities 0.2, 0.4, 0.4) on booms from the ±y faces, each
  1.5-3.5 times the bus's longest side and 0.5-1.0 times its height, 3-5 cm thick, canted about
  its boom by up to 45°, its boom rooted anywhere in the middle half of the face;
* a dish on a mast rooted anywhere in the middle half of one of the four other faces
  (probability 0.6);
* one to three instruments: a box of 0.1-0.35 m at the end of a 0.2-0.8 m boom that leaves a
  face at a random point (within 80 % of its half sides), tilted up to 40° off its normal.

The draws make almost every spacecraft asymmetric, as a mesh of a real one is; a spacecraft
without wings, dish or instrument offsets would not be, and the draws give it no weight. The
rectangle catalogue lists the bus's six faces and both faces of each wing.
"""

from __future__ import annotations

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.sim.targets import (
    Rectangle,
    Target,
    assemble,
    box_part,
    box_rectangles,
    cone_part,
    cylinder_part,
    rename_sheet_faces,
)
from spacepose.errors import ConfigError

PREFIX = "random:"


def generated_seed(name: str) -> int | None:
    """The seed ``K`` of a target named ``random:K``; None for any other name (a mesh file).

    Raises
    ------
    ConfigError
        A ``random:`` name whose seed is not a whole number ≥ 0.
    """
    if not name.startswith(PREFIX):
        return None
    text = name[len(PREFIX) :]
    if not (text.isascii() and text.isdigit()):
        raise ConfigError(f"target {name!r}: write random:K with K a whole number >= 0")
    return int(text)


def random_spacecraft(seed: int) -> Target:
    """The spacecraft ``random:seed`` (module docstring), model frame at the bus centre, metres.

    The same seed gives the same spacecraft on any machine.
    """
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ConfigError(f"a generated spacecraft's seed must be a whole number >= 0: {seed!r}")
    rng = np.random.default_rng(int(seed))
    bus = rng.uniform(1.0, 2.5, 3)
    parts = [box_part(bus, (0.0, 0.0, 0.0))]
    rects = box_rectangles("bus", bus, np.eye(4))
    wings = int(rng.choice(3, p=(0.2, 0.4, 0.4)))
    sides = [float(rng.choice((-1.0, 1.0)))] if wings == 1 else [1.0, -1.0][:wings]
    for i, side in enumerate(sides):
        _add_wing(rng, bus, side, f"wing{i}", parts, rects)
    if rng.random() < 0.6:
        _add_dish(rng, bus, parts)
    for _ in range(int(rng.integers(1, 4))):
        _add_instrument(rng, bus, parts)
    return assemble(f"{PREFIX}{seed}", parts, rename_sheet_faces(rects))


def _add_wing(
    rng: np.random.Generator,
    bus: NDArray[np.float64],
    side: float,
    name: str,
    parts: list[trimesh.Trimesh],
    rects: list[Rectangle],
) -> None:
    """A wing on a boom from the bus's ``side`` y face (+1 or −1), its long side along y."""
    length = rng.uniform(1.5, 3.5) * bus.max()
    extents = (rng.uniform(0.5, 1.0) * bus[2], length, rng.uniform(0.03, 0.05))
    boom = rng.uniform(0.2, 1.0)
    # The boom's root off the face's centre, within its middle half.
    x, z = rng.uniform(-0.25, 0.25, 2) * bus[[0, 2]]
    root = np.array([x, side * bus[1] / 2, z])
    tip = root + side * boom * np.array([0.0, 1.0, 0.0])
    parts.append(cylinder_part(0.04, root, tip))
    R = Rotation.from_euler("y", rng.uniform(-45.0, 45.0), degrees=True).as_matrix()
    T = se3.make_transform(R, tip + side * length / 2 * np.array([0.0, 1.0, 0.0]))
    parts.append(box_part(extents, np.zeros(3)).apply_transform(T))
    rects += box_rectangles(name, extents, T, faces=("+z", "-z"))


def _face_point(
    rng: np.random.Generator, bus: NDArray[np.float64], axis: int, sign: float, spread: float
) -> NDArray[np.float64]:
    """A point on the bus face ``sign`` along ``axis``, within ``spread`` of its half sides."""
    point = rng.uniform(-spread, spread, 3) * bus / 2
    point[axis] = sign * bus[axis] / 2
    return point


def _add_dish(
    rng: np.random.Generator, bus: NDArray[np.float64], parts: list[trimesh.Trimesh]
) -> None:
    """A shallow cone (reflector) on a mast from the middle half of one of the ±x, ±z faces."""
    axis = int(rng.choice((0, 2)))
    sign = float(rng.choice((-1.0, 1.0)))
    normal = sign * np.eye(3)[axis]
    base = _face_point(rng, bus, axis, sign, 0.5)
    top = base + rng.uniform(0.1, 0.4) * normal
    radius = rng.uniform(0.2, 0.45) * min(bus[(axis + 1) % 3], bus[(axis + 2) % 3])
    parts.append(cylinder_part(0.03, base, top))
    parts.append(cone_part(radius, 0.3 * radius, top, normal))


def _add_instrument(
    rng: np.random.Generator, bus: NDArray[np.float64], parts: list[trimesh.Trimesh]
) -> None:
    """A box on a boom from a random point of a random face, tilted off the face's normal."""
    axis = int(rng.integers(3))
    sign = float(rng.choice((-1.0, 1.0)))
    normal = sign * np.eye(3)[axis]
    root = _face_point(rng, bus, axis, sign, 0.8)
    tilt = Rotation.from_rotvec(np.radians(rng.uniform(0.0, 40.0)) * _unit_normal_to(rng, normal))
    out = tilt.apply(normal)
    tip = root + rng.uniform(0.2, 0.8) * out
    size = rng.uniform(0.1, 0.35)
    parts.append(cylinder_part(0.03, root, tip))
    parts.append(box_part((size, size, size), tip + 0.5 * size * out))


def _unit_normal_to(rng: np.random.Generator, v: NDArray[np.float64]) -> NDArray[np.float64]:
    """A random unit vector perpendicular to the unit vector ``v``."""
    u = np.cross(v, rng.normal(size=3))
    return u / np.linalg.norm(u)
