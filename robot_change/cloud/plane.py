"""The dominant plane (ALGORITHM.md section 1): a RANSAC fit over point triples with an adaptive
stop, optionally restricted to planes near a known up direction, refined on its inliers, and
its removal from a cloud.

Numeric module: arrays in, arrays out; no I/O, no logging, no global state.  The kernels are
numba-compiled (``cache=True, nogil=True``), single-threaded and without fastmath, so the NumPy
twins in ``tests/test_filters.py`` give identical results.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numba
import numpy as np

from robot_change import validate
from robot_change.cloud.geometry import check_points
from robot_change.errors import InputError

__all__ = [
    "Plane",
    "RANSAC_BAIL_SIGMAS",
    "RANSAC_SAMPLE",
    "fit_plane_ransac",
    "ransac_sample",
    "ransac_triples",
    "remove_plane",
]


# --------------------------------------------------------------------------------------------
# RANSAC plane


@dataclasses.dataclass(frozen=True, eq=False)
class Plane:
    """A plane ``normal . p + offset = 0`` (metres) and which points lie on it.

    ``normal``: (3,) float64 unit vector, oriented so that the camera origin is on its positive
    side (``offset >= 0``).  ``inliers``: (M,) bool over the points it was fitted to.
    ``n_inliers``: their number.  When no plane was found: ``normal`` and ``offset`` are NaN,
    no inliers (``found`` is False).  ``iterations``: sample triples tried.
    """

    normal: np.ndarray
    offset: float
    inliers: np.ndarray
    n_inliers: int
    iterations: int = 0

    @property
    def found(self) -> bool:
        return self.n_inliers > 0

    @classmethod
    def none(cls, n_points: int, iterations: int = 0) -> Plane:
        """The result when no plane qualifies."""
        return cls(np.full(3, np.nan), math.nan, np.zeros(n_points, dtype=bool), 0, iterations)

    def distances(self, points: np.ndarray) -> np.ndarray:
        """(N,) float64 signed distances of (N, 3) points to the plane, metres."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.normal + self.offset


#: Points per block when counting plane inliers: a branch-free inner loop the compiler can
#: vectorise, with the "cannot win any more" test between blocks.
_RANSAC_BLOCK = 256

#: Points on which RANSAC scores its hypotheses (preemptive RANSAC): with 4096 the inlier
#: fraction of a hypothesis is known to within about 0.7 % (one standard deviation at 30 %),
#: far finer than the margin between a floor and the next largest plane, and scoring costs
#: 4096 instead of M point tests per triple.  Only the winner is counted on every point.
RANSAC_SAMPLE = 4096


#: Bail-out of a hypothesis while it is scored: after each block it is dropped when its count
#: so far is more than this many standard deviations (plus one point) below what the best
#: plane's inlier fraction predicts for the points scored.  As the sample is in random order,
#: a plane at least as large as the best is dropped with probability below 0.2 %; a typical
#: hypothesis (a few % inliers against a floor's 25 %) is dropped after its first block.
RANSAC_BAIL_SIGMAS = 3.0


@functools.lru_cache(maxsize=8)
def _sample_order(size: int) -> np.ndarray:
    order = np.random.default_rng(0).permutation(size).astype(np.int64)
    order.setflags(write=False)
    return order


def ransac_sample(m: int, size: int = RANSAC_SAMPLE) -> np.ndarray:
    """(min(m, size),) int64 distinct rows on which :func:`fit_plane_ransac` scores hypotheses,
    in a fixed random order (any prefix is a random subset, which the bail-out relies on):
    evenly strided over ``0..m-1`` (``j * m // size``), all rows when ``m <= size``.  A voxel
    cloud is sorted by key, so the stride spreads the sample over space."""
    n = min(m, size)
    order = _sample_order(n)
    if m <= size:
        return order.copy()
    return order * m // size


