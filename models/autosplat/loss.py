"""The per-sample loss of each AutoSplat stage (:func:`stage_loss`), and the renderer that keeps
what a training step's log and densification need of its renders (:class:`StepRenderer`).

One sample is one training frame seen by every selected camera:

1. ``bg_phase1``: the road set and the sky set, each rendered alone and supervised on its own
   pixels;
2. ``bg_phase2``: all background Gaussians, pixels of tracked objects masked out (when the scene
   is decomposed);
3. ``foreground``: objects (with mirror copies and residual SH) over the detached background,
   full images, plus the L1 sparsity of the residuals;
4. ``fusion``: everything, full images, plus the sparsity;

and β·C (flatness, :func:`.background.flatness`) in every stage but the foreground's when the
flatness switch is on.
"""
from __future__ import annotations

import time

import torch

from ..common.gaussians import GaussianSet
from .background import flatness, masked_photometric, reference_frames
from .init import ROAD, SKY

__all__ = ["StepRenderer", "stage_loss"]


class StepRenderer:
    """Renders Gaussian sets of a scene through clsplat over its sky colour, and keeps, until
    :meth:`drain`, the ``(meta, layout)`` of each training render (the densifier's statistics),
    the OpenCL profiling events and the wall time inside the rasteriser (the step's log).

    Args:
        data: the run's ``RunData`` (intrinsics, image size); device: the OpenCL device.
        eps2d, rasterize_mode: the rasteriser's 2D dilation and its mode (the preset's fields of
            the same names), for every render of the run: :attr:`options`.
    """

    def __init__(self, data, device=None, eps2d: float = 0.3, rasterize_mode: str = "classic") -> None:
        self.data, self.device = data, device
        #: the ``rasterization`` keywords every render of the run passes (training and evaluation)
        self.options = {"eps2d": float(eps2d), "rasterize_mode": rasterize_mode}
        self.renders: list = []
        self.events: list = []
        self.wall = 0.0

    def render(self, model, gs: GaussianSet, viewmats: torch.Tensor, layout=None, absgrad: bool = True):
        """``(colours [C, H, W, 3], alphas, meta)`` of ``gs`` from ``viewmats [C, 4, 4]``; a
        training render passes its ``layout`` (the ``(set key, rows)`` blocks of ``gs``)."""
        C = viewmats.shape[0]
        bg = torch.sigmoid(model.sky_color).expand(C, 3)
        t0 = time.perf_counter()
        out = gs.render(viewmats, self.data.Ks, self.data.width, self.data.height, backgrounds=bg,
                        absgrad=absgrad, packed=False, device=self.device, events=self.events, **self.options)
        self.wall += time.perf_counter() - t0
        if layout is not None:
            self.renders.append((out[2], layout))
        return out

    def drain(self) -> tuple[list, float, float]:
        """(the training renders, kernels' device seconds, wall seconds in the rasteriser) since
        the last call; starts afresh."""
        out = (self.renders, sum((ev.profile.end - ev.profile.start) for _, ev in self.events) * 1e-9, self.wall)
        self.renders, self.events, self.wall = [], [], 0.0
        return out


def _flatness(model) -> torch.Tensor:
    rows, normals = model.flatness_frames()
    bg = model.background
    return flatness(bg.quats[rows], bg.log_scales[rows].exp(), reference_frames(normals))


def _sparsity(model, n_tracks: int, frame: int) -> torch.Tensor | None:
    res = [model.residual(k, frame) for k in range(n_tracks) if bool(model.present[k, frame])]
    res = [r for r in res if r is not None]
    return torch.cat([r.reshape(-1) for r in res]).abs().mean() if res else None


def stage_loss(model, renderer: StepRenderer, data, preset, switches, stage: str, frame: int,
               n_tracks: int) -> dict[str, torch.Tensor]:
    """The loss terms (``loss`` their weighted sum) of training ``frame`` in ``stage``."""
    p, d, m = preset, data, model
    target, vm = d.images[frame], d.viewmats[frame]
    terms: dict[str, torch.Tensor] = {}
    loss = torch.zeros(())
    if stage == "bg_phase1":
        for cls, name in ((ROAD, "road"), (SKY, "sky")):
            mask = d.classes[frame] == cls
            if not bool(mask.any()):
                continue
            gs, layout = m.scene_at(frame, background=(cls,), objects=False)
            if len(gs) == 0:
                continue
            col, _, _ = renderer.render(m, gs, vm, layout)
            l, l1, _ = masked_photometric(col, target, mask, p.lambda_dssim)
            loss = loss + l
            terms[f"l1_{name}"] = l1
    else:
        if stage == "bg_phase2":
            gs, layout = m.scene_at(frame, background=True, objects=False)
            mask = ~d.foreground[frame] if switches.decompose else None
        else:
            gs, layout = m.scene_at(frame, background=True, objects=True, detach_background=(stage == "foreground"))
            mask = None
        col, _, _ = renderer.render(m, gs, vm, layout)
        l, l1, dssim = masked_photometric(col, target, mask, p.lambda_dssim)
        loss = loss + l
        terms["l1"], terms["dssim"] = l1, dssim
    if switches.flatness and stage != "foreground":
        c = _flatness(m)
        terms["flatness"] = c
        loss = loss + p.beta_flatness * c
    if stage in ("foreground", "fusion"):
        sp = _sparsity(m, n_tracks, frame)
        if sp is not None:
            terms["sparsity"] = sp
            loss = loss + p.sparsity_weight * sp
    terms["loss"] = loss
    return terms
