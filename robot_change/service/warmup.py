"""Warm-up: compile (or load from the numba cache) the kernels before the daemon says READY.

A cold cache (no warm-up of these sources marked it warm: robot_change.kernel_cache) takes
most of a minute on one core, so it is compiled in two helper processes at once
(``python -m robot_change.service.warmup --share registration|cloud PID``): the registration's,
the transport's, the depth decoders' and two kernels only a check reaches in one; the cloud's,
the mixture's, the free-space check's and the regions' in the other (25-26 and 25-27 s alone on
the 2-core test VM of 2026-12-07).  This process only waits, so its other threads keep the
interpreter to themselves (the daemon's link: BOOTING heartbeats every 100 ms, none more than
105 ms apart through a cold compile; a compile in this process held them up to 318 ms, its
garbage collector's full passes holding the interpreter 175-243 ms each).
Then the whole capture-and-check path runs here once, loading what the helpers left (it
compiles none), and the cache is marked warm.  A kernel no helper left (another argument type,
a helper that failed) is compiled here then: the helpers only save time, they are never needed.
A warm cache runs the whole path alone: about a second.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import numpy as np

from hw.depth import Intrinsics
from robot_change.arrays import readonly_view
from robot_change.change.detect import detect_changes
from robot_change.change.scene import build_scene
from robot_change.errors import EmptySceneError, InputError
from robot_change.kernel_cache import clear_stale_kernels, kernels_warm, mark_kernels_warm
from robot_change.service.config import Config
from robot_change.service.params import change_params

__all__ = ["warm_up"]

#: Longest wait for the helper processes before this process compiles the rest itself.
HELPER_TIMEOUT_S = 120.0


def _synthetic_room(width: int, height: int, box: bool = False) -> np.ndarray:
    """A small synthetic depth image: floor, back wall, a side wall, optionally a box."""
    cam = Intrinsics.openni_default(width, height)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x = (u - cam.cx) / cam.fx
    y = (v - cam.cy) / cam.fy
    z = np.full((height, width), 3.0)  # back wall 3 m ahead
    floor = np.where(y > 1e-6, 1.0 / np.maximum(y, 1e-6), np.inf)  # floor 1 m below the camera
    z = np.minimum(z, floor)
    side = np.where(x > 1e-6, 1.2 / np.maximum(x, 1e-6), np.inf)  # wall 1.2 m to the right
    z = np.minimum(z, side)
    if box:
        px, py = x * 2.0, y * 2.0  # a 40 cm box standing 2 m ahead
        inside = (np.abs(px + 0.2) < 0.2) & (py > 0.6) & (py < 1.0)
        z = np.where(inside, np.minimum(z, 2.0), z)
    ripple = 0.002 * np.sin(u * 0.7) * np.cos(v * 0.5)
    return np.clip((z + ripple) * 1000.0, 0, 65535).astype(np.uint16)


def _tiny_scene() -> tuple[Intrinsics, tuple[np.ndarray, np.ndarray]]:
    width, height = 160, 120
    return Intrinsics.openni_default(width, height), (_synthetic_room(width, height),
                                                      _synthetic_room(width, height, box=True))


def _registration_share() -> None:
    """A helper's share: the registration's kernels (the same argument types as a
    check: a read-only reference image, a writable current one), two kernels only a check
    reaches (:func:`_check_only_kernels`), the depth decoders' and the transport's (the greedy
    EMD on mixture-sized problems; the exact :func:`emd` alone is on no capture or check
    path)."""
    from robot_change.change import registration
    from robot_change.change.transport import greedy_emd, ground_distance

    cam, rooms = _tiny_scene()
    for before, after in (rooms, rooms[::-1]):
        reference = before.copy()
        reference.setflags(write=False)
        registration.register_depth(reference, after.copy(), cam)
    _table_top_kernels()
    _check_only_kernels()
    _decoder_kernels()
    rng = np.random.default_rng(0)
    for k in (6, 9):
        means_a, means_b = rng.random((k, 3)), rng.random((k + 2, 3))
        covs_a = np.repeat(np.eye(3)[None] * 0.01, k, axis=0)
        covs_b = np.repeat(np.eye(3)[None] * 0.02, k + 2, axis=0)
        cost = ground_distance(means_a, means_b, covs_a, covs_b, kind="wasserstein2")
        weights_a, weights_b = rng.random(k) + 0.1, rng.random(k + 2) + 0.1
        candidates = np.zeros(k + 2, dtype=bool)
        candidates[k:] = True
        greedy_emd(weights_a, weights_b, cost, candidates, 2)


def _check_only_kernels() -> None:
    """Two kernels of a check that the synthetic room does not reach before the whole path
    (the core's read-through at the turned poses, the moved objects' counterparts), called
    on empty inputs with the argument types a check gives them (read-only depth images and
    sigma tables, an int64 sensing window), so that they are compiled here, not on the
    whole path after both shares."""
    from robot_change.change.free_space import _read_through_kernel
    from robot_change.change.objects import _counterparts_kernel

    depth = readonly_view(np.zeros((4, 4), np.uint16))
    labels = np.full((4, 4), -1, np.int32)
    window = np.array([0, 0, 4, 4], np.int64)
    noise = readonly_view(np.ones(8))
    normals = np.zeros((1, 1, 3), np.float32)
    _counterparts_kernel(labels, 0, depth, np.eye(3), np.zeros(3), 1.0, 1.0, 2.0, 2.0, window,
                         0.1, 5.0, depth, readonly_view(labels), np.zeros(0, np.bool_), 1,
                         normals, normals, 4, noise, 3.0, 0.01, 0.9, 2, 0.5, labels.copy(), 0)
    flat = depth.ravel()
    _read_through_kernel(flat, np.zeros(0, np.int64), np.eye(3)[None].copy(), np.zeros((1, 3)),
                         1.0, 1.0, 2.0, 2.0, 4, window, 0.1, 5.0, np.zeros(16, np.uint16),
                         np.zeros(16, np.uint16), flat, noise, 3.0, 0.01, 0.0)


def _free_space_kernels(cam: Intrinsics, rooms) -> None:
    """The free-space check's kernels, with the argument types a reference's cloud gives them
    (a read-only (H, W) int32 pixel -> point map, uint16 depth images), on the synthetic rooms
    without cleaning them."""
    from robot_change.change.free_space import free_space_votes
    from robot_change.noise.profile import DEFAULT_PROFILE, builtin_profile, sigma_table

    profile = builtin_profile(DEFAULT_PROFILE)

    offset = np.eye(4)
    offset[:3, 3] = (0.01, 0.0, 0.0)
    for before, after in (rooms, rooms[::-1]):
        valid = before > 0
        pixel_voxel = np.full(before.shape, -1, np.int32)
        pixel_voxel[valid] = np.arange(int(valid.sum())) // 4
        pixel_voxel.setflags(write=False)
        n_points = int(pixel_voxel.max()) + 1
        free_space_votes(pixel_voxel, after, before.copy(), n_points, sigma_table(profile),
                         3.0, 0.01, 3, 5, True, intrinsics=cam, other_from_own=offset,
                         edge_px=profile.edge_px)


def _region_kernels() -> None:
    """The regions' kernels, with the argument type a cloud gives them (read-only int64 voxel
    keys), and the object completion's surface segments (float32 vertex and normal maps) and
    their pixels (read-only depth and pixel maps, as every epoch's are passed)."""
    from robot_change.change.objects import _pixels_kernel
    from robot_change.change.regions import label_voxel_components
    from robot_change.change.registration.surfaces import cell_segments

    keys = np.arange(500, dtype=np.int64) * 3
    keys.setflags(write=False)
    label_voxel_components(keys, 1)
    cells = np.zeros((6, 6, 3), np.float32)
    cells[..., 2] = 1.0
    labels = readonly_view(cell_segments(cells, -cells, 0.9, 0.03, 0.01, 2))  # as kept
    depth = np.full((24, 24), 1000, np.uint16)
    pixel_voxel = np.zeros((24, 24), np.int32)
    _pixels_kernel(readonly_view(depth), readonly_view(pixel_voxel), labels, cells, -cells, 4,
                   500.0, 500.0, 12.0, 12.0, 0.03, 0.01, 2)


def _decoder_kernels() -> None:
    """The depth decoders' kernels (a PNG's rows, an RVL stream), which a bag, a RealSense
    recording or an image folder's first frame would otherwise compile in the camera thread."""
    from hw.compressed_depth import decode_compressed_depth, encode_compressed_depth

    depth = np.arange(16, dtype=np.uint16).reshape(4, 4)
    for codec in ("png", "rvl"):
        decode_compressed_depth(*encode_compressed_depth(depth, codec), "warm-up")


def _cloud_share() -> None:
    """The other helper's share: the cloud's, the mixture's (a reference built, the current's
    mixture, the novelty fit over a background), the free-space check's and the regions'
    kernels, without registration or EMD (the default configuration's
    argument types: a configuration's values do not change them)."""
    from robot_change.change.greedy import posteriors
    from robot_change.mixture.model import fit_mixture, fit_over_background

    cam, rooms = _tiny_scene()
    params = Config().scene_params()
    for before, _after in (rooms, rooms[::-1]):
        try:
            reference = build_scene(np.stack([before] * 2), params, intrinsics=cam)
        except (EmptySceneError, InputError):
            continue
        mix = reference.mixture
        points = reference.cloud.points
        refit = fit_mixture(points, init=mix, leaf=params.cloud.leaf_m, split=False, tol=1e-2)
        log_bg = mix.score_samples(points)
        seed_w = np.array([0.9, 0.1])
        novelty = fit_over_background(points, mix, log_bg, seed_w, mix.means[:1],
                                      mix.covariances[:1], leaf=params.cloud.leaf_m, tol=1e-2)
        posteriors(novelty, points, np.arange(len(points)), (mix.n_components, log_bg))
        del refit
    _free_space_kernels(cam, rooms)
    _region_kernels()


#: The helpers' shares, by the name their command line gives.
SHARES = {"registration": _registration_share, "cloud": _cloud_share}


def _start_helper(share: str) -> subprocess.Popen | None:
    """A helper process for ``share`` (same interpreter, same numba cache), or None when it
    cannot start."""
    try:
        return subprocess.Popen([sys.executable, "-m", "robot_change.service.warmup",
                                 "--share", share, str(os.getpid())],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except OSError:
        return None


def _compile_in_helpers() -> None:
    """Both shares at once, each in a helper process; wait at most HELPER_TIMEOUT_S for them
    (one that is not done is killed: the whole path compiles what it left)."""
    procs = [proc for proc in map(_start_helper, SHARES) if proc is not None]
    end = time.monotonic() + HELPER_TIMEOUT_S
    try:
        for proc in procs:
            try:
                proc.wait(timeout=max(0.0, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def warm_up(config: Config | None = None, helper: bool = True) -> float:
    """Compile (or load from the numba cache) every kernel a capture and a check use, on a tiny
    synthetic scene; returns the seconds it took.  ``helper``: compile a cold cache in helper
    processes (see the module's docstring); False: all here."""
    config = config or Config()
    t0 = time.perf_counter()
    clear_stale_kernels()  # before any kernel is loaded: a callee's change numba cannot see
    if helper and not kernels_warm():
        _compile_in_helpers()
    _whole_path(config)
    mark_kernels_warm()
    return time.perf_counter() - t0


def _whole_path(config: Config) -> None:
    """Every kernel a capture and a check use, on the tiny scene: both directions, through a
    registration and through a given transform, the table-top registration kernels and the
    depth decoders'."""
    cam, rooms = _tiny_scene()
    params = config.scene_params()
    # regions of any size, and any registration taken as at the station, so that every stage
    # runs on the tiny scene (both directions; the box is a large share of it)
    change = change_params(config, config.parameters()).replace(min_region_points=1)
    change = change.replace(registration=change.registration.replace(
        min_fitness=0.0, max_seen_through=1.0, max_translation_m=100.0,
        max_rotation_deg=180.0))
    # a transform taken as given (registration off): the comparison through a transform
    shifted = change.replace(registration=change.registration.replace(enabled=False))
    offset = np.eye(4)
    offset[:3, 3] = (0.01, 0.0, 0.0)
    for before, after in (rooms, rooms[::-1]):
        try:
            reference = build_scene(np.stack([before] * 2), params, intrinsics=cam,
                                    source="warm-up")
            detect_changes(reference, after, change)
            detect_changes(reference, after, shifted, initial_pose=offset)
        except (EmptySceneError, InputError):
            pass  # a tiny scene may be too small for some parameter set; kernels ran anyway
    _table_top_kernels()
    _decoder_kernels()


def _table_top_kernels() -> None:
    """The registration kernels only a table reaches (the table-plane starts' grid; the
    table station's counts over many poses; the synthetic room passes neither gate), with
    the argument types a check gives them: float32 vertex maps, float64 transforms."""
    from robot_change.change.registration import (
        RegistrationParams,
        agreement,
        table_top,
    )

    v = np.zeros((2, 2, 3), np.float32)
    table_top._plane_grid(v, np.eye(3), np.zeros(3), 0.02, 0.0, 0.0, 8, 8, 0.015, 0.03)
    agreement.through_counts(v, v, np.eye(3)[None], np.zeros((1, 3)), 1.0, 1.0, 0.5, 0.5,
                             *RegistrationParams().through_args())


def _exit_with_parent(parent: int) -> None:
    """The helper ends when the process that started it (pid ``parent``) is gone -- a daemon
    stopped mid-way -- or when it is handed to another parent."""
    first = os.getppid()

    def alive() -> bool:
        try:
            os.kill(parent, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True

    def watch() -> None:
        while os.getppid() == first and alive():
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, name="rc-warmup-parent", daemon=True).start()


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--share" and sys.argv[2] in SHARES:
        _exit_with_parent(int(sys.argv[3]))
        SHARES[sys.argv[2]]()
