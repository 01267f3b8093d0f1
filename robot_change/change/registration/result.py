"""Registration: the estimated transform between the two camera frames, and how far to trust
it (fitness, weak directions, the station test)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .params import RegistrationParams
from .rigid import invert, rotation_angle_deg, rotation_to_rpy_deg, rotation_vector

#: Names of the six directions of the estimate, in the order of the Gauss-Newton step
#: (rotation vector, then translation), camera optical frame: rotations about x (right),
#: y (down), z (forward), translations along them.
AXES = ("rot_x", "rot_y", "rot_z", "x", "y", "z")


@dataclasses.dataclass(frozen=True, eq=False)
class Registration:
    """The estimated rigid transform between the two camera frames, and how far to trust it.

    ``T_ref_from_cur`` (4, 4) float64 maps current camera-frame points into the reference
    camera frame (metres).  ``fitness``: fraction of the current's cells with an inlier
    correspondence (0..1); ``rmse_m`` of those residuals (point-to-plane).
    ``seen_through``: the larger of the two whole views' fractions seen through by the other
    (finest level, floor and table included).  ``behind``: the fraction of the current's cells
    that lie behind a nearer reading of the reference (hidden from it: where an object was
    taken away, or seen past an edge from the new place).  ``weak``: names
    (:data:`AXES`) of directions the views leave unconstrained (not moved along; the estimate
    there is the starting value), the slide that no surface facing along it pins at the
    estimate (``slide_support_share``) or that most of what faces along it contradicts
    (``slide_contested_share``), and on a table top the directions in the table's plane
    together, when one of them is weak, the two tables do not overlap at the estimate
    (``RegistrationParams.table_outline_holes``) or no object stayed put
    (``table_static_share``): not to be trusted.  ``eigenvalues`` (6,) of the scaled normal
    matrix per unit weight, ascending.  ``n_pairs`` inlier correspondences, ``n_cells``
    current cells at the finest level; ``iterations`` run; ``ms`` the time taken;
    ``converged``.
    """

    T_ref_from_cur: np.ndarray
    fitness: float
    rmse_m: float
    weak: tuple[str, ...]
    eigenvalues: np.ndarray
    n_pairs: int
    n_cells: int
    iterations: int
    converged: bool
    ms: float
    seen_through: float = 0.0
    behind: float = 0.0

    @property
    def translation_m(self) -> np.ndarray:
        """(3,) translation of ``T_ref_from_cur``: where the current camera stands in the
        reference camera frame, metres."""
        return self.T_ref_from_cur[:3, 3].copy()

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation of ``T_ref_from_cur``, degrees."""
        return rotation_angle_deg(self.T_ref_from_cur[:3, :3])

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.T_ref_from_cur, np.eye(4)))

    def inverse(self) -> np.ndarray:
        """(4, 4) ``T_cur_from_ref``."""
        return invert(self.T_ref_from_cur)

    def pinned_offset(self) -> tuple[float, float]:
        """(metres, degrees): the offset along the directions the views pin, the translation
        and the rotation vector without their :attr:`weak` components (along a weak direction
        the estimate is the starting value or a search's pick, not measured)."""
        t = self.translation_m.copy()
        w = rotation_vector(self.T_ref_from_cur[:3, :3])
        for name in self.weak:
            i = AXES.index(name)
            (w if i < 3 else t)[i % 3] = 0.0
        return float(np.linalg.norm(t)), math.degrees(float(np.linalg.norm(w)))

    def not_at_station(self, params: RegistrationParams) -> str:
        """Why the camera is not at the station by the tolerance of ``params``; "" when it is.
        The offset tested is :meth:`pinned_offset`."""
        moved, turned = self.pinned_offset()
        if self.fitness + self.behind < params.min_fitness:
            return (f"registration fitness {self.fitness:.2f} (and {self.behind:.2f} behind "
                    f"what the reference saw nearer) < {params.min_fitness:.2f}: the views do "
                    f"not overlap enough")
        if moved > params.max_translation_m:
            return f"offset {moved:.2f} m > {params.max_translation_m:.2f} m"
        if turned > params.max_rotation_deg:
            return f"rotation {turned:.1f} deg > {params.max_rotation_deg:.1f} deg"
        if self.seen_through > params.max_seen_through:
            return (f"{self.seen_through:.0%} of one view is seen through by the other (more "
                    f"than {params.max_seen_through:.0%}): another place, or a change too large "
                    f"to register against")
        return ""

    def to_dict(self) -> dict:
        """JSON-ready: the transform, translation (m) and roll/pitch/yaw (deg) of
        ``T_ref_from_cur`` in the camera optical frame, fitness, RMSE, weak directions, ms."""
        return {
            "T_ref_from_cur": [[round(float(v), 9) for v in row] for row in self.T_ref_from_cur],
            "translation_m": [round(float(v), 5) for v in self.translation_m],
            "rotation_deg": [round(float(v), 4)
                             for v in rotation_to_rpy_deg(self.T_ref_from_cur[:3, :3])],
            "fitness": round(self.fitness, 4),
            "rmse_m": round(self.rmse_m, 5),
            "seen_through": round(self.seen_through, 4),
            "behind": round(self.behind, 4),
            "weak_directions": list(self.weak),
            "n_pairs": self.n_pairs,
            "iterations": self.iterations,
            "converged": self.converged,
            "ms": round(self.ms, 3),
        }


def identity_registration(transform: np.ndarray | None = None) -> Registration:
    """A registration taken as given (registration switched off): ``transform`` (4, 4), the
    identity by default, with fitness 1."""
    T = np.eye(4) if transform is None else np.array(transform, dtype=np.float64)
    return Registration(T, 1.0, 0.0, (), np.ones(6), 0, 0, 0, True, 0.0)
