"""Fingerprints of what rasterization() computes, to compare two trees bit for bit.

    python bench/experiments/engine_hash.py [--n 200000] [--label NAME]

One random 640x352 scene (:func:`clsplat.bench.scenes.random_frustum_scene`), unpacked layout,
a forward and a backward of ``img.square().sum() + alpha.sum()`` for float32 and float64, classic
and antialiased. Prints one JSON line: per configuration, an md5 over the image, alpha,
``meta`` means2d, conics, radii and the five leaf gradients. Run it from each tree's venv: equal
lines mean bitwise equal results on this device.
"""
from __future__ import annotations

import argparse
import hashlib
import json

import clsplat  # first: thread defaults before torch loads

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python bench/experiments/engine_hash.py", description=__doc__.split("\n")[0])
    p.add_argument("--n", type=int, default=200_000)
    p.add_argument("--label", default="")
    a = p.parse_args(argv)
    import torch

    from clsplat.bench.percall import _leaves
    from clsplat.bench.scenes import random_frustum_scene

    torch.set_num_threads(1)
    out = {"label": a.label, "n": a.n}
    for precision in ("float32", "float64"):
        for mode in ("classic", "antialiased"):
            args = _leaves(random_frustum_scene(a.n, 640, 352, sh_degree=None, seed=1))
            img, alpha, meta = clsplat.rasterization(**args, packed=False, rasterize_mode=mode,
                                                     config=clsplat.RenderConfig(precision=precision))
            (img.square().sum() + alpha.sum()).backward()
            parts = [img, alpha, meta["means2d"], meta["conics"], meta["radii"]]
            parts += [args[k].grad for k in ("means", "quats", "scales", "opacities", "colors")]
            digest = hashlib.md5(b"".join(t.detach().contiguous().numpy().tobytes() for t in parts))
            out[f"{precision}_{mode}"] = digest.hexdigest()[:16]
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
