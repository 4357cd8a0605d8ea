"""models/common/view.py: a checkpoint (or run folder) of each model family becomes a scene for
``clsplat view`` / ``clsplat render``: its Gaussians, the cameras with their images and, per
family, depth maps (DrivingForward, PGT) or trajectory, LiDAR, boxes and a time slider (AutoSplat).
An unknown family or a file that is not a checkpoint is a ValueError naming the path."""
import numpy as np
import pytest
import torch

from clsplat.models.common.train import CHECKPOINT_FORMAT, save_checkpoint
from clsplat.models.registry import scene_from_checkpoint
from clsplat.viewer.render import render_view


def _untrained(tmp_path, family, model, preset):
    """A checkpoint of an untrained model (what matters here is its layout, not its quality)."""
    run = tmp_path / family
    run.mkdir()
    save_checkpoint(run / "checkpoint.pt", {"model": model.state_dict(), "step": 0}, family, preset)
    return run


def _check_scene(sc, n_cameras):
    assert len(sc) > 0 and torch.isfinite(sc.means).all()
    assert len(sc.cameras) == n_cameras and all(c.image is not None for c in sc.cameras)
    img, secs = render_view(sc, sc.cameras[0])
    assert img.shape == (sc.cameras[0].height, sc.cameras[0].width, 3) and np.isfinite(img).all()


def test_drivingforward_checkpoint(tmp_path):
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.cli import build_model
    preset = get_preset("drivingforward", "tiny")
    run = _untrained(tmp_path, "drivingforward", build_model(preset), preset)
    sc = scene_from_checkpoint(run / "checkpoint.pt")
    V = len(sc.cameras)
    assert V >= 1 and len(sc) == V * preset.height * preset.width    # SF: one Gaussian per input pixel
    _check_scene(sc, V)
    assert set(sc.depths) == {c.name for c in sc.cameras}
    assert all(d.shape == (preset.height, preset.width, 3) for d in sc.depths.values())
    # another input, picked in the viewer: the front camera alone, three frames -> 3 x 1 x H x W Gaussians
    other = sc.variant("sample 1, frames [-1, 0, 1], front camera")
    assert len(other.cameras) == 1 and len(other) == 3 * preset.height * preset.width
    names = [c.name for c in sc.cameras]
    back = sc.variant(f"sample 0, frames [0], camera {names[-1]}")   # any single camera of the rig
    assert [c.name for c in back.cameras] == [names[-1]] and len(back) == preset.height * preset.width
    assert [c.name for c in sc.variant("sample 0, frames [0], front three cameras").cameras] == names[:3]
    # without --data the run's own data (its metrics.json) is used; --data wins over it
    (run / "metrics.json").write_text('{"data": "pandaset:/no/such/folder"}')
    with pytest.raises(ValueError, match="/no/such/folder"):
        scene_from_checkpoint(run / "checkpoint.pt")
    assert len(scene_from_checkpoint(run / "checkpoint.pt", data="synthetic")) == len(sc)


def test_pgt_checkpoint(tmp_path):
    from clsplat.models.common.presets import get_preset
    from clsplat.models.pgt.model import PGT
    preset = get_preset("pgt", "tiny")
    run = _untrained(tmp_path, "pgt", PGT(preset), preset)
    sc = scene_from_checkpoint(run)      # the run folder
    n_in = sum(c.name.startswith("input") for c in sc.cameras)
    assert n_in == preset.num_views and len(sc) <= n_in * preset.height * preset.width
    _check_scene(sc, len(sc.cameras))
    assert len(sc.depths) == n_in
    one = [v for v in sc.variants if v.startswith("sample 1: ")]
    assert len(one) == 1 and len(sc.variant(one[0]).cameras) == len(sc.cameras)
    # one sample per camera of the preset: each camera can be picked as the input
    assert {v.split(": ")[1].split(",")[0].split("+")[0] for v in sc.variants} >= set(preset.cameras)


@pytest.mark.slow   # trains the tiny preset
def test_autosplat_run_folder(tmp_path):
    from clsplat.models.autosplat.cli import train
    run = tmp_path / "as"
    assert train(["--preset", "tiny", "--frames", "0:4", "--out", str(run), "--no-progress", "--stop-after", "2"]) == 0
    sc = scene_from_checkpoint(run)
    _check_scene(sc, len(sc.cameras))
    assert sc.trajectory.shape[1] == 3 and len(sc.trajectory) == 4
    assert sc.lidar is not None and sc.lidar.shape[1] == 3
    assert sc.boxes and len(sc.times) == 4 and sc.at_time is not None
    later = sc.at_time(sc.times[-1])
    moved = [not np.allclose(a.center, b.center) for a, b in zip(sc.boxes, later.boxes)]
    assert any(moved)                                   # the street's cars drive: their boxes move with t
    assert later.means.shape[1] == 3


def test_not_a_checkpoint_and_unknown_family(tmp_path):
    bad = tmp_path / "x.pt"
    bad.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="x.pt.*is not a scene"):
        scene_from_checkpoint(bad)
    ck = tmp_path / "y.pt"
    torch.save({"format": CHECKPOINT_FORMAT, "family": "nerf"}, ck)
    with pytest.raises(ValueError, match="y.pt.*unknown model family 'nerf'"):
        scene_from_checkpoint(ck)


