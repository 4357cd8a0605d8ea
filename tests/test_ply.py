"""INRIA 3DGS .ply export / import."""
import numpy as np
import pytest
import torch

from clsplat.io.ply import SH_C0, read_ply, write_ply

INRIA_ORDER_K1 = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                  "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _gaussians(n=50, k=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g), torch.rand(n, 3, generator=g) + 0.01,
            torch.rand(n, generator=g) * 0.98 + 0.01, torch.randn(n, k, 3, generator=g))


@pytest.mark.parametrize("k", [1, 4, 16])
def test_roundtrip(tmp_path, k):
    m, q, s, o, sh = _gaussians(k=k)
    write_ply(tmp_path / "g.ply", m, q, s, o, sh)
    r = read_ply(tmp_path / "g.ply")
    assert torch.equal(r.means, m) and torch.equal(r.quats, q) and torch.equal(r.sh, sh)
    assert torch.allclose(r.scales, s, rtol=1e-5) and torch.allclose(r.opacities, o, atol=1e-6)
    assert r.sh.shape == (50, k, 3) and r.means.dtype == torch.float32


def test_layout_is_inria(tmp_path):
    m, q, s, o, sh = _gaussians(n=3, k=4)
    p = write_ply(tmp_path / "g.ply", m, q, s, o, sh)
    raw = p.read_bytes()
    header = raw[: raw.index(b"end_header\n") + 11].decode()
    props = [ln.split()[2] for ln in header.splitlines() if ln.startswith("property")]
    assert all(ln.startswith("property float ") for ln in header.splitlines() if ln.startswith("property"))
    assert props == INRIA_ORDER_K1[:9] + [f"f_rest_{i}" for i in range(9)] + INRIA_ORDER_K1[9:]
    assert "format binary_little_endian 1.0" in header and "element vertex 3" in header
    data = np.frombuffer(raw[len(header):], "<f4").reshape(3, len(props))
    col = {n: i for i, n in enumerate(props)}
    assert np.all(data[:, 3:6] == 0)
    # channel-major f_rest: f_rest_{c*(K-1)+(k-1)} = sh[:, k, c]
    assert np.allclose(data[:, col["f_rest_4"]], sh[:, 2, 1].numpy())  # c=1, k=2
    assert np.allclose(data[:, col["opacity"]], torch.logit(o).numpy(), atol=1e-5)
    assert np.allclose(data[:, col["scale_1"]], torch.log(s[:, 1]).numpy(), atol=1e-6)


def test_rgb_input_and_big_endian(tmp_path):
    m, q, s, o, _ = _gaussians(n=5)
    rgb = torch.rand(5, 3)
    write_ply(tmp_path / "c.ply", m, q, s, o, rgb)
    r = read_ply(tmp_path / "c.ply")
    assert torch.allclose(r.sh[:, 0] * SH_C0 + 0.5, rgb, atol=1e-6)
    # the same file re-encoded big endian reads the same
    raw = (tmp_path / "c.ply").read_bytes()
    cut = raw.index(b"end_header\n") + 11
    hdr = raw[:cut].replace(b"binary_little_endian", b"binary_big_endian")
    body = np.frombuffer(raw[cut:], "<f4").astype(">f4").tobytes()
    (tmp_path / "be.ply").write_bytes(hdr + body)
    assert torch.equal(read_ply(tmp_path / "be.ply").means, r.means)


def test_errors(tmp_path):
    m, q, s, o, sh = _gaussians(n=4, k=1)
    with pytest.raises(FileNotFoundError, match="ply file not found"):
        read_ply(tmp_path / "none.ply")
    (tmp_path / "x.ply").write_bytes(b"hello")
    with pytest.raises(ValueError, match="not a PLY file"):
        read_ply(tmp_path / "x.ply")
    p = write_ply(tmp_path / "g.ply", m, q, s, o, sh)
    raw = p.read_bytes()
    (tmp_path / "t.ply").write_bytes(raw[:-10])
    with pytest.raises(ValueError, match="truncated PLY, header declares 4 vertices"):
        read_ply(tmp_path / "t.ply")
    (tmp_path / "h.ply").write_bytes(raw[:40])
    with pytest.raises(ValueError, match="no 'end_header'"):
        read_ply(tmp_path / "h.ply")
    (tmp_path / "a.ply").write_bytes(raw.replace(b"binary_little_endian", b"ascii"))
    with pytest.raises(ValueError, match="format 'ascii' not supported"):
        read_ply(tmp_path / "a.ply")
    (tmp_path / "m.ply").write_bytes(raw.replace(b"property float opacity", b"property float opacitx"))
    with pytest.raises(ValueError, match=r"missing vertex properties \['opacity'\]"):
        read_ply(tmp_path / "m.ply")
    (tmp_path / "d.ply").write_bytes(raw.replace(b"property float x\n", b"property double x\n"))
    with pytest.raises(ValueError, match="must be float32"):
        read_ply(tmp_path / "d.ply")
    with pytest.raises(ValueError, match=r"means must have shape \[\*, 3\]"):
        write_ply(tmp_path / "b.ply", m[:, :2], q, s, o, sh)
    with pytest.raises(ValueError, match="K = \\(degree\\+1\\)\\^2"):
        write_ply(tmp_path / "b.ply", m, q, s, o, torch.zeros(4, 3, 3))
    with pytest.raises(ValueError, match="scales must be > 0"):
        write_ply(tmp_path / "b.ply", m, q, -s, o, sh)
    with pytest.raises(ValueError, match=r"opacities must lie in \[0, 1\]"):
        write_ply(tmp_path / "b.ply", m, q, s, o + 2, sh)
    with pytest.raises(ValueError, match="must end in .ply"):
        write_ply(tmp_path / "b.txt", m, q, s, o, sh)
    with pytest.raises(FileNotFoundError, match="output folder does not exist"):
        write_ply(tmp_path / "no" / "b.ply", m, q, s, o, sh)
