"""Where on a moving object AutoSplat's held-out error lies (issue 36, bench/notes/autosplat_moving_objects.md):
the object pixels split into a silhouette band (pixels of the track within ``--band`` pixels of a
pixel that is not the track's) and the interior (the rest), PSNR pooled over each, for the moving
tracks and, as the control, the parked vehicles; and the same split of the error energy (the share
of the squared error that lies in the band). A silhouette that is off (box error, timing, a blurred
outline) shows as a band far worse than the interior; an object whose detail is missing, as an
interior as bad as its band. Second table: the moving tracks' pixels where the background alone
(rendered without the objects) puts its expected depth in front of the object (below
``--front`` times the generator's depth there): background Gaussians that occlude the object in
the composite (occlusion between objects and background), their share of the pixels and PSNR
there and elsewhere.

    cd /tmp && PYTHONPATH=<tree> .venv/bin/python bench/experiments/autosplat_object_edges.py RUN [RUN ...]

Each RUN is a finished ``clsplat train autosplat`` folder on generated data (the masks are the
generator's instance masks of the held-out frames).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def _band(mask: np.ndarray, width: int) -> np.ndarray:
    """``[C, H, W]`` bool: pixels of ``mask`` within ``width`` pixels (Chebyshev) of a pixel outside it."""
    m = torch.from_numpy(mask).float()[:, None]
    outside = 1 - m
    near = torch.nn.functional.max_pool2d(outside, 2 * width + 1, 1, width)[:, 0].numpy() > 0
    return mask & near


def analyse(run: Path, band: int, front_share: float = 0.9) -> dict:
    from clsplat.models.autosplat.evaluate import trainer_from_checkpoint
    from clsplat.models.autosplat.init import moving_track_ids
    from clsplat.models.common.train import load_checkpoint

    ck = load_checkpoint(run / "checkpoint.pt", "autosplat")
    tr = trainer_from_checkpoint(ck, run / "checkpoint.pt", run, None, out_dir=Path("/tmp"))
    d = tr.data
    moving = moving_track_ids(d.seq, tr.preset.dynamic_threshold)
    acc = {k: np.zeros(2) for k in ("moving_band", "moving_interior", "static_band", "static_interior",
                                    "moving_bg_front", "moving_bg_behind")}
    with torch.no_grad():
        for i in d.test_frames:
            r = tr.render_frame(i).numpy().astype(np.float64)
            g = d.images[i].numpy().astype(np.float64)
            err = ((np.clip(r, 0, 1) - np.clip(g, 0, 1)) ** 2).sum(-1)
            inst = np.stack([d.seq.frames[i].instances[c] for c in d.cameras])
            true_depth = np.stack([d.seq.frames[i].depths[c] for c in d.cameras])
            gs_bg, _ = tr.model.scene_at(i, background=True, objects=False)
            bg = gs_bg.render(d.viewmats[i], d.Ks, d.width, d.height, packed=False, device=tr.device,
                              render_mode="RGB+ED", **tr.renderer.options)[0][..., 3].numpy()
            mov = np.isin(inst, sorted(moving))
            front = mov & (bg < front_share * true_depth)
            acc["moving_bg_front"] += [err[front].sum(), 3 * front.sum()]
            acc["moving_bg_behind"] += [err[mov & ~front].sum(), 3 * (mov & ~front).sum()]
            for t in np.unique(inst[inst > 0]):
                m = inst == t
                b = _band(m, band)
                kind = "moving" if int(t) in moving else "static"
                for part, sel in (("band", b), ("interior", m & ~b)):
                    acc[f"{kind}_{part}"] += [err[sel].sum(), 3 * sel.sum()]
    out = {}
    for k, (e, n) in acc.items():
        out[k] = {"psnr": None if n == 0 else float(-10 * np.log10(e / n)), "pixels": int(n // 3)}
    for kind in ("moving", "static"):
        e_b, e_i = acc[f"{kind}_band"][0], acc[f"{kind}_interior"][0]
        out[f"{kind}_band_error_share"] = None if e_b + e_i == 0 else float(e_b / (e_b + e_i))
        n_b, n_i = acc[f"{kind}_band"][1], acc[f"{kind}_interior"][1]
        out[f"{kind}_band_pixel_share"] = None if n_b + n_i == 0 else float(n_b / (n_b + n_i))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--band", type=int, default=1, help="silhouette band width in pixels (default 1)")
    p.add_argument("--front", type=float, default=0.9,
                   help="background in front: its expected depth below this share of the true depth (default 0.9)")
    a = p.parse_args()
    print(f"| run | moving: band / interior PSNR | band share of pixels / of error | parked: band / interior "
          f"| band share of pixels / of error |  (band {a.band} px)")
    print("|---|---|---|---|---|")
    f = lambda x: "–" if x is None else f"{x:.2f}"  # noqa: E731
    occl = []
    for run in a.runs:
        o = analyse(run, a.band, a.front)
        occl.append((run.name, o))
        print(f"| {run.name} | {f(o['moving_band']['psnr'])} / {f(o['moving_interior']['psnr'])} | "
              f"{f(o['moving_band_pixel_share'])} / {f(o['moving_band_error_share'])} | "
              f"{f(o['static_band']['psnr'])} / {f(o['static_interior']['psnr'])} | "
              f"{f(o['static_band_pixel_share'])} / {f(o['static_band_error_share'])} |", flush=True)
    print(f"\n| run | moving pixels with the background in front (expected depth < {a.front:g} x true) | "
          "PSNR there | PSNR elsewhere |")
    print("|---|---|---|---|")
    for name, o in occl:
        fr, be = o["moving_bg_front"], o["moving_bg_behind"]
        n = fr["pixels"] + be["pixels"]
        print(f"| {name} | {fr['pixels'] / n if n else 0:.3f} ({fr['pixels']} px) | {f(fr['psnr'])} | {f(be['psnr'])} |")


if __name__ == "__main__":
    main()
