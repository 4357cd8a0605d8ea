"""How novel are AutoSplat's novel views? The share of pixels no training camera saw (issue 33),
from the generator's geometry alone (no model is trained).

For a generated street (``--world classic|varied|straight|divided``, ``--seed``), AutoSplat's split of
the synthetic data (16 frames at 0.2 s, every 4th frame from frame 2 held out) and ``--cameras``
of the rig, it prints for each lateral shift of the held-out rigs (0 = the recorded views, then
1, 2, 3 m left: the ``lane-change`` set) and for the rigs mirrored across every moving vehicle
(the ``far-side`` set, over the vehicle's own pixels, views where it covers at least
``MIN_OBJECT_PIXELS``) the share of the counted pixels whose surface point no training camera
saw (:func:`clsplat.models.autosplat.viewsets.unseen_pixels`, the figure ``eval autosplat``
writes as ``unseen_share``), and how the 3 m set's unseen pixels split over the semantic classes
(``by_class_3m``: each class's share of the counted pixels that are unseen pixels of that class).
The ``divided`` world (issue 33) puts a median wall taller than the cameras beside the ego's lane.

    .venv/bin/python bench/experiments/autosplat_unseen_share.py --world straight --seed 1 --scale 0.25
    .venv/bin/python bench/experiments/autosplat_unseen_share.py --world classic --cameras CAM_FRONT
    .venv/bin/python bench/experiments/autosplat_unseen_share.py --world divided --seed 0 1 2
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

RIG = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")


def unseen_shares(world: str, seed: int, scale: float, cameras: list[str], frames: int = 16,
                  holdout: int = 4) -> dict:
    """{"shift_<s>m": share over the held-out rigs shifted s m left, "far_side": share over the
    mirrored rigs' vehicle pixels, "far_side_pixels": their count, "tracks": moving track ids,
    "by_class_3m": {class: unseen pixels of that class / counted pixels of the 3 m set}}."""
    from clsplat.data.scene import SEMANTIC_CLASSES
    from clsplat.data.synthetic import SyntheticConfig, generate_sequence
    from clsplat.data.synthetic.views import mirror_across_box, shift_sideways
    from clsplat.models.autosplat.data import SYNTHETIC_DT
    from clsplat.models.autosplat.init import moving_track_ids
    from clsplat.models.autosplat.presets import AutoSplatPreset
    from clsplat.models.autosplat.viewsets import (LATERAL_SHIFTS_M, MIN_OBJECT_PIXELS, _exact_box,
                                                   _generator_views, _rig, unseen_pixels)

    seq = generate_sequence(SyntheticConfig(height=max(8, round(176 * scale)), width=max(8, round(320 * scale)),
                                            num_frames=frames, seed=seed, dt=SYNTHETIC_DT, world=world, lidar=False))
    test = [i for i in range(frames) if i % holdout == holdout // 2]
    c0 = seq.cameras[0]
    run = SimpleNamespace(data=SimpleNamespace(seq=seq, cameras=list(cameras), height=c0.height, width=c0.width,
                                               train_frames=[i for i in range(frames) if i not in test]))
    out: dict = {}
    for shift in (0.0, *LATERAL_SHIFTS_M):
        u = n = 0
        by_class = np.zeros(len(SEMANTIC_CLASSES), dtype=np.int64)
        for f in test:
            c2w = shift_sideways(_rig(seq, f, cameras), seq.frames[f].ego_to_world, shift)
            views = _generator_views(run, f, c2w)
            un, solid = unseen_pixels(run, f, c2w, views)
            u, n = u + int(un.sum()), n + int(solid.sum())
            by_class += np.bincount(np.stack([v.semantic for v in views])[un], minlength=len(SEMANTIC_CLASSES))
        out[f"shift_{shift:g}m"] = u / n if n else None
        if shift == LATERAL_SHIFTS_M[-1]:
            out["by_class_3m"] = {c: int(k) / n for c, k in zip(SEMANTIC_CLASSES, by_class) if k and n}
    moving = sorted(moving_track_ids(seq, AutoSplatPreset.dynamic_threshold))
    u = n = 0
    for f in range(frames):
        for t in moving:
            box = _exact_box(seq, f, t)
            if box is None:
                continue
            c2w = mirror_across_box(_rig(seq, f, cameras), box.box_to_world)
            gt = _generator_views(run, f, c2w)
            mask = np.stack([g.instance == t for g in gt])
            keep = mask.reshape(len(cameras), -1).sum(1) >= MIN_OBJECT_PIXELS
            if keep.any():
                un = unseen_pixels(run, f, c2w, gt, only=mask)[0]
                u, n = u + int(un[keep].sum()), n + int(mask[keep].sum())
    out.update(far_side=u / n if n else None, far_side_pixels=n, tracks=moving)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--world", default="straight", choices=("classic", "varied", "straight", "divided"))
    p.add_argument("--seed", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--scale", type=float, default=0.25, help="image scale of the 176 x 320 rig (default 0.25)")
    p.add_argument("--cameras", nargs="+", default=list(RIG))
    a = p.parse_args(argv)
    for seed in a.seed:
        t0 = time.perf_counter()
        r = unseen_shares(a.world, seed, a.scale, a.cameras)
        fmt = lambda v: "n/a" if v is None else f"{100 * v:.1f} %"  # noqa: E731
        print(f"{a.world} seed {seed} ({len(a.cameras)} cameras, scale {a.scale:g}): "
              + ", ".join(f"{k.replace('shift_', '')} {fmt(v)}" for k, v in r.items() if k.startswith("shift_"))
              + f"; far side {fmt(r['far_side'])} of {r['far_side_pixels']} vehicle px (tracks {r['tracks']})"
              + "; 3 m unseen by class " + ", ".join(f"{c} {fmt(v)}" for c, v in r["by_class_3m"].items())
              + f"  [{time.perf_counter() - t0:.0f} s]", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
