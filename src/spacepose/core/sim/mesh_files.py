"""Mesh files as simulator targets: read, checked, scaled and centred (methods.md §3.3).

trimesh reads the formats; what it lets through or reports in its own terms (a face on a vertex
the file does not hold, corners of NaN, triangles without area, a text file named .ply) is
named here, with the file, before anything is rendered.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import plyfile
import trimesh
from numpy.typing import NDArray

from spacepose.core.cloud import MAX_ABS_COORDINATE
from spacepose.core.ply_checks import read_checked_ply
from spacepose.core.sim.targets import Target, sheet_faces
from spacepose.core.structured_text import not_a_file, parse_problem
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off")


def load_mesh(path: str | Path, scale: float = 1.0, center: bool = True) -> Target:
    """Read a mesh file (OBJ/STL/PLY/GLB/OFF) as a target.

    Parameters
    ----------
    path
        Mesh file; a multi-part scene is flattened into one mesh.
    scale
        Factor applied to the file's coordinates (e.g. 0.001 for millimetres).
    center
        Move the bounding-box centre to the model-frame origin, so the target sits where the
        scenario puts the target frame.

    Raises
    ------
    FileFormatError
        Missing file, unknown extension, unreadable content, a vertex of NaN or inf, or no
        triangles (none at all, or none of non-zero area).
    InputError
        A scale that is not a positive finite number.
    """
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise FileFormatError(
            f"unknown mesh extension {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}", path
        )
    problem = not_a_file(path)
    if problem is not None:
        # A pipe or a device was "no such mesh file".
        raise FileFormatError(f"cannot read the mesh: {problem}", path)
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(f"mesh scale must be a positive number, got {scale}", path)
    try:
        # Unprocessed first: processing drops the faces on a NaN or inf vertex without a word
        # (a box with one such corner lost 4 of its 12 triangles; one of a single triangle was
        # "no triangles").
        raw = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files; report them alike
        problem = _obj_face_problem(path) or _not_ply(path) or _not_gltf(path)
        problem = problem or _off_problem(path) or _stl_problem(path) or _glb_problem(path)
        raise FileFormatError(problem or f"cannot read mesh: {exc}", path) from None
    if not isinstance(raw, trimesh.Trimesh) or len(raw.faces) == 0:
        # A binary STL whose header miscounts its triangles was "no triangles" too.
        raise FileFormatError(_stl_problem(path) or "the file holds no triangles", path)
    # trimesh reads an OBJ face on vertex 0 (OBJ counts from 1) as one on the last vertex: the
    # file loaded, with a wrong face, or was refused as "all triangles have zero area". An OFF
    # file miscounted was read by its counts: faces dropped or taken as vertices, no word.
    problem = _obj_face_problem(path) or _off_problem(path)
    if problem is not None:
        raise FileFormatError(problem, path)
    if path.suffix.lower() == ".ply":
        # trimesh read an ASCII PLY cut before its last faces, or a face list shorter or longer
        # than its count, as the faces it could make out, without a word.
        problem = _ply_index_problem(read_checked_ply(path))
        if problem is not None:
            raise FileFormatError(problem, path)
    faces, vertices = np.asarray(raw.faces), np.asarray(raw.vertices)
    # A face on a vertex the file does not hold ended in numpy's "index 8 is out of bounds for
    # axis 0 with size 4", naming neither the face nor the vertex count.
    outside = (faces < 0) | (faces >= len(vertices))
    if outside.any():
        k = int(np.flatnonzero(outside.any(axis=1))[0])
        raise FileFormatError(
            f"face {k + 1} of {len(faces)} refers to vertex index {faces[k][outside[k]][0]}, but "
            f"the file has {len(vertices)} vertices (indices 0 to {len(vertices) - 1})",
            path,
        )
    bad = np.count_nonzero(~np.isfinite(vertices[faces]).all(axis=(1, 2)))
    if bad:
        raise FileFormatError(
            f"{bad} of {len(faces)} triangles have a corner of NaN or inf coordinates, and "
            "would be left out",
            path,
        )
    peak = float(np.abs(vertices).max()) * scale
    if peak > MAX_ABS_COORDINATE:
        # Their areas and normals overflowed (numpy's bare warnings), and the error that
        # followed named a sampled cloud, not this file.
        raise FileFormatError(
            f"vertices reach |coordinate| {peak:.3g}, beyond {MAX_ABS_COORDINATE:.3g}: their "
            "squares overflow float64 (wrong units or a corrupt file?)",
            path,
        )
    if not _has_area(vertices[faces]):
        # Rendered, such a mesh failed at frame 0 as "the sensor sees nothing (target 1.23 m
        # away ...)", which sent the user to the range and the scale, not the file.
        raise FileFormatError(
            f"all {len(faces)} triangles have zero area: no surface to render", path
        )
    # Processed once, here: the file is read once.
    mesh = _wound_outward(trimesh.Trimesh(vertices * scale, faces, process=True), path)
    if center:
        mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return Target(path.stem, mesh)


def _wound_outward(mesh: trimesh.Trimesh, path: Path) -> trimesh.Trimesh:
    """``mesh`` with each closed part wound so that its normals point outwards (positive
    signed volume), with a warning naming ``path`` when any was not.

    A model is culled by its normals to the faces a sensor sees, so a part wound inwards (as
    trimesh's ``revolve`` builds a dish or a nozzle, and CAD exports often are) was culled
    where it faces the sensor: against such a mesh, runs had up to 36 ``ok`` frames 2-3° off
    at 3-39σ. Sheets (open parts) are seen from both sides anyway (``sample_surface``).
    """
    part = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    a, b, c = mesh.triangles.transpose(1, 0, 2)
    # Six times each part's signed volume, by the divergence theorem over its faces; a solid
    # only: closed, wound one way throughout, at least a tetrahedron's four faces (a face
    # given twice, as some exports close a sheet, has no inside).
    volume = np.bincount(part, weights=np.einsum("ij,ij->i", a, np.cross(b, c)))
    solid = _wound_one_way(mesh.faces) & ~sheet_faces(mesh)
    solid &= np.bincount(part)[part] >= 4
    solid &= np.bincount(part, weights=solid)[part] == np.bincount(part)[part]
    inward = solid & (volume[part] < 0.0)
    if not inward.any():
        return mesh
    faces = mesh.faces.copy()
    faces[inward] = faces[inward][:, ::-1]
    warnings.warn(
        SpaceposeWarning(
            f"{len(np.unique(part[inward]))} closed part(s) wound inwards ({inward.sum()} of "
            f"{len(faces)} faces): turned outwards, as a sensor sees them",
            path,
        ),
        stacklevel=3,
    )
    return trimesh.Trimesh(mesh.vertices, faces, process=False)


def _wound_one_way(faces: NDArray[np.int64]) -> NDArray[np.bool_]:
    """(F,) True for the faces (F, 3) each of whose edges is crossed once in each direction,
    by it and by one other face: the faces of a closed, consistently wound surface."""
    n = int(faces.max()) + 1
    start, end = faces.ravel(), np.roll(faces, -1, axis=1).ravel()
    keys, counts = np.unique(start * n + end, return_counts=True)
    once = counts[np.searchsorted(keys, start * n + end)] == 1
    reverse = np.searchsorted(keys, end * n + start)
    reversed_once = (reverse < len(keys)) & (
        keys[np.minimum(reverse, len(keys) - 1)] == end * n + start
    )
    reversed_once &= counts[np.minimum(reverse, len(keys) - 1)] == 1
    return (once & reversed_once).reshape(-1, 3).all(axis=1)


def _has_area(triangles: NDArray[np.float64]) -> bool:
    """Whether any of the (F, 3, 3) triangles has an area, beyond rounding, for its size: a
    sliver of corners on one line has a cross product of rounding error, not exactly zero."""
    edges = triangles[:, 1:] - triangles[:, :1]
    # Scaled by the largest coordinate difference: squares of 1e200 would overflow.
    size = np.abs(edges).max(axis=(1, 2))
    unit = edges / np.where(size > 0, size, 1.0)[:, None, None]
    doubled = np.linalg.norm(np.cross(unit[:, 0], unit[:, 1]), axis=1)
    return bool(np.any((size > 0) & (doubled > 1e-12)))


def _ply_index_problem(ply: plyfile.PlyData) -> str | None:
    """The first face of a PLY whose vertex indices, stored as floats, are no whole numbers
    (trimesh cut 3.5 to vertex 3 without a word), or None."""
    if "face" not in ply:
        return None
    for prop in ply["face"].properties:
        if prop.name not in ("vertex_indices", "vertex_index") or not hasattr(prop, "len_dtype"):
            continue
        if np.dtype(prop.val_dtype).kind != "f":
            continue
        for k, row in enumerate(ply["face"].data[prop.name], start=1):
            split = row[row != np.floor(row)]
            if split.size:
                return f"face {k} lists vertex index {split[0]:g}: an index is a whole number"
    return None


def _not_ply(path: Path) -> str | None:
    """Why a .ply file is no PLY at all (trimesh said "list index out of range" of a text file
    so named), or None."""
    if path.suffix.lower() != ".ply":
        return None
    try:
        with path.open("rb") as fh:
            head = fh.read(4)
    except OSError:
        return None  # unreadable: trimesh's own error stands, as for an OBJ
    if head.rstrip(b"\r\n") == b"ply":
        return None
    return f"not a PLY file: it begins with {head!r}, not the line 'ply'"


def _not_gltf(path: Path) -> str | None:
    """Why a .gltf file is not glTF's JSON (trimesh said "cannot read mesh: model.gltf" of a
    text that is not JSON, or "'list' object has no attribute 'get'" of a JSON array), or None."""
    if path.suffix.lower() != ".gltf":
        return None
    try:
        text = path.read_bytes()
    except OSError:
        return None  # unreadable: trimesh's own error stands
    try:
        document = json.loads(text.decode("utf-8"))
    except UnicodeDecodeError:
        return "not valid glTF JSON: not UTF-8 text (a binary .glb named .gltf?)"
    except json.JSONDecodeError as exc:
        return f"not valid glTF JSON: {parse_problem(exc)}"
    except RecursionError:
        return "not valid glTF JSON: nested too deep"
    if not isinstance(document, dict):
        kind = "an array" if isinstance(document, list) else "a single value"
        return f"not valid glTF JSON: it holds {kind}, not glTF's object of 'asset', 'meshes', ..."
    return None


def _size_and_head(path: Path, suffix: str, count: int) -> tuple[int, bytes] | None:
    """The file's size and first ``count`` bytes when its suffix is ``suffix``; None otherwise,
    or when it cannot be read (the reader's own error then stands)."""
    if path.suffix.lower() != suffix:
        return None
    try:
        with path.open("rb") as fh:
            return path.stat().st_size, fh.read(count)
    except OSError:
        return None


def _glb_problem(path: Path) -> str | None:
    """Why a .glb file is no whole binary glTF, or None: trimesh said "Unterminated string" of
    one cut short (its JSON chunk read past the end), "not enough values to unpack" of a bare
    header."""
    opened = _size_and_head(path, ".glb", 12)
    if opened is None:
        return None
    size, head = opened
    if not head:
        return "the file is empty"
    if head[:4] != b"glTF":
        return f"not a binary glTF: it begins with {head[:4]!r}, not b'glTF' (a .gltf's JSON?)"
    if len(head) < 12:
        return f"a .glb of {size} bytes, shorter than its 12-byte header"
    length = int.from_bytes(head[8:12], "little")
    if length != size:
        return f"its header says {length:,} bytes, the file holds {size:,}: a cut or damaged .glb"
    return None


def _off_problem(path: Path) -> str | None:
    """Why an OFF file's body does not hold what its counts say, in words, or None.

    trimesh read it by its counts: a face line beyond them was dropped, one short of them (or
    of a vertex) taken from the next section (a face read as a vertex), a face listing fewer
    corners than its count read as the corners it lists.
    """
    if path.suffix.lower() != ".off":
        return None
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return None  # unreadable: trimesh's own error stands
    lines = [fields for line in text.splitlines() if (fields := line.split("#")[0].split())]
    if not lines or not lines[0][0].upper().endswith("OFF"):
        return None
    counts, rest = lines[0][1:], lines[1:]
    if not counts and rest:
        counts, rest = rest[0], rest[1:]
    try:
        vertices, faces = int(counts[0]), int(counts[1])
    except (IndexError, ValueError):
        return None  # no counts: trimesh's own error stands
    if len(rest) != vertices + faces:
        return (
            f"the header counts {vertices:,} vertices and {faces:,} faces, {vertices + faces:,} "
            f"lines, but {len(rest):,} follow it: a cut or miscounted OFF file"
        )
    for k, fields in enumerate(rest[:vertices], start=1):
        if len(fields) < 3:
            return f"vertex {k} has {len(fields)} coordinates, not 3"
    for k, fields in enumerate(rest[vertices:], start=1):
        corners = int(fields[0]) if fields[0].isdigit() else -1
        if not 0 <= corners <= len(fields) - 1:
            return f"face {k} counts {fields[0]} corners but lists {len(fields) - 1}"
    return None


def _stl_problem(path: Path) -> str | None:
    """Why a binary STL file does not hold the triangles its header counts, or None (trimesh
    called it "the file holds no triangles")."""
    opened = _size_and_head(path, ".stl", 84)
    if opened is None:
        return None
    size, head = opened
    if len(head) < 84:
        return (
            None
            if head.lstrip().lower().startswith(b"solid")
            else (f"a binary STL of {size} bytes, shorter than its 84-byte header")
        )
    count = int.from_bytes(head[80:84], "little")
    if size == 84 + 50 * count or head.lstrip().lower().startswith(b"solid"):
        return None  # as counted, or ASCII STL: trimesh's own error stands
    return (
        f"its header counts {count:,} triangles ({84 + 50 * count:,} bytes), but the file holds "
        f"{size:,} bytes: a cut or miscounted binary STL"
    )


def _obj_face_problem(path: Path) -> str | None:
    """The first statement of an OBJ file trimesh misreads, in words, or None: a face on a
    vertex the file does not hold (numpy's "index 9 is out of bounds for axis 0 with size 4"),
    a face of fewer than 3 corners (dropped without a word), a vertex of fewer than 3
    coordinates (numpy's AxisError traceback), or a byte-order mark before the first statement
    (that statement dropped: a vertex lost shifted every face onto the next vertex).
    """
    if path.suffix.lower() != ".obj":
        return None
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return None
    if lines and lines[0].startswith("\ufeff") and lines[0][1:].split()[:1] not in ([], ["#"]):
        return (
            f"line 1 begins with a byte-order mark, which hides its statement "
            f"({lines[0][1:].strip()[:40]!r}) from the OBJ reader: save the file without it"
        )
    vertices = faces = 0
    for number, line in enumerate(lines, start=1):
        fields = line.split()
        if fields and fields[0] == "v":
            vertices += 1
            if len(fields) < 4:
                return f"vertex {vertices} (line {number}) has {len(fields) - 1} coordinates, not 3"
        elif fields and fields[0] == "f":
            faces += 1
            if len(fields) < 4:
                return (
                    f"face {faces} (line {number}) has {len(fields) - 1} corners: a face has 3 "
                    "or more"
                )
            for corner in fields[1:]:
                try:
                    index = int(corner.split("/")[0])
                except ValueError:
                    continue
                # OBJ counts vertices from 1; a negative index counts back from the last so far.
                if not (1 <= index <= vertices or -vertices <= index <= -1):
                    return (
                        f"face {faces} (line {number}) refers to vertex {index}, but the file "
                        f"has {vertices} vertices before it (OBJ numbers them from 1)"
                    )
    return None
