"""The scoring totals, the pose levels, and the no-change and harsh-noise sets of
bench/eval_change.py: the real static rooms
(sim_fixtures.real_static: ``--static``, and with ``--real``), the held-out real static
recordings (``--heldout [DIR]``) and the harsh Kinect model's
no-change pairs and re-rendered changed scenes (sim_fixtures.real_noise / harsh_noise:
``--harsh``); how each is loaded and what each is told by.  A benchmark's helper, never a test.
"""

from __future__ import annotations

import numpy as np

from robot_change.change.scene import SceneParams, build_scene
from robot_change.noise.profile import builtin_profile

#: Offset groups of the simulated scenes: "" (the robot at its station) and the pose levels.
LEVELS = ("", "pose_2cm", "pose_5cm", "pose_10cm")


def level_of(name: str) -> str:
    """The pose level of a scene name ('' for a scene at its station)."""
    for level in LEVELS[1:]:
        if name.endswith("_" + level):
            return level
    return ""


def prf(tp, pred, true):
    p = tp / pred if pred else (1.0 if true == 0 else 0.0)
    r = tp / true if true else 1.0
    f = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return p, r, f


def summarise(rows: list[dict]) -> dict:
    tot = {k: sum(r[k] for r in rows) for k in ("app_tp", "app_pred", "app_true", "dis_tp",
                                                   "dis_pred", "dis_true")}
    a = prf(tot["app_tp"], tot["app_pred"], tot["app_true"])
    d = prf(tot["dis_tp"], tot["dis_pred"], tot["dis_true"])
    c = prf(tot["app_tp"] + tot["dis_tp"], tot["app_pred"] + tot["dis_pred"],
            tot["app_true"] + tot["dis_true"])
    return {"app_p": a[0], "app_r": a[1], "app_f1": a[2], "dis_p": d[0], "dis_r": d[1],
            "dis_f1": d[2], "p": c[0], "r": c[1], "f1": c[2], **tot}


def load_static(name: str, scene_params: SceneParams, heldout_dir=None, heldout=False):
    """A real static pair (sim_fixtures.real_static; ``heldout``: a held-out one, read from
    ``heldout_dir``, default real_static.HELDOUT_DIR): each side's frames fused with the pair's
    built-in noise profile (``pair.profile``), no truth (any change reported is false)."""
    from sim_fixtures.real_static import load_heldout_pair, load_static_pair

    pair = load_heldout_pair(name, heldout_dir) if heldout else load_static_pair(name)
    noise = builtin_profile(pair.profile)
    ref = build_scene(pair.reference, scene_params, intrinsics=pair.intrinsics,
                      source=f"{name}/reference", noise=noise)
    cur = build_scene(pair.current, scene_params, intrinsics=pair.intrinsics,
                      source=f"{name}/current", noise=noise)
    none = np.zeros(pair.reference[0].shape, bool)
    return ref, cur, none, none, pair


def load_heldout(name: str, scene_params: SceneParams, heldout_dir=None):
    """A held-out real static pair (sim_fixtures.real_static.load_heldout_pair), as
    :func:`load_static`."""
    return load_static(name, scene_params, heldout_dir, heldout=True)


def static_summary(rows: list[dict], within: dict[str, bool] | None = None) -> str:
    """The real static rooms' verdict: changed outcomes (must be 0), and within the promised
    range how many ended no_change (all must).  ``within``: each row's pair's
    ``within_range`` by name (default: the tuning pairs, loaded again to tell)."""
    from sim_fixtures.real_static import load_static_pair

    if within is None:
        within = {r["scene"]: load_static_pair(r["scene"]).within_range for r in rows}
    changed = [r["scene"] for r in rows if r["outcome"] == "changed"]
    inside = [r for r in rows if within[r["scene"]]]
    kept = [r["scene"] for r in inside if r["outcome"] != "no_change"]
    return (f"changed {len(changed)}/{len(rows)} {changed}; within range no_change "
            f"{len(inside) - len(kept)}/{len(inside)} (not: {kept})")


#: --harsh: the no-change pairs' seeds and offsets (metres), the current's frame counts.
HARSH_SEEDS = (0, 1)
HARSH_OFFSETS_M = (0.0, 0.03, 0.08)
HARSH_CURRENT_FRAMES = (3, 1)
#: --harsh: the range of depths (m) the target "F1 >= 0.95 at 1-3 m" speaks of.
HARSH_RANGE_M = (1.0, 3.0)


