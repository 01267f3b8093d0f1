"""The parameters of a check (:class:`ChangeParams`): every ingredient of the method can be
switched so it can be measured; the defaults are the library's and the daemon's alike
(docs/evaluation.md has the numbers behind each).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

from robot_change import validate
from robot_change.change.registration import RegistrationParams
from robot_change.errors import InputError

__all__ = [
    "ChangeParams",
    "GROUND_DISTANCES",
    "METHODS",
    "NOVELTY_SEEDS",
    "OUTCOMES",
]


METHODS = ("novelty", "plain", "geometric", "nn")


#: What a check found: something changed, nothing changed, or the camera is not where the
#: reference was taken (registration failed or the offset is beyond the station tolerance).
OUTCOMES = ("changed", "no_change", "not_at_station")
GROUND_DISTANCES = ("euclidean", "wasserstein2")
NOVELTY_SEEDS = ("density", "density+free_space")


_num = functools.partial(validate.number, "ChangeParams")
_int = functools.partial(validate.whole, "ChangeParams")
_bool = functools.partial(validate.flag, "ChangeParams")
_choice = functools.partial(validate.choice, "ChangeParams")


@dataclasses.dataclass(frozen=True)
class ChangeParams:
    """Parameters of :func:`detect_changes`, validated on construction (:class:`InputError`
    naming the field, its value and what is allowed).

    Every ingredient can be switched so it can be measured (docs/evaluation.md has the
    numbers behind each default).
    """

    # --- the mixture part ------------------------------------------------------------------
    # True: novelty components over the other epoch's mixture held fixed (ours).  False: the
    # plain method, two independent fits and greedy EMD over all components.
    novelty: bool = True
    # Points below this quantile of the fixed mixture's log-density on its own cloud seed the
    # novelty components.
    novelty_quantile: float = 0.01
    # Which points seed the novelty components: "density" (log-density below the quantile) or
    # "density+free_space" (those, and the points the other epoch's depth image sees through).
    novelty_seed: str = "density+free_space"
    # Fixed components keep their relative weights in the novelty fit (only their total mass
    # is re-estimated), so the EMD of an unchanged view is ~0 instead of the reweighting noise.
    novelty_fix_weights: bool = True
    # True: MDL may split the seeded novelty components further (split-EM over the free
    # components); False: EM of the seeded components only (one component per connected
    # group of novel points).  Measured: F1 0.965 vs 0.964 (dev, single frame), 0.939 vs 0.932
    # (real), ~20 ms less per direction; so False.
    novelty_split: bool = False
    # EM tolerance of the novelty fit (change of mean log-likelihood per point; the seeds
    # start at their groups' moments, so EM has little to do).  1e-2 instead of
    # fit_mixture's 1e-3: the same F1 on the dev scenes and the real pairs, the two novelty
    # fits 48 -> 16 ms.
    novelty_tol: float = 1e-2
    # The current's own mixture for the mirror (reference cloud fitted with it held fixed),
    # when the current comes as a depth image without one: "fit" (split-EM from K = 1, as a
    # reference is built) or "from_reference" (EM from the reference mixture, all components
    # free, no splits: a removed object's component moves away or dies; ~5x faster: 10-16 ms
    # instead of 80-110 ms, same F1 to 0.001 on the dev scenes).
    current_mixture: str = "from_reference"
    # Most points the "from_reference" EM of the current's mixture runs on: above it, a fixed
    # stride subsample of the current cloud (0 = every point).  The mixture is only the
    # background the reference's points are held against; measured (bench/eval_change.py
    # --as-daemon, dev + real): 4000, 6000, 8000 and 12000 give the same changed points as
    # every point on every scene; a room view's fit (31k points) 9.0 ms -> 1.7 ms at 6000.
    current_fit_points: int = 6000
    # After the "from_reference" EM, a component of the current's mixture goes when more than
    # this share of the reference's points it explains best is seen through by the current
    # camera (the disappeared direction's free-space check): a removed object's component
    # that EM pulled onto the wall the object hid explains no surface of the current.  A
    # majority rule, not tuned: 0.5.
    gone_component_share: float = 0.5
    # Most novelty components on top of the fixed ones (bounds K = K_ref + this).
    max_novelty_components: int = 8
    # Ground distance between components for the EMD: "euclidean" (between means) or
    # "wasserstein2" (closed-form 2-Wasserstein between the Gaussians: shape counts).
    ground_distance: str = "wasserstein2"
    # True: greedy EMD (the paper's selection) decides which novelty components are changes,
    # by the acceptance rule below.  False: every novelty component is a candidate and the
    # free-space check decides point by point; the greedy trajectory is still computed and
    # reported.  Measured (docs/evaluation.md): on the table-top pairs the greedy loop stops
    # before the novelty components of objects that moved a few cm (their removal does not
    # lower the EMD): on the real table tops F1 0.524 with it vs 0.797 without against the
    # geometric truth (0.575 vs 0.953 against the changed objects whole); on the simulated
    # dev scenes no difference.  So off by default.
    greedy: bool = False
    # Acceptance rule on the greedy trajectory: a removal is accepted while its EMD drop is at
    # least accept_min_drop_m (metres: drop ~ weight x distance) AND at least
    # accept_min_drop_rel x the starting EMD, and the component holds at least
    # min_region_points points (N w_k).  The first rejected step stops the loop.
    accept_min_drop_m: float = 0.0005
    accept_min_drop_rel: float = 0.02
    # Segmentation: posterior mass of the accepted components above this.
    posterior_threshold: float = 0.5
    # --- the geometric part -----------------------------------------------------------------
    # Free-space check against the other epoch's depth image.
    free_space: bool = True
    # Seen through = other depth > own depth + free_space_sigmas x the noise of the
    # difference of two readings at that depth, sqrt(2 sigma(z)^2 + free_space_pose_m^2):
    # sigma(z) from the camera's profile (robot_change.noise; the reference's, raised by its
    # frames), free_space_pose_m what the registration and the camera's resting pose leave.
    # With the Kinect's profile: 3.0 / 3.0 / 4.2 / 7.3 / 12.7 cm at 0.5 / 1 / 2 / 3 / 4 m;
    # before the profile (until 2026-12-06) 3 cm + 0.004 z^2, a margin under 2 sigma beyond
    # 3.5 m, where a real Xtion's static rooms were reported changed (docs/evaluation.md).
    free_space_sigmas: float = 3.0
    free_space_pose_m: float = 0.01
    # ... and what it leaves of the camera's turn, degrees: what is seen through must be seen
    # through (in its core, away from flying pixels) at the estimate and at the poses turned
    # this much about the camera's x and y axes, or it makes no region by itself (a turn of
    # 0.5 degrees moves the image 5 px at an Xtion's focal length; real registrations were
    # 0.3-1 degree off on the SUN3D study room, docs/evaluation.md).  0: the estimate alone.
    free_space_pose_deg: float = 0.5
    free_space_no_reading_is_free: bool = True
    # The other image's nearest reading within this many pixels is compared (a camera back
    # at its station within a few pixels must not make static edges look seen through).
    free_space_pose_radius_px: int = 3
    # Where that window has no reading, the farthest reading within this many pixels stands
    # in (projector shadows and dropouts); 0 = the pixel alone.
    free_space_hole_radius_px: int = 5
    # With no reading in either window, a pixel is not seen through when a nearer reading
    # along its row could cast a shadow that wide on it: the camera's projector (structured
    # light) or second imager (stereo) stands the profile's shadow_baseline_m from it (Kinect,
    # PrimeSense, Xtion: 7.5 cm).  A table's edge or legs, a cupboard, 1-1.5 m away, shadow the
    # floor and wall behind them over 10-30 pixels, wider than the hole window.  And a camera
    # reads nothing nearer than the profile's min_range_m (about 0.5 m for those): a point
    # that lands nearer than that plus the margin on a pixel of the other image with no
    # reading was not observed by the other camera (a table's edge right before the robot,
    # an object close to the lens), rather than seen through.
    # With no reading in either window, a pixel is seen through only when the hole opens onto
    # something farther: the first reading along its row, to the left or to the right, lies
    # beyond the point by more than the margin.  A hole bordered only by surfaces at the
    # point's depth or nearer is a dropout, or the mark of a surface too near to read.
    free_space_hole_needs_far_edge: bool = True
    # A point passes when at least this fraction of its pixels are seen through.
    free_space_min_fraction: float = 0.5
    # Optional nearest-neighbour check: a changed point needs no point of the other epoch
    # within this distance (m); 0 = off.
    nn_check_m: float = 0.0
    # --- regions ----------------------------------------------------------------------------
    # Voxels are connected when their indices differ by at most this much per axis
    # (1 = the 26-neighbourhood).
    region_connectivity: int = 1
    # A region needs this many points (also the smallest group seeded as a novelty component)
    # and a box at least this long along its longest side (m); the daemon's wire parameters
    # min_region_points / min_region_extent_mm start from these.
    min_region_points: int = 12
    min_region_extent_m: float = 0.01
    # ... and it grows only from a connected group of changed points that holds at least this
    # many seen through in the core (robot_change.change.free_space: by a reading of the other
    # image, clear of flying pixels, at every pose the registration may be off by): what
    # noise, flicker, an edge a registration moved or a hole cannot make by themselves.
    evidence_min_points: int = 4
    # Changed points are completed to the objects they lie on (robot_change.change.objects):
    # the depth image is cut into surface segments, on cells of object_cell_px pixels, where
    # the surface folds inwards by more than object_fold_deg (an object's foot, an object
    # against a wall) or steps in depth, and a segment is claimed when the changed points'
    # pixels make up at least object_min_share of it (chosen on the 8000 station seeds, where
    # 0.3 / 0.2 / 0.12 gave F1 0.940 / 0.956 / 0.966 at the station; docs/algorithm.md), and
    # at least the share of the image it covers (a table top, a floor or a wall that fills
    # half the view is claimed only when half of it was found).
    object_completion: bool = True
    object_min_share: float = 0.12
    object_fold_deg: float = 20.0
    object_cell_px: int = 4
    # With completion, a segment also changed when it stands where a changed surface of the
    # other epoch stood: of its pixels that land on the same surface of the other image (a
    # reading within the free-space margin, the cells' normals within object_fold_deg), more
    # than object_counterpart_share land on changed points at least free_space_pose_radius_px
    # inside their outline (a majority; an object's foot is table), and those make up
    # object_min_share of it (an object moved by less than its own size: what the other
    # epoch's completion claimed is its other place).
    object_counterparts: bool = True
    object_counterpart_share: float = 0.5
    # ... or when it is hidden behind its other place: an object moved towards the camera
    # hides its old place behind the new one (away: the new behind the old), and nothing of
    # the hidden one is seen through.  More than object_hidden_share of its landing pixels lie
    # on or behind (by at most object_hidden_gap_m) changed points (nothing of it is still
    # seen unchanged where it stood: an object before which another was added showed 30 %),
    # and the two largest principal spreads of it and of the changed segment that hides it
    # most agree within a factor object_hidden_shape (a new object hides what stands behind
    # it too, and table pieces at an object's feet hide behind it; 0.9 from stations 8008
    # and 10005, the gap and the factor chosen before any run).
    object_hidden_gap_m: float = 0.3
    object_hidden_share: float = 0.9
    object_hidden_shape: float = 1.5
    # Run the mirror (what disappeared); False reports appearances only (the paper).
    disappeared: bool = True
    # Fewer points than this in either clean cloud raises EmptySceneError.
    min_cloud_points: int = 50
    # A current view that reads nothing where the reference read more than this share of
    # what the reference sees from there (robot_change.change.blind) raises EmptySceneError:
    # a lens covered, something nearer than the camera's minimum range.  Real pairs at most
    # 0.12 (static rooms, hand-held, table tops), another room 0.13, table stations 0.55 (15
    # cm off, a moved box nearer than the Kinect's 0.5 m: the one above 0.41 of 300 checks);
    # a lens covered 90 %: 0.89.  Chosen after seeing them all.
    max_unread_share: float = 0.7
    # Seed of the mixture fits (subsets); same seed, same result.
    seed: int = 0
    # Threads of one check: 2 runs the registration beside the current's cleaning, and what
    # appeared beside what disappeared (the kernels release the GIL), on two cores; 1 runs
    # all in the caller's thread.  The same result either way; the same CPU time, about 0.6x
    # the wall time on two cores (docs/benchmarks.md).
    threads: int = 2
    # --- registration -----------------------------------------------------------------------
    # How the current view is registered to the reference before comparing (and the station
    # tolerance); RegistrationParams(enabled=False) compares in the shared pixel grid.
    registration: RegistrationParams = RegistrationParams()

    def __post_init__(self) -> None:
        if not isinstance(self.registration, RegistrationParams):
            raise InputError(f"ChangeParams.registration must be a RegistrationParams, got "
                             f"{type(self.registration).__name__}")
        _choice("novelty_seed", self.novelty_seed, NOVELTY_SEEDS)
        _choice("current_mixture", self.current_mixture, ("fit", "from_reference"))
        for name in ("novelty", "novelty_fix_weights", "novelty_split", "greedy", "free_space",
                     "free_space_no_reading_is_free", "free_space_hole_needs_far_edge",
                     "object_completion", "object_counterparts", "disappeared"):
            _bool(name, getattr(self, name))
        _num("novelty_tol", self.novelty_tol, 0.0, 1.0, low_open=True)
        _num("novelty_quantile", self.novelty_quantile, 0.0, 0.5, low_open=True)
        _int("current_fit_points", self.current_fit_points, 0, 10**9)
        _num("gone_component_share", self.gone_component_share, 0.0, 1.0)
        _int("max_novelty_components", self.max_novelty_components, 1, 64)
        _choice("ground_distance", self.ground_distance, GROUND_DISTANCES)
        _num("accept_min_drop_m", self.accept_min_drop_m, 0.0, 100.0, unit=" metres")
        _num("accept_min_drop_rel", self.accept_min_drop_rel, 0.0, 1.0)
        _num("posterior_threshold", self.posterior_threshold, 0.0, 1.0, low_open=True,
             high_open=True)  # a share > 1.0 never is: 1.0 would switch detection off
        _num("free_space_sigmas", self.free_space_sigmas, 0.0, 100.0, low_open=True,
             unit=" sigmas")
        _num("free_space_pose_m", self.free_space_pose_m, 0.0, 10.0, unit=" metres")
        _num("free_space_pose_deg", self.free_space_pose_deg, 0.0, 10.0, unit=" degrees")
        _num("free_space_min_fraction", self.free_space_min_fraction, 0.0, 1.0, low_open=True)
        _num("nn_check_m", self.nn_check_m, 0.0, 10.0, unit=" metres")
        _int("free_space_pose_radius_px", self.free_space_pose_radius_px, 0, 50)
        _int("free_space_hole_radius_px", self.free_space_hole_radius_px, 0, 50)
        _int("region_connectivity", self.region_connectivity, 1, 3)
        _int("min_region_points", self.min_region_points, 1, 10**9)
        _int("evidence_min_points", self.evidence_min_points, 1, 10**9)
        _num("min_region_extent_m", self.min_region_extent_m, 0.0, 10.0, unit=" metres")
        _num("object_min_share", self.object_min_share, 0.0, 1.0, low_open=True)
        _num("object_counterpart_share", self.object_counterpart_share, 0.0, 1.0)
        _num("object_hidden_gap_m", self.object_hidden_gap_m, 0.0, 2.0, unit=" metres")
        _num("object_hidden_share", self.object_hidden_share, 0.0, 1.0)
        _num("object_hidden_shape", self.object_hidden_shape, 1.0, 10.0)
        _num("object_fold_deg", self.object_fold_deg, 0.0, 180.0, unit=" degrees")
        _int("object_cell_px", self.object_cell_px, 1, 64, unit=" pixels")
        _int("min_cloud_points", self.min_cloud_points, 1, 10**9)
        _num("max_unread_share", self.max_unread_share, 0.0, 1.0)
        _int("seed", self.seed, 0, 2**63 - 1)
        _int("threads", self.threads, 1, 2)

    def replace(self, **changes: Any) -> ChangeParams:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)
