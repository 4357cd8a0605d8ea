"""DrivingForward's training parts, as ``clsplat train drivingforward`` puts them together: the
optimiser (the pose network at its own rate, its gradient optionally clipped on its own:
``pose_grad_clip``), the learning-rate schedule (the warm-up, and the pose network's exponential
decay ``pose_lr_half_life`` down to ``pose_lr_floor``), the per-sample loss of the shared loop, and the validation learning
curve (:class:`ValCurve`)."""
from __future__ import annotations

import torch

__all__ = ["make_optimizer", "make_scheduler", "lr_factors", "PoseClippedAdam", "make_sample_loss", "ValCurve"]


class PoseClippedAdam(torch.optim.Adam):
    """Adam whose pose-network group (``param_groups[1]``) has its gradient's total L2 norm clipped
    to ``pose_grad_clip`` before every step (the shared loop's ``grad_clip`` clips all parameters
    together, where the depth and Gaussian networks' gradients set the norm). Under Adam this bounds
    what enters the moments (a spike of gradient norm 100 enters as ``pose_grad_clip``), not the size
    of a step: a steady gradient of any norm still moves each weight by about the learning rate."""

    def __init__(self, groups: list[dict], lr: float, pose_grad_clip: float) -> None:
        super().__init__(groups, lr=lr)
        self.pose_grad_clip = float(pose_grad_clip)

    @torch.no_grad()
    def step(self, closure=None):
        grads = [q for q in self.param_groups[1]["params"] if q.grad is not None]
        if grads:
            torch.nn.utils.clip_grad_norm_(grads, self.pose_grad_clip)
        return super().step(closure)


def make_optimizer(model, preset) -> torch.optim.Adam:
    """Adam at ``preset.lr``; the pose network (group 1) at ``preset.pose_lr`` when the preset sets
    one, with its gradient clipped to ``preset.pose_grad_clip`` (:class:`PoseClippedAdam`) when set."""
    pose = list(model.pose_net.parameters())
    ids = {id(q) for q in pose}
    rest = [q for q in model.parameters() if id(q) not in ids]
    groups = [{"params": rest}, {"params": pose, "lr": preset.pose_lr or preset.lr}]
    clip = getattr(preset, "pose_grad_clip", None)
    if clip is not None:
        return PoseClippedAdam(groups, preset.lr, clip)
    return torch.optim.Adam(groups, lr=preset.lr)


def lr_factors(preset, step: int) -> tuple[float, float]:
    """The multipliers of (the other networks', the pose network's) learning rates at ``step``
    (from 0): the linear warm-up of ``preset.lr_warmup`` on both, min(1, (step + 1) / lr_warmup),
    times ``lr_decay_factor`` on both from step ``lr_decay_at`` on (when set), and on the pose
    network's alone max(pose_lr_floor, 0.5 ** (step / pose_lr_half_life)) when
    ``pose_lr_half_life`` is set (the floor 0.0 unless the preset names one)."""
    n = preset.lr_warmup
    warm = min(1.0, (step + 1) / n) if n else 1.0
    at = getattr(preset, "lr_decay_at", None)
    if at is not None and step >= at:
        warm *= preset.lr_decay_factor
    h = getattr(preset, "pose_lr_half_life", None)
    floor = getattr(preset, "pose_lr_floor", 0.0)
    return warm, warm * (max(floor, 0.5 ** (step / h)) if h else 1.0)


def make_scheduler(opt: torch.optim.Optimizer, preset) -> torch.optim.lr_scheduler.LambdaLR | None:
    """The learning-rate schedule of :func:`lr_factors` as a per-group ``LambdaLR`` over
    :func:`make_optimizer`'s two groups (None when it is constant: no ``lr_warmup``, no
    ``lr_decay_at``, no ``pose_lr_half_life``). Its state (the step) travels in the checkpoint, so
    a resumed run continues the decay where it stopped."""
    if (preset.lr_warmup == 0 and getattr(preset, "lr_decay_at", None) is None
            and getattr(preset, "pose_lr_half_life", None) is None):
        return None
    return torch.optim.lr_scheduler.LambdaLR(opt, [lambda s: lr_factors(preset, s)[0],
                                                   lambda s: lr_factors(preset, s)[1]])


