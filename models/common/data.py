"""Training and evaluation data for the models: ``--data`` specs -> DrivingSequence windows.

    synthetic          a new procedural street (clsplat.data.synthetic) per sample index, in the
                       family's default world (DrivingForward: ``varied``; the others: ``classic``);
                       train, validation and test streets never share a seed
    synthetic:WORLD    the same in a named world: ``classic`` (the one street of the earlier
                       releases), ``varied`` (speed, path, road, layout, traffic and sun drawn per
                       street) or ``straight`` (varied, but the ego keeps its lane on a straight road)
    synthetic-cache:DIR  the same streets, read from an on-disk cache (clsplat.data.synthetic_cache;
                       fill it with ``clsplat data synth``); a street the cache lacks is generated
                       and added to it
    pandaset:PATH      a PandaSet sequence folder (clsplat.data.load_pandaset)
    nuscenes:PATH      a nuScenes root, optionally ``nuscenes:PATH@VERSION#SCENE``
                       (clsplat.data.load_nuscenes_scene; default v1.0-mini, scene 0)

A :class:`DataSource` hands out windows of ``num_frames`` consecutive frames at the model's
resolution, from one of three splits: ``train``, ``val`` (where every preset field is chosen) and
``test`` (reported once per recipe). Synthetic splits are disjoint seed ranges; for real data the
first 70 % of the frames are the train split, the next 10 % the validation split and the last 20 %
the test split, so that held-out windows never overlap training frames.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from clsplat.data import CAMERA_NAMES, Camera, DrivingSequence, Frame
from clsplat.data.synthetic import SyntheticConfig, generate_sequence

__all__ = ["DataSource", "parse_data", "resize_sequence", "to_torch_frame", "TEST_SEED_OFFSET", "VAL_SEED_OFFSET",
           "SPLITS", "WORLDS"]

#: synthetic test streets use seeds from here on; train streets use seeds below it.
TEST_SEED_OFFSET = 1_000_000
#: synthetic validation streets use seeds from here on (above every test seed a run reaches).
VAL_SEED_OFFSET = 2_000_000
#: share of a real sequence's frames (from the start) outside the test split: the train split
#: and, at its end, the validation split (``VAL_SHARE`` of the frames).
TRAIN_SHARE = 0.8
VAL_SHARE = 0.1
SPLITS = ("train", "val", "test")
#: the synthetic worlds (``SyntheticConfig.world``)
WORLDS = ("classic", "varied", "straight")
_SEED_OFFSET = {"train": 0, "val": VAL_SEED_OFFSET, "test": TEST_SEED_OFFSET}


def _check_cameras(cameras: Sequence[str] | None, available: Sequence[str]) -> list[str]:
    if cameras is None:
        return list(available)
    names = [cameras] if isinstance(cameras, str) else list(cameras)
    bad = [c for c in names if c not in available]
    if bad or not names:
        raise ValueError(f"cameras: unknown or empty camera list {bad or names}; available: {list(available)}")
    if len(set(names)) != len(names):
        raise ValueError(f"cameras: duplicate names in {names}")
    return names


def _check_size(num_frames: int, height: int, width: int) -> None:
    for name, v in (("num_frames", num_frames), ("height", height), ("width", width)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"{name}: expected a positive int, got {v!r}")


class DataSource:
    """Windows of driving sequences for training and evaluation (see the module docstring).

    Args:
        kind: "synthetic", "synthetic-cache" (path: the cache folder), "pandaset" or "nuscenes".
        path: dataset folder (real data only).
        seed: base seed; synthetic street ``index`` of the train split has seed ``seed + index``.
        synthetic: extra :class:`SyntheticConfig` fields for synthetic streets (e.g. num_parked).
        version, scene: nuScenes version folder and scene (index, name or token).
        world: synthetic world (one of :data:`WORLDS`); None: ``default_world``.
        default_world: the world of ``--data synthetic`` without a name (the family's choice).
        safe_pickle: PandaSet's pickled DataFrames are read with the allow-listed unpickler
            (True, the default); False trusts the files (``--trust-pickle``).
    """

    def __init__(self, kind: str, path: str | Path | None = None, seed: int = 0,
                 synthetic: dict | None = None, version: str = "v1.0-mini", scene: int | str = 0,
                 safe_pickle: bool = True, world: str | None = None, default_world: str = "classic") -> None:
        if kind not in ("synthetic", "synthetic-cache", "pandaset", "nuscenes"):
            raise ValueError(f"kind: expected 'synthetic', 'synthetic-cache', 'pandaset' or 'nuscenes', got {kind!r}")
        self._cache = None
        if kind == "synthetic-cache":
            if path is None:
                raise ValueError("data: synthetic-cache needs a folder (synthetic-cache:DIR)")
            from clsplat.data.synthetic_cache import SyntheticCache
            self._cache = SyntheticCache(path)
        elif kind != "synthetic":
            if path is None or not Path(path).is_dir():
                raise ValueError(f"data: {kind} folder {str(path)!r} does not exist")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < TEST_SEED_OFFSET:
            raise ValueError(f"seed: expected an int in [0, {TEST_SEED_OFFSET}), got {seed!r}")
        self.kind, self.path, self.seed = kind, None if path is None else Path(path), int(seed)
        self.synthetic = dict(synthetic or {})
        bad = [k for k in self.synthetic if k not in SyntheticConfig.__dataclass_fields__]
        if bad:
            raise ValueError(f"synthetic: unknown SyntheticConfig fields {bad}")
        for name, w in (("world", world), ("default_world", default_world)):
            if w is not None and w not in WORLDS:
                raise ValueError(f"{name}: expected one of {list(WORLDS)}, got {w!r}")
        if "world" in self.synthetic:
            raise ValueError("synthetic: give the world as --data synthetic:WORLD, not as a SyntheticConfig field")
        self.world = world if world is not None else default_world
        self.version, self.scene = version, scene
        self.safe_pickle = safe_pickle
        self._full: DrivingSequence | None = None  # the loaded real sequence (native resolution)

    @property
    def name(self) -> str:
        if self.synthetic_streets:
            return f"synthetic:{self.world}" if self.path is None else f"{self.kind}:{self.path} ({self.world} world)"
        return f"{self.kind}:{self.path}"

    def __repr__(self) -> str:
        return f"DataSource({self.name!r}, seed={self.seed})"

    # ------------------------------------------------------------------ real data
    @property
    def synthetic_streets(self) -> bool:
        """True for ``synthetic`` and ``synthetic-cache`` (a new street per index)."""
        return self.kind in ("synthetic", "synthetic-cache")

    def full_sequence(self) -> DrivingSequence:
        """The whole real sequence at native resolution (loaded once)."""
        if self.synthetic_streets:
            raise ValueError("data: a synthetic source has no fixed sequence; use sequence(index, ...)")
        if self._full is None:
            if self.kind == "pandaset":
                from clsplat.data import load_pandaset
                self._full = load_pandaset(self.path, load_lidar=any((self.path / "lidar").glob("*.pkl.gz")),
                                           safe_pickle=self.safe_pickle)
            else:
                from clsplat.data import load_nuscenes_scene
                self._full = load_nuscenes_scene(self.path, self.version, self.scene)
        return self._full

    def _window_starts(self, n_frames: int, num_frames: int, split: str) -> range:
        n_held = int(round(n_frames * TRAIN_SHARE))
        n_train = int(round(n_frames * (TRAIN_SHARE - VAL_SHARE)))
        lo, hi = {"train": (0, n_train), "val": (n_train, n_held), "test": (n_held, n_frames)}[split]
        if hi - lo < num_frames:
            raise ValueError(f"num_frames: the {split} split of {self.name} has {hi - lo} frames, "
                             f"fewer than the {num_frames} a window needs")
        return range(lo, hi - num_frames + 1)

    # ------------------------------------------------------------------ the one entry point
    def sequence(self, index: int, *, num_frames: int, height: int, width: int, split: str = "train",
                 cameras: Sequence[str] | None = None, lidar: bool = False, dt: float | None = None,
                 t0: float | None = None, supersample: int | None = None,
                 depth_only: bool = False) -> DrivingSequence:
        """Window ``index`` of ``split``: ``num_frames`` consecutive frames at ``height x width``.

        Args:
            index: sample index >= 0 (synthetic: which street; real: which window, cycling).
            num_frames: frames in the window.
            height, width: image size; real images are resampled and intrinsics scaled.
            split: "train", "val" or "test".
            cameras: camera names (default: all); other cameras are never rendered or loaded.
            lidar: synthetic only: simulate LiDAR (real data carries what the files hold).
            dt, t0, supersample: synthetic only: frame interval, time of the first frame and rays
                per pixel side (default: the SyntheticConfig's).
            depth_only: synthetic only: trace the depth maps alone, the images black
                (``SyntheticConfig.depth_only``: for image-blind controls); real data is read whole.
        Returns:
            a :class:`DrivingSequence` whose cameras are ``height x width``.
        """
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
            raise ValueError(f"index: expected a non-negative int, got {index!r}")
        if split not in SPLITS:
            raise ValueError(f"split: expected one of {list(SPLITS)}, got {split!r}")
        _check_size(num_frames, height, width)
        if self.synthetic_streets:
            names = _check_cameras(cameras, CAMERA_NAMES)
            seed = self.seed + int(index) + _SEED_OFFSET[split]
            world = {} if self.world == "classic" else {"world": self.world}   # classic: the earlier config, bit for bit
            fields = {**self.synthetic, **world, "seed": seed, "num_frames": num_frames, "height": height,
                      "width": width, "cameras": tuple(names), "lidar": lidar}
            if dt is not None:
                fields["dt"] = dt
            if t0 is not None:
                fields["t0"] = t0
            if supersample is not None:
                fields["supersample"] = supersample
            if depth_only:
                fields["depth_only"] = True
            cfg = SyntheticConfig(**fields)
            return self._cache.sequence(cfg) if self._cache is not None else generate_sequence(cfg)
        full = self.full_sequence()
        names = _check_cameras(cameras, full.camera_names)
        starts = self._window_starts(len(full.frames), num_frames, split)
        s = starts[int(index) % len(starts)]
        cams = [full.camera(n) for n in names]
        frames = [_select_cameras(f, names) for f in full.frames[s:s + num_frames]]
        window = DrivingSequence(cams, frames, name=f"{full.name}[{s}:{s + num_frames}]",
                                 metadata={**full.metadata, "window_start": s})
        return resize_sequence(window, height, width)


_DATA_FORMS = "'synthetic[:WORLD]', 'synthetic-cache:DIR', 'pandaset:PATH' or 'nuscenes:PATH'"


def parse_data(spec: str, seed: int = 0, **kwargs) -> DataSource:
    """A :class:`DataSource` from a ``--data`` spec (see the module docstring); ``kwargs`` go to
    :class:`DataSource` (``default_world``: the world of a plain ``synthetic``)."""
    if not isinstance(spec, str) or not spec:
        raise ValueError(f"data: expected {_DATA_FORMS}, got {spec!r}")
    if spec == "synthetic":
        return DataSource("synthetic", seed=seed, **kwargs)
    kind, sep, rest = spec.partition(":")
    if kind == "synthetic":
        if rest not in WORLDS:
            raise ValueError(f"data: unknown synthetic world {rest!r} in {spec!r}; expected one of {list(WORLDS)}")
        return DataSource("synthetic", seed=seed, world=rest, **kwargs)
    if kind == "synthetic-cache" and sep and rest:
        return DataSource("synthetic-cache", rest, seed=seed, **kwargs)
    if not sep or kind not in ("pandaset", "nuscenes") or not rest:
        raise ValueError(f"data: expected {_DATA_FORMS}, got {spec!r}")
    if kind == "nuscenes":
        path, _, scene = rest.partition("#")
        path, _, version = path.partition("@")
        scene_arg: int | str = int(scene) if scene.isdigit() else (scene or 0)
        return DataSource("nuscenes", path, seed=seed, version=version or "v1.0-mini", scene=scene_arg, **kwargs)
    return DataSource("pandaset", rest, seed=seed, **kwargs)


# ---------------------------------------------------------------------------------------
# resampling
# ---------------------------------------------------------------------------------------
def _select_cameras(f: Frame, names: list[str]) -> Frame:
    keep = lambda d: {k: v for k, v in d.items() if k in names}  # noqa: E731
    return replace(f, images=keep(f.images), depths=keep(f.depths), semantics=keep(f.semantics),
                   instances=keep(f.instances), camera_poses=keep(f.camera_poses))


def _resize(a: np.ndarray, h: int, w: int, nearest: bool) -> np.ndarray:
    t = torch.from_numpy(np.ascontiguousarray(a))
    chw = t.permute(2, 0, 1)[None] if t.dim() == 3 else t[None, None]
    if nearest:
        out = F.interpolate(chw.float(), size=(h, w), mode="nearest-exact")
    else:
        out = F.interpolate(chw.float(), size=(h, w), mode="bilinear", antialias=True, align_corners=False)
    out = out[0].permute(1, 2, 0) if t.dim() == 3 else out[0, 0]
    return out.numpy().astype(a.dtype)


def resize_sequence(seq: DrivingSequence, height: int, width: int) -> DrivingSequence:
    """Resample every image to ``height x width`` and scale the intrinsics to match.

    Images are antialiased bilinear (area-like when shrinking); depth, semantic and instance maps
    nearest (a depth edge must not blend foreground and background; ``inf`` sky stays ``inf``).
    With the pixel-centre convention, continuous coordinates scale by (W'/W, H'/H), so fx, cx scale
    by W'/W and fy, cy by H'/H.
    """
    _check_size(1, height, width)
    if all(c.height == height and c.width == width for c in seq.cameras):
        return seq
    cams = []
    for c in seq.cameras:
        S = np.diag([width / c.width, height / c.height, 1.0])
        cams.append(Camera(c.name, S @ c.K, c.cam_to_ego, width, height))
    frames = []
    for f in seq.frames:
        frames.append(replace(
            f, images={k: np.clip(_resize(v, height, width, False), 0, 1) for k, v in f.images.items()},
            depths={k: _resize(v, height, width, True) for k, v in f.depths.items()},
            semantics={k: _resize(v, height, width, True) for k, v in f.semantics.items()},
            instances={k: _resize(v, height, width, True) for k, v in f.instances.items()}))
    return DrivingSequence(cams, frames, name=seq.name, metadata=seq.metadata)


def to_torch_frame(seq: DrivingSequence, frame_index: int, cameras: Sequence[str] | None = None,
                   dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
    """One frame of ``seq`` as tensors, cameras in the given (default: rig) order.

    Returns:
        dict with images [V, 3, H, W], depths [V, H, W] (inf = sky; absent when the data has
        none), Ks [V, 3, 3], cam_to_ego [V, 4, 4], ego_to_world [4, 4], cam_to_world [V, 4, 4],
        viewmats [V, 4, 4] (world-to-camera).
    """
    names = _check_cameras(cameras, seq.camera_names)
    f = seq.frames[frame_index]
    c2w = np.stack([seq.cam_to_world(frame_index, n) for n in names])
    out = {
        "images": torch.from_numpy(seq.images(frame_index, names)).permute(0, 3, 1, 2).to(dtype),
        "Ks": torch.from_numpy(seq.Ks(names)).to(dtype),
        "cam_to_ego": torch.from_numpy(np.stack([seq.camera(n).cam_to_ego for n in names])).to(dtype),
        "ego_to_world": torch.from_numpy(f.ego_to_world).to(dtype),
        "cam_to_world": torch.from_numpy(c2w).to(dtype),
        "viewmats": torch.from_numpy(np.linalg.inv(c2w)).to(dtype),
    }
    if all(n in f.depths for n in names):
        out["depths"] = torch.from_numpy(seq.depths(frame_index, names)).to(dtype)
    return out
