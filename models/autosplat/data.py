"""The data of one AutoSplat run: the sequence (``--data``: the built-in street, the street of the
novel-view protocol, PandaSet, nuScenes) cut to ``--frames`` and scaled by ``--scale``, each
argument named when it is wrong;
and its tensors (:class:`RunData`: images, cameras, per-pixel classes from masks or labelled
LiDAR, foreground masks of the tracked boxes, the train / held-out split)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from clsplat.data.scene import SEMANTIC_CLASSES, DrivingSequence

from ..common.metrics import SSIM_WINDOW
from .background import foreground_mask
from .init import ROAD, ROAD_CLASSES, UNKNOWN, moving_track_ids, pixel_classes, project_to_pixels

__all__ = ["load_sequence", "parse_frames", "SYNTHETIC_DT", "SYNTHETIC_SPECS", "RunData", "prepare_data",
           "ROAD_SEMANTIC", "DYNAMIC_THRESHOLD_M"]

ROAD_SEMANTIC = SEMANTIC_CLASSES.index("road")
#: the presets' default ``dynamic_threshold`` (metres a track's centre moves before it is decomposed)
DYNAMIC_THRESHOLD_M = 0.5

#: frame interval of the built-in street (seconds): 16 frames cover 3 s of driving.
SYNTHETIC_DT = 0.2
#: ``--data`` values of the generated street: ``synthetic`` (``make demo``'s) and ``synthetic:views``,
#: the street of the novel-view protocol (issue 19): moving vehicles with brake lights and
#: indicators, a footbridge whose shadow they drive through, and tracked boxes with correlated
#: tracker noise (:class:`clsplat.data.synthetic.views.TrackerNoise`'s defaults; the exact boxes
#: kept for scoring); ``synthetic:views-exact`` is the same street with exact boxes (the far-side and
#: appearance sets without the tracker noise that dominates the object pixels' error);
#: ``synthetic:straight`` (issue 33) a street of the ``straight`` world, where the ego keeps its lane
#: and every moving vehicle passes on its left (so a view shifted sideways, or a vehicle's far side,
#: shows surfaces no training camera saw), and ``synthetic:varied`` one of the varied world (exact
#: boxes in both); issue 36's moving-object cases: ``synthetic:overtake`` (one car overtaking close
#: beside the ego) and ``synthetic:busy`` (20 and more movers: cars, trucks, pedestrians), exact
#: boxes, and ``synthetic:overtake-noisy`` / ``synthetic:busy-noisy``, the same streets with the
#: tracker noise of ``synthetic:views`` (the exact boxes kept for scoring); ``synthetic:divided``
#: (issue 33) a street of the ``divided`` world: a median wall taller than the cameras beside the
#: ego's lane hides the other carriageway, where the 3 m lane-change rig stands, and the traffic
#: passes on the ego's right only, in its direction (exact boxes)
SYNTHETIC_SPECS = ("synthetic", "synthetic:views", "synthetic:views-exact", "synthetic:straight", "synthetic:varied",
                   "synthetic:overtake", "synthetic:overtake-noisy", "synthetic:busy", "synthetic:busy-noisy",
                   "synthetic:divided")
_WORLD_SPECS = {"synthetic:straight": "straight", "synthetic:varied": "varied", "synthetic:overtake": "overtake",
                "synthetic:overtake-noisy": "overtake", "synthetic:busy": "busy", "synthetic:busy-noisy": "busy",
                "synthetic:divided": "divided"}
#: the specs whose boxes carry :class:`clsplat.data.synthetic.views.TrackerNoise`'s defaults
_NOISY_SPECS = ("synthetic:views", "synthetic:overtake-noisy", "synthetic:busy-noisy")
_SYNTHETIC_FRAMES = 16


def parse_frames(text: str | None) -> tuple[int, int] | None:
    """``"A:B"`` -> (A, B) with 0 <= A < B; ValueError naming ``--frames`` otherwise."""
    if text is None:
        return None
    try:
        a, b = (int(x) for x in text.split(":"))
    except ValueError:
        raise ValueError(f"--frames: expected A:B with integers A < B, got {text!r}") from None
    if a < 0 or b <= a:
        raise ValueError(f"--frames: the range {text!r} is empty or negative; expected 0 <= A < B")
    return a, b


def load_sequence(spec: str, cameras: list[str] | None, frames: tuple[int, int] | None, scale: float,
                  seed: int = 0, safe_pickle: bool = True) -> DrivingSequence:
    """The sequence named by ``--data``, cut to ``frames`` and scaled by ``scale`` (PandaSet's
    pickles allow-listed unless ``safe_pickle=False``, ``--trust-pickle``)."""
    if not (isinstance(scale, (int, float)) and 0 < scale <= 4):
        raise ValueError(f"--scale: expected a number in (0, 4], got {scale!r}")
    synthetic = spec in SYNTHETIC_SPECS
    if synthetic:
        from clsplat.data.synthetic import SyntheticConfig, generate_sequence
        a, b = frames or (0, _SYNTHETIC_FRAMES)
        views = spec in ("synthetic:views", "synthetic:views-exact")
        cfg = SyntheticConfig(height=max(8, round(176 * scale)), width=max(8, round(320 * scale)), num_frames=b,
                              seed=seed, dt=SYNTHETIC_DT, signals=views, shadow=views,
                              world=_WORLD_SPECS.get(spec, "classic"))
        seq = generate_sequence(cfg)
        if a:
            seq = DrivingSequence(seq.cameras, seq.frames[a:b], seq.name, seq.metadata)
        if spec in _NOISY_SPECS:   # after the cut: the exact boxes are keyed by the run's frame indices
            from clsplat.data.synthetic.views import TrackerNoise, add_tracker_noise
            add_tracker_noise(seq, TrackerNoise(), seed=seed)
    elif spec.startswith("pandaset:"):
        from clsplat.data.pandaset import load_pandaset
        idx = None if frames is None else list(range(*frames))
        seq = load_pandaset(spec.split(":", 1)[1], cameras=cameras, frames=idx, safe_pickle=safe_pickle)
    elif spec.startswith("nuscenes:"):
        from clsplat.data.nuscenes import load_nuscenes_scene
        seq = load_nuscenes_scene(spec.split(":", 1)[1])
        if frames is not None:
            if frames[1] > len(seq.frames):
                raise ValueError(f"--frames: {frames[0]}:{frames[1]} is past the scene's {len(seq.frames)} frames")
            seq = DrivingSequence(seq.cameras, seq.frames[frames[0]:frames[1]], seq.name, seq.metadata)
    else:
        raise ValueError(f"--data: expected one of {', '.join(SYNTHETIC_SPECS)}, pandaset:PATH or nuscenes:PATH, "
                         f"got {spec!r}")
    if frames is not None and not synthetic and not seq.frames:
        raise ValueError(f"--frames: {frames[0]}:{frames[1]} selects no frame")
    if not synthetic and scale != 1:
        from ..common.data import resize_sequence
        c0 = seq.cameras[0]
        seq = resize_sequence(seq, max(8, round(c0.height * scale)), max(8, round(c0.width * scale)))
    small = [c for c in seq.cameras if min(c.height, c.width) < SSIM_WINDOW]
    if small:
        raise ValueError(f"--scale: {scale:g} makes camera {small[0].name} {small[0].height}x{small[0].width} "
                         f"pixels, smaller than SSIM's {SSIM_WINDOW}-pixel window; use a larger --scale")
    return seq


@dataclass
class RunData:
    """Tensors of one sequence, for the selected cameras.

    images [F,C,H,W,3], viewmats [F,C,4,4], Ks [C,3,3]; classes [F,C,H,W] uint8 (``BG_CLASSES``
    or 255 = unknown); foreground [F,C,H,W] bool, the pixels of the moving tracks (those
    AutoSplat decomposes); train / test frame indices.
    """

    seq: DrivingSequence
    cameras: list[str]
    train_frames: list[int]
    test_frames: list[int]
    images: torch.Tensor
    viewmats: torch.Tensor
    Ks: torch.Tensor
    classes: torch.Tensor
    foreground: torch.Tensor
    width: int
    height: int


def _lidar_classes(seq: DrivingSequence, i: int, cam: str, road_classes: tuple[str, ...] = ROAD_CLASSES) -> np.ndarray:
    """Per-pixel classes from the frame's labelled LiDAR points (3x3-dilated), 255 elsewhere."""
    labels = seq.metadata.get("lidar_semantics")
    c = seq.camera(cam)
    out = np.full((c.height, c.width), UNKNOWN, np.uint8)
    f = seq.frames[i]
    if labels is None or labels[i] is None or f.lidar is None:
        return out
    pts = f.lidar.to_world(f.ego_to_world).points.astype(np.float64)
    lab = np.asarray(labels[i])
    vis, lin, _, _, _ = project_to_pixels(seq, i, cam, pts, 0.1)
    road = np.zeros((c.height, c.width), np.float32)
    road.reshape(-1)[lin[vis]] = np.isin(lab[vis], [SEMANTIC_CLASSES.index(n) for n in road_classes])
    road = torch.nn.functional.max_pool2d(torch.from_numpy(road)[None, None], 3, 1, 1)[0, 0].numpy() > 0
    out[road] = ROAD
    return out


