"""PandaSet sequence loader and writer (devkit folder layout, no devkit dependency).

Layout of one sequence folder (as in the PandaSet devkit)::

    <seq>/camera/<name>_camera/NN.jpg            images, NN = 00, 01, ...
    <seq>/camera/<name>_camera/intrinsics.json   {"fx", "fy", "cx", "cy"}
    <seq>/camera/<name>_camera/poses.json        [{"position": {x,y,z}, "heading": {w,x,y,z}}, ...]
                                                 camera-to-world, OpenCV camera axes
    <seq>/camera/<name>_camera/timestamps.json   [seconds, ...]
    <seq>/lidar/NN.pkl.gz                        pandas DataFrame x, y, z (world), i, t, d
    <seq>/lidar/poses.json, timestamps.json      LiDAR (= our ego) pose per frame
    <seq>/annotations/cuboids/NN.pkl.gz          pandas DataFrame, one row per box
    <seq>/annotations/semseg/NN.pkl.gz           pandas DataFrame, column ``class``: one label per
                                                 LiDAR point (both devices, same row order)
    <seq>/annotations/semseg/classes.json        {"1": "Smoke", ..., "42": "Other Static Object"}

Mapping to :class:`~clsplat.data.scene.DrivingSequence`:

* The ego frame is the LiDAR frame of ``lidar/poses.json``; ``Frame.ego_to_world`` is that
  pose and ``Frame.timestamp`` its timestamp.  (For real PandaSet data the LiDAR axes are the
  sensor's, not x-forward; our writer stores the x-forward ego pose there.)
* Each camera's exact per-frame pose goes to ``Frame.camera_poses``; ``Camera.cam_to_ego`` is
  the frame-0 relative pose.
* Camera folders map to nuScenes names: front -> CAM_FRONT, front_left -> CAM_FRONT_LEFT,
  front_right -> CAM_FRONT_RIGHT, left -> CAM_BACK_LEFT, right -> CAM_BACK_RIGHT,
  back -> CAM_BACK.  Other ``*_camera`` folders keep their folder name.
* LiDAR points are loaded in the world frame; intensity ``i`` (0..255) is divided by 255;
  ``d`` is the device id (0 = spinning LiDAR); the loader keeps ``lidar_device`` only.
* Cuboids: ``position.*`` is the box centre in world, ``dimensions.x/y/z`` the extents along the
  box's local x/y/z axes and ``yaw`` the rotation about world z (devkit ``center_box_to_corners``
  geometry), so ``Box3D.size = (dimensions.x, dimensions.y, dimensions.z)``.  Track ids are the
  ``uuid`` strings numbered 1.. in order of first appearance; ``Box3D.uuid`` keeps the string.

* Semantic segmentation (when ``annotations/semseg`` exists): the per-point class ids are
  filtered with the same device mask as the points, mapped by name onto
  :data:`~clsplat.data.scene.SEMANTIC_CLASSES` (:func:`pandaset_class_to_clsplat`: road surface
  and markings -> road, Sidewalk -> sidewalk, Building -> building, every vehicle class ->
  vehicle, the rest -> other; LiDAR never returns sky) and stored aligned with ``Frame.lidar``
  in ``seq.metadata["lidar_semantics"]`` (a list of uint8 ``[M]`` per frame, None for a frame
  without labels).  The writer writes them back (road -> Road, sidewalk -> Sidewalk, building
  -> Building, vehicle -> Car, other -> Other Static Object).

Pickled DataFrames can execute code on load, so they are read safely by default: an allow-list
of the numpy/pandas constructors a DataFrame needs, refusing any file that names anything else
(:func:`clsplat.data.files.read_pickled_dataframe`). ``safe_pickle=False`` is the explicit
opt-out for sequences from a source you trust.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from .files import read_json, read_pickled_dataframe
from .scene import (
    SEMANTIC_CLASSES,
    Box3D,
    Camera,
    DrivingSequence,
    Frame,
    LidarPoints,
    invert_transform,
    make_transform,
    quat_to_rotmat,
    rotmat_to_quat,
)

__all__ = ["load_pandaset", "write_pandaset", "PANDASET_TO_NUSCENES", "pandaset_class_to_clsplat",
           "PANDASET_CLASSES"]

PANDASET_TO_NUSCENES = {
    "front_camera": "CAM_FRONT",
    "front_left_camera": "CAM_FRONT_LEFT",
    "front_right_camera": "CAM_FRONT_RIGHT",
    "left_camera": "CAM_BACK_LEFT",
    "right_camera": "CAM_BACK_RIGHT",
    "back_camera": "CAM_BACK",
}
_NUSCENES_TO_PANDASET = {v: k for k, v in PANDASET_TO_NUSCENES.items()}
#: PandaSet's 42 semantic-segmentation classes (the devkit's classes.json).
PANDASET_CLASSES: dict[int, str] = dict(enumerate([
    "Smoke", "Exhaust", "Spray or rain", "Reflection", "Vegetation", "Ground", "Road", "Lane Line Marking",
    "Stop Line Marking", "Other Road Marking", "Sidewalk", "Driveway", "Car", "Pickup Truck", "Medium-sized Truck",
    "Semi-truck", "Towed Object", "Motorcycle", "Other Vehicle - Construction Vehicle", "Other Vehicle - Uncommon",
    "Other Vehicle - Pedicab", "Emergency Vehicle", "Bus", "Personal Mobility Device", "Motorized Scooter",
    "Bicycle", "Train", "Trolley", "Tram / Subway", "Pedestrian", "Pedestrian with Object", "Animals - Bird",
    "Animals - Other", "Pylons", "Road Barriers", "Signs", "Cones", "Construction Signs",
    "Temporary Construction Barriers", "Rolling Containers", "Building", "Other Static Object"], start=1))
_ROAD_CLASSES = {"road", "lane line marking", "stop line marking", "other road marking", "driveway"}
_VEHICLE_CLASSES = {"car", "pickup truck", "medium-sized truck", "semi-truck", "towed object", "motorcycle",
                    "emergency vehicle", "bus", "train", "trolley", "tram / subway"}
_WRITE_CLASS = {"road": 7, "sidewalk": 11, "building": 41, "vehicle": 13, "other": 42, "sky": 42}


def pandaset_class_to_clsplat(name: str) -> int:
    """Index into :data:`~clsplat.data.scene.SEMANTIC_CLASSES` of a PandaSet class name."""
    n = str(name).strip().lower()
    if n in _ROAD_CLASSES:
        return SEMANTIC_CLASSES.index("road")
    if n == "sidewalk":
        return SEMANTIC_CLASSES.index("sidewalk")
    if n == "building":
        return SEMANTIC_CLASSES.index("building")
    if n in _VEHICLE_CLASSES or n.startswith("other vehicle"):
        return SEMANTIC_CLASSES.index("vehicle")
    return SEMANTIC_CLASSES.index("other")


_CUBOID_COLUMNS = ["uuid", "label", "yaw", "stationary", "camera_used", "position.x", "position.y", "position.z",
                   "dimensions.x", "dimensions.y", "dimensions.z", "attributes.object_motion",
                   "cuboids.sibling_id", "cuboids.sensor_id"]


def _pd():
    import pandas as pd

    return pd


def _read_json(path: Path):
    return read_json(path, "PandaSet file")


def _pose_from_json(entry, where: str) -> np.ndarray:
    try:
        pos = entry["position"]
        hd = entry["heading"]
        t = [float(pos["x"]), float(pos["y"]), float(pos["z"])]
        q = [float(hd["w"]), float(hd["x"]), float(hd["y"]), float(hd["z"])]
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: pose must be {{position{{x,y,z}}, heading{{w,x,y,z}}}}, problem: {exc!r}") from None
    if not all(math.isfinite(v) for v in t + q) or np.linalg.norm(q) < 1e-9:
        raise ValueError(f"{where}: pose has non-finite values or a zero quaternion")
    return make_transform(quat=q, t=t)


def _pose_to_json(T: np.ndarray) -> dict:
    q = rotmat_to_quat(T[:3, :3])
    return {"position": {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])},
            "heading": {"w": float(q[0]), "x": float(q[1]), "y": float(q[2]), "z": float(q[3])}}


def _read_pickle(path: Path, safe: bool):
    return read_pickled_dataframe(path, safe)


def _cuboid_number(path: Path, row: int, column: str, value) -> float:
    """``value`` as a finite float; ValueError naming the file, row and column otherwise."""
    try:
        if isinstance(value, (bool, np.bool_)) or isinstance(value, (str, bytes)):
            raise TypeError
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{str(path)!r} row {row}, column {column!r}: expected a number, got {value!r:.80}") from None
    if not math.isfinite(v):
        raise ValueError(f"{str(path)!r} row {row}, column {column!r}: expected a finite number, got {v}")
    return v


def _list_len(obj, where: str, n: int | None) -> list:
    if not isinstance(obj, list):
        raise ValueError(f"{where} must hold a JSON list, got {type(obj).__name__}")
    if n is not None and len(obj) < n:
        raise ValueError(f"{where} has {len(obj)} entries, need at least {n}")
    return obj


def load_pandaset(
    seq_dir: str | Path,
    cameras: Sequence[str] | None = None,
    frames: Sequence[int] | None = None,
    load_lidar: bool = True,
    load_cuboids: bool = True,
    lidar_device: int = 0,
    load_semseg: bool = True,
    safe_pickle: bool = True,
) -> DrivingSequence:
    """Load one PandaSet sequence folder.

    Args:
        seq_dir: the sequence folder (contains ``camera/``, ``lidar/``).
        cameras: camera names to load (nuScenes names such as ``"CAM_FRONT"`` or folder names
            such as ``"front_camera"``); default all camera folders, nuScenes order first.
        frames: frame indices to load (default all frames with an image in every camera).
        load_lidar: read ``lidar/NN.pkl.gz`` into ``Frame.lidar`` (world frame).
        load_cuboids: read ``annotations/cuboids/NN.pkl.gz`` into ``Frame.boxes`` when present.
        load_semseg: read ``annotations/semseg/NN.pkl.gz`` (with ``classes.json``) into
            ``metadata["lidar_semantics"]`` when present (needs ``load_lidar``).
        lidar_device: keep LiDAR points with this ``d`` value.
        safe_pickle: True (the default): unpickle the ``.pkl.gz`` files with an allow-list of the
            numpy/pandas constructors a DataFrame needs, refusing any other (a pickle can run
            arbitrary code when loaded). False: trust the files (pandas' own reader).
    Returns:
        a :class:`DrivingSequence`.
    """
    from ..io.images import read_image

    if not isinstance(seq_dir, (str, Path)) or not str(seq_dir):
        raise ValueError(f"seq_dir: expected a sequence folder path, got {seq_dir!r}")
    root = Path(seq_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"PandaSet sequence folder not found: {str(root)!r}")
    cam_root = root / "camera"
    if not cam_root.is_dir():
        raise FileNotFoundError(f"PandaSet sequence {str(root)!r} has no 'camera' folder")
    dirs = sorted(p.name for p in cam_root.iterdir() if p.is_dir() and p.name.endswith("_camera"))
    if not dirs:
        raise ValueError(f"{str(cam_root)!r} has no '<name>_camera' folders")
    known = [d for d in PANDASET_TO_NUSCENES if d in dirs]
    ordered = known + [d for d in dirs if d not in PANDASET_TO_NUSCENES]
    if cameras is not None:
        sel = []
        for c in cameras:
            d = _NUSCENES_TO_PANDASET.get(c, c)
            if d not in dirs:
                raise ValueError(f"cameras: {c!r} not found in {str(cam_root)!r}; available {dirs}")
            sel.append(d)
        ordered = sel
    lid_root = root / "lidar"
    ego_poses = [_pose_from_json(e, f"{lid_root / 'poses.json'}[{i}]")
                 for i, e in enumerate(_list_len(_read_json(lid_root / "poses.json"), str(lid_root / "poses.json"), 1))]
    ego_ts = _list_len(_read_json(lid_root / "timestamps.json"), str(lid_root / "timestamps.json"), len(ego_poses))
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in ego_ts):
        raise ValueError(f"{str(lid_root / 'timestamps.json')!r} must hold finite numbers (seconds)")
    n_avail = len(ego_poses)
    cam_data = {}
    for d in ordered:
        cdir = cam_root / d
        intr = _read_json(cdir / "intrinsics.json")
        try:
            fx, fy, cx, cy = (float(intr[k]) for k in ("fx", "fy", "cx", "cy"))
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{str(cdir / 'intrinsics.json')!r} must hold numbers fx, fy, cx, cy") from None
        if not (all(math.isfinite(v) for v in (fx, fy, cx, cy)) and fx > 0 and fy > 0):
            raise ValueError(f"{str(cdir / 'intrinsics.json')!r}: fx, fy must be finite and > 0, cx, cy finite; "
                             f"got {fx}, {fy}, {cx}, {cy}")
        poses_json = _list_len(_read_json(cdir / "poses.json"), str(cdir / "poses.json"), 1)
        poses = [_pose_from_json(e, f"{cdir / 'poses.json'}[{i}]") for i, e in enumerate(poses_json)]
        _list_len(_read_json(cdir / "timestamps.json"), str(cdir / "timestamps.json"), len(poses))
        n_img = 0
        while (cdir / f"{n_img:02d}.jpg").is_file():
            n_img += 1
        if n_img == 0:
            raise FileNotFoundError(f"no images 00.jpg, 01.jpg, ... in {str(cdir)!r}")
        n_avail = min(n_avail, len(poses), n_img)
        cam_data[d] = (np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), poses)
    if frames is not None and not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in frames):
        raise ValueError(f"frames: expected a list of ints, got {frames!r}")
    idx = list(range(n_avail)) if frames is None else [int(i) for i in frames]
    for i in idx:
        if not 0 <= i < n_avail:
            raise ValueError(f"frames: index {i} out of range, sequence {str(root)!r} has {n_avail} complete frames")
    if not idx:
        raise ValueError("frames must select at least one frame")
    sem_root = root / "annotations" / "semseg"
    sem_lut = None
    if load_semseg and load_lidar and (sem_root / "classes.json").is_file():
        classes = _read_json(sem_root / "classes.json")
        if not isinstance(classes, dict):
            raise ValueError(f"{str(sem_root / 'classes.json')!r} must map class ids to names")
        try:
            ids = {int(k): str(v) for k, v in classes.items()}
        except ValueError:
            raise ValueError(f"{str(sem_root / 'classes.json')!r}: class ids must be integers") from None
        if not ids or max(ids) > 65535:
            raise ValueError(f"{str(sem_root / 'classes.json')!r}: needs class ids in 0..65535, got "
                             f"{'none' if not ids else max(ids)}")
        sem_lut = np.full(max(ids) + 1, SEMANTIC_CLASSES.index("other"), np.uint8)
        for k, v in ids.items():
            if k < 0:
                raise ValueError(f"{str(sem_root / 'classes.json')!r}: class id {k} is negative")
            sem_lut[k] = pandaset_class_to_clsplat(v)
    lidar_semantics: list = []
    out_frames = []
    cams: list[Camera] = []
    uuids: dict[str, int] = {}
    for k, i in enumerate(idx):
        E = ego_poses[i]
        imgs, cposes = {}, {}
        for d in ordered:
            name = PANDASET_TO_NUSCENES.get(d, d)
            img = read_image(cam_root / d / f"{i:02d}.jpg", channels=3)
            imgs[name] = np.clip(img, 0.0, 1.0)
            cposes[name] = cam_data[d][1][i]
            if k == 0:
                cams.append(Camera(name, cam_data[d][0], invert_transform(E) @ cposes[name], img.shape[1], img.shape[0]))
        lidar = None
        if load_lidar:
            df = _read_pickle(lid_root / f"{i:02d}.pkl.gz", safe_pickle)
            miss = [c for c in ("x", "y", "z", "i") if c not in df.columns]
            if miss:
                raise ValueError(f"{str(lid_root / f'{i:02d}.pkl.gz')!r} lacks columns {miss}")
            keep = (df["d"] == lidar_device).to_numpy() if "d" in df.columns else np.ones(len(df), bool)
            sem_file = sem_root / f"{i:02d}.pkl.gz"
            if sem_lut is not None and sem_file.is_file():
                sdf = _read_pickle(sem_file, safe_pickle)
                if "class" not in sdf.columns or len(sdf) != len(df):
                    raise ValueError(f"{str(sem_file)!r} must hold a 'class' column with one row per LiDAR point "
                                     f"({len(df)} in {str(lid_root / f'{i:02d}.pkl.gz')!r}), got {len(sdf)} rows")
                cls = sdf["class"].to_numpy().astype(np.int64)
                if cls.size and (cls.min() < 0 or cls.max() >= len(sem_lut)):
                    raise ValueError(f"{str(sem_file)!r} holds class ids outside classes.json")
                lidar_semantics.append(sem_lut[cls[keep]])
            else:
                lidar_semantics.append(None)
            df = df[keep]
            lf = lid_root / f"{i:02d}.pkl.gz"
            try:
                pts = df[["x", "y", "z"]].to_numpy(np.float32)
                inten = df["i"].to_numpy(np.float32)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{str(lf)!r}: columns x, y, z, i must be numbers ({exc})") from None
            if not (np.isfinite(pts).all() and np.isfinite(inten).all()):
                raise ValueError(f"{str(lf)!r}: columns x, y, z, i hold NaN or Inf")
            lidar = LidarPoints(pts, np.clip(inten / 255.0, 0, 1), "world")
        boxes = []
        cub = root / "annotations" / "cuboids" / f"{i:02d}.pkl.gz"
        if load_cuboids and cub.is_file():
            df = _read_pickle(cub, safe_pickle)
            need = ["uuid", "label", "yaw", "position.x", "position.y", "position.z",
                    "dimensions.x", "dimensions.y", "dimensions.z"]
            miss = [c for c in need if c not in df.columns]
            if miss:
                raise ValueError(f"{str(cub)!r} lacks columns {miss}")
            for j, row in enumerate(df.itertuples(index=False)):
                r = dict(zip(df.columns, row))
                u = str(r["uuid"])
                yaw, *size = (_cuboid_number(cub, j, c, r[c]) for c in ("yaw", "dimensions.x", "dimensions.y",
                                                                        "dimensions.z"))
                pos = [_cuboid_number(cub, j, f"position.{a}", r[f"position.{a}"]) for a in "xyz"]
                if min(size) < 0:
                    raise ValueError(f"{str(cub)!r} row {j}: dimensions.* must be >= 0, got {size}")
                tid = uuids.setdefault(u, len(uuids) + 1)
                q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
                boxes.append(Box3D(tid, str(r["label"]), size, pos, q, uuid=u))
        out_frames.append(Frame(float(ego_ts[i]), E, imgs, lidar=lidar, boxes=boxes, camera_poses=cposes))
    meta = {"source": "pandaset", "path": str(root)}
    if any(x is not None for x in lidar_semantics):
        meta["lidar_semantics"] = lidar_semantics
    return DrivingSequence(cams, out_frames, name=root.name, metadata=meta)


def write_pandaset(seq: DrivingSequence, out_dir: str | Path, jpeg_quality: int = 95) -> Path:
    """Write ``seq`` as a PandaSet sequence folder (see module docstring); returns ``out_dir``.

    Cameras with nuScenes names are written to the matching PandaSet folders, other cameras to
    ``<lowercase name>_camera``.  LiDAR is written in world frame with ``i = 255 * intensity``,
    ``t = frame timestamp``, ``d = 0``.  Boxes must be yaw-only rotations (about z).
    """
    from ..io.atomic import write_text_atomic
    from ..io.images import write_image

    pd = _pd()
    if not isinstance(seq, DrivingSequence):
        raise ValueError(f"seq must be a DrivingSequence, got {type(seq).__name__}")
    root = Path(out_dir)
    if root.exists() and not root.is_dir():
        raise ValueError(f"out_dir {str(root)!r} exists and is not a folder")
    if len(seq.frames) > 100:
        raise ValueError(f"PandaSet file names NN hold at most 100 frames, sequence has {len(seq.frames)}")
    (root / "lidar").mkdir(parents=True, exist_ok=True)
    (root / "annotations" / "cuboids").mkdir(parents=True, exist_ok=True)
    for cam in seq.cameras:
        d = _NUSCENES_TO_PANDASET.get(cam.name, cam.name.lower() + "_camera")
        cdir = root / "camera" / d
        cdir.mkdir(parents=True, exist_ok=True)
        K = cam.K
        write_text_atomic(cdir / "intrinsics.json", json.dumps(
            {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}))
        write_text_atomic(cdir / "poses.json", json.dumps([_pose_to_json(seq.cam_to_world(i, cam.name))
                                                           for i in range(len(seq.frames))]))
        write_text_atomic(cdir / "timestamps.json", json.dumps([f.timestamp for f in seq.frames]))
        for i, f in enumerate(seq.frames):
            write_image(cdir / f"{i:02d}.jpg", f.images[cam.name], quality=jpeg_quality)
    write_text_atomic(root / "lidar" / "poses.json", json.dumps([_pose_to_json(f.ego_to_world) for f in seq.frames]))
    write_text_atomic(root / "lidar" / "timestamps.json", json.dumps([f.timestamp for f in seq.frames]))
    sem = seq.metadata.get("lidar_semantics")
    if sem is not None:
        (root / "annotations" / "semseg").mkdir(parents=True, exist_ok=True)
        write_text_atomic(root / "annotations" / "semseg" / "classes.json",
                          json.dumps({str(k): v for k, v in PANDASET_CLASSES.items()}))
    for i, f in enumerate(seq.frames):
        if f.lidar is not None and sem is not None and sem[i] is not None:
            lab = np.asarray(sem[i])
            if lab.shape != (f.lidar.points.shape[0],):
                raise ValueError(f"seq.metadata['lidar_semantics'][{i}] must hold one label per LiDAR point")
            ids = np.array([_WRITE_CLASS[SEMANTIC_CLASSES[c]] for c in range(len(SEMANTIC_CLASSES))])[lab]
            pd.DataFrame({"class": ids.astype(np.int64)}).to_pickle(
                root / "annotations" / "semseg" / f"{i:02d}.pkl.gz", compression="gzip")
        if f.lidar is not None:
            lw = f.lidar.to_world(f.ego_to_world)
            m = lw.points.shape[0]
            df = pd.DataFrame({"x": lw.points[:, 0].astype(np.float64), "y": lw.points[:, 1].astype(np.float64),
                               "z": lw.points[:, 2].astype(np.float64),
                               "i": (lw.intensity * 255.0).astype(np.float64),
                               "t": np.full(m, f.timestamp), "d": np.zeros(m, dtype=np.int64)})
            df.to_pickle(root / "lidar" / f"{i:02d}.pkl.gz", compression="gzip")
        rows = []
        for b in f.boxes:
            R = quat_to_rotmat(b.quat)
            if not (abs(R[2, 2] - 1.0) < 1e-6):
                raise ValueError(f"frame {i} box {b.track_id}: PandaSet cuboids hold yaw only; box has roll/pitch")
            rows.append({"uuid": b.uuid or f"track-{b.track_id}", "label": b.label,
                         "yaw": float(math.atan2(R[1, 0], R[0, 0])), "stationary": False, "camera_used": -1,
                         "position.x": float(b.center[0]), "position.y": float(b.center[1]),
                         "position.z": float(b.center[2]), "dimensions.x": float(b.size[0]),
                         "dimensions.y": float(b.size[1]), "dimensions.z": float(b.size[2]),
                         "attributes.object_motion": None, "cuboids.sibling_id": "-", "cuboids.sensor_id": -1})
        pd.DataFrame(rows, columns=_CUBOID_COLUMNS).to_pickle(root / "annotations" / "cuboids" / f"{i:02d}.pkl.gz",
                                                              compression="gzip")
    return root
