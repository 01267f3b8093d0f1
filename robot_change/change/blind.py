"""Whether the current camera still reads what the reference read from the station: a lens
covered, or something nearer than the camera's minimum range, leaves the current view without
readings where the reference had them, and what it does read may register and compare as if
nothing changed.  The share it does not read is measured after registration, on the finest
cells of the registration's pyramids; above ``ChangeParams.max_unread_share`` a check raises
EmptySceneError."""

from __future__ import annotations

import numpy as np

from hw.depth import Intrinsics
from robot_change.change.registration import RegistrationParams, invert
from robot_change.change.registration.agreement import agreement_counts
from robot_change.change.registration.pyramid import kept_levels

__all__ = ["unread_share"]


def unread_share(reference: np.ndarray, current: np.ndarray, intrinsics: Intrinsics,
                 T_ref_from_cur: np.ndarray, params: RegistrationParams,
                 keep: dict | None = None, keep_current: dict | None = None) -> float:
    """Of the reference's cells (its (H, W) uint16 mm depth, the finest level of
    :func:`~robot_change.change.registration.pyramid.levels`) that land inside the current
    image when moved by ``T_ref_from_cur`` (4, 4), the share that land on no reading of the
    current (0 when none land there).  ``keep`` / ``keep_current``: where the two pyramids are
    kept (the registration's)."""
    rl = kept_levels(np.ascontiguousarray(reference), intrinsics, params, keep)[-1]
    cl = kept_levels(np.ascontiguousarray(current), intrinsics, params, keep_current)[-1]
    _, _, _, compared, holes, _ = agreement_counts(
        *rl.onto(cl, invert(np.asarray(T_ref_from_cur, dtype=np.float64))), 0.0, 1.0,
        *params.noise_args(0.0), False)
    return holes / (holes + compared) if holes + compared else 0.0
