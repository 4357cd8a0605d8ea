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
"""
from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic", help="--data spec (default: the varied world)")
    p.add_argument("--preset", default="small")
    p.add_argument("--train", type=int, default=100, help="training windows of the fit")
    p.add_argument("--val", type=int, default=40, help="validation windows it is scored on")
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
    a = p.parse_args(argv)

    import numpy as np
    import torch

    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import gt_ego_motion, load_triplet
    from clsplat.models.drivingforward.depth import ground_prior_depth
    from clsplat.models.drivingforward.fusion import scale_intrinsics
    from clsplat.models.drivingforward.pose import flow_statistics, local_correlation

    preset = get_preset("drivingforward", a.preset)
    src = parse_data(a.data, default_world="varied")

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

    def design(split: str, n: int):
        X, Y = [], []
        for i in range(n):
            s = load_triplet(src, i, preset, split)
            E = s["cam_to_ego"].double()
            R = E[:, :3, :3]
            T0 = torch.linalg.inv(E[0]) @ gt_ego_motion(s)[2].double() @ E[0]
            cue = local_correlation(s["images"][1], s["images"][2], a.radius, a.level, a.temperature)
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
            X.append(M.reshape(3, -1).numpy())
            Y.append(T0[:3, 3].numpy())
        return np.concatenate(X), np.concatenate(Y)

    Xt, Yt = design("train", a.train)
    Xv, Yv = design("val", a.val)
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
    for name, X, Y in (("train (fit)", Xt, Yt), ("val", Xv, Yv)):
        P, T = (X @ A).reshape(-1, 3), Y.reshape(-1, 3)
        err, n = np.linalg.norm(P - T, axis=1), np.linalg.norm(T, axis=1)
        mv = n > 0.05
        print(f"{name}: {len(n)} windows ({mv.sum()} moving): translation error median {np.median(err[mv] / n[mv]) * 100:.0f} % "
              f"moving, {err[~mv].mean() if (~mv).any() else float('nan'):.3f} m standing; "
              f"corr(|pred|, |true|) {np.corrcoef(np.linalg.norm(P, axis=1), n)[0, 1]:.2f}")
    # the constant-motion control on the same windows: the training windows' mean translation
    c = Yt.reshape(-1, 3).mean(0)
    T = Yv.reshape(-1, 3)
    n = np.linalg.norm(T, axis=1)
    mv = n > 0.05
    print(f"constant motion (train mean {np.linalg.norm(c):.3f} m) on val: median {np.median(np.linalg.norm(T - c, axis=1)[mv] / n[mv]) * 100:.0f} % moving")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
