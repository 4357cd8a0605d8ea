"""kernels/sort.cl (clsplat.stages.sort_segments) against numpy.lexsort, exactly."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from clsplat import stages
from clsplat.config import RenderConfig


def make_keys(rng, lens, n_depths=None, cam_n=100000):
    """Keys (float32 depth bits << 32 | id) in segments of the given lengths, ids unique as in
    the engine; with n_depths, depths are drawn from that few values so ties are frequent."""
    M = int(sum(lens))
    ids = rng.permutation(max(M, 1) * 3)[:M].astype(np.uint64)
    if n_depths:
        pool = rng.uniform(0.1, 50, n_depths).astype(np.float32)
        depths = pool[rng.integers(0, n_depths, M)]
    else:
        depths = rng.uniform(0.01, 1e4, M).astype(np.float32)
    keys = (depths.view(np.uint32).astype(np.uint64) << np.uint64(32)) | ids
    off = np.concatenate([[0], np.cumsum(lens)]).astype(np.int32)
    return keys, off, depths, ids


def run_sort(rt, cfg, keys, off):
    k = rt.array(torch.from_numpy(keys.view(np.int64).copy()))
    o = rt.array(torch.from_numpy(off.copy()))
    stages.sort_segments(rt, cfg, k, o)
    return k.host().numpy().view(np.uint64).copy()


def expected(keys, off, depths, ids):
    out = keys.copy()
    for s, e in zip(off[:-1], off[1:]):
        order = np.lexsort((ids[s:e], depths[s:e]))  # by depth, ties by id
        out[s:e] = keys[s:e][order]
    return out


@pytest.mark.parametrize("layout", ["serial", "bitonic"])
@pytest.mark.parametrize("n_depths", [None, 3])
def test_many_small_segments(rt, n_depths, layout):
    rng = np.random.default_rng(0 if n_depths is None else 1)
    lens = rng.integers(0, 300, 400)
    lens[::17] = 0
    lens[::23] = 1
    keys, off, d, ids = make_keys(rng, lens, n_depths)
    got = run_sort(rt, RenderConfig(sort_layout=layout), keys, off)
    assert np.array_equal(got, expected(keys, off, d, ids))


@pytest.mark.parametrize("sort_local", [2, 64, 256])
@pytest.mark.parametrize("seed", [0, 1])
def test_global_merge_path(rt, sort_local, seed):
    """Segments larger than SORT_LOCAL are merged globally; the lengths give both odd and even
    numbers of merge passes, partial last runs and non-power-of-two sizes."""
    rng = np.random.default_rng(seed)
    lens = np.array([1000, 5000, 0, 1, 64, 65, 127, 128, 129, 2 * sort_local + 1, 3001, 4096, 17])
    lens = np.concatenate([lens, rng.integers(0, 2000, 12)])
    if sort_local == 2:
        lens = lens[lens < 600]  # keep the pass count (log2 of 300) modest
    keys, off, d, ids = make_keys(rng, lens, n_depths=5 if seed else None)
    got = run_sort(rt, RenderConfig(sort_local=sort_local, sort_layout="bitonic"), keys, off)
    assert np.array_equal(got, expected(keys, off, d, ids))


@pytest.mark.parametrize("length", [65, 128, 129, 192, 256, 257, 512, 513, 1024, 1500])
def test_pass_counts(rt, length):
    """One big segment per run: with sort_local=64 these need 1..5 merge passes (odd and even)."""
    rng = np.random.default_rng(length)
    keys, off, d, ids = make_keys(rng, [length], n_depths=2)
    got = run_sort(rt, RenderConfig(sort_local=64, sort_layout="bitonic"), keys, off)
    assert np.array_equal(got, expected(keys, off, d, ids))


@pytest.mark.parametrize("layout", ["serial", "bitonic"])
def test_already_sorted_and_reversed(rt, layout):
    rng = np.random.default_rng(5)
    keys, off, d, ids = make_keys(rng, [3000, 700])
    want = expected(keys, off, d, ids)
    cfg = RenderConfig(sort_local=128, sort_layout=layout)
    assert np.array_equal(run_sort(rt, cfg, want.copy(), off), want)
    rev = np.concatenate([want[:3000][::-1], want[3000:][::-1]])
    assert np.array_equal(run_sort(rt, cfg, rev, off), want)


@pytest.mark.parametrize("layout", ["serial", "bitonic"])
def test_trivial_inputs(rt, layout):
    cfg = RenderConfig(sort_layout=layout)
    rng = np.random.default_rng(3)
    for lens in ([], [0, 0, 0], [1], [1, 0, 1], [2]):
        keys, off, d, ids = make_keys(rng, lens)
        got = run_sort(rt, cfg, keys, off)
        assert np.array_equal(got, expected(keys, off, d, ids))


@pytest.mark.parametrize("layout", ["serial", "bitonic"])
def test_deterministic_regardless_of_input_order(rt, layout):
    """The bin stage's atomics shuffle each segment; the sort must erase that."""
    rng = np.random.default_rng(9)
    lens = [500, 3000, 40]
    keys, off, d, ids = make_keys(rng, lens, n_depths=4)
    cfg = RenderConfig(sort_local=256, sort_layout=layout)
    outs = []
    for s in range(3):
        sh = keys.copy()
        for a, b in zip(off[:-1], off[1:]):
            sh[a:b] = np.random.default_rng(s).permutation(sh[a:b])
        outs.append(run_sort(rt, cfg, sh, off))
    assert all(np.array_equal(outs[0], o) for o in outs[1:])
