"""Per-object reporting (issue 36): labels map to classes, per-class PSNR and SSIM equal a hand
computation on constructed images with known boxes, the worst-tracks sheet is written, and a run's
``metrics.json`` carries the ``objects`` section."""
import math

import numpy as np
import pytest
import torch

from clsplat.data.synthetic import generate_sequence
from clsplat.models.autosplat.object_report import (MIN_TRACK_PIXELS, OBJECT_CLASSES, object_class, object_report,
                                                    object_scores, track_masks, worst_tracks_sheet)

C1, C2 = 0.01 ** 2, 0.03 ** 2


@pytest.mark.parametrize("label,cls", [("car", "car"), ("Car", "car"), ("Pickup Truck", "car"), ("vehicle.car", "car"),
                                       ("Pedestrian", "pedestrian"), ("Pedestrian with Object", "pedestrian"),
                                       ("human.pedestrian.adult", "pedestrian"), ("pedestrian", "pedestrian"),
                                       ("Medium-sized Truck", "other"), ("Bus", "other"), ("Motorcycle", "other"),
                                       ("bicycle", "other"), ("", "other")])
def test_labels_map_to_the_three_classes(label, cls):
    assert object_class(label) == cls
    assert cls in OBJECT_CLASSES


def _scene():
    """One view of 2 cameras, 24 x 32: truth 0.5 everywhere; the render equals it except in a car's
    box (0.3: error 0.2) and a pedestrian's box (0.4: error 0.1); a truck's box is rendered exactly."""
    truth = torch.full((2, 24, 32, 3), 0.5)
    render = truth.clone()
    car = np.zeros((2, 24, 32), bool)
    car[0, 4:10, 5:15] = True                   # 60 pixels in camera 0
    car[1, 0:3, 0:4] = True                     # 12 pixels in camera 1
    ped = np.zeros((2, 24, 32), bool)
    ped[1, 8:20, 20:24] = True                  # 48 pixels
    truck = np.zeros((2, 24, 32), bool)
    truck[0, 15:20, 20:30] = True
    render[torch.from_numpy(car)] = 0.3
    render[torch.from_numpy(ped)] = 0.4
    return render, truth, {1: car, 2: ped, 3: truck}, {1: "Car", 2: "Pedestrian", 3: "Semi-truck"}


def test_per_class_psnr_equals_the_hand_computation():
    render, truth, masks, labels = _scene()
    s = object_scores([render], [truth], [masks], labels)
    pc = s["per_class"]
    assert pc["car"]["pixels"] == 72 and pc["pedestrian"]["pixels"] == 48 and pc["other"]["pixels"] == 50
    # every pixel of the car is off by 0.2 in all channels: MSE 0.04, PSNR = -10 log10(0.04)
    assert pc["car"]["psnr"] == pytest.approx(-10 * math.log10(0.04), abs=1e-4)
    assert pc["pedestrian"]["psnr"] == pytest.approx(20.0, abs=1e-4)      # MSE 0.01
    assert pc["other"]["psnr"] == math.inf                                 # rendered exactly
    assert pc["other"]["ssim"] == pytest.approx(1.0, abs=1e-6)
    assert [pc[c]["tracks"] for c in OBJECT_CLASSES] == [1, 1, 1]
    assert s["per_track"][1]["best_view"] == (0, 0, 60)
    # pooled, not averaged per track: two views of the car, the second rendered exactly
    s2 = object_scores([render, truth.clone()], [truth, truth], [masks, masks], labels)
    assert s2["per_class"]["car"]["psnr"] == pytest.approx(-10 * math.log10(0.02), abs=1e-4)
    assert s2["per_class"]["car"]["pixels"] == 144


def test_per_class_ssim_equals_the_hand_computation():
    """Constant images a (render) and b (truth): every window has mean a / b and no variance, so the
    SSIM map is (2ab + C1) / (a^2 + b^2 + C1) at every pixel, also at the reflect-padded border."""
    a, b = 0.3, 0.6
    render, truth = torch.full((1, 20, 20, 3), a), torch.full((1, 20, 20, 3), b)
    m = np.zeros((1, 20, 20), bool)
    m[0, 0:5, 12:20] = True
    s = object_scores([render], [truth], [{7: m}], {7: "pedestrian"})
    want = (2 * a * b + C1) / (a * a + b * b + C1)
    assert s["per_class"]["pedestrian"]["ssim"] == pytest.approx(want, abs=1e-5)
    assert s["per_class"]["pedestrian"]["psnr"] == pytest.approx(-10 * math.log10(0.09), abs=1e-4)
    assert s["per_class"]["car"] == {"psnr": None, "ssim": None, "pixels": 0, "tracks": 0}


def test_mismatched_views_are_a_clear_error():
    render, truth, masks, labels = _scene()
    with pytest.raises(ValueError, match="one entry per view"):
        object_scores([render], [truth, truth], [masks], labels)
    with pytest.raises(ValueError, match=r"masks\[0\]\[1\]"):
        object_scores([render], [truth], [{1: np.zeros((2, 5, 5), bool)}], labels)


