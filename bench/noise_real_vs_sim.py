"""Real depth noise against the simulated one (sim_fixtures.noise, .harsh_noise), measured alike.

    .venv/bin/python bench/noise_real_vs_sim.py [--data ../shared/data] [--plot PNG | --no-plot]
        [--json OUT] [--fit [--rounds N]] [--layouts]

Real: SUN3D's study room (ASUS Xtion, 50 frames of a static room, hand-held camera 1.2-1.9 cm
a frame): pairs of consecutive frames and of frames 5 apart, the given poses improved by
point-to-plane alignment (``sim_fixtures.real_noise.refine_pose``: the poses are good to ~1 cm,
more than the noise); PCL's grabber sequence (3 Kinect-class frames 0.25 s apart, 0.7-1.7 m,
tiny motion, aligned from the identity); the edges of SUN3D, rtabmap's two lab views and PCL's
five room clouds (single frames).

Simulated: a study-room aisle like SUN3D's (cubicle panels, chairs, a far end at ~7 m; SUN3D's
intrinsics), three views along it, rendered by sim_fixtures.render: two frames of one pose
(``static``: independent per-frame noise, same epoch), and the pose moved 1.5 cm / 0.3 deg
(``pose1.5``, against SUN3D's consecutive frames) and 7.5 cm / 1 deg (``pose7.5``, against
frames 5 apart), each a new epoch, aligned like the real ones.  Once with the old KinectNoise,
once with RealisticKinectNoise (the harsh model).  ``--layouts`` adds the five stored room
layouts (office, lounge, lab, storage, meeting) as a check of another geometry.

Statistics (sim_fixtures.real_noise): per 0.5 m bin of depth the frame-to-frame difference's
robust sigma, its 99 % quantile, the flicker rate (valid in one frame, not in the other), the
whole-step rate, the sigma of its 31x31 px box mean (the correlated part) and its
correlation at 1-16 px; at edges the flying-pixel share and band width.  Prints a table and
draws ``--plot`` (default docs/img/noise_real_vs_sim.png).

``--fit`` re-fits the harsh model's per-frame sigma, correlation, dropout, error field,
flying-pixel, grazing, registration-fill and edge-drop parameters to SUN3D, starting from the
defaults (grids and a few rounds of ratio updates, see :func:`fit`), prints them, and uses
them for the table; the defaults of ``RealisticKinectNoise`` are its output.  A benchmark,
never a test: ~25 s on the 2-core machine, ``--fit`` ~3 min, ``--layouts`` ~20 s more.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hw.depth import Intrinsics  # noqa: E402
from hw.imagefile import read_image  # noqa: E402
from sim_fixtures.harsh_noise import RealisticKinectNoise  # noqa: E402
from sim_fixtures.noise import KinectNoise  # noqa: E402
from sim_fixtures.real_noise import (  # noqa: E402
    DEFAULT_BINS_M,
    edge_stats,
    fit_quant_c,
    pair_stats,
    refine_pose,
)
from sim_fixtures.render import Pose, render  # noqa: E402
from sim_fixtures.scenes import SCENES, bin_, box, chair, pose_offset, room, table  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
SUN3D_K = (570.342205, 570.342205, 320.0, 240.0)
SUN3D_INTR = Intrinsics(640, 480, *SUN3D_K)
GRABBER_K = (525.0, 525.0, 320.0, 240.0)
LAYOUTS = ("office_no_change", "lounge_chair_removed", "lab_crate_moved",
           "storage_carton_removed", "meeting_box_added")


# ----------------------------------------------------------------------------- real data


def sun3d(data: Path):
    folder = data / "sun3d-studyroom-xtion-50f-pose" / "frames"
    files = sorted(glob.glob(str(folder / "frame-*.depth.png")))
    if not files:
        raise SystemExit(f"no SUN3D frames in {folder} (--data: the shared data folder)")
    depths = [read_image(f) for f in files]
    poses = [np.loadtxt(f.replace(".depth.png", ".pose.txt")) for f in files]
    return depths, poses


def sun3d_pairs(depths, poses, gap: int, every: int) -> list[tuple]:
    """(a, b, T_b_from_a refined, K) for frames i, i + gap, i = 0, every, ..."""
    out = []
    for i in range(0, len(depths) - gap, every):
        j = i + gap
        T = np.linalg.inv(poses[j]) @ poses[i]
        out.append((depths[i], depths[j], refine_pose(depths[i], depths[j], T, SUN3D_K),
                    SUN3D_K))
    return out


def grabber_pairs(data: Path) -> list[tuple]:
    files = sorted(glob.glob(str(data / "pcl-grabber-seq" / "*_depth.tiff")))
    d = [read_image(f) for f in files]
    return [(d[i], d[j], refine_pose(d[i], d[j], np.eye(4), GRABBER_K), GRABBER_K)
            for i, j in ((0, 1), (1, 2), (0, 2))]


def edge_frames(data: Path) -> dict[str, list[np.ndarray]]:
    out = {}
    files = sorted(glob.glob(str(data / "rtabmap-kinect-lab-2views" / "depth" / "*.png")))
    out["rtabmap"] = [read_image(f) for f in files]
    clouds = sorted(glob.glob(str(data / "pcl-pairwise-kinect-room-5views" / "*.pcd")))
    if clouds:
        from hw.depth import open_depth

        frames = []
        for c in clouds:
            with open_depth(f"pcd:{c}") as cam:
                frames.append(cam.read().depth)
        out["pcl-room"] = frames
    return out


# ----------------------------------------------------------------------------- simulation


def study_aisle():
    """A cubicle aisle like SUN3D's study room: panels 1.45 m high, chairs, desks, a bin, the
    aisle's end ~7 m away; the camera 1.45 m up, pitched 24 deg down."""
    objs = room(7.6, 4.4, 2.7) + [
        box("panel_front", 2.45, 0.85, (0.06, 1.7, 1.45)),
        box("panel_right", 5.0, 1.7, (5.0, 0.06, 1.45)),
        box("panel_left", 5.2, 3.3, (4.6, 0.06, 1.45)),
        box("panel_l1", 4.0, 3.9, (0.06, 1.2, 1.45)),
        box("panel_l2", 6.0, 3.9, (0.06, 1.2, 1.45)),
        table("desk_l1", 4.9, 3.85, w=1.6, d=0.7),
        chair("chair", 2.1, 2.55, yaw_deg=200),
        chair("chair_2", 4.3, 2.9, yaw_deg=160),
        chair("chair_3", 6.4, 2.2, yaw_deg=20),
        bin_("bin", 1.9, 0.55, r=0.2, h=0.65),
        box("cabinet", 7.3, 2.6, (0.5, 1.0, 1.2)),
    ]
    return objs, Pose((0.2, 2.3, 1.45), -12.0, 24.0, 0.0)


