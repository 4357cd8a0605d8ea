"""Novel viewpoints and tracker noise for the generated street, each aimed at one claim of a
street reconstruction that a camera on the driven path cannot test (AutoSplat, issue 19):

* :func:`mirror_across_box` -- a camera reflected across a vehicle's plane of symmetry (the box's
  x-z plane): where the recorded camera saw the vehicle's near side, the mirrored one sees its
  far side, from the same distance and angle;
* :func:`shift_sideways` -- the rig moved sideways in the ego frame (a lane change);
* :func:`add_tracker_noise` -- temporally correlated errors on the tracked boxes (a slow drift
  per track, AR(1) over frames, plus a small per-frame jitter), as trackers make them; the exact
  boxes are kept in ``seq.metadata["exact_boxes"]`` to score corrections against.

The generator renders the exact ground truth of any such view (``StreetScene.render``).
"""
from __future__ import annotations

import math

import numpy as np

from ..scene import Box3D, DrivingSequence, quat_to_rotmat, rotmat_to_quat

__all__ = ["mirror_across_box", "shift_sideways", "add_tracker_noise", "TrackerNoise"]

#: world reflection across the box frame's y = 0 plane, and the camera-frame flip of x that keeps
#: the mirrored camera right-handed (its image is the mirror image of the reflected world's view)
_FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])
_FLIP_X = np.diag([-1.0, 1.0, 1.0, 1.0])


def mirror_across_box(cam_to_world: np.ndarray, box_to_world: np.ndarray) -> np.ndarray:
    """``[..., 4, 4]`` OpenCV cam-to-world of ``cam_to_world [..., 4, 4]`` reflected across the
    plane y = 0 of the box frame ``box_to_world [4, 4]`` (a proper rotation: the camera's x axis is
    flipped after the reflection)."""
    B = np.asarray(box_to_world, np.float64)
    S = B @ _FLIP_Y @ np.linalg.inv(B)
    return S @ np.asarray(cam_to_world, np.float64) @ _FLIP_X


def shift_sideways(cam_to_world: np.ndarray, ego_to_world: np.ndarray, shift: float) -> np.ndarray:
    """``[..., 4, 4]`` cam-to-world moved ``shift`` metres along the ego's +y (left)."""
    E = np.asarray(ego_to_world, np.float64)
    S = np.eye(4)
    S[1, 3] = shift
    return E @ S @ np.linalg.inv(E) @ np.asarray(cam_to_world, np.float64)


class TrackerNoise:
    """Correlated box errors: per track, ``drift`` is AR(1) over frames with coefficient ``rho``
    and stationary standard deviation ``drift_m`` (x, y) / ``drift_deg`` (yaw), plus i.i.d.
    ``jitter_m`` / ``jitter_deg`` per frame. Frozen defaults: drift 0.15 m and 1.5 deg, jitter
    0.03 m and 0.3 deg, rho 0.9 per frame (a tracker lagging or leading for about ten frames)."""

    def __init__(self, drift_m: float = 0.15, jitter_m: float = 0.03, drift_deg: float = 1.5,
                 jitter_deg: float = 0.3, rho: float = 0.9) -> None:
        for name, v in (("drift_m", drift_m), ("jitter_m", jitter_m), ("drift_deg", drift_deg),
                        ("jitter_deg", jitter_deg)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"TrackerNoise.{name}: expected a number >= 0, got {v!r}")
        if not (isinstance(rho, (int, float)) and 0 <= rho < 1):
            raise ValueError(f"TrackerNoise.rho: expected a number in [0, 1), got {rho!r}")
        self.drift_m, self.jitter_m, self.drift_deg, self.jitter_deg, self.rho = \
            float(drift_m), float(jitter_m), float(drift_deg), float(jitter_deg), float(rho)

    def sample(self, num_frames: int, rng: np.random.Generator) -> np.ndarray:
        """``[F, 3]`` errors (dx, dy in metres, dyaw in radians) of one track over ``num_frames``."""
        sd = np.array([self.drift_m, self.drift_m, math.radians(self.drift_deg)])
        jit = np.array([self.jitter_m, self.jitter_m, math.radians(self.jitter_deg)])
        drift = np.zeros((num_frames, 3))
        drift[0] = sd * rng.standard_normal(3)
        innov = sd * math.sqrt(1 - self.rho ** 2)
        for k in range(1, num_frames):
            drift[k] = self.rho * drift[k - 1] + innov * rng.standard_normal(3)
        return drift + jit * rng.standard_normal((num_frames, 3))

    def to_dict(self) -> dict:
        return {"drift_m": self.drift_m, "jitter_m": self.jitter_m, "drift_deg": self.drift_deg,
                "jitter_deg": self.jitter_deg, "rho": self.rho}


def add_tracker_noise(seq: DrivingSequence, noise: TrackerNoise, seed: int = 0) -> DrivingSequence:
    """Perturb every tracked box of ``seq`` in place with ``noise`` (one seeded draw per track,
    in track-id order); returns ``seq``. ``seq.metadata["exact_boxes"]`` keeps the boxes before
    (``{frame index: {track id: Box3D}}``), ``["tracker_noise"]`` the settings and seed."""
    if "exact_boxes" in seq.metadata:
        raise ValueError("seq: its boxes already carry tracker noise")
    tracks = sorted({b.track_id for f in seq.frames for b in f.boxes})
    F = len(seq.frames)
    errors = {t: noise.sample(F, np.random.default_rng([seed, 19, int(t)])) for t in tracks}
    exact: dict[int, dict[int, Box3D]] = {}
    for i, f in enumerate(seq.frames):
        exact[i] = {b.track_id: b for b in f.boxes}
        out = []
        for b in f.boxes:
            dx, dy, dyaw = errors[b.track_id][i]
            c, s = math.cos(dyaw), math.sin(dyaw)
            R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ quat_to_rotmat(b.quat)
            out.append(Box3D(b.track_id, b.label, b.size, b.center + np.array([dx, dy, 0.0]), rotmat_to_quat(R),
                             b.uuid))
        f.boxes = out
    seq.metadata["exact_boxes"] = exact
    seq.metadata["tracker_noise"] = {**noise.to_dict(), "seed": int(seed)}
    return seq
