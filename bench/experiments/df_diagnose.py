"""DrivingForward depth-collapse diagnosis: which loss term moves the depth scale, and where to.

Two probes on fresh synthetic training streets (``bench/notes/drivingforward_training.md``, "Why the
depth collapses"):

* ``landscape``: every loss term with the depth replaced by the generator's true depth times a
  factor (0.25 .. 8), with the true camera motion and with the pose network's; the Gaussian and
  pose networks as initialised (seeded).
* ``grads CHECKPOINT|init``: per term, the weighted gradient of the term with respect to the
  logarithm of the predicted depth, summed over pixels (negative: a descent step makes the depth
  farther), with the temporal terms attached as after any warm-up.
* ``motion CHECKPOINT|init``: the temporal terms and the render error with the network's own depth
  and the true camera motion scaled by 0 .. 3, and per street the pose network's t -> t+1
  translation beside the true one and the gradient of the total loss with respect to it.

A checkpoint's weights are loaded into ``--preset``'s networks as they are (its optimisation
fields, such as a probe's learning rate, need not match).

    .venv/bin/python bench/experiments/df_diagnose.py landscape --scenes 2
    .venv/bin/python bench/experiments/df_diagnose.py landscape --scenes 2 --set supersample=3 --factors 0.5 0.8 1 1.25 2
    .venv/bin/python bench/experiments/df_diagnose.py grads bench/out/df_small/checkpoint.pt --scenes 3
    .venv/bin/python bench/experiments/df_diagnose.py motion bench/out/df_small/checkpoint.pt --scenes 3
"""
from __future__ import annotations

import argparse

import torch

FACTORS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
TERMS = ("reproj", "spatial", "spatio_temporal", "smooth", "render")


def _setup(preset_name: str, checkpoint: str | None, sets: list[str] | None = None):
    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import apply_sets, get_preset
    from clsplat.models.drivingforward.model import DrivingForward

    torch.manual_seed(0)
    torch.set_num_threads(1)
    preset = apply_sets(get_preset("drivingforward", preset_name), sets)
    model = DrivingForward(preset)
    if checkpoint:
        from clsplat.models.common.train import load_checkpoint
        model.load_state_dict(load_checkpoint(checkpoint, "drivingforward")["model"])
    return model, preset, parse_data("synthetic")


def landscape(preset_name: str, scenes: int, sets: list[str] | None = None,
              factors: tuple[float, ...] = FACTORS) -> dict:
    """Mean of each term over ``scenes`` streets for (pose in {true, net}, factor); ``sets``:
    ``FIELD=VALUE`` preset changes (e.g. ``supersample=3``, ``height=128``)."""
    from clsplat.models.drivingforward.data import load_triplet

    model, p, src = _setup(preset_name, None, sets)
    depth_fwd, pose_fwd = model.depth_net.forward, model.pose_net.forward
    rows: dict = {}
    try:
        for idx in range(scenes):
            s = load_triplet(src, idx, p, "train")
            true_depth = s["depths"][1].unsqueeze(1).float().clamp(max=p.max_depth * 1.5)
            V = s["viewmats"][:, 0].float()
            true_motion = [V[1] @ torch.linalg.inv(V[0]), V[2] @ torch.linalg.inv(V[1])]
            for pose in ("true", "net"):
                for f in factors:
                    def depth_net(*a, f=f, **k):
                        d = depth_fwd(*a, **k)
                        d["depth"] = true_depth * f
                        return d
                    calls = iter(true_motion)   # training_losses asks for t-1 -> t, then t -> t+1
                    model.depth_net.forward = depth_net
                    model.pose_net.forward = (lambda *a, **k: next(calls)) if pose == "true" else pose_fwd
                    with torch.no_grad():
                        t = model.training_losses(s["images"], s["images"], s["Ks"], s["cam_to_ego"])
                    for k in TERMS + ("mse", "loss"):
                        rows.setdefault((pose, f), {}).setdefault(k, []).append(float(t[k]) if k in t else float("nan"))
    finally:
        model.depth_net.forward, model.pose_net.forward = depth_fwd, pose_fwd
    return {key: {k: sum(v) / len(v) for k, v in d.items()} for key, d in rows.items()}


def grads(checkpoint: str | None, preset_name: str, scenes: int) -> list[dict]:
    """Per street: median predicted depth and, per term, sum(d(w L)/d depth * depth)."""
    from clsplat.models.drivingforward.data import load_triplet

    model, p, src = _setup(preset_name, checkpoint)
    w = {"reproj": 1.0, "spatial": p.w_spatial, "spatio_temporal": p.w_spatio_temporal,
         "smooth": p.w_smooth, "render": p.w_render}
    depth_fwd = model.depth_net.forward
    out = []
    try:
        for idx in range(scenes):
            s = load_triplet(src, 1000 + idx, p, "train")
            box = {}

            def depth_net(*a, **k):
                d = depth_fwd(*a, **k)
                d["depth"].retain_grad()
                box["d"] = d["depth"]
                return d
            model.depth_net.forward = depth_net
            t = model.training_losses(s["images"], s["images"], s["Ks"], s["cam_to_ego"])
            row = {"median_depth": float(box["d"].median())}
            for k in TERMS:
                model.zero_grad()
                box["d"].grad = None
                if k in t:                      # a term of weight 0 is not computed: no gradient
                    (w[k] * t[k]).backward(retain_graph=True)
                g = box["d"].grad
                row[k] = 0.0 if g is None else float((g * box["d"]).sum())
            out.append(row)
    finally:
        model.depth_net.forward = depth_fwd
    return out