@dataclasses.dataclass
class SimViews:
    """Ideal renders: per view the base render and the renders 1.5 / 7.5 cm away, with the
    true T_b_from_a of each."""

    base: list
    moved: dict  # tag -> list of (render, T_b_from_a)
    intrinsics: list


def sim_views(scenes: str = "aisle", baseline: float = 0.075) -> SimViews:
    base, moved, intr = [], {"pose1.5": [], "pose7.5": []}, []
    items = []
    if scenes == "aisle":
        objs, pose = study_aisle()
        for k, dx in enumerate((0.0, 0.35, 0.7)):
            items.append((objs, pose.moved(dx=dx, dyaw_deg=4.0 * k), SUN3D_INTR, 900 + k))
    else:
        for k, name in enumerate(LAYOUTS):
            spec = SCENES[name]
            items.append((spec.reference, spec.reference_pose, spec.intrinsics, 950 + k))
    for objs, pose, K, seed in items:
        base.append(render(objs, pose, K, None, baseline))
        intr.append(K)
        for tag, (t, deg) in (("pose1.5", (0.015, 0.3)), ("pose7.5", (0.075, 1.0))):
            other = pose_offset(pose, t, deg, seed + (0 if tag == "pose1.5" else 50))
            T = np.linalg.inv(other.matrix()) @ pose.matrix()
            moved[tag].append((render(objs, other, K, None, baseline), T))
    return SimViews(base, moved, intr)


