"""nuScenes loader and writer.

The loader reads the nuScenes JSON tables (``<dataroot>/<version>/*.json``) and follows the
devkit's table semantics:

* ``sample`` (key frame) -> its ``sample_data`` records (``is_key_frame``), one per sensor
  channel, found through ``calibrated_sensor -> sensor.channel``;
* each ``sample_data`` has ``ego_pose`` (ego-to-global at that record's timestamp) and
  ``calibrated_sensor`` (sensor-to-ego; camera axes are OpenCV), ``prev``/``next`` links to
  the neighbouring records of the same sensor (key frames and sweeps);
* ``sample_annotation``: global-frame boxes, ``size = [width, length, height]``, rotation wxyz,
  grouped into tracks by ``instance``; timestamps are integer microseconds.

Two back ends give the same result:

* default: a small built-in JSON reader (no extra dependency);
* ``use_devkit=True``: tables loaded by ``nuscenes.nuscenes.NuScenes`` from the optional
  ``nuscenes-devkit`` package, installed by hand in an environment of its own: the devkit
  1.2.0 wheel requires ``numpy<2`` and would downgrade this project's pinned numpy 2.4.6, so
  clsplat declares no extra for it.

Mapping to :class:`~clsplat.data.scene.DrivingSequence`: ``Camera.cam_to_ego`` is the camera's
``calibrated_sensor``; every frame also stores each camera's exact pose
(``ego_pose(sample_data) @ calibrated_sensor``) in ``Frame.camera_poses``, since nuScenes cameras
fire at slightly different times.  ``Frame.ego_to_world``/``timestamp`` come from the first
camera's record.  LiDAR (``LIDAR_TOP`` ``.pcd.bin``, 5 float32 columns x, y, z, intensity
0..255, ring) is returned in world frame.  Track ids number the ``instance`` tokens 1.. in
table order; ``Box3D.uuid`` is the instance token.

The writer produces a tiny self-consistent table set (all 13 tables the devkit constructor
loads: category, attribute, visibility, instance, sensor, calibrated_sensor, ego_pose, log,
scene, sample, sample_data, sample_annotation, map) from a :class:`DrivingSequence`.
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from .files import path_inside, read_json
from .scene import (
    CAMERA_NAMES,
    Box3D,
    Camera,
    DrivingSequence,
    Frame,
    LidarPoints,
    invert_transform,
    make_transform,
    rotmat_to_quat,
)

__all__ = ["load_nuscenes_scene", "load_nuscenes_sample", "write_nuscenes", "load_tables", "TABLE_NAMES"]

#: tables the devkit's ``NuScenes()`` constructor loads.
TABLE_NAMES = ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose", "log",
               "scene", "sample", "sample_data", "sample_annotation", "map")
_LABEL_TO_CATEGORY = {"car": "vehicle.car", "truck": "vehicle.truck", "bus": "vehicle.bus.rigid",
                      "pedestrian": "human.pedestrian.adult", "bicycle": "vehicle.bicycle",
                      "motorcycle": "vehicle.motorcycle"}
_CATEGORY_TO_LABEL = {v: k for k, v in _LABEL_TO_CATEGORY.items()}
LIDAR_CHANNEL = "LIDAR_TOP"


def _import_devkit():
    try:
        from nuscenes.nuscenes import NuScenes  # type: ignore
    except ImportError as exc:
        raise ImportError(
            "use_devkit=True needs the optional nuScenes devkit (`pip install nuscenes-devkit`; "
            "it requires numpy<2, so use an environment of its own). "
            f"Original error: {exc}. Without it, use use_devkit=False (built-in JSON reader)."
        ) from exc
    return NuScenes


class _Tables:
    """Table lists plus a token index per table."""

    def __init__(self, tables: dict[str, list[dict]], root: Path):
        self.root = root
        self.tables = tables
        self.index = {name: {r["token"]: r for r in recs} for name, recs in tables.items()}

    def get(self, table: str, token: str) -> dict:
        try:
            return self.index[table][token]
        except KeyError:
            raise ValueError(f"nuScenes table {table!r} has no record with token {token!r}") from None


def load_tables(dataroot: str | Path, version: str = "v1.0-mini", use_devkit: bool = False) -> _Tables:
    """Load the 13 nuScenes tables of ``<dataroot>/<version>``.

    Raises FileNotFoundError for a missing folder/table, ValueError for malformed JSON or records
    without ``token``; ImportError (naming ``nuscenes-devkit``) if ``use_devkit`` and the devkit
    is not installed.
    """
    if not isinstance(dataroot, (str, Path)) or not isinstance(version, str) or not version:
        raise ValueError(f"dataroot, version: expected a folder path and a version name, got {dataroot!r}, {version!r}")
    root = Path(dataroot)
    if not root.is_dir():
        raise FileNotFoundError(f"nuScenes dataroot not found: {str(root)!r}")
    troot = root / version
    if not troot.is_dir():
        raise FileNotFoundError(f"nuScenes version folder not found: {str(troot)!r} (version={version!r})")
    if use_devkit:
        NuScenes = _import_devkit()
        nusc = NuScenes(version=version, dataroot=str(root), verbose=False)
        return _Tables({name: getattr(nusc, name) for name in TABLE_NAMES}, root)
    tables = {}
    for name in TABLE_NAMES:
        p = troot / f"{name}.json"
        if not p.is_file():
            raise FileNotFoundError(f"nuScenes table missing: {str(p)!r}")
        recs = read_json(p, "nuScenes table")
        if not isinstance(recs, list) or not all(isinstance(r, dict) and isinstance(r.get("token"), str)
                                                 for r in recs):
            raise ValueError(f"nuScenes table {str(p)!r} must be a JSON list of records with a 'token'")
        tables[name] = recs
    return _Tables(tables, root)


def _pose(rec: dict, where: str) -> np.ndarray:
    try:
        q = np.asarray(rec["rotation"], dtype=np.float64)
        t = np.asarray(rec["translation"], dtype=np.float64)
        if q.shape != (4,) or t.shape != (3,) or not (np.isfinite(q).all() and np.isfinite(t).all()):
            raise ValueError(f"got rotation {rec['rotation']!r}, translation {rec['translation']!r}")
        return make_transform(quat=q, t=t)
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"{where}: needs finite 'rotation' (wxyz) [4] and 'translation' [3]: {exc}") from None


def _annotation_field(rec: dict, field: str, n: int) -> list[float]:
    """``rec[field]`` as ``n`` finite floats; ValueError naming the table, the token and the field."""
    v = rec.get(field)
    where = f"sample_annotation {rec.get('token')!r}: field {field!r}"
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise ValueError(f"{where} must be a list of {n} numbers, got {v!r:.120}")
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
        raise ValueError(f"{where} must hold numbers, got {v!r:.120}")
    if not all(math.isfinite(x) for x in v):
        raise ValueError(f"{where} must be finite, got {v!r}")
    return [float(x) for x in v]


class _Reader:
    def __init__(self, t: _Tables):
        self.t = t
        self.channel_of_cs = {}
        for cs in t.tables["calibrated_sensor"]:
            self.channel_of_cs[cs["token"]] = t.get("sensor", cs["sensor_token"])["channel"]
        self.key_data: dict[str, dict[str, str]] = {}
        for sd in t.tables["sample_data"]:
            if sd.get("is_key_frame"):
                self.key_data.setdefault(sd["sample_token"], {})[self.channel_of_cs[sd["calibrated_sensor_token"]]] = sd["token"]
        self.anns: dict[str, list[dict]] = {}
        for a in t.tables["sample_annotation"]:
            self.anns.setdefault(a["sample_token"], []).append(a)
        self.track_id = {r["token"]: i + 1 for i, r in enumerate(t.tables["instance"])}

    def channel(self, sd: dict) -> str:
        return self.channel_of_cs[sd["calibrated_sensor_token"]]

    def sensor_to_world(self, sd: dict) -> np.ndarray:
        ep = _pose(self.t.get("ego_pose", sd["ego_pose_token"]), f"ego_pose {sd['ego_pose_token']}")
        cs = _pose(self.t.get("calibrated_sensor", sd["calibrated_sensor_token"]), "calibrated_sensor")
        return ep @ cs

    def camera(self, sd: dict, img: np.ndarray) -> Camera:
        cs = self.t.get("calibrated_sensor", sd["calibrated_sensor_token"])
        try:
            K = np.asarray(cs.get("camera_intrinsic") or [], dtype=np.float64)
        except (ValueError, TypeError):
            K = np.zeros(0)
        if K.shape != (3, 3) or not np.isfinite(K).all():
            raise ValueError(f"calibrated_sensor {cs['token']} of {self.channel(sd)} has no finite 3x3 camera_intrinsic")
        return Camera(self.channel(sd), K, _pose(cs, "calibrated_sensor"), img.shape[1], img.shape[0])

    def image(self, sd: dict) -> np.ndarray:
        from ..io.images import read_image

        return np.clip(read_image(self.file(sd), channels=3), 0.0, 1.0)

    def file(self, sd: dict) -> Path:
        """The data file of a ``sample_data`` record; its ``filename`` must stay inside the root."""
        return path_inside(self.t.root, sd.get("filename"), f"sample_data {sd.get('token')} filename")

    def lidar(self, sd: dict) -> LidarPoints:
        p = self.file(sd)
        if not p.is_file():
            raise FileNotFoundError(f"nuScenes LiDAR file not found: {str(p)!r}")
        raw = np.fromfile(p, dtype=np.float32)
        if raw.size % 5:
            raise ValueError(f"{str(p)!r}: size {raw.size * 4} bytes is not a multiple of 5 float32 columns")
        raw = raw.reshape(-1, 5)
        T = self.sensor_to_world(sd)
        pts = (raw[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        return LidarPoints(pts, np.clip(raw[:, 3] / 255.0, 0, 1), "world", raw[:, 4].astype(np.int32))

    def boxes(self, sample_token: str, short_labels: bool) -> list[Box3D]:
        out = []
        for a in self.anns.get(sample_token, []):
            inst = self.t.get("instance", a["instance_token"])
            cat = self.t.get("category", inst["category_token"])["name"]
            label = _CATEGORY_TO_LABEL.get(cat, cat) if short_labels else cat
            w, l, h = _annotation_field(a, "size", 3)
            t = _annotation_field(a, "translation", 3)
            q = _annotation_field(a, "rotation", 4)
            if min(w, l, h) <= 0:
                raise ValueError(f"sample_annotation {a.get('token')!r}: field 'size' must be positive "
                                 f"[width, length, height], got {a['size']!r}")
            if math.sqrt(sum(v * v for v in q)) < 1e-12:
                raise ValueError(f"sample_annotation {a.get('token')!r}: field 'rotation' is a zero quaternion, "
                                 f"got {a['rotation']!r}")
            out.append(Box3D(self.track_id[a["instance_token"]], label, [l, w, h], t, q, uuid=a["instance_token"]))
        return out

    def frame(self, sds: dict[str, dict], cams: list[str], lidar_sd: dict | None, sample_token: str | None,
              short_labels: bool) -> tuple[Frame, dict[str, np.ndarray]]:
        imgs, poses = {}, {}
        for c in cams:
            imgs[c] = self.image(sds[c])
            poses[c] = self.sensor_to_world(sds[c])
        ref = sds[cams[0]]
        E = _pose(self.t.get("ego_pose", ref["ego_pose_token"]), "ego_pose")
        lid = self.lidar(lidar_sd) if lidar_sd is not None else None
        boxes = self.boxes(sample_token, short_labels) if sample_token else []
        return Frame(ref["timestamp"] * 1e-6, E, imgs, lidar=lid, boxes=boxes, camera_poses=poses), imgs


def _check_cams(cameras: Sequence[str]) -> list[str]:
    cams = list(cameras)
    if not cams or not all(isinstance(c, str) for c in cams):
        raise ValueError(f"cameras must be a non-empty list of channel names, got {cameras!r}")
    return cams


def _malformed_as_value_error(fn):
    """Turn the KeyError/TypeError/... of a record lacking a field, or holding the wrong type,
    into a ValueError that names the table folder."""
    @functools.wraps(fn)
    def wrapper(dataroot, version="v1.0-mini", *args, **kwargs):
        try:
            return fn(dataroot, version, *args, **kwargs)
        except (KeyError, TypeError, AttributeError, IndexError) as exc:
            raise ValueError(f"nuScenes tables in {str(Path(dataroot) / str(version))!r}: a record is malformed "
                             f"({type(exc).__name__}: {exc})") from None
    return wrapper


@_malformed_as_value_error
def load_nuscenes_scene(dataroot: str | Path, version: str = "v1.0-mini", scene: int | str = 0,
                        cameras: Sequence[str] = CAMERA_NAMES, load_lidar: bool = True, load_boxes: bool = True,
                        short_labels: bool = True, use_devkit: bool = False) -> DrivingSequence:
    """Load every key frame (sample) of one scene.

    Args:
        dataroot, version: nuScenes root and version folder name (e.g. ``"v1.0-mini"``).
        scene: index into the scene table, or a scene name or token.
        cameras: camera channels, in the order wanted.
        load_lidar: attach the sample's ``LIDAR_TOP`` sweep (world frame) when present.
        load_boxes: attach the sample's annotations.
        short_labels: map nuScenes category names to short labels (``vehicle.car`` -> ``car``).
        use_devkit: load tables through ``nuscenes-devkit`` (package ``nuscenes-devkit``).
    """
    t = load_tables(dataroot, version, use_devkit)
    r = _Reader(t)
    cams = _check_cams(cameras)
    scenes = t.tables["scene"]
    if isinstance(scene, (int, np.integer)) and not isinstance(scene, bool):
        if not 0 <= scene < len(scenes):
            raise ValueError(f"scene index {scene} out of range, {len(scenes)} scenes")
        srec = scenes[scene]
    else:
        match = [s for s in scenes if s["token"] == scene or s.get("name") == scene]
        if not match:
            raise ValueError(f"scene {scene!r} not found; scenes are {[s.get('name') for s in scenes]}")
        srec = match[0]
    frames, camera_objs = [], None
    tok = srec["first_sample_token"]
    seen: set[str] = set()
    while tok:
        if tok in seen:
            raise ValueError(f"nuScenes table 'sample': the 'next' links of scene {srec['token']} form a loop "
                             f"back to sample {tok}")
        seen.add(tok)
        smp = t.get("sample", tok)
        data = r.key_data.get(tok, {})
        missing = [c for c in cams if c not in data]
        if missing:
            raise ValueError(f"sample {tok} has no key-frame sample_data for channels {missing}")
        sds = {c: t.get("sample_data", data[c]) for c in cams}
        lsd = t.get("sample_data", data[LIDAR_CHANNEL]) if (load_lidar and LIDAR_CHANNEL in data) else None
        f, imgs = r.frame(sds, cams, lsd, tok if load_boxes else None, short_labels)
        if camera_objs is None:
            camera_objs = [r.camera(sds[c], imgs[c]) for c in cams]
        frames.append(f)
        tok = smp.get("next") or ""
    return DrivingSequence(camera_objs, frames, name=srec.get("name", ""),
                           metadata={"source": "nuscenes", "scene_token": srec["token"]})


@_malformed_as_value_error
def load_nuscenes_sample(dataroot: str | Path, version: str, sample_token: str, cameras: Sequence[str] = CAMERA_NAMES,
                         neighbors: int = 1, load_lidar: bool = True, load_boxes: bool = True,
                         short_labels: bool = True, use_devkit: bool = False) -> DrivingSequence:
    """Load one sample's cameras with ``neighbors`` previous and next frames.

    The neighbours follow each camera's ``sample_data`` ``prev``/``next`` links (sweeps or key
    frames, whichever comes next), so frame ``neighbors`` of the result is the sample itself
    (frames ``[-n..-1, 0, 1..n]``).  Boxes and LiDAR are attached to the centre frame only.
    ValueError if a camera lacks ``neighbors`` records on either side.
    """
    if not isinstance(neighbors, int) or neighbors < 0:
        raise ValueError(f"neighbors must be a non-negative int, got {neighbors!r}")
    t = load_tables(dataroot, version, use_devkit)
    r = _Reader(t)
    cams = _check_cams(cameras)
    if sample_token not in t.index["sample"]:
        raise ValueError(f"sample_token {sample_token!r} not found in {version!r}")
    data = r.key_data.get(sample_token, {})
    missing = [c for c in cams if c not in data]
    if missing:
        raise ValueError(f"sample {sample_token} has no key-frame sample_data for channels {missing}")
    chains: dict[str, list[dict]] = {}
    for c in cams:
        centre = t.get("sample_data", data[c])
        prev, nxt = [], []
        cur = centre
        for _ in range(neighbors):
            if not cur.get("prev"):
                raise ValueError(f"camera {c}: sample {sample_token} has fewer than {neighbors} previous frames")
            cur = t.get("sample_data", cur["prev"])
            prev.insert(0, cur)
        cur = centre
        for _ in range(neighbors):
            if not cur.get("next"):
                raise ValueError(f"camera {c}: sample {sample_token} has fewer than {neighbors} next frames")
            cur = t.get("sample_data", cur["next"])
            nxt.append(cur)
        chains[c] = prev + [centre] + nxt
    frames, camera_objs = [], None
    for k in range(2 * neighbors + 1):
        sds = {c: chains[c][k] for c in cams}
        is_centre = k == neighbors
        lsd = t.get("sample_data", data[LIDAR_CHANNEL]) if (is_centre and load_lidar and LIDAR_CHANNEL in data) else None
        f, imgs = r.frame(sds, cams, lsd, sample_token if (is_centre and load_boxes) else None, short_labels)
        if camera_objs is None:
            camera_objs = [r.camera(sds[c], imgs[c]) for c in cams]
        frames.append(f)
    return DrivingSequence(camera_objs, frames, name=sample_token,
                           metadata={"source": "nuscenes", "sample_token": sample_token, "centre_index": neighbors})


# --------------------------------------------------------------------------------------
# writer
# --------------------------------------------------------------------------------------
def _token(*parts) -> str:
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def write_nuscenes(seq: DrivingSequence, dataroot: str | Path, version: str = "v1.0-synth", scene_name: str | None = None,
                   keyframe_every: int = 1, jpeg_quality: int = 95) -> Path:
    """Write ``seq`` as a one-scene nuScenes table set under ``dataroot``.

    Frame ``k`` is a key frame (a ``sample``) when ``k % keyframe_every == 0``; other frames are
    sweeps (``sweeps/<CHANNEL>/``) attached to the preceding sample.  Camera records use
    ``Camera.cam_to_ego`` as ``calibrated_sensor`` and ``Frame.ego_to_world`` as ``ego_pose``
    (``Frame.camera_poses`` overrides are not representable and raise ValueError).  LiDAR is
    written in a ``LIDAR_TOP`` sensor frame at ego ``(0, 0, 1.8)`` (intensity x255, ring).
    Boxes become ``sample_annotation`` records (key frames only) grouped by ``track_id``.
    Returns the ``<dataroot>/<version>`` folder.
    """
    from ..io.atomic import write_text_atomic
    from ..io.images import write_image

    if not isinstance(seq, DrivingSequence):
        raise ValueError(f"seq must be a DrivingSequence, got {type(seq).__name__}")
    if not isinstance(keyframe_every, int) or keyframe_every < 1:
        raise ValueError(f"keyframe_every must be a positive int, got {keyframe_every!r}")
    if not seq.frames:
        raise ValueError("seq has no frames")
    for i, f in enumerate(seq.frames):
        if f.camera_poses:
            raise ValueError(f"frame {i} has per-camera pose overrides (camera_poses), which the writer cannot store")
    root = Path(dataroot)
    troot = root / version
    troot.mkdir(parents=True, exist_ok=True)
    name = scene_name or seq.name or "scene-synthetic"
    tb: dict[str, list[dict]] = {n: [] for n in TABLE_NAMES}
    log_tok = _token(name, "log")
    map_tok = _token(name, "map")
    scene_tok = _token(name, "scene")
    tb["log"].append({"token": log_tok, "logfile": name, "vehicle": "synthetic", "date_captured": "2026-01-01",
                      "location": "synthetic-city"})
    (root / "maps").mkdir(exist_ok=True)
    write_image(root / "maps" / f"{map_tok}.png", np.zeros((8, 8, 3), np.float32))
    tb["map"].append({"token": map_tok, "log_tokens": [log_tok], "category": "semantic_prior",
                      "filename": f"maps/{map_tok}.png"})
    tb["visibility"].append({"token": "4", "level": "v80-100", "description": "visibility of whole object is between 80 and 100%"})
    tb["attribute"].append({"token": _token("attr", "vehicle.moving"), "name": "vehicle.moving", "description": ""})
    channels = [c.name for c in seq.cameras]
    has_lidar = any(f.lidar is not None for f in seq.frames)
    lidar_mount = make_transform(t=[0.0, 0.0, 1.8])
    cs_tok = {}
    for c in seq.cameras:
        st = _token("sensor", c.name)
        tb["sensor"].append({"token": st, "channel": c.name, "modality": "camera"})
        cs_tok[c.name] = _token(name, "cs", c.name)
        q = rotmat_to_quat(c.cam_to_ego[:3, :3])
        tb["calibrated_sensor"].append({"token": cs_tok[c.name], "sensor_token": st,
                                        "translation": c.cam_to_ego[:3, 3].tolist(), "rotation": q.tolist(),
                                        "camera_intrinsic": c.K.tolist()})
    if has_lidar:
        st = _token("sensor", LIDAR_CHANNEL)
        tb["sensor"].append({"token": st, "channel": LIDAR_CHANNEL, "modality": "lidar"})
        cs_tok[LIDAR_CHANNEL] = _token(name, "cs", LIDAR_CHANNEL)
        tb["calibrated_sensor"].append({"token": cs_tok[LIDAR_CHANNEL], "sensor_token": st,
                                        "translation": lidar_mount[:3, 3].tolist(), "rotation": [1.0, 0.0, 0.0, 0.0],
                                        "camera_intrinsic": []})
    key_idx = [k for k in range(len(seq.frames)) if k % keyframe_every == 0]
    sample_tok = {k: _token(name, "sample", k) for k in key_idx}
    for j, k in enumerate(key_idx):
        tb["sample"].append({"token": sample_tok[k], "timestamp": int(round(seq.frames[k].timestamp * 1e6)),
                             "prev": sample_tok[key_idx[j - 1]] if j > 0 else "",
                             "next": sample_tok[key_idx[j + 1]] if j + 1 < len(key_idx) else "",
                             "scene_token": scene_tok})
    tb["scene"].append({"token": scene_tok, "log_token": log_tok, "nbr_samples": len(key_idx),
                        "first_sample_token": sample_tok[key_idx[0]], "last_sample_token": sample_tok[key_idx[-1]],
                        "name": name, "description": "synthetic sequence written by clsplat"})
    sd_chain: dict[str, list[dict]] = {ch: [] for ch in channels + ([LIDAR_CHANNEL] if has_lidar else [])}
    for k, f in enumerate(seq.frames):
        ts = int(round(f.timestamp * 1e6))
        ep_tok = _token(name, "ego_pose", k)
        q = rotmat_to_quat(f.ego_to_world[:3, :3])
        tb["ego_pose"].append({"token": ep_tok, "timestamp": ts, "rotation": q.tolist(),
                               "translation": f.ego_to_world[:3, 3].tolist()})
        key = k % keyframe_every == 0
        stok = sample_tok[k - k % keyframe_every]
        folder = "samples" if key else "sweeps"
        for c in seq.cameras:
            rel = f"{folder}/{c.name}/{name}__{c.name}__{ts}.jpg"
            (root / folder / c.name).mkdir(parents=True, exist_ok=True)
            write_image(root / rel, f.images[c.name], quality=jpeg_quality)
            sd_chain[c.name].append({"token": _token(name, "sd", c.name, k), "sample_token": stok,
                                     "ego_pose_token": ep_tok, "calibrated_sensor_token": cs_tok[c.name],
                                     "timestamp": ts, "fileformat": "jpg", "is_key_frame": key,
                                     "height": c.height, "width": c.width, "filename": rel})
        if f.lidar is not None:
            le = f.lidar.to_ego(f.ego_to_world)
            inv = invert_transform(lidar_mount)
            pts = le.points.astype(np.float64) @ inv[:3, :3].T + inv[:3, 3]
            ring = le.ring if le.ring is not None else np.zeros(pts.shape[0], np.int32)
            arr = np.concatenate([pts, le.intensity[:, None] * 255.0, ring[:, None]], 1).astype(np.float32)
            rel = f"{folder}/{LIDAR_CHANNEL}/{name}__{LIDAR_CHANNEL}__{ts}.pcd.bin"
            (root / folder / LIDAR_CHANNEL).mkdir(parents=True, exist_ok=True)
            arr.tofile(root / rel)
            sd_chain[LIDAR_CHANNEL].append({"token": _token(name, "sd", LIDAR_CHANNEL, k), "sample_token": stok,
                                            "ego_pose_token": ep_tok, "calibrated_sensor_token": cs_tok[LIDAR_CHANNEL],
                                            "timestamp": ts, "fileformat": "pcd", "is_key_frame": key,
                                            "height": 0, "width": 0, "filename": rel})
    for ch, recs in sd_chain.items():
        for j, rec in enumerate(recs):
            rec["prev"] = recs[j - 1]["token"] if j > 0 else ""
            rec["next"] = recs[j + 1]["token"] if j + 1 < len(recs) else ""
            tb["sample_data"].append(rec)
    # annotations
    cats: dict[str, str] = {}
    tracks: dict[int, list[dict]] = {}
    track_cat: dict[int, str] = {}
    for k in key_idx:
        for b in seq.frames[k].boxes:
            cat = _LABEL_TO_CATEGORY.get(b.label, b.label)
            if "." not in cat:
                raise ValueError(f"frame {k} box {b.track_id}: label {b.label!r} is neither a known short label "
                                 f"{sorted(_LABEL_TO_CATEGORY)} nor a nuScenes category name")
            if cat not in cats:
                cats[cat] = _token("category", cat)
                tb["category"].append({"token": cats[cat], "name": cat, "description": "", "index": len(cats)})
            track_cat.setdefault(b.track_id, cat)
            tracks.setdefault(b.track_id, []).append(
                {"token": _token(name, "ann", b.track_id, k), "sample_token": sample_tok[k],
                 "instance_token": _token(name, "instance", b.track_id), "visibility_token": "4",
                 "attribute_tokens": [], "translation": b.center.tolist(),
                 "size": [float(b.size[1]), float(b.size[0]), float(b.size[2])], "rotation": b.quat.tolist(),
                 "num_lidar_pts": 0, "num_radar_pts": 0})
    for tid in sorted(tracks):
        recs = tracks[tid]
        for j, rec in enumerate(recs):
            rec["prev"] = recs[j - 1]["token"] if j > 0 else ""
            rec["next"] = recs[j + 1]["token"] if j + 1 < len(recs) else ""
            tb["sample_annotation"].append(rec)
        tb["instance"].append({"token": _token(name, "instance", tid), "category_token": cats[track_cat[tid]],
                               "nbr_annotations": len(recs), "first_annotation_token": recs[0]["token"],
                               "last_annotation_token": recs[-1]["token"]})
    for n, recs in tb.items():
        write_text_atomic(troot / f"{n}.json", json.dumps(recs, indent=0))
    return troot