def make_sample_loss(source, preset, seed: int, cameras=None, lpips=None):
    """``sample_loss(model, step, index)`` for :func:`clsplat.models.common.train.train`: window
    ``index`` of the train split, jitter and automask noise from the sample's own generator."""
    from ..common.train import sample_generator
    from .data import colour_jitter, gt_ego_motion, load_triplet

    def sample_loss(model, step: int, index: int) -> dict:
        s = load_triplet(source, index, preset, "train", cameras)
        g = sample_generator(seed, index)
        net = colour_jitter(s["images"], g, preset.jitter)
        V = s["Ks"].shape[0]
        noise = torch.randn(V, 2, preset.height, preset.width, generator=g) * preset.automask_noise
        gt = None
        if preset.pose_source == "dataset":
            M = gt_ego_motion(s)
            gt = [M[0], M[2]]
        elif preset.pose_source == "geometric":
            from .geometric_pose import load_window_motions
            gt = load_window_motions(source, index, preset, "train", cameras, s)
        return model.training_losses(s["images"], net, s["Ks"], s["cam_to_ego"], noise, lpips, step, gt)

    return sample_loss


class ValCurve:
    """The validation learning curve of a run: :func:`~.evaluation.validation_point` before the
    first step and every ``every`` steps, one JSON line per point in ``path``, plotted to a PNG.
    On ``--resume`` the points after the resumed step (written by the interrupted run) are dropped
    when the first new one comes, so the file reads as one run. The points draw no random numbers,
    so the training they watch stays bitwise what it is without them."""

    def __init__(self, model, source, path, every: int, scenes: int, cameras=None, resume: bool = False) -> None:
        from pathlib import Path

        from .evaluation import validation_point
        self._point = validation_point
        self.model, self.source, self.path = model, source, Path(path)
        self.every, self.scenes, self.cameras = every, scenes, cameras
        self.records: list[dict] = []
        if resume and self.path.is_file():
            from ..common.train import read_log
            self.records = read_log(self.path)
        self._trim_at: int | None = 0 if resume else None
        try:                # a recorded sequence too short for a validation window: the run goes on without
            validation_point(model, source, 1, cameras)
        except ValueError as e:
            print(f"no validation curve: {e}", flush=True)
            self.every = 0
            return
        if not resume:
            self._add(0)

    def _add(self, step: int) -> None:
        import json
        from clsplat.io.atomic import write_text_atomic
        if self._trim_at is not None:       # the first point of a resumed run: drop what came after its start
            self.records = [r for r in self.records if r["step"] < step]
            self._trim_at = None
        self.records.append({"step": step, **self._point(self.model, self.source, self.scenes, self.cameras)})
        write_text_atomic(self.path, "".join(json.dumps(r, allow_nan=True) + "\n" for r in self.records))

    def on_step(self, step: int, rec: dict) -> None:
        if self.every and step % self.every == 0:
            self._add(step)

    def plot(self, png) -> None:
        """Three panels against step: AbsRel, scale ratio and the pose translation error (median %)."""
        if not self.records:
            return
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from clsplat.io.atomic import atomic_write
        fig, axes = plt.subplots(1, 3, figsize=(11, 3.2), dpi=110)
        for ax, key, label in zip(axes, ("abs_rel", "scale_ratio", "pose_t_err_pct_median"),
                                  ("depth AbsRel", "scale ratio (median gt / median pred)", "pose t error (median %)")):
            pts = [(r["step"], r[key]) for r in self.records if isinstance(r.get(key), (int, float))]
            if pts:
                ax.plot(*zip(*pts), marker=".")
            ax.set_title(label, fontsize=9)
            ax.set_xlabel("step")
            ax.grid(alpha=0.3)
        fig.suptitle(f"validation ({self.scenes} windows of {self.source.name})", fontsize=9)
        fig.tight_layout()
        atomic_write(png, lambda p: fig.savefig(p, format="png"))
        plt.close(fig)
