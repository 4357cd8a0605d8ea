"""DrivingForward in the viewer: the network run on a held-out sample, its predicted Gaussians with
the input cameras, their images and the predicted depth maps; other samples, input frames and
cameras (all, the front one, the front three, any single one) offered as variants that rerun the
model. :func:`model_scene` is also what
``clsplat train drivingforward --view`` shows of the model being trained."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import torch

from clsplat.viewer.scene import ViewCamera, ViewScene

from ..common.data import parse_data
from ..common.view import VARIANT_SAMPLES, depth_colour, gaussians_scene, model_snapshot, run_data
from .data import DEFAULT_WORLD, gt_ego_motion, load_triplet
from .evaluation import OFFSETS

__all__ = ["checkpoint_scene", "model_scene"]


def model_scene(model, preset, source, data_name: str, k: int = 0, frames: tuple[int, ...] | None = None,
                front_only: bool = False, cameras: Sequence[str] | None = None, title: str = "DrivingForward",
                split: str = "test") -> ViewScene:
    """The scene of ``model`` run on sample ``k`` of ``split``: its Gaussians (ego frame at t),
    the input cameras with their images at t and the predicted depth maps.

    Args:
        frames: input frame offsets in {-1, 0, 1} (default: the preset's mode, SF (0,), MF (-1, 1)).
        front_only: the first camera alone; cameras: camera names (default all, rig order).
    The model runs in eval mode without gradients and leaves the RNG as it found it
    (:func:`~..common.view.model_snapshot`), so that a training run watched is the run unwatched.
    """
    frames = frames or ((0,) if preset.mode == "SF" else (-1, 1))

    def build() -> ViewScene:
        s = load_triplet(source, k, preset, split=split, cameras=cameras)
        cams = slice(0, 1) if front_only else slice(None)
        fi = [OFFSETS[f] for f in frames]
        M = gt_ego_motion(s)
        to_ref = torch.stack([torch.linalg.inv(M[f].double()).float() for f in fi])
        Ks, E = s["Ks"][cams], s["cam_to_ego"][cams]
        g = model.reconstruct(s["images"][fi][:, cams], Ks, E, frame_to_ref=to_ref,
                              ref=0 if 1 not in fi else fi.index(1))
        depth = model.depth_net(s["images"][1][cams], Ks, E)["depth"][:, 0].numpy()
        names = s["names"][cams]
        sc = gaussians_scene(g, f"{title} {preset.name} on {data_name} sample {k}, frames {list(frames)} "
                                f"(ego frame)")
        V = (s["viewmats"][1][cams] @ s["ego_to_world"][1]).double().numpy()   # ego(t) -> camera
        imgs = s["images"][1][cams].permute(0, 2, 3, 1).numpy()
        sc.cameras = [ViewCamera(n, Ks[i].numpy(), V[i], preset.width, preset.height, imgs[i])
                      for i, n in enumerate(names)]
        sc.depths = {n: depth_colour(depth[i]) for i, n in enumerate(names)}
        return sc

    return model_snapshot(model, build)


def checkpoint_scene(model, preset, run: Path, data: str | None, sample: int = 0,
                     safe_pickle: bool = True) -> ViewScene:
    """The scene of a DrivingForward checkpoint's ``model`` (restored by the command skeleton)
    run on held-out sample ``sample`` of ``data``, with a variant per sample, frame set and camera
    set (``data``: default the run's, else synthetic; ``safe_pickle=False`` trusts the data's
    pickles)."""
    data = data or run_data(run) or "synthetic"

    model.eval()
    source = parse_data(data, safe_pickle=safe_pickle, default_world=DEFAULT_WORLD)
    sc = model_scene(model, preset, source, data, sample)
    names = [c.name for c in sc.cameras]          # the data's cameras, rig order
    camera_sets = {"all cameras": None, "front camera": names[:1],
                   **({"front three cameras": names[:3]} if len(names) > 3 else {}),
                   **{f"camera {n}": [n] for n in names[1:]}}
    options = {f"sample {k}, frames {list(fr)}, {cs}": (k, fr, cams)
               for k in range(max(VARIANT_SAMPLES, sample + 1)) for fr in ((0,), (-1, 1), (-1, 0, 1))
               for cs, cams in camera_sets.items()}
    sc.variants = list(options)
    sc.variant = lambda name: model_scene(model, preset, source, data, options[name][0], options[name][1],
                                          cameras=options[name][2])
    return sc
