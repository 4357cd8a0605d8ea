"""PGT in the viewer: the network run on a held-out sample, its predicted Gaussians with the input
and target cameras and the predicted depth maps; other samples offered as variants.
:func:`model_scene` is also what ``clsplat train pgt --view`` shows of the model being trained."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from clsplat.viewer.scene import ViewCamera, ViewScene

from ..common.data import parse_data
from ..common.view import VARIANT_SAMPLES, depth_colour, gaussians_scene, model_snapshot, run_data
from .data import RING, make_sample

__all__ = ["checkpoint_scene", "model_scene"]


def model_scene(model, preset, source, data_name: str, k: int = 0, title: str = "PGT",
                split: str = "test") -> ViewScene:
    """The scene of ``model`` run on sample ``k`` of ``split``: its Gaussians (after the budget
    when the model has one), the input and target cameras with their images, and the predicted
    depth of each input. Runs in eval mode without gradients, the RNG left as found."""

    def build() -> ViewScene:
        s = make_sample(source, preset, k, split, None)
        base = model(s.images, s.Ks, s.cam_to_world)
        g = base.gaussians()
        sc = gaussians_scene(g, f"{title} {preset.name} on {data_name} sample {k}")
        imgs = s.images.permute(0, 2, 3, 1).numpy()
        H, W = imgs.shape[1:3]
        sc.cameras = [ViewCamera(f"input {i}", s.Ks[i].numpy(), np.linalg.inv(s.cam_to_world[i].double().numpy()),
                                 W, H, imgs[i]) for i in range(len(imgs))]
        sc.cameras += [ViewCamera(f"target {i}", s.target_Ks[i].numpy(), s.target_viewmats[i].double().numpy(), W, H,
                                  s.target_images[i].permute(1, 2, 0).numpy()) for i in range(len(s.target_images))]
        dep = base.depth.reshape(len(imgs), H, W).numpy()
        sc.depths = {f"input {i}": depth_colour(dep[i], preset.max_depth) for i in range(len(imgs))}
        return sc

    return model_snapshot(model, build)


def _inputs(preset, k: int) -> str:
    """The input views of held-out sample ``k`` (as :func:`.data.make_sample` picks them)."""
    cam = preset.cameras[k % len(preset.cameras)]
    if preset.views == "frames":
        return f"{cam}, {preset.num_views} frames"
    start = RING.index(cam) if cam in RING else 0
    return "+".join(RING[(start + j) % len(RING)] for j in range(preset.num_views))


def checkpoint_scene(model, preset, run: Path, data: str | None, sample: int = 0,
                     safe_pickle: bool = True) -> ViewScene:
    """The scene of a PGT checkpoint's ``model`` (restored by the command skeleton) run on
    held-out sample ``sample`` of ``data`` (input and target cameras, predicted depth), with a
    variant per sample (``data``: default the run's, else synthetic; ``safe_pickle=False`` trusts
    the data's pickles)."""
    data = data or run_data(run) or "synthetic"

    model.eval()
    source = parse_data(data, safe_pickle=safe_pickle)
    sc = model_scene(model, preset, source, data, sample)
    # a held-out sample's input cameras follow from its index (make_sample's deterministic pick):
    # offering one sample per camera of the preset lets the viewer pick the input cameras
    options = {f"sample {k}: {_inputs(preset, k)}": k
               for k in range(max(VARIANT_SAMPLES, len(preset.cameras), sample + 1))}
    sc.variants = list(options)
    sc.variant = lambda name: model_scene(model, preset, source, data, options[name])
    return sc