def test_the_worst_tracks_sheet_ranks_by_psnr(tmp_path):
    render, truth, masks, labels = _scene()
    s = object_scores([render], [truth], [masks], labels)
    rows = worst_tracks_sheet([render], [truth], [masks], s, [3], ["CAM_A", "CAM_B"], tmp_path / "w.png", worst=2)
    assert rows == [1, 2]                                    # car (14.0 dB), then pedestrian (20 dB)
    assert (tmp_path / "w.png").stat().st_size > 1000
    tiny = {1: np.zeros((2, 24, 32), bool)}
    tiny[1][0, :2, :MIN_TRACK_PIXELS // 2] = True             # many pixels over two views, too few in either
    tiny[1][1, :2, :MIN_TRACK_PIXELS // 2 - 1] = True
    tiny[1][0, 0, 0] = False
    s = object_scores([render], [truth], [tiny], labels)
    assert worst_tracks_sheet([render], [truth], [tiny], s, [3], ["A", "B"], tmp_path / "x.png") == []
    assert not (tmp_path / "x.png").exists()


def test_track_masks_are_the_foreground_masks_of_each_track():
    """Box pixels (no instance masks) and instance pixels: track by track, the masks equal
    ``foreground_mask`` of that track alone, and tracks without a pixel are left out."""
    from dataclasses import replace

    from clsplat.data.scene import DrivingSequence
    from clsplat.models.autosplat.background import foreground_mask
    seq = generate_sequence(height=36, width=64, num_frames=1, lidar=False, world="busy", seed=1)
    cams = list(seq.camera_names)
    boxes_only = DrivingSequence(seq.cameras, [replace(f, instances={}) for f in seq.frames], seq.name, seq.metadata)
    tracks = sorted({b.track_id for b in seq.frames[0].boxes})
    for s in (seq, boxes_only):
        masks = track_masks(s, 0, cams, tracks + [999])
        assert 999 not in masks and len(masks) >= 10
        for t in tracks:
            want = foreground_mask(s, 0, cams, {t})
            assert np.array_equal(masks[t], want) if t in masks else not want.any()


def test_object_report_on_the_generated_street(tmp_path):
    """On generated frames the masks are the instance masks; a render equal to the truth scores
    inf everywhere, and a darkened car pixel set lowers the car class alone."""
    seq = generate_sequence(height=48, width=80, num_frames=3, lidar=False, cameras=("CAM_FRONT", "CAM_BACK"), dt=0.2)
    cams = ["CAM_FRONT", "CAM_BACK"]
    truths = [torch.from_numpy(seq.images(i, cams)) for i in (1, 2)]
    masks = track_masks(seq, 1, cams, [1, 2])
    assert masks and all(np.array_equal(m, np.stack([seq.frames[1].instances[c] == t for c in cams]))
                         for t, m in masks.items())
    rep = object_report(seq, cams, [1, 2], [t.clone() for t in truths], truths, 0.5, tmp_path / "w.png")
    assert rep["per_class"]["car"]["psnr"] == math.inf and rep["per_class"]["car"]["pixels"] > 0
    assert rep["per_class"]["pedestrian"]["pixels"] == 0
    dark = [t.clone() for t in truths]
    for k, i in enumerate((1, 2)):
        inst = torch.from_numpy(np.stack([seq.frames[i].instances[c] for c in cams]))
        dark[k][inst == 1] = 0.0
    rep = object_report(seq, cams, [1, 2], dark, truths, 0.5, tmp_path / "w.png")
    assert rep["per_track"]["1"]["psnr"] < 20 and rep["per_track"]["2"]["psnr"] == math.inf
    assert rep["static_per_class"]["car"]["tracks"] >= 1 and rep["static_per_class"]["car"]["psnr"] == math.inf
    assert set(rep["per_track"]) == {"1", "2"}                   # the moving tracks alone
    assert rep["worst"][0] == 1 and rep["sheet"] == "w.png" and (tmp_path / "w.png").is_file()


@pytest.mark.slow   # reads the session's trained tiny run (conftest autosplat_tiny_run)
def test_a_runs_metrics_carry_the_objects_section(autosplat_tiny_run):
    """``clsplat train autosplat`` writes the section: the car class pools the same pixels as
    ``all.psnr_objects`` on the built-in street (every mover a car), and the parked cars beside."""
    import json
    m = json.loads((autosplat_tiny_run / "metrics.json").read_text())
    o = m["objects"]
    assert set(o["per_class"]) == set(OBJECT_CLASSES) and o["frames"] == m["protocol"]["test_frames"]
    car = o["per_class"]["car"]
    if m["all"]["psnr_objects"] is None:
        assert car["pixels"] == 0 and car["psnr"] is None
    else:
        assert car["psnr"] == pytest.approx(m["all"]["psnr_objects"], abs=1e-6)
    assert o["per_class"]["pedestrian"]["pixels"] == 0 and "car" in o["static_per_class"]
    assert (o["sheet"] is None) == (not o["worst"])
    if o["sheet"]:
        assert (autosplat_tiny_run / o["sheet"]).is_file()
