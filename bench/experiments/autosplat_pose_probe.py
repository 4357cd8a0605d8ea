"""Issue 36 (tracker noise): can the photometric loss find a box error at all? A probe on a trained
AutoSplat run: its model is given the tracker-noise boxes of the same street (same images, the
generator's noisy boxes: ``synthetic:busy`` -> ``synthetic:busy-noisy``), every parameter is frozen
but the per-object, per-frame pose corrections (zeroed), and these alone are fitted with Adam on the
fusion stage's loss over the training frames (one frame, every camera, a step; frames drawn with a
seeded generator). Printed every ``--every`` steps: the boxes' centre error (x/y, metres) and yaw
error (degrees) after the correction, mean over the decomposed tracks' boxes on the training
frames, against the exact boxes, absolute and frame-to-frame (each track's mean error removed, the
part an object set cannot absorb), and the loss.

On a run trained with exact boxes the objects are sharp and sit in the exact boxes' frame, so the
absolute error is what is left to find; on a run trained on the noisy boxes themselves (``--data``
not changed) the objects are the blurred average the foreground stage fits, and the probe asks
whether the poses can be found against that.

    .venv/bin/python bench/experiments/autosplat_pose_probe.py /work/runs/i36s10_busy_base_s0 \\
        --noisy synthetic:busy-noisy --steps 150 --lr 2e-3 1e-2
    .venv/bin/python bench/experiments/autosplat_pose_probe.py RUN [--noisy DATA] --steps 0 --landscape

``--landscape``: the loss summed over the training frames with the boxes moved from the noisy towards
the exact ones, and the full-batch gradient on the corrections at the noisy boxes against the needed
correction (:func:`landscape`).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch


def box_errors(model, tracks, frames, exact_of, pixels=None) -> tuple[float, ...]:
    """(absolute centre m, absolute yaw °, frame-to-frame centre m, frame-to-frame yaw °, boxes, and
    with ``pixels`` (``[T, F]`` box pixels over the cameras) the absolute and frame-to-frame centre
    errors weighted by them) of the placed boxes ``T_f exp(delta_f)`` against
    ``exact_of(track_id, frame)`` (a 4 x 4 box-to-world)."""
    from clsplat.models.autosplat.fusion import axis_angle_to_quat
    from clsplat.models.common.geometry import quat_to_matrix

    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    ac, ay, fc, fy, w = [], [], [], [], []
    with torch.no_grad():
        for k, t in enumerate(tracks):
            fr = [i for i in frames if bool(model.present[k, i]) and exact_of(t.track_id, i) is not None]
            if not fr:
                continue
            c = model.objects[k].means.double().mean(0).numpy() if len(model.objects[k]) else np.zeros(3)
            pts, yaws = [], []
            for i in fr:
                T = np.eye(4)
                T[:3, :3] = model.track_R[k, i].double().numpy()
                T[:3, 3] = model.track_t[k, i].double().numpy()
                dl = model.pose(k, i).double()
                D = np.eye(4)
                D[:3, :3] = quat_to_matrix(axis_angle_to_quat(dl[:3])).numpy()
                D[:3, 3] = dl[3:].numpy()
                err = np.linalg.inv(exact_of(t.track_id, i)) @ (T @ D)
                pts.append(err[:3, :3] @ c + err[:3, 3] - c)
                yaws.append(np.arctan2(err[1, 0], err[0, 0]))
            pts, yaws = np.asarray(pts), np.asarray(yaws)
            ac += np.linalg.norm(pts[:, :2], axis=1).tolist()
            ay += np.degrees(np.abs(wrap(yaws))).tolist()
            mean_yaw = np.arctan2(np.sin(yaws).mean(), np.cos(yaws).mean())
            fc += np.linalg.norm((pts - pts.mean(0))[:, :2], axis=1).tolist()
            fy += np.degrees(np.abs(wrap(yaws - mean_yaw))).tolist()
            w += [0.0 if pixels is None else float(pixels[k, i]) for i in fr]
    out = (float(np.mean(ac)), float(np.mean(ay)), float(np.mean(fc)), float(np.mean(fy)), len(ac))
    if pixels is None or sum(w) == 0:
        return out
    return out + (float(np.average(ac, weights=w)), float(np.average(fc, weights=w)))


def landscape(tr, exact_of, alphas=(0.0, 0.25, 0.5, 0.75, 1.0)) -> None:
    """With every parameter frozen and the corrections at 0: the fusion loss summed over the
    training frames with the boxes moved a share ``alpha`` of the way from the noisy to the exact
    ones (translation linear, rotation along the geodesic); and at ``alpha`` 0 the full-batch
    gradient on the corrections against the needed ones (object frame, ``T_noisy^-1 E``):
    Pearson correlation of minus the gradient with the needed x / y translation and with the yaw."""
    from clsplat.models.autosplat.fusion import axis_angle_to_quat
    from clsplat.models.autosplat.loss import stage_loss
    from clsplat.models.common.geometry import matrix_to_quat, quat_to_matrix

    m, d, p = tr.model, tr.data, tr.preset
    R0, t0, q0 = m.track_R.clone(), m.track_t.clone(), m.track_q.clone()
    need_t, need_yaw, rel_aa = [], [], torch.zeros(*R0.shape[:2], 3)
    for k, t in enumerate(tr.tracks):
        for i in range(R0.shape[1]):
            E = exact_of(t.track_id, i)
            if E is None or not bool(m.present[k, i]):
                continue
            E = torch.from_numpy(E).float()
            rel = R0[k, i].T @ E[:3, :3]
            qr = matrix_to_quat(rel[None])[0]
            qr = qr * torch.sign(qr[0]) if qr[0] != 0 else qr
            ang = 2 * torch.atan2(qr[1:].norm(), qr[0])
            rel_aa[k, i] = qr[1:] / qr[1:].norm().clamp_min(1e-12) * ang
            if i in d.train_frames:
                need_t.append((k, i, (R0[k, i].T @ (E[:3, 3] - t0[k, i]))[:2]))
                need_yaw.append(float(torch.atan2(rel[1, 0], rel[0, 0])))
    dt = torch.zeros_like(t0)
    for k, t in enumerate(tr.tracks):
        for i in range(R0.shape[1]):
            E = exact_of(t.track_id, i)
            if E is not None and bool(m.present[k, i]):
                dt[k, i] = torch.from_numpy(E[:3, 3]).float() - t0[k, i]
    print("| alpha (share of the way to the exact boxes) | loss summed over the training frames |")
    print("|---|---|")
    with torch.no_grad():
        for a in alphas:
            Ra = R0 @ quat_to_matrix(axis_angle_to_quat(a * rel_aa))
            m.track_R.copy_(Ra)
            m.track_t.copy_(t0 + a * dt)
            m.track_q.copy_(matrix_to_quat(Ra.reshape(-1, 3, 3)).reshape(q0.shape))
            tot = sum(float(stage_loss(m, tr.renderer, d, p, tr.switches, "fusion", f, len(tr.tracks))["loss"])
                      for f in d.train_frames)
            tr.renderer.drain()
            print(f"| {a:.2f} | {tot:.5f} |", flush=True)
        m.track_R.copy_(R0), m.track_t.copy_(t0), m.track_q.copy_(q0)
    m.pose.delta.grad = None
    for f in d.train_frames:
        stage_loss(m, tr.renderer, d, p, tr.switches, "fusion", f, len(tr.tracks))["loss"].backward()
        tr.renderer.drain()
    g = -m.pose.delta.grad
    gt = torch.stack([g[k, i, 3:5] for k, i, _ in need_t]).reshape(-1).numpy()
    nt = torch.stack([n for _, _, n in need_t]).reshape(-1).numpy()
    gy = np.array([float(g[k, i, 2]) for k, i, _ in need_t])
    print(f"full-batch -gradient vs needed correction: translation x/y correlation "
          f"{np.corrcoef(gt, nt)[0, 1]:.3f} ({len(nt) // 2} boxes), "
          f"yaw correlation {np.corrcoef(gy, need_yaw)[0, 1]:.3f}; "
          f"boxes with a zero gradient {int((np.abs(gt.reshape(-1, 2)).sum(1) == 0).sum())}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a finished AutoSplat run folder (checkpoint.pt, metrics.json)")
    ap.add_argument("--noisy", default=None,
                    help="--data whose boxes replace the run's (same street and seed); default: the run's own boxes")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--lr", type=float, nargs="+", default=[2e-3])
    ap.add_argument("--every", type=int, default=25)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--translation-only", action="store_true",
                    help="fit the corrections' translation only (their rotation held at 0)")
    ap.add_argument("--landscape", action="store_true",
                    help="also the loss from the noisy to the exact boxes and the full-batch gradient's direction")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    from clsplat.models.autosplat.data import load_sequence, prepare_data
    from clsplat.models.autosplat.evaluate import trainer_from_checkpoint
    from clsplat.models.autosplat.loss import stage_loss
    from clsplat.models.autosplat.model import AutoSplatModel

    ck_path = a.run / "checkpoint.pt"
    ck = torch.load(ck_path, map_location="cpu", weights_only=False)
    proto = json.loads((a.run / "metrics.json").read_text())["protocol"]
    spec = a.noisy or proto["data"]
    for lr in a.lr:
        tr = trainer_from_checkpoint(ck, ck_path, a.run, None)
        p, m, d = tr.preset, tr.model, tr.data
        frames = proto.get("frames")
        seq = load_sequence(spec, d.cameras, None if frames is None else tuple(frames), proto.get("scale") or p.scale,
                            seed=p.seed)
        exact = seq.metadata.get("exact_boxes")
        if exact is None:
            raise ValueError(f"--noisy: {spec!r} carries no tracker noise (no exact boxes to score against)")
        dn = prepare_data(seq, d.cameras, p.holdout, p.dynamic_threshold, p.road_classes)
        if dn.train_frames != d.train_frames or not all(torch.equal(dn.images[i], d.images[i]) for i in d.train_frames):
            raise ValueError(f"--noisy: {spec!r} is not the run's street (other frames or images)")
        mn = AutoSplatModel(seq, tr.tracks, np.asarray(m.pose.trained), p.sh_degree, tr.switches, p.residual_width,
                            p.time_frequencies, p.position_frequencies)
        with torch.no_grad():
            for b in ("track_R", "track_t", "track_q", "present"):
                getattr(m, b).copy_(getattr(mn, b))
            m.pose.delta.zero_()
        for q in m.parameters():
            q.requires_grad_(False)
        m.pose.delta.requires_grad_(True)
        exact_of = lambda tid, i: None if tid not in exact[i] else exact[i][tid].box_to_world  # noqa: E731
        if a.landscape:
            print(f"\n{a.run.name} with the boxes of {spec}: the loss towards the exact boxes")
            landscape(tr, exact_of)
            if a.steps == 0:
                break
        opt = torch.optim.Adam([m.pose.delta], lr=lr, eps=1e-15)
        from clsplat.models.autosplat.objects import track_box_pixels
        pixels = np.zeros(m.present.shape)
        pixels[:, :] = track_box_pixels(seq, [t.track_id for t in tr.tracks], list(range(len(seq.frames))),
                                        d.cameras).sum(-1)
        rng = np.random.default_rng([p.seed, 99])
        what = " (translation)" if a.translation_only else ""
        print(f"\n{a.run.name} with the boxes of {spec}, pose corrections only{what}, Adam lr {lr}")
        print("| step | centre m | yaw ° | frame-to-frame centre m | frame-to-frame yaw ° | centre m, by box pixels "
              "| frame-to-frame centre m, by box pixels | loss (mean since last) | s |")
        print("|---" * 9 + "|")
        t0, losses = time.perf_counter(), []

        def row(step: int, loss: str) -> None:
            e = box_errors(m, tr.tracks, d.train_frames, exact_of, pixels)
            print(f"| {step} | {e[0]:.3f} | {e[1]:.2f} | {e[2]:.3f} | {e[3]:.2f} | {e[5]:.3f} | {e[6]:.3f} | {loss} | "
                  f"{time.perf_counter() - t0:.0f} |", flush=True)

        row(0, "–")
        for step in range(1, a.steps + 1):
            frame = d.train_frames[int(rng.integers(len(d.train_frames)))]
            opt.zero_grad()
            loss = stage_loss(m, tr.renderer, d, p, tr.switches, "fusion", frame, len(tr.tracks))["loss"]
            loss.backward()
            if a.translation_only:
                m.pose.delta.grad[..., :3] = 0
            opt.step()
            tr.renderer.drain()
            losses.append(float(loss.detach()))
            if step % a.every == 0 or step == a.steps:
                row(step, f"{np.mean(losses):.4f}")
                losses = []


if __name__ == "__main__":
    main()
