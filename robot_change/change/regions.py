"""Changed points into regions: connected components on the voxel grid (union-find over
voxel keys, a numba kernel with a NumPy twin in the tests), regions below the size limits
dropped, and the pixel mask of a set of points.
"""

from __future__ import annotations

import numba
import numpy as np

from robot_change.change.epoch import Epoch
from robot_change.change.params import ChangeParams
from robot_change.change.results import Region
from robot_change.cloud.voxels import KEY_BITS
from robot_change.errors import InputError
from robot_change.unionfind import forest_labels, union_sets

__all__ = [
    "group_regions",
    "label_voxel_components",
    "pixel_mask",
]


_FIELD = (1 << KEY_BITS) - 1


@numba.njit(cache=True, nogil=True)
def _neighbour(keys, k, dt, dm, dl):
    """Row of the voxel ``k`` + (dt, dm, dl) in ``keys`` (sorted, unique), or -1."""
    shift_top = np.int64(1) << np.int64(2 * KEY_BITS)
    shift_mid = np.int64(1) << np.int64(KEY_BITS)
    # the key's three fields (z, y, x from the top; the test treats them alike)
    jt = ((k >> np.int64(2 * KEY_BITS)) & _FIELD) + dt
    jm = ((k >> np.int64(KEY_BITS)) & _FIELD) + dm
    jl = (k & _FIELD) + dl
    if jt < 0 or jm < 0 or jl < 0 or jt > _FIELD or jm > _FIELD or jl > _FIELD:
        return -1
    nk = jt * shift_top + jm * shift_mid + jl
    j = np.searchsorted(keys, nk)
    if j < keys.shape[0] and keys[j] == nk:
        return j
    return -1


@numba.njit(cache=True, nogil=True)
def _components_kernel(keys, radius):
    """Connected components of voxels: ``keys`` (M,) int64 packed keys, sorted ascending and
    unique; voxels are neighbours when each index differs by at most ``radius``.  Returns
    (M,) int64 labels 0..C-1, numbered in order of each component's first voxel."""
    m = keys.shape[0]
    parent = np.arange(m)
    for i in range(m):
        for dt in range(-radius, radius + 1):
            for dm in range(-radius, radius + 1):
                for dl in range(-radius, radius + 1):
                    # each pair once: only neighbours with a larger key
                    if dt < 0 or (dt == 0 and (dm < 0 or (dm == 0 and dl <= 0))):
                        continue
                    j = _neighbour(keys, keys[i], dt, dm, dl)
                    if j >= 0:
                        union_sets(parent, i, j)
    return forest_labels(parent)


def label_voxel_components(keys: np.ndarray, radius: int = 1) -> np.ndarray:
    """Connected components of a set of voxels given by their packed keys.

    Parameters
    ----------
    keys : (M,) int64
        Packed voxel keys (:func:`robot_change.cloud.voxels.pack_keys`), any order, no duplicates.
    radius : int
        Voxels whose indices differ by at most this on every axis are connected (1: the
        26-neighbourhood).

    Returns
    -------
    (M,) int64
        Component label of each key (same order as given), 0..C-1.
    """
    keys = np.asarray(keys, dtype=np.int64)
    if keys.ndim != 1:
        raise InputError(f"keys must be (M,) int64, got shape {keys.shape}")
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    if sk.size > 1 and (np.diff(sk) == 0).any():
        raise InputError("keys must be unique (one point per voxel)")
    labels_sorted = _components_kernel(np.ascontiguousarray(sk), int(radius))
    labels = np.empty_like(labels_sorted)
    labels[order] = labels_sorted
    return labels


def in_groups_of(epoch: Epoch, changed: np.ndarray, core: np.ndarray, min_points: int,
                 connectivity: int) -> np.ndarray:
    """(M,) bool: the ``changed`` (M,) bool points of ``epoch`` in connected groups (voxel
    keys, :func:`label_voxel_components`) that hold at least ``min_points`` points of
    ``core`` (M,) bool."""
    idx = np.flatnonzero(changed)
    out = np.zeros_like(changed)
    if np.count_nonzero(core[idx]) < min_points:
        return out
    labels = label_voxel_components(epoch.keys[idx], connectivity)
    held = np.bincount(labels, weights=core[idx])
    out[idx[held[labels] >= min_points]] = True
    return out


def group_regions(kind: str, epoch: Epoch, changed: np.ndarray, params: ChangeParams,
                  posterior: np.ndarray | None = None,
                  change_components: np.ndarray | None = None) -> tuple[Region, ...]:
    """Group the changed points of ``epoch`` into :class:`Region` s (largest first).

    ``changed`` (M,) bool; ``posterior`` (M, K) responsibilities of the searched mixture and
    ``change_components`` the accepted components, to name each region's components.
    """
    idx = np.flatnonzero(changed)
    if idx.size == 0:
        return ()
    labels = label_voxel_components(epoch.keys[idx], params.region_connectivity)
    n_lab = int(labels.max()) + 1
    sizes = np.bincount(labels, minlength=n_lab)
    pix_count = np.bincount(epoch.pixel_voxel.ravel()[epoch.pixel_voxel.ravel() >= 0],
                            minlength=epoch.n_points)
    regions = []
    for lab in np.argsort(-sizes, kind="stable"):
        if sizes[lab] < params.min_region_points:
            break
        rows = idx[labels == lab]
        pts = epoch.points[rows].astype(np.float64)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        if float(np.max(hi - lo)) < params.min_region_extent_m:
            continue
        comps: tuple[int, ...] = ()
        if posterior is not None and change_components is not None and len(change_components):
            mass = posterior[rows][:, change_components].sum(axis=0)
            keep = np.argsort(-mass, kind="stable")
            comps = tuple(int(change_components[k]) for k in keep if mass[k] > 0.05 * len(rows))
        regions.append(Region(kind, pts.mean(axis=0), hi - lo, lo, hi, int(len(rows)),
                              int(pix_count[rows].sum()), comps, rows, epoch.points[rows]))
    return tuple(regions)


def pixel_mask(epoch: Epoch, rows: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of the points ``rows`` of ``epoch``."""
    sel = np.zeros(epoch.n_points + 1, dtype=bool)  # the last entry (False): pixel_voxel -1
    sel[rows] = True
    return sel[epoch.pixel_voxel]
