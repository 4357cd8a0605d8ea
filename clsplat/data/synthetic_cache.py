"""An on-disk cache of synthetic streets: ray-cast once, read many times.

The ray caster of :mod:`clsplat.data.synthetic` takes seconds per frame at 176x320 (and ``s^2``
times that with ``supersample=s``); a training run that draws a new street per sample would spend
most of its step there. :class:`SyntheticCache` stores each generated
:class:`~clsplat.data.scene.DrivingSequence` as one ``.npz`` file (``allow_pickle=False``: loading a
cache never runs code) named by a key that hashes

* every field of its :class:`~clsplat.data.synthetic.SyntheticConfig` (seed, size, frames, dt,
  supersample, cameras, LiDAR, ...): a street is found only for exactly the config that made it;
* the cache format (:data:`CACHE_FORMAT`) and a fingerprint of the generator's source
  (:func:`generator_fingerprint`): a changed generator never serves a stale street.

Files are written atomically (:mod:`clsplat.io.atomic`), so an interrupted fill leaves only whole
streets, and :func:`fill` skips streets already present: re-running the same ``clsplat data synth``
command resumes it. A cached sequence equals the generated one in every array (images, depths,
semantics, instances, poses, LiDAR, boxes); its ``metadata`` holds the config, the street's
``WorldParams`` (key ``"world"``, drawn again from the config) and the cache file, not the live
``StreetScene`` (which cannot be stored as data).

    clsplat data synth --count 600 --out streets --height 64 --width 112 --num-frames 3 --no-lidar
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from ..argparser import ArgumentParser
from .scene import Box3D, Camera, DrivingSequence, Frame, LidarPoints
from .synthetic import SyntheticConfig, config_world, generate_sequence

__all__ = ["CACHE_FORMAT", "SyntheticCache", "generator_fingerprint", "config_key", "fill", "main"]

#: bump when the file layout changes
CACHE_FORMAT = 1
_SUFFIX = ".npz"


def generator_fingerprint() -> str:
    """First 16 hex digits of the SHA-256 of the generator's source, every ``.py`` file of the
    ``clsplat/data/synthetic/`` package by name (any change to it invalidates the cache)."""
    from . import synthetic

    h = hashlib.sha256()
    for path in sorted(Path(synthetic.__file__).parent.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    return h.hexdigest()[:16]


def _config_dict(cfg: SyntheticConfig) -> dict:
    from .scene import CAMERA_NAMES

    d = {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}
    if d["cameras"] is None:                                   # None renders the whole rig, in rig order
        d["cameras"] = list(CAMERA_NAMES)
    return json.loads(json.dumps(d, sort_keys=True))          # tuples -> lists, canonical


def config_key(cfg: SyntheticConfig, fingerprint: str | None = None) -> str:
    """The file stem of ``cfg``'s street: ``seed<seed>-<hash of config, format, generator>``."""
    if not isinstance(cfg, SyntheticConfig):
        raise ValueError(f"config: expected a SyntheticConfig, got {type(cfg).__name__}")
    blob = json.dumps({"config": _config_dict(cfg), "format": CACHE_FORMAT,
                       "generator": fingerprint or generator_fingerprint()}, sort_keys=True)
    return f"seed{cfg.seed}-{hashlib.sha256(blob.encode()).hexdigest()[:20]}"


