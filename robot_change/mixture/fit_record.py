"""The record of a fit: :class:`FitStep`, one EM run of
:func:`robot_change.mixture.model.fit_mixture` (or
:func:`~robot_change.mixture.model.fit_over_background`), and :class:`FitRecord`, the fit's
settings, steps and totals.  Plain frozen dataclasses of numbers and strings, no arrays (the
scene file keeps them in its JSON header); re-exported by :mod:`robot_change.mixture.model`.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FitRecord", "FitStep"]


@dataclass(frozen=True)
class FitStep:
    """One EM run inside :func:`fit_mixture`.

    ``action`` is ``"start"`` (the initial EM), ``"split k"`` (component k of the current
    mixture was split; ``"split i,j,..."`` when several were split in one round), ``"seed"``
    (a novelty component was added), ``"refine"`` (EM on the refinement subset before the
    split-and-merge moves) and ``"refine i+j/k"`` (components i and j merged and k split, at
    the same K), ``"polish m"`` (EM on a random subset of m points, coarse to fine, after the
    search), ``"polish"`` (the final EM on all points after a search on a subsample) or
    ``"prune"`` (free components left with fewer than ``min_points`` points of mass by the
    polish were dropped and EM run again); ``accepted`` says whether the result became the
    current mixture.
    """

    action: str
    n_components: int
    criterion: float
    log_likelihood: float
    n_iter: int
    converged: bool
    accepted: bool
    seconds: float


@dataclass(frozen=True)
class FitRecord:
    """How a mixture was fitted: settings, every EM run, and the totals.

    ``n_pruned``: free components dropped after the polish because they held fewer than
    ``min_points`` points of mass (0 when nothing was dropped, and in records written before
    the prune existed).
    """

    criterion: str
    n_points: int
    reg_covar: float
    max_components: int
    steps: tuple[FitStep, ...]
    n_iter: int
    seconds: float
    stop_reason: str
    n_pruned: int = 0

    @property
    def k_tried(self) -> tuple[int, ...]:
        """K of every EM run, in order."""
        return tuple(s.n_components for s in self.steps)


def _replace_accepted(step: FitStep) -> FitStep:
    d = dict(step.__dict__)
    d["accepted"] = True
    return FitStep(**d)
