"""Closed least-squares B-spline through the boundary interpolants (Dierckx, FITPACK ``percur``).

Smoothing follows the paper's rule (its eq. 9), ``s = λ · Σ(y - ȳ)² / |y|``, scaled for the number
of interpolants: FITPACK's ``s`` bounds the *sum* of squared residuals over the m interpolants,
so we use ``s = λ · m · var`` with ``var = Σ_i |y_i - ȳ|² / m`` (both coordinates). λ is then
the allowed mean squared residual as a fraction of the boundary's variance: independent of the
number of depths sampled and of the embedding's scale. λ = 0 interpolates; λ ≥ 1 allows the
constant spline, so useful values are small (the pipeline's default is 0.002). FITPACK spends
the whole budget, so on clean data the loop shrinks by about √λ × its RMS radius.

``variance="local"`` reads the paper's variance as the jaggedness of the interpolants instead
("the larger the discontinuity of values the greater allowance for fitting error"): ``var`` is
a robust variance of each interpolant's offset, across the loop, from a moving average of its
neighbours. Then λ = 1 is Dierckx's own recommendation ``s ≈ m σ²`` for independent noise of
variance σ², and the fit neither shrinks clean boundaries nor depends on the cloud's density;
interleaved multi-depth interpolants are correlated along the loop and λ ≈ 2 suits them.
"""

from __future__ import annotations

import functools
import logging
import warnings
from typing import NamedTuple

import numpy as np
import shapely
from scipy.interpolate import splev, splprep
from sklearn.base import BaseEstimator

from .errors import FitError, InvalidInputError, NotFittedError, ReconstructionWarning
from .meshing import next_rows, previous_rows, sample_ring, signed_area

log = logging.getLogger(__name__)

MIN_INTERPOLANTS = 8
#: A spline that crosses itself is repaired to its largest loop (kinks where λ is small for the
#: noise) unless that loop holds less than this share of the area it winds round: then the
#: interpolants outline no one region (a depth deeper than the cloud is wide: 2,500 of a
#: washer chart's 2,800 points at depth 50, its largest loop 3 % of the chart), and the repair
#: would cut the chart down. Every chart of the five awkward 22k atlases at depths 1-5 and
#: λ 0.3-3: 682 crossing splines, largest loop 99.7 % or more; at depth 20, 35-100 %.
MIN_LOOP_SHARE = 0.9
#: Window of the circular moving average whose chord lengths parameterise the interpolants.
_PARAMETER_WINDOW = 5


