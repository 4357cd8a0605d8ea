"""DrivingForward in the viewer: the network run on a held-out sample, its predicted Gaussians with
the input cameras, their images and the predicted depth maps; other samples, frame sets and
camera sets offered as variants that rerun the model."""
from __future__ import annotations

from pathlib import Path

import torch

from clsplat.viewer.scene import ViewCamera, ViewScene

from ..common.data import parse_data
from ..common.view import VARIANT_SAMPLES, depth_colour, gaussians_scene
from .cli import load_model
from .data import gt_ego_motion, load_triplet
from .evaluation import OFFSETS

__all__ = ["checkpoint_scene"]


def checkpoint_scene(ck: dict, ck_path: Path, run: Path, data: str | None, sample: int = 0, device=None,
                     safe_pickle: bool = True) -> ViewScene:
    """The scene of a DrivingForward checkpoint run on held-out sample ``sample`` of ``data``, with
    a variant per sample, frame set and camera set."""
    data = data or "synthetic"

    model, preset = load_model(str(ck_path), device)
    model.eval()
    source = parse_data(data, safe_pickle=safe_pickle)
    default_frames = (0,) if preset.mode == "SF" else (-1, 1)

    def run(k: int, frames: tuple[int, ...], front_only: bool) -> ViewScene:
        s = load_triplet(source, k, preset, split="test")
        cams = slice(0, 1) if front_only else slice(None)
        fi = [OFFSETS[f] for f in frames]
        M = gt_ego_motion(s)
        to_ref = torch.stack([torch.linalg.inv(M[f].double()).float() for f in fi])
        Ks, E = s["Ks"][cams], s["cam_to_ego"][cams]
        with torch.no_grad():
            g = model.reconstruct(s["images"][fi][:, cams], Ks, E, frame_to_ref=to_ref,
                                  ref=0 if 1 not in fi else fi.index(1))
            depth = model.depth_net(s["images"][1][cams], Ks, E)["depth"][:, 0].numpy()
        names = s["names"][cams]
        sc = gaussians_scene(g, f"DrivingForward {preset.name} on {data} sample {k}, frames {list(frames)} "
                                 f"(ego frame)")
        V = (s["viewmats"][1][cams] @ s["ego_to_world"][1]).double().numpy()   # ego(t) -> camera
        imgs = s["images"][1][cams].permute(0, 2, 3, 1).numpy()
        sc.cameras = [ViewCamera(n, Ks[i].numpy(), V[i], preset.width, preset.height, imgs[i])
                      for i, n in enumerate(names)]
        sc.depths = {n: depth_colour(depth[i]) for i, n in enumerate(names)}
        return sc

    options = {f"sample {k}, frames {list(fr)}, {'front camera' if fo else 'all cameras'}": (k, fr, fo)
               for k in range(max(VARIANT_SAMPLES, sample + 1)) for fr in ((0,), (-1, 1), (-1, 0, 1))
               for fo in (False, True)}
    sc = run(sample, default_frames, False)
    sc.variants = list(options)
    sc.variant = lambda name: run(*options[name])
    return sc
