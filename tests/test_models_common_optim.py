"""SelectiveAdam (models/common/optim.py): plain Adam where nothing is selective, rows without a
gradient left exactly as they were where something is, and a checkpoint that resumes bitwise."""
import pytest
import torch

from clsplat.models.common.optim import SelectiveAdam


def _grads(step: int, shape=(3, 4, 6)) -> torch.Tensor:
    g = torch.zeros(shape)
    if step % 5 == 0:                       # row (1, 2) is visited every 5th step, row (0, 0) always
        g[1, 2] = torch.randn(6, generator=torch.Generator().manual_seed(step))
    g[0, 0] = torch.randn(6, generator=torch.Generator().manual_seed(1000 + step))
    return g


def _run(opt_cls, steps: int, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    a = torch.nn.Parameter(torch.zeros(3, 4, 6))
    b = torch.nn.Parameter(torch.zeros(3, 4, 6))
    opt = opt_cls([{"params": [a], "lr": 2e-3}, {"params": [b], "lr": 1e-2}], eps=1e-15, **kw)
    for s in range(steps):
        a.grad, b.grad = _grads(s), _grads(s)
        opt.step()
    return a.detach(), b.detach()


def test_nothing_selective_is_plain_adam_bit_for_bit():
    a0, b0 = _run(torch.optim.Adam, 40)
    a1, b1 = _run(SelectiveAdam, 40, selective=())
    assert torch.equal(a0, a1) and torch.equal(b0, b1)


def test_rows_without_gradient_stay_put_and_other_groups_are_plain_adam():
    a_plain, b_plain = _run(torch.optim.Adam, 41)
    a_sel, b_sel = _run(SelectiveAdam, 41, selective=[0])
    assert torch.equal(b_plain, b_sel)                      # group 1 is not selective
    untouched = torch.ones(3, 4, dtype=torch.bool)
    untouched[0, 0] = untouched[1, 2] = False
    assert torch.count_nonzero(a_sel[untouched]) == 0       # never a gradient: never moved
    assert torch.count_nonzero(a_plain[untouched]) == 0     # never a gradient, zero moments: Adam too


def test_a_visited_row_moves_on_its_visits_only():
    moved_on = {}
    for name, sel in (("plain", ()), ("selective", (0,))):
        a = torch.nn.Parameter(torch.zeros(3, 4, 6))
        opt = SelectiveAdam([a], selective=sel, lr=2e-3, eps=1e-15)
        steps = []
        for s in range(20):
            before = a.detach()[1, 2].clone()
            a.grad = _grads(s)
            opt.step()
            if not torch.equal(before, a.detach()[1, 2]):
                steps.append(s)
        moved_on[name] = steps
    assert moved_on["selective"] == [0, 5, 10, 15]
    assert moved_on["plain"] == list(range(20))             # momentum moves it between visits


def test_one_impulse_moves_a_row_one_learning_rate_not_ten():
    moved = {}
    for name, kw in (("plain", {"selective": ()}), ("selective", {"selective": [0]})):
        p = torch.nn.Parameter(torch.zeros(2, 6))
        opt = SelectiveAdam([{"params": [p], "lr": 1e-3}], eps=1e-15, **kw)
        for s in range(300):
            g = torch.zeros(2, 6)
            g[1] = 1.0                                     # a row with a gradient at every step
            if s == 100:
                g[0] = 1e-6                                # one tiny impulse on row 0
            p.grad = g
            opt.step()
        moved[name] = p[0].abs().max().item() / 1e-3
    assert moved["plain"] > 8                              # Adam is scale-free: the impulse's size is lost
    assert 0.5 < moved["selective"] < 1.5


def test_resume_from_state_dict_is_bitwise():
    full, _ = _run(SelectiveAdam, 30, selective=[0])
    a = torch.nn.Parameter(torch.zeros(3, 4, 6))
    b = torch.nn.Parameter(torch.zeros(3, 4, 6))
    opt = SelectiveAdam([{"params": [a], "lr": 2e-3}, {"params": [b], "lr": 1e-2}], selective=[0], eps=1e-15)
    for s in range(12):
        a.grad, b.grad = _grads(s), _grads(s)
        opt.step()
    saved = {k: v for k, v in opt.state_dict().items()}
    a2 = torch.nn.Parameter(a.detach().clone())
    b2 = torch.nn.Parameter(b.detach().clone())
    opt2 = SelectiveAdam([{"params": [a2], "lr": 2e-3}, {"params": [b2], "lr": 1e-2}], selective=[0], eps=1e-15)
    opt2.load_state_dict(saved)
    for s in range(12, 30):
        a2.grad, b2.grad = _grads(s), _grads(s)
        opt2.step()
    assert torch.equal(full, a2.detach())


def test_amsgrad_and_a_first_step_without_gradient_keep_idle_rows_at_zero():
    p = torch.nn.Parameter(torch.zeros(3, 6))
    opt = SelectiveAdam([p], selective=[0], lr=1e-2, amsgrad=True)
    for s in range(5):
        g = torch.zeros(3, 6)
        g[s % 2] = 1.0                                     # rows 0 and 1 alternate, row 2 never
        p.grad = g
        opt.step()
    assert torch.count_nonzero(p[2]) == 0
    assert all(torch.count_nonzero(opt.state[p][k][2]) == 0 for k in ("exp_avg", "exp_avg_sq", "max_exp_avg_sq"))


def test_a_group_out_of_range_is_named():
    p = torch.nn.Parameter(torch.zeros(2, 6))
    with pytest.raises(ValueError, match="selective: group 3 is out of range"):
        SelectiveAdam([p], selective=[3], lr=1e-3)
