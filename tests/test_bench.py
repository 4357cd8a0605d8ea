"""The benchmark reports in their --quick configuration: files, JSON schema, float64 baseline."""
import json

import torch

import pytest

from clsplat.bench.cli import main


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    d = tmp_path_factory.mktemp("bench")
    assert main(["all", "--quick", "--out", str(d), "--repeats", "1"]) == 0
    return d


@pytest.mark.slow   # runs the whole benchmark suite (bench all --quick)
def test_files(out):
    for name in ("stages.json", "stages.md", "precision.json", "precision.md", "precision.png",
                 "stability.json", "stability.md", "report.md"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert (out / "precision.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow   # runs the whole benchmark suite (bench all --quick)
def test_stages_schema(out):
    r = json.loads((out / "stages.json").read_text())
    assert r["limits"]["bandwidth_GBps"] > 0 and r["limits"]["flops_f32_G"] > 0
    for key in ("A", "B"):
        s = r["scenes"][key]
        assert {"project", "composite"} <= set(s["stages_ms"])
        assert any(n.startswith("sort") for n in s["stages_ms"])  # the depth sort (issue 35)
        for st in s["stages_ms"].values():
            assert {"median", "min", "max", "spread_pct"} <= set(st)
        assert s["kernel_total_ms"]["median"] > 0
        ev = s["evaluations"]
        assert 0 < ev["useful"] <= ev["kernel"] <= ev["segment"]
        cc = s["composite_counts"]  # counted flops (CLS_COUNT)
        assert cc["tested"] >= cc["extent"] >= cc["sigma"] >= cc["alpha"] > 0 and cc["flops"] > 0
        f = s["limit_fraction"]["composite"]
        assert f["limit"] == "flops_f32 (counted)" and 0 < f["fraction"] and f["assumed_40"] > 0
        sv = s["sort_vs_numpy"]
        assert sv["correct"] is True
        assert {"clsplat_kernel_ms", "np_argsort_stable_ms", "np_sort_ms"} <= set(sv["medians_ms"])
    for key in ("scaling_n", "scaling_pixels"):
        assert len(r[key]["rows"]) >= 2 and "kernel_total_ms" in r[key]["loglog_slope"]
        assert "backward_kernel_total_ms" in r[key]["loglog_slope"]
        assert all(row["backward_kernel_total_ms"] > 0 for row in r[key]["rows"])


@pytest.mark.slow   # runs the whole benchmark suite (bench all --quick)
def test_backward_schema(out):
    r = json.loads((out / "stages.json").read_text())
    for key in ("A", "B"):
        b = r["backward"][key]
        assert {"composite_bwd", "reduce", "project_bwd"} <= set(b["backward_stages_ms"])
        if key == "A":  # SH degree 3
            assert "sh_bwd" in b["backward_stages_ms"]
        for st in b["backward_stages_ms"].values():
            assert {"median", "min", "max", "spread_pct"} <= set(st)
        assert b["backward_kernel_total_ms"]["median"] > 0 and b["forward_kernel_total_ms"]["median"] > 0
        assert b["bwd_fwd_ratio_kernels"] > 0
        assert "backward_kernel_total" in b["first_call_ms"]
        m = b["slot_memory"]
        assert m["sizeof_real"] == 4 and m["bytes_per_intersection"] == m["slot_width"] * 4
        assert m["total_bytes"] == m["bytes_per_intersection"] * m["intersections"] > 0
        t = r["training"][key]
        assert t["steps_per_s"] > 0 and t["step_ms"]["median"] > 0
        sp = r["specialisation"][key]
        cases = {c["case"] for c in sp["cases"]}
        assert {"no_depth", "frozen_colours_only", "frozen_means_only"} <= cases
        assert ("no_sh" in cases) == (key == "A")
        assert all(c["ratio_total"] > 0 for c in sp["cases"])
    md = (out / "stages.md").read_text()
    for text in ("Backward pass", "Training step", "bytes / intersection", "Specialisation gains"):
        assert text in md


@pytest.mark.slow   # runs the whole benchmark suite (bench all --quick)
def test_precision_schema(out):
    r = json.loads((out / "precision.json").read_text())
    assert len(r["scenes"]) == 2
    for rows in r["scenes"].values():
        knobs = {row["knob"] for row in rows}
        assert {"precision", "alpha_min", "t_min", "radius_rule", "fast_math", "prune_budget"} <= knobs
        for row in rows:
            assert {"value", "kernel_ms", "max_abs", "rmse", "psnr", "grad_rel_l2"} <= set(row)
        f64 = [row for row in rows if row["knob"] == "precision" and row["value"] == "float64"]
        assert len(f64) == 1 and f64[0]["max_abs"] <= 1e-9
        assert any(row.get("pareto") for row in rows)
        assert all("max_abs_vs_default" in row for row in rows)
    assert set(r["faster_within_1_255"]) == set(r["scenes"])
    for f in r["faster_within_1_255"].values():
        assert {"vs_f64", "vs_default", "default_kernel_ms", "tolerance"} <= set(f)
    assert "Faster than the float32 default" in (out / "precision.md").read_text()


@pytest.mark.slow   # runs the whole benchmark suite (bench all --quick)
def test_stability_schema(out):
    r = json.loads((out / "stability.json").read_text())
    cats = {row["category"] for row in r["rows"]}
    assert {"needle", "grazing", "huge", "sub-pixel", "opaque stack", "equal depths", "behind camera",
            "zero scales", "NaN/Inf input", "zero quaternion"} <= cats
    for row in r["rows"]:
        if row["category"] in ("NaN/Inf input", "zero quaternion"):
            assert row["outcome"] == "ValueError"
        else:
            assert row["outcome"] == "rendered", row
            assert row["nonfinite_f32"] == 0 and row["nonfinite_f64"] == 0
            assert {"grad_rel_l2", "grad_rel_l2_extreme", "grad_nonfinite_f32", "grad_nonfinite_f64"} <= set(row), row
            assert row["grad_rel_l2"] >= 0


def test_percall_report(tmp_path, capsys):
    """``clsplat bench percall`` times forward and backward of the tiny scene and writes one JSON
    line per scene and layout; a bad scene is one line naming --scenes."""
    js = tmp_path / "percall.jsonl"
    assert main(["percall", "--scenes", "tiny", "--repeats", "2", "--layout", "both", "--json", str(js)]) == 0
    rows = [json.loads(line) for line in js.read_text().splitlines()]
    assert len(rows) == 2 and {r["packed"] for r in rows} == {True, False}
    for r in rows:
        assert r["fwd_ms"] > 0 and r["bwd_ms"] > 0 and r["kernel_ms"] > 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["percall", "--scenes", "huge"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--scenes" in err[0]


@pytest.mark.slow   # runs the compositing benchmark
def test_composite_report(tmp_path):
    """``clsplat bench composite``: both compositing implementations side by side, same images."""
    assert main(["composite", "--quick", "--out", str(tmp_path), "--repeats", "1"]) == 0
    r = json.loads((tmp_path / "composite.json").read_text())
    assert (tmp_path / "composite.md").read_text().startswith("## Compositing")
    for key in ("A", "B"):
        s = r["scenes"][key]
        assert all(s["bitwise_equal"].values()), s["max_abs_diff"]
        ev = s["evaluations"]
        assert 0 < ev["kernel_alpha"] <= ev["kernel"] and ev["useful"] <= ev["kernel"]
        for impl in ("baseline", "tuned"):
            t = s["impls"][impl]
            assert t["stages_ms"]["composite"]["median"] > 0 and t["composite_pct_peak"] > 0
            assert t["fwd_bwd"]["composite_bwd"]["median"] > 0
        assert s["speedup"]["fwd_bwd_kernels"] > 0 and len(s["speedup"]["fwd_bwd_per_round"]) == 1


def _alpha_passed_reference(meta, W: int, H: int, ts: int, pix: int, cfg) -> int:
    """Torch: per work-item (pix pixels of a tile row), the samples of its tile, in sorted
    order, at which some pixel not yet done has sigma >= 0 and alpha >= ALPHA_MIN."""
    xy, con = meta["means2d"].detach().reshape(-1, 2), meta["conics"].reshape(-1, 3)
    op, ids = meta["opacities"].reshape(-1), meta["flatten_ids"].to(torch.int64)
    off = meta["isect_offsets"].reshape(-1).tolist() + [ids.numel()]
    tx, ty = meta["tile_width"], meta["tile_height"]
    ly, lx = torch.meshgrid(torch.arange(ts), torch.arange(ts), indexing="ij")
    total = 0
    for t in range(len(off) - 1):
        py = ly.reshape(-1) + (t % (tx * ty)) // tx * ts
        px = lx.reshape(-1) + (t % (tx * ty)) % tx * ts
        done = (px >= W) | (py >= H)
        T = torch.ones(ts * ts, dtype=xy.dtype)
        for g in ids[off[t]:off[t + 1]].tolist():
            dx, dy = xy[g, 0] - (px + 0.5), xy[g, 1] - (py + 0.5)
            sigma = 0.5 * (con[g, 0] * dx * dx + con[g, 2] * dy * dy) + con[g, 1] * dx * dy
            alpha = torch.clamp_max(op[g] * torch.exp(-sigma), cfg.alpha_max)
            valid = ~done & (sigma >= 0) & (alpha >= cfg.alpha_min)
            total += int(valid.reshape(ts, ts // pix, pix).any(-1).sum())
            next_T = T * (1 - alpha)
            stop = valid & (next_T <= cfg.t_min)
            done, valid = done | stop, valid & ~stop
            T = torch.where(valid, next_T, T)
    return total


def test_composite_counts_are_consistent(make_scene):
    """The compositing kernel's sample counters (CLS_COUNT, the bench's counted flops): the
    counted run composites rasterization()'s image bit for bit; every class is within the one
    before; the samples past the alpha test are what a torch replay of the kernel's decisions
    finds; the tuned and baseline builds test, pass the extent test and blend alike (only the
    tuned one has the sigma bound)."""
    import clsplat
    from clsplat.bench.stages import COMPOSITE_OPS, composite_counts, composite_flops
    from clsplat.config import RenderConfig

    sc = make_scene(seed=3, N=80, C=2, width=40, height=36) | {"sh_degree": None, "name": "counts"}
    got = {}
    for impl in ("tuned", "baseline"):
        cfg = RenderConfig(precision="float64", composite_impl=impl)
        r = got[impl] = composite_counts(sc, cfg)
        img, _, meta = clsplat.rasterization(
            *(sc[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")),
            sc["width"], sc["height"], packed=False, config=cfg)
        assert torch.equal(r["image"], img)
        assert r["tested"] >= r["extent"] >= r["sigma"] >= r["alpha"] > 0
        assert r["alpha"] == _alpha_passed_reference(meta, sc["width"], sc["height"], 16, r["pix"], cfg)
        assert r["flops"] == composite_flops(r) > 0
    t, b = got["tuned"], got["baseline"]
    assert (t["tested"], t["extent"], t["alpha"]) == (b["tested"], b["extent"], b["alpha"])
    assert b["sigma"] == b["extent"] and t["sigma"] <= t["extent"]
    assert t["pix"] == 4 and t["cchunk"] == 3  # float64 on the CPU: 4 doubles per item
    assert t["flops"] == (t["tested"] * COMPOSITE_OPS["tested"]["tuned"] + t["extent"] * (9 * 4 + 3)
                          + t["sigma"] * 35 * 4 + t["alpha"] * (6 + 2 * 3) * 4)
