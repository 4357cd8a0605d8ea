"""PGT samples: source views, their poses and the target views to render, from a DataSource.

``views="frames"`` (the default; driving: neighbouring frames of one camera): a window of
2·g·(V-1) + 1 frames of one camera; the sources are frames 0, 2g, .., 2g(V-1), the targets the
frames half-way between (g, 3g, ..). ``views="cameras"``: V adjacent cameras of the rig ring
(front, front-left, back-left, back, back-right, front-right) at frame 0 as sources, the same
cameras at frame 1 as targets.

Poses are re-expressed relative to source view 0 (computed in float64, then cast), so the
network and the Gaussians live in that camera's frame: metres, no large world offsets.
Training draws the camera (and, on synthetic streets, the start time t0 in [0, 2] s) from the
sample's generator; evaluation cycles through the cameras deterministically.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from clsplat.models.common.data import DataSource, to_torch_frame
from clsplat.models.common.geometry import invert_rigid

from .presets import PGTPreset

__all__ = ["Sample", "make_sample", "RING"]

#: the rig's cameras in ring order (neighbours overlap).
RING = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT", "CAM_FRONT_RIGHT")


@dataclass
class Sample:
    """One training/evaluation sample (float32, frame of source view 0).

    images [V, 3, H, W], Ks [V, 3, 3], cam_to_world [V, 4, 4], depths [V, H, W] or None (inf = sky);
    target_images [T, 3, H, W], target_Ks [T, 3, 3], target_viewmats [T, 4, 4] (world-to-camera),
    target_depths [T, H, W] or None; name: where it came from; target_cameras: the camera of each
    target view.
    """

    images: Tensor
    Ks: Tensor
    cam_to_world: Tensor
    depths: Tensor | None
    target_images: Tensor
    target_Ks: Tensor
    target_viewmats: Tensor
    target_depths: Tensor | None
    name: str
    target_cameras: tuple[str, ...] = ()


def _stack(frames: list[dict], key: str) -> Tensor | None:
    if any(key not in f for f in frames):
        return None
    return torch.cat([f[key] for f in frames])


def make_sample(source: DataSource, preset: PGTPreset, index: int, split: str = "train",
                generator: torch.Generator | None = None) -> Sample:
    """Build sample ``index`` of ``split``.

    Args:
        source: where the data comes from (:func:`clsplat.models.common.data.parse_data`).
        preset: sizes (height, width, num_views, views, frame_gap, cameras).
        index: sample index (synthetic: the street).
        split: "train" or "test".
        generator: randomness for the camera (and t0 on synthetic streets); None: deterministic
            (camera ``index mod len(cameras)``, t0 = 0).
    Returns:
        :class:`Sample`.
    """
    V, g = preset.num_views, preset.frame_gap
    extra = {}
    if generator is None:
        pick = index % len(preset.cameras)
    else:
        pick = int(torch.randint(len(preset.cameras), (), generator=generator))
        if source.synthetic_streets:
            extra["t0"] = 2.0 * float(torch.rand((), generator=generator, dtype=torch.float64))
    if preset.views == "frames":
        cam = preset.cameras[pick]
        seq = source.sequence(index, num_frames=2 * g * (V - 1) + 1, height=preset.height, width=preset.width,
                              split=split, cameras=[cam], **extra)
        src = [to_torch_frame(seq, 2 * g * k, [cam], dtype=torch.float64) for k in range(V)]
        tgt = [to_torch_frame(seq, 2 * g * k + g, [cam], dtype=torch.float64) for k in range(V - 1)]
        name = f"{seq.name}:{cam}"
        target_cameras = (cam,) * (V - 1)
    else:
        start = RING.index(preset.cameras[pick]) if preset.cameras[pick] in RING else 0
        names = [RING[(start + k) % len(RING)] for k in range(V)]
        seq = source.sequence(index, num_frames=2, height=preset.height, width=preset.width, split=split,
                              cameras=names, **extra)
        src = [to_torch_frame(seq, 0, names, dtype=torch.float64)]
        tgt = [to_torch_frame(seq, 1, names, dtype=torch.float64)]
        name = f"{seq.name}:{'+'.join(names)}"
        target_cameras = tuple(names)
    c2w = torch.cat([f["cam_to_world"] for f in src])
    ref = torch.linalg.inv(c2w[0])
    tc2w = ref @ torch.cat([f["cam_to_world"] for f in tgt])
    f32 = torch.float32
    depths, tdepths = _stack(src, "depths"), _stack(tgt, "depths")
    return Sample(
        images=torch.cat([f["images"] for f in src]).to(f32).contiguous(),
        Ks=torch.cat([f["Ks"] for f in src]).to(f32),
        cam_to_world=(ref @ c2w).to(f32),
        depths=None if depths is None else depths.to(f32),
        target_images=torch.cat([f["images"] for f in tgt]).to(f32).contiguous(),
        target_Ks=torch.cat([f["Ks"] for f in tgt]).to(f32),
        target_viewmats=invert_rigid(tc2w).to(f32),
        target_depths=None if tdepths is None else tdepths.to(f32),
        name=name, target_cameras=target_cameras)
