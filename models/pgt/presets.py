"""PGT presets: every size and constant of a pixel-aligned Gaussian run, as frozen dataclasses.

``tiny`` is for tests (seconds on two CPU cores), ``small`` for the CPU benchmark, ``paper`` for
GPS-Gaussian+'s sizes (encoder 32/48/96, 2 attention layers of 96 channels and 8 heads) at
DrivingForward's 176x320 nuScenes-like resolution. Registered under family ``"pgt"``.

Depth is handled in *normalised inverse depth* u in [0, 1] over ``[min_depth, max_depth]`` metres
(u = 1 at ``min_depth``, u = 0 at ``max_depth``): the plane sweep's hypotheses are uniform in u, the
residual head adds 0.5·tanh(r) in u (half the scene's depth range at most), sky (infinite
depth) is u = 0 clamped, i.e. ``max_depth``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from clsplat.models.common.presets import Preset, register

__all__ = ["PGTPreset", "MATCHINGS", "COLOURS", "SELECTIONS", "TARGETS", "KAPPA_SCHEDULES", "BUDGET_FIELDS",
           "saved_preset"]

MATCHINGS = ("plane_sweep", "epipolar_attention")
COLOURS = ("pixel", "sh")
SELECTIONS = ("topk", "stratified")
TARGETS = ("merge", "density")
KAPPA_SCHEDULES = ("progressive", "log_uniform")

#: fields only the budget stage and the evaluation read: a budget stage may start (``--init``)
#: from a base checkpoint written with other values of these
BUDGET_FIELDS = ("budget_steps", "budget_lr", "kappa_start", "kappa_decay", "kappa_interval", "kappa_min",
                 "kappa_max", "hf_temperature", "patch", "rate_kernel", "fill_window", "w_io", "w_io_opacity",
                 "budget_views", "selection", "importance_head", "budget_colour", "learned_fill", "coverage_input", "coverage_tol", "target",
                 "target_floor", "w_redundancy", "kappa_schedule", "fill_cap_px",
                 "kappa_decoder", "kappa_film")


@dataclass(frozen=True)
class PGTPreset(Preset):
    """One PGT configuration.

    Data: ``height`` x ``width`` images; ``num_views`` source views per sample. ``views="frames"``:
    frames t-g .. t+g (g = ``frame_gap``; the middle frame is the target) of one camera drawn from
    ``cameras``; ``views="cameras"``: one frame of adjacent rig cameras, target the next frame.
    Network: encoder ``channels`` at 1/2, 1/4, 1/8; matching at 1/8 with ``num_depths``
    hypotheses; decoder ``decoder_channels`` (1/8, 1/4, 1/2) up to full resolution, heads of
    ``head_channels``. Gaussians: scale = min(softplus(s)·depth/fx, ``scale_cap``) metres;
    colour from the source pixel or an SH head of ``sh_degree``.
    Losses: ``w_l1``·L1 + ``w_ssim``·(1-SSIM) (+ ``w_mse``·MSE + ``w_lpips``·LPIPS with weight
    files), ``w_depth``·L1 on u (coarse and refined) when the data has depth, otherwise
    ``w_chamfer``·Chamfer of ``chamfer_points`` lifted points per view.
    Optimiser: AdamW(``lr``, ``weight_decay``), one-cycle, clip ``grad_clip``.
    Budget stage (EcoSplat): κ ~ U(max(``kappa_start`` - ``kappa_decay``·⌊step/``kappa_interval``⌋,
    ``kappa_min``), ``kappa_max``); per-view budgets softmax(HF energy / ``hf_temperature``);
    importance target from ``patch`` x ``patch`` patches; loss ``w_io``·(``w_io_opacity``·BCE(opacity,
    target) + BCE(alpha, 1)) plus the render loss. ``fill_window`` (0 = off): a pruned set's kept
    Gaussians widen to cover the pixels pruned around them in that window (our addition, every
    method alike; :meth:`~.model.PGTOutput.gaussians`).

    Issue 18 (departures from EcoSplat's stage 2, each an ablation row in bench/RESULTS.md):
    ``budget_views`` source views per budget-stage sample (> 2: the multi-view protocol of
    :func:`~.data.make_rig_sample`, where cross-view redundancy exists); ``selection``
    ``"topk"`` (EcoSplat) or ``"stratified"`` (density-proportional, spread:
    :func:`~.budget.stratified_mask`); ``importance_head``: a separate selection-score head, the
    opacity left to rendering; ``coverage_input``: the heads also read the cross-view share 1/n
    (from the model's own depth, ``coverage_tol`` relative depth agreement); ``budget_colour``:
    with ``colour="pixel"``, the budget heads add a colour residual (zero at the start) so a kept
    Gaussian can take its pruned neighbours' colour; ``learned_fill``: the budget heads scale the
    fill widening per axis (anisotropic growth, zero = the fill as is); ``target``
    ``"merge"`` (EcoSplat's patch merging) or ``"density"`` (:func:`~.budget.density_target`
    with ``target_floor`` and ``w_redundancy``); ``kappa_schedule`` ``"progressive"`` or
    ``"log_uniform"`` over [``kappa_min``, ``kappa_max``]; ``fill_cap_px`` (0 = off): a pruned
    set's Gaussians may grow to that many pixel footprints even where that exceeds ``scale_cap``
    metres (far scenery), for every method alike. ``kappa_decoder`` (0 = off): the budget stage
    trains copies of the decoder's last that many stages (1 = the output conv, 2 = also the 1/2
    block, .. 4) and, with ``kappa_film``, scales and shifts each copied stage's input by κ
    (:class:`~.budget.KappaDecoder`; EcoSplat conditions its decoder on κ, not only the heads).
    """

    #: fields renamed since checkpoints were first written (issue 20: one name per meaning across
    #: the families); a checkpoint's old names are read as the new ones
    RENAMED: ClassVar[dict[str, str]] = {"near": "min_depth", "far": "max_depth", "scale_cap_m": "scale_cap"}

    name: str
    height: int
    width: int
    num_views: int = 2
    views: str = "frames"
    frame_gap: int = 1
    cameras: tuple[str, ...] = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT",
                                "CAM_BACK_RIGHT", "CAM_BACK")
    channels: tuple[int, int, int] = (32, 48, 96)
    norm: str = "group"
    matching: str = "plane_sweep"
    num_depths: int = 32
    min_depth: float = 1.0
    max_depth: float = 80.0
    attn_layers: int = 2
    attn_heads: int = 8
    cost_channels: int = 64
    decoder_channels: tuple[int, int, int] = (96, 64, 48)
    head_channels: int = 32
    residual: bool = True
    colour: str = "pixel"
    sh_degree: int = 0
    scale_cap: float = 0.5
    w_l1: float = 0.8
    w_ssim: float = 0.2
    w_mse: float = 0.0
    w_lpips: float = 0.0
    w_depth: float = 1.0
    w_chamfer: float = 0.5
    chamfer_points: int = 10000
    lr: float = 2e-4
    weight_decay: float = 1e-5
    grad_clip: float = 1.0
    steps: int = 1000
    batch_size: int = 1
    budget_steps: int = 500
    budget_lr: float = 2e-4
    kappa_start: float = 0.85
    kappa_decay: float = 0.05
    kappa_interval: int = 1000
    kappa_min: float = 0.05
    kappa_max: float = 0.95
    hf_temperature: float = 0.3
    patch: int = 4
    rate_kernel: int = 7
    fill_window: int = 9
    w_io: float = 0.1
    w_io_opacity: float = 0.1
    budget_views: int = 2
    selection: str = "topk"
    importance_head: bool = False
    budget_colour: bool = False
    learned_fill: bool = False
    coverage_input: bool = False
    coverage_tol: float = 0.05
    target: str = "merge"
    target_floor: float = 0.1
    w_redundancy: float = 1.0
    kappa_schedule: str = "progressive"
    fill_cap_px: float = 0.0
    kappa_decoder: int = 0
    kappa_film: bool = True

    def __post_init__(self) -> None:
        def bad(field: str, why: str) -> ValueError:
            return ValueError(f"PGTPreset({self.name!r}).{field}: {why}, got {getattr(self, field)!r}")
        for f in ("height", "width"):
            if getattr(self, f) < 8 or getattr(self, f) % 8:
                raise bad(f, "must be a positive multiple of 8")
        if self.num_views < 2:
            raise bad("num_views", "PGT needs at least 2 source views")
        if self.views not in ("frames", "cameras"):
            raise bad("views", "expected 'frames' or 'cameras'")
        if self.matching not in MATCHINGS:
            raise bad("matching", f"expected one of {MATCHINGS}")
        if self.colour not in COLOURS:
            raise bad("colour", f"expected one of {COLOURS}")
        if not 0 <= self.sh_degree <= 3 or (self.colour == "pixel" and self.sh_degree):
            raise bad("sh_degree", "expected 0..3, and 0 with colour='pixel'")
        if not 0 < self.min_depth < self.max_depth:
            raise bad("min_depth", f"must satisfy 0 < min_depth < max_depth={self.max_depth}")
        if self.num_depths < 2:
            raise bad("num_depths", "need at least 2 depth hypotheses")
        if self.channels[2] % self.attn_heads:
            raise bad("attn_heads", f"must divide channels[2]={self.channels[2]}")
        if not 0 < self.kappa_min <= self.kappa_start <= self.kappa_max <= 1:
            raise bad("kappa_start", "need 0 < kappa_min <= kappa_start <= kappa_max <= 1")
        if self.hf_temperature <= 0:
            raise bad("hf_temperature", "must be > 0")
        if self.rate_kernel % 2 == 0:
            raise bad("rate_kernel", "must be odd")
        if self.fill_window < 0 or (self.fill_window and self.fill_window % 2 == 0):
            raise bad("fill_window", "must be 0 (off) or odd")
        if self.height % self.patch or self.width % self.patch:
            raise bad("patch", "must divide height and width")
        if self.budget_views != 2 and not 3 <= self.budget_views <= 24:
            raise bad("budget_views", "expected 2 (the base protocol) or 3..24 (the multi-view protocol)")
        if self.selection not in SELECTIONS:
            raise bad("selection", f"expected one of {SELECTIONS}")
        if self.target not in TARGETS:
            raise bad("target", f"expected one of {TARGETS}")
        if self.kappa_schedule not in KAPPA_SCHEDULES:
            raise bad("kappa_schedule", f"expected one of {KAPPA_SCHEDULES}")
        if not 0 < self.target_floor <= 1:
            raise bad("target_floor", "must be in (0, 1]")
        if self.w_redundancy < 0:
            raise bad("w_redundancy", "must be >= 0")
        if not 0 < self.coverage_tol < 1:
            raise bad("coverage_tol", "must be in (0, 1)")
        if self.fill_cap_px < 0:
            raise bad("fill_cap_px", "must be >= 0 (0 = off)")
        if not 0 <= self.kappa_decoder <= 4:
            raise bad("kappa_decoder", "expected 0 (κ only at the heads) .. 4 (every decoder stage)")

    @property
    def sh_coeffs(self) -> int:
        """K = (sh_degree + 1)²."""
        return (self.sh_degree + 1) ** 2


TINY = register("pgt", PGTPreset(
    name="tiny", height=32, width=48, channels=(16, 24, 32), num_depths=8, attn_layers=1,
    attn_heads=4, cost_channels=16, decoder_channels=(32, 24, 16), head_channels=16,
    chamfer_points=512, steps=20, budget_steps=10, kappa_interval=5))
#: small's budget stage is issue 18's (bench/RESULTS.md "Issue 18"): multi-view samples, a separate
#: importance head, the density target (detail only: its cross-view term measured worse, floor 0.3
#: better than 0.1), stratified selection, colour and per-axis fill residuals, κ log-uniform down
#: to 0.02 from the first step, far Gaussians free to widen to 8 footprints, and κ-conditioned
#: copies of the decoder's last two stages (1/2 block and output conv) feeding the budget heads;
#: 800 budget steps, chosen over 400 on validation streets by a rule written before the runs (issue 33,
#: bench/notes/ecosplat_controls.md: +0.33 dB at kappa 0.1/0.05, selection margin and kappa-1 gap not worse)
SMALL = register("pgt", PGTPreset(
    name="small", height=64, width=112, num_depths=32, attn_heads=8, cost_channels=48,
    steps=1200, budget_steps=800, budget_lr=1e-3, kappa_interval=20, chamfer_points=4096,
    budget_views=8, selection="stratified", importance_head=True, budget_colour=True, learned_fill=True,
    target="density", target_floor=0.3, w_redundancy=0.0,
    kappa_schedule="log_uniform", kappa_min=0.02, fill_cap_px=8.0, kappa_decoder=2))
PAPER = register("pgt", PGTPreset(
    name="paper", height=176, width=320, num_depths=64, cost_channels=64, steps=30000,
    budget_steps=10000, kappa_interval=1000, colour="sh", sh_degree=1))


def saved_preset(saved: dict) -> PGTPreset:
    """The preset a PGT checkpoint was written with (:func:`~clsplat.models.common.presets.preset_from_saved`),
    except that a budget-stage field its record lacks (a checkpoint from before the field existed)
    takes the class default, the behaviour of the code that wrote it, not the registered preset's
    current value (``small`` changed its budget stage in issue 18)."""
    import dataclasses
    from clsplat.models.common.presets import preset_from_saved
    preset = preset_from_saved("pgt", saved)
    record = PGTPreset.upgrade(saved) if isinstance(saved, dict) else {}
    defaults = {f.name: f.default for f in dataclasses.fields(PGTPreset) if f.default is not dataclasses.MISSING}
    missing = {k: defaults[k] for k in BUDGET_FIELDS if k not in record and getattr(preset, k) != defaults[k]}
    if not missing:
        return preset
    if "kappa_min" in missing or "kappa_start" in missing:  # keep kappa_min <= kappa_start valid
        missing.setdefault("kappa_min", defaults["kappa_min"])
    return dataclasses.replace(preset, **missing)
