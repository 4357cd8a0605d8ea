"""Why are far-side object pixels "seen"? (issue 33) A breakdown of the ``far-side`` view set's
vehicle pixels that some training camera saw, from the generator's geometry alone (no model).

For a generated street (``--world``, ``--seed``) and AutoSplat's synthetic split (16 frames at
0.2 s, every 4th from frame 2 held out, ``--cameras`` of the rig), the rig is mirrored across every
moving vehicle at every frame (``clsplat.models.autosplat.viewsets.far_side``'s views, those where
the vehicle covers at least ``MIN_OBJECT_PIXELS``), and each counted vehicle pixel gets

* its **surface**: the vehicle part it lies on (``body``, ``cabin``, ``wheel``) and that part's
  face, named for the vehicle: ``far`` (the side face whose outward normal points away from the
  ego at that frame: the face the issue means), ``near`` (the other side face), ``front`` /
  ``back``, ``top``, ``bottom``; wheels are ``wheel`` whatever their face;
* ``silhouette``: a 4-neighbour of the pixel in the mirrored view shows another surface;
* whether a training camera saw it (the test of :func:`viewsets.unseen_pixels`, re-run here so that
  it can say **which** training view saw it first (frame, camera) and **how**: ``exact`` (a same-
  surface footprint depth within ``SEEN_REL_TOL`` of the point's) or ``range`` (only inside the
  range of the 2 x 2 footprint's depths, i.e. across a depth step within one surface label);
  the script asserts its unseen mask equals ``unseen_pixels``'s);
* the vehicle's **place** relative to the ego at that frame: its longitudinal offset ``dx`` in the
  ego frame, ``alongside`` when ``|dx| <= ALONGSIDE_M``, else ``ahead`` / ``behind``; and the
  mirrored camera's angle to the vehicle's lateral axis (``view_deg``: 0 = looking straight at
  the far face).

``--view-set`` picks the views scored (``AutoSplatPreset.far_side_view``): ``mirrored`` (the set as
``eval autosplat`` scores it by default) or ``side-on`` (:func:`viewsets.side_on_camera`).

    .venv/bin/python bench/experiments/autosplat_farside_why.py --world divided --seed 0 1 2 --scale 0.5
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

RIG = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
#: a vehicle is "alongside" the ego when its centre is within this many metres of the ego's along the road
ALONGSIDE_M = 4.0


def _surface(parts, p: np.ndarray, ego_dir_box: np.ndarray, box_R: np.ndarray) -> np.ndarray:
    """Surface names (``[N]`` object array) of world points ``p [N, 3]`` on a vehicle made of ``parts``
    (generator box primitives); ``ego_dir_box [3]``: the direction to the ego in the vehicle's box frame
    (its y sign says which side face is near); ``box_R [3, 3]``: the vehicle box's rotation."""
    best = np.full(len(p), np.inf)
    name = np.full(len(p), "?", dtype=object)
    near_sign = 1.0 if ego_dir_box[1] >= 0 else -1.0
    for b in parts:
        Ti = np.linalg.inv(b.T)
        loc = p @ Ti[:3, :3].T + Ti[:3, 3]
        out = np.max(np.abs(loc) - b.half, axis=1)        # <= ~0 inside / on the part
        ax = np.argmax(np.abs(loc) - b.half, axis=1)     # the face the point lies on
        sgn = np.sign(loc[np.arange(len(p)), ax])
        # the face's outward normal in the vehicle's box frame
        n_world = b.T[:3, :3][:, ax].T * sgn[:, None]
        n_box = n_world @ box_R
        k = np.argmax(np.abs(n_box), axis=1)
        s = np.sign(n_box[np.arange(len(p)), k])
        face = np.where(k == 2, np.where(s > 0, "top", "bottom"),
                        np.where(k == 0, np.where(s > 0, "front", "back"),
                                 np.where(s == near_sign, "near", "far")))
        if b.kind == "wheel":
            face = np.full(len(p), "wheel", dtype=object)
        else:
            face = np.array([f"{b.kind}:{f}" for f in face], dtype=object)
        better = out < best - 1e-9
        best = np.where(better, out, best)
        name = np.where(better, face, name)
    return name