# ------------------------------------------------------------------------------ (de)serialisation
def _to_arrays(seq: DrivingSequence, cfg: SyntheticConfig, fingerprint: str) -> dict[str, np.ndarray]:
    names = seq.camera_names
    frames = []
    arrays: dict[str, np.ndarray] = {
        "K": np.stack([c.K for c in seq.cameras]), "cam_to_ego": np.stack([c.cam_to_ego for c in seq.cameras])}
    for i, f in enumerate(seq.frames):
        p = f"f{i}_"
        arrays[p + "ego_to_world"] = f.ego_to_world
        arrays[p + "images"] = np.stack([f.images[n] for n in names])
        for kind in ("depths", "semantics", "instances"):
            maps = getattr(f, kind)
            if maps:
                arrays[p + kind] = np.stack([maps[n] for n in names])
        if f.lidar is not None:
            arrays[p + "lidar_points"] = f.lidar.points
            arrays[p + "lidar_intensity"] = f.lidar.intensity
            if f.lidar.ring is not None:
                arrays[p + "lidar_ring"] = f.lidar.ring
        if f.boxes:
            arrays[p + "box_size"] = np.stack([b.size for b in f.boxes])
            arrays[p + "box_center"] = np.stack([b.center for b in f.boxes])
            arrays[p + "box_quat"] = np.stack([b.quat for b in f.boxes])
        frames.append({"timestamp": f.timestamp, "depths": bool(f.depths), "semantics": bool(f.semantics),
                       "instances": bool(f.instances),
                       "lidar": None if f.lidar is None else {"frame": f.lidar.frame, "ring": f.lidar.ring is not None},
                       "boxes": [{"track_id": b.track_id, "label": b.label, "uuid": b.uuid} for b in f.boxes]})
    meta = {"format": CACHE_FORMAT, "generator": fingerprint, "config": _config_dict(cfg), "name": seq.name,
            "cameras": [{"name": c.name, "width": c.width, "height": c.height} for c in seq.cameras],
            "frames": frames}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    return arrays


def _from_arrays(z, path: Path) -> tuple[dict, DrivingSequence]:
    meta = json.loads(bytes(z["meta"]).decode())
    cams = [Camera(c["name"], z["K"][i], z["cam_to_ego"][i], c["width"], c["height"])
            for i, c in enumerate(meta["cameras"])]
    names = [c.name for c in cams]
    frames = []
    for i, fm in enumerate(meta["frames"]):
        p = f"f{i}_"
        per_cam = lambda key: {n: z[p + key][k] for k, n in enumerate(names)}  # noqa: E731
        lidar = None
        if fm["lidar"] is not None:
            lidar = LidarPoints(z[p + "lidar_points"], z[p + "lidar_intensity"], fm["lidar"]["frame"],
                                z[p + "lidar_ring"] if fm["lidar"]["ring"] else None)
        boxes = [Box3D(b["track_id"], b["label"], z[p + "box_size"][k], z[p + "box_center"][k],
                       z[p + "box_quat"][k], b["uuid"]) for k, b in enumerate(fm["boxes"])]
        frames.append(Frame(fm["timestamp"], z[p + "ego_to_world"], per_cam("images"),
                            per_cam("depths") if fm["depths"] else {},
                            per_cam("semantics") if fm["semantics"] else {},
                            per_cam("instances") if fm["instances"] else {}, lidar, boxes))
    return meta, DrivingSequence(cams, frames, name=meta["name"], metadata={"cache_file": str(path)})


class SyntheticCache:
    """Generated streets under ``root`` (created if missing), one ``.npz`` per config.

    Args:
        root: the cache folder.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise ValueError(f"cache: {str(self.root)!r} exists and is not a folder")
        self.root.mkdir(parents=True, exist_ok=True)
        self._fingerprint = generator_fingerprint()

    def __repr__(self) -> str:
        return f"SyntheticCache({str(self.root)!r})"

    def path(self, cfg: SyntheticConfig) -> Path:
        """Where ``cfg``'s street is (or would be) stored."""
        return self.root / (config_key(cfg, self._fingerprint) + _SUFFIX)

    def __contains__(self, cfg: SyntheticConfig) -> bool:
        return self.path(cfg).is_file()

    def get(self, cfg: SyntheticConfig) -> DrivingSequence | None:
        """The cached street of ``cfg``, or None when absent or unreadable (a damaged file is
        treated as a miss and rewritten by :meth:`sequence`)."""
        path = self.path(cfg)
        if not path.is_file():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                meta, seq = _from_arrays(z, path)
        except (OSError, ValueError, KeyError, json.JSONDecodeError):
            return None
        if (meta.get("format") != CACHE_FORMAT or meta.get("generator") != self._fingerprint
                or meta.get("config") != _config_dict(cfg)):
            return None
        seq.metadata["config"] = cfg
        seq.metadata["world"] = config_world(cfg)
        return seq

    def put(self, cfg: SyntheticConfig, seq: DrivingSequence) -> Path:
        """Store ``seq`` (generated from ``cfg``) atomically; returns its path."""
        from clsplat.io.atomic import atomic_write

        arrays = _to_arrays(seq, cfg, self._fingerprint)

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)

        return atomic_write(self.path(cfg), write)

    def sequence(self, cfg: SyntheticConfig) -> DrivingSequence:
        """``cfg``'s street: read from the cache, or generated, stored and returned."""
        seq = self.get(cfg)
        if seq is None:
            seq = generate_sequence(cfg)
            self.put(cfg, seq)
            seq = self.get(cfg) or seq        # the same arrays either way; cached form for consistency
        return seq


