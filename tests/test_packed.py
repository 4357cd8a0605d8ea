"""clsplat.packed: packed pair ids and LazyMeta, gsplat's meta built on first read."""
from __future__ import annotations

import pickle

import torch

import clsplat
import clsplat.rendering as rendering
from clsplat.packed import LazyMeta, pack_pairs


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
