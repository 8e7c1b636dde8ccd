"""Rectangle recognition from the distribution matrix of a plane's points (methods.md §2.2).

For an a×b rectangle (a <= b) sampled uniformly with isotropic noise σ, the distribution matrix has
eigenvalues ``(σ², a²/12 + σ², b²/12 + σ²)``, so the noise-corrected sides are
``a = √(12(λ_mid − σ²))`` and ``b = √(12(λ_max − σ²))``
(:func:`spacepose.core.rectangle_measurement.measure_rectangle`). A measured plane is matched to
a catalogue of the target's known rectangles by these sides.

A plane that is only part of a rectangle (occluded, or cut by the field of view) must not be
matched: its centroid is not the rectangle's centre, so it would bias the pose. These checks
reject such planes before the size match:

* the fourth-moment ratio ``E[u⁴] / E[u²]²`` along each side must be 1.8 (uniform on a segment;
  a disc or an ellipse gives 2.0, a triangle 2.4 along its height);
* the quantile extent along each side must agree with the side from the second moment (an
  L-shaped, occluded rectangle keeps its full extent but loses variance), and the centroid must
  sit at the middle of that extent (a hole or a band hidden off-centre, e.g. behind a boom or a
  panel, moves the centroid but not the extent);
* for a range camera with known focal length, the point count must be what a whole rectangle of
  the measured size gives at its range and incidence
  (:func:`spacepose.core.rectangle_measurement.fill_ratio`): a hidden part inside the outline
  lowers it;
* the two sides must differ by more than the side tolerance, since for a square the
  distribution matrix leaves the in-plane axes (hence the attitude) undetermined;
* the sides must match a catalogue entry (a rectangle cut straight is a smaller rectangle).
  Faces of equal size (a box's opposite faces, a panel's two sides, two equal wings) all match:
  :func:`candidates` lists them, and a predicted pose (or the lost-in-space start of
  :mod:`spacepose.core.navigation`) tells which one it is.

Before any of this a plane keeps only its dense connected region
(:func:`spacepose.core.rectangle_search.measure_planes`): the stray points a RANSAC slab collects
around the face would otherwise pull the distribution matrix.

All vectors are in the frame of the points (the sensor frame), in metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from spacepose.core import se3
from spacepose.core.config import (
    StageConfig,
    config_error,
    holds_text,
    refuse_boolean,
    square_stays_finite,
    stage_config,
)
from spacepose.core.rectangle_measurement import RectangleMeasurement, fill_ratio
from spacepose.core.se3 import real_array
from spacepose.errors import InputError

__all__ = [
    "UNIFORM_KURTOSIS",
    "CatalogueEntry",
    "RectangleConfig",
    "candidates",
    "catalogue_entries",
    "recognise",
    "rejection_reason",
    "side_tolerance",
]

# E[u⁴] / E[u²]² of a uniform distribution on a segment.
UNIFORM_KURTOSIS = 1.8


class CatalogueEntry(BaseModel):
    """A known rectangular face of the target.

    Attributes
    ----------
    name
        Unique name of the face.
    center
        (3,) centre of the rectangle in the model frame B' (m).
    R_model_plane
        (3, 3) rotation whose columns are, in the model frame, the short side (x), the long side
        (y) and the outward normal (z).
    a, b
        Full side lengths (m), ``0 < a <= b``.
    """

    # NaN and inf are refused as such ("a finite number"), not by the bounds they fail.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = Field(min_length=1)
    center: tuple[float, float, float]
    R_model_plane: tuple[
        tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]
    ]
    a: float = Field(gt=0)
    b: float = Field(gt=0)

    def __init__(self, /, **data: Any) -> None:
        # As a StageConfig: pydantic's multi-line ValidationError escaped from ``CatalogueEntry(
        # a=2, b=1, ...)`` (parse_catalogue validates a file's entries with model_validate).
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise config_error(type(self), exc) from None

    @field_validator("*", mode="before")
    @classmethod
    def _no_boolean_numbers(cls, value: object, info: ValidationInfo) -> object:
        value = refuse_boolean(cls, value, info)
        if info.field_name != "name" and holds_text(value):
            raise ValueError(f"{value!r} holds text where numbers go (write them unquoted)")
        return value

    @field_validator("R_model_plane")
    @classmethod
    def _rotation(cls, R: tuple) -> tuple:
        M = np.asarray(R, dtype=np.float64)
        if not np.all(np.isfinite(M)):
            raise ValueError("R_model_plane has non-finite entries")
        try:
            return tuple(tuple(row) for row in se3.typed_rotation(M, "R_model_plane").tolist())
        except InputError as exc:
            raise ValueError(exc.reason) from None

    @model_validator(mode="after")
    def _sides(self) -> CatalogueEntry:
        if self.a > self.b:
            raise ValueError(f"short side a = {self.a} exceeds long side b = {self.b}")
        return self

    @property
    def rotation(self) -> NDArray[np.float64]:
        """``R_model_plane`` as a (3, 3) float64 array."""
        return np.asarray(self.R_model_plane, dtype=np.float64)

    @property
    def centre(self) -> NDArray[np.float64]:
        """``center`` as a (3,) float64 array."""
        return np.asarray(self.center, dtype=np.float64)


class RectangleConfig(StageConfig):
    """Settings of rectangle recognition.

    Attributes
    ----------
    sigma
        Noise standard deviation of the points (m), removed from the eigenvalues.
    side_tolerance_abs, side_tolerance_rel
        A measured side s matches a catalogue side s₀ when
        ``|s − s₀| <= side_tolerance_abs + side_tolerance_rel · s₀``.
    sampling
        How the points were drawn. ``"grid"``: one range image (a sensor's pixel grid), whose
        moments scatter little, so the shape checks use the tolerances below as they are.
        ``"random"``: independent uniform points, whose moment ratios, extents and centroid
        scatter by about ``2.4/√N``, ``0.5 s/√N`` and ``0.29 s/√N`` (side s); 3 of these are
        added to the tolerances so that whole rectangles are not rejected by chance. The sides
        and the centre are then measured from the edges
        (:func:`~spacepose.core.rectangle_measurement.measure_rectangle`).
    support
        Measure only the plane's dense connected region
        (:func:`spacepose.core.plane_support.dense_support`), not every point of the RANSAC slab.
    kurtosis_tolerance
        Largest allowed ``|E[u⁴]/E[u²]² − 1.8|`` along either side (noise-corrected); a disc or
        an ellipse gives 2.0; hidden corners and bands move it by 0.1 and more (1.64 to 2.74
        on the occluded faces of the simulated orbit target).
    extent_tolerance
        Largest relative difference between the quantile extent of a side and the side from the
        second moment (an allowance of 3σ is added).
    max_centre_offset
        Largest distance between the centroid and the middle of the quantile extent, as a share
        of the side (an allowance of σ is added).
    focal_px
        Focal length (pixels) of the range camera that took the points, enabling the fill check;
        None for clouds that are not one camera image.
    min_fill
        Smallest :func:`fill_ratio` accepted when ``focal_px`` is set (dropped pixels lower it
        by their rate; whole faces of the simulated orbit target give 0.99–1.0).
    min_points
        Fewer points are not measured reliably and are rejected.
    max_thickness
        Largest noise-corrected out-of-plane spread ``√(λ_min − σ²)`` (m).
    """

    sigma: float = Field(0.0, ge=0)
    side_tolerance_abs: float = Field(0.01, ge=0)
    side_tolerance_rel: float = Field(0.05, ge=0)
    sampling: Literal["grid", "random"] = "grid"
    kurtosis_tolerance: float = Field(0.1, gt=0)
    extent_tolerance: float = Field(0.03, gt=0)
    max_centre_offset: float = Field(0.02, gt=0)
    focal_px: float | None = Field(None, gt=0)
    min_fill: float = Field(0.95, gt=0)
    min_points: int = Field(50, ge=3)
    max_thickness: float = Field(0.01, gt=0)
    support: bool = True

    # The noise's σ and the focal length are squared (a config file's 1e300 ended navigate in
    # an OverflowError traceback).
    _squares_finite = field_validator("sigma", "focal_px")(square_stays_finite)


def side_tolerance(side: float, config: RectangleConfig) -> float:
    """Allowed difference (m) between a measured and a catalogue side of length ``side``."""
    return config.side_tolerance_abs + config.side_tolerance_rel * side


def _shape_problem(m: RectangleMeasurement, config: RectangleConfig) -> str | None:
    """Why the points are not a whole uniform rectangle, or None."""
    if m.n_points < config.min_points:
        return f"{m.n_points} points, fewer than min_points = {config.min_points}"
    thickness = float(np.sqrt(max(m.eigenvalues[0] - m.sigma**2, 0.0)))
    if thickness > config.max_thickness:
        return f"out-of-plane spread {thickness:.4g} m exceeds max_thickness"
    if m.a <= 0:
        return "short side variance does not exceed the noise variance"
    if m.b - m.a < side_tolerance(m.b, config):
        # Equal in-plane eigenvalues leave the eigenvectors anywhere in the plane.
        return f"near-square ({m.a:.4g} x {m.b:.4g} m): the in-plane axes are undetermined"
    # Sampling scatter of independent points, per unit of the coefficients in the docstring.
    scatter = 3.0 / np.sqrt(m.n_points) if config.sampling == "random" else 0.0
    # NaN-safe: a NaN ratio fails the comparison and is rejected.
    if not np.all(
        np.abs(m.kurtosis - UNIFORM_KURTOSIS) <= config.kurtosis_tolerance + 2.4 * scatter
    ):
        k = ", ".join(f"{v:.3f}" for v in m.kurtosis)
        return f"fourth-moment ratios ({k}) are not those of a uniform rectangle (1.8)"
    sides = m.moment_sides
    allowed = (config.extent_tolerance + 0.5 * scatter) * sides + 3.0 * m.sigma
    if np.any(np.abs(m.extent - sides) > allowed):
        return (
            f"extents ({m.extent[0]:.4g}, {m.extent[1]:.4g}) m disagree with the sides "
            f"({sides[0]:.4g}, {sides[1]:.4g}) m: not a whole rectangle (occluded?)"
        )
    if config.focal_px is not None and fill_ratio(m, config.focal_px) < config.min_fill:
        return (
            f"{m.n_points} points are {fill_ratio(m, config.focal_px):.1%} of what a whole "
            f"{m.a:.4g} x {m.b:.4g} m rectangle gives the camera: part of it is hidden"
        )
    allowed = (config.max_centre_offset + 0.29 * scatter) * sides + m.sigma
    if np.any(np.abs(m.centre_offset) > allowed):
        return (
            f"centroid off the middle of the extent by ({m.centre_offset[0]:.3g}, "
            f"{m.centre_offset[1]:.3g}) m: part of the rectangle is hidden"
        )
    return None


def catalogue_entries(catalogue: Sequence[CatalogueEntry]) -> list[CatalogueEntry]:
    """The catalogue as a list of :class:`CatalogueEntry` (None, text or dicts ended in a
    TypeError or AttributeError)."""
    try:
        if isinstance(catalogue, str | bytes | dict):
            raise TypeError
        entries = list(catalogue)
    except TypeError:
        raise InputError(
            f"the catalogue must be a list of CatalogueEntry, got {type(catalogue).__name__}"
        ) from None
    wrong = [e for e in entries if not isinstance(e, CatalogueEntry)]
    if wrong:
        raise InputError(
            f"the catalogue must be a list of CatalogueEntry, got a {type(wrong[0]).__name__} "
            "(tools.catalogue.parse_catalogue reads one from a file's data)"
        )
    return entries


def _checked(
    measurement: RectangleMeasurement,
    catalogue: Sequence[CatalogueEntry],
    config: RectangleConfig,
) -> tuple[list[CatalogueEntry], RectangleConfig]:
    """The catalogue as a list and the config, checked with the measurement (text, None or
    dicts ended in an AttributeError, or in None, "not recognised", without a word)."""
    if not isinstance(measurement, RectangleMeasurement):
        raise InputError(
            f"measurement must be a RectangleMeasurement (measure_rectangle), got "
            f"{type(measurement).__name__}"
        )
    return catalogue_entries(catalogue), stage_config(config, RectangleConfig)


def candidates(
    measurement: RectangleMeasurement,
    catalogue: Sequence[CatalogueEntry],
    config: RectangleConfig = RectangleConfig(),
) -> list[CatalogueEntry]:
    """Catalogue entries the measurement may be, best size match first.

    Empty when a shape check fails (not a whole uniform rectangle) or no entry has both sides
    within :func:`side_tolerance`. Several entries come back for faces of equal size, such as
    the opposite faces of a box.
    """
    catalogue, config = _checked(measurement, catalogue, config)
    if _shape_problem(measurement, config) is not None:
        return []
    scored = []
    for entry in catalogue:
        da = abs(measurement.a - entry.a) / side_tolerance(entry.a, config)
        db = abs(measurement.b - entry.b) / side_tolerance(entry.b, config)
        if da <= 1.0 and db <= 1.0:
            scored.append((max(da, db), entry))
    return [entry for _, entry in sorted(scored, key=lambda item: item[0])]


def _decide(
    m: RectangleMeasurement,
    catalogue: Sequence[CatalogueEntry],
    config: RectangleConfig,
    predicted_R_sensor_model: ArrayLike | None,
) -> tuple[CatalogueEntry | None, str | None]:
    """The recognised entry, or None and the reason."""
    catalogue, config = _checked(m, catalogue, config)
    if predicted_R_sensor_model is not None:
        R = real_array(predicted_R_sensor_model, "predicted_R_sensor_model")
        if R.shape != (3, 3) or not np.isfinite(R).all():
            raise InputError(
                f"predicted_R_sensor_model must be a finite 3x3 rotation, got shape {R.shape}"
            )
    problem = _shape_problem(m, config)
    if problem is not None:
        return None, problem
    found = candidates(m, catalogue, config)
    if not found:
        return None, (
            f"sides {m.a:.4g} x {m.b:.4g} m match no catalogue rectangle "
            "(a partial rectangle, or an unknown face)"
        )
    if len(found) == 1:
        return found[0], None
    if predicted_R_sensor_model is None:
        names = ", ".join(e.name for e in found)
        return None, f"sides match several rectangles ({names}); a predicted attitude is needed"
    # The visible face's outward normal points at the sensor, as the measured normal does.
    R_pred = np.asarray(predicted_R_sensor_model, dtype=np.float64)
    alignment = [float(m.normal @ (R_pred @ e.rotation[:, 2])) for e in found]
    return found[int(np.argmax(alignment))], None


def rejection_reason(
    measurement: RectangleMeasurement,
    catalogue: Sequence[CatalogueEntry],
    config: RectangleConfig = RectangleConfig(),
    predicted_R_sensor_model: ArrayLike | None = None,
) -> str | None:
    """Why ``measurement`` is not recognised (see :func:`recognise`), or None if it is."""
    return _decide(measurement, catalogue, config, predicted_R_sensor_model)[1]


def recognise(
    measurement: RectangleMeasurement,
    catalogue: Sequence[CatalogueEntry],
    config: RectangleConfig = RectangleConfig(),
    predicted_R_sensor_model: ArrayLike | None = None,
) -> str | None:
    """Name of the catalogue rectangle the measurement is, or None.

    Parameters
    ----------
    measurement
        From :func:`~spacepose.core.rectangle_measurement.measure_rectangle`.
    catalogue
        The target's known rectangles.
    config
        Tolerances of the shape checks and the size match.
    predicted_R_sensor_model
        Optional (3, 3) predicted target attitude. Faces of equal size (opposite faces of a box,
        the two faces of a panel) are told apart only with it: the entry whose predicted outward
        normal is nearest the measured normal (which faces the sensor) wins. Without it such a
        measurement is ambiguous and None is returned.

    Returns
    -------
    The entry's name; None for a partial or non-rectangular plane, unknown sizes, or an
    ambiguity no prediction resolves.
    """
    entry = _decide(measurement, catalogue, config, predicted_R_sensor_model)[0]
    return None if entry is None else entry.name