MOTION_SCALES = (0.0, 0.1, 0.25, 0.5, 1.0, 2.0, 3.0)


def motion(checkpoint: str | None, preset_name: str, scenes: int) -> tuple[dict, list[dict]]:
    """(mean terms per motion scale, per street the predicted and true translation and dL/dt)."""
    from clsplat.models.drivingforward import pose as pose_module
    from clsplat.models.drivingforward.data import load_triplet

    model, p, src = _setup(preset_name, checkpoint)
    pose_fwd, se3_exp = model.pose_net.forward, pose_module.se3_exp
    scan: dict = {}
    streets = []
    try:
        for idx in range(scenes):
            s = load_triplet(src, 1000 + idx, p, "train")
            V = s["viewmats"][:, 0].float()
            true = [V[1] @ torch.linalg.inv(V[0]), V[2] @ torch.linalg.inv(V[1])]
            for a in MOTION_SCALES:
                scaled = []
                for T in true:
                    T = T.clone()
                    T[:3, 3] *= a
                    scaled.append(T)
                calls = iter(scaled)
                model.pose_net.forward = lambda *x, **k: next(calls)
                with torch.no_grad():
                    t = model.training_losses(s["images"], s["images"], s["Ks"], s["cam_to_ego"])
                for k in ("reproj", "spatio_temporal", "mse"):
                    scan.setdefault(a, {}).setdefault(k, []).append(float(t[k]) if k in t else float("nan"))
            model.pose_net.forward = pose_fwd
            outs = []

            def hooked(rot, trans):
                trans.retain_grad()
                outs.append(trans)
                return se3_exp(rot, trans)
            pose_module.se3_exp = hooked
            t = model.training_losses(s["images"], s["images"], s["Ks"], s["cam_to_ego"])
            pose_module.se3_exp = se3_exp
            model.zero_grad()
            t["loss"].backward()
            nxt = outs[1]                       # training_losses asks for t-1 -> t, then t -> t+1
            streets.append({"true": true[1][:3, 3].tolist(), "pred": nxt.detach().tolist(),
                            "dL_dt": nxt.grad.tolist()})
    finally:
        model.pose_net.forward, pose_module.se3_exp = pose_fwd, se3_exp
    return {a: {k: sum(v) / len(v) for k, v in d.items()} for a, d in scan.items()}, streets


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    a1 = sub.add_parser("landscape")
    a1.add_argument("--preset", default="small")
    a1.add_argument("--scenes", type=int, default=2)
    a1.add_argument("--set", action="append", default=None, metavar="FIELD=VALUE", help="preset change (repeatable)")
    a1.add_argument("--factors", type=float, nargs="+", default=None, help=f"depth factors (default {FACTORS})")
    a2 = sub.add_parser("grads")
    a2.add_argument("checkpoint", help="a DrivingForward checkpoint, or 'init' for the seeded initialisation")
    a2.add_argument("--preset", default="small", help="with 'init'")
    a2.add_argument("--scenes", type=int, default=3)
    a3 = sub.add_parser("motion")
    a3.add_argument("checkpoint", help="a DrivingForward checkpoint, or 'init'")
    a3.add_argument("--preset", default="small")
    a3.add_argument("--scenes", type=int, default=3)
    a = p.parse_args(argv)
    if a.cmd == "landscape":
        res = landscape(a.preset, a.scenes, a.set, tuple(a.factors) if a.factors else FACTORS)
        keys = TERMS[:-1] + ("mse", "loss")
        print("| pose | depth x | " + " | ".join(keys) + " |")
        print("|---|---|" + "---|" * len(keys))
        for (pose, f), r in res.items():
            print(f"| {pose} | {f} | " + " | ".join(f"{r[k]:.4f}" for k in keys) + " |")
    elif a.cmd == "motion":
        scan, streets = motion(None if a.checkpoint == "init" else a.checkpoint, a.preset, a.scenes)
        print("| true motion x | reproj | spatio_temporal | mse |")
        print("|---|---|---|---|")
        for f, r in scan.items():
            print(f"| {f} | {r['reproj']:.4f} | {r['spatio_temporal']:.4f} | {r['mse']:.4f} |")
        print("\n| street | true t -> t+1 (m) | predicted (m) | dL/dt |")
        print("|---|---|---|---|")
        for i, r in enumerate(streets):
            fmt = lambda v, f: "(" + ", ".join(format(x, f) for x in v) + ")"  # noqa: E731
            print(f"| {i} | {fmt(r['true'], '.3f')} | {fmt(r['pred'], '.4f')} | {fmt(r['dL_dt'], '+.1e')} |")
    else:
        rows = grads(None if a.checkpoint == "init" else a.checkpoint, a.preset, a.scenes)
        print("| street | median depth (m) | " + " | ".join(TERMS) + " |")
        print("|---|---|" + "---|" * len(TERMS))
        for i, r in enumerate(rows + [{k: sum(x[k] for x in rows) / len(rows) for k in rows[0]}]):
            name = str(i) if i < len(rows) else "mean"
            print(f"| {name} | {r['median_depth']:.1f} | " + " | ".join(f"{r[k]:+.2e}" for k in TERMS) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
