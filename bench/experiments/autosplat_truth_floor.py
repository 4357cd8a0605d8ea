"""How far the images an AutoSplat run trains on lie from the street they show (issue 36).

A PandaSet-format street written by ``autosplat_pandaset.py`` holds JPEG images (quality 95) of the
generator's ``2 x 2``-supersampled render. Neither is the street itself: JPEG drops fine detail and
colour resolution, and four rays a pixel alias a texture finer than a pixel differently in every frame.
No model consistent across views can fit that noise, so it bounds the PSNR any run can score against
those images, per part of the image. This script regenerates the street the writer drew (seed and world
from the folder, flat ground as written), renders chosen frames at the written supersampling and at a
much finer one (the reference: the street's pixel averages), and reports, on the whole image and on each
class of truly moving tracks' instance pixels (and parked cars):

* ``jpeg``: the folder's JPEG against the written render (the JPEG's loss alone; also a check that the
  street regenerated is the one written: the pixels must agree to JPEG's error);
* ``alias``: the written render against the fine reference (the supersampling's aliasing alone);
* ``floor``: the folder's JPEG against the fine reference (both together: the truth the runs see,
  against the street).

Usage::

    .venv/bin/python bench/experiments/autosplat_truth_floor.py /work/runs/busy6_s0 --frames 0 1 2 5 9 \\
        --reference-supersample 8 --json OUT.json
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

PARTS = ("image", "car", "pedestrian", "other", "parked")


def _psnr(sse: float, n: int) -> float | None:
    return None if n == 0 else float(10 * np.log10(n / max(sse, 1e-20)))


def floors(folder: Path, world: str, frames: list[int], written_ss: int, ref_ss: int) -> dict:
    """``{"jpeg"|"alias"|"floor": {part: psnr}, "pixels": {part: n}}`` over ``frames`` of ``folder``."""
    from clsplat.data.pandaset import load_pandaset
    from clsplat.data.synthetic import SyntheticConfig, draw_world, generate_sequence
    from clsplat.data.synthetic.rig import render_view
    from clsplat.models.autosplat.init import moving_track_ids
    from clsplat.models.autosplat.object_report import object_class

    g = re.search(r"_s(\d+)$", folder.name)
    if not g:
        raise ValueError(f"folder: expected a name ending _sSEED as autosplat_pandaset.py's runs name them, got {folder.name!r}")
    seed = int(g.group(1))
    stamps = json.loads((folder / "camera" / "front_camera" / "timestamps.json").read_text())
    n = len(stamps)
    bad = [f for f in frames if not 0 <= f < n]
    if bad:
        raise ValueError(f"--frames: {bad} outside the folder's 0..{n - 1}")
    rec = load_pandaset(folder, frames=frames, load_lidar=False, load_cuboids=False)
    H, W = rec.cameras[0].height, rec.cameras[0].width
    dt = (stamps[-1] - stamps[0]) / max(1, n - 1)
    names = tuple(c.name for c in rec.cameras)
    cfg = SyntheticConfig(height=H, width=W, num_frames=n, seed=seed, dt=round(dt, 6), cameras=names,
                          lidar=False, depth_only=True, world=world, fine_texture=0.3)
    wp = None if world == "classic" else replace(draw_world(seed, world), grade=0.0, vcurv=0.0, crossfall=0.0)
    gen = generate_sequence(cfg) if wp is None else generate_sequence(cfg, world_params=wp)
    scene = gen.metadata["scene"]
    moving = set(moving_track_ids(gen, 0.5))
    kind = {}
    for f in gen.frames:
        for b in f.boxes:
            c = object_class(b.label)
            kind[b.track_id] = c if b.track_id in moving else ("parked" if c == "car" else None)
    sse = {k: {p: 0.0 for p in PARTS} for k in ("jpeg", "alias", "floor")}
    num = {p: 0 for p in PARTS}
    for j, i in enumerate(frames):
        f = gen.frames[i]
        for cam in gen.cameras:
            w = render_view(scene, cam, f.ego_to_world, f.timestamp, written_ss)
            ref = render_view(scene, cam, f.ego_to_world, f.timestamp, ref_ss).rgb.astype(np.float64)
            jpg = np.asarray(rec.frames[j].images[cam.name], dtype=np.float64)
            wr = np.clip(w.rgb.astype(np.float64), 0, 1)
            errs = {"jpeg": ((jpg - wr) ** 2).sum(-1), "alias": ((wr - ref) ** 2).sum(-1),
                    "floor": ((jpg - ref) ** 2).sum(-1)}
            masks = {"image": np.ones((H, W), bool)}
            for p in PARTS[1:]:
                masks[p] = np.isin(w.instance, [t for t, k in kind.items() if k == p])
            for p, m in masks.items():
                num[p] += int(m.sum()) * 3
                for k, e in errs.items():
                    sse[k][p] += float(e[m].sum())
    return {"folder": str(folder), "frames": frames, "written_supersample": written_ss,
            "reference_supersample": ref_ss,
            **{k: {p: _psnr(sse[k][p], num[p]) for p in PARTS} for k in sse},
            "pixels": {p: num[p] // 3 for p in PARTS}}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("folder", help="a PandaSet folder written by autosplat_pandaset.py (name ending _sSEED)")
    p.add_argument("--world", default="busy", help="the world it was written from (default busy)")
    p.add_argument("--frames", type=int, nargs="+", default=[0, 1, 2, 5, 9], help="frame indices to score")
    p.add_argument("--written-supersample", type=int, default=2, help="the writer's --supersample (default 2)")
    p.add_argument("--reference-supersample", type=int, default=8, help="the fine reference's rays a side (default 8)")
    p.add_argument("--json", help="write the figures here too")
    a = p.parse_args(argv)
    try:
        folder = Path(a.folder)
        if not folder.is_dir():
            raise ValueError(f"folder: no such directory {a.folder!r}")
        for name in ("written_supersample", "reference_supersample"):
            if getattr(a, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')}: expected an integer >= 1, got {getattr(a, name)}")
        if a.reference_supersample <= a.written_supersample:
            raise ValueError("--reference-supersample: must exceed --written-supersample "
                             f"({a.reference_supersample} <= {a.written_supersample})")
        t0 = time.perf_counter()
        o = floors(folder, a.world, a.frames, a.written_supersample, a.reference_supersample)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"autosplat_truth_floor.py: {e}")
    fmt = lambda v: "–" if v is None else f"{v:.2f}"   # noqa: E731
    print(f"{folder}: frames {a.frames}, written {a.written_supersample}x{a.written_supersample}, reference "
          f"{a.reference_supersample}x{a.reference_supersample} ({time.perf_counter() - t0:.0f} s)")
    print("| PSNR dB | " + " | ".join(PARTS) + " |")
    print("|---" * (len(PARTS) + 1) + "|")
    for k, label in (("jpeg", "JPEG vs written render"), ("alias", "written render vs reference"),
                     ("floor", "JPEG vs reference (the floor)")):
        print(f"| {label} | " + " | ".join(fmt(o[k][q]) for q in PARTS) + " |")
    print("| pixels | " + " | ".join(str(o["pixels"][q]) for q in PARTS) + " |")
    if a.json:
        Path(a.json).write_text(json.dumps(o, indent=1))


if __name__ == "__main__":
    main()
