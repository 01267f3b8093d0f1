"""Model-selection criteria of the split search: ``L_SC = -log L + P(K)`` (MDL, BIC, AIC) of a
mixture's total log-likelihood (nats) over N points, counting only the free parameters
(components held fixed are given, not estimated).  Re-exported by
:mod:`robot_change.mixture.model`.
"""

from __future__ import annotations

import math

import numpy as np

from robot_change.errors import InputError

__all__ = ["CRITERIA", "N_PARAMS_COMPONENT", "criterion_value"]

CRITERIA = ("mdl", "bic", "aic")
#: Free parameters of one full-covariance 3-D Gaussian (3 for the mean, 6 for the covariance).
N_PARAMS_COMPONENT = 9


def _n_free_weights(k: int, n_fixed: int, fix_weights: bool) -> int:
    if fix_weights and n_fixed > 0:
        return (k - n_fixed) + 1 - 1
    return k - 1


def criterion_value(name: str, log_likelihood: float, n_points: int, weights,
                    fixed=None, fix_weights: bool = False) -> float:
    """Model-selection criterion L_SC = -log L + P(K); smaller is better.

    Parameters
    ----------
    name : {"mdl", "bic", "aic"}
    log_likelihood : float
        Total log-likelihood ``sum_n log p(x_n)``.
    n_points : int
        N.
    weights : array, shape (K,)
    fixed : array of bool, shape (K,), optional
        Components given, not estimated: their 9 parameters are not counted (nor their
        weights when ``fix_weights``).

    Returns
    -------
    float
        AIC = -2 log L + 2p; BIC = -2 log L + p ln N; MDL (Figueiredo & Jain) = -log L +
        (Np/2) sum_k log(N w_k / 12) + (K/2) log(N/12) + K (Np + 1)/2, with p = 10K - 1 and
        Np = 9 when no component is fixed.
    """
    w = np.asarray(weights, dtype=np.float64)
    k = w.shape[0]
    fixed = np.zeros(k, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
    n_fixed = int(fixed.sum())
    k_free = k - n_fixed
    p = N_PARAMS_COMPONENT * k_free + _n_free_weights(k, n_fixed, fix_weights)
    n = float(n_points)
    if name == "aic":
        return -2.0 * log_likelihood + 2.0 * p
    if name == "bic":
        return -2.0 * log_likelihood + p * math.log(n)
    if name == "mdl":
        k_w = _n_free_weights(k, n_fixed, fix_weights) + 1
        nw = np.maximum(n * w[~fixed], 1e-300)
        return (-log_likelihood + 0.5 * N_PARAMS_COMPONENT * float(np.log(nw / 12.0).sum())
                + 0.5 * k_w * math.log(n / 12.0) + 0.5 * (N_PARAMS_COMPONENT * k_free + k_w))
    raise InputError(f"criterion must be one of {CRITERIA}, got {name!r}")
