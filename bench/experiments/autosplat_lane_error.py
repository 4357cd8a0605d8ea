"""Where the lane-change error of an AutoSplat run lives (issue 19): the squared error of the
rig moved ``--shift`` metres left at the held-out frames (the ``lane_change`` view set of
:mod:`models.autosplat.viewsets`), split by the generator's classes, for finished runs of
``bench/experiments/autosplat_views.py`` (their checkpoints, rebuilt on their own data).

Classes (from the generator's exact render of the shifted view): road, sidewalk, building (façades),
footbridge (the ``synthetic:views`` street's only shadow caster, a building-class box whose
pixels lie in the sky band of the front and back cameras), vehicle moving (the decomposed
tracks), vehicle parked, sky, other (poles, trees). Each static pixel is also marked "seen" when
its surface point (the generator's depth) is visible, within a depth tolerance, in some training
view of the recorded path (the generator's depth maps of the training frames), else "unseen".

Per row and seed: each class's pixel share, pooled PSNR and share of the total squared error;
then the **upper bound**: the run's renders with the pixels of some classes replaced by the ground
truth (road for flatness; moving vehicles for decomposition / symmetry; sky for the sky model),
scored with the lane-change metric itself (mean over images of per-image PSNR), i.e. the most any
constraint acting on those classes could add to that run.

    nice -n 5 .venv/bin/python bench/experiments/autosplat_lane_error.py \\
        --runs bench/out/autosplat_views --rows full plain --seeds 0 1 2 --out bench/out/autosplat_lane_error
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from clsplat.data.synthetic.config import FOOTBRIDGE_HALF, FOOTBRIDGE_X, FOOTBRIDGE_Z, SEM  # noqa: E402
from clsplat.data.synthetic.views import shift_sideways  # noqa: E402
from models.autosplat.evaluate import trainer_from_checkpoint  # noqa: E402
from models.autosplat.init import moving_track_ids  # noqa: E402
from models.common.train import load_checkpoint  # noqa: E402
from models.common.metrics import psnr as psnr_metric  # noqa: E402

CLASSES = ("road", "sidewalk", "building", "footbridge", "vehicle moving", "vehicle parked", "sky", "other")
#: class sets whose pixels the upper bound replaces by the ground truth
BOUNDS = {"road": ("road",), "moving vehicles": ("vehicle moving",), "sky": ("sky",),
          "road + moving vehicles + sky": ("road", "vehicle moving", "sky"),
          "road + sidewalk": ("road", "sidewalk"),
          "footbridge": ("footbridge",), "building": ("building",),
          "everything unseen from the path": ("@unseen",)}
#: a shifted view's surface point counts as seen from the path when a training view's depth at
#: its pixel agrees within this relative tolerance (plus DEPTH_TOL_M)
DEPTH_TOL_REL, DEPTH_TOL_M = 0.03, 0.15


def class_map(view, moving: set[int], origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """``[H, W]`` index into :data:`CLASSES` of one generator render (``dirs [H, W, 3]`` world
    rays with camera-z 1, so ``origin + depth * dirs`` is the surface point)."""
    sem, inst = view.semantic, view.instance
    out = np.full(sem.shape, CLASSES.index("other"), np.int64)
    out[sem == SEM["road"]] = CLASSES.index("road")
    out[sem == SEM["sidewalk"]] = CLASSES.index("sidewalk")
    out[sem == SEM["sky"]] = CLASSES.index("sky")
    b = sem == SEM["building"]
    out[b] = CLASSES.index("building")
    p = origin + np.where(np.isfinite(view.depth), view.depth, 0)[..., None] * dirs
    bridge = b & (np.abs(p[..., 0] - FOOTBRIDGE_X) <= FOOTBRIDGE_HALF[0] + 1e-3) \
        & (np.abs(p[..., 2] - FOOTBRIDGE_Z) <= FOOTBRIDGE_HALF[2] + 1e-3)
    out[bridge] = CLASSES.index("footbridge")
    v = sem == SEM["vehicle"]
    out[v & np.isin(inst, list(moving))] = CLASSES.index("vehicle moving")
    out[v & ~np.isin(inst, list(moving))] = CLASSES.index("vehicle parked")
    return out


def ray_dirs(K: np.ndarray, c2w: np.ndarray, w: int, h: int) -> np.ndarray:
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    dc = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return dc @ c2w[:3, :3].T


def seen_from_path(seq, cams: list[str], train: list[int], points: np.ndarray) -> np.ndarray:
    """``[N]`` bool: world ``points [N, 3]`` visible (depth test) in some training view."""
    seen = np.zeros(len(points), bool)
    for i in train:
        f = seq.frames[i]
        for c in cams:
            cam = seq.camera(c)
            w2c = np.linalg.inv(seq.cam_to_world(i, c))
            pc = points @ w2c[:3, :3].T + w2c[:3, 3]
            z = pc[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                uvw = pc @ cam.K.T
                u = np.floor(uvw[:, 0] / uvw[:, 2])
                v = np.floor(uvw[:, 1] / uvw[:, 2])
            ok = (z > 0.1) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
            d = f.depths[c]
            zz = np.full(len(points), np.nan)
            zz[ok] = d[v[ok].astype(int), u[ok].astype(int)]
            seen |= ok & (np.abs(zz - z) <= DEPTH_TOL_REL * z + DEPTH_TOL_M)
    return seen


def ground_truth(trainer, shift: float) -> dict:
    """Per held-out frame: the shifted rig's generator renders, class maps and seen masks."""
    d = trainer.data
    seq = d.seq
    scene = seq.metadata["scene"]
    moving = moving_track_ids(seq, trainer.preset.dynamic_threshold)
    out = {"rgb": [], "cls": [], "seen": [], "c2w": []}
    for frame in d.test_frames:
        rig = np.stack([seq.cam_to_world(frame, c) for c in d.cameras])
        c2w = shift_sideways(rig, seq.frames[frame].ego_to_world, shift)
        t = seq.frames[frame].timestamp
        rgbs, clss, seens = [], [], []
        for j, c in enumerate(d.cameras):
            K = seq.camera(c).K
            v = scene.render(K, c2w[j], d.width, d.height, t)
            dirs = ray_dirs(K, c2w[j], d.width, d.height)
            cls = class_map(v, moving, c2w[j][:3, 3], dirs)
            static = np.isfinite(v.depth) & (cls != CLASSES.index("vehicle moving"))
            pts = (c2w[j][:3, 3] + v.depth[..., None] * dirs)[static]
            seen = np.zeros(v.depth.shape, bool)
            seen[static] = seen_from_path(seq, d.cameras, d.train_frames, pts)
            rgbs.append(v.rgb), clss.append(cls), seens.append(seen)
        out["rgb"].append(np.stack(rgbs)), out["cls"].append(np.stack(clss)), out["seen"].append(np.stack(seens))
        out["c2w"].append(c2w)
    return {k: np.stack(v) for k, v in out.items()}   # [F, C, H, W(, 3)]