def fill(cache: SyntheticCache, base: SyntheticConfig, seeds: Iterable[int],
         progress: Callable[[int, int, bool], None] | None = None) -> tuple[int, int]:
    """Generate every street ``base`` with ``seed`` in ``seeds`` that the cache lacks.

    Args:
        cache: the target; base: every field but the seed; seeds: street seeds.
        progress: called ``(done, total, written)`` after each street.
    Returns:
        (written, already present).
    """
    seeds = list(seeds)
    written = present = 0
    for i, s in enumerate(seeds):
        cfg = dataclasses.replace(base, seed=int(s))
        if cfg in cache:
            present += 1
            new = False
        else:
            cache.put(cfg, generate_sequence(cfg))
            written += 1
            new = True
        if progress is not None:
            progress(i + 1, len(seeds), new)
    return written, present


def main(argv: list[str]) -> int:
    """``clsplat data synth``: fill a cache with ``--count`` streets from ``--seed`` on; exit code."""
    import argparse
    import sys
    import time

    from .scene import CAMERA_NAMES

    d = SyntheticConfig()
    p = ArgumentParser(prog="clsplat data synth", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--count", type=int, required=True, help="number of streets (seeds SEED .. SEED+COUNT-1)")
    p.add_argument("--out", required=True, help="cache folder (created if missing; streets already there are kept)")
    p.add_argument("--seed", type=int, default=0, help="first street seed (models' held-out streets start at 1000000)")
    p.add_argument("--height", type=int, default=d.height)
    p.add_argument("--width", type=int, default=d.width)
    p.add_argument("--num-frames", type=int, default=d.num_frames)
    p.add_argument("--dt", type=float, default=d.dt, help="seconds between frames")
    p.add_argument("--supersample", type=int, default=d.supersample, help="rays per pixel side")
    p.add_argument("--cameras", nargs="+", default=None, help=f"camera names (default: all of {list(CAMERA_NAMES)})")
    p.add_argument("--no-lidar", action="store_true", help="no LiDAR sweeps (the image models do not need them)")
    p.add_argument("--world", choices=("classic", "varied", "straight"), default=d.world,
                   help="which street world (clsplat.data.synthetic.world; default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no per-street line")
    if argv[:1] != ["synth"]:
        print("usage: clsplat data synth --count N --out DIR [options]   (clsplat data synth --help)",
              file=sys.stderr)
        return 2
    a = p.parse_args(argv[1:])
    try:
        if a.count < 1:
            raise ValueError(f"--count: expected a positive integer, got {a.count}")
        if a.seed < 0:
            raise ValueError(f"--seed: expected a non-negative integer, got {a.seed}")
        if a.cameras is not None:
            bad = [c for c in a.cameras if c not in CAMERA_NAMES]
            if bad:
                raise ValueError(f"--cameras: unknown camera names {bad}; known: {list(CAMERA_NAMES)}")
        base = SyntheticConfig(height=a.height, width=a.width, num_frames=a.num_frames, dt=a.dt,
                               supersample=a.supersample, lidar=not a.no_lidar, world=a.world,
                               cameras=tuple(a.cameras) if a.cameras else None)
        base.validate()
        cache = SyntheticCache(a.out)
    except ValueError as e:
        print(f"clsplat data synth: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()

    def report(done: int, total: int, new: bool) -> None:
        if not a.quiet:
            print(f"street {done}/{total} {'written' if new else 'already cached'} "
                  f"({time.perf_counter() - t0:.1f} s)", flush=True)

    written, present = fill(cache, base, range(a.seed, a.seed + a.count), report)
    print(f"{cache.root}: {written} streets written, {present} already cached "
          f"({time.perf_counter() - t0:.1f} s; generator {generator_fingerprint()}, format {CACHE_FORMAT})")
    return 0
