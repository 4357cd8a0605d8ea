"""What a viewer shows: :class:`ViewScene` (Gaussians plus what a driving recording has) and
:class:`ViewCamera` (a pinhole camera, OpenCV convention: x right, y down, z forward).

Conventions: Gaussians are post-activation float32 CPU tensors as in :mod:`clsplat.io.ply`;
``viewmat`` is world-to-camera ``[4, 4]``; ``K`` is ``[3, 3]``; images are float32 ``[H, W, 3]``
in [0, 1].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

__all__ = ["ViewCamera", "ViewBox", "ViewScene", "scene_from_ply", "covariances", "look_at_viewmat",
           "default_camera"]


@dataclass
class ViewCamera:
    """One pinhole camera.

    Attributes:
        name: label shown in the viewer and used for output file names.
        K: [3, 3] intrinsics (pixels).
        viewmat: [4, 4] world-to-camera.
        width, height: image size in pixels.
        image: optional [H, W, 3] float32 recorded image (shown on the frustum).
        time: optional time stamp (seconds) for scenes with moving objects.
    """

    name: str
    K: np.ndarray
    viewmat: np.ndarray
    width: int
    height: int
    image: np.ndarray | None = None
    time: float | None = None

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64)
        self.viewmat = np.asarray(self.viewmat, dtype=np.float64)
        if self.K.shape != (3, 3) or self.viewmat.shape != (4, 4):
            raise ValueError(f"camera {self.name!r}: K must be 3x3 and viewmat 4x4, got "
                             f"{list(self.K.shape)} and {list(self.viewmat.shape)}")
        if not (np.isfinite(self.K).all() and np.isfinite(self.viewmat).all()):
            raise ValueError(f"camera {self.name!r}: K or the world-to-camera matrix has NaN or Inf")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise ValueError(f"camera {self.name!r}: focal lengths must be > 0, got fx={self.K[0, 0]} fy={self.K[1, 1]}")
        if not (isinstance(self.width, (int, np.integer)) and isinstance(self.height, (int, np.integer))
                and 1 <= self.width <= 16384 and 1 <= self.height <= 16384):
            raise ValueError(f"camera {self.name!r}: width and height must be integers in 1..16384, "
                             f"got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)
        R = self.viewmat[:3, :3]
        if abs(abs(np.linalg.det(R)) - 1) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            raise ValueError(f"camera {self.name!r}: the world-to-camera rotation is not orthonormal")

    @property
    def cam_to_world(self) -> np.ndarray:
        """[4, 4] camera-to-world."""
        return np.linalg.inv(self.viewmat)

    @property
    def fov_y(self) -> float:
        """Vertical field of view, radians."""
        return 2 * math.atan(self.height / (2 * self.K[1, 1]))


@dataclass
class ViewBox:
    """A tracked box: centre [3], size [3] (length, width, height in the box frame), rotation wxyz [4]."""

    name: str
    center: np.ndarray
    size: np.ndarray
    wxyz: np.ndarray
    time: float | None = None


@dataclass
class ViewScene:
    """Everything ``clsplat view`` shows.

    Attributes:
        means [N,3], quats [N,4] wxyz, scales [N,3], opacities [N], sh [N,K,3]: the Gaussians.
        cameras: recorded cameras (frusta with images) and the default viewpoints.
        trajectory: optional [T, 3] ego positions.
        lidar: optional [P, 3] points.
        boxes: tracked boxes.
        times: time stamps the time slider offers (seconds); empty for a static scene.
        at_time: optional ``t -> ViewScene`` giving the Gaussians (and boxes) at time t
            (AutoSplat's moving objects); None for a static scene.
        depths: optional named [H, W, 3] colour-coded depth maps shown in the side panel.
        variants, variant: other inputs of a feed-forward model (names, and ``name -> ViewScene``
            that runs the model on that input); the viewer offers them in a dropdown.
        title: shown in the viewer.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    cameras: list[ViewCamera] = field(default_factory=list)
    trajectory: np.ndarray | None = None
    lidar: np.ndarray | None = None
    boxes: list[ViewBox] = field(default_factory=list)
    times: list[float] = field(default_factory=list)
    at_time: Callable[[float], "ViewScene"] | None = None
    depths: dict[str, np.ndarray] = field(default_factory=dict)
    variants: list[str] = field(default_factory=list)
    variant: Callable[[str], "ViewScene"] | None = None
    title: str = "clsplat"

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        shapes = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
        for name, want in shapes.items():
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor) or tuple(t.shape) != want:
                raise ValueError(f"{name}: expected a tensor of shape {list(want)}, got "
                                 f"{list(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__}")
        if not isinstance(self.sh, torch.Tensor) or self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3 \
                or math.isqrt(self.sh.shape[1]) ** 2 != self.sh.shape[1]:
            raise ValueError(f"sh: expected [N, K, 3] with K a perfect square, got {list(self.sh.shape)}")
        for name in ("means", "quats", "scales", "opacities", "sh"):
            setattr(self, name, getattr(self, name).detach().to("cpu", torch.float32).contiguous())

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return math.isqrt(self.sh.shape[1]) - 1

    def rgb(self) -> np.ndarray:
        """[N, 3] view-independent colour (the DC term) in [0, 1], what the browser's splats show."""
        from ..io.ply import sh_to_rgb
        return sh_to_rgb(self.sh).clamp(0, 1).numpy()

    def bounds(self) -> tuple[np.ndarray, float]:
        """(centre [3], radius): the median of the Gaussians' centres and their median distance from
        it, robust to what surrounds a scene (a driving scene's sky dome, far background)."""
        if len(self) == 0:
            return np.zeros(3), 1.0
        m = self.means.numpy().astype(np.float64)
        c = np.median(m, axis=0)
        return c, float(max(np.median(np.linalg.norm(m - c, axis=1)), 1e-3))


