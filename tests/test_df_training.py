"""DrivingForward's optimiser and schedule (models/drivingforward/training.py): the pose network's
own learning-rate decay (``pose_lr_half_life``, its floor ``pose_lr_floor``) and gradient clip (``pose_grad_clip``), and the
step decay of every rate (``lr_decay_at``), do what the preset says, leave the rest alone, and are off unless named."""
import math

import pytest
import torch

from clsplat.models.drivingforward.presets import SMALL, TINY
from clsplat.models.drivingforward.training import (PoseClippedAdam, lr_factors, make_optimizer,
                                                    make_scheduler)


class _Toy(torch.nn.Module):
    """A stand-in with DrivingForward's split: ``pose_net`` and everything else."""

    def __init__(self) -> None:
        super().__init__()
        self.depth_net = torch.nn.Linear(4, 4)
        self.pose_net = torch.nn.Linear(4, 3)


def _rates(opt) -> tuple[float, float]:
    return opt.param_groups[0]["lr"], opt.param_groups[1]["lr"]


def _rates_over(preset, steps: int) -> list[tuple[float, float]]:
    """The two groups' rates at steps 0 .. steps-1 under ``preset``'s optimiser and schedule."""
    opt = make_optimizer(_Toy(), preset)
    sched = make_scheduler(opt, preset)
    seen = []
    for _ in range(steps):
        seen.append(_rates(opt))
        opt.step()
        sched.step()
    return seen


def test_every_preset_leaves_both_fields_off():
    for p in (TINY, SMALL):
        assert p.pose_lr_half_life is None and p.pose_grad_clip is None
        assert type(make_optimizer(_Toy(), p)) is torch.optim.Adam


def test_half_life_halves_the_pose_rate_and_only_it():
    p = TINY.replace(pose_lr=1e-3, pose_lr_half_life=10)
    seen = _rates_over(p, 31)
    assert all(r == pytest.approx(p.lr) for r, _ in seen)               # the other networks: constant
    for s in (0, 10, 20, 30):                                            # the pose: 0.5 ** (s / 10)
        assert seen[s][1] == pytest.approx(1e-3 * 0.5 ** (s / 10), rel=1e-12)
    assert seen[5][1] == pytest.approx(1e-3 / math.sqrt(2), rel=1e-12)


def test_half_life_composes_with_the_warm_up_and_resumes_where_it_stopped():
    p = TINY.replace(lr_warmup=4, pose_lr_half_life=8)
    assert lr_factors(p, 0) == pytest.approx((0.25, 0.25))
    assert lr_factors(p, 8) == pytest.approx((1.0, 0.5))
    opt = make_optimizer(_Toy(), p)
    sched = make_scheduler(opt, p)
    for _ in range(12):
        opt.step()
        sched.step()
    state_o, state_s = opt.state_dict(), sched.state_dict()
    opt2 = make_optimizer(_Toy(), p)
    sched2 = make_scheduler(opt2, p)
    opt2.load_state_dict(state_o)
    sched2.load_state_dict(state_s)
    assert _rates(opt2) == pytest.approx((p.lr, p.lr * 0.5 ** (12 / 8)))
    opt2.step()
    sched2.step()
    assert _rates(opt2)[1] == pytest.approx(p.lr * 0.5 ** (13 / 8))


def test_pose_lr_floor_stops_the_decay_there_and_is_off_by_default():
    for p in (TINY, SMALL):
        assert p.pose_lr_floor == 0.0
    off = TINY.replace(pose_lr_half_life=10)
    assert lr_factors(off, 100)[1] == pytest.approx(0.5 ** 10, rel=1e-12)        # no floor: today's decay
    p = TINY.replace(pose_lr=1e-3, pose_lr_half_life=10, pose_lr_floor=0.1)
    assert lr_factors(p, 20) == pytest.approx((1.0, 0.25))                      # above the floor: the decay
    opt = make_optimizer(_Toy(), p)
    sched = make_scheduler(opt, p)
    for _ in range(100):
        opt.step()
        sched.step()
    assert _rates(opt) == pytest.approx((p.lr, 1e-4), rel=1e-12)               # 0.5 ** 10 < 0.1: held at it


