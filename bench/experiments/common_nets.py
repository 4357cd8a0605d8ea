"""Speed of the shared losses in ``clsplat.models.common.losses``, each side by side with the
straightforward way to write it, interleaved run by run so that machine load hits both alike.

- ``ssim3``: monodepth2's 3x3 SSIM map (``ssim_map3``, box statistics as shifted sums) against
  the same statistics from ``kornia.filters.box_blur(x, 3, border_type="reflect")``; forward and
  forward+backward on 6-camera batches.
- ``ssim11``: the engine's 11x11 Gaussian SSIM map (``clsplat.image_metrics.ssim_map``: the five
  moments stacked and filtered at once) against ``kornia.metrics.ssim``, the same map; 'same'
  forward+backward (AutoSplat's loss: six 480x270 cameras, and ``demo``'s 88x160), 'valid'
  forward+backward (PGT's loss) and 'valid' forward without gradient (the metric).
- ``chamfer``: ``chamfer_distance`` (one pass over the distances for both directions) against a
  per-direction search of the expanded form ``|p|² + |q|² - 2 p.q``; forward+backward at
  10k x 10k points (GPS-Gaussian+'s sample size).

Medians over ``--repeats`` after one warm-up, one torch thread.
Run: ``python bench/common_nets.py --out DIR`` (writes ``DIR/common_nets.json``).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch


def _ssim_kornia(a, b):
    from kornia.filters import box_blur

    def blur(x):
        return box_blur(x, 3, border_type="reflect")

    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    return (2 * mu_a * mu_b + 1e-4) * (2 * cov + 9e-4) / ((mu_a**2 + mu_b**2 + 1e-4) * (var_a + var_b + 9e-4))


def _chamfer_per_direction(p, q, max_elems: int = 1 << 24):
    def nearest_sq(p, q):
        B, N, _ = p.shape
        chunk = max(1, max_elems // (B * q.shape[1]))
        with torch.no_grad():
            qd = q.detach()
            q2 = (qd * qd).sum(-1)[:, None, :]
            idx = []
            for s in range(0, N, chunk):
                pc = p.detach()[:, s : s + chunk]
                d = (pc * pc).sum(-1)[:, :, None] + q2 - 2.0 * torch.bmm(pc, qd.transpose(1, 2))
                idx.append(d.argmin(-1))
            idx = torch.cat(idx, 1)
        return ((p - torch.gather(q, 1, idx[..., None].expand(B, N, 3))) ** 2).sum(-1)

    return nearest_sq(p, q).mean(1) + nearest_sq(q, p).mean(1)


def _side_by_side(fns: dict, repeats: int) -> dict:
    times = {name: [] for name in fns}
    for i in range(repeats + 1):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            if i:
                times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def bench_ssim3(repeats: int) -> list[dict]:
    from clsplat.models.common.losses import ssim_map3

    rows = []
    for shape in [(6, 3, 176, 320), (6, 3, 352, 640)]:
        g = torch.Generator().manual_seed(0)
        a, b = torch.rand(shape, generator=g), torch.rand(shape, generator=g)
        torch.testing.assert_close(ssim_map3(a, b), _ssim_kornia(a, b), atol=1e-4, rtol=0)
        ag = a.clone().requires_grad_(True)
        fwd = _side_by_side({"ours": lambda: ssim_map3(a, b), "kornia": lambda: _ssim_kornia(a, b)}, repeats)
        both = _side_by_side(
            {"ours": lambda: ssim_map3(ag, b).mean().backward(), "kornia": lambda: _ssim_kornia(ag, b).mean().backward()},
            repeats,
        )
        rows.append(dict(shape=list(shape), fwd_ms={k: v * 1e3 for k, v in fwd.items()},
                         fwd_bwd_ms={k: v * 1e3 for k, v in both.items()}))
    return rows


def bench_ssim11(repeats: int) -> list[dict]:
    from kornia.metrics import ssim as kornia_ssim

    from clsplat.image_metrics import ssim_map

    rows = []
    for shape, padding, grad in [((6, 3, 270, 480), "same", True), ((6, 3, 88, 160), "same", True),
                                 ((4, 3, 128, 224), "valid", True), ((6, 3, 270, 480), "valid", False)]:
        g = torch.Generator().manual_seed(0)
        a, b = torch.rand(shape, generator=g), torch.rand(shape, generator=g)
        assert torch.equal(ssim_map(a, b, padding), kornia_ssim(a, b, 11, max_val=1.0, eps=0.0, padding=padding))
        x = a.clone().requires_grad_(grad)

        def call(f):
            if grad:
                return lambda: f(x).mean().backward()
            return lambda: f(x)
        with torch.set_grad_enabled(grad):
            t = _side_by_side({"ours": call(lambda x: ssim_map(x, b, padding)),
                               "kornia": call(lambda x: kornia_ssim(x, b, 11, max_val=1.0, eps=0.0, padding=padding))},
                              repeats)
        rows.append(dict(shape=list(shape), padding=padding, grad=grad, ms={k: v * 1e3 for k, v in t.items()}))
    return rows


def bench_chamfer(repeats: int) -> list[dict]:
    from clsplat.models.common.losses import chamfer_distance

    rows = []
    for B in (1, 2):
        g = torch.Generator().manual_seed(1)
        p = (torch.randn(B, 10000, 3, generator=g) * 20).requires_grad_(True)
        q = torch.randn(B, 10000, 3, generator=g) * 20
        torch.testing.assert_close(chamfer_distance(p, q), _chamfer_per_direction(p, q))
        t = _side_by_side(
            {"ours": lambda: chamfer_distance(p, q).sum().backward(),
             "per_direction": lambda: _chamfer_per_direction(p, q).sum().backward()},
            repeats,
        )
        rows.append(dict(batch=B, points=10000, fwd_bwd_ms={k: v * 1e3 for k, v in t.items()}))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench/out", help="folder for common_nets.json")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    result = dict(threads=1, repeats=args.repeats, ssim3=bench_ssim3(args.repeats),
                  ssim11=bench_ssim11(args.repeats), chamfer=bench_chamfer(args.repeats))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "common_nets.json").write_text(json.dumps(result, indent=1))
    for r in result["ssim3"]:
        f, fb = r["fwd_ms"], r["fwd_bwd_ms"]
        print(f"ssim3 {r['shape']}: fwd {f['ours']:.1f} vs kornia {f['kornia']:.1f} ms "
              f"(x{f['kornia'] / f['ours']:.2f}); fwd+bwd {fb['ours']:.1f} vs {fb['kornia']:.1f} ms "
              f"(x{fb['kornia'] / fb['ours']:.2f})")
    for r in result["ssim11"]:
        t = r["ms"]
        print(f"ssim11 {r['shape']} {r['padding']} {'fwd+bwd' if r['grad'] else 'fwd, no grad'}: "
              f"{t['ours']:.1f} vs kornia {t['kornia']:.1f} ms (x{t['ours'] / t['kornia']:.2f} the time)")
    for r in result["chamfer"]:
        t = r["fwd_bwd_ms"]
        print(f"chamfer B={r['batch']} 10k x 10k fwd+bwd: {t['ours']:.0f} vs per-direction "
              f"{t['per_direction']:.0f} ms (x{t['per_direction'] / t['ours']:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
