"""Per-stage timing of the forward pipeline with OpenCL profiling events.

For a scene, :func:`time_forward` runs :func:`clsplat.rasterization` (``events=``) ``repeats + 1``
times on a fresh :class:`~clsplat.runtime.Runtime` (so the first call pays the program builds
and PoCL's JIT; PoCL's on-disk cache under ~/.cache/pocl may be warm) and reports per stage
the device time from profiling events (end - start), summed over the stage's launches
(``sort_merge`` runs once per merge pass; ``scan`` is not captured: pyopencl's legacy
ExclusiveScanKernel returns its output Array, whose events are already drained),
as median, min, max over the repeats, with the first call apart.

Compositing work is counted four ways (see :func:`count_evaluations`):

* ``segment``: sum over tiles of segment length x in-image pixels of the tile (upper bound);
* ``kernel``:  what the kernel evaluates: per work-item (PIX pixels of a row) the samples up to
  and including the one where its last pixel stops, times its in-image pixels; this is
  emulated in float32 from the engine's own projected values and sorted keys;
* ``useful``:  per pixel, samples up to and including its own stop;
* ``kernel_alpha``: of the ``kernel`` count, the samples where some pixel of the work-item has
  alpha >= ALPHA_MIN (and sigma >= 0): a lower bound of the samples whose exp the kernel
  evaluates, since the extent test that skips the others is conservative.

All use the configuration's ALPHA_MAX clamp (until issue 21 item 5 the emulation clamped
at 0.99 whatever the configuration said; the default is 0.999).

The compositor's fraction of the float32 FMA peak is counted, not assumed
(:func:`composite_counts`): the forward runs once more through the stage drivers with the
compositing kernel's sample counters compiled in (``CLS_COUNT``, kernels/composite.cl; the
timed runs have none), which give per work-item the samples tested against its row
segment's extent, past that test, past the sigma bound and past the alpha test; each class
is charged the floating-point operations the kernel source executes for it
(:data:`COMPOSITE_OPS`). Until issue 35 every kernel-exact evaluation was charged an
assumed 40 flops (``FLOPS_PER_EVAL``, still reported beside as ``assumed_40``).

The per-tile sort (:func:`clsplat.stages.sort_segments`, on the forward's keys shuffled inside
each segment) is compared with numpy on the same unsorted uint64 keys, side by side in
the same loop: ``np.argsort(keys, kind='stable')``, ``np.argsort(keys)`` and ``np.sort(keys)``.
"""
from __future__ import annotations

import time
from collections import defaultdict

import numpy as np
import torch

import clsplat
from clsplat import stages as engine
from clsplat.config import RenderConfig
from clsplat.runtime import Runtime, get_runtime, read_back

from . import backward as BW
from . import scenes as S
from .timing import event_ms, summarise

__all__ = ["time_forward", "count_evaluations", "sort_vs_numpy", "stage_bytes", "scaling",
           "FLOPS_PER_EVAL", "COMPOSITE_OPS", "composite_counts", "composite_flops"]

#: floating-point operations per compositing evaluation that were assumed for the FLOP
#: fraction until issue 35 (reported beside the counted one as ``assumed_40``): conic
#: quadratic form 8, alpha (mul, min) 2, exp counted as 15, tests and selects 6,
#: transmittance 2, weight 1, 3 colour channels 6.
FLOPS_PER_EVAL = 40