class BoundarySpline(BaseEstimator):
    """Closed cubic B-spline least-squares fit of an ordered loop of 2D interpolants.

    Parameters
    ----------
    lam : λ ≥ 0, allowed mean squared residual as a fraction of the interpolants' variance.
    n_samples : points of ``polygon_``; None gives max(64, 4 × number of interpolants).
    degree : spline degree (1..5), cubic by default.
    variance : "global" (spread about the centroid, the paper's rule) or "local" (jaggedness).

    Fitted: ``tck_`` (knots, coefficients, degree), ``u_ (m + 1,)`` parameters of the closed
    interpolants, ``smoothing_`` the s given to FITPACK, ``residual_`` RMS residual (units of
    the input), ``n_knots_``, ``polygon_ (p, 2)`` closed (first == last), ``length_``,
    ``is_simple_``. If the spline crosses itself (λ too small for the noise), ``polygon_`` is
    repaired to its largest loop (the largest face between its crossings) with a
    `ReconstructionWarning` and ``is_simple_`` is False; a spline that collapses (λ too large)
    raises `FitError`. Orientation follows the interpolants' order.
    """

    def __init__(
        self,
        lam: float = 0.002,
        n_samples: int | None = None,
        degree: int = 3,
        variance: str = "global",
    ):
        self.lam = lam
        self.n_samples = n_samples
        self.degree = degree
        self.variance = variance

    def fit(self, points) -> BoundarySpline:
        """points : (m, 2) float interpolants in loop order (first point not repeated), or
        their `spline_input` (a caller fitting them with several λ keeps it)."""
        if not (np.isfinite(self.lam) and self.lam >= 0):
            raise InvalidInputError(f"lam must be a finite number >= 0, got {self.lam}")
        if int(self.degree) != self.degree or not 1 <= self.degree <= 5:
            raise InvalidInputError(f"degree must be a whole number in 1..5, got {self.degree}")
        if self.n_samples is not None and not (int(self.n_samples) == self.n_samples >= 8):
            raise InvalidInputError(f"n_samples must be a whole number >= 8, got {self.n_samples}")
        if self.variance not in ("global", "local"):
            raise InvalidInputError(f"variance must be 'global' or 'local', got {self.variance!r}")
        given = points if isinstance(points, SplineInput) else spline_input(points)
        loop, u, spread = given.loop, given.u, given.spread
        m = len(loop)
        variance = spread if self.variance == "global" else given.scatter
        smoothing = self.lam * m * variance
        # A fresh closed copy: splprep(per=1) ignores (and may overwrite) the last point.
        closed = np.vstack([loop, loop[:1]]).T.copy()
        try:
            (tck, u_out), fp, ier, msg = splprep(
                closed, u=u, s=smoothing, k=int(self.degree), per=1, full_output=1, quiet=1
            )
        except ValueError as exc:
            raise FitError(f"boundary spline fit failed: {exc}") from exc
        if ier > 0:
            raise FitError(f"boundary spline fit failed (FITPACK ier={ier}): {msg}")
        raw = _evaluate(tck, self.n_samples or max(64, 4 * m))
        raw = np.vstack([raw, raw[:1]])
        is_simple = bool(shapely.LinearRing(raw).is_simple)
        polygon, share = (raw, 1.0) if is_simple else _largest_loop(raw)
        if polygon is None or abs(signed_area(polygon)) <= 1e-9 * spread:
            raise FitError(
                f"boundary spline collapsed to a curve without area: lam={self.lam} "
                "is too large, use a smaller --lam"
            )
        if share < MIN_LOOP_SHARE:
            raise FitError(
                f"boundary spline crosses itself all over (lam={self.lam}): its largest loop "
                f"holds {share:.0%} of the area it winds round, the interpolants outline no "
                "one region; use a smaller --depth or a larger --lam"
            )
        if not is_simple:
            warnings.warn(
                f"boundary spline crosses itself (lam={self.lam}): kept its largest loop; "
                "a larger --lam gives a smoother boundary",
                ReconstructionWarning,
                stacklevel=2,
            )
        self.tck_ = tck
        self.u_ = np.asarray(u_out)
        self.smoothing_ = float(smoothing)
        self.residual_ = float(np.sqrt(max(fp, 0.0) / m))
        self.n_knots_ = len(tck[0])
        self.is_simple_ = is_simple
        self.polygon_ = polygon
        self.length_ = float(np.sum(np.hypot(*np.diff(self.polygon_, axis=0).T)))
        self.__dict__.pop("region_", None)  # of the last fit's polygon
        log.debug(
            "spline: %d interpolants, s=%.3g, %d knots, RMS residual %.3g",
            m,
            smoothing,
            self.n_knots_,
            self.residual_,
        )
        return self

    def evaluate(self, n: int) -> np.ndarray:
        """(n, 2) points at n parameters evenly spaced over one period (no repeated end)."""
        self._check_fitted()
        if int(n) != n or n < 1:
            raise InvalidInputError(f"n must be a whole number >= 1, got {n}")
        return _evaluate(self.tck_, int(n))

    def sample_by_spacing(self, spacing: float) -> np.ndarray:
        """(q, 2) points along ``polygon_`` about ``spacing`` apart in arc length (q >= 3)."""
        self._check_fitted()
        if not (np.isfinite(spacing) and spacing > 0):
            raise InvalidInputError(f"spacing must be a positive number, got {spacing}")
        return sample_ring(self.polygon_, spacing)

    @functools.cached_property
    def region_(self) -> shapely.Polygon:
        """``polygon_`` as a prepared shapely polygon, made when first asked (`contains`; a
        re-mesh asks none)."""
        region = shapely.Polygon(self.polygon_)
        shapely.prepare(region)
        return region

    def contains(self, points) -> np.ndarray:
        """(n,) bool: which of ``points (n, 2)`` lie strictly inside ``polygon_``."""
        self._check_fitted()
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return shapely.contains_xy(self.region_, points[:, 0], points[:, 1])

    def _check_fitted(self) -> None:
        if not hasattr(self, "tck_"):
            raise NotFittedError("fit() the boundary spline first")


class SplineInput(NamedTuple):
    """What a spline fit takes from its interpolants whatever λ: the checked ``loop`` (m, 2),
    its chord parameters ``u`` (m + 1,), and its variance by the global rule (``spread``) and
    by the local one (``scatter``)."""

    loop: np.ndarray
    u: np.ndarray
    spread: float
    scatter: float