def prepare_data(seq: DrivingSequence, cameras: list[str] | None, holdout: int,
                 dynamic_threshold: float = DYNAMIC_THRESHOLD_M,
                 road_classes: tuple[str, ...] = ROAD_CLASSES) -> RunData:
    """Select cameras, split frames (every ``holdout``-th frame, offset ``holdout // 2``, is held
    out) and build the per-frame tensors; the foreground masks cover the tracks that move more
    than ``dynamic_threshold`` metres (the preset's); pixels of the semantic classes ``road_classes``
    (the preset's) are the road set's. ValueError naming the argument on bad input."""
    if cameras is None:
        cameras = seq.camera_names
    if not cameras:
        raise ValueError("cameras: select at least one camera")
    for c in cameras:
        if c not in seq.camera_names:
            raise ValueError(f"cameras: {c!r} is not in the data; cameras are {seq.camera_names}")
    sizes = {(seq.camera(c).height, seq.camera(c).width) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"cameras: the selected cameras have different image sizes {sorted(sizes)}")
    if isinstance(holdout, bool) or not isinstance(holdout, int) or holdout < 2:
        raise ValueError(f"holdout: expected an int >= 2 (every k-th frame is held out), got {holdout!r}")
    F = len(seq.frames)
    if F == 0:
        raise ValueError("frames: the frame range is empty")
    test = [i for i in range(F) if i % holdout == holdout // 2]
    train = [i for i in range(F) if i not in test]
    if not train:
        raise ValueError(f"frames: {F} frame(s) leave no training frame with holdout {holdout}")
    H, W = sizes.pop()
    images = torch.from_numpy(np.stack([seq.images(i, cameras) for i in range(F)]))
    viewmats = torch.from_numpy(np.stack([seq.viewmats(i, cameras) for i in range(F)]).astype(np.float32))
    Ks = torch.from_numpy(seq.Ks(cameras).astype(np.float32))
    classes = np.full((F, len(cameras), H, W), UNKNOWN, np.uint8)
    for i in range(F):
        for j, c in enumerate(cameras):
            pc = pixel_classes(seq.frames[i], c, road_classes)
            classes[i, j] = pc if pc is not None else _lidar_classes(seq, i, c, road_classes)
    moving = moving_track_ids(seq, dynamic_threshold)
    fg = np.stack([foreground_mask(seq, i, cameras, moving) for i in range(F)])
    return RunData(seq, list(cameras), train, test, images, viewmats, Ks, torch.from_numpy(classes),
                   torch.from_numpy(fg), W, H)