def sim_frames(views: SimViews, noise, seed: int = 0) -> list[np.ndarray]:
    """Single frames for the edge statistics: two of every base view, one of every moved."""
    out = []
    for v, r in enumerate(views.base):
        out += [noise.apply(r, np.random.default_rng([seed, v, 0, k])) for k in range(2)]
        for i, tag in enumerate(("pose1.5", "pose7.5")):
            out.append(noise.apply(views.moved[tag][v][0],
                                   np.random.default_rng([seed, v, 1, i])))
    return out


def sim_pairs(views: SimViews, noise, seed: int = 0) -> dict[str, list[tuple]]:
    """Frame pairs of ``noise`` on ``views``: 'static', 'pose1.5', 'pose7.5'."""
    out = {"static": [], "pose1.5": [], "pose7.5": []}
    frames = []
    epoch1 = noise.for_epoch(1) if hasattr(noise, "for_epoch") else noise
    for v, (r, K) in enumerate(zip(views.base, views.intrinsics, strict=True)):
        k = (K.fx, K.fy, K.cx, K.cy)
        a = noise.apply(r, np.random.default_rng([seed, v, 0, 0]))
        b = noise.apply(r, np.random.default_rng([seed, v, 0, 1]))
        out["static"].append((a, b, None, k))
        frames += [a, b]
        for tag in ("pose1.5", "pose7.5"):
            rb, T = views.moved[tag][v]
            c = epoch1.apply(rb, np.random.default_rng([seed, v, 1, 0 if tag == "pose1.5" else 1]))
            out[tag].append((a, c, refine_pose(a, c, T, k), k))
            frames.append(c)
    out["frames"] = frames
    return out


# ----------------------------------------------------------------------------- measuring


def measure(pairs: dict[str, list]) -> dict:
    return {tag: pair_stats(p) for tag, p in pairs.items() if tag != "frames"}


def fmt(values, scale=1.0, digits=1) -> str:
    return " ".join(" " * 6 + "-" if not np.isfinite(v) else f"{v * scale:7.{digits}f}"
                    for v in values)


def text_table(real: dict, sims: dict, edges: dict) -> str:
    """The comparison as text."""
    bins = DEFAULT_BINS_M
    centres = (bins[1:] + bins[:-1]) / 2
    lines = ["depth bin (m)          " + " ".join(f"{c:7.2f}" for c in centres)]

    def block(title, attr, scale, digits, rows):
        lines.append(title)
        for label, st in rows:
            lines.append(f"  {label:21s}" + fmt(getattr(st, attr), scale, digits))

    rows = [("real SUN3D +1", real["sun3d_1"]), ("real SUN3D +5", real["sun3d_5"]),
            ("real grabber", real["grabber"])]
    for name, st in sims.items():
        rows += [(f"{name} static", st["static"]), (f"{name} pose1.5", st["pose1.5"]),
                 (f"{name} pose7.5", st["pose7.5"])]
    block("pixels (thousands)", "n", 1e-3, 0, rows)
    block("difference sigma (mm, 1.4826 MAD)", "sigma", 1e3, 1, rows)
    block("|difference| 99 % (mm)", "q99", 1e3, 0, rows)
    block("quantisation step (mm)", "step", 1e3, 1, rows)
    block("flicker valid<->invalid (%)", "flicker", 100, 2, rows)
    block("whole-step rate, >= 1 step (%)", "jump", 100, 1, rows)
    block("whole-step rate, >= 2 steps (%)", "jump2", 100, 1, rows)
    block("low-frequency sigma, 31 px box mean (mm)", "lowfreq_sigma", 1e3, 1, rows)
    lines.append("correlation of the difference at lags " +
                 " ".join(f"{v:d}" for v in real["sun3d_1"].corr_lags) + " px (1.5-5 m)")
    for label, st in rows:
        lines.append(f"  {label:21s}" + " ".join(f"{c:6.2f}" for c in st.corr))
    lines.append("edges (single frames): crossings, flying share, holes, width hist 0/1/2/3/4+,"
                 " mean width; flying share per fore depth bin (%)")
    for label, e in edges.items():
        lines.append(f"  {label:21s} {e.crossings:6d} {100 * e.flying_share:5.2f}% "
                     f"{100 * e.hole_share:5.2f}%  "
                     + "/".join(f"{100 * h:.1f}" for h in e.width_hist)
                     + f"  {e.mean_width:.2f}   " + fmt(e.flying_share_by_bin, 100, 1))
    return "\n".join(lines)


