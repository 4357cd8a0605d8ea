"""Bad ``.ply`` files and arguments: a ValueError/FileNotFoundError naming the file or the
argument, never garbage, an allocator failure or a half-written file."""
import errno

import numpy as np
import pytest
import torch

from clsplat.io import ply
from clsplat.io.ply import read_ply, write_ply


def gaussians(n=3):
    g = torch.Generator().manual_seed(0)
    return dict(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                scales=torch.rand(n, 3, generator=g) + 0.1, opacities=torch.rand(n, generator=g) * 0.9 + 0.05,
                sh=torch.randn(n, 1, 3, generator=g))


def header(n, props=ply._property_names(1), extra=""):
    lines = ["ply", "format binary_little_endian 1.0", extra, f"element vertex {n}"]
    lines += [f"property float {p}" for p in props] + ["end_header"]
    return ("\n".join(x for x in lines if x) + "\n").encode()


def test_claims_9_gib_of_vertices(tmp_path):
    p = tmp_path / "big.ply"
    p.write_bytes(header(9 << 30 // 68) + b"\0" * 68)
    with pytest.raises(ValueError, match=r"big\.ply.*truncated PLY"):
        read_ply(p)


def test_vertices_that_do_not_fit_in_memory_refused_before_reading(tmp_path, monkeypatch):
    p = write_ply(tmp_path / "g.ply", **gaussians(100))
    monkeypatch.setattr("clsplat.memory.available_host_memory", lambda: 1000)
    with pytest.raises(ValueError, match=r"g\.ply.*100 vertices.*host memory"):
        read_ply(p)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_nan_or_inf_values_refused(tmp_path, value):
    p = write_ply(tmp_path / "g.ply", **gaussians())
    raw = bytearray(p.read_bytes())
    body = len(raw) - 3 * 17 * 4
    raw[body + 4 * 17 + 4 * 2: body + 4 * 17 + 4 * 3] = np.float32(value).tobytes()  # vertex 1, z
    p.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"g\.ply.*NaN or Inf.*vertex 1 property 'z'"):
        read_ply(p)


def test_log_scale_that_overflows_float32_refused(tmp_path):
    p = write_ply(tmp_path / "g.ply", **gaussians())
    raw = bytearray(p.read_bytes())
    body = len(raw) - 3 * 17 * 4
    raw[body + 4 * 10: body + 4 * 11] = np.float32(200.0).tobytes()  # vertex 0, scale_0 = e^200
    p.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"g\.ply.*scale_.*overflows float32"):
        read_ply(p)


def test_end_header_inside_a_comment_is_not_the_end(tmp_path):
    g = gaussians()
    good = write_ply(tmp_path / "good.ply", **g).read_bytes()
    p = tmp_path / "c.ply"
    p.write_bytes(good.replace(b"format binary_little_endian 1.0\n",
                               b"format binary_little_endian 1.0\ncomment made by end_header tool\n", 1))
    got, want = read_ply(p), read_ply(tmp_path / "good.ply")
    for a, b in zip(got, want):
        assert torch.equal(a, b)


def test_no_end_header_line(tmp_path):
    p = tmp_path / "h.ply"
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\ncomment end_header\nelement vertex 1\n")
    with pytest.raises(ValueError, match=r"h\.ply.*no 'end_header'"):
        read_ply(p)


@pytest.mark.parametrize("path", [None, 3, b"x.ply"])
def test_path_of_the_wrong_type(path):
    with pytest.raises(ValueError, match="^path: expected a file path"):
        read_ply(path)


def test_giant_element_count_is_a_clear_error(tmp_path):
    p = tmp_path / "n.ply"
    p.write_bytes(header("9" * 5000) + b"\0" * 68)
    with pytest.raises(ValueError, match=r"n\.ply"):
        read_ply(p)


def test_failed_write_keeps_the_previous_file(tmp_path, monkeypatch):
    """A full disk while writing: the earlier .ply stays whole, the error names the file."""
    p = write_ply(tmp_path / "g.ply", **gaussians(3))
    before = p.read_bytes()

    real_open = open

    class Full:
        def __init__(self, fh):
            self.fh = fh

        def __enter__(self):
            return self

        def __exit__(self, *a):
            self.fh.close()

        def write(self, b):
            self.fh.write(b[:10])
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("builtins.open", lambda f, m="r", *a, **k: Full(real_open(f, m)) if "w" in m
                        else real_open(f, m, *a, **k))
    with pytest.raises(OSError, match=r"g\.ply.*No space left.*unchanged") as e:
        write_ply(p, **gaussians(50))
    assert e.value.errno == errno.ENOSPC
    monkeypatch.undo()
    assert p.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["g.ply"]