@numba.njit(cache=True, nogil=True)
def _ransac_kernel(points, sample, triples, distance, up, cos_min, confidence, bail_sigmas):
    """Best plane over the given sample triples, scored on the sample rows.

    ``points`` (M, 3) float32; ``sample`` (S,) int64 rows on which a plane is scored;
    ``triples`` (T, 3) int64 row indices (into ``points``); ``up`` (3,) float64 unit vector or
    all zeros for no constraint; a plane counts only when ``|n . up| >= cos_min``.
    A triple whose cross product is below 1e-12 m^2 (repeated or collinear points) is skipped.
    The plane through the triple is ``n = normalize((p1 - p0) x (p2 - p0))``, ``d = -n . p0``
    (float64); a sample point is an inlier when ``|n . p + d| <= distance``.  The first triple
    with the strictly largest inlier count on the sample wins.  The sample is counted in blocks
    of ``_RANSAC_BLOCK``; after each, a triple stops being counted (and cannot win) when it can
    no longer beat the best count, or when its count is below the bail-out bound
    ``n w - RANSAC_BAIL_SIGMAS sqrt(n w (1 - w)) - 1`` for the ``n`` points counted and the
    best fraction ``w`` so far (:data:`RANSAC_BAIL_SIGMAS`).

    Adaptive stop: after triple t, stop once ``t + 1 >= log(1 - confidence) / log(1 - w**3)``
    with ``w`` = best count / S (the classic RANSAC bound; ``confidence >= 1`` never stops
    early).  Returns (triple index or -1, count on the sample, n (3,), d, triples tried).
    """
    m = sample.shape[0]
    xs = np.empty(m, dtype=np.float64)
    ys = np.empty(m, dtype=np.float64)
    zs = np.empty(m, dtype=np.float64)
    for i in range(m):
        r = sample[i]
        xs[i] = points[r, 0]
        ys[i] = points[r, 1]
        zs[i] = points[r, 2]
    use_up = up[0] != 0.0 or up[1] != 0.0 or up[2] != 0.0
    log_miss = math.log(1.0 - confidence) if confidence < 1.0 else -np.inf
    needed = np.inf
    best_t = -1
    best_count = 0
    best_n = np.zeros(3, dtype=np.float64)
    best_d = 0.0
    tried = 0
    for t in range(triples.shape[0]):
        tried = t + 1
        a = triples[t, 0]
        b = triples[t, 1]
        c = triples[t, 2]
        ax = np.float64(points[a, 0])
        ay = np.float64(points[a, 1])
        az = np.float64(points[a, 2])
        ux = np.float64(points[b, 0]) - ax
        uy = np.float64(points[b, 1]) - ay
        uz = np.float64(points[b, 2]) - az
        vx = np.float64(points[c, 0]) - ax
        vy = np.float64(points[c, 1]) - ay
        vz = np.float64(points[c, 2]) - az
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        norm = math.sqrt(nx * nx + ny * ny + nz * nz)
        if norm >= 1e-12 and not (
            use_up and abs(nx / norm * up[0] + ny / norm * up[1] + nz / norm * up[2]) < cos_min
        ):
            nx /= norm
            ny /= norm
            nz /= norm
            d = -(nx * ax + ny * ay + nz * az)
            count = 0
            start = 0
            while start < m:
                stop = min(m, start + _RANSAC_BLOCK)
                # slices index from 0, so the loop vectorises (no negative-index checks)
                bx = xs[start:stop]
                by = ys[start:stop]
                bz = zs[start:stop]
                block = 0
                for i in range(bx.shape[0]):
                    r = nx * bx[i] + ny * by[i] + nz * bz[i] + d
                    block += abs(r) <= distance
                count += block
                start = stop
                if count + (m - start) <= best_count:
                    count = -1
                    break  # cannot beat the best any more
                if best_count > 0:
                    w = best_count / m
                    expect = start * w
                    if count < expect - bail_sigmas * math.sqrt(expect * (1.0 - w)) - 1.0:
                        count = -1
                        break  # far below the best fraction: bail out
            if count > best_count:
                best_count = count
                best_t = t
                best_n[0] = nx
                best_n[1] = ny
                best_n[2] = nz
                best_d = d
                w3 = (best_count / m) ** 3
                if w3 >= 1.0:
                    needed = 0.0
                elif confidence < 1.0:
                    needed = log_miss / math.log(1.0 - w3)
        if tried >= needed:
            break
    return best_t, best_count, best_n, best_d, tried