def analyse(world: str, seed: int, scale: float, cameras: list[str], view_set: str = "mirrored",
            frames: int = 16, holdout: int = 4) -> dict:
    """Counters of the far-side set's vehicle pixels (see the module): ``"pixels"``, ``"unseen"``
    and, over the seen ones, ``"by_surface"``, ``"by_track"``, ``"by_place"``, ``"by_seer"`` (training
    frame, camera), ``"by_how"``, ``"by_silhouette"``; ``"surface_all"`` over all counted pixels;
    ``"views"``: per view (frame, track, camera, place, view_deg, pixels, unseen)."""
    from clsplat.data.synthetic import SyntheticConfig, generate_sequence
    from clsplat.models.autosplat import viewsets as vs
    from clsplat.models.autosplat.data import SYNTHETIC_DT
    from clsplat.models.autosplat.init import moving_track_ids
    from clsplat.models.autosplat.presets import AutoSplatPreset

    seq = generate_sequence(SyntheticConfig(height=max(8, round(176 * scale)), width=max(8, round(320 * scale)),
                                            num_frames=frames, seed=seed, dt=SYNTHETIC_DT, world=world, lidar=False))
    scene = seq.metadata["scene"]
    test = [i for i in range(frames) if i % holdout == holdout // 2]
    c0 = seq.cameras[0]
    H, W = c0.height, c0.width
    run = SimpleNamespace(data=SimpleNamespace(seq=seq, cameras=list(cameras), height=H, width=W,
                                               train_frames=[i for i in range(frames) if i not in test]),
                          preset=SimpleNamespace(dynamic_threshold=AutoSplatPreset.dynamic_threshold,
                                                 far_side_view=view_set))
    train = vs._training_views(run)
    cam_of = [c for _ in run.data.train_frames for c in cameras]
    moving = sorted(moving_track_ids(seq, AutoSplatPreset.dynamic_threshold))
    tol = vs.SEEN_REL_TOL
    res = {k: Counter() for k in ("by_surface", "by_track", "by_place", "by_seer", "by_how", "by_silhouette",
                                  "surface_all", "unseen_by_surface", "joint")}
    res["views"] = []
    tot_n = tot_u = 0
    for f, tr, c2w, idx in vs._far_side_views(run, view_set):
        t_f = seq.frames[f].timestamp
        E = seq.frames[f].ego_to_world
        box = vs._exact_box(seq, f, tr)
        names = [cameras[j] for j in idx]
        gt = vs._generator_views(run, f, c2w, names)
        mask = np.stack([g.instance == tr for g in gt])
        keep = mask.reshape(len(names), -1).sum(1) >= vs.MIN_OBJECT_PIXELS
        if not keep.any():
            continue
        ref_un = vs.unseen_pixels(run, f, c2w, gt, cameras=names, only=mask)[0]
        B = box.box_to_world
        Binv = np.linalg.inv(B)
        ego_box = Binv[:3, :3] @ E[:3, 3] + Binv[:3, 3]
        rel = np.linalg.inv(E) @ np.append(B[:3, 3], 1.0)
        dx, dist = float(rel[0]), float(np.linalg.norm(rel[:2]))
        place = "alongside" if abs(dx) <= ALONGSIDE_M else ("ahead" if dx > 0 else "behind")
        spec = next(v for v in scene.vehicles if v.track_id == tr)
        parts = scene.vehicle_parts(spec, t_f)
        for k, cam in enumerate(names):
            if not keep[k]:
                continue
            v = gt[k]
            ok = mask[k] & np.isfinite(v.depth)
            vv, uu = np.nonzero(ok)
            K = np.asarray(seq.camera(cam).K, dtype=np.float64)
            z = v.depth[ok].astype(np.float64)
            pc = np.stack([(uu + 0.5 - K[0, 2]) / K[0, 0] * z, (vv + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1)
            T = c2w[k]
            pw = pc @ T[:3, :3].T + T[:3, 3]
            surf = _surface(parts, pw, ego_box, B[:3, :3])
            lab = vs._label(v.instance[ok], v.semantic[ok])
            inst_pad = np.pad(v.instance, 1, constant_values=-1)
            sil = np.zeros(len(z), dtype=bool)
            for dy_, dx_ in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                sil |= inst_pad[vv + 1 + dy_, uu + 1 + dx_] != tr
            pl = pw @ Binv[:3, :3].T + Binv[:3, 3]
            seer = np.full(len(z), -1)
            how = np.full(len(z), "", dtype=object)
            for j, (tf, Kt, w2c, dt, lt) in enumerate(train):
                todo = np.nonzero(seer < 0)[0]
                if not len(todo):
                    break
                bt = vs._exact_box(seq, tf, tr)
                if bt is None:
                    continue
                Bt = bt.box_to_world
                P = pl[todo] @ Bt[:3, :3].T + Bt[:3, 3]
                vis, exact = vs.footprint_visible(P, lab[todo], Kt, w2c, dt, lt, tol)
                seer[todo[vis]] = j
                how[todo[vis]] = np.where(exact[vis], "exact", "range")
            un = seer < 0
            full_un = np.zeros_like(ok)
            full_un[ok] = un
            assert np.array_equal(full_un, ref_un[k]), "the re-run visibility test disagrees with unseen_pixels"
            n, u = len(z), int(un.sum())
            tot_n, tot_u = tot_n + n, tot_u + u
            view_deg = _view_angle(T, B)
            res["views"].append({"frame": f, "track": tr, "camera": cam, "place": place, "dx": round(dx, 2),
                                 "dist": round(dist, 2),
                                 "view_deg": round(view_deg, 1), "pixels": n, "unseen": u})
            s = ~un
            res["surface_all"].update(surf.tolist())
            res["unseen_by_surface"].update(surf[un].tolist())
            res["by_surface"].update(surf[s].tolist())
            res["by_track"].update([tr] * int(s.sum()))
            res["joint"].update([f"{a}|{b}|{c}|{p_}" for a, b, c, p_ in zip(
                surf[s], how[s], np.where(sil[s], "silhouette", "interior"), [place] * int(s.sum()))])
            res["by_place"].update([place] * int(s.sum()))
            res["by_how"].update(how[s].tolist())
            res["by_silhouette"].update(np.where(sil[s], "silhouette", "interior").tolist())
            res["by_seer"].update([f"{train[j][0]}:{cam_of[j]}" for j in seer[s]])
            res.setdefault("place_pixels", Counter()).update({place: n})
            res.setdefault("place_unseen", Counter()).update({place: u})
            res.setdefault("track_pixels", Counter()).update({tr: n})
    res.update(pixels=tot_n, unseen=tot_u, tracks=moving)
    return res


def _view_angle(cam_to_world: np.ndarray, box_to_world: np.ndarray) -> float:
    """Angle (deg) between the direction from the camera to the box centre and the box's lateral
    axis (0: the camera looks straight at a side face)."""
    d = box_to_world[:3, 3] - cam_to_world[:3, 3]
    d = d / np.linalg.norm(d)
    ly = box_to_world[:3, 1]
    return float(np.degrees(np.arccos(min(1.0, abs(float(d @ ly))))))


def _pct(c: Counter, n: int, top: int = 12) -> str:
    return ", ".join(f"{k} {100 * v / n:.1f}%" for k, v in c.most_common(top)) if n else "-"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--world", default="divided", choices=("classic", "varied", "straight", "divided"))
    p.add_argument("--seed", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--scale", type=float, default=0.5, help="image scale of the 176 x 320 rig (default 0.5, demo's)")
    p.add_argument("--cameras", nargs="+", default=list(RIG))
    p.add_argument("--view-set", default="mirrored", choices=("mirrored", "side-on"),
                   help="the far-side set's views (AutoSplatPreset.far_side_view)")
    p.add_argument("--range", type=float, default=None,
                   help="side-on: keep vehicles within this many metres of the ego (default SIDE_ON_RANGE_M)")
    p.add_argument("--json", type=Path, default=None, help="write every counter here")
    a = p.parse_args(argv)
    dump = {}
    for seed in a.seed:
        t0 = time.perf_counter()
        if a.range is not None:
            from clsplat.models.autosplat import viewsets
            viewsets.SIDE_ON_RANGE_M = a.range
            viewsets.side_on_camera.__defaults__ = (a.range,)
        r = analyse(a.world, seed, a.scale, a.cameras, a.view_set)
        n, u = r["pixels"], r["unseen"]
        seen = n - u
        print(f"== {a.world} seed {seed}, scale {a.scale:g}, view set {a.view_set}: {n} vehicle px, "
              f"unseen {100 * u / max(n, 1):.1f} %, tracks {r['tracks']}  [{time.perf_counter() - t0:.0f} s]")
        print("  all counted px by surface: " + _pct(r["surface_all"], n))
        print("  unseen share per surface:  " + ", ".join(
            f"{k} {100 * r['unseen_by_surface'][k] / v:.0f}% of {v}" for k, v in r["surface_all"].most_common()))
        print("  seen px by surface:        " + _pct(r["by_surface"], seen))
        print("  seen px by silhouette:     " + _pct(r["by_silhouette"], seen))
        print("  seen px by how:            " + _pct(r["by_how"], seen))
        print("  seen px by place:          " + _pct(r["by_place"], seen)
              + "   | place: px / unseen %: " + ", ".join(
                  f"{k} {v} / {100 * r['place_unseen'][k] / v:.0f}%" for k, v in r["place_pixels"].items()))
        print("  seen px by track:          " + _pct(r["by_track"], seen)
              + "   | track px: " + ", ".join(f"{k} {v}" for k, v in sorted(r["track_pixels"].items())))
        print("  seen px by first seer:     " + _pct(r["by_seer"], seen, 10))
        print("  seen px, surface|how|edge|place: " + _pct(r["joint"], seen, 14))
        dump[seed] = {k: (dict(v) if isinstance(v, Counter) else v) for k, v in r.items()}
    if a.json:
        a.json.write_text(json.dumps(dump, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