def covariances(quats: torch.Tensor, scales: torch.Tensor) -> np.ndarray:
    """[N, 3, 3] world covariances R diag(s^2) R^T from wxyz ``quats`` [N, 4] (any norm) and ``scales`` [N, 3]."""
    q = quats.double()
    q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(1)
    R = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)
    M = R * scales.double()[:, None, :]
    return (M @ M.transpose(1, 2)).numpy()


def look_at_viewmat(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] world-to-camera (OpenCV) of a camera at ``eye`` looking at ``target`` with ``up`` up."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    if np.linalg.norm(z) < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z /= np.linalg.norm(z)
    x = np.cross(z, up)  # right = forward x up
    if np.linalg.norm(x) < 1e-9:  # looking along up: any perpendicular will do
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return V


def default_camera(scene: ViewScene, width: int = 640, height: int = 480, fov_y_deg: float = 60.0) -> ViewCamera:
    """The scene's first recorded camera, else one looking at the scene's centre along its longest
    horizontal extent (z up) from 1.5 times its median radius."""
    if scene.cameras:
        return scene.cameras[0]
    c, r = scene.bounds()
    f = height / (2 * math.tan(math.radians(fov_y_deg) / 2))
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    # look along the scene's longest horizontal extent (down a street), from a little above it
    m = scene.means.numpy().astype(np.float64)
    near = m[np.linalg.norm(m - c, axis=1) < 2 * r][:, :2] - c[:2]
    axis = np.linalg.svd(near, full_matrices=False)[2][0] if len(near) >= 2 else np.array([1.0, 0.0])
    eye = c + r * np.array([-1.5 * axis[0], -1.5 * axis[1], 0.3])
    return ViewCamera("default", K, look_at_viewmat(eye, c), width, height)


def scene_from_ply(path: str | Path) -> ViewScene:
    """A :class:`ViewScene` of the Gaussians in an INRIA-layout ``.ply`` (ValueError naming the file otherwise)."""
    from ..io.ply import read_ply

    g = read_ply(path)
    if g.means.shape[0] == 0:
        raise ValueError(f"{str(path)!r} holds no Gaussians")
    return ViewScene(g.means, g.quats, g.scales, g.opacities, g.sh, title=Path(path).name)
