"""PGT samples: source views, their poses and the target views to render, from a DataSource.

``views="frames"`` (the default; driving: neighbouring frames of one camera): a window of
2·g·(V-1) + 1 frames of one camera; the sources are frames 0, 2g, .., 2g(V-1), the targets the
frames half-way between (g, 3g, ..). ``views="cameras"``: V adjacent cameras of the rig ring
(front, front-left, back-left, back, back-right, front-right) at frame 0 as sources, the same
cameras at frame 1 as targets.

The multi-view protocol (:func:`make_rig_sample`, issue 18: the regime EcoSplat's budget is
for): N source frames of one street from several rig cameras at several instants, the held-out
targets at the instants half-way between them.

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

__all__ = ["Sample", "make_sample", "make_rig_sample", "rig_layout", "make_views_sample", "RING", "SPREAD"]

#: the rig's cameras in ring order (neighbours overlap).
RING = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT", "CAM_FRONT_RIGHT")
#: the ring visited so that any first c cameras are spread around the car (front, back, sides)
SPREAD = ("CAM_FRONT", "CAM_BACK", "CAM_FRONT_LEFT", "CAM_BACK_RIGHT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT")
#: the most source views the multi-view protocol takes (EcoSplat's largest context)
MAX_VIEWS = 24


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
    return _assemble(src, tgt, name, target_cameras)


def _assemble(src: list[dict], tgt: list[dict], name: str, target_cameras: tuple) -> Sample:
    """A float32 :class:`Sample` from source and target frames (float64, as ``to_torch_frame``
    gives them), poses relative to the first source camera."""
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


def rig_layout(views: int) -> tuple[int, int]:
    """(instants, cameras per instant) of the multi-view protocol for ``views`` source frames:
    instants = max(2, ceil(views / 6)), cameras = ceil(views / instants) (the last instant takes
    what is left): 8 -> 2 x 4, 12 -> 2 x 6, 18 -> 3 x 6, 24 -> 4 x 6."""
    if isinstance(views, bool) or not isinstance(views, int) or not 3 <= views <= MAX_VIEWS:
        raise ValueError(f"views: the multi-view protocol takes 3..{MAX_VIEWS} source views, got {views!r}")
    instants = max(2, -(-views // len(SPREAD)))
    return instants, -(-views // instants)


def make_rig_sample(source: DataSource, preset: PGTPreset, index: int, views: int, split: str = "test",
                    generator: torch.Generator | None = None) -> Sample:
    """The multi-view protocol: ``views`` source frames of street ``index``.

    With (T, c) = :func:`rig_layout`, the sources are c cameras (``SPREAD`` order from a start
    camera) at instants 0, 2g, .., 2g(T-1) (g = ``preset.frame_gap``, instant-major, the last
    instant possibly with fewer cameras); the targets are the same c cameras at the instants
    g, 3g, .., half-way between (never a source). Start camera and t0: from ``generator``
    (training); without one, start ``index mod 6`` and t0 = 0 (evaluation).
    """
    T, c = rig_layout(views)
    g = preset.frame_gap
    extra = {}
    if generator is None:
        start = index % len(SPREAD)
    else:
        start = int(torch.randint(len(SPREAD), (), generator=generator))
        if source.synthetic_streets:
            extra["t0"] = 2.0 * float(torch.rand((), generator=generator, dtype=torch.float64))
    cams = [SPREAD[(start + k) % len(SPREAD)] for k in range(c)]
    seq = source.sequence(index, num_frames=2 * g * (T - 1) + 1, height=preset.height, width=preset.width,
                          split=split, cameras=cams, **extra)
    src, n = [], 0
    for t in range(T):
        take = cams[:min(c, views - n)]
        src.append(to_torch_frame(seq, 2 * g * t, take, dtype=torch.float64))
        n += len(take)
    tgt = [to_torch_frame(seq, 2 * g * t + g, cams, dtype=torch.float64) for t in range(T - 1)]
    return _assemble(src, tgt, f"{seq.name}:{T}x{'+'.join(cams)}", tuple(cams) * (T - 1))


def make_views_sample(source: DataSource, preset: PGTPreset, index: int, views: int, split: str = "test",
                      generator: torch.Generator | None = None) -> Sample:
    """``views`` == 2: the preset's own protocol (:func:`make_sample` with ``num_views`` 2);
    3..24: the multi-view protocol (:func:`make_rig_sample`)."""
    if views == 2:
        import dataclasses
        return make_sample(source, dataclasses.replace(preset, num_views=2), index, split, generator)
    return make_rig_sample(source, preset, index, views, split, generator)