@numba.njit(cache=True, nogil=True)
def _plane_inliers(points, normal, offset, distance):
    """(M,) bool ``|n . p + d| <= distance`` (float64, ``n0 x + n1 y + n2 z + d`` in that
    order) and the number of inliers."""
    m = points.shape[0]
    nx = normal[0]
    ny = normal[1]
    nz = normal[2]
    inliers = np.empty(m, dtype=np.bool_)
    count = 0
    for i in range(m):
        r = nx * np.float64(points[i, 0]) + ny * np.float64(points[i, 1]) + nz * np.float64(
            points[i, 2]) + offset
        ok = abs(r) <= distance
        inliers[i] = ok
        count += ok
    return inliers, count


@numba.njit(cache=True, nogil=True)
def _inlier_scatter(points, inliers, count):
    """Centroid (3,) and scatter matrix (3, 3) of the rows where ``inliers`` (``count`` of
    them, > 0): sums in row order, the centroid as sum / count, the scatter as the sums of the
    products of the centred coordinates (float64)."""
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for i in range(points.shape[0]):
        if inliers[i]:
            sx += np.float64(points[i, 0])
            sy += np.float64(points[i, 1])
            sz += np.float64(points[i, 2])
    cx = sx / count
    cy = sy / count
    cz = sz / count
    xx = 0.0
    xy = 0.0
    xz = 0.0
    yy = 0.0
    yz = 0.0
    zz = 0.0
    for i in range(points.shape[0]):
        if inliers[i]:
            dx = np.float64(points[i, 0]) - cx
            dy = np.float64(points[i, 1]) - cy
            dz = np.float64(points[i, 2]) - cz
            xx += dx * dx
            xy += dx * dy
            xz += dx * dz
            yy += dy * dy
            yz += dy * dz
            zz += dz * dz
    centroid = np.empty(3, dtype=np.float64)
    centroid[0] = cx
    centroid[1] = cy
    centroid[2] = cz
    scatter = np.empty((3, 3), dtype=np.float64)
    scatter[0, 0] = xx
    scatter[0, 1] = xy
    scatter[0, 2] = xz
    scatter[1, 0] = xy
    scatter[1, 1] = yy
    scatter[1, 2] = yz
    scatter[2, 0] = xz
    scatter[2, 1] = yz
    scatter[2, 2] = zz
    return centroid, scatter


def _check_up(up: object, max_tilt_deg: object) -> tuple[np.ndarray, float]:
    if up is None and max_tilt_deg is None:
        return np.zeros(3), 0.0
    if up is None or max_tilt_deg is None:
        raise InputError(
            f"up={up!r}, max_tilt_deg={max_tilt_deg!r}: give both (the camera-frame up vector "
            "and the largest angle between it and the plane normal) or neither"
        )
    vec = np.asarray(up, dtype=np.float64)
    norm = float(np.linalg.norm(vec)) if vec.shape == (3,) else 0.0
    if vec.shape != (3,) or not math.isfinite(norm) or norm == 0.0:
        raise InputError(
            f"up={up!r}: must be a non-zero finite 3-vector in the camera frame, e.g. (0, -1, 0) "
            "for a level camera (y points down)"
        )
    tilt = validate.number("fit_plane_ransac", "max_tilt_deg", max_tilt_deg, 0.0, 90.0,
                           unit=" degrees")
    return vec / norm, math.cos(math.radians(tilt))


