"""Issue 36 (tracker noise): can the LiDAR find what the photometric loss does not? A bound for
refining tracker boxes by registering each frame's LiDAR points on the object to the others'.

For each moving track of a generated street with tracker-noise boxes (``--data``, e.g.
``synthetic:busy-noisy``) and each frame: the LiDAR points inside its noisy box grown by
``--margin`` metres sideways (the ground within ``--ground`` metres of the box's bottom left out),
in the noisy box's frame. Every frame with at least ``--min-points`` points is registered to the
union of the track's other frames (rigid in the ground plane: x, y, yaw; nearest neighbours in 3-D,
pairs farther than ``--trim`` metres dropped, ``--rounds`` rounds, the union rebuilt from the
registered frames after each). The registered box's error against the generator's exact box,
``Err_f = C_f B_f^-1 E_f`` (``C_f`` the registration, ``B_f`` the noisy box, ``E_f`` the exact one),
is constant over a track's frames when the registration is right up to the shape's own frame (a
gauge the object set absorbs), so what is printed is its frame-to-frame variation (each track's mean
removed): the box centre's x/y distance and the yaw, before (``C_f`` = I) and after, per class and in
all, over the registered boxes (a box with too few points keeps its noisy pose and is counted apart).

    .venv/bin/python bench/experiments/autosplat_lidar_box_probe.py --data synthetic:busy-noisy --seed 0 1 2
"""
from __future__ import annotations

import argparse

import numpy as np
import torch