@torch.no_grad()
def renders(trainer, c2w: np.ndarray) -> np.ndarray:
    """``[F, C, H, W, 3]`` model renders of the rigs ``c2w [F, C, 4, 4]`` at the held-out frames."""
    from models.autosplat.viewsets import render_views

    return np.stack([render_views(trainer, f, c2w[k]).numpy() for k, f in enumerate(trainer.data.test_frames)])


def lane_metric(r: np.ndarray, g: np.ndarray) -> float:
    """The lane-change PSNR: mean over images of per-image PSNR (``viewsets.lane_change``)."""
    rr = torch.from_numpy(r.reshape(-1, *r.shape[-3:])).permute(0, 3, 1, 2)
    gg = torch.from_numpy(g.reshape(-1, *g.shape[-3:])).permute(0, 3, 1, 2)
    return float(psnr_metric(rr, gg).mean())


def breakdown(r: np.ndarray, gt: dict) -> dict:
    """Per class (and seen / unseen): pixel share, pooled PSNR, share of the squared error."""
    err = ((np.clip(r, 0, 1) - np.clip(gt["rgb"], 0, 1)).astype(np.float64) ** 2).sum(-1)   # [F, C, H, W]
    total, n = err.sum(), err.size
    res = {"_all": {"pixels": int(n), "psnr_pooled": float(-10 * np.log10(total / (3 * n)))}}
    for k, name in enumerate(CLASSES):
        m = gt["cls"] == k
        for tag, mm in (("", m), (" / seen", m & gt["seen"]), (" / unseen", m & ~gt["seen"])):
            if tag and name in ("sky", "vehicle moving"):
                continue
            cnt = int(mm.sum())
            e = float(err[mm].sum())
            res[name + tag] = {"pixel_share": cnt / n, "error_share": e / total,
                               "psnr": None if cnt == 0 or e == 0 else float(-10 * np.log10(e / (3 * cnt)))}
    return res


