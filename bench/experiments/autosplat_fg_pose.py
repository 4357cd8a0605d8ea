"""Issue 36 (tracker noise): tables of the pose corrections trained in the foreground stage
(``--set fg_pose_correction=True``) against the same runs without (bench/notes/autosplat_moving_objects.md,
"Pose corrections trained in the foreground stage").

Reads AutoSplat run folders named ``PREFIX_<street>_<config>_s<seed>`` (e.g. ``i36s10_busynoisy_fgpc_s0``)
and prints, per run, the held-out image PSNR, the per-class object PSNR of ``metrics.json``'s
``objects`` section, the ``pose_correction`` section (the boxes' centre error before / after the
learnt correction, metres, and yaw, degrees; training and held-out frames; only on streets with
tracker noise) and the command's CPU seconds (``<times>/<run>.time``, ``/usr/bin/time -v``); then,
per street and config, each seed paired against ``--base`` (mean, min..max), and the adoption rule
written before the runs (the note): noisy-box cars gain >= 0.5 dB on every busy-noisy seed (overtake-
noisy: >= 0.5 on average, no seed negative), image >= -0.1 dB on average on every street, exact-box
cars >= -0.1 dB on average.

    .venv/bin/python bench/experiments/autosplat_fg_pose.py /work/runs/i36s10_*_s[012] --times /work/runs/i36s10_logs
    .venv/bin/python bench/experiments/autosplat_fg_pose.py /work/runs/i36s10_busynoisy_*_s0 --spread

``--spread`` adds, from each run's checkpoint, the part of the box error an object set cannot absorb
(its frame-to-frame variation, :func:`spread`): the ``pose_correction`` section's absolute error
counts a constant offset that the object's Gaussians may have taken up.
"""
from __future__ import annotations

import argparse
import json
import re
import statistics
from pathlib import Path

NAME = re.compile(r"^[^_]+_(?P<street>[^_]+)_(?P<config>.+)_s(?P<seed>\d+)$")
CLASSES = ("car", "pedestrian", "other")


def _cpu(run: Path, times: Path | None) -> float | None:
    f = None if times is None else times / f"{run.name}.time"
    if f is None or not f.is_file():
        return None
    text = f.read_text()
    return sum(float(re.search(rf"{k} time \(seconds\): ([0-9.]+)", text).group(1)) for k in ("User", "System"))


def load(run: Path, times: Path | None) -> dict:
    """One run's figures: ``image``, ``car`` / ``pedestrian`` / ``other`` (None without pixels), the
    pose section's ``train`` / ``held_out`` blocks (None without tracker noise), ``cpu``."""
    m = json.loads((run / "metrics.json").read_text())
    pc = (m.get("objects") or {}).get("per_class", {})
    out = {"image": m["all"]["psnr"], "cpu": _cpu(run, times), "pose": m.get("pose_correction")}
    out.update({c: pc[c]["psnr"] if c in pc and pc[c]["pixels"] else None for c in CLASSES})
    return out


def spread(run: Path) -> dict | None:
    """The boxes' error that no object set can absorb, from the run's checkpoint (rebuilt on its
    recorded data): per decomposed track and training frame, the error transform from the placed
    box to the exact one, ``Err_f = E_f^-1 T_f exp(delta_f)``; a constant ``Err`` over a track's
    frames is a gauge its object set absorbs (its Gaussians shifted and turned once), so what
    counts is each frame's deviation from the track's mean: the x/y distance of the track's
    Gaussians' centroid mapped by ``Err_f`` from its mean over the frames (metres), and ``Err_f``'s
    yaw from its mean (degrees); with ``delta`` = 0 (``injected``) and with the learnt one
    (``left``); and the centre's deviation weighted by each box's pixels over the cameras (what the
    images see: far and small boxes count little). None without tracker noise."""
    import numpy as np
    import torch
    from clsplat.models.autosplat.evaluate import trainer_from_checkpoint
    from clsplat.models.autosplat.fusion import axis_angle_to_quat
    from clsplat.models.common.geometry import quat_to_matrix

    ck = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)
    tr = trainer_from_checkpoint(ck, run / "checkpoint.pt", run, None)
    d, m = tr.data, tr.model
    exact = d.seq.metadata.get("exact_boxes")
    if exact is None or not tr.tracks:
        return None
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    from clsplat.models.autosplat.objects import track_box_pixels
    pixels = track_box_pixels(d.seq, [t.track_id for t in tr.tracks], list(range(len(d.seq.frames))),
                              d.cameras).sum(-1)
    out = {"injected": ([], [], []), "left": ([], [], [])}
    with torch.no_grad():
        for k, t in enumerate(tr.tracks):
            frames = [i for i in d.train_frames if bool(m.present[k, i]) and t.track_id in exact[i]]
            if len(frames) < 2 or len(m.objects[k]) == 0:
                continue
            c = m.objects[k].means.double().mean(0).numpy()
            for key in out:
                pts, yaws = [], []
                for i in frames:
                    T = np.eye(4)
                    T[:3, :3] = m.track_R[k, i].double().numpy()
                    T[:3, 3] = m.track_t[k, i].double().numpy()
                    if key == "left" and tr.switches.pose_correction:
                        dl = m.pose(k, i).double()
                        D = np.eye(4)
                        D[:3, :3] = quat_to_matrix(axis_angle_to_quat(dl[:3])).numpy()
                        D[:3, 3] = dl[3:].numpy()
                        T = T @ D
                    err = np.linalg.inv(exact[i][t.track_id].box_to_world) @ T
                    pts.append(err[:3, :3] @ c + err[:3, 3])
                    yaws.append(np.arctan2(err[1, 0], err[0, 0]))
                pts, yaws = np.asarray(pts), np.asarray(yaws)
                mean_yaw = np.arctan2(np.sin(yaws).mean(), np.cos(yaws).mean())
                out[key][0].extend(np.linalg.norm((pts - pts.mean(0))[:, :2], axis=1).tolist())
                out[key][1].extend(np.degrees(np.abs(wrap(yaws - mean_yaw))).tolist())
                out[key][2].extend(float(pixels[k, i]) for i in frames)
    return {key: (float(np.mean(a)), float(np.mean(b)), len(a), float(np.average(a, weights=w)))
            for key, (a, b, w) in out.items()}


