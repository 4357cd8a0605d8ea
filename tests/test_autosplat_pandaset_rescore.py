"""bench/experiments/autosplat_pandaset_rescore.py: the learnt corrections' size is read from the
model's own table (interpolated at held-out frames, only where the track is present), and a run
folder that is not finished fails in one line."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from clsplat.models.autosplat.fusion import PoseCorrection


def _trainer(on: bool = True):
    trained = torch.tensor([True, False, True, True])
    pose = PoseCorrection(2, 4, trained)
    with torch.no_grad():
        pose.delta[0, 0, 3:] = torch.tensor([0.3, 0.4, 0.0])           # 0.5 m
        pose.delta[0, 2, 3:] = torch.tensor([0.0, 0.0, 0.1])           # 0.1 m
        pose.delta[1, 3, :3] = torch.tensor([0.0, 0.0, 0.02])          # 1.146 deg; track 1 absent there
    present = torch.tensor([[True, True, True, False], [True, True, True, False]])
    model = SimpleNamespace(present=present, pose=pose)
    return SimpleNamespace(model=model, tracks=[0, 1], switches=SimpleNamespace(pose_correction=on))


def test_correction_size_reads_the_table_where_the_tracks_are(bench_script):
    rs = bench_script("autosplat_pandaset_rescore")
    c = rs.correction_size(_trainer(), [0, 2, 3])
    assert c["boxes"] == 4                                   # frame 3 has no track present
    assert c["translation_m_median"] == pytest.approx(0.05, abs=1e-6)   # 0.5, 0.1, 0, 0
    assert c["rotation_deg_p90"] == pytest.approx(0.0, abs=1e-9)        # the rotated row is absent
    held = rs.correction_size(_trainer(), [1])     # halfway between frames 0 and 2 (track 0), 0 (track 1)
    half = float(torch.tensor([0.15, 0.2, 0.05]).norm())
    assert held["boxes"] == 2 and held["translation_m_p90"] == pytest.approx(0.9 * half, rel=1e-5)
    assert rs.correction_size(_trainer(on=False), [0]) is None


def test_an_unfinished_run_fails_in_one_line(tmp_path, capsys, bench_script):
    rs = bench_script("autosplat_pandaset_rescore")
    with pytest.raises(SystemExit):
        rs.main([str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith(f"runs: {tmp_path / 'metrics.json'} not found (a finished run folder expected)")


def test_both_frame_sets_of_one_run_stay_apart_in_the_tables(tmp_path, capsys, bench_script):
    rs = bench_script("autosplat_pandaset_rescore")
    parts = {p: 20.0 for p in rs.PARTS}

    def rec(frames: str, image: float) -> dict:
        return {"run": "i36_pbusy_M_s0", "frames": frames, "metrics": parts, "pixels": {p: 1 for p in rs.PARTS},
                "inside": 1.0, "metrics_json": {"image": image, "objects": 20.0}, "tracks": {},
                "moving": {"true": 1, "run": 1, "run_not_true": 0}, "correction": None}
    j = tmp_path / "out.json"
    import json
    j.write_text(json.dumps([rec("test", 30.0), rec("train", 32.0)]))
    rs.main(["--from-json", str(j)])
    out = capsys.readouterr().out
    assert "| i36_pbusy_M_s0 [train] | 32.00" in out and "| i36_pbusy_M_s0 | 30.00" in out
    assert "| pbusy | M | 1 | 30.00 |" in out and "| pbusy | M [train] | 1 | 32.00 |" in out
