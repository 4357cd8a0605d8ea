"""Background initialisation: accumulated LiDAR -> coloured, labelled Gaussians (+ sky dome).

* LiDAR sweeps of the training frames are taken to the world frame and accumulated; points
  inside (or within ``box_margin`` of) a tracked box **of the same frame** are removed, so the
  moving and parked vehicles do not leave trails in the background.
* Each point is coloured from a camera of its own frame in which it is visible. Visibility is a
  z-buffer test against the frame's own LiDAR points splatted into that camera (min-pooled over
  ``ZBUF_WINDOW`` pixels, so the test works on sparse real sweeps without any depth maps).
* Labels road / sky / other (``BG_CLASSES``) come from the image semantics at the pixel the
  point projects to (synthetic masks, or a user mask folder loaded by :func:`load_mask_folder`),
  else from the dataset's per-point labels (``seq.metadata["lidar_semantics"]``, PandaSet
  semseg), else "other". Vehicle pixels not covered by a box count as "other" (background). The
  semantic classes that count as road are the preset's ``road_classes`` (the paper's road; the
  ``demo`` preset adds the sidewalk, the same ground plane).
* A voxel grid of side ``lidar_voxel`` keeps one point per voxel (the first in frame order),
  then at most ``max_bg_points`` are kept (seeded draw). Scales: mean distance to the 3 nearest
  neighbours (3DGS), isotropic.
* Road Gaussians get a local reference normal (PCA of their 12 nearest road neighbours): the
  road's local frame for the flatness term. Sky has no LiDAR: it is a hemisphere of Gaussians
  (``dome_points``, Fibonacci lattice, radius ``dome_radius`` about the trajectory), coloured
  from sky pixels; their reference normal is radial. (Alternative: ``sky="color"``, no dome and
  a learnt background colour; measured in bench/RESULTS.md (AutoSplat).)
* Road continuation (``preset.road_extend_m`` > 0, off by default; issue 33): the road goes on
  where no sensor reached it. Along the road (its direction: the principal axis of the road
  Gaussians about each training pose), in strips ``ROAD_EXTEND_SPACING`` x ``lidar_voxel`` long,
  road Gaussians are added on a grid of that spacing from the observed road's outermost Gaussian
  of the strip outwards, ``road_extend_m`` metres on each side (:func:`extend_road`); each takes
  the mean height, colour and normal of its ``ROAD_EXTEND_NEIGHBOURS`` nearest observed road
  Gaussians (horizontal distance), is labelled road and never seen (``source`` -1). Everything
  comes from the LiDAR road points and the poses, nothing from the scene's layout.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from clsplat.data.scene import SEMANTIC_CLASSES, DrivingSequence, Frame

__all__ = ["BG_CLASSES", "ROAD", "SKY", "OTHER", "UNKNOWN", "BackgroundInit", "pixel_classes",
           "init_background", "knn_mean_distance", "load_mask_folder", "accumulate_lidar", "moving_track_ids",
           "extend_road"]

BG_CLASSES: tuple[str, ...] = ("road", "sky", "other")
ROAD, SKY, OTHER, UNKNOWN = 0, 1, 2, 255
ZBUF_WINDOW = 5
#: the semantic classes of the road set by default (``AutoSplatPreset.road_classes``)
ROAD_CLASSES: tuple[str, ...] = ("road",)
#: road continuation (:func:`extend_road`): the added grid's spacing in ``lidar_voxel``s (demo: 1 m;
#: it carries the road's colour on, not detail), the radius (m) of road Gaussians about a training
#: pose whose principal axis is the road's direction there, and how many nearest observed road
#: Gaussians give an added one its height, colour and normal
ROAD_EXTEND_SPACING = 4.0
ROAD_AXIS_RADIUS = 20.0
ROAD_EXTEND_NEIGHBOURS = 8


def sem_to_bg(road_classes: tuple[str, ...] = ROAD_CLASSES) -> np.ndarray:
    """``[len(SEMANTIC_CLASSES)]`` uint8: clsplat semantic class index -> background class, the
    classes named in ``road_classes`` forming the road set (ValueError naming an unknown one)."""
    bad = [c for c in road_classes if c not in SEMANTIC_CLASSES or c == "sky"]
    if bad or not road_classes:
        raise ValueError(f"road_classes: expected ground classes from {[c for c in SEMANTIC_CLASSES if c != 'sky']}, "
                         f"got {tuple(road_classes)!r}")
    return np.array([ROAD if n in road_classes else SKY if n == "sky" else OTHER for n in SEMANTIC_CLASSES],
                    dtype=np.uint8)


_SEM_TO_BG = sem_to_bg()


@dataclass
class BackgroundInit:
    """Initial background Gaussians (float32 numpy).

    Attributes:
        means [N,3] world; colors [N,3] in [0,1]; scales [N,3]; labels [N] int64 (``BG_CLASSES``);
        normals [N,3] reference normals for flatness (road: local, sky: radial, other: +z);
        source [N,3] int64 (frame index, camera index, linear pixel) the colour came from, -1 for dome
        Gaussians never seen.
    """

    means: np.ndarray
    colors: np.ndarray
    scales: np.ndarray
    labels: np.ndarray
    normals: np.ndarray
    source: np.ndarray

    def __len__(self) -> int:
        return int(self.means.shape[0])


def project_to_pixels(seq: DrivingSequence, i: int, cam: str, points: np.ndarray, min_z: float):
    """Where world ``points [N, 3]`` land in camera ``cam`` at frame ``i``.

    Returns:
        ``vis [N]`` (in front, z > ``min_z``, and inside the image), ``lin [N]`` int64 row-major
        pixel index (0 where not visible), ``z [N]`` camera depth, ``u, v [N]`` pixel columns and
        rows (floored; NaN or inf behind the camera).
    """
    c = seq.camera(cam)
    w2c = np.linalg.inv(seq.cam_to_world(i, cam))
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    uvw = pc @ c.K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(uvw[:, 0] / uvw[:, 2])
        v = np.floor(uvw[:, 1] / uvw[:, 2])
    vis = (pc[:, 2] > min_z) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
    lin = np.where(vis, v * c.width + u, 0).astype(np.int64)
    return vis, lin, pc[:, 2], u, v


def pixel_classes(frame: Frame, camera: str, road_classes: tuple[str, ...] = ROAD_CLASSES) -> np.ndarray | None:
    """``[H, W]`` uint8 background class of each pixel from the frame's semantics (the classes
    ``road_classes`` as road), None without."""
    sem = frame.semantics.get(camera)
    return None if sem is None else sem_to_bg(road_classes)[sem]


def load_mask_folder(seq: DrivingSequence, folder: str | Path, frame_ids: Sequence[int]) -> None:
    """Fill ``Frame.semantics`` from ``folder/<CAMERA>/<NN>.png`` (pixel = index into
    ``SEMANTIC_CLASSES``; NN = the frame's position in ``frame_ids``'s source numbering)."""
    from clsplat.io.images import read_image

    root = Path(folder)
    if not root.is_dir():
        raise ValueError(f"masks: folder {str(root)!r} does not exist")
    for k, i in enumerate(frame_ids):
        f = seq.frames[k]
        for c in seq.camera_names:
            p = root / c / f"{i:02d}.png"
            if not p.is_file():
                raise ValueError(f"masks: {str(p)!r} missing (one mask per camera and frame)")
            m = np.rint(read_image(p, channels=1)[..., 0] * 255.0).astype(np.uint8)
            if m.shape != f.images[c].shape[:2]:
                raise ValueError(f"masks: {str(p)!r} is {m.shape}, image is {f.images[c].shape[:2]}")
            if m.max() >= len(SEMANTIC_CLASSES):
                raise ValueError(f"masks: {str(p)!r} holds class {m.max()} >= {len(SEMANTIC_CLASSES)}")
            f.semantics[c] = m


def knn_mean_distance(points: torch.Tensor, k: int = 3, chunk: int = 2048) -> torch.Tensor:
    """Mean distance ``[N]`` of each point ``[N, 3]`` to its ``k`` nearest other points."""
    n = points.shape[0]
    if n <= 1:
        return torch.ones(n, dtype=points.dtype)
    k = min(k, n - 1)
    out = torch.empty(n, dtype=points.dtype)
    for s in range(0, n, chunk):
        d = torch.cdist(points[s:s + chunk], points)
        d[torch.arange(d.shape[0]), torch.arange(s, s + d.shape[0])] = float("inf")
        out[s:s + chunk] = d.topk(k, largest=False).values.mean(1)
    return out


def _knn_normals(points: torch.Tensor, k: int = 12, chunk: int = 2048) -> torch.Tensor:
    """Unit normals ``[N, 3]`` (z >= 0) from PCA of each point's ``k`` nearest neighbours."""
    n = points.shape[0]
    normals = torch.zeros(n, 3, dtype=points.dtype)
    normals[:, 2] = 1.0
    if n < 4:
        return normals
    k = min(k, n)
    for s in range(0, n, chunk):
        idx = torch.cdist(points[s:s + chunk], points).topk(k, largest=False).indices
        nb = points[idx]
        nb = nb - nb.mean(1, keepdim=True)
        _, vecs = torch.linalg.eigh(nb.transpose(1, 2) @ nb)
        nrm = vecs[:, :, 0]
        normals[s:s + chunk] = nrm * torch.where(nrm[:, 2:] < 0, -1.0, 1.0)
    return normals


