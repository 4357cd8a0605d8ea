"""clsplat.validate's value checks: the one-pass finite test against numpy's exact one."""
import warnings

import numpy as np
import pytest
import torch

from clsplat.validate import all_finite, check_finite


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_single_nan_or_inf_anywhere_is_found(dtype, bad):
    v = np.random.default_rng(0).standard_normal(1000).astype(dtype)
    for i in (0, 500, 999):
        w = v.copy()
        w[i] = bad
        assert not all_finite(w)
    assert all_finite(v)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_finite_values_whose_sum_overflows_are_finite(dtype):
    big = np.finfo(dtype).max
    v = np.array([big, big, -big / 2], dtype=dtype)   # the sum overflows, every value is finite
    with np.errstate(over="ignore"):
        assert not np.isfinite(v.sum())
    assert all_finite(v)
    w = np.array([np.inf, -np.inf], dtype=dtype)      # the infinities cancel into a NaN sum
    assert not all_finite(w)


def test_empty_strided_and_broadcast_arrays():
    assert all_finite(np.zeros(0, np.float32))
    x = np.arange(12, dtype=np.float32).reshape(3, 4)[:, ::2]
    assert all_finite(x)
    x = x.copy()
    x[1, 1] = np.nan
    assert not all_finite(x[:, ::1])
    g = torch.ones(()).expand(5, 7).numpy()           # a sum's gradient: stride 0
    assert all_finite(g)


def test_check_finite_names_the_argument_and_counts():
    t = torch.zeros(4, 3)
    t[1, 2], t[3, 0] = float("nan"), float("inf")
    with pytest.raises(ValueError, match=r"^means: contains 2 NaN or Inf value\(s\)$"):
        check_finite("means", t)
    check_finite("means", torch.zeros(4, 3))


def test_no_runtime_warning_for_infinities_or_overflow():
    big = np.finfo(np.float32).max
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not all_finite(np.array([np.inf, -np.inf], np.float32))
        assert all_finite(np.array([big, big], np.float32))
