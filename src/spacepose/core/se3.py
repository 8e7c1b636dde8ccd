"""Rigid transforms on SE(3), built on :class:`scipy.spatial.transform.Rotation`.

Conventions (methods.md §0)
------------------------
* ``T_a_b`` is a 4×4 float64 matrix mapping coordinates in frame b into frame a.
* A twist ``xi`` is a 6-vector ``(omega, v)``: rotation first, then translation, the same order
  as every 6×6 information matrix and covariance in the package.
* Perturbations are applied on the left: ``T ← exp(delta) @ T``, so ``delta`` is expressed in
  the frame the transform maps into.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.errors import InputError

_SMALL_ANGLE = 1e-8
_I3 = np.eye(3)
# Rotation angle beyond which log() takes scipy's route (the axis is ill-conditioned there).
NEAR_PI = np.pi - 0.1
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_ONES3 = np.ones(3)


def check_real(values: object, name: str, source: str | None = None) -> None:
    """Refuse an array of complex numbers, booleans or text where real numbers go: numpy casts
    them to float64 silently (a complex one with only a warning, dropping its imaginary parts),
    so a mask or a wrong array passed by mistake became coordinates."""
    if isinstance(values, list | tuple):
        # A list's items too: float64 reads "1" and True as numbers.
        try:
            values = np.asarray(values)
        except (TypeError, ValueError):  # ragged: the conversion to float64 says so
            return
    kind = values.dtype.kind if isinstance(values, np.ndarray | np.generic) else None
    if kind == "O" and any(isinstance(v, _NOT_NUMBERS) for v in np.ravel(values)):
        kind = "U"
    if kind in _NOT_REAL:
        raise InputError(f"{name} must be real numbers, got an array of {_NOT_REAL[kind]}", source)


_NOT_REAL = {
    "c": "complex numbers",
    "b": "booleans",
    "U": "text",
    "S": "bytes",
    "M": "dates",
    "m": "time spans",
}
_NOT_NUMBERS = (str, bytes, bool, np.bool_)


def whole_number(value: object, name: str, minimum: int = 1) -> int:
    """``value`` as an int: a whole number (Python or numpy integer, not a yes/no) of at least
    ``minimum``, or the package's error naming it."""
    whole = isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)
    if not whole or value < minimum:
        raise InputError(f"{name} must be a whole number >= {minimum}, got {value!r}")
    return int(value)


def real_number(value: object, name: str) -> float:
    """``value`` as a finite float (not text, not a yes/no), or the package's error naming it
    (``float`` reads "2.0" and True as numbers)."""
    if isinstance(value, str | bytes | bool | np.bool_):
        raise InputError(f"{name} must be a number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r:.60}") from None
    if not math.isfinite(number):
        raise InputError(f"{name} must be finite, got {number}")
    return number


def real_array(values: ArrayLike, name: str) -> NDArray[np.float64]:
    """``values`` as a float64 array; text, complex numbers or booleans are an InputError
    (numpy's ValueError named neither, and :func:`check_real`)."""
    check_real(values, name)
    if isinstance(values, str | bytes | bool):  # numpy reads "0.5" as 0.5 and True as 1
        raise InputError(f"{name} must be numbers, got {values!r:.60}")
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be numbers, got {values!r:.60}") from None


def as_transform(T: ArrayLike, name: str = "transform") -> NDArray[np.float64]:
    """Validate and return ``T`` as a 4×4 float64 homogeneous transform.

    Raises
    ------
    InputError
        If the shape is not 4×4, an entry is not finite, the last row is not (0, 0, 0, 1) or the
        rotation block is not orthonormal with determinant +1 (tolerance 1e-6).
    """
    check_real(T, name)
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a 4x4 matrix of numbers, got {T!r:.60}") from None
    if T.shape != (4, 4):
        raise InputError(f"{name} must be a 4x4 matrix, got shape {T.shape}")
    return _rigid(T, name)


