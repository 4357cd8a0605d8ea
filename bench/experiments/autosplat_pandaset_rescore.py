"""AutoSplat runs on a generated PandaSet-format street scored on the generator's instance masks
(issue 36, "exact and noisy boxes side by side"; bench/notes/autosplat_moving_objects.md, "The
PandaSet-format path").

A PandaSet folder has no instance masks, so a run on it (``--data pandaset:DIR``) scores its
objects on the pixels whose ray hits a track's box (:func:`clsplat.models.autosplat.object_report.
track_masks`): a box also holds road and façade around a pedestrian, and with tracker-noise boxes the
scored pixels are the noisy box's, not the object's. The folders written by
``autosplat_pandaset.py --world busy`` come from a generated street, so the object's true pixels can
be had again: this script regenerates the street (the folder's seed and world, flat ground, as the
writer drew it) at the run's image size with one ray a pixel, takes its instance masks, and scores
each run's held-out renders against the run's own truth (the written JPEGs at the run's scale) on

* ``inst``: each truly moving track's instance pixels (the exact street's ``moving_track_ids``),
  pooled per class (car / pedestrian / other), and the parked cars' (``parked``);
* ``box``: the run's own box pixels of the tracks the run decomposed, pooled per class: what
  ``metrics.json`` reports (printed beside it as a check; ``metrics.json`` counts a pixel in two
  boxes once per track, this script once per class, so the two differ by a few hundredths).

The image column is ``metrics.json``'s ``all.psnr`` (the mean over held-out images, the figure the
issue's gaps start from; the pooled image PSNR in brackets); "image − inst" is that minus the
instance-pixel class PSNR.

Instance ids are the generator's track ids; the run's track ids are matched through the cuboids'
``uuid`` (``synthetic-<seed>-<track>``, written by :func:`clsplat.data.pandaset.write_pandaset`).

    .venv/bin/python bench/experiments/autosplat_pandaset_rescore.py RUN [RUN ...] [--json OUT.json] [--frames test train] [--tracks]
    .venv/bin/python bench/experiments/autosplat_pandaset_rescore.py --from-json OUT.json [...]

Prints one markdown row per run (held-out PSNR, dB; ``--frames train``: on the frames the run trained
on, against ``metrics.json``'s ``train`` image PSNR, so that an object gap there reads as underfitting),
then, for runs named
``PREFIX_<street>_<config>_s<seed>``, the mean (min..max) over seeds per street and config.
``--from-json`` reads the ``--json`` files of earlier calls instead of runs (tables only). Each
run's learnt pose corrections are sized too (:func:`correction_size`: on exact boxes they should be 0).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

PARTS = ("image", "inst/car", "inst/pedestrian", "inst/other", "inst/objects", "inst/parked",
         "box/car", "box/pedestrian", "box/other", "box/objects")


def _psnr(sse: float, n: int) -> float | None:
    return None if n == 0 else float(-10 * np.log10(max(sse / n, 1e-12)))


def _street(seed: int, world: str, height: int, width: int, frames: int, dt: float, cameras: tuple[str, ...]):
    """The generated street the writer drew (flat ground unless classic), at ``height x width``, one ray, no LiDAR."""
    from clsplat.data.synthetic import SyntheticConfig, draw_world, generate_sequence
    cfg = SyntheticConfig(height=height, width=width, num_frames=frames, seed=seed, dt=dt, cameras=cameras,
                          world=world, lidar=False)
    if world == "classic":   # the writer's classic street: the generator's own ground
        return generate_sequence(cfg)
    return generate_sequence(cfg, world_params=replace(draw_world(seed, world), grade=0.0, vcurv=0.0, crossfall=0.0))


def _track_speed(seq, tid: int) -> float:
    """Mean speed (m/s) of track ``tid``'s box centre over the frames that hold it."""
    pts = [(f.timestamp, b.center) for f in seq.frames for b in f.boxes if b.track_id == tid]
    if len(pts) < 2:
        return 0.0
    return float(np.linalg.norm(pts[-1][1] - pts[0][1]) / max(pts[-1][0] - pts[0][0], 1e-9))


