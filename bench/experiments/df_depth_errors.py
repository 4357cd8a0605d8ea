"""Where a DrivingForward model's held-out depth error sits, and which loss term pushes it there.

* ``errors CHECKPOINT``: AbsRel on the held-out streets broken down by true depth, image row band,
  semantic class (vehicles split into parked and moving, from the data's boxes), camera, and the
  road's bottom corners per camera, with the share of the total each carries and the median predicted/true ratio there;
  also the AbsRel left after median scaling (what a scale error alone explains).
* ``grads CHECKPOINT``: on training streets, per loss term, the sum over a region's pixels of
  ``d(w L)/d log(depth)`` (negative: a descent step moves the region farther), for the side
  cameras and the front/back cameras apart, regions: near (< 6 m) over-estimated (> 1.25x), near
  within 1.25x, 6-15 m, > 15 m; ``--split overlap``: road and building pixels inside and outside
  the rig's overlap as it is at their true depth (where the spatial terms should have no say).
* ``landscape``: with the seeded initial networks, the true depth and the true motion, every loss
  term with the near road's depth (true depth < 6 m) alone multiplied by a factor: does the loss
  itself prefer the near road at its true depth? (``--set FIELD=VALUE`` changes the preset.)
* ``follow CHECKPOINT``: does training follow that gradient? Adam steps (lr 1e-4) cycling over six
  training streets, printing the near-road median ratio every six steps.
* ``basin``: the side cameras' near road alone (``--region parked-vehicles``: the parked vehicles in
  every camera), its true depth times a factor (true depth and motion elsewhere, six training
  streets): the per-pixel minimum reprojection error over the pixels a source sees, without and
  with the auto-mask, and the share the auto-mask drops. How wide is the photometric minimum the
  network has to land in? (``--set supersample=3``.)
* ``baselines``: depths that never look at the image, scored like a model on the held-out streets,
  overall and per class: the layout (per-pixel median true depth of ``--windows`` training
  windows, as ``eval`` reports it) and the ground prior alone at each of ``--caps``.
* ``drift CHECKPOINT [CHECKPOINT ...]``: median predicted/true depth of the near (< 6 m) and far
  pixels of the side and of the front/back cameras, on four held-out streets, per checkpoint (for
  checkpoints kept at successive steps of one run: where does the near road leave its basin?).

Streets come from ``--data`` (default ``synthetic``; a ``synthetic-cache:DIR`` reads a filled
cache); held-out streets are the test split of ``--seed`` (default 0).

    .venv/bin/python bench/experiments/df_depth_errors.py errors RUN/checkpoint.pt --data synthetic-cache:DIR
    .venv/bin/python bench/experiments/df_depth_errors.py grads RUN/checkpoint.pt --data synthetic-cache:DIR [--split overlap]
    .venv/bin/python bench/experiments/df_depth_errors.py basin --data synthetic-cache:DIR [--set supersample=3] [--region parked-vehicles]
    .venv/bin/python bench/experiments/df_depth_errors.py baselines --data synthetic-cache:DIR [--caps 10 20]
    .venv/bin/python bench/experiments/df_depth_errors.py drift RUN_s10/checkpoint.pt RUN_s40/checkpoint.pt --data ...
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

NEAR = 6.0          # metres: the near road the small preset over-estimates
DEPTH_EDGES = (0, 5, 10, 15, 20, 30, 50, 80)
SIDE_CAMERAS = (1, 2, 3, 4)   # rig order: front, front-left, front-right, back-left, back-right, back
VEHICLE = 3         # index of "vehicle" in clsplat.data.scene.SEMANTIC_CLASSES


def _load(checkpoint: str, data: str, seed: int):
    from clsplat.models.common.data import parse_data
    from clsplat.models.drivingforward.cli import load_model

    torch.manual_seed(0)
    torch.set_num_threads(1)
    model, preset = load_model(checkpoint)
    return model, preset, parse_data(data, seed=seed)


MOVING = 254   # _classes(): the class index given to vehicles that move between t-1 and t+1


def _classes(src, index: int, p, split: str, names: list[str], shape: torch.Size) -> torch.Tensor:
    """``[V, H, W]`` uint8 semantic class of window ``index``'s frame t (255 where the data has no
    labels). Vehicles that move in the world between t-1 and t+1 get :data:`MOVING`: the temporal
    warps assume a static scene, and such a vehicle breaks it."""
    kw = {"dt": p.scenes_dt, "supersample": p.supersample} if src.synthetic_streets else {}
    fr = src.sequence(index, num_frames=3, height=p.height, width=p.width, split=split, **kw).frames
    f = fr[1]
    if not f.semantics:
        return torch.full(shape, 255, dtype=torch.uint8)
    c = torch.stack([torch.as_tensor(f.semantics[n]) for n in names]).clone()
    box = lambda k: {b.track_id: np.asarray(b.center) for b in (fr[k].boxes or [])}  # noqa: E731
    b0, b2 = box(0), box(2)
    moving = [t for t in b0 if t in b2 and np.linalg.norm(b2[t] - b0[t]) > 0.1]
    if moving and f.instances:
        inst = torch.stack([torch.as_tensor(f.instances[n]) for n in names])
        c[torch.isin(inst.long(), torch.tensor(moving))] = MOVING
    return c


def errors(checkpoint: str, data: str, seed: int, scenes: int) -> None:
    from clsplat.models.drivingforward.data import load_triplet

    model, p, src = _load(checkpoint, data, seed)
    model.eval()
    P, G, C = [], [], []
    with torch.no_grad():
        for i in range(scenes):
            s = load_triplet(src, i, p, split="test")
            P.append(model.depth_net(s["images"][1], s["Ks"], s["cam_to_ego"])["depth"][:, 0])
            G.append(s["depths"][1])
            C.append(_classes(src, i, p, "test", s["names"], G[-1].shape))
    P, G, C = torch.stack(P).double(), torch.stack(G).double(), torch.stack(C)   # [S, V, H, W]
    valid = torch.isfinite(G) & (G > 1e-3) & (G < p.max_depth)            # as the evaluation counts them
    pc = P.clamp(1e-3, p.max_depth)
    rel = torch.where(valid, (pc - G).abs() / G, torch.zeros_like(G))
    ratio = pc / G
    n, total = int(valid.sum()), float(rel.sum())
    scaled = pc * (G[valid].median() / pc[valid].median())
    over = valid & (pc > G)
    print(f"AbsRel {total / n:.3f} over {n} pixels; after median scaling "
          f"{float(((scaled - G).abs() / G)[valid].mean()):.3f}; over-estimates carry {float(rel[over].sum()) / total:.0%} "
          f"of it ({float(over.sum()) / n:.0%} of pixels); pixels with AbsRel > 1 carry {float(rel[rel > 1].sum()) / total:.0%}")

    def row(name: str, m: torch.Tensor) -> None:
        if m.any():
            print(f"  {name:>14}: pixels {float(m.sum()) / n:5.1%}  AbsRel {float(rel[m].mean()):6.3f}  "
                  f"share {float(rel[m].sum()) / total:5.1%}  median pred/true {float(ratio[m].median()):5.2f}")
    print("by true depth (m)")
    for lo, hi in zip(DEPTH_EDGES[:-1], DEPTH_EDGES[1:]):
        row(f"{lo}-{hi}", valid & (G >= lo) & (G < hi))
    print("by image row band (top to bottom)")
    H = G.shape[2]
    rows = torch.arange(H).view(1, 1, H, 1)
    for b in range(8):
        row(f"band {b}", valid & (rows >= b * H // 8) & (rows < (b + 1) * H // 8))
    print("by camera")
    for c in range(G.shape[1]):
        m = torch.zeros_like(valid)
        m[:, c] = valid[:, c]
        row(f"camera {c}", m)
    print("by semantic class")
    from clsplat.data.scene import SEMANTIC_CLASSES
    for k, name in enumerate(SEMANTIC_CLASSES):
        row(name if name != "vehicle" else "vehicle, parked", valid & (C == k))
    row("vehicle, moving", valid & (C == MOVING))
    print("road, by camera: the bottom-left and bottom-right corners (a quarter of the height and width each) and the rest")
    H, W = G.shape[2:]
    road = valid & (C == 0)
    corner = torch.zeros_like(valid)
    for c in range(G.shape[1]):
        for name, cols in (("bottom-left", slice(0, W // 4)), ("bottom-right", slice(W - W // 4, W)), ("rest", None)):
            m = torch.zeros_like(valid)
            if cols is None:
                m[:, c] = road[:, c] & ~corner[:, c]
            else:
                m[:, c, H - H // 4:, cols] = road[:, c, H - H // 4:, cols]
                corner[:, c] |= m[:, c]
            row(f"cam {c} {name}", m)
    print("by camera group and depth")
    for name, cams in (("sides", SIDE_CAMERAS), ("front/back", tuple(c for c in range(G.shape[1]) if c not in SIDE_CAMERAS))):
        cm = torch.zeros_like(valid)
        cm[:, list(cams)] = True
        row(f"{name} <{NEAR:g}", valid & cm & (G < NEAR))
        row(f"{name} >={NEAR:g}", valid & cm & (G >= NEAR))


def _regions(gt: torch.Tensor, d: torch.Tensor) -> dict[str, torch.Tensor]:
    side = torch.zeros_like(gt, dtype=torch.bool)
    side[list(SIDE_CAMERAS)] = True
    out = {}
    for name, cm in (("sides", side), ("front/back", ~side)):
        out[f"{name} near, over 1.25x"] = cm & (gt < NEAR) & (d > 1.25 * gt)
        out[f"{name} near, within"] = cm & (gt < NEAR) & (d <= 1.25 * gt)
        out[f"{name} {NEAR:g}-15 m"] = cm & (gt >= NEAR) & (gt < 15)
        out[f"{name} > 15 m"] = cm & (gt >= 15) & torch.isfinite(gt)
    return out


def _overlap_regions(src, idx: int, p, s: dict, gt: torch.Tensor, d: torch.Tensor) -> dict[str, torch.Tensor]:
    """Road and building pixels split by whether a rig neighbour sees them at their *true* depth
    (the spatial terms' overlap as it would be at the truth; ``[V, 1, H, W]`` bool each)."""
    from clsplat.models.common.geometry import invert_rigid, warp
    from clsplat.models.drivingforward.losses import rig_neighbours

    E, K = s["cam_to_ego"].float(), s["Ks"].float()
    seen = torch.zeros_like(gt, dtype=torch.bool)
    for c, n in rig_neighbours(E):
        _, v = warp(s["images"][1][n:n + 1].float(), gt[c:c + 1, 0].float().clamp(max=p.max_depth * 1.5),
                    K[c:c + 1], K[n:n + 1], invert_rigid(E[n:n + 1]) @ E[c:c + 1])
        seen[c] |= v[0] > 0
    C = _classes(src, idx, p, "train", s["names"], gt[:, 0].shape).unsqueeze(1)
    road, building = C == 0, C == 2
    return {"road, in overlap at truth": road & seen, "road, outside": road & ~seen,
            "road, outside, > 1.5x": road & ~seen & (d > 1.5 * gt),
            "building, in overlap": building & seen, "building, outside": building & ~seen}


def grads(checkpoint: str, data: str, seed: int, scenes: int, first: int, split: str = "depth") -> None:
    """``split`` "depth": the regions of :func:`_regions`; "overlap": :func:`_overlap_regions`."""
    from clsplat.models.drivingforward.data import load_triplet

    model, p, src = _load(checkpoint, data, seed)
    model.train()
    w = {"reproj": 1.0, "spatial": p.w_spatial, "spatio_temporal": p.w_spatio_temporal,
         "smooth": p.w_smooth, "render": p.w_render}
    fwd = model.depth_net.forward
    box = {}

    def depth_net(*a, **k):
        d = fwd(*a, **k)
        d["depth"].retain_grad()
        box["d"] = d["depth"]
        return d
    model.depth_net.forward = depth_net
    acc: dict = {}
    try:
        for idx in range(first, first + scenes):
            s = load_triplet(src, idx, p, "train")
            gt = s["depths"][1].unsqueeze(1)
            t = model.training_losses(s["images"], s["images"], s["Ks"], s["cam_to_ego"])
            d = box["d"].detach()
            reg = _regions(gt, d) if split == "depth" else _overlap_regions(src, idx, p, s, gt, d)
            for k, wk in w.items():
                model.zero_grad()
                box["d"].grad = None
                if k in t:                  # a term of weight 0 is not computed: no gradient
                    (wk * t[k]).backward(retain_graph=True)
                g = box["d"].grad
                for r, m in reg.items():
                    a = acc.setdefault(r, {"pixels": 0, "ratio": []})
                    a[k] = a.get(k, 0.0) + (0.0 if g is None else float((g * d)[m].sum()) * 1e6)
            for r, m in reg.items():
                acc[r]["pixels"] += int(m.sum())
                if m.any():
                    acc[r]["ratio"].append(float((d[m] / gt[m]).median()))
    finally:
        model.depth_net.forward = fwd
    print(f"training streets {first}..{first + scenes - 1}: sum over the region of d(wL)/dlog(depth) x 1e6 "
          "(negative: a descent step moves it farther)")
    for r, a in acc.items():
        ratio = sum(a["ratio"]) / max(len(a["ratio"]), 1)
        print(f"  {r:>26}: pixels {a['pixels']:6d}  median pred/true {ratio:4.2f}  "
              + "  ".join(f"{k} {a[k]:+9.1f}" for k in w))


def landscape(data: str, seed: int, scenes: int, first: int, sets: list[str] | None) -> None:
    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.common.presets import apply_sets
    from clsplat.models.drivingforward.data import load_triplet
    from clsplat.models.drivingforward.model import DrivingForward

    torch.manual_seed(0)
    torch.set_num_threads(1)
    p = apply_sets(get_preset("drivingforward", "small"), sets)
    model, src = DrivingForward(p), parse_data(data, seed=seed)
    fwd, pose_fwd = model.depth_net.forward, model.pose_net.forward
    factors, terms = (0.7, 1.0, 1.4, 2.0, 4.0, 10.0), ("reproj", "spatial", "spatio_temporal", "smooth", "render", "loss")
    acc = {f: dict.fromkeys(terms, 0.0) for f in factors}
    try:
        for idx in range(first, first + scenes):
            s = load_triplet(src, idx, p, "train")
            true = s["depths"][1].unsqueeze(1).float().clamp(max=p.max_depth * 1.5)
            near = true < NEAR
            V = s["viewmats"][:, 0].float()
            motion = [V[1] @ torch.linalg.inv(V[0]), V[2] @ torch.linalg.inv(V[1])]
            for f in factors:
                def depth_net(*a, f=f, **k):
                    d = fwd(*a, **k)
                    d["depth"] = torch.where(near, true * f, true)
                    return d
                calls = iter(motion)   # training_losses asks for t-1 -> t, then t -> t+1
                model.depth_net.forward = depth_net
                model.pose_net.forward = lambda *a, **k: next(calls)
                with torch.no_grad():
                    t = model.training_losses(s["images"], s["images"], s["Ks"], s["cam_to_ego"])
                for k in terms:
                    acc[f][k] += float(t[k]) / scenes if k in t else float("nan")   # weight 0: not computed
    finally:
        model.depth_net.forward, model.pose_net.forward = fwd, pose_fwd
    print(f"near road (< {NEAR:g} m) depth x factor, elsewhere true; mean over {scenes} training streets, x 1e3 "
          "(change from factor 1 in brackets; the total is weighted)")
    print("factor " + "".join(f"{k:>20}" for k in terms))
    for f in factors:
        print(f"{f:6} " + "".join(f"{1e3 * acc[f][k]:10.2f} ({1e3 * (acc[f][k] - acc[1.0][k]):+6.2f})" for k in terms))


def follow(checkpoint: str, data: str, seed: int, first: int, steps: int, terms: list[str] | None = None) -> None:
    from clsplat.models.drivingforward.data import load_triplet

    model, p, src = _load(checkpoint, data, seed)
    model.train()
    streets = [load_triplet(src, i, p, "train") for i in range(first, first + 6)]
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    w = {"reproj": 1.0, "spatial": p.w_spatial, "spatio_temporal": p.w_spatio_temporal,
         "smooth": p.w_smooth, "render": p.w_render}

    def near_ratio() -> float:
        r = []
        with torch.no_grad():
            for s in streets:
                d = model.depth_net(s["images"][1], s["Ks"], s["cam_to_ego"])["depth"]
                gt = s["depths"][1].unsqueeze(1)
                m = gt < NEAR
                r.append(float((d[m] / gt[m]).median()))
        return sum(r) / len(r)
    print(f"step 0: near-road median pred/true {near_ratio():.3f}")
    for it in range(steps):
        s = streets[it % 6]
        t = model.training_losses(s["images"], s["images"], s["Ks"], s["cam_to_ego"])
        loss = t["loss"] if not terms else sum(w[k] * t[k] for k in terms if k in t)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % 6 == 5:
            print(f"step {it + 1}: near-road median pred/true {near_ratio():.3f}, loss {float(loss):.4f}")


def basin(data: str, seed: int, scenes: int, first: int, sets: list[str] | None, region_name: str = "near-road") -> None:
    from clsplat.models.common.data import parse_data
    from clsplat.models.common.geometry import warp
    from clsplat.models.common.losses import photometric_error
    from clsplat.models.common.presets import get_preset
    from clsplat.models.common.presets import apply_sets
    from clsplat.models.drivingforward.data import load_triplet

    torch.set_num_threads(1)
    p = apply_sets(get_preset("drivingforward", "small"), sets)
    src = parse_data(data, seed=seed)
    factors = (0.5, 0.7, 0.85, 1.0, 1.2, 1.4, 1.7, 2.0, 2.5, 3.0, 5.0)
    acc = {f: [0.0, 0.0, 0, 0] for f in factors}    # error sum (seen), error sum (masked min), masked, seen
    n = 0
    for idx in range(first, first + scenes):
        s = load_triplet(src, idx, p, "train")
        im, Ks, Vm = s["images"], s["Ks"], s["viewmats"].float()
        true = s["depths"][1].float().clamp(max=p.max_depth * 1.5)
        if region_name == "near-road":
            side = torch.zeros_like(true, dtype=torch.bool)
            side[list(SIDE_CAMERAS)] = True
            region = side & (true < NEAR)
        else:                           # parked vehicles, every camera
            region = _classes(src, idx, p, "train", s["names"], true.shape) == VEHICLE
        n += int(region.sum())
        ident = torch.cat([photometric_error(im[k], im[1]) for k in (0, 2)], 1).min(1).values
        for f in factors:
            d = torch.where(region, true * f, true)
            errs = []
            for k in (0, 2):
                w, valid = warp(im[k], d, Ks, Ks, Vm[k] @ torch.linalg.inv(Vm[1]))
                errs.append(torch.where(valid > 0, photometric_error(w, im[1]), torch.full_like(valid, float("inf"))))
            best = torch.cat(errs, 1).min(1).values
            seen = region & torch.isfinite(best)
            acc[f][0] += float(best[seen].sum())
            acc[f][1] += float(torch.minimum(best, ident)[region].sum())
            acc[f][2] += int((ident < best)[region].sum())
            acc[f][3] += int(seen.sum())
    what = f"side cameras' near road (< {NEAR:g} m" if region_name == "near-road" else "parked vehicles (every camera"
    print(f"{what}, {n} px over {scenes} training streets), its depth x factor: "
          "mean minimum reprojection error x 1e3 over the pixels a source sees | with the auto-mask; share masked")
    for f in factors:
        e, m, masked, seen = acc[f]
        print(f"x{f:<5} seen {seen / n:4.0%}  {1e3 * e / seen:7.1f} | {1e3 * m / n:6.1f}   masked {masked / n:4.0%}")


def baselines(data: str, seed: int, scenes: int, windows: int, caps: list[float]) -> None:
    """Image-blind depths scored like a model, overall and per semantic class: the layout baseline
    (per-pixel median true depth of ``windows`` training windows) and the ground prior alone at
    each cap (what ``ground_prior_cap`` starts the network from)."""
    from clsplat.data.scene import SEMANTIC_CLASSES
    from clsplat.models.common.metrics import depth_metrics
    from clsplat.models.common.data import parse_data
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.data import load_triplet
    from clsplat.models.drivingforward.depth import ground_prior_depth
    from clsplat.models.drivingforward.evaluation import layout_depth

    torch.set_num_threads(1)
    p = get_preset("drivingforward", "small")
    src = parse_data(data, seed=seed)
    S = [load_triplet(src, i, p, split="test") for i in range(scenes)]
    G = torch.stack([s["depths"][1] for s in S]).double()
    C = torch.stack([_classes(src, i, p, "test", s["names"], G.shape[1:]) for i, s in enumerate(S)])
    valid = torch.isfinite(G) & (G > 1e-3) & (G < p.max_depth)
    guesses = {f"layout ({windows} training windows)": layout_depth(src, p, windows).double().expand_as(G)}
    for cap in caps:
        guesses[f"ground prior alone, cap {cap:g} m"] = torch.stack(
            [ground_prior_depth(s["Ks"].double(), s["cam_to_ego"].double(), p.height, p.width, cap)[:, 0] for s in S])
    for name, P in guesses.items():
        m = depth_metrics(P, G, max_depth=p.max_depth)
        rel = (P.clamp(1e-3, p.max_depth) - G).abs() / G
        cls = " ".join(f"{n} {float(rel[valid & (C == k)].mean()):.3f}" for k, n in
                       [*enumerate(SEMANTIC_CLASSES), (MOVING, "moving-vehicle")] if (valid & (C == k)).any())
        print(f"{name}: AbsRel {m['abs_rel']:.3f} delta1 {m['delta1']:.3f} scale {m['scale_ratio']:.3f} | AbsRel by class: {cls}")


def drift(checkpoints: list[str], data: str, seed: int) -> None:
    from clsplat.models.common.data import parse_data
    from clsplat.models.drivingforward.cli import load_model
    from clsplat.models.drivingforward.data import load_triplet

    torch.set_num_threads(1)
    src, samples = parse_data(data, seed=seed), None
    for ck in checkpoints:
        model, p = load_model(ck)
        model.eval()
        if samples is None:
            samples = [load_triplet(src, i, p, split="test") for i in range(4)]
        with torch.no_grad():
            P = torch.stack([model.depth_net(s["images"][1], s["Ks"], s["cam_to_ego"])["depth"][:, 0] for s in samples])
        G = torch.stack([s["depths"][1] for s in samples])
        P, G = P.double(), G.double()
        valid = torch.isfinite(G) & (G < p.max_depth)
        side = torch.zeros_like(G, dtype=torch.bool)
        side[:, list(SIDE_CAMERAS)] = True
        r = P.clamp(1e-3, p.max_depth) / G
        cells = [f"{name} {float(r[valid & m].median()):5.2f}" for name, m in (
            ("side<6", side & (G < NEAR)), ("front/back<6", ~side & (G < NEAR)),
            ("side>=6", side & (G >= NEAR)), ("front/back>=6", ~side & (G >= NEAR)))]
        step = torch.load(ck, map_location="cpu", weights_only=False).get("step", "?")
        print(f"step {step:>5}: median predicted/true  " + "  ".join(cells) + f"  (median depth {float(P[valid].median()):.1f} m)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("errors", "grads", "landscape", "follow", "basin", "drift", "baselines"):
        a = sub.add_parser(name)
        if name == "drift":
            a.add_argument("checkpoint", nargs="+")
        elif name not in ("landscape", "basin", "baselines"):
            a.add_argument("checkpoint")
        a.add_argument("--set", action="append", default=None, metavar="FIELD=VALUE", help="landscape, basin: preset change")
        a.add_argument("--data", default="synthetic")
        a.add_argument("--seed", type=int, default=0)
        a.add_argument("--scenes", type=int, default={"errors": 8, "baselines": 8, "landscape": 4}.get(name, 6))
        a.add_argument("--first", type=int, default=200, help="first training street (grads, follow)")
        a.add_argument("--steps", type=int, default=24, help="follow: Adam steps")
        a.add_argument("--windows", type=int, default=32, help="baselines: training windows of the layout")
        a.add_argument("--caps", type=float, nargs="+", default=[10.0, 20.0], help="baselines: ground prior caps (m)")
        a.add_argument("--region", default="near-road", choices=("near-road", "parked-vehicles"),
                       help="basin: the pixels whose depth is scaled")
        a.add_argument("--split", default="depth", choices=("depth", "overlap"),
                       help="grads: regions by true depth, or road/building in and outside the rig overlap at the true depth")
        a.add_argument("--terms", nargs="+", default=None, choices=("reproj", "spatial", "spatio_temporal", "smooth", "render"),
                       help="follow: train on these terms only (default: the total loss)")
    args = ap.parse_args(argv)
    if args.cmd == "errors":
        errors(args.checkpoint, args.data, args.seed, args.scenes)
    elif args.cmd == "landscape":
        landscape(args.data, args.seed, args.scenes, args.first, args.set)
    elif args.cmd == "baselines":
        baselines(args.data, args.seed, args.scenes, args.windows, args.caps)
    elif args.cmd == "basin":
        basin(args.data, args.seed, args.scenes, args.first, args.set, args.region)
    elif args.cmd == "drift":
        drift(args.checkpoint, args.data, args.seed)
    elif args.cmd == "grads":
        grads(args.checkpoint, args.data, args.seed, args.scenes, args.first, args.split)
    else:
        follow(args.checkpoint, args.data, args.seed, args.first, args.steps, args.terms)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
