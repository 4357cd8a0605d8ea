"""kernels/reduce.cl: per-pair sums of intersection slots, checked against a numpy sum over
each pair's tile rectangle, and bitwise reproducible."""
from __future__ import annotations

import numpy as np
import torch

from clsplat import stages
from clsplat.config import RenderConfig


def test_reduce_slots_sums_each_pairs_tiles(rt):
    g = torch.Generator().manual_seed(0)
    C, N, CH = 2, 50, 4
    x0 = torch.randint(0, 5, (C, N), generator=g)
    y0 = torch.randint(0, 4, (C, N), generator=g)
    w = torch.randint(0, 4, (C, N), generator=g)
    h = torch.randint(1, 3, (C, N), generator=g)
    rects = torch.stack([x0, y0, x0 + w, y0 + h], -1).to(torch.int32)
    cfg = RenderConfig(precision="float64")
    r = rt.array(rects)
    offs = stages.isect_offsets(rt, r)
    n = (w * h).reshape(-1)
    M = int(n.sum())
    G = stages.slot_width(CH, True, True, True)
    slots = torch.randn(M, G, generator=g, dtype=torch.float64)
    outs = [stages.reduce_slots(rt, cfg, r, offs, rt.array(slots), CH, geom=True, color=True,
                                absgrad=True) for _ in range(2)]
    start = np.concatenate([[0], np.cumsum(n.numpy())[:-1]])
    want = np.stack([slots[s:s + k].sum(0).numpy() for s, k in zip(start, n.numpy())])
    got = torch.cat([outs[0][k].host().reshape(C * N, -1) for k in
                     ("v_means2d", "v_conics", "v_opacities", "absgrad", "v_feats")], -1).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    for k in outs[0]:
        assert torch.equal(outs[0][k].host(), outs[1][k].host())