#: Floating-point operations the forward compositing kernel (kernels/composite.cl) executes
#: per work-item and sample, by how far the sample got; ``lane`` ones run on each of the
#: item's PIX pixels, ``scalar`` ones once. A multiply-add counts 2 (as the FMA peak does),
#: an add, multiply, compare, select (fmin, fmax, fabs, ?:) or int-float conversion 1;
#: integer, mask and lane-reduction work 0.
#:  - ``tested``: the extent test. Tuned build: extent_bits on vectors of samples, per sample
#:    dy = |y - pyc| (2), dx = max(0, max(px_first - x, x - px_last)) (4), 2 compares = 8.
#:    Baseline build: outside_extent per sample, the same 6 + ext_y < 0 + two bounds
#:    ext * (1 + m) + m (2 each) and 2 compares = 12.
#:  - ``extent`` (past the extent test): dx (1/lane), dy (1), sigma = 0.5 (ca dx dx + cc dy dy)
#:    + cb dx dy: ca dx dx (2/lane), cc dy dy (2), + (1/lane), 0.5 x (1/lane), cb dx dy
#:    (2/lane), + (1/lane): 8/lane + 3; the tuned build's sigma <= bound test 1/lane more.
#:  - ``sigma`` (past the sigma bound: the exp runs): -sigma 1, exp 29 (common.h's cls_vexp,
#:    SLEEF's expf_u10: scale 1, rint by add 1, convert 1, two-part reduction 4, degree-7
#:    polynomial 6 FMAs 12, s^2 1, last FMA 2, + 1 1, two 2^k scalings 2, two range
#:    selects 4; the baseline's library exp is the same algorithm), o x exp 1, fmin 2,
#:    sigma >= 0 and alpha >= ALPHA_MIN 2: 35/lane.
#:  - ``alpha`` (past the alpha test: the blend runs): 1 - alpha 1, T x 1, <= T_MIN 1,
#:    alpha T 1, its select 1, T's select 1: 6/lane, and per channel of the launch an FMA
#:    into the accumulator: 2/lane.
COMPOSITE_OPS = {
    "tested": {"tuned": 8, "baseline": 12},
    "extent": {"lane": {"tuned": 9, "baseline": 8}, "scalar": 3},
    "sigma": {"lane": 35},
    "alpha": {"lane": 6, "lane_per_channel": 2},
}

STAGE_ORDER = ("project", "sh", "sort_small", "sort_depth", "bin_gather", "bin_place", "bin_count", "scan",
               "bin_scatter", "sort_serial", "sort_local", "sort_merge", "composite")


