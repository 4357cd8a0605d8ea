"""The rig's ego motion from the road's optical flow: a robust plane-induced fit (issue 32).

No learning and no ground truth: the calibration a user has (intrinsics, extrinsics, the ego
frame standing on the ground, z up, z = 0 the road: the named prior of
:func:`~clsplat.models.drivingforward.depth.ground_prior_depth`) predicts, for every pixel whose
ray meets the ground, the 3D point it sees. A rig motion ``M`` (ego coordinates at the earlier
instant to ego coordinates at the later one, ``p_later = M p_earlier``, the convention of
:func:`~clsplat.models.drivingforward.data.gt_ego_motion`) moves that point to a known pixel of the
later image in the same camera: the plane-induced flow :func:`plane_flow`. :func:`fit_ground_motion`
finds the motion whose plane-induced flow best explains a measured flow on those pixels, over all
cameras jointly, by iteratively reweighted Gauss-Newton from zero motion (Huber or Cauchy weights,
their scale re-estimated from the residuals' median at every step): pixels that are not road
(parked cars, kerbs, facades, moving vehicles) disagree with the plane and lose their weight.

:func:`fit_ground_motion_direct` is the direct form: the same motion model aligns the later
images with the earlier ones on the ground pixels (a parametric Lucas-Kanade over all cameras,
coarse to fine), so untextured road carries no weight and a lane marking or a kerb constrains the
flow across it.

Motion parameters ``theta [6]`` = ego-frame axis-angle ``(wx, wy, wz)`` then translation
``(tx, ty, tz)``; ``dof`` 3 frees ``(wz, tx, ty)`` (planar motion), 4 adds ``tz``, 6 frees all.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ..common.geometry import se3_exp
from .depth import ground_prior_depth
from .fusion import scale_intrinsics

__all__ = ["plane_flow", "fit_ground_motion", "fit_ground_motion_direct", "ground_points", "DOF_INDEX"]

#: central-difference step of the Jacobian (rad / m; float64: truncation error ~1e-12 relative)
_FD_STEP = 1e-6
#: the free entries of ``theta`` for each ``dof``
DOF_INDEX = {3: (2, 3, 4), 4: (2, 3, 4, 5), 6: (0, 1, 2, 3, 4, 5)}


def ground_points(Ks: Tensor, depth: Tensor) -> tuple[Tensor, Tensor]:
    """Every pixel centre and the camera-frame point at ``depth`` along its ray.

    Ks: ``[V, 3, 3]`` at the map's resolution; depth: ``[V, 1, h, w]`` (z-depth, m) ->
    ``(uv [V, 2, h*w]`` pixel-centre coordinates, ``X [V, 3, h*w]`` camera-frame points).
    """
    V, _, h, w = depth.shape
    v, u = torch.meshgrid(torch.arange(h, dtype=Ks.dtype, device=Ks.device) + 0.5,
                          torch.arange(w, dtype=Ks.dtype, device=Ks.device) + 0.5, indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], 0).reshape(3, -1)                   # [3, hw]
    rays = torch.linalg.inv(Ks) @ pix                                                 # [V, 3, hw], z = 1
    return pix[:2].expand(V, 2, h * w), rays * depth.reshape(V, 1, h * w).to(Ks.dtype)


def plane_flow(theta: Tensor, Ks: Tensor, cam_to_ego: Tensor, uv: Tensor, X: Tensor) -> Tensor:
    """Flow of camera-frame points ``X`` under the rig motion ``theta``.

    theta: ``[6]`` (axis-angle, translation; ego frame, earlier -> later coordinates);
    Ks ``[V, 3, 3]``; cam_to_ego ``[V, 4, 4]``; uv ``[V, 2, N]`` the points' pixels at the earlier
    instant; X ``[V, 3, N]`` -> ``[V, 2, N]`` pixel displacement to the later image.
    """
    return _flow(theta, Ks, torch.linalg.inv(cam_to_ego), cam_to_ego, uv, X)


def _flow(theta: Tensor, Ks: Tensor, ego_to_cam: Tensor, cam_to_ego: Tensor, uv: Tensor, X: Tensor) -> Tensor:
    """:func:`plane_flow` with the inverse extrinsics given (a fit calls it hundreds of times)."""
    M = se3_exp(theta[:3], theta[3:])
    T = ego_to_cam @ M @ cam_to_ego                                                    # [V, 4, 4]
    Y = T[:, :3, :3] @ X + T[:, :3, 3:]
    q = Ks @ Y
    return q[:, :2] / q[:, 2:].clamp_min(1e-6) - uv


def fit_ground_motion(flow: Tensor, Ks: Tensor, cam_to_ego: Tensor, ground_depth: Tensor,
                      weight: Tensor | None = None, dof: int = 6, loss: str = "huber",
                      iters: int = 10) -> tuple[Tensor, Tensor]:
    """The rig motion that best explains ``flow`` on the ground prior's pixels.

    Args:
        flow: ``[V, 2, h, w]`` measured displacements (pixels of that resolution) from the earlier
            to the later image of each camera.
        Ks: ``[V, 3, 3]`` at that resolution; cam_to_ego: ``[V, 4, 4]`` (ego frame on the ground).
        ground_depth: ``[V, 1, h, w]`` depth of the ground along each pixel's ray; pixels where it
            is not finite or not positive take no part.
        weight: ``[V, 1, h, w]`` >= 0, a pixel's prior weight (0: left out); None: all ones.
        dof: 3, 4 or 6 (:data:`DOF_INDEX`); loss: "huber", "cauchy" or "l2".
        iters: Gauss-Newton steps from zero motion.
    Returns:
        ``(M [4, 4]`` ego motion, earlier -> later ego coordinates, float64; ``w [V, 1, h, w]``
        the final robust weights (0 where left out)).
    """
    if dof not in DOF_INDEX:
        raise ValueError(f"dof: expected one of {sorted(DOF_INDEX)}, got {dof!r}")
    if loss not in ("huber", "cauchy", "l2"):
        raise ValueError(f"loss: expected 'huber', 'cauchy' or 'l2', got {loss!r}")
    _check_iters(iters)
    if flow.ndim != 4 or flow.shape[1] != 2 or ground_depth.shape != (flow.shape[0], 1, *flow.shape[-2:]):
        raise ValueError(f"flow / ground_depth: expected [V, 2, h, w] / [V, 1, h, w], got "
                         f"{list(flow.shape)} / {list(ground_depth.shape)}")
    dt = torch.float64
    V, _, h, w = flow.shape
    K, E = Ks.to(dt), cam_to_ego.to(dt)
    Z = ground_depth.to(dt)
    prior = torch.ones_like(Z) if weight is None else weight.to(dt)
    ok = torch.isfinite(Z) & (Z > 0) & (prior > 0) & torch.isfinite(flow.to(dt)).all(1, keepdim=True)
    uv, X = ground_points(K, torch.where(ok, Z, torch.ones_like(Z)))
    keep = ok.reshape(V, -1)
    obs = flow.to(dt).reshape(V, 2, -1)
    pw = torch.where(ok, prior, torch.zeros_like(prior)).reshape(V, -1)
    free = list(DOF_INDEX[dof])
    theta = torch.zeros(6, dtype=dt)
    rw = keep.to(dt)
    if not bool(keep.any()):
        return torch.eye(4, dtype=dt), rw.reshape(V, 1, h, w)

    seen = keep.any(0)                                                                  # [h*w]
    m = keep[:, seen]

    def residual(p: Tensor) -> Tensor:
        full = torch.zeros(6, dtype=dt).index_put((torch.tensor(free),), p)
        return (plane_flow(full, K, E, uv, X) - obs)[:, :, seen]                        # [V, 2, n]

    for _ in range(iters):
        p = theta[free]
        r = residual(p)                                                                 # [V, 2, n]
        J = torch.stack([(residual(p + d) - residual(p - d)) / (2 * _FD_STEP)          # [V, 2, n, k]
                         for d in _FD_STEP * torch.eye(len(free), dtype=dt)], -1)
        e = r.norm(dim=1)                                                               # [V, n]
        wt = _robust_weights(e, loss, e[m]) * pw[:, seen] * m
        Jw = (J * wt[:, None, :, None]).reshape(-1, len(free))
        A = Jw.T @ J.reshape(-1, len(free))
        b = Jw.T @ r.reshape(-1)
        step = -torch.linalg.solve(A + 1e-9 * torch.eye(len(free), dtype=dt), b)
        theta = theta.index_put((torch.tensor(free),), p + step)
        rw = torch.zeros(V, h * w, dtype=dt)
        rw[:, seen] = wt
        if float(step.abs().max()) < 1e-7:
            break
    return se3_exp(theta[:3], theta[3:]).detach(), rw.reshape(V, 1, h, w)


def _check_iters(iters) -> None:
    if isinstance(iters, bool) or not isinstance(iters, int) or iters < 0:
        raise ValueError(f"iters: expected an int >= 0 (Gauss-Newton steps), got {iters!r}")


def _check_grid(name: str, grid, unit: str) -> None:
    """A search grid ``(lo, hi, count)``: None, or lo < hi and an int count >= 2; else a ValueError."""
    if grid is None:
        return
    ok = isinstance(grid, (tuple, list)) and len(grid) == 3 and not isinstance(grid[2], bool) \
        and isinstance(grid[2], int) and grid[2] >= 2
    if not ok or not float(grid[0]) < float(grid[1]):
        raise ValueError(f"{name}: expected None or (lo, hi, count) {unit} with lo < hi and an int count >= 2, "
                         f"got {grid!r}")


def _robust_weights(e: Tensor, loss: str, ref: Tensor | None = None) -> Tensor:
    """IRLS weights of residual magnitudes ``e`` (any shape): Huber / Cauchy at a scale from the
    median of ``ref`` (default ``e``; 1.4826 MAD), or ones."""
    if loss == "l2":
        return torch.ones_like(e)
    scale = (1.4826 * (e if ref is None else ref).median()).clamp_min(1e-6)
    if loss == "huber":
        c = 1.345 * scale
        return torch.where(e <= c, torch.ones_like(e), c / e.clamp_min(1e-12))
    c = 2.385 * scale
    return 1.0 / (1.0 + (e / c) ** 2)


def _sample(img: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear samples of ``img [V, C, h, w]`` at pixel coordinates ``uv [V, 2, N]`` (pixel-centre
    convention) -> ``(values [V, C, N]``, ``inside [V, N]``)."""
    h, w = img.shape[-2:]
    size = uv.new_tensor([[w], [h]])                                                  # x by w, y by h
    grid = (2 * uv / size - 1).transpose(1, 2)[:, None]                               # [V, 1, N, 2]
    out = torch.nn.functional.grid_sample(img, grid, mode="bilinear", padding_mode="border",
                                          align_corners=False)[:, :, 0]
    inside = ((uv > 0.5) & (uv < size - 0.5)).all(1)
    return out, inside


