"""DrivingForward: the three networks, SF/MF training losses and feed-forward reconstruction.

Frames of a sample are t-1, t, t+1 (indices 0, 1, 2); the reference is t. Conventions: camera
motion ``T`` maps points of a camera's frame at one instant to its frame at another
(``p_src = T p_t``); ego motion ``M_{t->s}`` maps ego coordinates at t to ego coordinates at s.
Gaussians live in the ego frame at the reference instant; a camera c at frame s renders them with
``viewmat = E_c^-1 M_{t->s}`` (E = cam_to_ego).

* SF: the V images at t give the Gaussians; training renders every camera at t-1 and t+1 with
  the pose network's motion; evaluation renders every camera at t+1 with the true motion.
* MF: frames t-1 and t+1 of camera c give the Gaussians (moved into the ego frame at t) that render
  camera c at t.

:meth:`DrivingForward.reconstruct` takes any subset of cameras and frames and returns one Gaussian
per input pixel.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..common.gaussians import GaussianSet
from ..common.geometry import check_rigid, invert_rigid
from .depth import DepthNetwork, ground_prior_depth
from .fusion import scale_intrinsics
from .gaussian import GaussianNetwork, pixels_to_gaussians
from .losses import render_loss, smoothness_loss, spatial_loss, spatio_temporal_loss, temporal_loss
from .pose import PoseNetwork, ego_motion, negate_translation

__all__ = ["DrivingForward"]


class DrivingForward(nn.Module):
    """Pose, depth and Gaussian networks of DrivingForward.

    Args:
        preset: a :class:`~.presets.DFPreset`.
        weights: optional path of a local torchvision ResNet-18 state dict for both encoders
            (the pose encoder's 6-channel conv1 gets the duplicated, halved weights); random
            initialisation otherwise. ``init_message`` says which was used.
        device: OpenCL device for rendering (None: clsplat's default).
    """

    def __init__(self, preset, weights: str | None = None, device=None) -> None:
        super().__init__()
        self.preset = preset
        self.pose_net = PoseNetwork(preset)
        self.depth_net = DepthNetwork(preset)
        self.gaussian_net = GaussianNetwork(preset)
        self.render_device = device
        if weights is None:
            self.init_message = "backbones: random initialisation (no --weights given)"
        else:
            from ..common.backbones import load_backbone_weights
            m1 = load_backbone_weights(self.depth_net.encoder, weights, in_channels=3)
            m2 = load_backbone_weights(self.pose_net.encoder, weights, in_channels=6)
            self.init_message = f"backbones: depth encoder {m1}; pose encoder {m2}"

    # ------------------------------------------------------------------ input checks
    def check_views(self, images: Tensor, Ks: Tensor, cam_to_ego: Tensor, prefix: str = "") -> None:
        """ValueError naming the argument unless images ``[V, 3, H, W]`` (preset size, finite),
        Ks ``[V, 3, 3]`` and rigid cam_to_ego ``[V, 4, 4]`` agree."""
        p = self.preset
        if not isinstance(images, Tensor) or images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"{prefix}images: expected a tensor [V, 3, {p.height}, {p.width}], got "
                             f"{list(images.shape) if isinstance(images, Tensor) else type(images).__name__}")
        if tuple(images.shape[-2:]) != (p.height, p.width):
            raise ValueError(f"{prefix}images: preset {p.name!r} needs {p.height}x{p.width} (HxW) images, got "
                             f"{images.shape[-2]}x{images.shape[-1]}; resize them (common.data.resize_sequence)")
        if not torch.isfinite(images).all():
            raise ValueError(f"{prefix}images: contain NaN or infinite values")
        V = images.shape[0]
        if not isinstance(Ks, Tensor) or Ks.shape != (V, 3, 3):
            raise ValueError(f"{prefix}Ks: expected [{V}, 3, 3] (one intrinsics per image), got "
                             f"{list(Ks.shape) if isinstance(Ks, Tensor) else type(Ks).__name__}")
        if not isinstance(cam_to_ego, Tensor) or cam_to_ego.shape != (V, 4, 4):
            raise ValueError(f"{prefix}cam_to_ego: expected [{V}, 4, 4] (one extrinsic per image), got "
                             f"{list(cam_to_ego.shape) if isinstance(cam_to_ego, Tensor) else type(cam_to_ego).__name__}")
        if not (torch.isfinite(Ks).all() and torch.isfinite(cam_to_ego).all()):
            raise ValueError(f"{prefix}Ks / cam_to_ego: contain NaN or infinite values")
        for i in range(V):
            check_rigid(cam_to_ego[i], f"{prefix}cam_to_ego[{i}]")

    # ------------------------------------------------------------------ building blocks
    def frame_gaussians(self, net_images: Tensor, colours: Tensor, Ks: Tensor, cam_to_ego: Tensor,
                        depth_out: dict[str, Tensor] | None = None) -> tuple[GaussianSet, dict[str, Tensor]]:
        """Depth and Gaussians of one instant's cameras, in that instant's ego frame.

        Args:
            net_images: ``[V, 3, H, W]`` network inputs; colours: ``[V, 3, H, W]`` the pixels' colours;
            Ks ``[V, 3, 3]``; cam_to_ego ``[V, 4, 4]``; depth_out: a precomputed depth network output.
        Returns:
            (``GaussianSet`` of V*H*W, the depth network output).
        """
        d = depth_out if depth_out is not None else self.depth_net(net_images, Ks, cam_to_ego)
        params = self.gaussian_net(net_images, d["depth"], d["f2"], d["f4"], d["f8"])
        return pixels_to_gaussians(params, colours, d["depth"], Ks, cam_to_ego), d

    def ego_motions(self, frames: Tensor, Ks: Tensor, cam_to_ego: Tensor, ref: int) -> list[Tensor]:
        """Pose-network ego motion ``M_{ref->f}`` ``[4, 4]`` for every frame f of ``frames [F, V, 3, H, W]``."""
        out = []
        for f in range(frames.shape[0]):
            if f == ref:
                out.append(torch.eye(4, dtype=Ks.dtype, device=Ks.device))
            elif f > ref:
                out.append(ego_motion(self.pose_net(frames[ref], frames[f], Ks, cam_to_ego), cam_to_ego[0]))
            else:
                out.append(invert_rigid(ego_motion(self.pose_net(frames[f], frames[ref], Ks, cam_to_ego), cam_to_ego[0])))
        return out

    def render(self, gaussians: GaussianSet, viewmats: Tensor, Ks: Tensor) -> tuple[Tensor, Tensor]:
        """Render ``[C, 3, H, W]`` colours and ``[C, 1, H, W]`` alphas (viewmats map the Gaussians'
        frame to each camera) at the preset's size, background and clipping planes."""
        p = self.preset
        bg = torch.tensor(p.background, dtype=viewmats.dtype).expand(viewmats.shape[0], 3).contiguous()
        colors, alphas, _ = gaussians.render(viewmats, Ks, p.width, p.height, backgrounds=bg,
                                             near_plane=p.near_plane, far_plane=p.far_plane,
                                             device=self.render_device)
        return colors.permute(0, 3, 1, 2), alphas.permute(0, 3, 1, 2)

    # ------------------------------------------------------------------ inference
    @torch.no_grad()
    def reconstruct(self, images: Tensor, Ks: Tensor, cam_to_ego: Tensor, frame_to_ref: Tensor | None = None,
                    ref: int | None = None) -> GaussianSet:
        """Gaussians from any subset of cameras and frames, one per input pixel.

        Args:
            images: ``[V, 3, H, W]`` (one instant) or ``[F, V, 3, H, W]`` in [0, 1], at the preset size.
            Ks: ``[V, 3, 3]``; cam_to_ego: ``[V, 4, 4]`` (the first camera is the pose reference).
            frame_to_ref: ``[F, 4, 4]`` ego motion of each frame into the reference ego frame
                (``M_{f->ref}``); None: predicted by the pose network (needs F >= 2 frames of the same rig).
            ref: the reference frame index (default ``F // 2``).
        Returns:
            a :class:`GaussianSet` of ``F*V*H*W`` Gaussians in the ego frame at the reference instant
            (frame-major, then camera, then row-major pixels).
        """
        frames = images.unsqueeze(0) if isinstance(images, Tensor) and images.ndim == 4 else images
        if not isinstance(frames, Tensor) or frames.ndim != 5:
            raise ValueError(f"images: expected [V, 3, H, W] or [F, V, 3, H, W], got "
                             f"{list(images.shape) if isinstance(images, Tensor) else type(images).__name__}")
        F_ = frames.shape[0]
        for f in range(F_):
            self.check_views(frames[f], Ks, cam_to_ego, prefix=f"frame {f}: " if F_ > 1 else "")
        ref = F_ // 2 if ref is None else ref
        if not 0 <= ref < F_:
            raise ValueError(f"ref: frame index {ref} out of range for {F_} frames")
        if frame_to_ref is None:
            motions = [invert_rigid(M) for M in self.ego_motions(frames, Ks, cam_to_ego, ref)]
        else:
            if not isinstance(frame_to_ref, Tensor) or frame_to_ref.shape != (F_, 4, 4):
                raise ValueError(f"frame_to_ref: expected [{F_}, 4, 4], got "
                                 f"{list(frame_to_ref.shape) if isinstance(frame_to_ref, Tensor) else frame_to_ref!r}")
            for f in range(F_):
                check_rigid(frame_to_ref[f], f"frame_to_ref[{f}]")
            motions = list(frame_to_ref)
        sets = []
        for f in range(F_):
            g, _ = self.frame_gaussians(frames[f], frames[f], Ks, cam_to_ego)
            identity = torch.equal(motions[f], torch.eye(4, dtype=motions[f].dtype, device=motions[f].device))
            sets.append(g if identity else g.transform(motions[f]))
        return GaussianSet.cat(sets)

    # ------------------------------------------------------------------ training
    def photometric_terms(self, tgt: Tensor, srcs: list[Tensor], depth: Tensor, d_t: Tensor, Ks: Tensor,
                          E: Tensor, Tc: list[Tensor], M: list[Tensor], noise: Tensor | None,
                          automask: bool = True) -> dict[str, Tensor]:
        """The reprojection, spatial and spatio-temporal terms, at full resolution (the paper) or
        averaged over an image pyramid of ``preset.photometric_scales`` levels.

        Level s averages the images over 2^s x 2^s blocks and the depth through its disparity (so a
        depth edge's far side does not swamp the block), with the intrinsics scaled to match: a
        coarser level sees a displacement of n pixels as n / 2^s, which widens the basin where the
        motion is large against the texture (the near road; measured worse, bench/RESULTS.md issue
        17). Arguments as in :meth:`training_losses` (``d_t``: the depth the temporal terms see;
        ``depth``: the one the spatial term sees; ``automask``: the reprojection minimum includes
        the unwarped frames).
        Returns ``reproj``, and ``spatial`` and ``spatio_temporal`` where the preset weighs them
        (a term of weight 0 is not computed, and not reported).
        """
        p = self.preset
        levels = p.photometric_scales
        out = {"reproj": 0.0}
        if p.w_spatial > 0:
            out["spatial"] = 0.0
        if p.w_spatio_temporal > 0:
            out["spatio_temporal"] = 0.0
        for s in range(levels):
            f = 2 ** s
            pool = (lambda x: x) if f == 1 else (lambda x: F.avg_pool2d(x, f))
            dep, dt = (depth, d_t) if f == 1 else (1.0 / pool(1.0 / depth), 1.0 / pool(1.0 / d_t))
            K = Ks if f == 1 else scale_intrinsics(Ks, 1.0 / f)
            t, ss = pool(tgt), [pool(x) for x in srcs]
            nz = None if noise is None else noise[..., ::f, ::f]
            out["reproj"] = out["reproj"] + temporal_loss(t, ss, dt, K, Tc, nz, automask, p.automask_margin) / levels
            if "spatial" in out:
                out["spatial"] = out["spatial"] + spatial_loss(t, dep, K, E) / levels
            if "spatio_temporal" in out:
                out["spatio_temporal"] = out["spatio_temporal"] + spatio_temporal_loss(t, ss, dt, K, E, M) / levels
        return out

    def training_losses(self, raw: Tensor, net: Tensor, Ks: Tensor, cam_to_ego: Tensor,
                        noise: Tensor | None = None, lpips: nn.Module | None = None,
                        step: int | None = None, ego_motion_gt: list[Tensor] | None = None) -> dict[str, Tensor]:
        """Every loss term of one sample (frames t-1, t, t+1).

        Args:
            raw: ``[3, V, 3, H, W]`` images (loss targets); net: the same, colour-jittered (network inputs);
            Ks ``[V, 3, 3]``; cam_to_ego ``[V, 4, 4]``; noise ``[V, 2, H, W]`` automask tie-break;
            lpips: LPIPS module for the render loss (None: the term is off and not reported).
            step: the training step (for the preset's warm-ups; None: after them).
            ego_motion_gt: the given ego motion ``[M_{t->t-1}, M_{t->t+1}]`` (each ``[4, 4]``, ego
                coordinates at t to ego at the other frame): the data's, or the images' own
                (:mod:`~.geometric_pose`); required when the preset's ``pose_source`` is "dataset"
                or "geometric", where it replaces the pose network (which then gets no gradient),
                else unused.
        Returns:
            ``loss`` (weighted total) and the terms ``reproj, smooth, spatial, spatio_temporal, render,
            mse`` (``spatial`` and ``spatio_temporal`` only where their weight is above 0; ``lpips``
            when on; ``reproj_pose`` with ``pose_road_anchor``), and the logged-only ``diag_depth_median`` and
            ``diag_translation`` (metres, pose network t -> t+1), no gradient.
        """
        p = self.preset
        for f in range(3):
            self.check_views(raw[f], Ks, cam_to_ego, prefix=f"frame {f}: ")
        E = cam_to_ego
        sign_test = p.pose_sign_test is not None and p.pose_source == "network" and step is not None
        if p.pose_source in ("dataset", "geometric"):
            # given poses (the data's, or measured from the images): they drive every warp; the
            # pose network is not run
            if ego_motion_gt is None or len(ego_motion_gt) != 2 or any(
                    not isinstance(m, Tensor) or m.shape != (4, 4) for m in ego_motion_gt):
                raise ValueError(f"ego_motion_gt: preset pose_source {p.pose_source!r} needs the given ego motion "
                                 "[M_{t->t-1}, M_{t->t+1}] (two [4, 4] tensors)")
            M = [m.to(Ks.dtype) for m in ego_motion_gt]
            T_next = torch.linalg.inv(E[0]) @ M[1] @ E[0]
        else:
            # pose network: camera-0 motion t -> t-1 and t -> t+1, carried to every camera
            if sign_test:       # a window that ended decides the translation's sign first
                self.pose_net.sign_test_decide(step)
            P = [self.pose_net(net[0], net[1], Ks, E), self.pose_net(net[1], net[2], Ks, E)]
            T_prev, T_next = invert_rigid(P[0]), P[1]
            M = [ego_motion(T_prev, E[0]), ego_motion(T_next, E[0])]           # ego_t -> ego_s
        Tc = [torch.linalg.inv(E) @ m @ E for m in M]                          # pose.carry_pose
        d = self.depth_net(net[1], Ks, E)
        depth = d["depth"]
        tgt, srcs = raw[1], [raw[0], raw[2]]
        # warm-up: the temporal terms train the pose network only (their pull on an untrained
        # pose's depth is towards the far plane; bench/RESULTS.md, DrivingForward)
        warm = step is not None and step < p.warmup_steps
        d_t = depth.detach() if warm else depth
        # the auto-mask for the preset's first automask_steps steps (all of them by default)
        automask = p.automask_steps is None or (step is not None and step < p.automask_steps)
        anchor = p.pose_road_anchor and p.pose_source == "network"
        if anchor:
            # the pose learns from the road alone, warped with the ground prior (calibration), so
            # its scale is the rig's; the depth's temporal terms see the motion as a constant
            cap = p.ground_prior_cap if p.pose_road_cap is None else p.pose_road_cap
            prior = ground_prior_depth(Ks, E, p.height, p.width, cap)
            road = (prior < cap).to(prior.dtype)
            pose_term = temporal_loss(tgt, srcs, prior, Ks, Tc, noise, automask, p.automask_margin, road)
            Tc, M = [t.detach() for t in Tc], [m.detach() for m in M]
        if sign_test and step < p.pose_sign_test:
            # the pose's own objective with the translations as predicted and negated, no gradient
            with torch.no_grad():
                Pn = [negate_translation(x.detach()) for x in P]
                Mn = [ego_motion(invert_rigid(Pn[0]), E[0]), ego_motion(Pn[1], E[0])]
                Tcn = [torch.linalg.inv(E) @ m @ E for m in Mn]
                if anchor:
                    here = pose_term.detach()
                    there = temporal_loss(tgt, srcs, prior, Ks, Tcn, noise, automask, p.automask_margin, road)
                else:
                    dd = d_t.detach()
                    here = temporal_loss(tgt, srcs, dd, Ks, [t.detach() for t in Tc], noise, automask,
                                         p.automask_margin)
                    there = temporal_loss(tgt, srcs, dd, Ks, Tcn, noise, automask, p.automask_margin)
                self.pose_net.sign_test_accumulate(float(here - there))
        terms = self.photometric_terms(tgt, srcs, depth, d_t, Ks, E, Tc, M, noise, automask)
        if sign_test:
            if step < p.pose_sign_test:
                terms["diag_sign_delta"] = (here - there).detach()
            terms["diag_translation_sign"] = self.pose_net.translation_sign.detach().clone()
        if anchor:
            terms["reproj_pose"] = pose_term
        terms["smooth"] = smoothness_loss(depth, tgt, p.smooth_order)
        inv_E = invert_rigid(E)
        # the render's view of the motion: a constant when the preset says so (no render gradient
        # reaches the pose network; tests/test_df_model.py)
        Mr = [m.detach() for m in M] if p.detach_render_pose else M
        if p.mode == "SF":
            g, _ = self.frame_gaussians(net[1], tgt, Ks, E, d)
            viewmats = torch.cat([inv_E @ Mr[0], inv_E @ Mr[1]])
            render, _ = self.render(g, viewmats, torch.cat([Ks, Ks]))
            r = render_loss(render, torch.cat(srcs), lpips, p.w_lpips)
        else:
            sets = []
            for k, f in enumerate((0, 2)):
                g, _ = self.frame_gaussians(net[f], raw[f], Ks, E)
                sets.append(g.transform(invert_rigid(Mr[k])))
            V, HW = E.shape[0], p.height * p.width
            renders = []
            for c in range(V):
                gc = GaussianSet.cat([s.index(torch.arange(c * HW, (c + 1) * HW)) for s in sets])
                renders.append(self.render(gc, inv_E[c:c + 1], Ks[c:c + 1])[0])
            r = render_loss(torch.cat(renders), tgt, lpips, p.w_lpips)
        terms.update(r)
        terms["diag_depth_median"] = depth.detach().median()   # logged, not optimised: shows a collapse
        terms["diag_translation"] = T_next.detach()[:3, 3].norm()
        loss = terms["reproj"] + terms.get("reproj_pose", 0.0) + p.w_smooth * terms["smooth"]
        for k, w in (("spatial", p.w_spatial), ("spatio_temporal", p.w_spatio_temporal)):
            if k in terms:                      # a term of weight 0 was not computed
                loss = loss + w * terms[k]
        terms["loss"] = loss + p.w_render * terms["render"]
        return terms