def plot(real: dict, sims: dict, edges: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bins = DEFAULT_BINS_M
    c = (bins[1:] + bins[:-1]) / 2
    fig, axes = plt.subplots(2, 2, figsize=(10.5, 7.6))
    colours = {"old KinectNoise": "tab:blue", "RealisticKinectNoise": "tab:red"}
    ax = axes[0, 0]
    ax.plot(c, real["sun3d_1"].sigma * 1e3, "k-o", label="real SUN3D, consecutive")
    ax.plot(c, real["sun3d_5"].sigma * 1e3, "k--s", mfc="none", label="real SUN3D, 5 apart")
    ax.plot(c, real["grabber"].sigma * 1e3, "k:^", label="real PCL grabber")
    for name, st in sims.items():
        ax.plot(c, st["pose1.5"].sigma * 1e3, "-o", color=colours[name], ms=4,
                label=f"{name}, 1.5 cm")
        ax.plot(c, st["pose7.5"].sigma * 1e3, "--s", color=colours[name], ms=4, mfc="none",
                label=f"{name}, 7.5 cm")
    ax.set_yscale("log")
    ax.set_xlabel("depth (m)")
    ax.set_ylabel("frame-to-frame difference sigma (mm)")
    ax.set_title("difference sigma (1.4826 MAD) per 0.5 m bin")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)

    ax = axes[0, 1]
    ax.plot(c, real["sun3d_1"].flicker * 100, "k-o", label="real SUN3D, consecutive")
    ax.plot(c, real["sun3d_5"].flicker * 100, "k--s", mfc="none", label="real SUN3D, 5 apart")
    for name, st in sims.items():
        ax.plot(c, st["pose1.5"].flicker * 100, "-o", color=colours[name], ms=4,
                label=f"{name}, 1.5 cm")
        ax.plot(c, st["static"].flicker * 100, ":", color=colours[name],
                label=f"{name}, same pose")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.set_xlabel("depth (m)")
    ax.set_ylabel("valid <-> invalid between frames (%)")
    ax.set_title("flicker rate")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)

    ax = axes[1, 0]
    ax.plot(c, real["sun3d_1"].lowfreq_sigma * 1e3, "k-o", label="real SUN3D, consecutive")
    ax.plot(c, real["sun3d_5"].lowfreq_sigma * 1e3, "k--s", mfc="none",
            label="real SUN3D, 5 apart")
    for name, st in sims.items():
        ax.plot(c, st["pose1.5"].lowfreq_sigma * 1e3, "-o", color=colours[name], ms=4,
                label=f"{name}, 1.5 cm")
        ax.plot(c, st["pose7.5"].lowfreq_sigma * 1e3, "--s", color=colours[name], ms=4,
                mfc="none", label=f"{name}, 7.5 cm")
    ax.set_yscale("log")
    ax.set_xlabel("depth (m)")
    ax.set_ylabel("sigma of the 31x31 px mean (mm)")
    ax.set_title("correlated (low-frequency) part of the difference")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)

    ax = axes[1, 1]
    styles = {"real SUN3D": ("k", "-o"), "real rtabmap": ("0.4", "-^"),
              "real pcl-room": ("0.6", "-v"), "old KinectNoise": ("tab:blue", "-o"),
              "RealisticKinectNoise": ("tab:red", "-o")}
    for label, e in edges.items():
        colour, style = styles.get(label, ("tab:green", "-o"))
        ax.plot(c, e.flying_share_by_bin * 100, style, color=colour, ms=4,
                label=f"{label}: {100 * e.flying_share:.1f} % flying, "
                      f"{100 * e.hole_share:.0f} % holes")
    ax.set_yscale("symlog", linthresh=0.5)
    ax.set_xlabel("foreground depth (m)")
    ax.set_ylabel("flying pixels at edges (%)")
    ax.set_title("edges: depth between fore- and background")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=72)
    plt.close(fig)


