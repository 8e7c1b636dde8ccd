"""Target geometry for the simulator (methods.md §3): procedural satellites and rectangles (a
mesh file is read by :mod:`spacepose.core.sim.mesh_files`).

A :class:`Target` is one triangle mesh in its model frame (the target frame of every simulated
pose), plus the catalogue of its flat rectangular faces that rectangle-based pose estimation
(methods.md §2.2–2.3) recognises. The procedural targets are concatenations of trimesh primitives;
the primitives are kept so that surface samples hidden inside another part can be dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.errors import InputError

# Cylinders and cones: enough facets that the silhouette is round at the lab's 2.5 mm pixels,
# few enough that building the ray-casting BVH stays cheap.
_SECTIONS = 32


@dataclass(frozen=True)
class Rectangle:
    """A flat rectangular face of the target, in the model frame.

    Attributes
    ----------
    name
        Unique label, e.g. ``"bus+z"`` or ``"wing_front"``.
    center
        (3,) face centre in the model frame, metres.
    R_model_plane
        (3, 3) rotation of the plane frame P into the model frame; columns: x along the short
        side ``a``, y along the long side ``b``, z the outward normal (right-handed).
    a, b
        Full side lengths in metres, ``a <= b``.
    """

    name: str
    center: NDArray[np.float64]
    R_model_plane: NDArray[np.float64]
    a: float
    b: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form: ``{name, center, R_model_plane, a, b}`` with plain lists."""
        return {
            "name": self.name,
            "center": [float(v) for v in self.center],
            "R_model_plane": [[float(v) for v in row] for row in self.R_model_plane],
            "a": float(self.a),
            "b": float(self.b),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Rectangle:
        """Inverse of :meth:`to_dict`."""
        return cls(
            str(data["name"]),
            np.asarray(data["center"], dtype=np.float64),
            np.asarray(data["R_model_plane"], dtype=np.float64),
            float(data["a"]),
            float(data["b"]),
        )


@dataclass(frozen=True, eq=False)
class Target:
    """A target: its mesh in the model (target) frame and its rectangle catalogue.

    Attributes
    ----------
    name
        ``"lab"``, ``"orbit"``, ``"orbit-symmetric"`` or the mesh file's name.
    mesh
        The whole surface, one triangle mesh, model frame, metres.
    rectangles
        Flat rectangular faces (empty for a mesh file).
    parts
        The closed convex primitives the mesh was built from (empty for a mesh file); a surface
        sample inside another part is hidden and dropped by :func:`sample_surface`.
    """

    name: str
    mesh: trimesh.Trimesh
    rectangles: tuple[Rectangle, ...] = ()
    parts: tuple[trimesh.Trimesh, ...] = field(default=(), repr=False)


def box_rectangles(
    prefix: str, extents: ArrayLike, T_model_box: ArrayLike, faces: tuple[str, ...] | None = None
) -> list[Rectangle]:
    """The rectangle catalogue entries of a box's faces.

    Parameters
    ----------
    prefix
        Name prefix; a face is named ``prefix + axis`` such as ``"bus+x"``.
    extents
        (3,) full side lengths along the box's own x, y, z, metres.
    T_model_box
        (4, 4) pose of the box frame (centre, axes along the sides) in the model frame.
    faces
        Which faces to list (``"+x"``, ``"-z"`` ...); all six when omitted.
    """
    ext = np.asarray(extents, dtype=np.float64)
    T = np.asarray(T_model_box, dtype=np.float64)
    out = []
    for axis in range(3):
        for sign, label in ((1.0, "+"), (-1.0, "-")):
            key = f"{label}{'xyz'[axis]}"
            if faces is not None and key not in faces:
                continue
            others = [i for i in range(3) if i != axis]
            short, long_ = sorted(others, key=lambda i: (ext[i], i))
            z = sign * np.eye(3)[axis]
            y = np.eye(3)[long_]
            x = np.cross(y, z)  # right-handed by construction; x is ± the short axis
            R_box_plane = np.column_stack([x, y, z])
            out.append(
                Rectangle(
                    name=f"{prefix}{key}",
                    center=se3.transform_points(T, (0.5 * ext[axis] * z)[None])[0],
                    R_model_plane=T[:3, :3] @ R_box_plane,
                    a=float(ext[short]),
                    b=float(ext[long_]),
                )
            )
    return out


def box_part(extents: ArrayLike, center: ArrayLike) -> trimesh.Trimesh:
    """Box of full sides ``extents`` (3,) along the model axes, centred at ``center`` (3,)."""
    return trimesh.creation.box(extents=extents, transform=se3.make_transform(np.eye(3), center))


def cylinder_part(radius: float, p0: ArrayLike, p1: ArrayLike) -> trimesh.Trimesh:
    """Cylinder of ``radius`` from ``p0`` (3,) to ``p1`` (3,)."""
    return trimesh.creation.cylinder(radius=radius, segment=np.array([p0, p1]), sections=_SECTIONS)


def cone_part(radius: float, height: float, base: ArrayLike, axis: ArrayLike) -> trimesh.Trimesh:
    """Cone with its base disc centred at ``base`` and its apex at ``base + height * axis``."""
    R = Rotation.align_vectors([axis], [[0.0, 0.0, 1.0]])[0]
    return trimesh.creation.cone(
        radius=radius, height=height, sections=_SECTIONS, transform=se3.make_transform(R, base)
    )


def assemble(name: str, parts: list[trimesh.Trimesh], rectangles: list[Rectangle]) -> Target:
    """The target of closed convex ``parts`` (model frame) and its rectangle catalogue."""
    mesh = trimesh.util.concatenate(parts)
    return Target(name, mesh, tuple(rectangles), tuple(parts))


def lab_target() -> Target:
    """The lab mock-up of Li et al. (methods.md §3), model frame at the bus centre.

    Bus 0.20 × 0.16 × 0.16 m (x × y × z); two 0.30 × 0.12 m wings (5 mm thick) along ±x on booms
    of different lengths (60 and 30 mm); a 0.06 m radius dish on the +z face, off-centre; a nozzle
    on the −z face, off-centre. The unequal booms and the offsets make the pose unique.
    """
    bus = (0.20, 0.16, 0.16)
    wing = (0.30, 0.12, 0.005)
    parts = [box_part(bus, (0.0, 0.0, 0.0))]
    rects = box_rectangles("bus", bus, np.eye(4))
    for side, boom in ((1.0, 0.06), (-1.0, 0.03)):
        root = side * bus[0] / 2
        tip = side * (bus[0] / 2 + boom)
        parts.append(cylinder_part(0.006, (root, 0.0, 0.0), (tip, 0.0, 0.0)))
        centre = np.array([tip + side * wing[0] / 2, 0.0, 0.0])
        parts.append(box_part(wing, centre))
        label = "wing_right" if side > 0 else "wing_left"
        T = se3.make_transform(np.eye(3), centre)
        rects += box_rectangles(f"{label}", wing, T, faces=("+z", "-z"))
    # Dish: a shallow cone (reflector) on a short mast, off-centre so the +z face is not symmetric.
    mast_base, mast_top = (0.03, -0.02, bus[2] / 2), (0.03, -0.02, bus[2] / 2 + 0.03)
    parts.append(cylinder_part(0.008, mast_base, mast_top))
    parts.append(cone_part(0.06, 0.025, mast_top, (0.0, 0.0, 1.0)))
    # Nozzle: a cone opening away from the bus on the −z face, also off-centre.
    parts.append(cone_part(0.03, 0.05, (-0.04, 0.03, -bus[2] / 2 - 0.05), (0.0, 0.0, 1.0)))
    return assemble("lab", parts, rename_sheet_faces(rects))


def symmetric_orbit_target() -> Target:
    """The first orbit satellite: a box bus with one wing on its y axis; model frame = B'.

    Bus 2.4 × 1.8 × 1.4 m (x × y × z) centred at the B' origin (the nominal centre of mass), axes
    along the principal axes; one 6.0 × 2.0 m wing (4 cm thick) on a 0.5 m boom from the +y face,
    its long side along y and its faces normal to ±z. Kept as a test case of a symmetric target:
    a 180° turn about y maps the whole shape onto itself, and every rectangle has a twin of equal
    size (the opposite bus face, the wing's other face), so no range image can tell those two
    attitudes apart.
    """
    bus = (2.4, 1.8, 1.4)
    parts = [box_part(bus, (0.0, 0.0, 0.0))]
    rects = box_rectangles("bus", bus, np.eye(4))
    _add_wing(parts, rects, bus)
    return assemble("orbit-symmetric", parts, rename_sheet_faces(rects))


def orbit_target() -> Target:
    """The default orbit satellite (methods.md §3), asymmetric as real ones are; model frame = B'.

    The bus and wing of :func:`symmetric_orbit_target` (bus 2.4 × 1.8 × 1.4 m, one 6.0 × 2.0 m
    wing on a 0.5 m boom from +y, faces normal to ±z), plus:

    * an antenna panel 0.8 × 1.2 m (4 cm thick) on a 0.6 m mast from the −y face, its faces
      normal to ±x, its long side along z and its centre 0.5 m above the bus mid-plane;
    * an instrument: a 0.25 m cube at the end of a 0.8 m boom (4 cm radius) leaving the bus edge
      between +x and −y at z = −0.3 m, diagonally outwards.

    No rotation maps the shape onto itself, but rectangles of equal size remain: the opposite bus
    faces (2.4 × 1.8, 2.4 × 1.4, 1.8 × 1.4 m), the wing's two faces (2.0 × 6.0 m) and the
    panel's two faces (0.8 × 1.2 m). A rectangle's sides name its size class only; which face of
    the class it is, and the pose, follow from the other visible faces and parts
    (:mod:`spacepose.core.lost_in_space`).
    """
    bus = (2.4, 1.8, 1.4)
    parts = [box_part(bus, (0.0, 0.0, 0.0))]
    rects = box_rectangles("bus", bus, np.eye(4))
    _add_wing(parts, rects, bus)
    panel, mast = (0.04, 0.8, 1.2), 0.6
    root = -bus[1] / 2
    parts.append(cylinder_part(0.04, (0.0, root, 0.5), (0.0, root - mast, 0.5)))
    centre = np.array([0.0, root - mast - panel[1] / 2, 0.5])
    parts.append(box_part(panel, centre))
    rects += box_rectangles("antenna", panel, se3.make_transform(np.eye(3), centre), ("+x", "-x"))
    # The boom leaves from the bus edge (+x, −y), so that no face has a hole in its middle.
    root = np.array([bus[0] / 2, -bus[1] / 2, -0.3])
    out = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    tip = root + 0.8 * out
    parts.append(cylinder_part(0.04, root, tip))
    parts.append(box_part((0.25, 0.25, 0.25), tip + 0.125 * out))
    return assemble("orbit", parts, rename_sheet_faces(rects))


def _add_wing(parts: list[trimesh.Trimesh], rects: list[Rectangle], bus: tuple) -> None:
    """The 6.0 × 2.0 m wing on its 0.5 m boom from the bus's +y face (both wing faces listed)."""
    wing, boom = (2.0, 6.0, 0.04), 0.5
    root = bus[1] / 2
    parts.append(cylinder_part(0.05, (0.0, root, 0.0), (0.0, root + boom, 0.0)))
    centre = np.array([0.0, root + boom + wing[1] / 2, 0.0])
    parts.append(box_part(wing, centre))
    rects += box_rectangles("wing", wing, se3.make_transform(np.eye(3), centre), ("+z", "-z"))


def rename_sheet_faces(rects: list[Rectangle]) -> list[Rectangle]:
    """Wing and panel faces read better as ``..._front`` (+z, +x) and ``..._back`` (−z, −x)."""
    names = {"+z": "_front", "-z": "_back", "+x": "_front", "-x": "_back"}
    return [
        Rectangle(r.name[:-2] + names[r.name[-2:]], r.center, r.R_model_plane, r.a, r.b)
        if r.name.startswith(("wing", "antenna"))
        else r
        for r in rects
    ]


def sample_surface(target: Target, count: int, seed: int = 0) -> PointCloud:
    """Uniform samples of the target's visible surface, with outward normals, in the model frame.

    Parameters
    ----------
    target
        The target; samples falling inside another of its parts (a boom's end inside the bus)
        are dropped, so the count returned is at most ``count``.
    count
        Number of area-uniform samples drawn.
    seed
        Seed of the sampling.

    Returns
    -------
    PointCloud (M, 3) with the hit faces' normals.
    """
    if count < 1:
        raise InputError(f"surface sample count must be >= 1, got {count}")
    points, face = trimesh.sample.sample_surface(target.mesh, count, seed=seed)
    normals = target.mesh.face_normals[face]
    if len(target.parts) > 1:
        # Which part each face came from: parts were concatenated in order.
        part_of_face = np.repeat(np.arange(len(target.parts)), [len(p.faces) for p in target.parts])
        owner = part_of_face[face]
        hidden = np.zeros(len(points), dtype=bool)
        for j, part in enumerate(target.parts):
            hidden[owner != j] |= _depth_inside_convex(part, points[owner != j]) > 1e-6
        points, normals, face = points[~hidden], normals[~hidden], face[~hidden]
    # A sheet (a dish, a foil) is seen from both sides: its samples carry both normals, as a
    # closed part's two faces would, so that a model culled by its normals keeps it from behind.
    sheet = sheet_faces(target.mesh)[face]
    points = np.vstack([points, points[sheet]])
    normals = np.vstack([normals, -normals[sheet]])
    return PointCloud(points, normals, source=f"{target.name} surface samples")


def sheet_faces(mesh: trimesh.Trimesh) -> NDArray[np.bool_]:
    """(F,) True for the faces of the connected parts that do not close (an edge of theirs
    borders one face only, once coincident vertices are merged).

    A closed part with a crack (a mesh defect) counts as a sheet too, and is then seen from
    both sides; the shared meshes have none (the Hubble kit: no open part; satellite_panels:
    its dish alone, 352 of 33,626 faces).
    """
    merged = mesh.copy()
    merged.merge_vertices(merge_tex=True, merge_norm=True)
    border_edges = trimesh.grouping.group_rows(merged.edges_sorted, require_count=1)
    border_faces = merged.edges_face[border_edges]
    part = trimesh.graph.connected_component_labels(
        merged.face_adjacency, node_count=len(merged.faces)
    )
    return np.isin(part, part[border_faces])


def _depth_inside_convex(part: trimesh.Trimesh, points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Depth (M,) of points inside a closed convex mesh (−inf outside): min over face planes."""
    depth = np.full(len(points), -np.inf)
    # Only points in the part's bounding box can be inside; the plane test is (M, F) work.
    near = np.flatnonzero(np.all((points >= part.bounds[0]) & (points <= part.bounds[1]), axis=1))
    normals = part.face_normals
    offsets = np.einsum("fi,fi->f", normals, part.triangles[:, 0])
    depth[near] = (offsets[None, :] - points[near] @ normals.T).min(axis=1)
    return depth
