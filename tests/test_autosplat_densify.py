"""AutoSplat densification: gsplat-style clone / split / prune from absgrad statistics, with
Adam's state following the Gaussians; and on a real fit, the set grows where the image needs it."""
import torch

from clsplat.models.autosplat.densify import GaussianParams, GradStats, densify_and_prune
from clsplat.models.common.gaussians import GaussianSet


def _params():
    # rows: 0 small + high grad (clone), 1 large + high grad (split), 2 low opacity (prune),
    # 3 quiet (kept), 4 huge scale (pruned when growable), 5 high grad but not growable
    means = torch.arange(18, dtype=torch.float32).view(6, 3)
    scales = torch.tensor([0.05, 0.5, 0.05, 0.05, 20.0, 0.05])[:, None].repeat(1, 3)
    g = GaussianParams.from_points(means, torch.full((6, 3), 0.5), scales, 1, opacity=0.5,
                                   labels=torch.tensor([0, 1, 2, 2, 2, 1]))
    with torch.no_grad():
        g.opacity_logits[2] = -10.0
    return g


def test_clone_split_prune_and_adam_state_follow():
    g = _params()
    opt = torch.optim.Adam([{"params": [p]} for p in g.parameters()])
    sum(p.sum() for p in g.parameters()).backward()
    opt.step()
    stats = GradStats(6)
    stats.grad = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 1.0])
    stats.count = torch.ones(6)
    growable = torch.tensor([True, True, True, True, True, False])
    old_means = g.means.detach().clone()
    old_scale = g.log_scales.detach()[1].exp()
    old_avg = opt.state[g.means]["exp_avg"].clone()
    res = densify_and_prune(g, stats, opt, grad_threshold=0.5, split_scale=0.15, prune_opacity=0.01,
                            prune_scale=8.0, max_gaussians=100, growable=growable,
                            generator=torch.Generator().manual_seed(0))
    assert res == {"cloned": 1, "split": 1, "pruned": 2, "total": 6}
    # kept rows 0, 3, 5 in order, then the clone of 0, then two children of 1
    assert torch.equal(g.means[:3].detach(), old_means[[0, 3, 5]])
    assert torch.equal(g.means[3].detach(), old_means[0])
    assert torch.allclose(g.log_scales[4:].exp().detach(), (old_scale / 1.6).expand(2, 3))
    assert not torch.equal(g.means[4].detach(), g.means[5].detach())
    assert torch.equal(g.labels, torch.tensor([0, 2, 1, 0, 1, 1]))
    st = opt.state[g.means]["exp_avg"]
    assert st.shape == (6, 3) and torch.equal(st[:3], old_avg[[0, 3, 5]]) and not st[3:].any()
    assert all(any(p is q for grp in opt.param_groups for q in grp["params"]) for p in g.parameters())
    assert stats.grad.shape == (6,) and not stats.grad.any()


def test_growth_is_capped_by_max_gaussians_highest_gradient_first():
    g = _params()
    opt = torch.optim.Adam(g.parameters())
    stats = GradStats(6)
    stats.grad = torch.tensor([2.0, 1.0, 0.0, 3.0, 0.0, 0.0])
    stats.count = torch.ones(6)
    res = densify_and_prune(g, stats, opt, grad_threshold=0.5, split_scale=0.15, prune_opacity=0.01,
                            prune_scale=8.0, max_gaussians=7, growable=torch.ones(6, dtype=torch.bool),
                            generator=torch.Generator().manual_seed(0))
    assert res["cloned"] == 1 and res["split"] == 0  # room for one: row 3 (grad 3) wins


def test_fit_grows_the_set_where_the_image_has_detail():
    """A coarse grey set over a grey background, fitted to a checkerboard in the left half of the
    image (grey on the right): absgrad densification adds Gaussians over the detailed half (at least
    twice as many there as on the right), and the fit improves."""
    torch.manual_seed(0)
    W = H = 32
    n_side = 6
    u, v = torch.meshgrid(torch.linspace(-1.5, 1.5, n_side), torch.linspace(-1.5, 1.5, n_side), indexing="xy")
    pts = torch.stack([u.flatten(), v.flatten(), torch.zeros(n_side ** 2)], -1)
    g = GaussianParams.from_points(pts, torch.full((pts.shape[0], 3), 0.5), torch.full((pts.shape[0], 3), 0.3), 0,
                                   opacity=0.8)
    K = torch.tensor([[[16.0, 0, 16], [0, 16.0, 16], [0, 0, 1]]])
    V = torch.eye(4)[None]
    V[0, 2, 3] = 3.0
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    checker = (((xx // 3) + (yy // 3)) % 2).float()
    target = torch.where(xx < W // 2, checker, torch.full_like(checker, 0.5))[None, ..., None].repeat(1, 1, 1, 3)
    opt = torch.optim.Adam([{"params": [g.means], "lr": 0.005}, {"params": [g.quats], "lr": 0.01},
                            {"params": [g.log_scales], "lr": 0.02}, {"params": [g.opacity_logits], "lr": 0.05},
                            {"params": [g.sh0], "lr": 0.05}, {"params": [g.shN], "lr": 0.0}])
    stats = GradStats(len(g))
    grey = torch.full((1, 3), 0.5)

    def step():
        img, _, meta = GaussianSet(*g.activated()).render(V, K, W, H, backgrounds=grey, absgrad=True, packed=False)
        loss = (img - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        stats.add(meta["means2d"].absgrad, meta["radii"], W, H, torch.arange(len(g)))
        return float(loss.detach())

    first = step()
    n0 = len(g)
    for it in range(1, 120):
        loss = step()
        if it % 20 == 0 and it <= 80:
            densify_and_prune(g, stats, opt, grad_threshold=2e-4, split_scale=0.05, prune_opacity=0.005,
                              prune_scale=8.0, max_gaussians=2000, growable=torch.ones(len(g), dtype=torch.bool),
                              generator=torch.Generator().manual_seed(it))
            stats = GradStats(len(g))
    assert len(g) > 2 * n0, len(g)
    x = g.means.detach()[:, 0]
    assert int((x < 0).sum()) > 2 * int((x >= 0).sum()), (int((x < 0).sum()), int((x >= 0).sum()))
    assert loss < 0.8 * first, (first, loss)
