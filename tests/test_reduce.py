"""kernels/reduce.cl: per-pair sums of intersection slots, checked against a numpy sum over
each pair's tile rectangle for every slot layout the build options make (geometry, colour and
absgrad gradients on or off, channel counts, both precisions), including pairs that cover no
tile; bitwise reproducible."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from clsplat import stages
from clsplat.config import RenderConfig


def _layout(channels: int, geom: bool, color: bool, absgrad: bool) -> list[tuple[str, int]]:
    """The slot fields in the order kernels/composite_bwd.cl writes them."""
    fields = [("v_means2d", 2), ("v_conics", 3), ("v_opacities", 1)] if geom else []
    fields += [("absgrad", 2)] if geom and absgrad else []
    return fields + ([("v_feats", channels)] if color else [])


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("channels,geom,color,absgrad", [
    (4, True, True, True), (3, True, True, False), (3, True, False, False), (5, False, True, False),
    (1, True, False, True)])
def test_reduce_slots_sums_each_pairs_tiles(rt, precision, channels, geom, color, absgrad):
    g = torch.Generator().manual_seed(channels)
    C, N = 2, 50
    dtype = torch.float64 if precision == "float64" else torch.float32
    x0 = torch.randint(0, 5, (C, N), generator=g)
    y0 = torch.randint(0, 4, (C, N), generator=g)
    w = torch.randint(0, 4, (C, N), generator=g)      # 0: the pair covers no tile (culled)
    h = torch.randint(1, 3, (C, N), generator=g)
    assert (w == 0).any()
    rects = torch.stack([x0, y0, x0 + w, y0 + h], -1).to(torch.int32)
    cfg = RenderConfig(precision=precision)
    r = rt.array(rects)
    offs = stages.isect_offsets(rt, r)
    n = (w * h).reshape(-1)
    M = int(n.sum())
    G = stages.slot_width(channels, geom, color, absgrad)
    assert G == sum(k for _, k in _layout(channels, geom, color, absgrad))
    slots = torch.randn(M, G, generator=g, dtype=torch.float64).to(dtype)
    outs = [stages.reduce_slots(rt, cfg, r, offs, rt.array(slots), channels, geom=geom, color=color,
                                absgrad=absgrad) for _ in range(2)]
    start = np.concatenate([[0], np.cumsum(n.numpy())[:-1]])
    want = np.stack([slots[s:s + k].double().sum(0).numpy() for s, k in zip(start, n.numpy())])
    got = torch.cat([outs[0][k].host().reshape(C * N, -1).double()
                     for k, _ in _layout(channels, geom, color, absgrad)], -1).numpy()
    tol = 1e-12 if precision == "float64" else 1e-5
    np.testing.assert_allclose(got, want, rtol=tol, atol=tol)
    assert np.all(got[n.numpy() == 0] == 0)            # no tile, no gradient
    for k in outs[0]:
        assert torch.equal(outs[0][k].host(), outs[1][k].host())