def _inputs(scene: dict, cfg: RenderConfig) -> dict:
    c = lambda t: t.detach().to(cfg.dtype).contiguous()  # noqa: E731
    return {k: c(scene[k]) for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")}


class Forward:
    """What one forward render leaves for the counters: outputs, ``meta``, runtime, config."""

    def __init__(self, rt, cfg, scene, render, alpha, meta):
        self.rt, self.cfg, self.scene = rt, cfg, scene
        self.render, self.alpha, self.meta = render, alpha, meta
        self.width, self.height, self.tile_size = scene["width"], scene["height"], meta["tile_size"]


def run_forward(rt: Runtime, cfg: RenderConfig, scene: dict, events=None, inputs=None,
                tile_size: int = 16) -> Forward:
    """One forward render through :func:`clsplat.rasterization` (no graph recorded)."""
    x = inputs or _inputs(scene, cfg)
    with torch.no_grad():
        render, alpha, meta = clsplat.rasterization(
            x["means"], x["quats"], x["scales"], x["opacities"], x["colors"], x["viewmats"], x["Ks"],
            scene["width"], scene["height"], sh_degree=scene["sh_degree"], tile_size=tile_size,
            device=rt, config=cfg, events=events)
    return Forward(rt, cfg, scene, render, alpha, meta)


def time_forward(scene: dict, repeats: int = 5, device=None, cfg: RenderConfig | None = None,
                 fresh: bool = True, keep_state: bool = False) -> dict:
    """Per-stage device milliseconds (first call apart) and wall time per forward pass."""
    cfg = cfg or RenderConfig()
    base = get_runtime(device)
    rt = Runtime(base.device) if fresh else base
    x = _inputs(scene, cfg)
    runs, walls, state = [], [], None
    for r in range(repeats + 1):
        events: list = []
        t0 = time.perf_counter()
        st = run_forward(rt, cfg, scene, events, x)
        rt.queue.finish()
        walls.append((time.perf_counter() - t0) * 1e3)
        per = defaultdict(float)
        for name, ev in events:
            per[name] += event_ms(ev)
        runs.append(dict(per))
        if r == repeats and keep_state:
            state = st
        else:
            rt.finish()
    names = [n for n in STAGE_ORDER if any(n in run for run in runs)] + sorted(
        {n for run in runs for n in run} - set(STAGE_ORDER))
    warm = runs[1:]
    out = {
        "scene": scene["name"], "n_gaussians": int(scene["means"].shape[0]), "n_pixels": S.n_pixels(scene),
        "n_cameras": int(scene["viewmats"].shape[0]), "width": scene["width"], "height": scene["height"],
        "precision": cfg.precision, "repeats": repeats,
        "first_call_ms": {n: runs[0].get(n, 0.0) for n in names} | {"wall": walls[0]},
        "stages_ms": {n: summarise([run.get(n, 0.0) for run in warm]) for n in names},
        "kernel_total_ms": summarise([sum(run.values()) for run in warm]),
        "wall_ms": summarise(walls[1:]),
    }
    out["first_call_ms"]["kernel_total"] = sum(runs[0].values())
    out["build_and_jit_ms"] = walls[0] - out["wall_ms"]["median"]
    if keep_state:
        out["_state"], out["_rt"] = state, rt
    return out


def count_evaluations(st, scene: dict) -> dict:
    """Compositing evaluation counts (segment bound, kernel-exact emulation, useful)."""
    rt, cfg, meta = st.rt, st.cfg, st.meta
    W, H, ts = st.width, st.height, st.tile_size
    C = int(scene["viewmats"].shape[0])
    tx, ty = -(-W // ts), -(-H // ts)
    pix = engine.composite_layout(rt, cfg, ts, st.render.shape[-1])[0]
    ids = meta["flatten_ids"].to(torch.int64)
    off = np.concatenate([meta["isect_offsets"].reshape(-1).numpy().astype(np.int64), [ids.numel()]])
    xy = meta["means2d"].detach().reshape(-1, 2).float()
    con = meta["conics"].detach().reshape(-1, 3).float()
    op = meta["opacities"].detach().reshape(-1).float()
    ly, lx = torch.meshgrid(torch.arange(ts), torch.arange(ts), indexing="ij")
    ly, lx = ly.reshape(-1), lx.reshape(-1)
    n_tiles = C * tx * ty
    t_in_cam = torch.arange(n_tiles) % (tx * ty)
    PY = (t_in_cam // tx)[:, None] * ts + ly[None]                              # [tiles, ts*ts]
    PX = (t_in_cam % tx)[:, None] * ts + lx[None]
    INSIDE = (PX < W) & (PY < H)
    lens = torch.from_numpy(np.diff(off))
    seg_total = int((lens * INSIDE.sum(1)).sum())
    kern_total = useful_total = alpha_total = 0
    # Tiles in batches, padded to the longest segment of the batch (sorted by length so that
    # padding stays small); padding samples are invalid and never stop a pixel.
    order = torch.argsort(lens)
    budget = 4_000_000
    i = 0
    while i < n_tiles:
        n_max = max(int(lens[order[min(i + 1, n_tiles) - 1]]), 1)
        j = i + 1
        while j < n_tiles and (j - i + 1) * max(int(lens[order[j]]), 1) * ts * ts <= budget:
            j += 1
        tiles = order[i:j]
        n_max = max(int(lens[tiles].max()), 1)
        i = j
        starts = torch.from_numpy(off[:-1])[tiles]
        k = torch.arange(n_max)
        pos = starts[:, None] + k[None]                                         # [b, n]
        real = k[None] < lens[tiles][:, None]
        g = ids[pos.clamp_max(max(ids.numel() - 1, 0))] if ids.numel() else torch.zeros_like(pos)
        px = PX[tiles].float()[:, None, :] + 0.5
        py = PY[tiles].float()[:, None, :] + 0.5
        dx = xy[g, 0][..., None] - px
        dy = xy[g, 1][..., None] - py
        sigma = 0.5 * (con[g, 0][..., None] * dx * dx + con[g, 2][..., None] * dy * dy) + con[g, 1][..., None] * dx * dy
        alpha = torch.clamp_max(op[g][..., None] * torch.exp(-sigma), cfg.alpha_max)
        valid = (sigma >= 0) & (alpha >= cfg.alpha_min) & real[..., None]
        Tc = torch.cumprod(torch.where(valid, 1 - alpha, torch.ones_like(alpha)), 1)
        hit = Tc <= cfg.t_min                                                   # [b, n, P]
        any_hit = hit.any(1)
        n_t = lens[tiles][:, None].expand_as(any_hit)
        stop = torch.where(any_hit, hit.to(torch.uint8).argmax(1) + 1, n_t)
        inside = INSIDE[tiles]
        stop = torch.where(inside, stop, torch.zeros_like(stop))
        useful_total += int(stop.sum())
        b = len(tiles)
        item = stop.reshape(b, ts, ts // pix, pix).amax(-1)
        n_in = inside.reshape(b, ts, ts // pix, pix).sum(-1)
        kern_total += int((item * n_in).sum())
        seen = valid.reshape(b, n_max, ts, ts // pix, pix).any(-1) & (k[None, :, None, None] < item[:, None])
        alpha_total += int((seen.sum(1) * n_in).sum())
    return {"segment": int(seg_total), "kernel": int(kern_total), "useful": int(useful_total),
            "kernel_alpha": int(alpha_total), "pix_per_item": pix, "intersections": int(off[-1])}


def composite_flops(counts: dict) -> float:
    """Floating-point operations of the forward compositing, from the kernel's sample counts
    (:func:`composite_counts`) and :data:`COMPOSITE_OPS`; every launch blends ``cchunk``
    channels (the last one's padding included)."""
    impl, pix = "tuned" if counts["tuned"] else "baseline", counts["pix"]
    ops = COMPOSITE_OPS
    return float(counts["tested"] * ops["tested"][impl]
                 + counts["extent"] * (ops["extent"]["lane"][impl] * pix + ops["extent"]["scalar"])
                 + counts["sigma"] * ops["sigma"]["lane"] * pix
                 + counts["alpha"] * (ops["alpha"]["lane"]
                                      + ops["alpha"]["lane_per_channel"] * counts["cchunk"]) * pix)


def composite_counts(scene: dict, cfg: RenderConfig | None = None, device=None,
                     tile_size: int = 16) -> dict:
    """The forward of :func:`clsplat.rasterization` (no background, its default keywords),
    run through the stage drivers with the compositing kernel's sample counters on.

    Returns the totals over work-items (and channel-chunk launches) of samples ``tested``
    against an item's extent, past that test (``extent``), past the sigma bound (``sigma``)
    and past the alpha test (``alpha``), each launch of a chunk of channels counting again;
    the layout (``pix``, ``tuned``, ``launches``, ``cchunk`` channels a launch), ``flops`` (:func:`composite_flops`) and the composited ``image``
    [C,H,W,CH] and ``T`` [C,H,W], which equal rasterization()'s bit for bit.
    """
    from clsplat.autograd import _centre_viewmats
    from clsplat.validate import rescale_large_quats

    cfg = cfg or RenderConfig()
    rt = get_runtime(device)
    x = _inputs(scene, cfg)
    x["quats"] = rescale_large_quats(x["quats"])
    W, H, ts = scene["width"], scene["height"], tile_size
    arr = rt.array
    p = engine.project(rt, cfg, arr(x["means"]), arr(x["quats"]), arr(x["scales"]), arr(x["opacities"]),
                       arr(x["viewmats"]), arr(x["Ks"]), W, H, ts, near_plane=0.01, far_plane=1e10,
                       eps2d=0.3, radius_clip=0.0, antialiased=False)
    C, N = x["viewmats"].shape[0], x["means"].shape[0]
    if scene["sh_degree"] is not None:
        feats = engine.sh_colors(rt, cfg, arr(x["means"]), arr(_centre_viewmats(x["viewmats"])),
                                 arr(x["colors"]), p.radii, scene["sh_degree"])
    else:
        c = x["colors"]
        feats = arr((c.expand(C, N, c.shape[-1]) if c.dim() == 2 else c).contiguous())
    offsets, keys = engine.tile_lists(rt, cfg, p.rects, p.depths, W, H, ts)
    CH = feats.tensor.shape[-1]
    pix, _, chunk, _ = engine.composite_layout(rt, cfg, ts, CH)
    group = ts * ts // pix
    counts = rt.empty((C * (-(-W // ts)) * (-(-H // ts)) * group, 4), torch.int32)
    out, T, _ = engine.composite(rt, cfg, p.means2d, p.conics, p.opacities, p.extents, feats,
                                 offsets, keys, W, H, ts, save_last=False, counts=counts)
    image, T_t, n = (t.clone() for t in read_back(out, T, counts))
    rt.finish()
    tot = n.to(torch.int64).sum(0).tolist()
    res = {"tested": tot[0], "extent": tot[1], "sigma": tot[2], "alpha": tot[3], "pix": pix,
           "tuned": engine.composite_tuned(rt, cfg), "launches": -(-CH // chunk), "cchunk": chunk,
           "items": int(n.shape[0]), "image": image, "T": T_t}
    res["flops"] = composite_flops(res)
    return res


def sort_vs_numpy(st, repeats: int = 5) -> dict:
    """The per-tile sort against numpy on the same unsorted keys, medians side by side."""
    rt, cfg, meta = st.rt, st.cfg, st.meta
    ids = meta["flatten_ids"].to(torch.int64)
    off = np.concatenate([meta["isect_offsets"].reshape(-1).numpy().astype(np.int64), [ids.numel()]])
    depth_bits = meta["depths"].detach().reshape(-1).to(torch.float32).view(torch.int32).to(torch.int64) & 0xFFFFFFFF
    sorted_keys = (depth_bits[ids] << 32) | ids
    # The bin stage leaves segments in atomic order; a fixed random permutation inside each
    # segment stands for it (the local bitonic sort's work does not depend on the order).
    seg = np.repeat(np.arange(len(off) - 1), np.diff(off))
    rnd = np.random.default_rng(0).random(seg.size)
    perm = np.lexsort((rnd, seg))
    unsorted = sorted_keys[torch.from_numpy(perm)].contiguous()
    k_np = unsorted.numpy().view(np.uint64)
    offsets = rt.array(torch.from_numpy(off.astype(np.int32)))
    res = defaultdict(list)
    ok = True
    for r in range(repeats + 1):
        ka = rt.array(unsorted.clone())
        ev: list = []
        t0 = time.perf_counter()
        engine.sort_segments(rt, cfg, ka, offsets, events=ev)
        rt.queue.finish()
        wall = (time.perf_counter() - t0) * 1e3
        if r == 0:
            order = np.lexsort((k_np, seg))
            ok = bool(np.array_equal(ka.host().numpy().view(np.uint64), k_np[order]))
            continue
        res["clsplat_kernel_ms"].append(sum(event_ms(e) for _, e in ev))
        res["clsplat_wall_ms"].append(wall)
        for name, fn in (("np_argsort_stable_ms", lambda: np.argsort(k_np, kind="stable")),
                         ("np_argsort_ms", lambda: np.argsort(k_np)),
                         ("np_sort_ms", lambda: np.sort(k_np))):
            t0 = time.perf_counter()
            fn()
            res[name].append((time.perf_counter() - t0) * 1e3)
        rt.finish()
    med = {k: float(np.median(v)) for k, v in res.items()}
    return {"n_keys": int(k_np.size), "n_segments": int((np.diff(off) > 0).sum()),
            "max_segment": int(np.diff(off).max()) if len(off) > 1 else 0, "correct": ok,
            "medians_ms": med, "all_ms": {k: list(map(float, v)) for k, v in res.items()},
            "ratio_kernel_vs_argsort_stable": med["clsplat_kernel_ms"] / med["np_argsort_stable_ms"],
            "ratio_wall_vs_argsort_stable": med["clsplat_wall_ms"] / med["np_argsort_stable_ms"],
            "ratio_kernel_vs_argsort_default": med["clsplat_kernel_ms"] / med["np_argsort_ms"]}


def stage_bytes(scene: dict, M: int, real: int = 4) -> dict:
    """Approximate bytes each stage reads plus writes (for the bandwidth fraction)."""
    C, N = int(scene["viewmats"].shape[0]), int(scene["means"].shape[0])
    Kc = scene["colors"].shape[1] if scene["sh_degree"] is not None else 0
    CH = 3
    P = S.n_pixels(scene)
    return {
        "project": N * 11 * real + C * N * (8 * real + 6 * 4),
        "sh": N * (Kc * 3 + 3) * real + C * N * (8 + CH * real),
        "bin_count": C * N * 16 + M * 8,
        "bin_scatter": C * N * (16 + real) + M * (8 + 8 + 4),
        "sort_local": M * 16,
        "sort_merge": M * 16,
        # kernels/order.cl (issue 35), with every pair touching a tile (an upper bound): the
        # radix sort's pass 0 reads rects and depths and writes 8-byte packed rectangles, then
        # reads those and depths again and writes the keys; 3 more passes read the keys twice
        # and write them once; the gather reads a key and a packed rectangle (at random) and
        # writes one; the placement reads the sorted rectangles twice, the keys once and
        # writes the tile lists. order_small: project's rectangles instead of packed ones.
        "sort_depth": C * N * (16 + real + 8 + 8 + real + 8 + 3 * 24),
        "bin_gather": C * N * (8 + 8 + 8),
        "bin_place": C * N * (2 * 8 + 8) + M * 8,
        "sort_small": C * N * (2 * (16 + real) + 8 + 3 * 24 + 2 * (8 + 16)) + M * 8,
        "composite": M * (8 + (6 + CH) * real) + P * (CH + 1) * real,
    }


def scaling(scene_iter, repeats: int = 3, device=None, x_key: str = "n_gaussians",
            backward: bool = True) -> dict:
    """Time per forward (and forward+backward) vs a size; log-log slopes of total kernel time,
    composite, sort, project, wall and the backward's kernel total."""

    rows = []
    for sc in scene_iter:
        r = time_forward(sc, repeats, device, fresh=False)
        row = {"scene": sc["name"], "n_gaussians": r["n_gaussians"], "n_pixels": r["n_pixels"],
               "kernel_total_ms": r["kernel_total_ms"]["median"], "wall_ms": r["wall_ms"]["median"],
               "stages_ms": {k: v["median"] for k, v in r["stages_ms"].items()}}
        if backward:
            b = BW.time_backward(sc, max(1, repeats - 1), device)
            row["backward_kernel_total_ms"] = b["backward_kernel_total_ms"]["median"]
            row["backward_stages_ms"] = {k: v["median"] for k, v in b["backward_stages_ms"].items()}
            row["bwd_fwd_ratio"] = b["bwd_fwd_ratio_kernels"]
            row["intersections"] = b["intersections"]
        rows.append(row)
    x = np.log10([row[x_key] for row in rows])
    slopes = {}
    for key in ("kernel_total_ms", "wall_ms") + (("backward_kernel_total_ms",) if backward else ()):
        y = np.log10([max(row[key], 1e-6) for row in rows])
        slopes[key] = float(np.polyfit(x, y, 1)[0]) if len(rows) > 1 else float("nan")
    for st in ("composite", "sort", "project"):
        y = np.log10([max(_stage(row["stages_ms"], st), 1e-6) for row in rows])
        slopes[st] = float(np.polyfit(x, y, 1)[0]) if len(rows) > 1 else float("nan")
    if backward:
        y = np.log10([max(row["backward_stages_ms"].get("composite_bwd", 0.0), 1e-6) for row in rows])
        slopes["composite_bwd"] = float(np.polyfit(x, y, 1)[0]) if len(rows) > 1 else float("nan")
    return {"x": x_key, "rows": rows, "loglog_slope": slopes}


def _stage(stages_ms: dict, name: str) -> float:
    """Median ms of a stage; "sort" sums every stage whose name starts with "sort"."""
    if name == "sort":
        return sum(v["median"] if isinstance(v, dict) else v for k, v in stages_ms.items() if k.startswith("sort"))
    v = stages_ms.get(name, 0.0)
    return v["median"] if isinstance(v, dict) else v


def _fmt(x, nd=2):
    return "-" if x is None else f"{x:.{nd}f}"


def scene_report(scene: dict, repeats: int, device, limits: dict, exact_counts: bool = True) -> dict:
    """Stage times, evaluation rates, limit fractions and the sort comparison for one scene."""
    r = time_forward(scene, repeats, device, keep_state=True)
    st, _ = r.pop("_state"), r.pop("_rt")
    counts = count_evaluations(st, scene) if exact_counts else None
    counted = composite_counts(scene, device=device)
    counted.pop("image"), counted.pop("T")
    r["composite_counts"] = counted
    comp_s = r["stages_ms"]["composite"]["median"] * 1e-3
    if counts:
        r["evaluations"] = counts
        r["evals_per_s"] = {k: counts[k] / comp_s for k in ("segment", "kernel", "useful")}
        best_s = r["stages_ms"]["composite"]["min"] * 1e-3
        r["evals_per_s_best"] = {k: counts[k] / best_s for k in ("segment", "kernel", "useful")}
    M = int(st.meta["flatten_ids"].numel())
    nbytes = stage_bytes(scene, M)
    bw = limits["bandwidth_GBps"] * 1e9
    frac = {}
    for name, s in r["stages_ms"].items():
        t = s["median"] * 1e-3
        if t <= 0:
            continue
        if name == "composite":
            peak = limits["flops_f32_G"] * 1e9
            frac[name] = {"limit": "flops_f32 (counted)", "fraction": counted["flops"] / t / peak}
            if counts:
                frac[name]["assumed_40"] = counts["kernel"] * FLOPS_PER_EVAL / t / peak
        elif name in nbytes or name.startswith("sort"):
            frac[name] = {"limit": "bandwidth", "fraction": nbytes.get(name, M * 16) / t / bw}
    r["limit_fraction"] = frac
    r["intersections"] = M
    r["sort_vs_numpy"] = sort_vs_numpy(st, repeats)
    st.rt.finish()
    return r


def run(out_dir, device=None, quick: bool = False, repeats: int = 5) -> dict:
    """The ``stages`` report: limits, scenes A and B, scaling; writes stages.{json,md}."""
    import json
    from pathlib import Path

    from clsplat.runtime import describe_devices

    from .limits import measure_limits

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rt = get_runtime(device)
    limits = measure_limits(rt, repeats, quick=quick)
    if quick:
        repeats = min(repeats, 2)
        sa = S.scene_a(n=2000, width=160, height=96)
        sb = S.scene_b(height=24, width=40)
        sweeps = (list(S.sweep_n((300, 1000, 3000), 160, 96)),
                  list(S.sweep_pixels(((80, 48), (160, 96)), n=1000, base_width=160)))
    else:
        sa, sb = S.scene_a(), S.scene_b()
        sweeps = (S.sweep_n(), S.sweep_pixels())
    result = {"device": rt.name, "devices": describe_devices(), "quick": quick, "repeats": repeats,
              "limits": limits, "flops_per_eval_assumed": FLOPS_PER_EVAL,
              "composite_ops": COMPOSITE_OPS, "scenes": {},
              "backward": {}, "training": {}, "specialisation": {}}
    for key, sc in (("A", sa), ("B", sb)):
        result["scenes"][key] = scene_report(sc, repeats, device, limits)
    for key, sc in (("A", sa), ("B", sb)):
        result["backward"][key] = BW.time_backward(sc, repeats, device)
        result["training"][key] = BW.training_steps(sc, max(2, repeats), device)
        result["specialisation"][key] = BW.specialisation(sc, repeats, device)
    sc_rep = max(1, min(repeats, 3))
    result["scaling_n"] = scaling(sweeps[0], sc_rep, device, "n_gaussians")
    result["scaling_pixels"] = scaling(sweeps[1], sc_rep, device, "n_pixels")
    (out / "stages.json").write_text(json.dumps(result, indent=1))
    (out / "stages.md").write_text(markdown(result))
    return result


def markdown(res: dict) -> str:
    L = [f"## Stage timings ({res['device']})", "",
         f"Limits: copy bandwidth **{res['limits']['bandwidth_GBps']:.1f} GB/s** (read+write, "
         f"{res['limits']['copy_MiB']} MiB), FMA peak **{res['limits']['flops_f32_G']:.0f} GFLOP/s** float32"
         + (f", {res['limits']['flops_f64_G']:.0f} GFLOP/s float64" if res['limits'].get('flops_f64_G') else "") + ".",
         f"Repeats: {res['repeats']} (+1 first call); device ms from profiling events; "
         "median [min-max].", ""]
    for key, r in res["scenes"].items():
        L += [f"### Scene {r['scene']}", "",
              f"{r['n_gaussians']} Gaussians, {r['n_pixels']} pixels, {r['intersections']} intersections.", "",
              "| stage | first call ms | median ms | min-max ms | fraction of limit |", "|---|---|---|---|---|"]
        for name, s in r["stages_ms"].items():
            if name == "scan" and s["max"] == 0:
                L.append("| scan | - | - | - | not captured: pyopencl's ExclusiveScanKernel returns no event |")
                continue
            f = r["limit_fraction"].get(name)
            fs = f"{100 * f['fraction']:.1f}% of {f['limit']}" if f else "-"
            L.append(f"| {name} | {r['first_call_ms'].get(name, 0):.2f} | {s['median']:.2f} | "
                     f"{s['min']:.2f}-{s['max']:.2f} | {fs} |")
        kt, w = r["kernel_total_ms"], r["wall_ms"]
        L.append(f"| **kernels total** | {r['first_call_ms']['kernel_total']:.1f} | **{kt['median']:.1f}** | "
                 f"{kt['min']:.1f}-{kt['max']:.1f} | |")
        L.append(f"| wall (host+device) | {r['first_call_ms']['wall']:.1f} | {w['median']:.1f} | "
                 f"{w['min']:.1f}-{w['max']:.1f} | |")
        L.append("")
        L.append(f"Build + JIT on the first call (wall, first - median): {r['build_and_jit_ms']:.0f} ms.")
        if "composite_counts" in r:
            cc = r["composite_counts"]
            f = r["limit_fraction"].get("composite", {})
            L.append(f"Compositing, counted (kernels/composite.cl with CLS_COUNT, {cc['pix']} pixels per item): "
                     f"{cc['tested']:.4g} samples tested against an item's extent, {cc['extent']:.4g} past it, "
                     f"{cc['sigma']:.4g} past the sigma bound (exp), {cc['alpha']:.4g} past the alpha test "
                     f"(blend): {cc['flops']:.4g} flops, **{100 * f.get('fraction', 0):.1f}%** of the float32 "
                     f"peak" + (f" (the former assumed 40 flops per kernel-exact evaluation: "
                                f"{100 * f['assumed_40']:.1f}%)" if "assumed_40" in f else "") + ".")
        if "evals_per_s" in r:
            e, c = r["evals_per_s"], r["evaluations"]
            L.append(f"Compositing evaluations/s (median composite time): **{e['kernel']:.3g}** kernel-exact ({c['kernel']:.4g} evals), "
                     f"{e['useful']:.3g} useful ({c['useful']:.4g}), {e['segment']:.3g} by segment x pixels "
                     f"({c['segment']:.4g}); at the fastest repeat {r['evals_per_s_best']['kernel']:.3g} kernel-exact.")
        sv = r["sort_vs_numpy"]
        m = sv["medians_ms"]
        L.append(f"Sort of {sv['n_keys']} keys in {sv['n_segments']} segments (max {sv['max_segment']}), "
                 f"correct={sv['correct']}: clsplat kernels {m['clsplat_kernel_ms']:.1f} ms (wall "
                 f"{m['clsplat_wall_ms']:.1f}), numpy argsort stable {m['np_argsort_stable_ms']:.1f} ms, "
                 f"argsort {m['np_argsort_ms']:.1f} ms, sort {m['np_sort_ms']:.1f} ms; ratio clsplat/argsort-stable "
                 f"**{sv['ratio_kernel_vs_argsort_stable']:.2f}**.")
        L.append("")
    if res.get("backward"):
        L.append(BW.markdown(res))
    for key, label in (("scaling_n", "N (fixed resolution, SH3)"), ("scaling_pixels", "pixels (fixed Gaussians)")):
        sc = res[key]
        L += [f"### Scaling with {label}", "",
              "Forward: medians of a no-grad forward; backward: device ms of the backward kernels with every "
              "parameter requiring grad (medians, fewer repeats); ratio = backward / forward kernel totals of the "
              "grad-recording pass.", "",
              "| scene | N | pixels | kernels ms | composite ms | sort ms | wall ms | backward kernels ms | "
              "composite_bwd ms | bwd/fwd |",
              "|---|---|---|---|---|---|---|---|---|---|"]
        for row in sc["rows"]:
            s = row["stages_ms"]
            L.append(f"| {row['scene']} | {row['n_gaussians']} | {row['n_pixels']} | {row['kernel_total_ms']:.1f} | "
                     f"{s.get('composite', 0):.1f} | {_stage(s, 'sort'):.1f} | {row['wall_ms']:.1f} | "
                     + (f"{row['backward_kernel_total_ms']:.1f} | {row['backward_stages_ms'].get('composite_bwd', 0):.1f} | "
                        f"{row['bwd_fwd_ratio']:.2f} |" if "backward_kernel_total_ms" in row else "- | - | - |"))
        sl = sc["loglog_slope"]
        L += ["", "log-log slope: " + ", ".join(f"{k} {v:.2f}" for k, v in sl.items()), ""]
    return "\n".join(L) + "\n"