def track_table(o: dict) -> str:
    """Markdown: one run's truly moving tracks by PSNR on their instance pixels, then the cars pooled
    by size (their pixels over the scored frames, in thirds) and by speed (0-5, 5-10, 10+ m/s)."""
    tr = o.get("tracks") or {}
    f = lambda x: "–" if x is None else f"{x:.2f}"  # noqa: E731
    rows = sorted(tr.items(), key=lambda kv: (kv[1]["psnr"] is None, kv[1]["psnr"] or 0.0))
    out = [f"{o['run']} ({o.get('frames', 'test')} frames): moving tracks by PSNR on their instance pixels",
           "| track | class | speed m/s | pixels | PSNR |", "|---|---|---|---|---|"]
    out += [f"| {t} | {v['class']} | {v['speed_mps']:.1f} | {v['pixels']} | {f(v['psnr'])} |" for t, v in rows]
    cars = [v for v in tr.values() if v["class"] == "car" and v["psnr"] is not None]
    if cars:
        def pooled(vs: list) -> str:
            n = sum(v["pixels"] for v in vs)
            sse = sum(v["pixels"] * 10 ** (-v["psnr"] / 10) for v in vs)
            return f"{-10 * np.log10(max(sse / n, 1e-12)):.2f} ({len(vs)} tracks, {n} px)"
        px = sorted(v["pixels"] for v in cars)
        cut = (px[len(px) // 3], px[2 * len(px) // 3])
        out += ["", "| cars | pooled PSNR |", "|---|---|"]
        for name, keep in (("smallest third", lambda v: v["pixels"] < cut[0]),
                           ("middle third", lambda v: cut[0] <= v["pixels"] < cut[1]),
                           ("largest third", lambda v: v["pixels"] >= cut[1]),
                           ("0-5 m/s", lambda v: v["speed_mps"] < 5), ("5-10 m/s", lambda v: 5 <= v["speed_mps"] < 10),
                           ("10+ m/s", lambda v: v["speed_mps"] >= 10)):
            vs = [v for v in cars if keep(v)]
            if vs:
                out.append(f"| {name} | {pooled(vs)} |")
    return "\n".join(out)


def analyse(run: Path, world: str, cache: dict, frames: str = "test") -> dict:
    """``{"run", "metrics": {part: psnr}, "pixels": {part: n}, "inside": share}`` of one run, on its
    held-out frames (``frames="test"``) or on its training frames (``"train"``: what the run fitted;
    a gap there is underfitting, not a failure to generalise to held-out instants)."""
    from clsplat.models.autosplat.evaluate import trainer_from_checkpoint
    from clsplat.models.autosplat.init import moving_track_ids
    from clsplat.models.autosplat.object_report import object_class, track_masks
    from clsplat.models.common.train import load_checkpoint

    m = json.loads((run / "metrics.json").read_text())
    spec = m.get("protocol", m).get("data", "")
    if not spec.startswith("pandaset:"):
        raise ValueError(f"{run}: not a run on pandaset:DIR data ({spec!r})")
    ck = load_checkpoint(run / "checkpoint.pt", "autosplat")
    tr = trainer_from_checkpoint(ck, run / "checkpoint.pt", run, None, out_dir=Path("/tmp"))
    d = tr.data
    folder = Path(spec.split(":", 1)[1])
    g = re.search(r"_s(\d+)$", folder.name)
    seed = int(g.group(1)) if g else tr.preset.seed
    f0, f1 = d.seq.frames[0].timestamp, d.seq.frames[-1].timestamp
    dt = (f1 - f0) / max(1, len(d.seq.frames) - 1)
    key = (seed, world, d.height, d.width, len(d.seq.frames), round(dt, 6), tuple(d.cameras))
    if key not in cache:
        cache[key] = _street(*key)
    gen = cache[key]
    true_moving = set(moving_track_ids(gen, tr.preset.dynamic_threshold))
    kind_true = {}
    for f in gen.frames:
        for b in f.boxes:
            c = object_class(b.label)
            kind_true[b.track_id] = c if b.track_id in true_moving else ("parked" if c == "car" else "static")
    # the run's track id -> the generator's, through the uuid
    to_gen = {}
    for f in d.seq.frames:
        for b in f.boxes:
            u = re.fullmatch(rf"synthetic-{seed}-(\d+)", str(b.uuid or ""))
            if u:
                to_gen[b.track_id] = int(u.group(1))
    run_moving = moving_track_ids(d.seq, tr.preset.dynamic_threshold)
    kind_run = {}
    for f in d.seq.frames:
        for b in f.boxes:
            kind_run[b.track_id] = object_class(b.label)
    sse = {p: 0.0 for p in PARTS}
    num = {p: 0 for p in PARTS}
    inside = [0, 0]
    track_sse: dict[int, float] = {}
    track_n: dict[int, int] = {}
    for i in (d.test_frames if frames == "test" else d.train_frames):
        with torch.no_grad():
            r = tr.render_frame(i).numpy().astype(np.float64)
        t = np.clip(d.images[i].numpy().astype(np.float64), 0, 1)
        err = ((np.clip(r, 0, 1) - t) ** 2).sum(-1)               # [C, H, W], summed over channels
        sse["image"] += err.sum()
        num["image"] += err.size * 3
        inst = np.stack([gen.frames[i].instances[c] for c in d.cameras])
        boxm = track_masks(d.seq, i, d.cameras, run_moving)
        own = {to_gen.get(tid): msk for tid, msk in boxm.items()}
        union_inst = {k: np.zeros(inst.shape, bool) for k in ("car", "pedestrian", "other", "parked")}
        for tid in np.unique(inst[inst > 0]):
            k = kind_true.get(int(tid))
            if k in union_inst:
                union_inst[k] |= inst == tid
            if int(tid) in true_moving:
                one = inst == tid
                track_sse[int(tid)] = track_sse.get(int(tid), 0.0) + float(err[one].sum())
                track_n[int(tid)] = track_n.get(int(tid), 0) + int(one.sum())
            if int(tid) in true_moving and int(tid) in own:
                inside[0] += int((own[int(tid)] & (inst == tid)).sum())
                inside[1] += int((inst == tid).sum())
            elif int(tid) in true_moving:
                inside[1] += int((inst == tid).sum())
        union_inst["objects"] = union_inst["car"] | union_inst["pedestrian"] | union_inst["other"]
        for k, msk in union_inst.items():
            sse[f"inst/{k}"] += err[msk].sum()
            num[f"inst/{k}"] += int(msk.sum()) * 3
        union_box = {k: np.zeros(inst.shape, bool) for k in ("car", "pedestrian", "other")}
        for tid, msk in boxm.items():
            union_box[kind_run[tid]] |= msk
        union_box["objects"] = union_box["car"] | union_box["pedestrian"] | union_box["other"]
        for k, msk in union_box.items():
            sse[f"box/{k}"] += err[msk].sum()
            num[f"box/{k}"] += int(msk.sum()) * 3
    pc = (m.get("objects") or {}).get("per_class", {})
    if frames == "train" and "train" not in m:
        raise ValueError(f"{run}: metrics.json has no training-frame scores (a run with --views recorded has)")
    image = m["all"]["psnr"] if frames == "test" else m["train"]["psnr"]
    return {"run": run.name, "frames": frames, "metrics": {p: _psnr(sse[p], num[p]) for p in PARTS},
            "pixels": {p: num[p] // 3 for p in PARTS}, "inside": inside[0] / max(1, inside[1]),
            "metrics_json": {"image": image, "objects": (m["all"] if frames == "test" else m["train"]).get("psnr_objects"),
                             **({c: pc[c]["psnr"] for c in ("car", "pedestrian", "other") if c in pc and pc[c]["pixels"]}
                                if frames == "test" else {})},
            "tracks": {str(t): {"class": kind_true[t], "speed_mps": _track_speed(gen, t), "pixels": track_n[t],
                                "psnr": _psnr(track_sse[t], 3 * track_n[t])} for t in sorted(track_n)},
            "moving": {"true": len(true_moving), "run": len(run_moving),
                       "run_not_true": len({to_gen.get(t) for t in run_moving} - true_moving)},
            "correction": correction_size(tr, d.test_frames if frames == "test" else d.train_frames)}


def correction_size(tr, frames: list[int]) -> dict | None:
    """The learnt per-object pose corrections' size over the decomposed tracks' boxes at ``frames``
    (interpolated at held-out frames): median and 90th percentile of the translation (m) and of the
    rotation angle (degrees). On exact boxes the right correction is zero, so this is how far the
    optimiser moved the objects off their boxes. None without pose correction or tracks."""
    m = tr.model
    if not tr.switches.pose_correction or not tr.tracks:
        return None
    t, r = [], []
    with torch.no_grad():
        for k in range(len(tr.tracks)):
            for i in frames:
                if bool(m.present[k, i]):
                    d = m.pose(k, i).double()
                    t.append(float(d[3:].norm()))
                    r.append(float(np.degrees(float(d[:3].norm()))))
    if not t:
        return None
    q = lambda v, p: float(np.percentile(v, p))  # noqa: E731
    return {"boxes": len(t), "translation_m_median": q(t, 50), "translation_m_p90": q(t, 90),
            "rotation_deg_median": q(r, 50), "rotation_deg_p90": q(r, 90)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--world", default=None, help="the world the folders were written from (default: busy, or "
                    "classic where the folder's name holds 'classic')")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here too")
    ap.add_argument("--from-json", action="store_true", help="RUNS are --json files of earlier calls: tables only")
    ap.add_argument("--frames", choices=("test", "train"), nargs="+", default=["test"],
                    help="score the held-out frames (default), the training frames (underfit or not), or both "
                         "(one street generation for both)")
    ap.add_argument("--tracks", action="store_true",
                    help="also each run's moving tracks by PSNR, and its cars pooled by size and by speed")
    a = ap.parse_args(argv)
    need = "" if a.from_json else "metrics.json"
    for r in a.runs:  # (before any street is generated: a run still training fails at once, in one line)
        if not (r / need).is_file():
            ap.error(f"runs: {r / need} not found ({'a --json file' if a.from_json else 'a finished run folder'} expected)")
    torch.set_num_threads(1)
    cache: dict = {}
    if a.from_json:
        out = [o for fj in a.runs for o in json.loads(fj.read_text())]
    else:
        try:
            out = [analyse(r, a.world or ("classic" if "classic" in r.name else "busy"), cache, fr)
                   for fr in dict.fromkeys(a.frames) for r in a.runs]
        except ValueError as e:
            sys.exit(f"autosplat_pandaset_rescore.py: {e}")
    f = lambda x: "–" if x is None else f"{x:.2f}"  # noqa: E731
    print("| run | image (pooled) | instance px: car / pedestrian / other / all moving / parked cars | image − inst car / ped "
          "| box px (metrics.json's): car / pedestrian / other / all | metrics.json car / ped / other / objects "
          "| moving tracks: true / run's (run's not truly moving) | instance px inside own box |")
    print("|---" * 8 + "|")
    for o in out:
        p, j, mv = o["metrics"], o["metrics_json"], o["moving"]
        gap = lambda k: "–" if p[k] is None else f"{j['image'] - p[k]:.2f}"  # noqa: E731
        print(f"| {_label(o)} | {f(j['image'])} ({f(p['image'])}) | " + " / ".join(f(p[f'inst/{k}']) for k in ("car", "pedestrian", "other", "objects", "parked"))
              + f" | {gap('inst/car')} / {gap('inst/pedestrian')} | "
              + " / ".join(f(p[f'box/{k}']) for k in ("car", "pedestrian", "other", "objects"))
              + " | " + " / ".join(f(j.get(k)) for k in ("car", "pedestrian", "other", "objects"))
              + f" | {mv['true']} / {mv['run']} ({mv['run_not_true']}) | {o['inside']:.3f} |")
    for o in out:
        c = o.get("correction")
        if c:
            print(f"{_label(o)}: pose corrections over {c['boxes']} boxes: translation median {c['translation_m_median']:.3f} m "
                  f"(p90 {c['translation_m_p90']:.3f}), rotation median {c['rotation_deg_median']:.2f} deg "
                  f"(p90 {c['rotation_deg_p90']:.2f})")
    if a.tracks:
        for o in out:
            print("\n" + track_table(o))
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    _seeds(out)


def _label(o: dict) -> str:
    """A run's name, with ``[train]`` when it was scored on its training frames."""
    return o["run"] + (" [train]" if o.get("frames") == "train" else "")


def _seeds(out: list[dict]) -> None:
    """Runs named ``PREFIX_<street>_<config>_s<seed>`` grouped by street and config: mean (min..max).
    The street is the folder's kind, the first name part that starts with ``p`` (``pbusy``,
    ``pclassicnoisy``, ...), so the prefix may hold parts of its own (``i36s14_test_pbusy_cl_s3``)."""
    import statistics
    name = re.compile(r"^[^_]+(?:_[^p_][^_]*)*_(?P<street>p[^_]+)_(?P<config>.+)_s(?P<seed>\d+)$")
    groups: dict[tuple[str, str], list[dict]] = {}
    for o in out:
        g = name.match(o["run"])
        if g:
            cfg = g["config"] + (" [train]" if o.get("frames") == "train" else "")
            groups.setdefault((g["street"], cfg), []).append(o)

    def agg(v: list) -> str:
        v = [x for x in v if x is not None]
        return "–" if not v else f"{statistics.mean(v):.2f} ({min(v):.2f}..{max(v):.2f})" if len(v) > 1 else f"{v[0]:.2f}"

    cols = {"image": lambda o: o["metrics_json"]["image"]}
    for k in ("car", "pedestrian", "other", "objects", "parked"):
        cols[f"inst {k}"] = lambda o, k=k: o["metrics"][f"inst/{k}"]
    for k in ("car", "pedestrian", "objects"):
        cols[f"image − inst {k}"] = lambda o, k=k: (None if o["metrics"][f"inst/{k}"] is None
                                                   else o["metrics_json"]["image"] - o["metrics"][f"inst/{k}"])
    print("\n| street | config | runs | " + " | ".join(cols) + " |")
    print("|---" * (3 + len(cols)) + "|")
    for (street, cfg), rs in sorted(groups.items()):
        print(f"| {street} | {cfg} | {len(rs)} | " + " | ".join(agg([f(o) for o in rs]) for f in cols.values()) + " |")


if __name__ == "__main__":
    sys.exit(main())