class _Level(NamedTuple):
    """One pyramid level of :func:`fit_ground_motion_direct`, the prior's pixels of each camera
    first (padded to the busiest camera with weight-0 pixels); N of them a camera."""
    a: Tensor          # [V, 1, N] grey of the earlier image at those pixels
    b3: Tensor         # [V, 3, h, w] the later image's grey and its x / y gradients
    K: Tensor          # [V, 3, 3] intrinsics at this level
    uv: Tensor         # [V, 2, N] pixel coordinates
    X: Tensor          # [V, 3, N] the ground points in camera coordinates
    pw: Tensor         # [V, N] pixel weights
    b1: Tensor         # [V, 1, h, w] the later image's grey alone (the search's read)
    used: Tensor       # [V, N] bool: a prior pixel, not padding
    n_used: int        # the prior's pixels over all cameras (``used.sum()``)
    norm: Tensor       # [3, 3] pixel coordinates to grid_sample's, plus one ([0, 2] across the image)
    Xh: Tensor         # [V, 4, N] ``X`` in homogeneous coordinates (the search's one product a camera)
    pad: Tensor        # [V, N] bool: padding, not a prior pixel (``~used``)


def fit_ground_motion_direct(earlier: Tensor, later: Tensor, Ks: Tensor, cam_to_ego: Tensor, cap: float,
                             levels: tuple[int, ...] = (1,), dof: int = 6, loss: str = "huber",
                             iters: int = 8, search: tuple[float, float, int] | None = (-3.0, 3.0, 61),
                             weight: Tensor | None = None, tau: float = 0.05, keep: float = 1.0,
                             depth: Tensor | None = None,
                             yaw_search: tuple[float, float, int] | None = None) -> Tensor:
    """The rig motion that best aligns the later images with the earlier ones on the ground.

    A direct (photometric) form of :func:`fit_ground_motion`: every pixel whose ray meets the ground
    prior closer than ``cap`` is moved by the plane-induced flow of the motion and the later grey
    image is read there; the motion minimises the robust sum of ``I_later(x + flow) - I_earlier(x)``
    over all cameras (Gauss-Newton on the image gradient, so an untextured pixel carries no weight
    and an edge constrains the flow across it only), over ``levels`` in order (images averaged over
    ``l x l`` blocks; default: full resolution only, since on a low-contrast road the coarse levels'
    cost is lowest at zero motion). ``search``: before the first level, the forward translation
    (ego x, metres per frame interval, ``(lo, hi, count)``) is chosen from a grid by the mean
    absolute residual truncated at ``tau`` (grey levels in [0, 1]: a pixel worse than that, or
    moved out of view, counts as unmatched) at the first level, then from 21 values within one grid
    step of the best (a generic bound on the motion between frames, like the pose network's own
    clamp; None: start from zero motion). ``keep`` < 1 makes that cost least-trimmed, the mean of
    the lowest ``keep`` share of the prior's truncated residuals only, and gives the refinement's
    residuals beyond that share's quantile no weight (1: all of them, the plain mean, bit for bit).
    Pixels the ground prior wrongly holds on the plane (cars, kerbs, facade bases: a fifth to a
    quarter of those within 20 m) are misplaced by the plane's flow at the true motion but not at
    zero, so at 0.06-0.12 m a frame their misfit outweighs the road's signal and the plain mean is
    lowest at zero (a crawling car reads as standing); trimmed, they drop out, while at zero the
    road's own ~1-px flow still costs (issue 32; bench/notes/drivingforward_varied_world.md,
    "Crawling windows").

    Args:
        earlier, later: ``[V, 3, H, W]`` images in [0, 1]; Ks ``[V, 3, 3]`` at that size;
            cam_to_ego ``[V, 4, 4]`` (ego frame on the ground); cap: metres.
        weight: ``[V, 1, H, W]`` >= 0 prior pixel weights (0: left out; a block counts at a level
            only if all its pixels count); None: ones.
        yaw_search: ``(lo, hi, count)`` radians: after the forward search, the yaw (ego z) is
            chosen from that grid by the same cost, then the forward translation again from 21
            values within one of its grid steps. Gauss-Newton from zero yaw does not reach a turn's
            1-2 degrees a frame: the trimmed cost drops the far pixels the turn moves most, and the
            fit reads a turning window as driving straight (issue 32). None: no yaw search.
        depth: ``[V, 1, H, W]`` z-depth (m) of the earlier frame that places the prior's pixels in
            3D instead of the calibrated plane (the same pixels: those the plane puts within
            ``cap``); None: the plane. A measurement's upper bound (the data's own depth: what
            the fit would read if the road were the plane), never a model's input.
    Returns:
        ``M [4, 4]`` float64, ego coordinates at the earlier instant to the later one; the identity
        where no pixel sees the ground within ``cap`` (no evidence of motion).
    """
    if dof not in DOF_INDEX:
        raise ValueError(f"dof: expected one of {sorted(DOF_INDEX)}, got {dof!r}")
    if loss not in ("huber", "cauchy", "l2"):
        raise ValueError(f"loss: expected 'huber', 'cauchy' or 'l2', got {loss!r}")
    if earlier.shape != later.shape or earlier.ndim != 4 or earlier.shape[1] != 3:
        raise ValueError(f"earlier / later: expected two [V, 3, H, W] images, got {list(earlier.shape)} / "
                         f"{list(later.shape)}")
    if not (bool(torch.isfinite(earlier).all()) and bool(torch.isfinite(later).all())):
        raise ValueError("earlier / later: the images hold NaN or Inf")
    if not cap > 0:
        raise ValueError(f"cap: expected a positive number of metres, got {cap!r}")
    if not tau > 0:
        raise ValueError(f"tau: expected a positive grey-level difference, got {tau!r}")
    if isinstance(keep, bool) or not isinstance(keep, (int, float)) or not 0 < keep <= 1:
        raise ValueError(f"keep: expected a share of the pixels in (0, 1], got {keep!r}")
    _check_iters(iters)
    _check_grid("search", search, "metres")
    _check_grid("yaw_search", yaw_search, "radians")
    if depth is not None and (depth.shape != (earlier.shape[0], 1, *earlier.shape[-2:])
                              or not bool(torch.isfinite(depth).all()) or not bool((depth > 0).all())):
        raise ValueError(f"depth: expected a finite positive [V, 1, H, W] z-depth like the images, got "
                         f"{list(depth.shape)}")
    if not levels or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in levels):
        raise ValueError(f"levels: expected a non-empty sequence of ints >= 1, got {levels!r}")
    dt = torch.float64
    F_ = torch.nn.functional
    V, _, H, W = earlier.shape
    g1, g2 = earlier.to(dt).mean(1, keepdim=True), later.to(dt).mean(1, keepdim=True)
    E = cam_to_ego.to(dt)
    E_inv = torch.linalg.inv(E)
    pw_full = torch.ones(V, 1, H, W, dtype=dt) if weight is None else weight.to(dt)
    free = list(DOF_INDEX[dof])
    idx = (torch.tensor(free),)
    theta = torch.zeros(6, dtype=dt)
    kx = torch.tensor([[[[-0.5, 0.0, 0.5]]]], dtype=dt)

    def setup(level: int):
        a = F_.avg_pool2d(g1, level) if level > 1 else g1
        b = F_.avg_pool2d(g2, level) if level > 1 else g2
        K = scale_intrinsics(Ks.to(dt), 1.0 / level)
        h, w = a.shape[-2:]
        Z = ground_prior_depth(K, E, h, w, cap)
        pw = F_.avg_pool2d(pw_full, level) if level > 1 else pw_full
        pw = (pw * (pw > 1 - 1e-9) * (Z < cap)).reshape(V, -1)
        if depth is not None:
            Zd = depth.to(dt)
            uv, X = ground_points(K, F_.avg_pool2d(Zd, level) if level > 1 else Zd)
        else:
            uv, X = ground_points(K, Z)
        # Only the prior's pixels enter a cost or a step, so the rest is never moved or sampled: each
        # camera's own pixels first, in raster order (the same sums in the same order as over the
        # whole image), padded to the busiest camera with pixels of weight 0 (2-3x fewer samples).
        used = pw > 0
        n = max(int(used.sum(1).max()), 1)
        order = torch.argsort(used.to(torch.int8), dim=1, descending=True, stable=True)[:, :n]  # [V, n]
        pick = lambda t: t.gather(-1, order[:, None].expand(V, t.shape[1], n))               # noqa: E731
        gx = F_.conv2d(F_.pad(b, (1, 1, 0, 0), mode="replicate"), kx)
        gy = F_.conv2d(F_.pad(b, (0, 0, 1, 1), mode="replicate"), kx.transpose(-1, -2))
        pw = pw.gather(1, order)
        # the search's cost reads the grey image only (grid_sample treats channels apart: the same
        # values as the three-channel read), and the prior's pixel mask once per level
        norm = torch.tensor([[2 / w, 0, 0], [0, 2 / h, 0], [0, 0, 1]], dtype=dt)      # pixels -> [0, 2]
        X = pick(X)
        return _Level(pick(a.reshape(V, 1, -1)), torch.cat([b, gx, gy], 1), K, pick(uv), X, pw,
                      b.contiguous(), pw > 0, int((pw > 0).sum()), norm,
                      torch.cat([X, torch.ones_like(X[:, :1])], 1), pw <= 0)

    def residual(th: Tensor, lv: _Level) -> tuple[Tensor, Tensor, Tensor]:
        q = lv.uv + _flow(th, lv.K, E_inv, E, lv.uv, lv.X)
        s, inside = _sample(lv.b3, q)
        return s[:, 0] - lv.a[:, 0], s[:, 1:], lv.pw * inside

    def cost(th: Tensor, lv: _Level) -> float:
        """Mean truncated absolute residual over the prior's pixels, ``min(|r|, tau)``; a pixel moved
        out of the image counts as unmatched (``tau``), so a motion can lower the cost neither by
        moving pixels out of view nor through the pixels that are not on the ground; with ``keep``
        < 1, the mean of the lowest ``keep`` share of those.

        The search calls this hundreds of times a fit, so the read is :func:`residual`'s in fewer
        passes over the pixels: the motion, the extrinsics, the intrinsics and grid_sample's
        normalisation folded into one 3x4 matrix a camera, applied by one batched product (the same
        pixels and the same bilinear read; the coordinates differ from :func:`_flow`'s by rounding)."""
        h, w = lv.b1.shape[-2:]
        P = lv.norm @ lv.K @ (E_inv @ se3_exp(th[:3], th[3:]) @ E)[:, :3]             # [V, 3, 4]
        q = torch.bmm(P, lv.Xh)                                                         # [V, 3, N]
        g = (q[:, :2] / q[:, 2:].clamp_min(1e-6)).sub_(1)                               # grid_sample's [-1, 1]
        lim = g.new_tensor([[1 - 1 / w], [1 - 1 / h]])                                   # pixel centres 0.5 .. w - 0.5
        inside = (g.abs() < lim).all(1)
        s = torch.nn.functional.grid_sample(lv.b1, g.transpose(1, 2)[:, None], mode="bilinear",
                                            padding_mode="border", align_corners=False)[:, 0, 0]
        # the padding's pixels at +inf: never among the lowest k, nor in a sum below the k-th
        e = (s - lv.a[:, 0]).abs_().clamp_(max=tau).masked_fill_(~inside, tau).masked_fill_(lv.pad, float("inf"))
        n = lv.n_used
        if keep < 1:            # the mean of the k lowest, in O(n): those below the k-th, then its ties
            k = max(1, int(keep * n))
            kth = e.flatten().kthvalue(k).values
            below = e < kth
            return float((torch.where(below, e, 0.0).sum() + kth * (k - int(below.sum()))) / k)
        return float(torch.where(lv.pad, 0.0, e).sum() / n)

    searched = False
    for level in levels:
        lv = setup(level)
        if not bool(lv.used.any()):        # no ground pixel at this level: nothing to align (a search
            continue                     # would pick its grid's first value from equal costs)
        if not searched and search is not None:
            searched = True
            lo, hi, count = float(search[0]), float(search[1]), int(search[2])
            step_m = (hi - lo) / max(count - 1, 1)
            best = None
            for grid in (torch.linspace(lo, hi, count, dtype=dt), None):
                if grid is None:
                    grid = float(best[1][3]) + torch.linspace(-step_m, step_m, 21, dtype=dt)
                for tx in grid:
                    th = theta.clone()
                    th[3] = tx
                    c = cost(th, lv)
                    if best is None or c < best[0]:
                        best = (c, th)
            theta = best[1]
            if yaw_search is not None:
                grids = ((2, torch.linspace(float(yaw_search[0]), float(yaw_search[1]), int(yaw_search[2]),
                                            dtype=dt)),
                         (3, float(theta[3]) + torch.linspace(-step_m, step_m, 21, dtype=dt)))
                for k, grid in grids:
                    for v in grid:
                        th = theta.clone()
                        th[k] = v
                        c = cost(th, lv)
                        if c < best[0]:
                            best = (c, th)
                    theta = best[1]
        for _ in range(iters):
            r, grad, m = residual(theta, lv)                                            # [V, N], [V, 2, N]
            if not bool((m > 0).any()):
                break
            cols = []
            for d in _FD_STEP * torch.eye(6, dtype=dt)[free]:
                dflow = (_flow(theta + d, lv.K, E_inv, E, lv.uv, lv.X)
                         - _flow(theta - d, lv.K, E_inv, E, lv.uv, lv.X)) / (2 * _FD_STEP)
                cols.append((grad * dflow).sum(1))                                      # [V, N]
            J = torch.stack(cols, -1)[m > 0]                                            # [n, k]
            rr = r[m > 0]
            wt = _robust_weights(rr.abs(), loss) * m[m > 0]
            if keep < 1:        # least-trimmed here too: the residuals beyond the keep share weigh nothing
                k = min(rr.numel(), max(1, int(keep * lv.n_used)))
                wt = wt * (rr.abs() <= rr.abs().kthvalue(k).values)
            A = (J * wt[:, None]).T @ J
            bvec = (J * wt[:, None]).T @ rr
            step = -torch.linalg.solve(A + 1e-9 * torch.eye(len(free), dtype=dt) * (1 + A.diagonal().max()), bvec)
            theta = theta.index_put(idx, theta[free] + step)
            if float(step.abs().max()) < 1e-7:
                break
    return se3_exp(theta[:3], theta[3:])
