"""Fingerprints of small renders (the array pool's sizes), to compare two trees bit for bit.

    python bench/experiments/small_hash.py [--label NAME]
    python bench/experiments/run_tree.py TREE bench/experiments/small_hash.py --label old

Small scenes (100-300 Gaussians, 64x48 to 96x64) in many configurations: float32 and float64,
packed and unpacked, classic and antialiased with absgrad, SH degree 2 and plain colours,
RGB, RGB+D, RGB+ED and D, tile sizes 8 and 16, backgrounds, two cameras, a batch of two. Each
configuration renders three times in a row (forward + backward of a weighted loss, so that
the runtime's pooled arrays are handed out again), changing means, colours and opacities in
place between calls (as an optimiser step does: kept input arrays must see it), and the
results of the first call are held and hashed only after the other two ran: a returned tensor
a later call overwrote would change the fingerprint. Prints one JSON line: per configuration,
an md5 over images, alphas, meta's means2d, radii, isect_offsets and flatten_ids, and every leaf
gradient (and absgrad).
"""
from __future__ import annotations

import argparse
import hashlib
import json

import clsplat  # first: thread defaults before torch loads

__all__ = ["main"]

CONFIGS = [
    dict(name="tiny", n=100, w=64, h=48),
    dict(name="f64_sh2_ed", n=150, w=64, h=48, precision="float64", sh=2, render_mode="RGB+ED"),
    dict(name="unpacked_aa_absgrad", n=200, w=96, h=64, packed=False, rasterize_mode="antialiased",
         absgrad=True),
    dict(name="rgbd_tile8_bg_2cams", n=120, w=64, h=48, render_mode="RGB+D", tile_size=8, bg=True, C=2),
    dict(name="sh1_bg_batch2", n=100, w=64, h=48, sh=1, bg=True, batch=2),
    dict(name="depth_only", n=300, w=64, h=48, render_mode="D"),
]


def _run(cfg: dict, torch) -> str:
    from clsplat.bench.scenes import random_frustum_scene, render_args

    dt = torch.float64 if cfg.get("precision") == "float64" else torch.float32
    a = render_args(random_frustum_scene(cfg["n"], cfg["w"], cfg["h"], sh_degree=cfg.get("sh"), seed=3))
    C = cfg.get("C", 1)
    if C > 1:
        a["viewmats"] = a["viewmats"].repeat(C, 1, 1)
        a["viewmats"][1:, 0, 3] += 0.05
        a["Ks"] = a["Ks"].repeat(C, 1, 1)
    names = ("means", "quats", "scales", "opacities", "colors")
    for k in names:
        a[k] = a[k].to(dt)
    a["viewmats"], a["Ks"] = a["viewmats"].to(dt), a["Ks"].to(dt)
    B = cfg.get("batch", 0)
    if B:
        for k in names + ("viewmats", "Ks"):
            x = a[k].unsqueeze(0).repeat((B,) + (1,) * a[k].dim())
            x[1:] *= 1.01 if k in ("means", "colors") else 1.0
            a[k] = x
    for k in names:
        a[k] = a[k].clone().requires_grad_()
    kw = {k: cfg[k] for k in ("packed", "rasterize_mode", "absgrad", "render_mode", "tile_size") if k in cfg}
    if cfg.get("bg"):
        D = 3
        bg = torch.linspace(0.1, 0.9, C * D, dtype=dt).reshape(C, D)
        kw["backgrounds"] = bg.unsqueeze(0).repeat(B, 1, 1) if B else bg
    held = []
    for _ in range(3):
        img, alpha, meta = clsplat.rasterization(**a, **kw)
        w = torch.linspace(0.5, 1.5, img.numel(), dtype=dt).reshape(img.shape)
        meta["means2d"].retain_grad()
        ((img * w).sum() + alpha.square().sum()).backward()
        parts = [img, alpha, meta["means2d"], meta["radii"], meta["isect_offsets"], meta["flatten_ids"],
                 meta["means2d"].grad]
        if cfg.get("absgrad"):
            parts.append(meta["means2d"].absgrad)
        parts += [a[k].grad for k in names]
        held.append(parts)
        for k in names:
            a[k].grad = None
        with torch.no_grad():  # an optimiser's step, in place: the next call sees new values
            a["means"].add_(0.002)
            a["colors"].mul_(0.97)
            a["opacities"].mul_(0.99)
    h = hashlib.md5()
    for parts in held:  # the first call's results hashed after the later calls ran
        for t in parts:
            h.update(b"none" if t is None else t.detach().contiguous().cpu().numpy().tobytes())
    return h.hexdigest()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python bench/experiments/small_hash.py", description=__doc__.split("\n")[0])
    p.add_argument("--label", default="")
    a = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    print(json.dumps({"label": a.label, **{c["name"]: _run(c, torch) for c in CONFIGS}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