def _orient(normal: np.ndarray, offset: float) -> tuple[np.ndarray, float]:
    """Flip so that the camera origin is on the positive side (offset >= 0)."""
    if offset < 0.0:
        return -normal, -offset
    return normal, offset


@functools.lru_cache(maxsize=8)
def _triple_uniforms(iterations: int, seed: int) -> np.ndarray:
    """(iterations, 3) float64 uniforms in [0, 1) from ``np.random.default_rng(seed)``, read-only
    and cached: a robot draws with the same seed every frame, only the cloud size changes."""
    u = np.random.default_rng(seed).random((iterations, 3))
    u.setflags(write=False)
    return u


@numba.njit(cache=True, nogil=True)
def _triples_kernel(u, m):
    """(T, 3) uniforms, m >= 3 -> (T, 3) int64 distinct rows: ``a = floor(u0 m)``, ``b`` and
    ``c`` drawn from the m - 1 and m - 2 rows left and shifted past the ones taken."""
    t = u.shape[0]
    out = np.empty((t, 3), dtype=np.int64)
    for i in range(t):
        a = min(np.int64(u[i, 0] * m), m - 1)
        b = min(np.int64(u[i, 1] * (m - 1)), m - 2)
        c = min(np.int64(u[i, 2] * (m - 2)), m - 3)
        b += b >= a
        lo = min(a, b)
        hi = max(a, b)
        c += c >= lo
        c += c >= hi
        out[i, 0] = a
        out[i, 1] = b
        out[i, 2] = c
    return out


def ransac_triples(m: int, iterations: int, seed: int) -> np.ndarray:
    """(iterations, 3) int64 triples of distinct row indices in 0..m-1 (m >= 3), uniform over
    ordered triples of distinct rows, from ``np.random.default_rng(seed).random((iterations,
    3))`` scaled to the cloud size (the uniforms are cached, so a frame does not pay for the
    generator; the first n triples of a longer draw are the triples of a draw of n)."""
    return _triples_kernel(_triple_uniforms(int(iterations), int(seed)), int(m))