def harsh_none_checks() -> dict[str, tuple]:
    """name -> (layout, seed, offset m, current frames) of the harsh no-change rows, the two
    frame counts of one pair next to each other."""
    from sim_fixtures.real_noise import HARSH_LAYOUTS

    return {f"harsh_none_{lay}_s{seed}_{round(off * 100)}cm_{n}f": (lay, seed, off, n)
            for off in HARSH_OFFSETS_M for seed in HARSH_SEEDS for lay in HARSH_LAYOUTS
            for n in HARSH_CURRENT_FRAMES}


_HARSH_LAST: dict = {}


def load_harsh_pair(check: tuple, scene_params: SceneParams):
    """A harsh no-change row: the pair's reference fused from its 3 frames, the current from
    its first ``n`` (the last pair and its reference model are kept for the next row)."""
    from sim_fixtures.real_noise import harsh_pair

    layout, seed, offset, n = check
    key = (layout, seed, offset, scene_params)
    if _HARSH_LAST.get("key") != key:
        pair = harsh_pair(layout, seed, offset)
        ref = build_scene(pair.reference, scene_params, intrinsics=pair.intrinsics,
                          source=f"harsh/{layout}/reference")
        _HARSH_LAST.clear()
        _HARSH_LAST.update(key=key, pair=pair, ref=ref)
    pair, ref = _HARSH_LAST["pair"], _HARSH_LAST["ref"]
    cur = build_scene(pair.current[:n], scene_params, intrinsics=pair.intrinsics,
                      source=f"harsh/{layout}/current")
    none = np.zeros(pair.reference[0].shape, bool)
    return ref, cur, none, none, pair


def forget_harsh() -> None:
    """Drop the harsh reference kept between the no-change rows of one layout."""
    _HARSH_LAST.clear()


def harsh_changed_names() -> list[str]:
    """The stored changed Kinect-noise scenes of dev and holdout, at the station and revisited
    (what "harsh changes" re-renders)."""
    from sim_fixtures import load_scene, scene_names

    out = []
    for name in scene_names("dev") + scene_names("holdout"):
        sc = load_scene(name)
        if sc.meta["noise"]["model"] == "kinect" and sc.has_change \
                and sc.change != "not_at_station":
            out.append(name)
    return out


def load_harsh_scene(name: str, single_frame: bool, scene_params: SceneParams):
    """A "harsh changes" row: ``harsh_<scene>``, harsh_noise.harsh_scene of the stored scene."""
    from sim_fixtures.harsh_noise import harsh_scene

    sc = harsh_scene(name.removeprefix("harsh_"))
    ref = build_scene(sc.reference_frames(), scene_params, intrinsics=sc.intrinsics,
                      source=f"{name}/reference")
    frames = sc.current_frames()[:1] if single_frame else sc.current_frames()
    cur = build_scene(frames, scene_params, intrinsics=sc.intrinsics, source=f"{name}/current")
    return ref, cur, sc.truth_appeared, sc.truth_disappeared, sc


def change_depths_m(changes: list[dict]) -> list[float]:
    """The depth z (m) of the visible centroid of every changed side (before: reference
    camera, after: current camera) of scene.json-style ``changes``."""
    return [c[side]["visible_centroid_m"][2] for c in changes for side in ("before", "after")
            if side in c and c[side]["visible_centroid_m"] is not None]


def harsh_none_summary(rows: list[dict]) -> str:
    """The harsh no-change verdict: how many ended changed (must be 0) and how the rest ended."""
    changed = [r["scene"] for r in rows if r["outcome"] == "changed"]
    others = sorted({r["outcome"] for r in rows} - {"changed"})
    counts = ", ".join(f"{o} {sum(r['outcome'] == o for r in rows)}" for o in others)
    return f"changed {len(changed)}/{len(rows)} {changed}; {counts}"


def harsh_levels_summary(rows: list[dict]) -> str:
    """F1 / P / R of the harsh change rows per pose level."""
    cells = []
    for level in LEVELS:
        sel = [r for r in rows if level_of(r["scene"]) == level]
        if sel:
            t = summarise(sel)
            cells.append(f"{level or 'station'} F1 {t['f1']:.3f} P {t['p']:.3f} R {t['r']:.3f}")
    return " | ".join(cells)