# ----------------------------------------------------------------------------- fitting


def _ls_power(z, y, w, ref=4.0, exponents=(0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0)):
    """Fit y = A (z / ref)^k, k from ``exponents``, A >= 0 by weighted least squares (weights
    ``w`` on the squared residuals; NaN targets left out); (A, k)."""
    ok = np.isfinite(y) & np.isfinite(w) & (w > 0)
    best = None
    for k in exponents:
        x = (z[ok] / ref) ** k
        A = max(float(np.sum(w[ok] * x * y[ok]) / np.sum(w[ok] * x * x)), 0.0)
        res = float(np.sum(w[ok] * (y[ok] - A * x) ** 2))
        if best is None or res < best[0]:
            best = (res, A, k)
    return best[1], best[2]


def fit(real: dict, views: SimViews, edges_real, start: RealisticKinectNoise,
        rounds: int = 4, log=print) -> RealisticKinectNoise:
    """The harsh model's parameters fitted to SUN3D: its consecutive pairs against the
    simulated 1.5 cm pairs of the study aisle, its frames' edges against the simulated frames'.

    First grids, in this order: ``noise_corr_px`` (2.5-5 px) to the difference's correlation
    at 1, 2 and 4 px; ``register_fill_px`` (2-6) to the hole share at edges; the grazing
    ramp's start (86-80 deg, 2 deg wide; without dropouts) so that the flicker at >= 4 m
    exceeds SUN3D's least (on a tie the higher start: fewer drops); the flying-pixel
    probability p4 (z / 4)^k (p4 0-0.5, k 2-4) to SUN3D's flying share per bin of the
    foreground depth (relative squared error, bins with >= 200 edge pixels in both).  Then
    ``rounds`` rounds of ratio updates, each re-simulating with the last values:

    - per-frame sigma a + b (z - 0.4)^p: the model's sigma per bin times real / simulated
      difference sigma, refitted by least squares of relative residuals for p in 2-3
      (bins of 1-5 m with >= 20k real pixels, weighted by the square root of their
      pixels);
    - dropout p4 (z / 4)^k: the model's rate plus real - simulated flicker, fitted over the
      bins of 2-6 m (least squares weighted by the root of the bin's pixels, k in 0-4 by
      half steps, as below);
    - error field A (z / 4)^k: the low-frequency sigma's excess over the model without a
      field, sqrt((real^2 - sim_without^2) / 2) (two independent fields; 0 where there is
      none), fitted likewise over the bins of 1-5 m;
    - edge drop probability: times the real hole share's excess over the simulated one
      without edge drops, over the simulated excess (0 where the real share is below it).

    Last, as a diagnostic only, a grid of the residual lens distortion ``k1`` (0-0.25)
    against how much larger SUN3D's difference sigma and low-frequency sigma are 5 frames
    apart than 1 apart (the simulated 7.5 cm pairs over the 1.5 cm ones; squared log
    ratios).  It is not taken over: only k1 >= 0.2 comes near the real growth of the
    low-frequency part, none reproduces the growth of the sigma (real 1.14-1.31x,
    simulated 1.0-1.2x), so the growth has another cause as well (the poses' error over
    7.5 cm, the sensor's own depth warping), and a k1 of 0.2 is not the small residual of
    a factory undistortion.  Every simulation of one step uses the same seed, so the rounds
    converge instead of chasing noise.
    """
    st = real["sun3d_1"]
    bins = DEFAULT_BINS_M
    z = (bins[1:] + bins[:-1]) / 2
    use = (st.n >= 20000) & (z > 1.0) & (z < 5.0)
    w = np.where(use, st.n.astype(float), 0.0)
    model = start
    best = None
    for corr_px in (2.5, 3.0, 3.5, 4.0, 5.0):
        m = dataclasses.replace(model, noise_corr_px=corr_px)
        c = pair_stats(sim_pairs(views, m, seed=50)["pose1.5"]).corr
        err = float(np.sum((c[:3] - st.corr[:3]) ** 2))
        log(f"noise_corr_px {corr_px}: correlation " + " ".join(f"{v:.2f}" for v in c) +
            " (real " + " ".join(f"{v:.2f}" for v in st.corr) + f"), error {err:.4f}")
        if best is None or err < best[0]:
            best = (err, corr_px)
    model = dataclasses.replace(model, noise_corr_px=best[1])
    best = None
    for fill in (2, 3, 4, 5, 6):
        m = dataclasses.replace(model, register_fill_px=fill)
        e = edge_stats(sim_pairs(views, m, seed=60)["frames"])
        err = abs(e.hole_share - edges_real.hole_share)
        log(f"register_fill_px {fill}: holes at edges {100 * e.hole_share:.1f} % "
            f"(real {100 * edges_real.hole_share:.1f} %)")
        if best is None or err < best[0]:
            best = (err, fill)
    model = dataclasses.replace(model, register_fill_px=best[1])
    far = (z >= 4.0) & (st.n_flicker >= 20000)
    best = None
    for start_deg in (86.0, 84.0, 82.0, 80.0):  # on a tie the steadier (fewer drops) wins
        m = dataclasses.replace(model, grazing_start_deg=start_deg,
                                grazing_stop_deg=start_deg + 2.0, dropout_at_4m=0.0)
        f = pair_stats(sim_pairs(views, m, seed=70)["pose1.5"]).flicker
        err = float(np.nansum(np.where(far, np.maximum(f - st.flicker, 0.0), 0.0) ** 2))
        log(f"grazing {start_deg}-{start_deg + 2} deg, no dropout: flicker >= 4 m (%) " +
            fmt(np.where(far, f, np.nan), 100, 2))
        if best is None or err < best[0] - 1e-9:
            best = (err, start_deg)
    model = dataclasses.replace(model, grazing_start_deg=best[1],
                                grazing_stop_deg=best[1] + 2.0)
    edge_bins = edges_real.flying_share_by_bin
    best = None
    for f4 in (0.0, 0.03, 0.06, 0.12, 0.25, 0.5):
        for fe in ((2.0,) if f4 == 0 else (2.0, 3.0, 4.0)):
            m = dataclasses.replace(model, flying_at_4m=f4, flying_exponent=fe)
            e = edge_stats(sim_frames(views, m, seed=80))
            share = e.flying_share_by_bin
            ok = np.isfinite(share) & np.isfinite(edge_bins) & (z > 1.0)
            err = float(np.sum(((share[ok] - edge_bins[ok]) / (edge_bins[ok] + 0.02)) ** 2))
            log(f"flying {f4} (z/4)^{fe}: share per bin (%) " + fmt(share, 100, 1) +
                f", error {err:.2f}")
            if best is None or err < best[0]:
                best = (err, f4, fe)
    log("real flying share per bin (%)          " + fmt(edge_bins, 100, 1))
    model = dataclasses.replace(model, flying_at_4m=best[1], flying_exponent=best[2])
    for k in range(rounds):
        pairs = sim_pairs(views, model, seed=100)
        sim = pair_stats(pairs["pose1.5"])
        e_sim = edge_stats(pairs["frames"])
        # per-frame sigma
        ratio = st.sigma / sim.sigma
        target = model.sigma(z) * ratio
        ok = use & np.isfinite(target)
        W = (w[ok] / w[ok].max()) ** 0.25  # sqrt(n) weights on squared residuals
        fits = []
        for expo in (2.0, 2.25, 2.5, 2.75, 3.0):
            X = np.stack([np.ones(ok.sum()), (z[ok] - 0.4) ** expo], axis=1)
            coef = np.linalg.lstsq(X * W[:, None], target[ok] * W, rcond=None)[0]
            res = float(np.sum(((X @ coef - target[ok]) / target[ok] * W) ** 2))
            fits.append((res, expo, coef))
        _, expo, (a, b) = min(fits, key=lambda f: f[0])
        a = float(max(a, 0.0005))
        # dropout
        flick_target = model.dropout(z) + (st.flicker - sim.flicker)
        p4, pk = _ls_power(z, flick_target, np.where(z >= 2.0, np.sqrt(st.n_flicker), 0.0))
        # error field
        no_field = dataclasses.replace(model, field_sigma_m_at_4m=0.0)
        lf0 = pair_stats(sim_pairs(views, no_field, seed=100)["pose1.5"]).lowfreq_sigma
        field_var = (st.lowfreq_sigma ** 2 - lf0 ** 2) / 2
        fA, fk = _ls_power(z, np.sqrt(np.clip(field_var, 0.0, None)), np.sqrt(w))
        # edge drops, over the model without them
        e0 = edge_stats(sim_frames(views, dataclasses.replace(model, edge_drop_prob=0.0),
                                   seed=100))
        hole_x = edges_real.hole_share - e0.hole_share
        sim_hx = e_sim.hole_share - e0.hole_share
        drop = model.edge_drop_prob * hole_x / sim_hx if sim_hx > 0 and hole_x > 0 else 0.0
        model = dataclasses.replace(
            model, axial_a_m=round(a, 5), axial_b_per_m=round(float(b), 5),
            axial_exponent=expo,
            dropout_at_4m=round(p4, 5), dropout_exponent=round(min(max(pk, 0.0), 6.0), 2),
            field_sigma_m_at_4m=round(fA, 5), field_exponent=round(min(max(fk, 0.0), 4.0), 2),
            edge_drop_prob=round(float(np.clip(drop, 0.0, 1.0)), 4))
        log(f"round {k + 1}: sigma real/sim " + fmt(ratio, 1, 2) +
            "\n  flicker real-sim (%) " + fmt(st.flicker - sim.flicker, 100, 2) +
            "\n  low-freq real/sim " + fmt(st.lowfreq_sigma / sim.lowfreq_sigma, 1, 2) +
            f"\n  holes at edges real {100 * edges_real.hole_share:.1f} %, sim "
            f"{100 * e_sim.hole_share:.1f} %, without edge drops {100 * e0.hole_share:.1f} %"
            f"\n  -> axial {model.axial_a_m} + {model.axial_b_per_m} (z-0.4)^"
            f"{model.axial_exponent}, dropout "
            f"{model.dropout_at_4m} (z/4)^{model.dropout_exponent}, field "
            f"{model.field_sigma_m_at_4m} (z/4)^{model.field_exponent}, flying "
            f"{model.flying_at_4m} (z/4)^{model.flying_exponent}, edge drop "
            f"{model.edge_drop_prob}")
    # residual distortion: the growth from 1.5 to 7.5 cm pairs
    r5 = real["sun3d_5"]
    ok5 = use & (r5.n >= 20000)
    real_growth = np.concatenate([r5.sigma[ok5] / st.sigma[ok5],
                                  r5.lowfreq_sigma[ok5] / st.lowfreq_sigma[ok5]])
    best = None
    for k1 in (0.0, 0.05, 0.1, 0.15, 0.2, 0.25):
        pairs = sim_pairs(views, dataclasses.replace(model, k1=k1), seed=400)
        a1, a5 = pair_stats(pairs["pose1.5"]), pair_stats(pairs["pose7.5"])
        growth = np.concatenate([a5.sigma[ok5] / a1.sigma[ok5],
                                 a5.lowfreq_sigma[ok5] / a1.lowfreq_sigma[ok5]])
        err = float(np.sum(np.log(growth / real_growth) ** 2))
        log(f"k1 {k1}: 7.5 / 1.5 cm sigma and low-freq ratios " + fmt(growth, 1, 2) +
            " (real " + fmt(real_growth, 1, 2) + f"), error {err:.3f}")
        if best is None or err < best[0]:
            best = (err, k1)
    log(f"best k1 {best[1]} (a diagnostic: k1 stays {model.k1}, see the docstring)")
    return model