def _rigid(T: NDArray[np.float64], name: str) -> NDArray[np.float64]:
    """``T`` (4, 4) itself once it is finite and rigid (tolerances of :func:`as_transform`)."""
    if not np.isfinite(T).all():
        raise InputError(f"{name} has non-finite entries")
    # Plain max-abs tests: np.allclose costs ~10 µs a call, and every registration and pose
    # graph validates its transforms.
    if np.abs(T[3] - _LAST_ROW).max() > 1e-9:
        raise InputError(f"{name} last row must be (0, 0, 0, 1), got {T[3]}")
    R = T[:3, :3]
    off = np.abs(R.T @ R - _I3).max()
    if off > 1e-6 or np.linalg.det(R) < 0:
        # How far it is says which: a scale or shear, a reflection, or digits cut too short.
        raise InputError(
            f"{name} rotation block is not a proper rotation (RᵀR off the identity by "
            f"{off:.2g}, det {np.linalg.det(R):.4g}; a rotation has 0 and 1)"
        )
    return T


def non_rigid(T: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(N,) which of the finite (N, 4, 4) transforms are not rigid, to the tolerances of
    :func:`as_transform`: a rotation block off orthonormal by more than 1e-6 or reflected, or a
    last row other than (0, 0, 0, 1)."""
    R = T[:, :3, :3]
    ortho_err = np.abs(np.einsum("nji,njk->nik", R, R) - _I3).max(axis=(1, 2))
    return (
        (ortho_err > 1e-6)
        | (np.linalg.det(R) < 0)
        | (np.abs(T[:, 3] - _LAST_ROW).max(axis=1) > 1e-9)
    )


def make_transform(R: ArrayLike | Rotation, t: ArrayLike) -> NDArray[np.float64]:
    """Build ``T`` (4×4) from a rotation (3×3 matrix or ``Rotation``) and a translation (3,).

    Raises
    ------
    InputError
        ``R`` is not 3×3 (a 4×4 transform, a stack of rotations) or ``t`` is not 3 numbers.
    """
    R = R.as_matrix() if isinstance(R, Rotation) else real_array(R, "make_transform: R")
    t = real_array(t, "make_transform: t")
    if R.shape != (3, 3):
        raise InputError(f"make_transform: R must be a 3x3 rotation matrix, got shape {R.shape}")
    if t.size != 3:
        raise InputError(f"make_transform: t must be 3 numbers (x, y, z), got shape {t.shape}")
    if not np.isfinite(R).all() or not np.isfinite(t).all():
        raise InputError("make_transform: R and t must be finite numbers")
    _check_rotation(R, "make_transform: R")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t.reshape(3)
    return T


def _check_rotation(R: NDArray[np.float64], name: str) -> None:
    """Refuse a finite 3×3 ``R`` that is not a proper rotation (a scale, a shear, a reflection)
    to :func:`as_transform`'s tolerances (RᵀR off the identity by at most 1e-6, det > 0), in
    plain floats: :func:`log` runs for every edge of every pose-graph iteration."""
    a, b, c, d, e, f, g, h, i = R.ravel().tolist()
    # The entries of RᵀR: the columns' dot products.
    off = max(
        abs(a * a + d * d + g * g - 1.0),
        abs(b * b + e * e + h * h - 1.0),
        abs(c * c + f * f + i * i - 1.0),
        abs(a * b + d * e + g * h),
        abs(a * c + d * f + g * i),
        abs(b * c + e * f + h * i),
    )
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if off > 1e-6 or det < 0.0:
        raise InputError(
            f"{name} is not a proper rotation (RᵀR off the identity by {off:.2g}, det "
            f"{det:.4g}; a rotation has 0 and 1): a scale, a shear or a reflection"
        )


# A rotation typed by hand (five decimals) is off a rotation by about 1e-5; this much is 0.006°,
# under a star tracker's error.
TYPED_ROTATION_TOLERANCE = 1e-4


def typed_rotation(R: ArrayLike, name: str) -> NDArray[np.float64]:
    """The proper rotation nearest a 3×3 ``R`` written with a few decimals (R_O_C, a
    catalogue's R_model_plane): RᵀR within ``TYPED_ROTATION_TOLERANCE`` of the identity and
    det > 0, made orthonormal by SVD. Five decimals were refused as "not a rotation".

    Raises
    ------
    InputError
        Not 3×3, not finite, or further off a rotation (the message gives how far).
    """
    M = real_array(R, name)
    if M.shape != (3, 3) or not np.all(np.isfinite(M)):
        raise InputError(f"{name} must be a finite 3x3 rotation matrix, got shape {M.shape}")
    off = float(np.abs(M.T @ M - np.eye(3)).max())
    det = float(np.linalg.det(M))
    if off > TYPED_ROTATION_TOLERANCE or det <= 0.0:
        raise InputError(
            f"{name} is not a proper rotation: RᵀR off the identity by {off:.2g} (at most "
            f"{TYPED_ROTATION_TOLERANCE:g}), det {det:.4g} (a rotation has 1)"
        )
    U, _, Vt = np.linalg.svd(M)
    return U @ Vt


def invert(T: ArrayLike) -> NDArray[np.float64]:
    """Inverse of a rigid transform, or of a stack (..., 4, 4), without a general inverse.

    Raises
    ------
    InputError
        ``T`` is not (..., 4, 4) (a 3×3 rotation ended in numpy's IndexError), or not rigid
        (a scaled matrix's "inverse" undid a quarter of it, without a word); a single ``T``
        not finite either (a stack's NaN members, missing poses, stay NaN).
    """
    T = real_array(T, "invert: T")
    if T.shape[-2:] != (4, 4):
        raise InputError(f"invert needs a 4x4 transform (or a stack of them), got shape {T.shape}")
    if T.ndim == 2:
        _rigid(T, "invert: T")
    else:
        # A stack may hold missing poses (NaN); those it has must be rigid.
        flat = T.reshape(-1, 4, 4)
        known = np.isfinite(flat).all(axis=(1, 2))
        bad = np.flatnonzero(known)[non_rigid(flat[known])]
        if len(bad):
            raise InputError(
                f"invert: transform {int(bad[0])} of {len(flat)} is not rigid (a scale, a shear, "
                "a reflection or a last row other than (0, 0, 0, 1))"
            )
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def compose(*transforms: ArrayLike) -> NDArray[np.float64]:
    """Product ``T1 @ T2 @ ...`` of rigid transforms (``compose(T_a_b, T_b_c) = T_a_c``).

    Raises
    ------
    InputError
        A transform is not 4×4 (numpy's matmul error named neither which nor why), not finite
        or not rigid.
    """
    out = np.eye(4)
    for k, T in enumerate(transforms):
        T = real_array(T, f"compose: transform {k}")
        if T.shape != (4, 4):
            raise InputError(f"compose: transform {k} must be 4x4, got shape {T.shape}")
        out = out @ _rigid(T, f"compose: transform {k}")
    return out


def transform_points(T_a_b: ArrayLike, points_b: ArrayLike) -> NDArray[np.float64]:
    """Map points (N, 3) given in frame b into frame a.

    Raises
    ------
    InputError
        ``T_a_b`` is not 4×4 (a 3×3 rotation was taken as a transform whose translation was
        its third column), not finite or not rigid, or the points are not (..., 3).
    """
    T_a_b, points_b = _pair(T_a_b, points_b, "points")
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def rotate_vectors(T_a_b: ArrayLike, vectors_b: ArrayLike) -> NDArray[np.float64]:
    """Rotate direction vectors (N, 3), e.g. normals, from frame b into frame a (``T_a_b``
    4×4, as :func:`transform_points`)."""
    T_a_b, vectors_b = _pair(T_a_b, vectors_b, "vectors")
    return vectors_b @ T_a_b[:3, :3].T


def _pair(
    T: ArrayLike, rows: ArrayLike, name: str
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A 4×4 transform and (..., 3) rows as float64 arrays; shape errors as InputError (numpy's
    matmul error named neither, and a 3×3 matrix passed silently)."""
    T = real_array(T, "T_a_b")
    rows = real_array(rows, name)
    if T.shape != (4, 4):
        raise InputError(f"T_a_b must be a 4x4 transform, got shape {T.shape}")
    if rows.ndim < 1 or rows.shape[-1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {rows.shape}")
    return _rigid(T, "T_a_b"), rows


def skew(v: ArrayLike) -> NDArray[np.float64]:
    """Cross-product matrices (..., 3) -> (..., 3, 3), with ``skew(a) @ b = a × b``."""
    v = real_array(v, "skew: v")
    if v.ndim < 1 or v.shape[-1] != 3:
        raise InputError(f"skew needs vectors of 3 numbers (..., 3), got shape {v.shape}")
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _left_jacobian_so3(omega: NDArray[np.float64]) -> NDArray[np.float64]:
    """Left Jacobian V of SO(3), so that ``exp((omega, v))`` has translation ``V @ v``."""
    theta = float(np.linalg.norm(omega))
    W = skew(omega)
    if theta < _SMALL_ANGLE:
        return np.eye(3) + 0.5 * W
    a = (1.0 - np.cos(theta)) / theta**2
    b = (theta - np.sin(theta)) / theta**3
    return np.eye(3) + a * W + b * (W @ W)


def exp(xi: ArrayLike) -> NDArray[np.float64]:
    """Exponential map: twist ``(omega, v)`` (6,) -> transform (4, 4).

    Raises
    ------
    InputError
        ``xi`` is not 6 numbers, or holds NaN or inf (a NaN transform was returned).
    """
    check_real(xi, "a twist")
    try:
        xi = np.asarray(xi, dtype=np.float64).reshape(6)
    except (TypeError, ValueError):
        raise InputError(f"a twist must be 6 numbers (omega, v), got {xi!r:.60}") from None
    omega, v = xi[:3], xi[3:]
    theta2 = omega @ omega
    # |omega|² and the sum of v are finite unless an entry is NaN or inf (or |omega| beyond
    # 1e154): two comparisons where np.isfinite costs ~1 µs, and ICP calls this every iteration.
    if not (theta2 < math.inf and abs(v @ _ONES3) < math.inf):
        if not np.isfinite(xi).all():
            raise InputError(f"exp: the twist has non-finite entries (NaN or inf), got {xi}")
        if not theta2 < math.inf:
            raise InputError(f"exp: the twist's rotation |omega|² overflows float64, got {xi}")
    theta = math.sqrt(theta2)
    wx, wy, wz = omega
    W = np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    W2 = W @ W
    # Rodrigues, R = I + sin θ/θ W + (1 − cos θ)/θ² W² (as 2 sin²(θ/2)/θ², no cancellation),
    # and the left Jacobian V = I + (1 − cos θ)/θ² W + (θ − sin θ)/θ³ W², written out: scipy's
    # Rotation costs ~15 µs a call and ICP and the pose graphs call this every iteration.
    if theta < _SMALL_ANGLE:
        a, b, c = 1.0, 0.5, 1.0 / 6.0
    else:
        a = math.sin(theta) / theta
        b = 2.0 * (math.sin(0.5 * theta) / theta) ** 2
        c = (theta - math.sin(theta)) / theta**3
    T = np.eye(4)
    T[:3, :3] = _I3 + a * W + b * W2
    T[:3, 3] = v + b * (W @ v) + c * (W2 @ v)
    return T


def log(T: ArrayLike) -> NDArray[np.float64]:
    """Logarithm map: transform (4, 4) -> twist ``(omega, v)`` (6,). Inverse of :func:`exp`.

    Raises
    ------
    InputError
        ``T`` is not 4×4, or holds NaN or inf (a NaN twist was returned).
    """
    T = real_array(T, "log: T")
    if T.shape != (4, 4):
        raise InputError(f"log needs a 4x4 transform, got shape {T.shape}")
    R = T[:3, :3]
    if np.isfinite(T).all():  # non-finite entries are refused below, with their own words
        _check_rotation(R, "log: T's rotation block")
        if T[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
            raise InputError(f"log: T's last row must be (0, 0, 0, 1), got {T[3]}")
    # 2 sin θ · axis from the skew part, cos θ from the trace; atan2 of the two is accurate at
    # every angle, unlike arccos near 0. Near π the skew part vanishes and the axis with it:
    # there scipy's quaternion route takes over. Written out because this runs for every edge
    # of every pose-graph iteration and scipy costs ~40 µs a call.
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin = 0.5 * math.sqrt(w @ w)
    cos = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    t = T[:3, 3]
    # NaN or inf anywhere in the top three rows leaves sin, cos or the sum of t non-finite (an
    # inf on the diagonal alone gave the zero twist): three comparisons here, np.isfinite
    # (~1 µs) only when one fails (or a square overflows).
    if not (sin < math.inf and abs(cos) < math.inf and abs(t @ _ONES3) < math.inf) and not (
        np.isfinite(T[:3]).all()
    ):
        raise InputError("log: the transform has non-finite entries (NaN or inf)")
    theta = math.atan2(sin, cos)
    if theta > NEAR_PI:
        omega = Rotation.from_matrix(R).as_rotvec()
    else:
        omega = 0.5 * w * (theta / sin if sin > 0.0 else 1.0)
    v = np.linalg.solve(_left_jacobian_so3(omega), t)
    return np.concatenate([omega, v])


def geodesic_mean(
    transforms: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    max_iterations: int = 50,
    tolerance: float = 1e-12,
) -> NDArray[np.float64]:
    """Weighted Karcher mean of rigid transforms on SE(3).

    Parameters
    ----------
    transforms
        Stack (M, 4, 4) of transforms mapping the same frames.
    weights
        Non-negative weights (M,), normalised internally; uniform when omitted.

    Returns
    -------
    The transform minimising the weighted sum of squared twist distances (Gauss-Newton on the
    left-perturbation tangent space, started at the chordal mean: independent of the order of
    ``transforms``; where the rotations spread so that several minima exist, the one nearest
    the chordal mean).
    """
    Ts = real_array(transforms, "geodesic_mean: transforms")
    if Ts.ndim != 3 or Ts.shape[1:] != (4, 4) or len(Ts) == 0:
        raise InputError(f"geodesic_mean needs a non-empty (M, 4, 4) stack, got {Ts.shape}")
    if not np.isfinite(Ts).all():
        raise InputError("geodesic_mean: the transforms have non-finite entries (NaN or inf)")
    bad = np.flatnonzero(non_rigid(Ts))
    if len(bad):
        # A scale or shear was averaged as if it were a turn: a non-rigid "mean" came back.
        raise InputError(f"geodesic_mean: transform {bad[0]} is not rigid (see as_transform)")
    max_iterations = whole_number(max_iterations, "geodesic_mean: max_iterations")
    # NaN never stops the iteration and a negative one never either: 50 steps for nothing.
    if real_number(tolerance, "geodesic_mean: tolerance") <= 0:
        raise InputError(f"geodesic_mean: tolerance must be positive, got {tolerance!r}")
    w = np.ones(len(Ts)) if weights is None else real_array(weights, "geodesic_mean weights")
    # A sum that overflows to inf made every normalised weight 0: the first transform came back.
    with np.errstate(over="ignore"):
        total = w.sum() if w.shape == (len(Ts),) else 0.0
    if not (np.all(np.isfinite(w)) and np.all(w >= 0) and 0 < total < math.inf):
        raise InputError(
            "geodesic_mean weights must be finite, non-negative, one per transform, not all 0"
        )
    w = w / w.sum()
    # Started at the chordal mean (scipy's Rotation.mean; the translations' mean), which no
    # order of the inputs changes: started at the first transform, turns of 0, +170 and -170°
    # about one axis came back as 0° (the sum of squared distances 57,800 deg², against 21,800
    # at ±120°), and as +120° listed 170, 0, -170.
    chordal = Rotation.from_matrix(Ts[:, :3, :3]).mean(weights=w)
    mean = make_transform(chordal, w @ Ts[:, :3, 3])
    for _ in range(max_iterations):
        mean_inv = invert(mean)
        step = sum(wi * log(T @ mean_inv) for wi, T in zip(w, Ts, strict=True))
        mean = exp(step) @ mean
        if float(np.dot(step, step)) < tolerance**2:
            break
    return mean


def adjoint(T: ArrayLike) -> NDArray[np.float64]:
    """6×6 adjoint of T for twists ordered ``(omega, v)``: ``exp(Ad_T xi) = T exp(xi) T⁻¹``.

    Raises
    ------
    InputError
        ``T`` is not 4×4 (a 3×3 rotation ended in numpy's IndexError), not finite or not
        rigid.
    """
    T = real_array(T, "adjoint: T")
    if T.shape != (4, 4):
        raise InputError(f"adjoint needs a 4x4 transform, got shape {T.shape}")
    R, t = _rigid(T, "adjoint: T")[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = skew(t) @ R
    return Ad