def fit_plane_ransac(
    points: np.ndarray,
    distance_m: float,
    iterations: int,
    seed: int,
    *,
    up: object = None,
    max_tilt_deg: float | None = None,
    min_inliers: int = 3,
    confidence: float = 0.999,
    bail_sigmas: float = RANSAC_BAIL_SIGMAS,
) -> Plane:
    """Largest plane by RANSAC, refined by least squares.

    Up to ``iterations`` triples of distinct points, drawn by :func:`ransac_triples` (NumPy's
    ``default_rng(seed)``), are scored in order by :func:`_ransac_kernel` on the fixed subsample
    :func:`ransac_sample` (``RANSAC_SAMPLE`` evenly strided rows in a fixed random order:
    preemptive RANSAC; inliers within ``distance_m``; a triple dropped early when its partial
    count falls ``bail_sigmas`` below the best fraction; with ``up`` and ``max_tilt_deg``, only
    planes whose normal is within ``max_tilt_deg`` of ``up`` count; adaptive stop at
    ``confidence``, with the inlier fraction measured on the subsample).  Only the winner's
    inliers are counted on all points; it needs ``min_inliers`` of them.  It is then refitted to
    its inliers (normal = eigenvector of the smallest eigenvalue of their covariance, through
    their centroid) and its inliers are counted again; the refit is kept when it still meets the
    tilt limit and has at least as many inliers.

    Parameters
    ----------
    points : (M, 3) float32
        Metres, finite.
    distance_m : float
        Inlier distance in metres, > 0.
    iterations : int
        Sample triples, >= 1.
    seed : int
        Seed of the triples; the same seed and points give the same plane.
    up : (3,) array-like or None
        Camera-frame direction the plane normal must be close to (e.g. (0, -1, 0) for the floor
        seen by a level camera).
    max_tilt_deg : float or None
        Largest angle between normal and ``up``, 0..90 degrees.
    min_inliers : int
        A plane needs at least this many inliers, >= 1.
    confidence : float
        Stop drawing triples once a plane at least as large as the best so far would have been
        hit with this probability (adaptive RANSAC); 1.0 tries all ``iterations``.
    bail_sigmas : float
        Bail-out bound of the scoring in standard deviations, >= 0 (:data:`RANSAC_BAIL_SIGMAS`);
        ``math.inf`` counts every triple on the whole sample.

    Returns
    -------
    Plane
        With ``inliers`` over ``points``; :meth:`Plane.none` when fewer than 3 points or no
        plane with ``min_inliers`` qualifies.
    """
    points = check_points(points)
    if not np.all(np.isfinite(points)):
        raise InputError("points contain NaN or inf; filter them first (voxel_grid drops them)")
    dist = validate.positive("fit_plane_ransac", "distance_m", distance_m, unit=" metres")
    validate.whole("fit_plane_ransac", "iterations", iterations, 1, 2**63 - 1)
    validate.whole("fit_plane_ransac", "min_inliers", min_inliers, 1, 2**63 - 1)
    validate.whole("fit_plane_ransac", "seed", seed, 0, 2**63 - 1)
    up_vec, cos_min = _check_up(up, max_tilt_deg)
    try:
        conf = float(confidence)
    except (TypeError, ValueError):
        conf = math.nan
    if not 0.0 < conf <= 1.0:
        raise InputError(f"confidence={confidence!r}: must be a probability in (0, 1], e.g. "
                         "0.999 (1 tries every iteration)")
    try:
        bail = float(bail_sigmas)
    except (TypeError, ValueError):
        bail = math.nan
    if not bail >= 0.0:
        raise InputError(f"bail_sigmas={bail_sigmas!r}: must be a number of standard deviations "
                         ">= 0 (math.inf: no bail-out)")
    m = points.shape[0]
    if m < 3:
        return Plane.none(m)
    triples = ransac_triples(m, iterations, seed)
    sample = ransac_sample(m)
    best_t, _, normal, offset, tried = _ransac_kernel(points, sample, triples, dist, up_vec,
                                                      cos_min, conf, bail)
    if best_t < 0:
        return Plane.none(m, tried)
    inliers, count = _plane_inliers(points, normal, float(offset), dist)
    if count < min_inliers or count < 3:
        return Plane.none(m, tried)
    normal, offset = _orient(normal, float(offset))
    # least-squares refit on the inliers
    centroid, scatter = _inlier_scatter(points, inliers, count)
    _, vectors = np.linalg.eigh(scatter)
    refit = vectors[:, 0]
    refit = refit / np.linalg.norm(refit)
    if refit @ normal < 0:
        refit = -refit
    refit_offset = -float(refit @ centroid)
    refit_inliers, refit_count = _plane_inliers(points, refit, refit_offset, dist)
    tilt_ok = not up_vec.any() or abs(float(refit @ up_vec)) >= cos_min
    if tilt_ok and refit_count >= count:
        normal, offset = _orient(refit, refit_offset)
        inliers = refit_inliers
        count = refit_count
    return Plane(normal=normal, offset=float(offset), inliers=inliers, n_inliers=int(count),
                 iterations=int(tried))


def remove_plane(
    points: np.ndarray,
    distance_m: float,
    iterations: int,
    seed: int,
    **options: object,
) -> tuple[np.ndarray, Plane]:
    """Fit the largest plane (:func:`fit_plane_ransac`, same arguments) and drop its inliers.
    Returns ``(points without the plane (K, 3) float32, plane)``."""
    plane = fit_plane_ransac(
        points, distance_m, iterations, seed, **options  # type: ignore[arg-type]
    )
    return points[~plane.inliers], plane
