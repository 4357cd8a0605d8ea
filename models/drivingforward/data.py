"""Samples for DrivingForward: frame triplets (t-1, t, t+1) and colour jitter on network inputs.

:func:`load_triplet` asks a ``--data`` source (``clsplat.models.common.data``) for window
``index`` of three frames at the preset's size and returns tensors; :func:`colour_jitter` applies
the paper's jitter (brightness, contrast, saturation 0.2, hue 0.05) with factors drawn from a
given generator, the same factors for every image of the sample (as monodepth2 does), so that a
sample's randomness derives from its index alone.

Real data has no depth maps: when the data carries LiDAR, :func:`lidar_depth` projects the sweep
of frame t into every camera (nearest return per pixel, NaN where none), which is what depth is
evaluated against there.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from ..common.data import DataSource, to_torch_frame

#: the synthetic world of a plain ``--data synthetic`` (the varied world: a constant ego motion
#: and one street would make a constant pose and the ground prior exact, issue 32)
DEFAULT_WORLD = "varied"

__all__ = ["DEFAULT_WORLD", "load_triplet", "colour_jitter", "gt_ego_motion", "camera0_motion", "ego_speed",
           "lidar_depth"]


def load_triplet(source: DataSource, index: int, preset, split: str = "train",
                 cameras: Sequence[str] | None = None, depth_only: bool = False) -> dict[str, Tensor]:
    """Frames t-1, t, t+1 of window ``index`` as tensors.

    Args:
        source: a :class:`DataSource` (synthetic: a new street per index).
        index: window / street index; preset: gives the image size and the frame interval.
        split: "train", "val" or "test"; cameras: camera names (default: all, rig order).
        depth_only: what an image-blind control reads: no ``images`` in the result, and a
            synthetic street traces its depth maps alone (:meth:`DataSource.sequence`).
    Returns:
        ``images [3, V, 3, H, W]``, ``Ks [V, 3, 3]``, ``cam_to_ego [V, 4, 4]``, ``depths [3, V, H, W]``
        (when the data has depth maps; inf = sky), else ``lidar_depth [V, H, W]`` at t when it has
        LiDAR (NaN: no return), ``viewmats [3, V, 4, 4]`` world-to-camera,
        ``ego_to_world [3, 4, 4]``, ``timestamps [3]`` (seconds, float64), ``names`` (list of camera
        names), and ``street_file`` (str) when the window was read from a street cache
        (``synthetic-cache:DIR``: the street's file, which names it).
    """
    kw = {"dt": preset.scenes_dt, "supersample": preset.supersample, "depth_only": depth_only} \
        if source.synthetic_streets else {}
    seq = source.sequence(index, num_frames=3, height=preset.height, width=preset.width, split=split,
                          cameras=cameras, **kw)
    frames = [to_torch_frame(seq, f) for f in range(3)]
    out = {"Ks": frames[1]["Ks"],
           "cam_to_ego": frames[1]["cam_to_ego"], "viewmats": torch.stack([f["viewmats"] for f in frames]),
           "ego_to_world": torch.stack([f["ego_to_world"] for f in frames]), "names": list(seq.camera_names),
           "timestamps": torch.tensor([float(f.timestamp) for f in seq.frames[:3]], dtype=torch.float64)}
    if seq.metadata.get("cache_file"):
        out["street_file"] = str(seq.metadata["cache_file"])
    if not depth_only:
        out["images"] = torch.stack([f["images"] for f in frames])
    if all("depths" in f for f in frames):
        out["depths"] = torch.stack([f["depths"] for f in frames])
    elif seq.frames[1].lidar is not None:
        lid = seq.frames[1].lidar
        pts = torch.tensor(lid.points, dtype=torch.float64)
        if lid.frame == "world":
            w2e = torch.linalg.inv(out["ego_to_world"][1].double())
            pts = pts @ w2e[:3, :3].T + w2e[:3, 3]
        out["lidar_depth"] = lidar_depth(pts, out["Ks"], out["cam_to_ego"], preset.height, preset.width)
    return out


def lidar_depth(points_ego: Tensor, Ks: Tensor, cam_to_ego: Tensor, height: int, width: int) -> Tensor:
    """Sparse depth maps from LiDAR points: the nearest return per pixel.

    Args:
        points_ego: ``[M, 3]`` points in the ego frame; Ks ``[V, 3, 3]``; cam_to_ego ``[V, 4, 4]``.
    Returns:
        ``[V, H, W]`` camera z-depth in metres, NaN at pixels without a return.
    """
    if not isinstance(points_ego, Tensor) or points_ego.ndim != 2 or points_ego.shape[1] != 3:
        raise ValueError(f"points_ego: expected [M, 3], got {list(getattr(points_ego, 'shape', []))}")
    V = Ks.shape[0]
    out = torch.full((V, height * width), float("inf"), dtype=torch.float64)
    e2c = torch.linalg.inv(cam_to_ego.double())
    for c in range(V):
        pc = points_ego.double() @ e2c[c, :3, :3].T + e2c[c, :3, 3]
        z = pc[:, 2]
        front = z > 1e-3
        uv = (pc[front] / z[front, None]) @ Ks[c].double().T
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()    # pixel (u, v) covers [u, u+1)
        inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
        idx = v[inside] * width + u[inside]
        out[c].scatter_reduce_(0, idx, z[front][inside], reduce="amin")
    out[~torch.isfinite(out)] = float("nan")
    return out.reshape(V, height, width).to(Ks.dtype)


def gt_ego_motion(sample: dict[str, Tensor], ref: int = 1) -> list[Tensor]:
    """True ego motion ``M_{ref->f}`` ``[4, 4]`` (ego coordinates at ``ref`` to ego at f) for every frame."""
    E = sample["ego_to_world"].double()
    return [(torch.linalg.inv(E[f]) @ E[ref]).to(sample["Ks"].dtype) for f in range(E.shape[0])]


def camera0_motion(sample: dict[str, Tensor], later: int = 2, earlier: int = 1) -> Tensor:
    """True motion ``[4, 4]`` (float64) of camera 0 from frame ``earlier`` to ``later`` of a triplet,
    in that camera's frame (``p_later = T p_earlier``): what the pose network predicts."""
    E0 = sample["cam_to_ego"][0].double()
    M = torch.linalg.inv(sample["ego_to_world"][later].double()) @ sample["ego_to_world"][earlier].double()
    return torch.linalg.inv(E0) @ M @ E0


def ego_speed(sample: dict[str, Tensor]) -> float:
    """The ego's mean speed (m/s) from frame t to t+1 of a triplet: distance over time."""
    E = sample["ego_to_world"].double()
    dt = float(sample["timestamps"][2] - sample["timestamps"][1])
    if not dt > 0:
        raise ValueError(f"timestamps: frames t and t+1 must be in time order, got {sample['timestamps'].tolist()}")
    return float((E[2, :3, 3] - E[1, :3, 3]).norm()) / dt


def colour_jitter(images: Tensor, generator: torch.Generator,
                  strength: tuple[float, float, float, float] = (0.2, 0.2, 0.2, 0.05)) -> Tensor:
    """Random brightness, contrast, saturation and hue, one draw for all images.

    Args:
        images: ``[..., 3, H, W]`` in [0, 1].
        generator: the sample's generator.
        strength: (brightness, contrast, saturation, hue); factors are drawn uniformly from
            [1 - s, 1 + s] (hue: a shift in [-s, s] turns), applied in that order.
    Returns:
        images of the same shape, clamped to [0, 1].
    """
    import kornia

    b, c, s, h = strength
    u = torch.rand(4, generator=generator, dtype=torch.float64)
    fb, fc, fs = (1 + (2 * u[i] - 1) * v for i, v in enumerate((b, c, s)))
    fh = (2 * u[3] - 1) * h
    shape = images.shape
    x = images.reshape(-1, 3, *shape[-2:])
    x = (x * float(fb)).clamp(0, 1)
    grey = kornia.color.rgb_to_grayscale(x)
    mean = grey.mean(dim=(1, 2, 3), keepdim=True)
    x = (mean + float(fc) * (x - mean)).clamp(0, 1)
    grey = kornia.color.rgb_to_grayscale(x)
    x = (grey + float(fs) * (x - grey)).clamp(0, 1)
    if fh != 0:
        x = kornia.enhance.adjust_hue(x, float(fh) * 2 * math.pi).clamp(0, 1)
    return x.reshape(shape)
