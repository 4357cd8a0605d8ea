"""The staged AutoSplat optimisation on the shared training loop (:func:`..common.train.train`):
the four stages as a schedule of Adam parameter groups, and AutoSplat's checkpoint state.
:class:`Trainer` is the family's :class:`~..common.train.LoopHooks` and has no loop of its own;
what each hook does lives beside it: the per-sample loss of each stage in :mod:`.loss`,
densification and its statistics in :mod:`.densify` (:class:`~.densify.Densifier`), the
evaluation in :mod:`.evaluate`, the run's tensors in :mod:`.data`.

Stages (iterations from the preset; one iteration = all selected cameras of ``batch_size``
training frames, 1 by default; sample ``index`` draws its frame with a generator keyed by
(seed, index), so a resumed run and a data-parallel run draw the same frames):

1. ``bg_phase1``: the road set and the sky set (and the sky colour).
2. ``bg_phase2``: all background Gaussians.
3. ``foreground``: objects (with mirror copies and residual SH) over the frozen background.
   Skipped when the sequence has no tracks. Its length, and each object's initial points and
   Gaussian cap, come from :func:`.objects.object_budget` (issue 36): fixed by the preset, or,
   with the preset's budget fields on, following the number of tracks and their boxes' pixels
   over the training views (0 iterations when no track's box shows).
4. ``fusion``: everything, with the per-object per-frame pose corrections (trained from the
   foreground stage on with ``preset.fg_pose_correction``).

Parameter groups outside a stage's set get no update (:meth:`Trainer.trainable_groups`: the loop
drops their gradients before Adam). Means' learning rates decay ×0.1 over the whole schedule (a
``LambdaLR``). Sets are densified and pruned while their stage runs (:meth:`Trainer.after_step`,
:mod:`.densify`, whose parameter and Adam-moment surgery is :mod:`clsplat.strategy`'s); under
``torchrun`` the screen-space gradient statistics are summed over the ranks every step, so every
rank densifies alike. Checkpoints are the shared loop's (model, optimizer, scheduler, step, RNG
states) with every set's size, the densification statistics and the run's identity under
``extra``, so a resumed run continues bitwise; a non-finite step is skipped (no update, no
densification) as for every family.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from ..common.gaussians import GaussianSet
from ..common.optim import SelectiveAdam
from ..common.train import LoopHooks, TrainSpec, distributed_info, sample_generator, seed_everything, train
from .background import reference_frames
from .densify import Densifier, GaussianParams
from .data import RunData
from .loss import StepRenderer, stage_loss
from .init import ROAD, SKY, init_background
from .model import AutoSplatModel, Switches, collect_tracks
from .objects import (ObjectBudget, budget_scales, fixed_object_budget, object_budget, object_points_and_colours,
                      track_box_pixels)
from .presets import AutoSplatPreset

__all__ = ["STAGES", "Trainer", "checkpoint_extra"]

STAGES: tuple[str, ...] = ("bg_phase1", "bg_phase2", "foreground", "fusion")
FAMILY = "autosplat"
#: the parameter kinds of a Gaussian set, one Adam group each (in this order)
_KINDS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")


def checkpoint_extra(ck: dict) -> dict:
    """AutoSplat's own checkpoint state (``ck["extra"]``; checkpoints written before issue 20 kept
    it at the top level)."""
    return ck.get("extra") or ck


class Trainer(LoopHooks):
    """One AutoSplat reconstruction.

    Args:
        data: :class:`RunData`.
        preset: :class:`AutoSplatPreset`.
        switches: constraints on/off.
        out_dir: run folder (checkpoint.pt, log.jsonl, loss.png, metrics.json, sheets).
        device: OpenCL device for :func:`clsplat.rasterization`.
        progress: tqdm progress bar.
        checkpoint_every: steps between checkpoints (and at the end).
        batch_size: training frames per iteration (the loss is their mean); under ``torchrun``
            each rank renders every world-th of them, so data parallelism needs
            ``batch_size >= WORLD_SIZE``.
    """

    def __init__(self, data: RunData, preset: AutoSplatPreset, switches: Switches, out_dir: str | Path,
                 device=None, progress: bool = True, checkpoint_every: int = 100, batch_size: int = 1) -> None:
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"--batch-size: expected a positive number of frames per iteration, got {batch_size!r}")
        self.data, self.preset, self.switches = data, preset, switches
        self.out = Path(out_dir)
        self.device, self.progress, self.checkpoint_every = device, progress, int(checkpoint_every)
        self.batch_size = batch_size
        self.tracks = collect_tracks(data.seq, data.train_frames, preset.dynamic_threshold)
        steps = preset.stage_steps()
        if not switches.decompose:  # plain 3DGS: one static set, one background phase
            self.tracks = []
            steps["bg_phase2"] += steps["bg_phase1"]
            steps["bg_phase1"] = 0
        self.budget = self._object_budget()
        steps["foreground"] = self.budget.fg_steps   # 0 without tracks: nothing to reconstruct
        self.steps = steps
        self.total = sum(steps.values())
        train_mask = np.zeros(len(data.seq.frames), bool)
        train_mask[data.train_frames] = True
        seed_everything(preset.seed)  # the residual MLPs' initial weights
        self.model = AutoSplatModel(data.seq, self.tracks, train_mask, preset.sh_degree, switches,
                                    preset.residual_width, preset.time_frequencies, preset.position_frequencies)
        self.model.pose.translation_only = preset.pose_translation_only
        self.densifier = Densifier(preset, self.model.sizes(), SKY, self._object_caps())
        self.renderer = StepRenderer(data, device, preset.eps2d, preset.rasterize_mode)
        self.stage_seconds = {s: 0.0 for s in STAGES}
        self.step = 0
        self.opt: torch.optim.Optimizer | None = None
        self.scheduler = None

    # ------------------------------------------------------------------ the object budget
    def _object_budget(self) -> ObjectBudget:
        """The foreground budget of this run (:func:`.objects.object_budget`): with the preset's
        budget fields on, from the decomposed tracks' box pixels over the training frames and the
        selected cameras (counted once here; a resumed run counts them again, so checkpoints need
        only the preset); else the preset's fixed budget, nothing counted."""
        p, d = self.preset, self.data
        if not (self.tracks and budget_scales(p)):
            return fixed_object_budget(p, len(self.tracks))
        t0 = time.perf_counter()
        pixels = track_box_pixels(d.seq, [t.track_id for t in self.tracks], d.train_frames, d.cameras)
        b = object_budget(p, pixels, d.width * d.height)
        return ObjectBudget(b.fg_steps, b.object_points, b.object_caps, b.visible_tracks, b.object_area,
                            time.perf_counter() - t0)

    def _object_caps(self) -> dict[str, int]:
        return {f"object{k}": c for k, c in enumerate(self.budget.object_caps)}

    # ------------------------------------------------------------------ initialisation
    def initialise(self) -> None:
        """Build every set from the data (LiDAR, templates) and the optimiser."""
        p, d, m = self.preset, self.data, self.model
        rng = np.random.default_rng([p.seed, 7])
        bg, mean_sky = init_background(d.seq, d.train_frames, d.cameras, p, rng, remove_boxes=self.switches.decompose)
        sky_rows = bg.labels == SKY
        quats = np.zeros((len(bg), 4), np.float32)
        quats[:, 0] = 1.0
        # start road and sky Gaussians aligned with their reference frame (flat discs; the dome is
        # built of discs tangent to it); the road isotropic as in 3DGS when preset.road_init says
        # so and flatness is off
        from ..common.geometry import matrix_to_quat
        ref = torch.from_numpy(bg.normals)
        flat_road = (bg.labels == ROAD) & (p.road_init == "flat" or self.switches.flatness)
        flat = torch.from_numpy(flat_road | sky_rows)
        if flat.any():
            quats[flat.numpy()] = matrix_to_quat(reference_frames(ref[flat])).numpy()
        scales = bg.scales.copy()
        scales[flat_road, 2] *= 0.1
        m.background = GaussianParams.from_points(bg.means, bg.colors, scales, p.sh_degree, opacity=0.7,
                                                  labels=bg.labels, normals=bg.normals, quats=quats)
        with torch.no_grad():
            m.sky_color.copy_(torch.logit(torch.from_numpy(mean_sky).clamp(0.02, 0.98)))
        for k, tr in enumerate(self.tracks):
            pts, cols = object_points_and_colours(d.seq, tr.track_id, d.train_frames, d.cameras, p.template,
                                                  self.budget.object_points[k], rng)
            from .init import knn_mean_distance
            sc = knn_mean_distance(torch.from_numpy(pts)).clamp(0.01, 0.3)[:, None].repeat(1, 3)
            m.objects[k] = GaussianParams.from_points(pts, cols, sc.numpy(), p.sh_degree, opacity=0.7)
        self.hold_road_opacity()
        self._build_optimizer()

    def hold_road_opacity(self) -> None:
        """``preset.road_opacity_floor`` > 0 with the flatness switch on (issue 33, H2: the road is
        an opaque surface): every road-labelled background Gaussian's opacity logit is clamped to at
        least ``logit(floor)`` (a projection, in place; Adam's moments are left as they are). No-op
        with a floor of 0 or flatness off."""
        floor = float(self.preset.road_opacity_floor)
        if not (floor > 0 and self.switches.flatness):
            return
        bg = self.model.background
        with torch.no_grad():
            lo = math.log(floor / (1.0 - floor))
            road = bg.labels == ROAD
            bg.opacity_logits.copy_(torch.where(road, bg.opacity_logits.clamp(min=lo), bg.opacity_logits))

    def _build_optimizer(self) -> None:
        """Adam with one group per (set, parameter kind), then the residual MLPs, the pose
        corrections and the sky colour; ``self.group_owner[i]`` names group i's owner (a set key,
        ``residuals``, ``pose`` or ``sky``), which :meth:`trainable_groups` selects by stage."""
        p, m = self.preset, self.model
        groups = []
        self.group_owner: list[str] = []
        decays: list = []
        lrs = {"means": p.lr_means, "quats": p.lr_quats, "log_scales": p.lr_scales,
               "opacity_logits": p.lr_opacity, "sh0": p.lr_sh0, "shN": p.lr_shN}
        total = max(self.total, 1)

        def add(owner: str, params, lr: float, decay: bool = False) -> None:
            groups.append({"params": list(params), "lr": lr})
            self.group_owner.append(owner)
            # lr at global step s: lr · 0.1^(s / total) for the means, lr otherwise
            decays.append((lambda s: 0.1 ** (s / total)) if decay else (lambda s: 1.0))

        for key, g in (("background", m.background), *((f"object{k}", o) for k, o in enumerate(m.objects))):
            for kind in _KINDS:
                scale = 1.0 if key == "background" else p.object_lr_scale
                add(key, [getattr(g, kind)], lrs[kind] * scale, decay=kind == "means")
        add("residuals", m.residuals.parameters(), p.lr_residual)
        add("pose", [m.pose.delta], p.lr_pose)
        add("sky", [m.sky_color], p.lr_sky)
        selective = [self.group_owner.index("pose")] if p.pose_selective_adam else []
        self.opt = SelectiveAdam(groups, selective=selective, eps=1e-15)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.opt, decays)
        self.densifier = Densifier(p, m.sizes(), SKY, self._object_caps())

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

    def trainable_groups(self, step: int) -> list[int]:
        """The optimiser groups ``step``'s stage trains: background and sky in the background phases;
        the objects and their residual SH in the foreground stage; all of them in fusion, plus the
        pose corrections when switched on (in the foreground stage too with
        ``preset.fg_pose_correction``: the foreground renders place each object with its correction
        either way)."""
        stage = self.stage_of(step)[0]
        owners = set(self._trained_sets(stage))
        if stage in ("bg_phase1", "bg_phase2", "fusion"):
            owners.add("sky")
        if stage in ("foreground", "fusion"):
            owners.add("residuals")
        pose_stages = ("foreground", "fusion") if self.preset.fg_pose_correction else ("fusion",)
        if stage in pose_stages and self.switches.pose_correction:
            owners.add("pose")
        return [i for i, o in enumerate(self.group_owner) if o in owners]

    # ------------------------------------------------------------------ one sample
    def frame_of(self, index: int) -> int:
        """The training frame of sample ``index`` (drawn with a generator keyed by (seed, index))."""
        rng = np.random.default_rng([self.preset.seed, index])
        return self.data.train_frames[int(rng.integers(len(self.data.train_frames)))]

    def sample_loss(self, model: AutoSplatModel, step: int, index: int) -> dict[str, torch.Tensor]:
        """The loss terms of sample ``index`` (one training frame, every selected camera) at global
        iteration ``step`` (:func:`.loss.stage_loss`); its renders are kept for :meth:`after_step`."""
        return stage_loss(model, self.renderer, self.data, self.preset, self.switches, self.stage_of(step)[0],
                          self.frame_of(index), len(self.tracks))

    # ------------------------------------------------------------------ after the optimiser step
    def after_step(self, step: int, applied: bool) -> dict:
        """Densification statistics and, on schedule, densification and pruning of the sets the
        stage trains (nothing on a skipped step); returns the step's diagnostics for the log."""
        m = self.model
        stage, s_in, n_stage = self.stage_of(step)
        trained = self._trained_sets(stage)
        B = self.batch_size
        record: dict = {"stage": stage, "frames": [self.frame_of(i) for i in range(step * B, (step + 1) * B)]}
        renders, device_s, wall_s = self.renderer.drain()
        if applied:
            self.densifier.accumulate(renders, trained, distributed_info()[1], self.data.width, self.data.height)
        if applied and self.switches.densify and self.densifier.due(s_in, n_stage):
            sets = {k: m.background if k == "background" else m.objects[int(k[6:])] for k in trained}
            record.update(self.densifier.densify(sets, self.opt, stage, sample_generator(self.preset.seed, step)))
        if applied and "background" in trained:
            self.hold_road_opacity()
        record.update(renderer_device_s=device_s, render_wall_s=wall_s, gaussians=sum(m.sizes().values()))
        return record

    # ------------------------------------------------------------------ checkpoints
    def _identity(self) -> dict:
        return {"switches": self.switches.to_dict(), "cameras": self.data.cameras,
                "train_frames": self.data.train_frames, "tracks": [t.track_id for t in self.tracks],
                "batch_size": self.batch_size}

    def state(self) -> dict:
        """AutoSplat's checkpoint ``extra``: set sizes, densification statistics, seconds per
        stage, the run's identity (switches, cameras, training frames, tracks, batch size) and its
        object budget (a record: a resumed run derives it again from the data and the preset)."""
        return {"sizes": self.model.sizes(), "stats": self.densifier.state(),
                **self._identity(), "stage_seconds": dict(self.stage_seconds),
                "object_budget": self.budget.to_dict()}

    def load_state(self, extra: dict, path: Path) -> None:
        """Check the checkpoint is this run's, give every set its recorded size (in place: the
        optimiser's groups keep their parameters) and restore the statistics."""
        ex = checkpoint_extra(extra)
        if not isinstance(ex.get("sizes"), dict) or not isinstance(ex.get("stats"), dict):
            raise ValueError(f"checkpoint: {str(path)!r} holds no AutoSplat set sizes and statistics; it cannot be "
                             "resumed (train again without --resume)")
        saved = {**ex, "batch_size": ex.get("batch_size", 1)}   # checkpoints before issue 19: one frame per step
        for key, mine in self._identity().items():
            if saved.get(key) != mine:
                raise ValueError(f"checkpoint: {str(path)!r} was made with {key} {saved.get(key)!r}, this run has "
                                 f"{mine!r}; resume with the same arguments")
        was = (ex.get("object_budget") or {}).get("fg_steps", self.budget.fg_steps)   # none before issue 36
        if was != self.budget.fg_steps:
            raise ValueError(f"checkpoint: {str(path)!r} was made with {was} foreground iterations, this run's "
                             f"tracks give {self.budget.fg_steps}; resume with the same data and preset")
        self.model.resize_(ex["sizes"])
        self.densifier.load(self.model.sizes(), ex["stats"])
        self.stage_seconds.update(ex.get("stage_seconds", {}))

    # ------------------------------------------------------------------ the run
    def fit(self, resume: bool = False, stop_at: int | None = None, on_step=None) -> None:
        """Train to the end of the schedule (or to ``stop_at`` steps) on the shared loop,
        checkpointing as it goes; ``on_step(step, record)`` (optional, e.g. the ``--view`` viewer)
        is called after each step."""
        if resume:
            self._build_optimizer()   # over the empty sets; load_state resizes them in place
        else:
            t0 = time.perf_counter()
            self.initialise()
            self.stage_seconds["init"] = time.perf_counter() - t0
        end = self.total if stop_at is None else min(stop_at, self.total)

        def stepped(step: int, rec: dict) -> None:
            self.step = step
            self.stage_seconds[rec["stage"]] += rec["time_s"]
            if on_step is not None:
                on_step(step, rec)

        spec = TrainSpec(out_dir=self.out, steps=end, batch_size=self.batch_size,
                         checkpoint_every=self.checkpoint_every, seed=self.preset.seed, resume=resume,
                         progress=self.progress)
        res = train(self.model, self.opt, spec, self.preset, FAMILY, self.sample_loss, scheduler=self.scheduler,
                    on_step=stepped, hooks=self)
        self.step = res["step"]

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def render_frame(self, frame: int, viewmats: torch.Tensor | None = None) -> torch.Tensor:
        """``[C, H, W, 3]`` render of ``frame`` (all parts) from ``viewmats`` (default the rig)."""
        gs, _ = self.model.scene_at(frame)
        vm = self.data.viewmats[frame] if viewmats is None else viewmats
        col, _, _ = self.renderer.render(self.model, gs, vm, absgrad=False)
        self.renderer.drain()
        return col.clamp(0, 1)

    def scene_gaussians(self, frame: int) -> GaussianSet:
        """Every Gaussian placed at ``frame`` (for the .ply export)."""
        with torch.no_grad():
            return self.model.scene_at(frame)[0].detach()
