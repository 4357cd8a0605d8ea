"""How much of the ego motion can the pose network's flow cue carry? (issue 32, lead "what the pose
network can see")

For training and validation windows of the varied world, :func:`local_correlation` (the cue of
``pose_corr_radius``) is computed between frames t and t+1 of every camera, reduced to the six
:func:`flow_statistics` per camera, and the flow head's map (``pose_corr_head="flow"``: camera 0's
translation = mean over cameras of ``R_0^T R_c (A phi_c + b)``) is fitted by least squares to the
data's true camera-0 translation on the training windows and scored on the validation windows.
This is the best the 21-parameter head can do on this cue (a ceiling for a run, not a result):
if it were no better than the constant motion, no training of the head could be.

    .venv/bin/python bench/experiments/df_flow_cue_probe.py --data synthetic --train 100 --val 40

Every read-out is also scored per ego-speed bin (standing < 0.5 m/s: mean error in metres; 0.5-5,
5-10, 10-15 m/s: median % of the true translation) and, for synthetic streets, on flat against
sloped streets (gradient, vertical curvature or crossfall drawn non-zero; ``draw_world``).

``--geometric`` (issue 32, a geometric lead, no fitting on data and no ground truth): every
validation window's rig motion is fitted directly to the same flow, by
:func:`~clsplat.models.drivingforward.ground_motion.fit_ground_motion`: on the pixels where the
ground prior (camera height and extrinsics, capped at ``--geo-cap``, default the preset's
``ground_prior_cap``) meets the road, the flow a rig motion induces through the ground plane is
known; the motion (``--geo-dof`` 6: rotation and translation; 4: yaw and translation; 3: yaw,
tx, ty) is found by iteratively reweighted Gauss-Newton from zero motion (``--geo-loss`` huber by
default), all cameras jointly. Pixels whose correlation flow sits at the window's edge
(``|dx|`` or ``|dy|`` > radius - 0.5: the soft-argmax saturates there, a property of the cue) are
left out unless ``--geo-keep-edge`` (the test reads the soft-argmax before any ``--lk``). ``--geo-mask movers`` leaves out the moving vehicles' pixels
and ``--geo-mask road`` keeps only pixels the generator labels road (both read the generator's
instance / semantic maps: ground truth, diagnostic bounds, never a result). With ``--true-flow``
the fit reads the exact static-scene flow (the bound of the fit itself). ``--geo-direct [LEVEL ...]`` fits the same motion model to the
images themselves instead of the correlation's flow (a parametric Lucas-Kanade on the ground
pixels, all cameras jointly, at full resolution by default; the forward translation first chosen
from a grid of -3..3 m per frame by the mean absolute residual: :func:`fit_ground_motion_direct`). ``--size H W`` reads
the streets at another size than the preset's (the cue at a higher input resolution).

    P=".venv/bin/python bench/experiments/df_flow_cue_probe.py --data synthetic-cache:/work/cache/df"
    $P --train 100 --val 40 --ridge --geometric                 # the no-fit estimate beside the read-out
    $P --train 100 --val 40 --ridge --geometric --true-flow     # its bound
"""
from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic", help="--data spec (default: the varied world)")
    p.add_argument("--preset", default="small")
    p.add_argument("--train", type=int, default=100, help="training windows of the fit")
    p.add_argument("--val", type=int, default=40, help="validation windows it is scored on")
    p.add_argument("--val-start", type=int, default=0, metavar="K",
                   help="score validation windows K .. K+val-1 (fresh windows for a choice made on the first ones)")
    p.add_argument("--radius", type=int, default=3)
    p.add_argument("--level", type=int, default=4)
    p.add_argument("--temperature", type=float, default=0.1, help="of the correlation's soft-argmax")
    p.add_argument("--metric", action="store_true",
                   help="add the lower half's statistics weighted by the ground prior's depth / f "
                        "(camera height and extrinsics: calibration, a named prior), capped at --cap")
    p.add_argument("--cap", type=float, default=30.0, help="ground prior cap (m) of --metric")
    p.add_argument("--grid", type=int, nargs=2, metavar=("GH", "GW"),
                   help="add the flow field itself, averaged to GH x GW cells per camera (a richer "
                        "linear read-out of the same cue)")
    p.add_argument("--true-flow", action="store_true",
                   help="replace the correlation's flow by the generator's exact flow of the static scene "
                        "(its depth and the true camera motion), averaged to the cue's resolution: what "
                        "the read-out could do with a perfect flow (a bound, ground truth)")
    p.add_argument("--lk", type=int, default=0, metavar="ITERS",
                   help="refine the correlation's flow by ITERS Lucas-Kanade steps on the full-resolution "
                        "images (7x7 windows, a small damping), then average it back to the cue's resolution")
    p.add_argument("--ridge", action="store_true",
                   help="ridge regression, its weight chosen by 5-fold cross-validation on the "
                        "training windows (never on the validation ones)")
    p.add_argument("--geometric", action="store_true",
                   help="also fit each validation window's rig motion to the road's flow through the ground "
                        "plane (no training windows, no ground truth; see the docstring)")
    p.add_argument("--geo-dof", type=int, default=6, choices=(3, 4, 6), help="free motion parameters of --geometric")
    p.add_argument("--geo-loss", default="huber", choices=("huber", "cauchy", "l2"), help="robust loss of --geometric")
    p.add_argument("--geo-cap", type=float, default=None,
                   help="ground prior cap (m) of --geometric: pixels whose ground lies farther are left out "
                        "(default: the preset's ground_prior_cap, else 20)")
    p.add_argument("--geo-keep-edge", action="store_true",
                   help="keep pixels whose correlation flow sits at the search window's edge")
    p.add_argument("--geo-mask", default="none", choices=("none", "movers", "road"),
                   help="ground-truth bounds of --geometric: leave out moving vehicles' pixels (movers) or keep "
                        "only pixels labelled road (road); diagnostic only")
    p.add_argument("--geo-direct", type=int, nargs="*", default=None, metavar="LEVEL",
                   help="--geometric by direct alignment of the images on the ground instead of the correlation's "
                        "flow (fit_ground_motion_direct), over these levels in order (default: 1, full resolution)")
    p.add_argument("--geo-search", type=int, default=61, metavar="COUNT",
                   help="--geo-direct: forward translations tried over -3..3 m before Gauss-Newton (default 61)")
    p.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), default=None,
                   help="render / read the streets at H x W instead of the preset's size (multiples of 8 and of "
                        "the levels; a synthetic-cache holds only the sizes it was filled at: use --data synthetic)")
    p.add_argument("--save", default=None, metavar="JSON", help="write per-window validation results here")
    a = p.parse_args(argv)
    if a.geo_cap is not None and not a.geo_cap > 0:
        p.error(f"--geo-cap: expected a positive number of metres, got {a.geo_cap}")
    if a.geo_direct is not None:
        a.geo_direct = a.geo_direct or [1]
        if any(v < 1 for v in a.geo_direct):
            p.error(f"--geo-direct: levels must be positive ints, got {a.geo_direct}")
        a.geometric = True
    if a.val_start < 0:
        p.error(f"--val-start: expected a non-negative window index, got {a.val_start}")
    if a.geo_search < 2:
        p.error(f"--geo-search: expected at least 2 values, got {a.geo_search}")
    if a.geo_mask != "none" and not a.geometric:
        p.error("--geo-mask: only with --geometric")

    import numpy as np
    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import gt_ego_motion, load_triplet
    from clsplat.models.drivingforward.depth import ground_prior_depth
    from clsplat.models.drivingforward.fusion import scale_intrinsics
    from clsplat.models.drivingforward.data import ego_speed
    from clsplat.models.drivingforward.ground_motion import fit_ground_motion, fit_ground_motion_direct
    from clsplat.models.drivingforward.pose import flow_statistics, local_correlation
    from clsplat.models.common.data import VAL_SEED_OFFSET, TEST_SEED_OFFSET
    from clsplat.data.synthetic import SPEED_BINS, draw_world, speed_bin

    preset = get_preset("drivingforward", a.preset)
    if a.size is not None:
        import dataclasses
        try:
            preset = dataclasses.replace(preset, height=a.size[0], width=a.size[1])
        except ValueError as e:
            p.error(f"--size: {e}")
    src = parse_data(a.data, default_world="varied")
    geo_cap = a.geo_cap if a.geo_cap is not None else (preset.ground_prior_cap or 20.0)
    meta: dict[str, list] = {"train": [], "val": []}     # per window: (speed m/s, flat street or None)
    geo: list[np.ndarray] = []                            # per validation window: camera-0 translation of --geometric
    geo_info: list[dict] = []

    def street_flat(split: str, i: int):
        """True / False: the synthetic street of window i is flat / sloped; None: not a synthetic street."""
        if not src.synthetic_streets:
            return None
        off = {"train": 0, "val": VAL_SEED_OFFSET, "test": TEST_SEED_OFFSET}[split]
        return bool(draw_world(src.seed + i + off, src.world).flat)

    def truth_masks(i: int, split: str, level: int):
        """[V, 1, h, w] bool at 1/level: a moving vehicle anywhere in the block (movers), the whole
        block labelled road (road). Ground truth: the diagnostic bounds only."""
        seq = src.sequence(i, num_frames=3, height=preset.height, width=preset.width, split=split,
                           dt=preset.scenes_dt, supersample=preset.supersample)
        f1, f2 = seq.frames[1], seq.frames[2]
        c2 = {b.track_id: b.center for b in f2.boxes}
        moving = [b.track_id for b in f1.boxes if b.track_id in c2 and np.linalg.norm(b.center - c2[b.track_id]) > 1e-3]
        inst = torch.from_numpy(np.stack([f1.instances[n] for n in seq.camera_names]).astype(np.int64))
        sem = torch.from_numpy(np.stack([f1.semantics[n] for n in seq.camera_names]).astype(np.int64))
        mv = torch.isin(inst, torch.tensor(moving, dtype=torch.int64)).double()[:, None]
        road = (sem == 0).double()[:, None]
        pool = torch.nn.functional.max_pool2d
        if level == 1:
            return mv > 0, road > 0
        return pool(mv, level) > 0, -pool(-road, level) > 0

    def exact_flow(s: dict, level: int) -> torch.Tensor:
        """[V, 2, H/level, W/level] flow from frame 1 to 2 (cue pixels), static scene, sky at 1 km."""
        D = s["depths"][1].double()                                           # [V, H, W]
        D = torch.where(torch.isfinite(D), D, torch.full_like(D, 1e3))
        V, H, W = D.shape
        K = s["Ks"].double()
        v, u = torch.meshgrid(torch.arange(H, dtype=D.dtype) + 0.5, torch.arange(W, dtype=D.dtype) + 0.5, indexing="ij")
        pix = torch.stack([u, v, torch.ones_like(u)], 0).reshape(3, -1)
        X = (torch.linalg.inv(K) @ pix) * D.reshape(V, 1, -1)                 # camera 1 frame
        T = s["viewmats"][2].double() @ torch.linalg.inv(s["viewmats"][1].double())   # cam(t) -> cam(t+1)
        Y = T[:, :3, :3] @ X + T[:, :3, 3:]
        q = K @ Y
        uv = q[:, :2] / q[:, 2:].clamp_min(1e-6)
        flow = (uv - pix[:2]).reshape(V, 2, H, W)
        return torch.nn.functional.avg_pool2d(flow, level) / level

    def lk_refine(im1: torch.Tensor, im2: torch.Tensor, flow: torch.Tensor, level: int, iters: int,
                  window: int = 7, damping: float = 1e-4) -> torch.Tensor:
        """[V, 2, h, w] cue-resolution flow -> refined, the same resolution (Lucas-Kanade from im1 to im2)."""
        F_ = torch.nn.functional
        g1, g2 = im1.double().mean(1, keepdim=True), im2.double().mean(1, keepdim=True)    # [V, 1, H, W]
        V, _, H, W = g1.shape
        f = F_.interpolate(flow.double() * level, size=(H, W), mode="bilinear", align_corners=False)
        ys, xs = torch.meshgrid(torch.arange(H, dtype=f.dtype), torch.arange(W, dtype=f.dtype), indexing="ij")
        box = lambda x: F_.avg_pool2d(x, window, 1, window // 2, count_include_pad=False)  # noqa: E731
        kx = torch.tensor([[[[-0.5, 0.0, 0.5]]]], dtype=f.dtype)
        for _ in range(iters):
            gx = 2 * (xs + f[:, 0]) / (W - 1) - 1
            gy = 2 * (ys + f[:, 1]) / (H - 1) - 1
            w2 = F_.grid_sample(g2, torch.stack([gx, gy], -1), align_corners=True, padding_mode="border")
            Ix = F_.conv2d(F_.pad(w2, (1, 1, 0, 0), mode="replicate"), kx)
            Iy = F_.conv2d(F_.pad(w2, (0, 0, 1, 1), mode="replicate"), kx.transpose(-1, -2))
            It = w2 - g1
            a11, a12, a22 = box(Ix * Ix) + damping, box(Ix * Iy), box(Iy * Iy) + damping
            b1, b2 = -box(Ix * It), -box(Iy * It)
            det = a11 * a22 - a12 * a12
            f = f + torch.cat([(a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det], 1)
        return (F_.avg_pool2d(f, level) / level).to(flow.dtype)

    def design(split: str, n: int, start: int = 0):
        X, Y = [], []
        for i in range(start, start + n):
            s = load_triplet(src, i, preset, split)
            E = s["cam_to_ego"].double()
            R = E[:, :3, :3]
            T0 = torch.linalg.inv(E[0]) @ gt_ego_motion(s)[2].double() @ E[0]
            cue = local_correlation(s["images"][1], s["images"][2], a.radius, a.level, a.temperature)
            raw_flow = cue[:, -2:].double()                                   # the soft-argmax, before --lk
            if a.lk:
                cue = torch.cat([cue[:, :-2], lk_refine(s["images"][1], s["images"][2], cue[:, -2:], a.level, a.lk)], 1)
            if a.true_flow:
                cue = torch.cat([cue[:, :-2], exact_flow(s, a.level).to(cue.dtype)], 1)
            Kl = scale_intrinsics(s["Ks"], 1.0 / a.level)
            phi = flow_statistics(cue[:, -2:], Kl).double()
            if a.metric:
                flow = cue[:, -2:].double()
                h, w = flow.shape[-2:]
                Zg = ground_prior_depth(Kl.double(), E, h, w, a.cap)            # [V, 1, h, w]
                ground = (Zg < a.cap).double()
                fl = flow * Zg / torch.stack([Kl[:, 0, 0], Kl[:, 1, 1]], 1).double().reshape(-1, 2, 1, 1)
                metric = flow_statistics(fl * ground, Kl.double())[:, :3]        # lower half
                phi = torch.cat([phi, metric], 1)
            if a.grid:
                cells = torch.nn.functional.adaptive_avg_pool2d(cue[:, -2:].double(), tuple(a.grid))
                phi = torch.cat([phi, cells.reshape(cells.shape[0], -1)], 1)
            phi = torch.cat([phi, torch.ones(phi.shape[0], 1, dtype=phi.dtype)], 1)
            M = torch.einsum("ckj,cm->kjm", R[0].T.unsqueeze(0) @ R, phi) / E.shape[0]   # t0 = M : [A | b]
            meta[split].append((ego_speed(s), street_flat(split, i)))
            if a.geometric and split == "val":
                Kl = scale_intrinsics(s["Ks"], 1.0 / a.level).double()
                flow = cue[:, -2:].double()
                h, w = flow.shape[-2:]
                Zg = ground_prior_depth(Kl, E, h, w, geo_cap)
                wgt = (Zg < geo_cap).double()
                if not a.geo_keep_edge and not a.true_flow:
                    wgt = wgt * (raw_flow.abs().amax(1, keepdim=True) <= a.radius - 0.5)
                if a.geo_mask != "none":
                    movers, road = truth_masks(i, split, a.level)
                    wgt = wgt * (~movers if a.geo_mask == "movers" else road)
                if a.geo_direct:
                    w1 = None
                    if a.geo_mask != "none":
                        movers, road = truth_masks(i, split, 1)
                        w1 = (~movers if a.geo_mask == "movers" else road).double()
                    Mg = fit_ground_motion_direct(s["images"][1], s["images"][2], s["Ks"], E, geo_cap,
                                                  levels=tuple(a.geo_direct), dof=a.geo_dof, loss=a.geo_loss,
                                                  weight=w1, search=(-3.0, 3.0, a.geo_search))
                    rw = torch.zeros(1)
                else:
                    Mg, rw = fit_ground_motion(flow, Kl, E, Zg, wgt, dof=a.geo_dof, loss=a.geo_loss)
                Tg = torch.linalg.inv(E[0]) @ Mg @ E[0]
                geo.append(Tg[:3, 3].numpy())
                geo_info.append({"pixels": int((wgt > 0).sum()), "weight": float(rw.sum())})
            X.append(M.reshape(3, -1).numpy())
            Y.append(T0[:3, 3].numpy())
        return np.concatenate(X), np.concatenate(Y)

    Xt, Yt = design("train", a.train)
    Xv, Yv = design("val", a.val, a.val_start)
    def fit(X, Y, alpha):
        return np.linalg.solve(X.T @ X + alpha * np.eye(X.shape[1]), X.T @ Y)

    if a.ridge:  # rows come three per window: folds split windows, not rows
        win = np.arange(len(Yt)) // 3
        folds = win % 5
        best = None
        for alpha in 10.0 ** np.arange(-4, 4):
            errs = []
            for f in range(5):
                tr, te = folds != f, folds == f
                P = (Xt[te] @ fit(Xt[tr], Yt[tr], alpha)).reshape(-1, 3)
                T = Yt[te].reshape(-1, 3)
                n = np.linalg.norm(T, axis=1)
                mv = n > 0.05
                errs.append(np.median(np.linalg.norm(P - T, axis=1)[mv] / n[mv]))
            if best is None or np.mean(errs) < best[0]:
                best = (float(np.mean(errs)), alpha)
        print(f"ridge: alpha {best[1]:g} chosen by 5-fold CV on the training windows ({best[0] * 100:.0f} %)")
        A = fit(Xt, Yt, best[1])
    else:
        A, *_ = np.linalg.lstsq(Xt, Yt, rcond=None)
    def report(name: str, P: np.ndarray, T: np.ndarray, split: str) -> dict:
        """Print (and return) the errors of camera-0 translations P against T [n, 3], per speed bin."""
        err, n = np.linalg.norm(P - T, axis=1), np.linalg.norm(T, axis=1)
        mv = n > 0.05
        sp = np.array([m[0] for m in meta[split]])
        fl = [m[1] for m in meta[split]]
        out = {"moving_median_pct": float(np.median(err[mv] / n[mv]) * 100) if mv.any() else float("nan"),
               "standing_mean_m": float(err[~mv].mean()) if (~mv).any() else float("nan"), "bins": {}}
        parts = []
        for b in SPEED_BINS:
            sel = np.array([speed_bin(v) == b for v in sp])
            if b == "standing":
                val = float(err[sel].mean()) if sel.any() else float("nan")
                parts.append(f"standing {val:.3f} m (n={sel.sum()})")
            else:
                val = float(np.median(err[sel] / n[sel]) * 100) if sel.any() else float("nan")
                parts.append(f"{b} {val:.0f} % (n={sel.sum()})")
            out["bins"][b] = val
        line = f"{name}: {len(n)} windows ({mv.sum()} moving): translation error median {out['moving_median_pct']:.0f} % " \
               f"moving, {out['standing_mean_m']:.3f} m standing; corr(|pred|, |true|) " \
               f"{np.corrcoef(np.linalg.norm(P, axis=1), n)[0, 1]:.2f}\n    bins: " + ", ".join(parts)
        if any(f is not None for f in fl):
            flat = np.array([f is True for f in fl])
            for lab, sel in (("flat", flat & mv), ("sloped", ~flat & mv)):
                v = float(np.median(err[sel] / n[sel]) * 100) if sel.any() else float("nan")
                out[lab + "_moving_median_pct"] = v
                line += f"; {lab} streets {v:.0f} % (n={sel.sum()})"
        print(line)
        return out

    results = {}
    for name, X, Y, split in (("train (fit)", Xt, Yt, "train"), ("val", Xv, Yv, "val")):
        results[name] = report(name, (X @ A).reshape(-1, 3), Y.reshape(-1, 3), split)
    # the constant-motion control on the same windows: the training windows' mean translation
    c = Yt.reshape(-1, 3).mean(0)
    Tv = Yv.reshape(-1, 3)
    results["constant"] = report(f"constant motion (train mean {np.linalg.norm(c):.3f} m) on val",
                                 np.broadcast_to(c, Tv.shape), Tv, "val")
    if a.geometric:
        tag = f"geometric ({'direct, levels ' + ' '.join(map(str, a.geo_direct)) + f', search {a.geo_search}, ' if a.geo_direct else ''}" \
              f"{a.geo_dof} dof, {a.geo_loss}, cap {geo_cap:g} m, " \
              f"{'edge kept' if a.geo_keep_edge else 'edge left out'}, mask {a.geo_mask}" \
              f"{', EXACT FLOW (bound)' if a.true_flow else ''}) on val"
        results["geometric"] = report(tag, np.stack(geo), Tv, "val")
        print(f"    road pixels per window: median {int(np.median([g['pixels'] for g in geo_info]))}")
    if a.save:
        import json
        per = [{"speed": m[0], "flat": m[1], "true_t": Tv[k].tolist(),
                **({"geometric_t": geo[k].tolist(), **geo_info[k]} if a.geometric else {})}
               for k, m in enumerate(meta["val"])]
        with open(a.save, "w") as fh:
            json.dump({"args": vars(a), "results": results, "windows": per}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
