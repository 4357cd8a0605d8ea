"""The staged AutoSplat optimisation: the four stages, densification, checkpoints, the loop
(the run's tensors come from :mod:`.data`, its evaluation is :mod:`.evaluate`).

Stages (iterations from the preset; one iteration = all selected cameras of one training frame,
drawn with a generator keyed by (seed, step), so a resumed run draws the same frames):

1. ``bg_phase1``: the road set and the sky set, each rendered alone and supervised on its own
   pixels, plus β·C (flatness).
2. ``bg_phase2``: all background Gaussians, pixels of tracked objects masked out, plus β·C.
3. ``foreground``: objects (with mirror copies and residual SH) over the frozen background, full
   images, plus the L1 sparsity of the residuals. Skipped when the sequence has no tracks.
4. ``fusion``: everything, full images, with the per-object per-frame pose corrections.

Parameters outside a stage's set get no update (their gradients are dropped before Adam). Sets
are densified and pruned while their stage runs (:mod:`.densify`). Checkpoints carry the model,
every set's size, Adam's state, the densification statistics, the step and the RNG states, so a
resumed run continues bitwise.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from ..common.gaussians import GaussianSet
from ..common.train import (JsonlLog, capture_rng, load_checkpoint, plot_losses, restore_rng, sample_generator,
                            save_checkpoint, seed_everything)
from .background import flatness, masked_photometric, reference_frames
from .densify import GaussianParams, GradStats, densify_and_prune
from .data import RunData
from .init import ROAD, SKY, init_background
from .model import AutoSplatModel, Switches, collect_tracks
from .objects import object_points_and_colours
from .presets import AutoSplatPreset

__all__ = ["STAGES", "Trainer", "checkpoint_extra"]

STAGES: tuple[str, ...] = ("bg_phase1", "bg_phase2", "foreground", "fusion")
FAMILY = "autosplat"


def checkpoint_extra(ck: dict) -> dict:
    """AutoSplat's own checkpoint state (``ck["extra"]``; checkpoints written before issue 20 kept
    it at the top level)."""
    return ck.get("extra") or ck


class Trainer:
    """One AutoSplat reconstruction.

    Args:
        data: :class:`RunData`.
        preset: :class:`AutoSplatPreset`.
        switches: constraints on/off.
        out_dir: run folder (checkpoint.pt, log.jsonl, loss.png, metrics.json, sheets).
        device: OpenCL device for :func:`clsplat.rasterization`.
        progress: tqdm progress bar.
        checkpoint_every: steps between checkpoints (and at the end).
    """

    def __init__(self, data: RunData, preset: AutoSplatPreset, switches: Switches, out_dir: str | Path,
                 device=None, progress: bool = True, checkpoint_every: int = 100) -> None:
        self.data, self.preset, self.switches = data, preset, switches
        self.out = Path(out_dir)
        self.device, self.progress, self.checkpoint_every = device, progress, int(checkpoint_every)
        self.tracks = collect_tracks(data.seq, data.train_frames, preset.dynamic_threshold)
        steps = preset.stage_steps()
        if not switches.decompose:  # plain 3DGS: one static set, one background phase
            self.tracks = []
            steps["bg_phase2"] += steps["bg_phase1"]
            steps["bg_phase1"] = 0
        if not self.tracks:
            steps["foreground"] = 0  # nothing to reconstruct in the foreground stage
        self.steps = steps
        self.total = sum(steps.values())
        train_mask = np.zeros(len(data.seq.frames), bool)
        train_mask[data.train_frames] = True
        seed_everything(preset.seed)  # the residual MLPs' initial weights
        self.model = AutoSplatModel(data.seq, self.tracks, train_mask, preset.sh_degree, switches,
                                    preset.residual_width, preset.time_frequencies, preset.position_frequencies)
        self.stats: dict[str, GradStats] = {}
        self.stage_seconds = {s: 0.0 for s in STAGES}
        self._events: list = []
        self._render_wall = 0.0
        self.step = 0
        self.opt: torch.optim.Optimizer | None = None

    # ------------------------------------------------------------------ initialisation
    def initialise(self) -> None:
        """Build every set from the data (LiDAR, templates) and the optimiser."""
        p, d, m = self.preset, self.data, self.model
        rng = np.random.default_rng([p.seed, 7])
        bg, mean_sky = init_background(d.seq, d.train_frames, d.cameras, p, rng, remove_boxes=self.switches.decompose)
        sky_rows = bg.labels == SKY
        quats = np.zeros((len(bg), 4), np.float32)
        quats[:, 0] = 1.0
        # start road and sky Gaussians aligned with their reference frame (flat discs)
        from ..common.geometry import matrix_to_quat
        ref = torch.from_numpy(bg.normals)
        flat = torch.from_numpy((bg.labels == ROAD) | sky_rows)
        if flat.any():
            quats[flat.numpy()] = matrix_to_quat(reference_frames(ref[flat])).numpy()
        scales = bg.scales.copy()
        scales[(bg.labels == ROAD), 2] *= 0.1
        m.background = GaussianParams.from_points(bg.means, bg.colors, scales, p.sh_degree, opacity=0.7,
                                                  labels=bg.labels, normals=bg.normals, quats=quats)
        with torch.no_grad():
            m.sky_color.copy_(torch.logit(torch.from_numpy(mean_sky).clamp(0.02, 0.98)))
        for k, tr in enumerate(self.tracks):
            pts, cols = object_points_and_colours(d.seq, tr.track_id, d.train_frames, d.cameras, p.template,
                                                  p.object_points, rng)
            from .init import knn_mean_distance
            sc = knn_mean_distance(torch.from_numpy(pts)).clamp(0.01, 0.3)[:, None].repeat(1, 3)
            m.objects[k] = GaussianParams.from_points(pts, cols, sc.numpy(), p.sh_degree, opacity=0.7)
        self._build_optimizer()

    def _build_optimizer(self) -> None:
        p, m = self.preset, self.model
        groups = []
        self.base_lr: list[float] = []
        self.is_means: list[bool] = []

        def add(params, lr, means=False):
            groups.append({"params": list(params), "lr": lr})
            self.base_lr.append(lr)
            self.is_means.append(means)

        for g in [m.background, *m.objects]:
            add([g.means], p.lr_means, True)
            add([g.quats], p.lr_quats)
            add([g.log_scales], p.lr_scales)
            add([g.opacity_logits], p.lr_opacity)
            add([g.sh0], p.lr_sh0)
            add([g.shN], p.lr_shN)
        add(m.residuals.parameters(), p.lr_residual)
        add([m.pose.delta], p.lr_pose)
        add([m.sky_color], p.lr_sky)
        self.opt = torch.optim.Adam(groups, eps=1e-15)
        self.stats = {k: GradStats(n) for k, n in m.sizes().items()}

    # ------------------------------------------------------------------ schedule
    def stage_of(self, step: int) -> tuple[str, int, int]:
        """(stage, step within the stage, the stage's length) of global ``step``."""
        s = step
        for name in STAGES:
            n = self.steps[name]
            if s < n:
                return name, s, n
            s -= n
        raise ValueError(f"step {step} is past the schedule's {self.total} steps")

    def _trained_sets(self, stage: str) -> list[str]:
        objs = [f"object{k}" for k in range(len(self.tracks))]
        return {"bg_phase1": ["background"], "bg_phase2": ["background"], "foreground": objs,
                "fusion": ["background", *objs]}[stage]

    def _active_params(self, stage: str) -> set[int]:
        m = self.model
        act: list[torch.nn.Parameter] = []
        if stage in ("bg_phase1", "bg_phase2", "fusion"):
            act += list(m.background.parameters()) + [m.sky_color]
        if stage in ("foreground", "fusion"):
            for o in m.objects:
                act += list(o.parameters())
            act += list(m.residuals.parameters())
        if stage == "fusion" and self.switches.pose_correction:
            act.append(m.pose.delta)
        return {id(q) for q in act}

    # ------------------------------------------------------------------ one step
    def _render(self, gs: GaussianSet, viewmats: torch.Tensor, absgrad: bool = True):
        C = viewmats.shape[0]
        bg = torch.sigmoid(self.model.sky_color).expand(C, 3)
        t0 = time.perf_counter()
        out = gs.render(viewmats, self.data.Ks, self.data.width, self.data.height, backgrounds=bg,
                        absgrad=absgrad, packed=False, device=self.device, events=self._events)
        self._render_wall += time.perf_counter() - t0
        return out

    def _flatness(self) -> torch.Tensor:
        rows, normals = self.model.flatness_frames()
        bg = self.model.background
        return flatness(bg.quats[rows], bg.log_scales[rows].exp(), reference_frames(normals))

    def _sparsity(self, frame: int) -> torch.Tensor | None:
        res = [self.model.residual(k, frame) for k in range(len(self.tracks)) if bool(self.model.present[k, frame])]
        res = [r for r in res if r is not None]
        return torch.cat([r.reshape(-1) for r in res]).abs().mean() if res else None

    def train_step(self, step: int) -> dict:
        """Run global iteration ``step``; returns its log record."""
        p, d, m = self.preset, self.data, self.model
        stage, s_in, n_stage = self.stage_of(step)
        rng = np.random.default_rng([p.seed, step])
        frame = d.train_frames[int(rng.integers(len(d.train_frames)))]
        decay = 0.1 ** (step / max(self.total, 1))
        for g, lr, is_m in zip(self.opt.param_groups, self.base_lr, self.is_means):
            g["lr"] = lr * decay if is_m else lr
        self.opt.zero_grad(set_to_none=True)
        self._events, self._render_wall = [], 0.0
        t0 = time.perf_counter()
        target, vm = d.images[frame], d.viewmats[frame]
        renders = []
        terms: dict[str, torch.Tensor] = {}
        loss = torch.zeros(())
        if stage == "bg_phase1":
            for cls, name in ((ROAD, "road"), (SKY, "sky")):
                mask = d.classes[frame] == cls
                if not bool(mask.any()):
                    continue
                gs, layout = m.scene_at(frame, background=(cls,), objects=False)
                if len(gs) == 0:
                    continue
                col, _, meta = self._render(gs, vm)
                l, l1, _ = masked_photometric(col, target, mask, p.lambda_dssim)
                loss = loss + l
                terms[f"l1_{name}"] = l1
                renders.append((meta, layout))
        else:
            if stage == "bg_phase2":
                gs, layout = m.scene_at(frame, background=True, objects=False)
                mask = ~d.foreground[frame] if self.switches.decompose else None
            else:
                gs, layout = m.scene_at(frame, background=True, objects=True,
                                        detach_background=(stage == "foreground"))
                mask = None
            col, _, meta = self._render(gs, vm)
            l, l1, dssim = masked_photometric(col, target, mask, p.lambda_dssim)
            loss = loss + l
            terms["l1"], terms["dssim"] = l1, dssim
            renders.append((meta, layout))
        if self.switches.flatness and stage != "foreground":
            c = self._flatness()
            terms["flatness"] = c
            loss = loss + p.beta_flatness * c
        if stage in ("foreground", "fusion"):
            sp = self._sparsity(frame)
            if sp is not None:
                terms["sparsity"] = sp
                loss = loss + p.sparsity_weight * sp
        terms["loss"] = loss
        if not torch.isfinite(loss):
            raise FloatingPointError(f"step {step} ({stage}): non-finite loss; terms "
                                     f"{ {k: float(v) for k, v in terms.items()} }")
        t_bwd = time.perf_counter()
        loss.backward()
        t_bwd = time.perf_counter() - t_bwd
        active = self._active_params(stage)
        for g in self.opt.param_groups:
            for q in g["params"]:
                if id(q) not in active:
                    q.grad = None
        self.opt.step()
        trained = self._trained_sets(stage)
        for meta, layout in renders:
            ag = getattr(meta["means2d"], "absgrad", None)
            if ag is None:
                continue
            start = 0
            for key, rows in layout:
                n = rows.shape[0]
                if key in trained:
                    self.stats[key].add(ag[:, start:start + n], meta["radii"][:, start:start + n], d.width,
                                        d.height, rows)
                start += n
        record = {"step": step + 1, "stage": stage, "frame": frame,
                  **{k: float(v.detach()) for k, v in terms.items()}}
        if (self.switches.densify and s_in + 1 >= p.densify_start and (s_in + 1) % p.densify_every == 0
                and s_in + 1 <= 0.8 * n_stage):
            gen = sample_generator(p.seed, step)
            for key in trained:
                g = m.background if key == "background" else m.objects[int(key[6:])]
                if len(g) == 0:
                    continue
                growable = g.labels != SKY if key == "background" else torch.ones(len(g), dtype=torch.bool)
                res = densify_and_prune(
                    g, self.stats[key], self.opt, grad_threshold=p.grad_threshold,
                    split_scale=p.split_scale if key == "background" else p.object_split_scale,
                    prune_opacity=p.prune_opacity, prune_scale=p.prune_scale,
                    max_gaussians=p.max_gaussians if key == "background" else max(4 * p.object_points, len(g)),
                    growable=growable, generator=gen)
                record[f"densify_{key}"] = res["total"]
        wall = time.perf_counter() - t0
        self.stage_seconds[stage] += wall
        dev = sum((ev.profile.end - ev.profile.start) for _, ev in self._events) * 1e-9
        record.update(time_s=wall, renderer_device_s=dev, render_wall_s=self._render_wall, backward_s=t_bwd,
                      gaussians=sum(m.sizes().values()))
        return record

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict:
        """The shared loop's checkpoint layout (model, optimizer, scheduler, step, rng) with
        AutoSplat's own state under ``extra`` (set sizes, densification statistics, the run's
        switches, cameras, training frames and tracks)."""
        return {"model": self.model.state_dict(), "optimizer": self.opt.state_dict(), "scheduler": None,
                "step": self.step, "rng": capture_rng(),
                "extra": {"sizes": self.model.sizes(), "stats": {k: s.state() for k, s in self.stats.items()},
                          "switches": self.switches.to_dict(), "cameras": self.data.cameras,
                          "train_frames": self.data.train_frames, "tracks": [t.track_id for t in self.tracks],
                          "stage_seconds": dict(self.stage_seconds)}}

    def save(self) -> Path:
        return save_checkpoint(self.out / "checkpoint.pt", self.state(), FAMILY, self.preset)

    def load(self, path: str | Path) -> None:
        """Restore a checkpoint of the same data, preset and switches."""
        ck = load_checkpoint(path, FAMILY, self.preset)
        ex = checkpoint_extra(ck)
        for key, mine in (("switches", self.switches.to_dict()), ("cameras", self.data.cameras),
                          ("train_frames", self.data.train_frames), ("tracks", [t.track_id for t in self.tracks])):
            if ex.get(key) != mine:
                raise ValueError(f"checkpoint: {str(path)!r} was made with {key} {ex.get(key)!r}, this run has "
                                 f"{mine!r}; resume with the same arguments")
        self.model.resize_(ex["sizes"])
        self.model.load_state_dict(ck["model"])
        self._build_optimizer()
        self.opt.load_state_dict(ck["optimizer"])
        for k, st in ex["stats"].items():
            self.stats[k].load(st)
        self.step = int(ck["step"])
        self.stage_seconds.update(ex.get("stage_seconds", {}))
        restore_rng(ck["rng"])

    # ------------------------------------------------------------------ the loop
    def fit(self, resume: bool = False, stop_at: int | None = None, on_step=None) -> None:
        """Train to the end of the schedule (or to ``stop_at`` steps), checkpointing as it goes;
        ``on_step(step, record)`` (optional, e.g. the ``--view`` viewer) is called after each step."""
        from tqdm.auto import tqdm

        self.out.mkdir(parents=True, exist_ok=True)
        if resume:
            self.load(self.out / "checkpoint.pt")
        else:
            t0 = time.perf_counter()
            self.initialise()
            self.stage_seconds["init"] = time.perf_counter() - t0
        log = JsonlLog(self.out / "log.jsonl", resume_step=self.step if resume else None)
        end = self.total if stop_at is None else min(stop_at, self.total)
        bar = tqdm(total=self.total, initial=self.step, desc="autosplat", disable=not self.progress,
                   dynamic_ncols=True)
        while self.step < end:
            rec = self.train_step(self.step)
            self.step += 1
            log.write(rec)
            if on_step is not None:
                on_step(self.step, rec)
            bar.set_postfix_str(f"{rec['stage']} loss {rec['loss']:.4f} N {rec['gaussians']}")
            bar.update(1)
            if self.step % self.checkpoint_every == 0 or self.step == end:
                self.save()
        bar.close()
        if self.step == 0:
            self.save()
        plot_losses(self.out / "log.jsonl", self.out / "loss.png", keys=None, title="AutoSplat training loss")

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def render_frame(self, frame: int, viewmats: torch.Tensor | None = None) -> torch.Tensor:
        """``[C, H, W, 3]`` render of ``frame`` (all parts) from ``viewmats`` (default the rig)."""
        gs, _ = self.model.scene_at(frame)
        vm = self.data.viewmats[frame] if viewmats is None else viewmats
        self._events, self._render_wall = [], 0.0
        col, _, _ = self._render(gs, vm, absgrad=False)
        return col.clamp(0, 1)

    def scene_gaussians(self, frame: int) -> GaussianSet:
        """Every Gaussian placed at ``frame`` (for the .ply export)."""
        with torch.no_grad():
            return self.model.scene_at(frame)[0].detach()