def test_no_schedule_when_neither_warm_up_nor_decay():
    assert make_scheduler(make_optimizer(_Toy(), TINY), TINY) is None


def test_pose_grad_clip_bounds_the_pose_gradient_and_what_enters_adam():
    """A gradient of norm ~1e4 on the pose network: with the clip its gradient is rescaled to norm 1
    and Adam's first moment after one step is (1 - beta1) x that (norm 0.1); without it, 1e3.
    The other networks' gradients are not touched."""
    def one_step(clip):
        torch.manual_seed(0)
        m = _Toy()
        opt = make_optimizer(m, TINY.replace(pose_grad_clip=clip))
        for q in m.parameters():
            q.grad = torch.full_like(q, 1e3)
        opt.step()
        pose_m = torch.cat([opt.state[q]["exp_avg"].flatten() for q in m.pose_net.parameters()])
        pose_g = torch.cat([q.grad.flatten() for q in m.pose_net.parameters()])
        rest_g = torch.cat([q.grad.flatten() for q in m.depth_net.parameters()])
        return opt, float(pose_g.norm()), float(pose_m.norm()), rest_g

    opt, g, mom, rest = one_step(1.0)
    assert isinstance(opt, PoseClippedAdam)
    assert g == pytest.approx(1.0, rel=1e-5) and mom == pytest.approx(0.1, rel=1e-4)
    assert torch.all(rest == 1e3)
    _, g0, mom0, _ = one_step(None)
    assert g0 == pytest.approx(1e3 * math.sqrt(15), rel=1e-6) and mom0 == pytest.approx(0.1 * g0, rel=1e-5)


def test_pose_grad_clip_leaves_a_small_gradient_as_it_is():
    m = _Toy()
    opt = make_optimizer(m, TINY.replace(pose_grad_clip=10.0))
    for q in m.parameters():
        q.grad = torch.full_like(q, 0.01)
    opt.step()
    assert all(torch.all(q.grad == 0.01) for q in m.pose_net.parameters())


@pytest.mark.parametrize("field,value", [("pose_lr_half_life", 0), ("pose_lr_half_life", 2.5),
                                         ("pose_lr_half_life", True), ("pose_grad_clip", 0.0),
                                         ("pose_grad_clip", -1.0), ("pose_grad_clip", float("inf")),
                                         ("pose_grad_clip", "1"), ("pose_lr_floor", -0.1),
                                         ("pose_lr_floor", 1.5), ("pose_lr_floor", True),
                                         ("pose_lr_floor", 0.1), ("lr_decay_at", 0), ("lr_decay_at", True),
                                         ("lr_decay_at", 2.5), ("lr_decay_factor", 0.0), ("lr_decay_factor", 1.5),
                                         ("lr_decay_factor", "0.1"), ("lr_decay_factor", True)])
def test_a_bad_value_names_the_field(field, value):
    with pytest.raises(ValueError, match=field) as e:
        TINY.replace(**{field: value})
    assert "\n" not in str(e.value)


def test_step_decay_multiplies_both_rates_from_its_step_and_is_off_by_default():
    """``lr_decay_at=S``: from step S (from 0) on, both groups run at ``lr_decay_factor`` of their
    rate, on top of the warm-up and the pose's half-life; before S nothing changes. Off in every
    preset (no scheduler where nothing else needs one)."""
    for p in (TINY, SMALL):
        assert p.lr_decay_at is None
    assert make_scheduler(make_optimizer(_Toy(), TINY), TINY) is None
    p = TINY.replace(lr_decay_at=6, lr_decay_factor=0.1)
    assert [lr_factors(p, s) for s in (0, 5)] == [(1.0, 1.0), (1.0, 1.0)]
    assert lr_factors(p, 6) == pytest.approx((0.1, 0.1)) and lr_factors(p, 60) == pytest.approx((0.1, 0.1))
    q = TINY.replace(lr_warmup=4, pose_lr_half_life=8, lr_decay_at=8, lr_decay_factor=0.5)
    assert lr_factors(q, 8) == pytest.approx((0.5, 0.25))
    seen = _rates_over(p, 8)
    assert seen[5] == pytest.approx((p.lr, p.lr)) and seen[6] == pytest.approx((p.lr * 0.1, p.lr * 0.1))
