"""Camera files for ``clsplat render --cameras FILE`` -> a list of :class:`~.scene.ViewCamera`.

Three layouts are accepted, told apart by their keys:

1. **clsplat** (the documented format): a JSON list of cameras, or ``{"cameras": [...]}``; each::

       {"name": "front_000",              # optional; default "view_NNNN"
        "width": 640, "height": 480,
        "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],     # or "fx", "fy", "cx", "cy"
        "world_to_camera": [[...], [...], [...], [0, 0, 0, 1]]}  # or "camera_to_world"

   Matrices are row-major, OpenCV camera axes (x right, y down, z forward), metres.
2. **INRIA** 3DGS ``cameras.json`` (written by its ``train.py``): a list of ``{"id", "img_name",
   "width", "height", "position": [3], "rotation": [3][3] (camera-to-world), "fx", "fy"}``; the
   principal point is the image centre, as INRIA's cameras assume.
3. **nerfstudio / instant-ngp** ``transforms.json``: ``{"fl_x", "fl_y", "cx", "cy", "w", "h",
   "frames": [{"file_path", "transform_matrix"}]}`` with per-frame overrides of the intrinsics;
   ``transform_matrix`` is camera-to-world with OpenGL axes (converted here). Distortion
   coefficients are refused (clsplat renders pinhole cameras), and nerfstudio's dataparser
   transform is *not* applied: the matrices must be in the ``.ply``'s world frame.

Every error is a ValueError naming the file and the camera.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .scene import ViewCamera

__all__ = ["read_cameras", "cameras_to_json"]

#: more cameras than this in one file is refused (a guard against a wrong file)
MAX_CAMERAS = 100_000
_MAX_FILE_BYTES = 256 << 20
_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def _mat(v, shape: tuple[int, int], what: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected a {shape[0]}x{shape[1]} matrix of numbers") from None
    if a.shape == (3, 4) and shape == (4, 4):
        a = np.vstack([a, [0, 0, 0, 1]])
    if a.shape != shape:
        raise ValueError(f"{what}: expected a {shape[0]}x{shape[1]} matrix, got shape {list(a.shape)}")
    return a


def _num(d: dict, key: str, what: str) -> float:
    if key not in d:
        raise ValueError(f"{what}: missing {key!r}")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{what}: {key!r} must be a number, got {v!r}")
    return float(v)


def _int(d: dict, key: str, what: str) -> int:
    v = _num(d, key, what)
    if v != int(v):
        raise ValueError(f"{what}: {key!r} must be an integer, got {v!r}")
    return int(v)


def _clsplat_camera(d: dict, i: int, what: str) -> ViewCamera:
    name = str(d.get("name", f"view_{i:04d}"))
    w, h = _int(d, "width", what), _int(d, "height", what)
    if "K" in d:
        K = _mat(d["K"], (3, 3), f"{what}: 'K'")
    else:
        K = np.array([[_num(d, "fx", what), 0, _num(d, "cx", what)], [0, _num(d, "fy", what), _num(d, "cy", what)],
                      [0, 0, 1]])
    if "world_to_camera" in d:
        V = _mat(d["world_to_camera"], (4, 4), f"{what}: 'world_to_camera'")
    elif "camera_to_world" in d:
        V = np.linalg.inv(_mat(d["camera_to_world"], (4, 4), f"{what}: 'camera_to_world'"))
    else:
        raise ValueError(f"{what}: needs 'world_to_camera' or 'camera_to_world'")
    return ViewCamera(name, K, V, w, h)


def _inria_camera(d: dict, i: int, what: str) -> ViewCamera:
    w, h = _int(d, "width", what), _int(d, "height", what)
    R = _mat(d["rotation"], (3, 3), f"{what}: 'rotation'")
    t = np.asarray(d["position"], dtype=np.float64)
    if t.shape != (3,):
        raise ValueError(f"{what}: 'position' must have 3 numbers")
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R, t
    K = np.array([[_num(d, "fx", what), 0, w / 2], [0, _num(d, "fy", what), h / 2], [0, 0, 1]])
    return ViewCamera(str(d.get("img_name", d.get("id", f"view_{i:04d}"))), K, np.linalg.inv(c2w), w, h)


def _nerfstudio_cameras(doc: dict, what: str) -> list[ViewCamera]:
    frames = doc["frames"]
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{what}: 'frames' must be a non-empty list")
    out = []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise ValueError(f"{what}: frame {i} is not an object")
        d = {**doc, **fr}
        wi = f"{what}: frame {i}"
        bad = [k for k in _DISTORTION if float(d.get(k, 0) or 0) != 0]
        if bad or d.get("camera_model", "OPENCV") not in ("OPENCV", "PINHOLE"):
            raise ValueError(f"{wi}: distorted or non-pinhole camera ({bad or d.get('camera_model')}); "
                             "clsplat renders pinhole cameras only")
        fx = _num(d, "fl_x", wi)
        fy = float(d.get("fl_y", fx))
        w, h = _int(d, "w", wi), _int(d, "h", wi)
        cx, cy = float(d.get("cx", w / 2)), float(d.get("cy", h / 2))
        c2w = _mat(d.get("transform_matrix"), (4, 4), f"{wi}: 'transform_matrix'").copy()
        c2w[:3, 1:3] *= -1  # OpenGL (y up, z back) -> OpenCV (y down, z forward)
        name = Path(str(fr.get("file_path", f"view_{i:04d}"))).stem or f"view_{i:04d}"
        out.append(ViewCamera(name, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), np.linalg.inv(c2w), w, h))
    return out


def read_cameras(path: str | Path, arg: str = "--cameras") -> list[ViewCamera]:
    """The cameras in a JSON file of any of the three layouts (see the module docstring).

    Raises:
        ValueError: naming ``arg``, the file and (where it applies) the camera, for a missing or
            unreadable file, an unknown layout, or a camera with a missing or bad field.
    """
    p = Path(path)
    what = f"{arg} {str(p)!r}"
    if not p.is_file():
        raise ValueError(f"{what}: no such file")
    if p.stat().st_size > _MAX_FILE_BYTES:
        raise ValueError(f"{what}: larger than {_MAX_FILE_BYTES >> 20} MiB; not a camera file")
    try:
        doc = json.loads(p.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{what}: not JSON ({e})") from None
    if isinstance(doc, dict) and "frames" in doc:
        try:
            cams = _nerfstudio_cameras(doc, what)
        except ValueError as e:
            raise ValueError(str(e) if str(e).startswith(what) else f"{what}: {e}") from None
    else:
        items = doc.get("cameras") if isinstance(doc, dict) else doc
        if not isinstance(items, list) or not items:
            raise ValueError(f"{what}: expected a non-empty list of cameras, {{'cameras': [...]}} or a "
                             "nerfstudio transforms.json with 'frames'")
        cams = []
        for i, d in enumerate(items):
            wi = f"{what}: camera {i}"
            if not isinstance(d, dict):
                raise ValueError(f"{wi} is not an object")
            try:
                cams.append((_inria_camera if "rotation" in d and "position" in d else _clsplat_camera)(d, i, wi))
            except ValueError as e:  # ViewCamera's own checks name the camera, not the file
                raise ValueError(str(e) if str(e).startswith(what) else f"{wi}: {e}") from None
    if len(cams) > MAX_CAMERAS:
        raise ValueError(f"{what}: {len(cams)} cameras, more than the limit {MAX_CAMERAS}")
    names = [c.name for c in cams]
    if len(set(names)) != len(names):  # output files are named after the cameras: make them unique
        for i, c in enumerate(cams):
            c.name = f"{i:04d}_{c.name}"
    return cams


def cameras_to_json(cameras: list[ViewCamera]) -> str:
    """The clsplat layout of ``cameras`` (what :func:`read_cameras` reads back)."""
    return json.dumps({"cameras": [{"name": c.name, "width": c.width, "height": c.height, "K": c.K.tolist(),
                                    "world_to_camera": c.viewmat.tolist()} for c in cameras]}, indent=1)