def moving_track_ids(seq: DrivingSequence, threshold: float) -> set[int]:
    """Track ids whose box centre moves more than ``threshold`` metres (from its first box) over
    the sequence: the tracks AutoSplat decomposes; the others (parked cars) stay in the background
    as the LiDAR points they are."""
    centres: dict[int, list] = {}
    for f in seq.frames:
        for b in f.boxes:
            centres.setdefault(b.track_id, []).append(np.asarray(b.center, np.float64))
    return {t for t, c in centres.items() if float(np.linalg.norm(np.array(c) - c[0], axis=1).max()) > threshold}


def accumulate_lidar(seq: DrivingSequence, frame_ids: Sequence[int], box_margin: float | None,
                     remove: set[int] | None = None):
    """World-frame LiDAR of ``frame_ids`` without points in the boxes of the tracks ``remove``
    (None: every tracked box; ``box_margin`` None: keep them all, for a single static set as in
    plain 3DGS).

    Returns ``[(frame index, kept points [M,3] float64, their dataset labels [M] uint8 or None,
    all points of the sweep [M', 3] (the occluders for the visibility test)), ...]``.
    """
    if not any(seq.frames[i].lidar is not None and len(seq.frames[i].lidar.points) for i in frame_ids):
        raise ValueError("data: the sequence has no LiDAR points in the training frames; AutoSplat initialises "
                         "the background from LiDAR (no image-only initialisation is built)")
    point_labels = seq.metadata.get("lidar_semantics")
    out = []
    for i in frame_ids:
        f = seq.frames[i]
        if f.lidar is None:
            continue
        pts = f.lidar.to_world(f.ego_to_world).points.astype(np.float64)
        lab = None if point_labels is None or point_labels[i] is None else np.asarray(point_labels[i], np.uint8)
        if lab is not None and lab.shape[0] != pts.shape[0]:
            raise ValueError(f"data: frame {i} has {lab.shape[0]} LiDAR labels for {pts.shape[0]} points")
        keep = np.ones(len(pts), dtype=bool)
        for b in (f.boxes if box_margin is not None else []):
            if remove is None or b.track_id in remove:
                keep &= ~b.contains(pts, margin=box_margin)
        out.append((i, pts[keep], None if lab is None else lab[keep], pts))
    return out