class _Payload:
    """A pickle that runs ``touch MARKER`` when loaded."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        import os
        return os.system, (f"touch {self.marker}",)


def test_view_runs_no_code_from_data_unless_told_to_trust_it(tmp_path, capsys):
    """``clsplat view CHECKPOINT --data pandaset:DIR``, DIR's LiDAR a pickle payload: refused by
    default naming the file; only ``--trust-pickle`` runs it (then it is no DataFrame)."""
    import gzip
    import pickle

    from clsplat.cli import console
    from clsplat.data.pandaset import write_pandaset
    from clsplat.data.synthetic import generate_sequence
    from clsplat.models.common.presets import get_preset
    from clsplat.models.drivingforward.cli import build_model

    preset = get_preset("drivingforward", "tiny")
    run = _untrained(tmp_path, "drivingforward", build_model(preset), preset)
    root = write_pandaset(generate_sequence(height=16, width=24, num_frames=3, seed=1), tmp_path / "seq")
    marker = tmp_path / "ran"
    with gzip.open(root / "lidar" / "00.pkl.gz", "wb") as fh:
        pickle.dump(_Payload(marker), fh)
    args = ["view", str(run), "--data", f"pandaset:{root}", "--port", "0"]
    capsys.readouterr()
    assert console(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("clsplat view: ") and "lidar/00.pkl.gz" in err and "safe mode refuses this pickle" in err
    assert not marker.exists()
    assert console(args + ["--trust-pickle"]) == 2
    assert marker.exists()                                 # the explicit opt-out trusted the file
    assert "holds a int, not a pandas DataFrame" in capsys.readouterr().err


@pytest.mark.slow   # drives a headless browser
def test_train_view_costs_nothing_without_a_browser_and_refreshes_with_one(two_colour_ply):
    """TrainView: no browser, no refresh (the <10% overhead); a headless Chromium connected: the
    Gaussians and the loss plot are refreshed every N steps and the exact render runs in the
    calling (training) thread."""
    pytest.importorskip("viser", reason="the view extra is not installed")
    from clsplat.models.common.view import TrainView
    from clsplat.viewer.browser import HeadlessChromium, find_chromium
    from clsplat.viewer.scene import scene_from_ply

    calls = []

    def scene_fn():
        calls.append(1)
        sc = scene_from_ply(two_colour_ply[0])
        sc.depths = {"front": np.full((8, 8, 3), min(len(calls), 255) / 255, np.float32)}  # as DF/PGT predict
        return sc

    tv = TrainView(scene_fn, port=0, every=2)
    try:
        for step in range(1, 6):
            tv.on_step(step, {"loss": 1.0 / step})
        assert len(calls) == 1 and tv.refreshes == 0 and tv.viewer.renders == 0   # only the initial scene
        assert tv.losses == [1.0, 0.5, 1 / 3, 0.25, 0.2]
        import os
        if find_chromium() is None and os.environ.get("CLSPLAT_REQUIRE_BROWSER") != "1":
            return
        import time
        with HeadlessChromium(tv.viewer.url, 800, 500):
            t0 = time.time()
            step = 5
            while (tv.refreshes < 2 or tv.viewer.renders < 1) and time.time() - t0 < 120:
                step += 1
                tv.on_step(step, {"loss": 1.0 / step})
                time.sleep(0.1)
            assert tv.refreshes >= 2 and tv.viewer.renders >= 1
            # the depth panel shows the latest prediction (updated in place, one image)
            assert len(tv.viewer._depth_handles) == 1
            assert int(tv.viewer._depth_handles[0].image[0, 0, 0]) == min(len(calls), 255)
            assert len(tv.plot.data[0]) == len(tv.plot.data[1]) > 5
    finally:
        tv.close()


def test_model_snapshot_leaves_the_run_unchanged():
    """What --view shows of a training model is built in eval mode, without gradients, and leaves
    torch's RNG and the model's mode as they were: a watched run is the run unwatched."""
    from clsplat.models.common.view import model_snapshot
    from clsplat.viewer.scene import ViewScene

    net = torch.nn.Sequential(torch.nn.Linear(3, 3), torch.nn.Dropout(0.5))
    net.train()
    torch.manual_seed(1)
    expected = torch.rand(4)
    torch.manual_seed(1)
    seen = {}

    def build():
        seen["training"], seen["grad"] = net.training, torch.is_grad_enabled()
        x = torch.randn(5, 3)                      # draws from the global RNG
        y = net(x)
        seen["deterministic"] = torch.equal(y, net(x))   # dropout off in eval mode
        n = 5
        return ViewScene(y.detach(), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), 0.1),
                         torch.full((n,), 0.5), torch.zeros(n, 1, 3))

    sc = model_snapshot(net, build)
    assert len(sc) == 5 and seen == {"training": False, "grad": False, "deterministic": True}
    assert net.training and torch.is_grad_enabled()
    assert torch.equal(torch.rand(4), expected)      # the RNG stream continues as if nothing ran
