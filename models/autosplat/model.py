"""The AutoSplat scene model: background set, one set per moving track, residual SH, pose corrections.

:class:`AutoSplatModel` holds every trainable part and assembles, for one frame, the world-frame
:class:`GaussianSet` that is rendered: the background (or its road / sky subsets), and each track
present at that frame, placed by its box pose times its learnt correction, with its mirrored copy
(symmetry) and its time-dependent SH residual (dynamic tracks only). It also returns a *layout*
that maps each rendered row back to a row of a trainable set, for densification statistics.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from clsplat.data.scene import DrivingSequence

from ..common.gaussians import GaussianSet
from .densify import GaussianParams
from .fusion import PoseCorrection, place
from .init import ROAD, SKY, moving_track_ids
from .objects import ResidualSH, mirror_means, mirror_quats, mirror_sh

__all__ = ["Switches", "TrackInfo", "AutoSplatModel", "collect_tracks"]


@dataclass(frozen=True)
class Switches:
    """Constraints that can be switched off for ablations (all on = the full model).

    ``decompose`` False is plain 3DGS from LiDAR: one static set from every LiDAR point (tracked
    objects included), trained on full images in one phase; no object sets, no phase 1.
    """

    decompose: bool = True
    flatness: bool = True
    symmetry: bool = True
    residual_sh: bool = True
    pose_correction: bool = True
    densify: bool = True

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class TrackInfo:
    """A tracked object: id, label, box size (L, W, H) and whether it moves."""

    track_id: int
    label: str
    size: tuple[float, float, float]
    dynamic: bool


def collect_tracks(seq: DrivingSequence, train_frames: list[int], dynamic_threshold: float,
                   moving_only: bool = True) -> list[TrackInfo]:
    """The tracks AutoSplat decomposes, in track-id order: those with a box in at least one
    training frame whose centre moves more than ``dynamic_threshold`` metres over the sequence
    (with ``moving_only`` False every track, static ones marked ``dynamic=False``). Static
    tracks stay in the background (:func:`.init.init_background`), as the seed has it.

    Raises ValueError when a frame holds two boxes with the same track id (boxes that are not
    tracks).
    """
    first: dict[int, object] = {}
    for i, f in enumerate(seq.frames):
        ids = [b.track_id for b in f.boxes]
        if len(set(ids)) != len(ids):
            dup = sorted({t for t in ids if ids.count(t) > 1})
            raise ValueError(f"data: frame {i} holds several boxes with track id(s) {dup}; AutoSplat needs tracked "
                             "boxes (one box per track and frame, ids stable over time)")
        if i in train_frames:
            for b in f.boxes:
                first.setdefault(b.track_id, b)
    moving = moving_track_ids(seq, dynamic_threshold)
    out = []
    for tid in sorted(first):
        b = first[tid]
        if moving_only and tid not in moving:
            continue
        out.append(TrackInfo(tid, b.label, tuple(float(s) for s in b.size), tid in moving))
    return out


class AutoSplatModel(nn.Module):
    """Every trainable part of one reconstructed sequence.

    Args:
        seq: the sequence (box poses and timestamps are read from it).
        tracks: the tracks to model (from :func:`collect_tracks`).
        train_mask: ``[F]`` bool, the training frames.
        sh_degree: SH degree of every set.
        switches: which constraints are on.
        residual_width, time_frequencies, position_frequencies: :class:`ResidualSH` shape.
    """

    def __init__(self, seq: DrivingSequence, tracks: list[TrackInfo], train_mask: np.ndarray, sh_degree: int,
                 switches: Switches, residual_width: int = 64, time_frequencies: int = 4,
                 position_frequencies: int = 2) -> None:
        super().__init__()
        F, T = len(seq.frames), len(tracks)
        self.tracks = tracks
        self.switches = switches
        self.sh_degree = sh_degree
        K = (sh_degree + 1) ** 2
        self.background = GaussianParams(0, sh_degree)
        self.objects = nn.ModuleList([GaussianParams(0, sh_degree) for _ in tracks])
        self.residuals = nn.ModuleDict({
            str(k): ResidualSH(K, residual_width, time_frequencies, position_frequencies)
            for k, t in enumerate(tracks) if t.dynamic and switches.residual_sh})
        self.pose = PoseCorrection(T, F, torch.from_numpy(np.asarray(train_mask, bool)))
        self.sky_color = nn.Parameter(torch.zeros(3))
        ts = np.array([f.timestamp for f in seq.frames], np.float64)
        span = max(ts[-1] - ts[0], 1e-9)
        self.register_buffer("times", torch.from_numpy(((ts - ts[0]) / span).astype(np.float32)))
        R = torch.eye(3).repeat(T, F, 1, 1)
        t = torch.zeros(T, F, 3)
        q = torch.zeros(T, F, 4)
        q[..., 0] = 1
        present = torch.zeros(T, F, dtype=torch.bool)
        index = {tr.track_id: k for k, tr in enumerate(tracks)}
        for fi, f in enumerate(seq.frames):
            for b in f.boxes:
                k = index.get(b.track_id)
                if k is None:
                    continue
                M = b.box_to_world
                R[k, fi] = torch.from_numpy(M[:3, :3].astype(np.float32))
                t[k, fi] = torch.from_numpy(M[:3, 3].astype(np.float32))
                q[k, fi] = torch.from_numpy(b.quat.astype(np.float32))
                present[k, fi] = True
        self.register_buffer("track_R", R)
        self.register_buffer("track_t", t)
        self.register_buffer("track_q", q)
        self.register_buffer("present", present)
        self.register_buffer("track_size", torch.tensor([tr.size for tr in tracks], dtype=torch.float32).reshape(T, 3))

    # ------------------------------------------------------------------ sizes (checkpoints)
    def sizes(self) -> dict[str, int]:
        """Gaussian count of every trainable set (``background``, ``object<k>``)."""
        return {"background": len(self.background), **{f"object{k}": len(o) for k, o in enumerate(self.objects)}}

    def resize_(self, sizes: dict[str, int]) -> None:
        """Give every set the size recorded in a checkpoint (then ``load_state_dict``)."""
        self.background.resize_(sizes["background"])
        for k, o in enumerate(self.objects):
            o.resize_(sizes[f"object{k}"])

    # ------------------------------------------------------------------ assembling a frame
    def background_set(self, classes: tuple[int, ...] | None = None) -> tuple[GaussianSet, torch.Tensor]:
        """Background Gaussians (optionally only ``classes``) and their row indices."""
        bg = self.background
        m, q, s, o, sh = bg.activated()
        if classes is None:
            idx = torch.arange(len(bg))
            return GaussianSet(m, q, s, o, sh), idx
        keep = torch.zeros(len(bg), dtype=torch.bool)
        for c in classes:
            keep |= bg.labels == c
        idx = torch.nonzero(keep).flatten()
        return GaussianSet(m[idx], q[idx], s[idx], o[idx], sh[idx]), idx

    def object_set(self, k: int, frame: int, pose_correction: bool | None = None) -> GaussianSet:
        """World-frame Gaussians of track ``k`` at ``frame`` (mirror copies appended with symmetry on)."""
        obj = self.objects[k]
        m, q, s, o, sh = obj.activated()
        if str(k) in self.residuals:
            sh = sh + self.residuals[str(k)](m / self.track_size[k], float(self.times[frame]))
        gs = GaussianSet(m, q, s, o, sh)
        if self.switches.symmetry:
            gs = GaussianSet.cat([gs, GaussianSet(mirror_means(m), mirror_quats(q), s, o, mirror_sh(sh))])
        use_pose = self.switches.pose_correction if pose_correction is None else pose_correction
        delta = self.pose(k, frame) if use_pose else None
        return place(gs, self.track_R[k, frame], self.track_t[k, frame], self.track_q[k, frame], delta)

    def residual(self, k: int, frame: int) -> torch.Tensor | None:
        """SH residuals ``[M, K, 3]`` of track ``k`` at ``frame`` (None for static / switched off)."""
        if str(k) not in self.residuals:
            return None
        return self.residuals[str(k)](self.objects[k].means / self.track_size[k], float(self.times[frame]))

    def scene_at(self, frame: int, background: bool | tuple[int, ...] = True, objects: bool = True,
                 detach_background: bool = False) -> tuple[GaussianSet, list[tuple[str, torch.Tensor]]]:
        """The world-frame set rendered at ``frame``, and its layout ``[(set key, rows), ...]``.

        ``background``: True (all), False (none) or a tuple of classes (e.g. ``(ROAD,)``).
        """
        sets, layout = [], []
        if background is not False:
            gs, idx = self.background_set(None if background is True else background)
            if detach_background:
                gs = gs.detach()
            sets.append(gs)
            layout.append(("background", idx))
        if objects:
            for k in range(len(self.tracks)):
                if not bool(self.present[k, frame]) or len(self.objects[k]) == 0:
                    continue
                gs = self.object_set(k, frame)
                rows = torch.arange(len(self.objects[k]))
                sets.append(gs)
                layout.append((f"object{k}", rows.repeat(len(gs) // len(rows))))
        if not sets:
            z = torch.zeros(0, 3)
            return GaussianSet(z, torch.zeros(0, 4), z, torch.zeros(0), torch.zeros(0, (self.sh_degree + 1) ** 2, 3)), []
        return GaussianSet.cat(sets), layout

    def flatness_frames(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows of the road and sky Gaussians and their reference normals."""
        rows = torch.nonzero((self.background.labels == ROAD) | (self.background.labels == SKY)).flatten()
        return rows, self.background.normals[rows]