def _rigid2d(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``[3, 3]`` homogeneous 2-D rigid transform taking ``src [N, 2]`` onto ``dst [N, 2]`` (least squares)."""
    ms, md = src.mean(0), dst.mean(0)
    H = (src - ms).T @ (dst - md)
    U, _, Vt = np.linalg.svd(H)
    R = Vt.T @ U.T
    if np.linalg.det(R) < 0:
        Vt[1] *= -1
        R = Vt.T @ U.T
    T = np.eye(3)
    T[:2, :2], T[:2, 2] = R, md - R @ ms
    return T


def _apply(T2: np.ndarray, p: np.ndarray) -> np.ndarray:
    out = p.copy()
    out[:, :2] = p[:, :2] @ T2[:2, :2].T + T2[:2, 2]
    return out


def register(clouds: dict[int, np.ndarray], rounds: int, trim: float) -> dict[int, np.ndarray]:
    """Each frame's ``[3, 3]`` 2-D correction registering its cloud (box frame) to the others'."""
    C = {f: np.eye(3) for f in clouds}
    for _ in range(rounds):
        placed = {f: _apply(C[f], p) for f, p in clouds.items()}
        for f, p in clouds.items():
            others = np.concatenate([q for g, q in placed.items() if g != f])
            T = C[f]
            for _ in range(5):   # inner ICP iterations against the fixed union
                cur = _apply(T, p)
                dist = torch.cdist(torch.from_numpy(cur), torch.from_numpy(others))
                dmin, j = dist.min(1)
                keep = (dmin < trim).numpy()
                if keep.sum() < 5:
                    break
                T = _rigid2d(cur[keep, :2], others[j.numpy()[keep], :2]) @ T
            C[f] = T
    return C


def _spread(errs: list[np.ndarray]) -> tuple[list[float], list[float]]:
    """Frame-to-frame centre (m) and yaw (°) deviations of one track's ``[4, 4]`` error transforms."""
    pts = np.array([e[:2, 3] for e in errs])
    yaws = np.array([np.arctan2(e[1, 0], e[0, 0]) for e in errs])
    my = np.arctan2(np.sin(yaws).mean(), np.cos(yaws).mean())
    wrap = (yaws - my + np.pi) % (2 * np.pi) - np.pi
    return np.linalg.norm(pts - pts.mean(0), axis=1).tolist(), np.degrees(np.abs(wrap)).tolist()


def probe(spec: str, seed: int, margin: float, ground: float, min_points: int, rounds: int, trim: float) -> dict:
    from clsplat.data.scene import invert_transform
    from clsplat.models.autosplat.data import load_sequence
    from clsplat.models.autosplat.init import moving_track_ids

    seq = load_sequence(spec, None, None, 0.25, seed=seed)
    exact = seq.metadata.get("exact_boxes")
    if exact is None:
        raise ValueError(f"--data: {spec!r} carries no tracker noise (no exact boxes to score against)")
    moving = moving_track_ids(seq, 0.5)
    world = [None if f.lidar is None else f.lidar.to_world(f.ego_to_world).points.astype(np.float64)
             for f in seq.frames]
    out: dict[str, dict[str, list]] = {}
    for tid in sorted(moving):
        boxes = {i: b for i, f in enumerate(seq.frames) for b in f.boxes if b.track_id == tid}
        clouds, label = {}, None
        for i, b in boxes.items():
            label = b.label
            if world[i] is None or tid not in exact[i]:
                continue
            T = invert_transform(b.box_to_world)
            local = world[i] @ T[:3, :3].T + T[:3, 3]
            half = b.size / 2
            keep = (np.abs(local[:, 0]) <= half[0] + margin) & (np.abs(local[:, 1]) <= half[1] + margin) \
                & (local[:, 2] <= half[2]) & (local[:, 2] >= -half[2] + ground)
            if keep.sum() >= min_points:
                clouds[i] = local[keep]
        cls = "car" if "car" in label.lower() else "pedestrian" if "ped" in label.lower() else "other"
        row = out.setdefault(cls, {"before_c": [], "before_y": [], "after_c": [], "after_y": [], "few": 0})
        row["few"] += sum(1 for i in boxes if i not in clouds)
        if len(clouds) < 3:
            continue
        C = register(clouds, rounds, trim)
        before, after = [], []
        for i in clouds:
            e = invert_transform(boxes[i].box_to_world) @ exact[i][tid].box_to_world   # B^-1 E
            c4 = np.eye(4)
            c4[:2, :2], c4[:2, 3] = C[i][:2, :2], C[i][:2, 2]
            before.append(e)
            after.append(c4 @ e)
        for key, errs in (("before", before), ("after", after)):
            cc, yy = _spread(errs)
            row[f"{key}_c"] += cc
            row[f"{key}_y"] += yy
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="synthetic:busy-noisy")
    ap.add_argument("--seed", type=int, nargs="+", default=[0])
    ap.add_argument("--margin", type=float, default=0.4)
    ap.add_argument("--ground", type=float, default=0.15)
    ap.add_argument("--min-points", type=int, default=15)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--trim", type=float, default=0.3)
    a = ap.parse_args()
    torch.set_num_threads(1)
    print(f"{a.data}: frame-to-frame box error (each track's mean removed), before → after the LiDAR registration")
    print("| seed | class | registered boxes | centre m | yaw ° | boxes with too few points |")
    print("|---|---|---|---|---|---|")
    for s in a.seed:
        res = probe(a.data, s, a.margin, a.ground, a.min_points, a.rounds, a.trim)
        rows = list(res.items())
        allr = {k: sum((r[k] for _, r in rows), [] if k != "few" else 0) for k in
                ("before_c", "before_y", "after_c", "after_y", "few")}
        for cls, r in [*rows, ("all", allr)]:
            if not r["before_c"]:
                print(f"| {s} | {cls} | 0 | – | – | {r['few']} |")
                continue
            print(f"| {s} | {cls} | {len(r['before_c'])} | "
                  f"{np.mean(r['before_c']):.3f} → {np.mean(r['after_c']):.3f} | "
                  f"{np.mean(r['before_y']):.2f} → {np.mean(r['after_y']):.2f} | {r['few']} |", flush=True)


if __name__ == "__main__":
    main()
