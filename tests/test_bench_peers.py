"""``clsplat bench peers`` (bench/peers.py): the peers it runs, the ones it skips and why, the
agreement checks, and the OpenSplat glue's projection convention."""
from __future__ import annotations

import json
import math

import pytest
import torch

from clsplat.bench import peers
from clsplat.bench.cli import main


def test_without_opensplat_it_says_so_and_checks_the_torch_peer(tmp_path, capsys):
    assert main(["peers", "--scenes", "tiny", "--repeats", "1", "--out", str(tmp_path)]) == 0
    assert "opensplat skipped (no --opensplat source tree given)" in capsys.readouterr().out
    res = json.loads((tmp_path / "peers.json").read_text())
    assert res["skipped"] == {"opensplat": "no --opensplat source tree given"}
    row = res["rows"][0]
    assert set(row["peers"]) == {"clsplat", "torch"}
    t = row["peers"]["torch"]
    # the float32 torch mirror renders the same image and gradients (issue 35: images and gradients agree)
    assert t["image_max_abs"] < 1e-4 and max(t["grad_rel"].values()) < 1e-4
    assert t["ratio_total"] == pytest.approx((row["peers"]["clsplat"]["fwd_ms"] + row["peers"]["clsplat"]["bwd_ms"])
                                             / (t["fwd_ms"] + t["bwd_ms"]))
    md = (tmp_path / "peers.md").read_text()
    assert "Skipped: opensplat" in md and "| random 300 at 96x64 |" in md and md.startswith("`clsplat bench peers")


def test_the_torch_peer_stops_at_its_size_limit(tmp_path):
    assert main(["peers", "--scenes", "tiny", "--repeats", "1", "--torch-max-n", "10", "--out", str(tmp_path)]) == 0
    assert set(json.loads((tmp_path / "peers.json").read_text())["rows"][0]["peers"]) == {"clsplat"}


def test_bad_arguments_are_named(tmp_path, capsys):
    for argv, name in ((["--opensplat", str(tmp_path)], "--opensplat"), (["--scenes", "huge"], "--scenes"),
                       (["--repeats", "0"], "--repeats"), (["--torch-max-n", "-1"], "--torch-max-n")):
        with pytest.raises(SystemExit) as e:
            main(["peers", *argv, "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and name in err and "Traceback" not in err
    with pytest.raises(FileNotFoundError, match="--opensplat"):
        peers.build_opensplat(tmp_path, tmp_path / "build")


def test_opensplat_projection_puts_points_where_the_pinhole_does():
    """OpenSplat's pixel centres are integers: u = 0.5 ((x_ndc + 1) W - 1) must equal
    fx x / z + cx - 0.5, clsplat's u less half a pixel, with an off-centre principal point too."""
    W, H = 96, 64
    K = torch.tensor([[80.0, 0, 41.0], [0, 75.0, 30.0], [0, 0, 1]])
    viewmat = torch.eye(4)
    viewmat[:3, 3] = torch.tensor([0.3, -0.2, 1.0])
    pts = torch.tensor([[0.5, 0.1, 4.0], [-1.0, 0.7, 9.0], [0.0, 0.0, 2.0]])
    hom = torch.cat([pts, torch.ones(3, 1)], 1) @ (peers._opengl_projection(K, W, H) @ viewmat).T
    ndc = hom[:, :3] / hom[:, 3:]
    u, v = 0.5 * ((ndc[:, 0] + 1) * W - 1), 0.5 * ((ndc[:, 1] + 1) * H - 1)
    cam = pts + viewmat[:3, 3]
    torch.testing.assert_close(u, K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2] - 0.5)
    torch.testing.assert_close(v, K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2] - 0.5)
    assert math.isclose(float(hom[0, 3]), float(cam[0, 2]))      # w is the view depth