def _colour_points(seq: DrivingSequence, i: int, cams: Sequence[str], pts: np.ndarray, all_pts: np.ndarray,
                   pt_labels: np.ndarray | None, road_classes: tuple[str, ...] = ROAD_CLASSES):
    """Colour, label and source pixel of world points of frame ``i`` from its cameras."""
    n = len(pts)
    f = seq.frames[i]
    colors = np.zeros((n, 3), np.float32)
    labels = np.full(n, UNKNOWN, np.uint8)
    source = np.full((n, 3), -1, np.int64)
    best = np.full(n, np.inf)
    for ci, c in enumerate(cams):
        cam = seq.camera(c)
        W, H = cam.width, cam.height
        w2c = np.linalg.inv(seq.cam_to_world(i, c))
        zbuf = np.full(H * W, np.inf)
        pc_all = all_pts @ w2c[:3, :3].T + w2c[:3, 3]
        za = pc_all[:, 2]
        ok = za > 0.1
        uva = pc_all[ok] @ cam.K.T
        ua, va = np.floor(uva[:, 0] / uva[:, 2]).astype(np.int64), np.floor(uva[:, 1] / uva[:, 2]).astype(np.int64)
        ins = (ua >= 0) & (ua < W) & (va >= 0) & (va < H)
        np.minimum.at(zbuf, va[ins] * W + ua[ins], za[ok][ins])
        zimg = torch.from_numpy(zbuf.reshape(1, 1, H, W))
        zimg = -torch.nn.functional.max_pool2d(-zimg, ZBUF_WINDOW, 1, ZBUF_WINDOW // 2)
        zbuf = zimg.reshape(-1).numpy()
        vis, lin, z, u, v = project_to_pixels(seq, i, c, pts, 0.1)
        vis &= z <= zbuf[lin] * 1.03 + 0.1
        # prefer the view that sees the point closest to the image centre
        centre = np.hypot(u - W / 2, v - H / 2) / max(W, H)
        take = vis & (centre < best)
        if not take.any():
            continue
        best[take] = centre[take]
        colors[take] = f.images[c].reshape(-1, 3)[lin[take]]
        pcls = pixel_classes(f, c, road_classes)
        if pcls is not None:
            labels[take] = pcls.reshape(-1)[lin[take]]
        source[take] = np.stack([np.full(take.sum(), i), np.full(take.sum(), ci), lin[take]], 1)
    if pt_labels is not None:
        unl = labels == UNKNOWN
        labels[unl] = sem_to_bg(road_classes)[np.minimum(pt_labels[unl], len(SEMANTIC_CLASSES) - 1)]
    seen = source[:, 0] >= 0
    labels[seen & (labels == UNKNOWN)] = OTHER
    return colors, labels, source, seen


def _nearest(query: torch.Tensor, points: torch.Tensor, k: int, chunk: int = 2048) -> torch.Tensor:
    """Indices ``[Q, k]`` of the ``k`` nearest ``points [N, D]`` to each ``query [Q, D]``."""
    k = min(k, points.shape[0])
    return torch.cat([torch.cdist(query[s:s + chunk], points).topk(k, largest=False).indices
                      for s in range(0, query.shape[0], chunk)]) if query.shape[0] else torch.zeros(0, k, dtype=torch.long)


def extend_road(means: np.ndarray, colors: np.ndarray, normals: np.ndarray, poses: np.ndarray, width: float,
                spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Road Gaussians continuing the observed road ``width`` metres beyond its lateral edges.

    Args:
        means [N,3], colors [N,3], normals [N,3]: the observed road Gaussians (world frame).
        poses [F,4,4]: the training frames' ego-to-world poses (x forward); they fix where "along"
            and "across" the road are, the road's direction itself is the principal axis of the
            road Gaussians within ``ROAD_AXIS_RADIUS`` of each pose (the pose's heading with fewer
            than 3 of them).
        width: metres added on each side (0: nothing); spacing: the added grid's step (metres).

    Each road Gaussian gets an along-road coordinate s (from its horizontally nearest pose) and a
    signed lateral one l (left positive). Per strip of ``spacing`` in s, grid points are placed at
    l = max l + k * spacing and min l - k * spacing, k = 1..round(width / spacing), and kept where
    no observed road Gaussian lies within half a step (a gap a neighbouring strip covers is not
    beyond the road). Each kept point takes the mean height, colour and normal (renormalised,
    z >= 0) of its ``ROAD_EXTEND_NEIGHBOURS`` horizontally nearest observed road Gaussians.

    Returns:
        ``(means [M,3], colors [M,3], normals [M,3])`` float64; M = 0 when ``width`` is 0 or there
        are fewer than 4 road Gaussians.
    """
    empty = (np.zeros((0, 3)),) * 3
    if not width > 0 or len(means) < 4 or len(poses) == 0:
        return empty
    xy = means[:, :2].astype(np.float64)
    centre = poses[:, :2, 3].astype(np.float64)
    axis = poses[:, :2, 0].astype(np.float64)
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-9)
    for j in range(len(poses)):
        near = xy[np.linalg.norm(xy - centre[j], axis=1) < ROAD_AXIS_RADIUS]
        if len(near) >= 3:
            c = near - near.mean(0)
            a = np.linalg.eigh(c.T @ c)[1][:, -1]
            axis[j] = a if a @ axis[j] >= 0 else -a
    left = np.stack([-axis[:, 1], axis[:, 0]], 1)
    # arc length of the poses along the road
    s_pose = np.concatenate([[0.0], np.cumsum(np.abs(np.einsum("ij,ij->i", np.diff(centre, axis=0), axis[:-1])))])
    j = _nearest(torch.from_numpy(xy), torch.from_numpy(centre), 1)[:, 0].numpy()
    rel = xy - centre[j]
    s = s_pose[j] + np.einsum("ij,ij->i", rel, axis[j])
    lat = np.einsum("ij,ij->i", rel, left[j])
    strip = np.floor(s / spacing).astype(np.int64)
    n = max(1, int(round(width / spacing)))
    steps = spacing * np.arange(1, n + 1)
    cand = []
    for b in np.unique(strip):
        m = strip == b
        sc = (b + 0.5) * spacing
        jj = int(np.argmin(np.abs(s_pose - sc)))
        base = centre[jj] + (sc - s_pose[jj]) * axis[jj]
        for ls in (lat[m].max() + steps, lat[m].min() - steps):
            cand.append(base + ls[:, None] * left[jj])
    cand = np.concatenate(cand)
    obs = torch.from_numpy(xy)
    d = torch.cat([torch.cdist(c, obs).min(1).values for c in torch.from_numpy(cand).split(2048)]).numpy()
    cand = cand[d >= 0.5 * spacing]
    if len(cand) == 0:
        return empty
    nb = _nearest(torch.from_numpy(cand), obs, ROAD_EXTEND_NEIGHBOURS).numpy()
    z = means[nb, 2].astype(np.float64).mean(1)
    col = colors[nb].astype(np.float64).mean(1)
    nrm = normals[nb].astype(np.float64).mean(1)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-9)
    nrm *= np.where(nrm[:, 2:] < 0, -1.0, 1.0)
    return np.concatenate([cand, z[:, None]], 1), col, nrm


def _sky_dome(seq: DrivingSequence, frame_ids: Sequence[int], cams: Sequence[str], n: int, radius: float):
    """Hemisphere of ``n`` sky Gaussians about the trajectory, coloured from sky pixels."""
    centre = np.mean([seq.frames[i].ego_to_world[:3, 3] for i in frame_ids], axis=0)
    centre[2] = 0.0
    k = np.arange(n) + 0.5
    z = np.sin(np.radians(-5.0)) + (1 - np.sin(np.radians(-5.0))) * k / n   # elevation -5..90 deg
    r = np.sqrt(np.clip(1 - z * z, 0, 1))
    phi = k * np.pi * (3 - np.sqrt(5))
    dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    means = centre + radius * dirs
    acc = np.zeros((n, 3))
    cnt = np.zeros(n)
    sky_pixels = []
    for i in frame_ids:
        f = seq.frames[i]
        for c in cams:
            pcls = pixel_classes(f, c)
            if pcls is None:
                continue
            vis, lin, _, _, _ = project_to_pixels(seq, i, c, means, 0.0)
            vis &= pcls.reshape(-1)[lin] == SKY
            acc[vis] += f.images[c].reshape(-1, 3)[lin[vis]]
            cnt[vis] += 1
            sky_pixels.append(f.images[c][pcls == SKY])
    sp = np.concatenate(sky_pixels) if sky_pixels else np.zeros((0, 3))
    mean_sky = sp.mean(0) if len(sp) else np.array([0.7, 0.8, 0.9])
    colors = np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], mean_sky)
    spacing = radius * np.sqrt(2 * np.pi * 1.1 / n)
    scales = np.tile([spacing * 0.8, spacing * 0.8, spacing * 0.02], (n, 1))  # thin discs, z radial
    source = np.full((n, 3), -1, np.int64)
    return means, colors, scales, dirs, source, mean_sky


def init_background(seq: DrivingSequence, frame_ids: Sequence[int], cameras: Sequence[str], preset,
                    generator: np.random.Generator, remove_boxes: bool = True) -> tuple[BackgroundInit, np.ndarray]:
    """Initial background Gaussians from the LiDAR of ``frame_ids`` seen by ``cameras``: the
    points in the boxes of moving tracks (``preset.dynamic_threshold``) are left out, those of
    static tracks stay (with ``remove_boxes`` False every point stays in: plain 3DGS's single set).

    Returns ``(BackgroundInit, mean_sky_colour [3])``.
    """
    sweeps = accumulate_lidar(seq, frame_ids, preset.box_margin if remove_boxes else None,
                              moving_track_ids(seq, preset.dynamic_threshold))
    P, C, L, S = [], [], [], []
    for i, pts, lab, occluders in sweeps:
        if len(pts) == 0:
            continue
        colors, labels, source, seen = _colour_points(seq, i, cameras, pts, occluders, lab,
                                                      tuple(getattr(preset, "road_classes", ROAD_CLASSES)))
        P.append(pts[seen]), C.append(colors[seen]), L.append(labels[seen]), S.append(source[seen])
    if not P or sum(len(p) for p in P) == 0:
        raise ValueError("data: no LiDAR point is visible in the selected cameras; check --cameras and the poses")
    P, C, L, S = (np.concatenate(x) for x in (P, C, L, S))
    hit = L != SKY  # a LiDAR return on a sky pixel is a label-boundary error: drop it
    P, C, L, S = P[hit], C[hit], L[hit], S[hit]
    key = np.floor(P / preset.lidar_voxel).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    first.sort()
    if len(first) > preset.max_bg_points:
        first = np.sort(generator.choice(first, preset.max_bg_points, replace=False))
    P, C, L, S = P[first], C[first], L[first], S[first]
    pts_t = torch.from_numpy(P)
    d = knn_mean_distance(pts_t).clamp(min=0.02, max=2.0).numpy()
    scales = np.repeat(d[:, None], 3, 1)
    normals = np.zeros_like(P)
    normals[:, 2] = 1.0
    road = L == ROAD
    if road.sum() >= 4:
        normals[road] = _knn_normals(pts_t[torch.from_numpy(road)]).numpy()
    width = float(getattr(preset, "road_extend_m", 0.0))
    if width > 0:
        spacing = ROAD_EXTEND_SPACING * preset.lidar_voxel
        em, ec, en = extend_road(P[road], C[road], normals[road],
                                 np.stack([seq.frames[i].ego_to_world for i in frame_ids]), width, spacing)
        P = np.concatenate([P, em]); C = np.concatenate([C, ec]); normals = np.concatenate([normals, en])
        scales = np.concatenate([scales, np.full((len(em), 3), spacing)])
        L = np.concatenate([L, np.full(len(em), ROAD, L.dtype)])
        S = np.concatenate([S, np.full((len(em), 3), -1, np.int64)])
    mean_sky = None
    if preset.sky == "dome":
        dm, dc, ds, dn, dsrc, mean_sky = _sky_dome(seq, frame_ids, cameras, preset.dome_points, preset.dome_radius)
        P = np.concatenate([P, dm]); C = np.concatenate([C, dc]); scales = np.concatenate([scales, ds])
        L = np.concatenate([L, np.full(len(dm), SKY, np.uint8)]); normals = np.concatenate([normals, dn])
        S = np.concatenate([S, dsrc])
    elif preset.sky == "color":
        *_, mean_sky = _sky_dome(seq, frame_ids, cameras, 1, preset.dome_radius)
    else:
        raise ValueError(f"preset.sky must be 'dome' or 'color', got {preset.sky!r}")
    init = BackgroundInit(P.astype(np.float32), np.clip(C, 0, 1).astype(np.float32), scales.astype(np.float32),
                          L.astype(np.int64), normals.astype(np.float32), S)
    return init, np.asarray(mean_sky, np.float32)
