"""clsplat.packed: packed pair ids and LazyMeta, gsplat's meta built on first read."""
from __future__ import annotations

import pickle

import torch

import clsplat
import clsplat.rendering as rendering
from clsplat.packed import LazyMeta, PackedMeans2d, PackedPairs, pack_pairs


def test_lazy_meta_builds_a_group_once_on_first_read():
    calls = []

    def group():
        calls.append(1)
        return {"a": 1, "b": 2}

    m = LazyMeta({"x": 0}, {"a": group, "b": group})
    assert len(m) == 3 and "a" in m and "c" not in m and not calls
    assert m["a"] == 1 and m["b"] == 2 and m.get("b") == 2 and calls == [1]
    assert m.get("c", 7) == 7


def test_lazy_meta_behaves_as_a_dict():
    def mk():
        return LazyMeta({"x": 0}, {"a": lambda: {"a": 1}})
    assert dict(mk()) == {"x": 0, "a": 1}
    assert {**mk()} == {"x": 0, "a": 1}
    assert sorted(mk()) == ["a", "x"] and sorted(mk().keys()) == ["a", "x"]
    assert sorted(mk().items()) == [("a", 1), ("x", 0)] and sorted(mk().values()) == [0, 1]
    assert mk() == {"x": 0, "a": 1} and mk().copy() == {"x": 0, "a": 1}
    assert pickle.loads(pickle.dumps(mk())) == {"x": 0, "a": 1}
    m = mk()
    m["a"] = 5  # overrides the pending entry, which is never built
    assert m["a"] == 5
    m = mk()
    assert m.pop("a") == 1 and "a" not in m and len(m) == 1
    m = mk()
    del m["a"]
    assert "a" not in m and dict(m) == {"x": 0}


def test_pack_pairs_ids():
    radii = torch.zeros(2, 3, 5, 2, dtype=torch.int32)
    vis = [(0, 0, 1), (0, 2, 4), (1, 1, 0), (1, 2, 3)]
    for b, c, g in vis:
        radii[b, c, g] = 3
    p = pack_pairs(radii)
    assert p.batch_ids.tolist() == [v[0] for v in vis]
    assert p.camera_ids.tolist() == [v[1] for v in vis]
    assert p.gaussian_ids.tolist() == [v[2] for v in vis]
    want = torch.full((30,), -1, dtype=torch.int64)
    want[p.flat] = torch.arange(4)
    assert torch.equal(p.lookup, want)
    one = pack_pairs(radii[:1, :1])  # B = C = 1: the ids without divisions
    assert one.gaussian_ids.tolist() == [1] and one.camera_ids.tolist() == [0] == one.batch_ids.tolist()


def test_meta_entries_built_on_read_and_equal_to_unpacked(make_scene, monkeypatch):
    calls = []
    real = rendering.intersection_meta

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(rendering, "intersection_meta", counting)
    scene = make_scene(0, N=60, C=2, width=48, height=32, dtype=torch.float32)
    scene["means"] = scene["means"].clone().requires_grad_()
    img, _, meta = clsplat.rasterization(**scene, packed=True)
    img.sum().backward()
    assert not calls  # a training step that reads no intersection entry pays for none
    ids, flat = meta["isect_ids"], meta["flatten_ids"]
    assert calls == [1]  # built together, once
    with torch.no_grad():  # per-pair entries keep the grad mode of the call
        depths = meta["depths"]
    assert depths.requires_grad
    _, _, full = clsplat.rasterization(**scene, packed=False)
    c, g = meta["camera_ids"], meta["gaussian_ids"]
    for k in ("radii", "depths", "conics", "opacities"):
        assert torch.equal(meta[k], full[k][c, g]), k
    assert torch.equal(ids, full["isect_ids"])
    assert torch.equal(g[flat.long()], full["flatten_ids"].long() % scene["means"].shape[0])


def _leaf_grads(scene: dict, packed: bool, extra) -> tuple[dict, dict]:
    leaves = {k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")}
    img, alpha, meta = clsplat.rasterization(**{**scene, **leaves}, packed=packed)
    meta["means2d"].retain_grad()
    (img.sum() + alpha.square().sum() + extra(meta)).backward()
    return {k: v.grad for k, v in leaves.items()}, meta


def test_packed_means2d_takes_the_render_gradient_without_a_scatter(make_scene, monkeypatch):
    """The packed node sits on the loss path (retain_grad sees the render's gradient) and the
    leaves get the unpacked layout's gradients bit for bit; with nothing but the render using
    it, its backward hands on the render's gradient instead of scattering (a loss on it scatters)."""
    scene = make_scene(1, N=80, C=3, width=48, height=32, dtype=torch.float32)
    scene["means"] = scene["means"].clone()
    scene["means"][:20] += torch.tensor([0.0, 0.0, 6.0])  # off-screen or behind some cameras
    scatters = []
    real = PackedPairs.scatter
    monkeypatch.setattr(PackedPairs, "scatter", lambda self, v: scatters.append(1) or real(self, v))
    routes = []
    real_init = PackedMeans2d.__init__
    monkeypatch.setattr(PackedMeans2d, "__init__", lambda self, p: routes.append(self) or real_init(self, p))

    def loss_on_means2d(meta):
        m = meta["means2d"]
        return (m.square().sum() if m.dim() == 2 else m[meta_c, meta_g].square().sum())

    g_up, m_up = _leaf_grads(scene, False, lambda m: 0)
    assert (m_up["radii"] == 0).all(-1).any()  # some pairs culled: the shortcut is not vacuous
    g_pk, m_pk = _leaf_grads(scene, True, lambda m: 0)
    assert routes[-1].shortcut_taken and not scatters
    meta_c, meta_g = m_pk["camera_ids"], m_pk["gaussian_ids"]
    assert torch.equal(m_pk["means2d"].grad, m_up["means2d"].grad[meta_c, meta_g])
    for k in g_up:
        assert torch.equal(g_pk[k], g_up[k]), k

    g_up, _ = _leaf_grads(scene, False, loss_on_means2d)
    g_pk, _ = _leaf_grads(scene, True, loss_on_means2d)
    assert not routes[-1].shortcut_taken and scatters == [1]
    for k in g_up:
        assert torch.allclose(g_pk[k], g_up[k], rtol=1e-6, atol=1e-7), k