def bounds(r: np.ndarray, gt: dict) -> dict:
    """The lane-change PSNR of ``r`` and of ``r`` with each :data:`BOUNDS` class set replaced by the truth."""
    out = {"as is": lane_metric(r, gt["rgb"])}
    for name, classes in BOUNDS.items():
        if classes == ("@unseen",):
            m = ~gt["seen"] & (gt["cls"] != CLASSES.index("sky")) & (gt["cls"] != CLASSES.index("vehicle moving"))
        else:
            m = np.isin(gt["cls"], [CLASSES.index(c) for c in classes])
        out[name] = lane_metric(np.where(m[..., None], gt["rgb"], r), gt["rgb"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", default="bench/out/autosplat_views", help="autosplat_views.py's --out")
    ap.add_argument("--rows", nargs="+", default=["full", "plain"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--shift", type=float, default=3.0, help="metres left")
    ap.add_argument("--out", default="bench/out/autosplat_lane_error")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = json.loads((out / "lane_error.json").read_text()) if (out / "lane_error.json").is_file() else {}
    for seed in a.seeds:
        gt = None
        for row in a.rows:
            key = f"{row}/seed{seed}/{a.shift:g}m"
            run = Path(a.runs) / row.replace(", ", "_").replace(" ", "_") / f"seed{seed}"
            if key in results or not (run / "checkpoint.pt").is_file():
                continue
            ck = load_checkpoint(run / "checkpoint.pt", "autosplat")
            tr = trainer_from_checkpoint(ck, run / "checkpoint.pt", run, None, out_dir=out / "scratch")
            if gt is None:
                gt = ground_truth(tr, a.shift)
            r = renders(tr, gt["c2w"])
            results[key] = {"breakdown": breakdown(r, gt), "bounds": bounds(r, gt),
                            "reported_psnr": (json.loads((run / "metrics.json").read_text())["lane_change"]
                                              .get(f"{a.shift:g}m") or {}).get("psnr")}
            np.savez_compressed(out / f"{row.replace(' ', '_')}_seed{seed}_{a.shift:g}m.npz", render=r.astype(np.float16),
                                gt=gt["rgb"].astype(np.float16), cls=gt["cls"].astype(np.uint8), seen=gt["seen"])
            (out / "lane_error.json").write_text(json.dumps(results, indent=1))
            print(key, json.dumps(results[key]["bounds"]), flush=True)
    print(report(results, a.rows, a.seeds, a.shift))
    (out / "lane_error.md").write_text(report(results, a.rows, a.seeds, a.shift))


def report(results: dict, rows: list[str], seeds: list[int], shift: float) -> str:
    """Markdown tables: the class breakdown (mean over seeds) of every row, then each row's upper
    bounds (mean over seeds of the lane-change PSNR gained by replacing class pixels by the truth)."""
    def runs(r):
        return [results[f"{r}/seed{s}/{shift:g}m"] for s in seeds if f"{r}/seed{s}/{shift:g}m" in results]
    rows = [r for r in rows if runs(r)]
    if not rows:
        return "no finished runs\n"
    names = [n for n in runs(rows[0])[0]["breakdown"] if n != "_all"]
    lines = [f"Class breakdown at {shift:g} m (pixels of the generator's render of the shifted rig, held-out frames), "
             "mean over seeds: pixel share, pooled PSNR (dB) and share of the squared error per row", "",
             "| class | pixels % | " + " | ".join(f"{r}: PSNR | {r}: error %" for r in rows) + " |",
             "|---|---|" + "---|---|" * len(rows)]
    for n in names:
        got0 = [g["breakdown"][n] for g in runs(rows[0])]
        cells = [f"{100 * np.mean([g['pixel_share'] for g in got0]):.1f}"]
        for r in rows:
            got = [g["breakdown"][n] for g in runs(r)]
            ps = [g["psnr"] for g in got if g["psnr"] is not None]
            cells += [f"{np.mean(ps):.2f}" if ps else "-", f"{100 * np.mean([g['error_share'] for g in got]):.1f}"]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    bnames = list(BOUNDS)
    lines += ["", f"Upper bounds at {shift:g} m: lane-change PSNR (mean over images of per-image PSNR) as is, and what "
              "replacing the pixels of these classes by the ground truth adds (mean ± sd over seeds, dB)", "",
              "| row | seeds | as is | " + " | ".join(f"+ {n}" for n in bnames) + " |",
              "|---|---|---|" + "---|" * len(bnames)]
    for r in rows:
        got = runs(r)
        asis = [g["bounds"]["as is"] for g in got]
        cells = [f"{np.mean(asis):.2f}"]
        for n in bnames:
            d = [g["bounds"][n] - g["bounds"]["as is"] for g in got]
            cells.append(f"{np.mean(d):.2f} ± {np.std(d, ddof=1):.2f}" if len(d) > 1 else f"{d[0]:.2f}")
        lines.append(f"| {r} | {len(got)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