def _f(x, fmt: str = ".2f") -> str:
    return "–" if x is None else format(x, fmt)


def _agg(v: list) -> str:
    v = [x for x in v if x is not None]
    if not v:
        return "–"
    return f"{statistics.mean(v):+.2f} ({min(v):+.2f}..{max(v):+.2f})" if len(v) > 1 else f"{v[0]:+.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--times", type=Path, default=None, help="folder of <run>.time files (/usr/bin/time -v)")
    ap.add_argument("--base", default="base")
    ap.add_argument("--spread", action="store_true",
                    help="also the boxes' frame-to-frame error before / after the correction (from each checkpoint)")
    a = ap.parse_args()
    if a.spread:
        print("| run | frame-to-frame centre error m: injected → left | yaw °: injected → left | "
              "centre, by box pixels | boxes |")
        print("|---" * 5 + "|")
        for r in a.runs:
            if (r / "checkpoint.pt").is_file() and (sp := spread(r)) is not None:
                (ci, yi, n, wi), (cl, yl, _, wl) = sp["injected"], sp["left"]
                print(f"| {r.name} | {ci:.3f} → {cl:.3f} | {yi:.2f} → {yl:.2f} | {wi:.3f} → {wl:.3f} | {n} |",
                      flush=True)
        print()
    runs: dict[str, dict[str, dict[int, dict]]] = {}
    for r in a.runs:
        g = NAME.match(r.name)
        if g and (r / "metrics.json").is_file():
            runs.setdefault(g["street"], {}).setdefault(g["config"], {})[int(g["seed"])] = load(r, a.times)

    print("| street | config | seed | image | car | pedestrian | other | centre error train m: injected → left "
          "| held-out | yaw train °: injected → left | CPU s |")
    print("|---" * 10 + "|")
    for street, cfgs in sorted(runs.items()):
        for cfg, seeds in sorted(cfgs.items()):
            for s, r in sorted(seeds.items()):
                p = r["pose"] or {}
                tr, ho = p.get("train") or {}, p.get("held_out") or {}
                print(f"| {street} | {cfg} | {s} | {r['image']:.2f} | " + " | ".join(_f(r[c]) for c in CLASSES)
                      + f" | {_f(tr.get('injected_m'), '.3f')} → {_f(tr.get('residual_m'), '.3f')}"
                      f" | {_f(ho.get('injected_m'), '.3f')} → {_f(ho.get('residual_m'), '.3f')}"
                      f" | {_f(tr.get('yaw_injected_deg'))} → {_f(tr.get('yaw_residual_deg'))}"
                      f" | {_f(r['cpu'], '.0f')} |")

    print(f"\n| street | config − {a.base} | seeds | image | car | pedestrian | other | car per seed "
          "| CPU ratio per seed |")
    print("|---" * 9 + "|")
    verdict: list[str] = []
    for street, cfgs in sorted(runs.items()):
        base = cfgs.get(a.base, {})
        for cfg, seeds in sorted(cfgs.items()):
            common = sorted(set(seeds) & set(base))
            if cfg == a.base or not common:
                continue
            d = {k: [None if seeds[s][k] is None or base[s][k] is None else seeds[s][k] - base[s][k] for s in common]
                 for k in ("image", *CLASSES)}
            cpu = " / ".join("–" if seeds[s]["cpu"] is None or base[s]["cpu"] is None
                             else f"{seeds[s]['cpu'] / base[s]['cpu']:.2f}" for s in common)
            print(f"| {street} | {cfg} − {a.base} | {','.join(map(str, common))} | "
                  + " | ".join(_agg(d[k]) for k in ("image", *CLASSES))
                  + f" | {' / '.join(_f(x, '+.2f') for x in d['car'])} | {cpu} |")
            cars = [x for x in d["car"] if x is not None]
            img = statistics.mean(d["image"])
            if street == "busynoisy":
                verdict.append(f"{street} {cfg}: cars >= +0.5 on every seed: {bool(cars) and min(cars) >= 0.5}")
            elif street == "overtakenoisy":
                verdict.append(f"{street} {cfg}: cars mean >= +0.5 and none < 0: "
                               f"{bool(cars) and statistics.mean(cars) >= 0.5 and min(cars) >= 0}")
            elif cars:
                verdict.append(f"{street} {cfg}: exact-box cars mean >= -0.1: {statistics.mean(cars) >= -0.1}")
            verdict.append(f"{street} {cfg}: image mean >= -0.1: {img >= -0.1}")
    print("\nthe rule (note, written before the runs):")
    for v in verdict:
        print("  " + v)


if __name__ == "__main__":
    main()
