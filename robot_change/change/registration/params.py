"""RegistrationParams: every setting of :func:`~robot_change.change.registration.register_depth`,
validated on construction (the one place their defaults live; the daemon's are these)."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

from robot_change import validate
from robot_change.errors import InputError
from robot_change.noise.profile import (
    DEFAULT_PROFILE,
    NoiseProfile,
    builtin_profile,
    sigma_table,
)

_num = functools.partial(validate.number, "RegistrationParams")
_int = functools.partial(validate.whole, "RegistrationParams")
_bool = functools.partial(validate.flag, "RegistrationParams")
#: The settings checked alike: shares (0..1); steps (0 < m <= 1) and lengths (0..1 m).
_SHARES = ("final_search_margin", "station_through_ratio", "station_through_min",
           "station_through_max", "fine_search_ratio", "restart_end_through",
           "restart_end_ratio", "table_plane_fraction", "trim_conflict_share",
           "table_outline_holes", "table_static_share", "slide_support_share",
           "slide_contested_share", "min_fitness")
_STEPS_M = ("search_step_m", "fine_search_step_m", "final_search_step_m")
_LENGTHS_M = ("fine_search_reach_m", "final_search_reach_m", "restart_step_m", "band_m",
              "table_object_m")


@dataclasses.dataclass(frozen=True)
class RegistrationParams:
    """Parameters of :func:`register_depth`, validated on construction.

    ``levels``: pyramid factors, coarse to fine (a level of factor f has (H/f) x (W/f) cells);
    ``iterations`` per level; ``max_distance_m`` per level: correspondences farther apart are
    not paired.  The defaults cover offsets of 15 cm and 6 degrees (docs/algorithm.md).
    """

    # Register at all (False: the identity, for cameras bolted in place, and to measure).
    enabled: bool = True
    levels: tuple[int, ...] = (16, 8, 4)
    iterations: tuple[int, ...] = (12, 10, 6)
    max_distance_m: tuple[float, ...] = (0.35, 0.15, 0.06)
    # After the level of index search_level (0 = coarsest), translations along the two least
    # constrained translation directions (this step, out to this reach) are scored by their
    # inlier count and ICP goes on from the best: rooms let ICP slide along the floor and
    # walls (ALGORITHM.md section 4), and a yaw error is first taken up by a sideways slide.
    search_level: int = 1
    search_step_m: float = 0.1
    search_reach_m: float = 0.4
    # ... and screw motions (rotation and translation together) along the two least
    # constrained directions of the whole 6-D system, rotations scaled by the cloud's radius,
    # search_screw_steps steps of search_step_m each way (0: none; 1 did as well as 2-4 on the
    # table tops): a table top leaves the turn about its normal coupled with a slide.
    search_screw_steps: int = 1
    # Then, when one translation direction is much less constrained than the other two (its
    # eigenvalue of the translation block below fine_search_ratio of the next one: a slide),
    # offsets along it, fine_search_step_m apart out to fine_search_reach_m each way, are
    # scored the same way and ICP goes on from the best when it ends scoring higher (reach 0:
    # none).  A table station's slide along its wall is pinned only by the table's legs and
    # the sides of the objects on it, a few centimetres wide: ICP's basin there is narrower
    # than search_step_m.  Ratios: table stations that slid 0.001-0.019; rooms, which need no
    # fine search, 0.10 and more (docs/algorithm.md, step 6).
    fine_search_step_m: float = 0.01
    fine_search_reach_m: float = 0.04
    fine_search_ratio: float = 0.05
    # At the end, when the estimate is weak along a translation (the normal equations, or a
    # slide nothing pins: weak_eigenvalue, slide_support_share) and not a table top, poses
    # along its least constrained translation, final_search_step_m apart out to
    # final_search_reach_m each way, are scored both ways at search_level (each view's
    # inliers, less the cells either sees through, less table_hole_weight times those
    # landing on no reading); ICP runs at the finest level from the final_search_starts
    # best peaks, and the best end replaces the estimate when its score, taken the same way
    # at the finest level, is higher by more than final_search_margin of the two views'
    # cells with a normal (reach 0: none).
    # Where every object on a table moved, the objects outnumber the legs and edges that pin
    # the slide along the wall, and ICP stays where they line up; taken both ways at the
    # finest level, the score often prefers the pose where the structure lines up
    # (docs/algorithm.md, registration step 7b).
    # Margins of right against wrong ends on the 8000 and 9000 table stations: wrong ones
    # won by 0.04-0.45 % (one by 1.0 %), right ones by 0.5-8.9 %.
    final_search_step_m: float = 0.01
    final_search_reach_m: float = 0.3
    final_search_starts: int = 2
    final_search_margin: float = 0.005
    # Then, at a table station (a table plane with the floor parallel beneath it), the
    # objects standing on the table are left out, and what is left (table, legs, floor,
    # walls) decides (docs/algorithm.md, registration step 7c): when the estimate's rest is
    # seen through in more than station_through_min of the two views' cells with a normal,
    # ICP runs on the rest alone from it and from the poses along its slide where the rest
    # is seen through least; the best end replaces the estimate when its rest is seen
    # through in at most station_through_max of the cells, in fewer than
    # station_through_ratio times the estimate's, and in fewer by station_through_min of
    # the cells (ratio 0: not looked at).  At the truth of the wrong estimates of the five
    # station sets 1-32 cells (~0.1 %) were seen through so, at those estimates 43-1,718.
    station_through_ratio: float = 0.5
    station_through_min: float = 0.001
    station_through_max: float = 0.002
    # At the coarsest level ICP also runs with Tukey's cut at least wide_cut_m (metres; 0:
    # not), and goes on from the better-scoring of the two ends (inliers less seen-through
    # cells, as the search).  On a table top the plane aligns first, the residual scale
    # collapses to the noise and the objects' pairs, still centimetres off, are cut: the
    # estimate drifts about the table's normal.  A room's walls keep the narrow cut right.
    wide_cut_m: float = 0.2
    # The starts of step 7d: the initial pose moved by restart_step_m along and turned by
    # restart_step_deg about each camera axis (12 starts; 0 and 0: none).
    restart_step_m: float = 0.1
    restart_step_deg: float = 5.0
    # When more than restart_end_through of one view is seen through by the other at the
    # end (after the final searches; 0: never), the coarse-to-fine passes run again from the
    # same 12 starts, and the best of their ends, scored both ways at the finest level,
    # replaces the first when it scores higher by more than final_search_margin of the two
    # views' cells with a normal and is seen through in less than restart_end_ratio of the
    # first's share.  Station 9001, one object removed, 15 cm / 6 deg away: ICP ended 27 cm /
    # 8 deg off with 0.20 of a view seen through; from 4 of the 12 starts at the truth (0.03).
    # Where every object on a table moved, the change alone is seen through in up to 0.19
    # of a view at the truth, and the moved objects can line up better elsewhere.
    restart_end_through: float = 0.15
    restart_end_ratio: float = 0.5
    # Table-plane starts (0: none): when the dominant plane of the reference's coarsest level
    # holds at least table_plane_fraction of its cells (a table top: 0.63-0.91 of the cells;
    # the current's need only be that plane again, its normal within table_max_tilt_deg of
    # the reference's), and both views' span at most
    # table_max_extent_m (a table top 0.8-1.2 m; room floors 0.40-0.81 but 2.7-3.5 m), the
    # two views are drawn top-down on that plane (table_cell_m cells: +1 above it by more than
    # table_object_m, -1 on it, 0 unseen) and cross-correlated over in-plane shifts (FFT) for
    # yaws about its normal out to table_yaw_deg in table_yaw_step_deg steps; the
    # table_starts best distinct peaks are run through ICP down to search_level and compete
    # there with the main estimate on the search's score.  A table top's moved objects drag
    # ICP into a compromise; its outline and the objects that stayed fix (x, y, yaw).
    table_starts: int = 3
    table_plane_fraction: float = 0.6
    table_max_tilt_deg: float = 20.0
    table_max_extent_m: float = 2.0
    table_cell_m: float = 0.02
    table_object_m: float = 0.015
    table_yaw_deg: float = 10.0
    table_yaw_step_deg: float = 2.0
    # The starts compete with the main estimate on a score taken both ways: each view's
    # inlier cells, less the cells either view sees through, less table_hole_weight times the
    # cells of either view that land on no reading of the other (a table top's outline).
    table_hole_weight: float = 1.0
    # On a table top, after the finest level: trim_rounds rounds of ICP from search_level down
    # to the finest level without the objects that changed: the connected groups of cells
    # standing more than table_object_m above each view's plane in which the cells that
    # contradict the other view (seen through, or paired beyond inlier_sigmas) outnumber
    # trim_conflict_share of those that contradict or fit.  Moved objects drag ICP into a
    # compromise; the table and the objects that stayed put are the static part.  0: none.
    trim_rounds: int = 2
    trim_conflict_share: float = 0.5
    # On a table top, at the final estimate: when more than table_outline_holes of each view's
    # table cells (within 1 cm of its plane) that land in the other image land on no reading
    # there, the two views' tables do not overlap at that pose (a wrong pose, or outlines
    # that differ, as when nothing on the table stayed put and the crop changed): the
    # directions in the table's plane (two slides, the turn about its normal) are reported
    # weak.  The smaller of the two views' shares was 0.001-0.015 at right poses (dropouts
    # and the field of view's edge; one of 147 at 0.032) and 0.027-0.087 at 13 of 15 wrong
    # ones on the table-top tuning sample (docs/benchmarks.md).  0: not checked.
    table_outline_holes: float = 0.02
    # On a table top, at the final estimate: when fewer than table_static_share of the two
    # views' object cells (standing more than table_object_m above their plane) fit the
    # other view, no object stayed put; the pose in the table's plane then rests on the
    # table's outline alone, like a bare table, and those directions are reported weak.
    # At right poses the share was 0.000-0.017 on the tuning pairs where every object moved
    # or shifted and 0.065-0.72 where one stayed (docs/benchmarks.md).  0: not checked.
    table_static_share: float = 0.03
    # At the final estimate, the least constrained translation direction of the finest
    # level's normal matrix is reported weak when fewer than slide_support_share of the
    # current's cells with a normal (both views' cells counted) face along it (normal within
    # 60 degrees) and fit the other view: nothing pins the estimate there.  Right estimates
    # had at least 55 such cells of ~19,000 (0.003) on table stations and 746 in rooms; the
    # table stations that slid along their wall (every object moved, lined up elsewhere) had
    # 0 (docs/algorithm.md, step 7).  0: not checked.
    slide_support_share: float = 0.001
    # ... or when more than slide_contested_share of those facing cells that the other view
    # judges contradict it (1: not checked): a majority of what would pin the slide argues
    # against the estimate.  Where every object on a table station moved, the legs pin the
    # truth and the moved objects, lined up elsewhere, a wrong pose; either way the contested
    # share is high.  At a table station both checks run again on what does not stand on
    # the table alone, when neither named a translation (step 7e: said, not searched).
    slide_contested_share: float = 0.7
    # Normals of a pair must agree within this angle.
    max_normal_angle_deg: float = 30.0
    # A cell is the mean of the block's readings within this band of the reading at its
    # centre: band = band_m + band_slope * (f * z / fx) (so a slanted floor's block is kept).
    band_m: float = 0.03
    band_slope: float = 2.0
    # Tukey's constant, in units of the robust residual scale (4.685: 95 % efficiency).
    tukey_c: float = 4.685
    # A correspondence is an inlier (fitness, RMSE) within this many sigmas of the camera's
    # noise at its depth (``noise``).
    inlier_sigmas: float = 3.0
    # Eigenvalues of the scaled normal matrix per unit weight below this are weak directions.
    weak_eigenvalue: float = 1e-4
    # Stop a level when the step is below this (metres; rotations times the cloud radius):
    # 0.1 mm, a tenth of the depth noise at 0.5 m; a smaller one buys no accuracy.
    tol_m: float = 1e-4
    # Station tolerance: fitness, plus the share of the current's cells that lie behind a
    # nearer reading of the reference (what was taken away, what the new place sees past an
    # edge: consistent with the station), below min_fitness, a translation above
    # max_translation_m or a rotation above max_rotation_deg (the range registration and the
    # checks are measured in, 15 cm and 7.8 deg -- the sets' 6 deg drawn as yaw / pitch / roll
    # steps compose to single turns of up to 7.8 deg at a table -- plus the 1 cm / 0.5 deg an
    # estimate converged within may be off: beyond it the robot is told where it stands,
    # nothing is compared; docs/algorithm.md, step 8), or more than max_seen_through of
    # either whole view seen through by the other (the views contradict each other: another
    # place, or a change too large to register against) is "not at the station".  Seen
    # through: a reading farther by more than seen_through_margin_m +
    # seen_through_margin_per_m2 * z^2, or by seen_through_sigmas sigmas of the difference of
    # two readings of the camera (k sqrt(2) sigma(z)) where that is wider (with the Kinect's
    # noise beyond 3 m: 9.4 -> 12.3 cm at 4 m; the paper's 100 mm noise: 42 cm); behind:
    # nearer by as much.  The floor is what the table stations were tuned with (a 5 mm lower
    # one takes station 0's every-object-moved revisit at 15 cm 33 cm off).
    min_fitness: float = 0.5
    max_seen_through: float = 0.25
    seen_through_margin_m: float = 0.03
    seen_through_margin_per_m2: float = 0.004
    seen_through_sigmas: float = 3.0
    max_translation_m: float = 0.16
    max_rotation_deg: float = 8.5
    # Depth readings outside this range are not used (metres; min_depth_m None: the camera's,
    # :attr:`near_m`).
    min_depth_m: float | None = None
    max_depth_m: float = 5.0
    # The camera's noise (robot_change.noise): weighs each residual, makes the inlier band and
    # the seen-through margin.  A check sets it from its reference's profile.
    noise: NoiseProfile = dataclasses.field(default_factory=lambda: builtin_profile(
        DEFAULT_PROFILE))

    def __post_init__(self) -> None:
        _bool("enabled", self.enabled)
        n = len(self.levels) if isinstance(self.levels, tuple) else -1
        for name in ("levels", "iterations", "max_distance_m"):
            value = getattr(self, name)
            if not isinstance(value, tuple) or len(value) != n or n < 1:
                raise InputError(f"RegistrationParams.{name} must be a tuple of the same length "
                                 f"as levels (>= 1), got {value!r}")
        for f in self.levels:
            _int("levels", f, 1, 64)
        if any(a != 2 * b for a, b in zip(self.levels, self.levels[1:], strict=False)):
            raise InputError(f"RegistrationParams.levels={self.levels!r}: each factor must be "
                             f"twice the next (coarse to fine), e.g. (16, 8, 4)")
        for it in self.iterations:
            _int("iterations", it, 0, 100)
        for d in self.max_distance_m:
            _num("max_distance_m", d, 0.0, 5.0, low_open=True, unit=" metres")
        _int("search_level", self.search_level, 0, n - 1)
        for name in _SHARES:
            _num(name, getattr(self, name), 0.0, 1.0)
        for name in _STEPS_M:
            _num(name, getattr(self, name), 0.0, 1.0, low_open=True, unit=" metres")
        for name in _LENGTHS_M:
            _num(name, getattr(self, name), 0.0, 1.0, unit=" metres")
        _num("search_reach_m", self.search_reach_m, 0.0, 5.0, unit=" metres")
        _int("search_screw_steps", self.search_screw_steps, 0, 20)
        _int("final_search_starts", self.final_search_starts, 1, 20)
        _num("wide_cut_m", self.wide_cut_m, 0.0, 5.0, unit=" metres")
        _num("restart_step_deg", self.restart_step_deg, 0.0, 45.0, unit=" degrees")
        _int("table_starts", self.table_starts, 0, 20)
        _num("table_max_tilt_deg", self.table_max_tilt_deg, 0.0, 90.0)
        _num("table_max_extent_m", self.table_max_extent_m, 0.0, 100.0, unit=" metres")
        _num("table_cell_m", self.table_cell_m, 0.002, 0.2, unit=" metres")
        _num("table_yaw_deg", self.table_yaw_deg, 0.0, 45.0)
        _num("table_yaw_step_deg", self.table_yaw_step_deg, 0.0, 45.0, low_open=True)
        _num("table_hole_weight", self.table_hole_weight, 0.0, 100.0)
        _int("trim_rounds", self.trim_rounds, 0, 20)
        _num("max_normal_angle_deg", self.max_normal_angle_deg, 0.0, 90.0, low_open=True)
        _num("band_slope", self.band_slope, 0.0, 100.0)
        _num("tukey_c", self.tukey_c, 0.0, 100.0, low_open=True)
        _num("inlier_sigmas", self.inlier_sigmas, 0.0, 100.0, low_open=True)
        _num("weak_eigenvalue", self.weak_eigenvalue, 0.0, 1.0)
        _num("tol_m", self.tol_m, 0.0, 1.0, low_open=True, unit=" metres")
        _num("max_seen_through", self.max_seen_through, 0.0, 1.0, low_open=True)
        _num("seen_through_margin_m", self.seen_through_margin_m, 0.0, 10.0, unit=" metres")
        _num("seen_through_margin_per_m2", self.seen_through_margin_per_m2, 0.0, 1.0,
             unit=" per metre")
        _num("seen_through_sigmas", self.seen_through_sigmas, 0.0, 100.0, unit=" sigmas")
        if not isinstance(self.noise, NoiseProfile):
            raise InputError(f"RegistrationParams.noise must be a NoiseProfile "
                             f"(robot_change.noise), got {type(self.noise).__name__}")
        _num("max_translation_m", self.max_translation_m, 0.0, 100.0, unit=" metres")
        _num("max_rotation_deg", self.max_rotation_deg, 0.0, 180.0)
        if self.min_depth_m is not None:
            _num("min_depth_m", self.min_depth_m, 0.0, 100.0, unit=" metres")
        _num("max_depth_m", self.max_depth_m, self.near_m, 100.0, low_open=True,
             unit=" metres")

    @property
    def near_m(self) -> float:
        """The nearest depth used, metres: ``min_depth_m``, or where that is None the camera's
        (``noise.near_m``)."""
        return self.noise.near_m if self.min_depth_m is None else float(self.min_depth_m)

    def replace(self, **changes: Any) -> RegistrationParams:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    def noise_args(self, inlier_sigmas: float | None = None) -> tuple:
        """What the agreement kernels take of the noise: (sigma table, inlier sigmas,
        :meth:`through_args` less the table)."""
        return (sigma_table(self.noise), self.inlier_sigmas if inlier_sigmas is None
                else inlier_sigmas, *self.through_args()[1:])

    def through_args(self) -> tuple:
        """The seen-through margin's (robot_change.noise.kernels.floored_margin_at): (sigma
        table, sigmas, floor m, floor per m^2)."""
        return (sigma_table(self.noise), self.seen_through_sigmas, self.seen_through_margin_m,
                self.seen_through_margin_per_m2)