# ----------------------------------------------------------------------------- main


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--plot", default=str(ROOT / "docs" / "img" / "noise_real_vs_sim.png"),
                        help="the picture to write ('' or --no-plot: none)")
    parser.add_argument("--no-plot", dest="plot", action="store_const", const="")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--fit", action="store_true", help="re-fit the harsh model first")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--layouts", action="store_true",
                        help="also the five stored room layouts (another geometry)")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    depths, poses = sun3d(args.data)
    real = {"sun3d_1": pair_stats(sun3d_pairs(depths, poses, 1, 2)),
            "sun3d_5": pair_stats(sun3d_pairs(depths, poses, 5, 3)),
            "grabber": pair_stats(grabber_pairs(args.data))}
    real_edges = edge_stats(depths[::5])
    c = fit_quant_c(np.concatenate([d[d > 0] for d in depths]))
    print(f"real data measured ({time.perf_counter() - t0:.0f} s); SUN3D quantisation "
          f"c = {c:.5f} /m (step = c z^2)")
    views = sim_views("aisle")
    harsh = RealisticKinectNoise()
    if args.fit:
        harsh = fit(real, views, real_edges, harsh, args.rounds)
        print("fitted:", {k: v for k, v in dataclasses.asdict(harsh).items()})
    models = {"old KinectNoise": KinectNoise(), "RealisticKinectNoise": harsh}
    sims, edges = {}, {"real SUN3D": real_edges}
    for name, model in models.items():
        pairs = sim_pairs(views, model)
        sims[name] = measure(pairs)
        edges[name] = edge_stats(pairs["frames"])
    for name, frames in edge_frames(args.data).items():
        edges[f"real {name}"] = edge_stats(frames)
    print(text_table(real, sims, edges))
    if args.layouts:
        lviews = sim_views("layouts")
        lsims = {name: measure(sim_pairs(lviews, m)) for name, m in models.items()}
        print("\nthe five stored layouts (OpenNI intrinsics), same statistics:")
        print(text_table(real, lsims, {}))
    if args.plot:
        path = Path(args.plot)
        plot(real, sims, edges, path)
        print(f"wrote {path} ({path.stat().st_size // 1024} kB)")
    if args.json:
        out = {"real": {k: v.to_json() for k, v in real.items()},
               "sim": {n: {k: v.to_json() for k, v in s.items()} for n, s in sims.items()},
               "edges": {k: v.to_json() for k, v in edges.items()},
               "harsh_model": harsh.to_json(), "sun3d_quant_c": c}
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