def spline_input(points) -> SplineInput:
    """The `SplineInput` of interpolants ``points`` (m, 2) in loop order: re-meshing with a new
    λ fits the same interpolants again (0.6 ms of a chart's 8 ms re-mesh)."""
    loop = _check_interpolants(points)
    spread = float(np.sum((loop - loop.mean(axis=0)) ** 2) / len(loop))
    u = np.append(_chord_parameter(loop), 1.0)
    for kept in (loop, u):  # shared by every fit of them (a fitted spline's ``u_`` is ``u``)
        kept.setflags(write=False)
    return SplineInput(loop, u, spread, _normal_scatter(loop))


def _evaluate(tck, n: int) -> np.ndarray:
    x, y = splev(np.linspace(0.0, 1.0, n, endpoint=False), tck)
    return np.column_stack([x, y])


def _check_interpolants(points) -> np.ndarray:
    """(m, 2) float64 loop without consecutive (or first/last) duplicates."""
    try:
        loop = np.array(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"interpolants are not numeric: {exc}") from exc
    if loop.ndim != 2 or loop.shape[1] != 2:
        raise InvalidInputError(f"expected interpolants of shape (m, 2), got {loop.shape}")
    if not np.isfinite(loop).all():
        raise InvalidInputError("the boundary interpolants have NaN or infinite coordinates")
    if len(loop):
        moved = np.any(loop != next_rows(loop), axis=1)
        loop = loop[moved] if moved.any() else loop[:1]
    distinct = len(np.unique(loop, axis=0)) if len(loop) else 0
    if distinct < MIN_INTERPOLANTS:
        raise InvalidInputError(
            f"{distinct} distinct boundary interpolants; the spline needs {MIN_INTERPOLANTS}"
        )
    return loop


def _chord_parameter(loop: np.ndarray) -> np.ndarray:
    """(m,) parameters in [0, 1): normalised chord length along a circular moving average of the
    loop, so that points interleaved from several depths advance by their progress along the
    boundary rather than by their zigzag between depths."""
    smooth = _moving_average(loop, min(_PARAMETER_WINDOW, len(loop)))
    chord = np.hypot(*(next_rows(smooth) - smooth).T)
    chord = np.maximum(chord, 1e-9 * max(chord.sum(), 1e-300))
    arc = np.concatenate([[0.0], np.cumsum(chord)])
    return arc[:-1] / arc[-1]


def _normal_scatter(loop: np.ndarray) -> float:
    """Robust variance (input units²) of the interpolants about their circular moving average,
    across the loop: the jaggedness of the boundary samples, not the boundary's size."""
    w = min(_PARAMETER_WINDOW, len(loop))
    mean = _moving_average(loop, w)
    tangent = next_rows(mean) - previous_rows(mean)
    rel = loop - mean
    offset = (tangent[:, 0] * rel[:, 1] - tangent[:, 1] * rel[:, 0]) / np.maximum(
        np.hypot(tangent[:, 0], tangent[:, 1]), 1e-300
    )
    # median(d²) = 0.455 var(d) for normal d; for i.i.d. offsets var(d) = σ² (1 - 1/w).
    return float(np.median(offset**2) / 0.455 * w / (w - 1))


def _moving_average(loop: np.ndarray, w: int) -> np.ndarray:
    """Circular moving average of the (m, 2) ``loop`` over ``w`` <= m rows: the mean of the
    loop rolled by −w // 2, ..., as slices of it thrice (np.roll's overhead was a tenth of a
    chart's re-mesh)."""
    m, shifts = len(loop), np.arange(w) - w // 2
    thrice = np.concatenate([loop, loop, loop])
    return np.mean([thrice[m - s:2 * m - s] for s in shifts], axis=0)


def _largest_loop(polygon: np.ndarray) -> tuple[np.ndarray | None, float]:
    """The largest face of a self-crossing closed ``polygon`` (p, 2), cut at its crossings
    (shapely's node and polygonize: the same loops as ``make_valid``, 20x faster), closed, with
    the original orientation and starting at the vertex nearest the polygon's start (None if no
    face has an area), and its share of the faces' area."""
    pieces = shapely.get_parts(shapely.node(shapely.LineString(polygon)))
    faces = shapely.get_parts(shapely.polygonize(pieces))
    areas = shapely.area(faces)
    if len(faces) == 0 or areas.max() <= 0:
        return None, 0.0
    largest = int(np.argmax(areas))
    ring = np.asarray(faces[largest].exterior.coords)
    if np.sign(signed_area(ring)) != np.sign(signed_area(polygon)):
        ring = ring[::-1]
    start = int(np.argmin(np.sum((ring[:-1] - polygon[0]) ** 2, axis=1)))
    return np.vstack([ring[start:-1], ring[:start + 1]]), float(areas[largest] / areas.sum())
