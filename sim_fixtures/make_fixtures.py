"""Write the synthetic scenes and the demo frame: ``python -m sim_fixtures.make_fixtures``.

For each scene of :data:`sim_fixtures.scenes.SCENES` a folder ``scenes/<name>/``::

    reference.oni            the reference frames: OpenNI2 recording, (H, W) uint16 depth in
                             millimetres, 0 = no reading, 30 fps, the smallest lossless codec
    current.oni              the current frames, likewise
    truth_appeared.png       uint8 mask of the current image, 255 = new or moved-to object
    truth_disappeared.png    uint8 mask of the reference image, 255 = removed or moved-from
    observed_reference.png   uint8 mask of the reference image, 255 = seen by the current camera
    observed_current.png     uint8 mask of the current image, 255 = seen by the reference camera
    ids_reference.png        uint8 object ids of the ideal reference render (0 = nothing)
    ids_current.png          uint8 object ids of the ideal current render
    scene.json               name, split, noise model, seed, intrinsics, poses, changes, files

A revisit scene (``<scene>_pose_<n>cm``, ``office_far_offset``, ``storage_other_room``) shares
its reference recording with the scene it revisits (``files.reference`` is
``../<scene>/reference.oni``), so it stores only its current recording.

and ``frames/room_vga.png`` (+ ``room_vga.json``): one VGA frame of a furnished room with Kinect
noise, the demo/benchmark frame.

Frame k of epoch e (0 reference, 1 current) draws its noise from
``numpy.random.default_rng([seed, e, k])``, so any frame can be regenerated alone, and the
files are byte-identical on every run (the .oni writer stores frame-count timestamps, no clock).
Recording formats are plug-ins: :data:`RECORDING_WRITERS` maps a name to a function
``(epoch_folder, frames, spec) -> [relative file names]``; ``oni`` is always written, ``png``
(``--png``) adds ``<epoch>/000.png ...`` (16-bit PNG per frame, ~0.85x the .oni size; not
stored by default to keep the folder small).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from sim_fixtures.noise import KinectNoise
from sim_fixtures.render import Render, render
from sim_fixtures.scenes import (
    SCENES,
    SceneSpec,
    _storage,
    change_geometry,
    object_ids,
    observed_masks,
    render_pair,
    true_transform,
    truth_masks,
)

ROOT = Path(__file__).resolve().parent
SCENES_DIR = ROOT / "scenes"
FRAMES_DIR = ROOT / "frames"
EPOCHS = ("reference", "current")
#: 2: frames in ``<epoch>.oni`` (1: per-frame PNGs only)
FORMAT_VERSION = 2
#: Codecs tried for a recording, in order of preference on equal size.
ONI_CODECS = ("16zt", "16z", "none")
DEMO_SEED = 7
FPS = 30


def write_image(path: Path, array: np.ndarray) -> None:
    """Write (H, W) uint16 / uint8 as PNG with our codec (zlib level 6: level 9 saves ~2 % on
    noisy depth and takes 10x longer)."""
    from hw.imagefile import write_png

    write_png(path, array, level=6)


def noisy_frames(spec: SceneSpec, r: Render, epoch: int, count: int) -> list[np.ndarray]:
    """``count`` independent noisy (H, W) uint16 mm frames of the ideal render ``r``; epoch 0
    is the reference, 1 the current (whose noise stream is ``spec.current_noise_epoch``)."""
    stream = 0 if epoch == 0 else spec.current_noise_epoch
    return [spec.noise.apply(r, np.random.default_rng([spec.seed, stream, k]))
            for k in range(count)]


def write_png_recording(folder: Path, frames: Sequence[np.ndarray], spec: SceneSpec) -> list[str]:
    """``folder/000.png``, ``001.png`` ...; returns the names relative to the scene folder."""
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for k, frame in enumerate(frames):
        path = folder / f"{k:03d}.png"
        write_image(path, frame)
        names.append(f"{folder.name}/{path.name}")
    return names


def best_codec(frames: Sequence[np.ndarray]) -> str:
    """The codec of :data:`ONI_CODECS` that stores ``frames`` ((H, W) uint16 mm) in the fewest
    bytes: ``16zt`` for quantised Kinect depth, ``16z`` or ``none`` for the paper's unquantised
    Gaussian noise (at sigma 0.1 m 16z is larger than raw)."""
    from hw.errors import FrameError
    from hw.oni import encode_16z, encode_16zt

    encoders = {"none": lambda f: f.nbytes, "16z": lambda f: len(encode_16z(f)),
                "16zt": lambda f: len(encode_16zt(f))}
    sizes = {}
    for codec in ONI_CODECS:
        try:
            sizes[codec] = sum(encoders[codec](f) for f in frames)
        except FrameError:  # values the codec cannot hold (16z > 32767 mm, 16zt > 32768 values)
            continue
    return min(sizes, key=lambda c: (sizes[c], ONI_CODECS.index(c)))


def write_oni_recording(folder: Path, frames: Sequence[np.ndarray], spec: SceneSpec) -> list[str]:
    """``<scene>/<epoch>.oni`` beside the epoch folder, in the smallest codec
    (:func:`best_codec`), via ``hw.oni``; returns its name relative to the scene folder."""
    from hw.oni import write_oni

    path = folder.parent / f"{folder.name}.oni"
    write_oni(path, frames, fps=FPS, codec=best_codec(frames), intrinsics=spec.intrinsics)
    return [path.name]


#: Recording formats: name -> writer(epoch_folder, frames, spec) -> relative file names.
RECORDING_WRITERS: dict[str, Callable[[Path, Sequence[np.ndarray], SceneSpec], list[str]]] = {
    "oni": write_oni_recording,
    "png": write_png_recording,
}


def scene_metadata(spec: SceneSpec, ref: Render, cur: Render) -> dict:
    """The JSON-ready description of ``spec`` (files are added by :func:`write_scene`)."""
    intr = spec.intrinsics
    ids = object_ids(spec)
    ref_names = {o.name for o in spec.reference}
    cur_names = {o.name for o in spec.current}
    kinds = {o.name: o.kind for o in list(spec.reference) + list(spec.current)}
    appeared, disappeared = truth_masks(spec, ref, cur)
    return {
        "format_version": FORMAT_VERSION,
        "name": spec.name,
        "split": spec.split,
        "change": spec.change,
        "description": spec.description,
        "depth_unit": "mm, uint16, 0 = no reading",
        "noise": spec.noise.to_json(),
        "seed": spec.seed,
        "frame_seeding": "numpy.random.default_rng([seed, stream, k]); stream 0 reference, "
        f"{spec.current_noise_epoch} current",
        "reference_from": spec.reference_from,
        "T_ref_from_cur": [[round(float(v), 12) for v in row] for row in true_transform(spec)],
        "T_ref_from_cur_note": "maps current camera-frame points into the reference camera "
        "frame (optical, metres); the registration's truth",
        "intrinsics": {"width": intr.width, "height": intr.height, "fx": intr.fx,
                       "fy": intr.fy, "cx": intr.cx, "cy": intr.cy},
        "room_size_m": list(spec.room_size_m),
        "camera": {"reference": spec.reference_pose.to_json(),
                   "current": spec.current_pose.to_json()},
        "objects": [
            {"id": i, "name": n, "kind": kinds[n], "in_reference": n in ref_names,
             "in_current": n in cur_names}
            for n, i in ids.items()
        ],
        "changes": change_geometry(spec, ref, cur),
        "changes_note": "'before' geometry in the reference camera frame, 'after' in the current "
        "camera frame (optical: x right, y down, z forward, metres); centroid/extent of the "
        "object's bounding box; visible_* from the ideal render",
        "truth": {
            "appeared_pixels": int(appeared.sum()),
            "disappeared_pixels": int(disappeared.sum()),
            "definition": "appeared: current-image pixels showing an added or moved (new place) "
            "object; disappeared: reference-image pixels showing a removed or moved (old place) "
            "object; from the ideal renders, before noise",
        },
        "frame_counts": {"reference": spec.frames[0], "current": spec.frames[1]},
        "fps": FPS,
    }


def write_scene(spec: SceneSpec, root: Path = SCENES_DIR, formats: Sequence[str] = ("oni",)
                ) -> dict:
    """Render, add noise and write one scene folder (replacing an old one); returns scene.json.

    ``formats``: recording formats of :data:`RECORDING_WRITERS`; ``oni`` is always written.
    scene.json's ``files`` gets ``reference`` / ``current`` (the .oni names), ``recordings``
    their codec and frame count, and with ``png`` also ``reference_png`` / ``current_png``."""
    from hw.oni import read_oni_header

    formats = ["oni"] + [f for f in formats if f != "oni"]
    ref, cur = render_pair(spec)
    appeared, disappeared = truth_masks(spec, ref, cur)
    observed_ref, observed_cur = observed_masks(spec, ref, cur)
    folder = root / spec.name
    tmp = root / f".{spec.name}.tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    meta = scene_metadata(spec, ref, cur)
    files: dict[str, object] = {}
    recordings: dict[str, dict] = {}
    for epoch, (name, r) in enumerate(zip(EPOCHS, (ref, cur), strict=True)):
        if epoch == 0 and spec.reference_from is not None:
            shared = root / spec.reference_from / "reference.oni"
            files[name] = f"../{spec.reference_from}/reference.oni"
            info = read_oni_header(shared)
            recordings[name] = {"file": files[name], "codec": info.codec,
                                "frames": info.frames, "fps": info.fps}
            continue
        frames = noisy_frames(spec, r, epoch, spec.frames[epoch])
        for fmt in formats:
            names = RECORDING_WRITERS[fmt](tmp / name, frames, spec)
            if fmt == "oni":
                files[name] = names[0]
                info = read_oni_header(tmp / names[0])
                recordings[name] = {"file": names[0], "codec": info.codec,
                                    "frames": info.frames, "fps": info.fps}
            else:
                files[f"{name}_{fmt}"] = names
    for key, image in (("truth_appeared", appeared.astype(np.uint8) * 255),
                       ("truth_disappeared", disappeared.astype(np.uint8) * 255),
                       ("ids_reference", ref.ids.astype(np.uint8)),
                       ("ids_current", cur.ids.astype(np.uint8)),
                       ("observed_reference", observed_ref.astype(np.uint8) * 255),
                       ("observed_current", observed_cur.astype(np.uint8) * 255)):
        write_image(tmp / f"{key}.png", image)
        files[key] = f"{key}.png"
    meta["files"] = files
    meta["recordings"] = recordings
    meta["bytes"] = {str(p.relative_to(tmp)): p.stat().st_size
                     for p in sorted(tmp.rglob("*")) if p.is_file()}
    (tmp / "scene.json").write_text(json.dumps(meta, indent=1) + "\n")
    if folder.exists():
        shutil.rmtree(folder)
    tmp.rename(folder)
    return meta


def demo_frame() -> tuple[np.ndarray, dict]:
    """The demo frame: the storage room's reference view with Kinect noise; (H, W) uint16 mm
    and its description."""
    objs, pose = _storage()
    noise = KinectNoise()
    r = render(objs, pose, projector_baseline_m=noise.projector_baseline_m)
    depth = noise.apply(r, np.random.default_rng([DEMO_SEED, 0, 0]))
    valid = depth > 0
    meta = {
        "what": "one VGA frame of a furnished storage room (4 x 4 x 2.5 m: shelves, cartons, a "
        "barrel) with the Kinect noise model; the `robot-change demo` / `bench` frame",
        "seed": DEMO_SEED,
        "noise": noise.to_json(),
        "camera": pose.to_json(),
        "intrinsics": {"width": 640, "height": 480, "fx": 525.0, "fy": 525.0, "cx": 319.5,
                       "cy": 239.5},
        "valid_fraction": round(float(valid.mean()), 4),
        "depth_range_mm": [int(depth[valid].min()), int(depth[valid].max())],
    }
    return depth, meta


def write_demo_frame(folder: Path = FRAMES_DIR) -> dict:
    """``frames/room_vga.png`` and ``frames/room_vga.json``."""
    folder.mkdir(parents=True, exist_ok=True)
    depth, meta = demo_frame()
    write_image(folder / "room_vga.png", depth)
    (folder / "room_vga.json").write_text(json.dumps(meta, indent=1) + "\n")
    return meta


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim_fixtures.make_fixtures",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="scenes to write (default: all)")
    parser.add_argument("--out", type=Path, default=SCENES_DIR, help="scenes folder")
    parser.add_argument("--png", action="store_true", help="also write every frame as a 16-bit "
                        "PNG (<epoch>/NNN.png; the .oni recordings are always written)")
    parser.add_argument("--no-demo", action="store_true", help="skip frames/room_vga.png")
    args = parser.parse_args(argv)
    unknown = [n for n in args.names if n not in SCENES]
    if unknown:
        parser.error(f"unknown scene(s) {unknown}; known: {', '.join(SCENES)}")
    formats = ("oni", "png") if args.png else ("oni",)
    total = time.perf_counter()
    for name in args.names or list(SCENES):
        start = time.perf_counter()
        meta = write_scene(SCENES[name], args.out, formats)
        size = sum(meta["bytes"].values())
        codecs = "/".join(sorted({r["codec"] for r in meta["recordings"].values()}))
        print(f"{name:28s} {meta['split']:8s} {meta['change']:12s} {codecs:9s} "
              f"{size / 1e6:6.2f} MB  {time.perf_counter() - start:5.1f} s", flush=True)
    if not args.no_demo and not args.names:
        meta = write_demo_frame()
        print(f"frames/room_vga.png valid {meta['valid_fraction']:.2f}")
    print(f"total {time.perf_counter() - total:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
