"""The immutable 3-D Gaussian mixture :class:`Mixture` (weights (K,), means (K, 3) m,
covariances (K, 3, 3) m^2): its checks, its densities and responsibilities through the EM
kernels, its rigid motion, and its file (a robot_change.npzfile, :meth:`Mixture.save` /
:meth:`Mixture.load`).  Re-exported by :mod:`robot_change.mixture.model`, where the fits that
make one are.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from robot_change import npzfile
from robot_change.errors import InputError, MixtureFileError
from robot_change.mixture import em
from robot_change.mixture.fit_record import FitRecord

__all__ = ["FILE_FORMAT", "FILE_VERSION", "Mixture"]

FILE_FORMAT = "robot_change.mixture"
FILE_VERSION = 2  # 2: the checksum of robot_change.npzfile (1: of the arrays alone)


def _check_points(points, name: str = "points") -> np.ndarray:
    """(N, 3) finite float64 copy-free view of ``points``; InputError otherwise."""
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a numeric (N, 3) array: {exc}") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    if arr.shape[0] == 0:
        raise InputError(f"{name} is empty: a mixture needs at least one point")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr).all(axis=1)).sum())
        raise InputError(f"{name} has {bad} rows with NaN or inf; drop them first "
                         f"(points[np.isfinite(points).all(axis=1)])")
    return np.ascontiguousarray(arr)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64, order="C", copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Mixture:
    """A Gaussian mixture in 3-D: ``sum_k w_k N(x | mu_k, Sigma_k)``.

    Attributes
    ----------
    weights : array, shape (K,)
        Non-negative, summing to 1.
    means : array, shape (K, 3)
    covariances : array, shape (K, 3, 3)
        Symmetric positive definite.
    record : FitRecord or None
        How :func:`fit_mixture` made it (not saved to file, not part of equality).

    The arrays are float64 read-only copies.
    """

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    record: FitRecord | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        w = _readonly(self.weights)
        mu = _readonly(self.means)
        cov = _readonly(self.covariances)
        if w.ndim != 1 or w.shape[0] < 1:
            raise InputError(f"weights must have shape (K,) with K >= 1, got {w.shape}")
        k = w.shape[0]
        if mu.shape != (k, 3):
            raise InputError(f"means must have shape ({k}, 3), got {mu.shape}")
        if cov.shape != (k, 3, 3):
            raise InputError(f"covariances must have shape ({k}, 3, 3), got {cov.shape}")
        for name, a in (("weights", w), ("means", mu), ("covariances", cov)):
            if not np.isfinite(a).all():
                raise InputError(f"{name} contain NaN or inf")
        if (w < 0).any() or abs(w.sum() - 1.0) > 1e-9:
            raise InputError(f"weights must be >= 0 and sum to 1, got sum {w.sum():.12g}, "
                             f"min {w.min():.3g}; normalise them (w / w.sum())")
        asym = np.abs(cov - cov.transpose(0, 2, 1)).max(axis=(1, 2))
        scale = np.abs(cov).max(axis=(1, 2))
        if (asym > 1e-12 * np.maximum(scale, 1e-300)).any():
            raise InputError("covariances must be symmetric; symmetrise them "
                             "(0.5 * (C + C.transpose(0, 2, 1)))")
        _, _, ok = em.precision_cholesky(np.array(cov))  # writable: one compiled type
        if not ok.all():
            bad = np.flatnonzero(~ok).tolist()
            raise InputError(f"covariances of components {bad} are not positive definite; "
                             "add a floor to their diagonal (reg_covar)")
        object.__setattr__(self, "weights", w)
        object.__setattr__(self, "means", mu)
        object.__setattr__(self, "covariances", cov)

    @property
    def n_components(self) -> int:
        """K, the number of components."""
        return int(self.weights.shape[0])

    @cached_property
    def _kernel_args(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(weights, means, precision Cholesky factors, their log-determinants): private
        writable copies, the array types the fit's own calls give the kernels (a read-only
        array would be another compile)."""
        prec, log_det, _ = em.precision_cholesky(np.array(self.covariances))
        return np.array(self.weights), np.array(self.means), prec, log_det

    def score_samples(self, points) -> np.ndarray:
        """Log density of each point under the mixture.

        Parameters
        ----------
        points : array, shape (N, 3)

        Returns
        -------
        log_prob : array, shape (N,)
        """
        return em.log_prob_samples(_check_points(points), *self._kernel_args)

    def score(self, points) -> float:
        """Mean log-likelihood per point (scikit-learn's ``GaussianMixture.score``)."""
        return float(self.score_samples(points).mean())

    def log_responsibilities(self, points) -> np.ndarray:
        """``log p(k | x_n)``, shape (N, K)."""
        log_resp, _ = em.e_step(_check_points(points), *self._kernel_args)
        return log_resp

    def responsibilities(self, points) -> np.ndarray:
        """Posterior probability of each component for each point, shape (N, K)."""
        return np.exp(self.log_responsibilities(points))

    def predict(self, points) -> np.ndarray:
        """Index of the most probable component for each point, shape (N,), int64 (the first
        on ties)."""
        return em.log_prob_labels(_check_points(points), *self._kernel_args)[1]

    def transformed(self, transform: np.ndarray) -> Mixture:
        """The mixture moved by the (4, 4) rigid ``transform``: means ``R mu + t``,
        covariances ``R Sigma R^T``, weights kept (the density of the moved points)."""
        T = np.asarray(transform, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise InputError("transform must be a finite (4, 4) rigid transform")
        R, t = T[:3, :3], T[:3, 3]
        cov = np.einsum("ij,kjl,ml->kim", R, np.asarray(self.covariances), R)
        return Mixture(np.asarray(self.weights).copy(), np.asarray(self.means) @ R.T + t,
                       (cov + cov.transpose(0, 2, 1)) / 2.0)

    def log_likelihood(self, points) -> float:
        """Total log-likelihood ``sum_n log p(x_n)``."""
        return float(self.score_samples(points).sum())

    # ----------------------------------------------------------------------- files

    def save(self, path) -> None:
        """Write to ``path`` (a robot_change.npzfile: arrays ``weights``, ``means``,
        ``covariances``, a JSON header with K and the criterion the fit used, if known, and a
        SHA-256 over both), atomically."""
        npzfile.write(path, FILE_FORMAT, FILE_VERSION,
                      {"weights": self.weights, "means": self.means,
                       "covariances": self.covariances},
                      {"n_components": self.n_components,
                       "criterion": self.record.criterion if self.record is not None else None},
                      compress=False)

    @classmethod
    def load(cls, path) -> Mixture:
        """Read a mixture written by :meth:`save` (version 1 files too); verify format, version
        and checksum.

        Raises
        ------
        MixtureFileError
            Unreadable or truncated file, another format, a newer version, a checksum that
            does not match, or arrays that do not form a valid mixture.
        FileNotFoundError
            ``path`` does not exist.
        """
        path = Path(path)
        redo = "fit and save the mixture again"
        header, arrays = npzfile.read(path, FILE_FORMAT, FILE_VERSION,
                                      ("weights", "means", "covariances"), MixtureFileError,
                                      redo, verify=_verify)
        try:
            mixture = cls(arrays["weights"], arrays["means"], arrays["covariances"])
        except InputError as exc:
            raise MixtureFileError(f"{path}: the arrays do not form a valid mixture ({exc}); "
                                   f"{redo}") from exc
        if header.get("n_components") != mixture.n_components:
            raise MixtureFileError(f"{path}: header says K = {header.get('n_components')}, "
                                   f"arrays hold {mixture.n_components}; {redo}")
        return mixture


def _verify(header: dict, arrays: dict[str, np.ndarray]) -> bool:
    """The checksum of a mixture file: robot_change.npzfile's since version 2; version 1 hashed
    the three arrays alone (as float64, little-endian)."""
    if header.get("version") == 1:
        h = hashlib.sha256()
        for name in ("weights", "means", "covariances"):
            h.update(np.ascontiguousarray(arrays[name], dtype="<f8").tobytes())
        return header.get("sha256") == h.hexdigest()
    return header.get("sha256") == npzfile.checksum(header, arrays)
