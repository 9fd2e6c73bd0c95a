"""bench/bench_dars_error.py: W strata of the test error, DARS's selection distance, run pairing."""

import importlib.util
import json
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from toolkit.pixels import PackedViews

_PATH = Path(__file__).resolve().parents[1] / "bench" / "bench_dars_error.py"
_spec = importlib.util.spec_from_file_location("bench_dars_error", _PATH)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def test_selection_tv_matches_the_closed_form():
    # W uniform on [0, 1] (rank-normalised): p ∝ (1 - ρ) + ρ W, TV = 0.5 E|p / mean - 1| = 0.5 ρ E|W - 0.5| / (1 - ρ / 2)
    w = torch.linspace(0.0, 1.0, 40001).reshape(1, 1, -1)
    run = SimpleNamespace(weight_maps=PackedViews.from_maps(w))
    assert bench.selection_tv(run, 0.5) == pytest.approx(0.5 * 0.25 / 1.5, rel=1e-3)
    assert bench.selection_tv(run, 0.0) == pytest.approx(0.0, abs=1e-12)
    assert bench.selection_tv(run, 1.0) == pytest.approx(0.25, rel=1e-3)  # 0.5 E|2W - 1|
    assert bench.selection_tv(SimpleNamespace(weight_maps=None), 0.5) is None


class _Out:
    def __init__(self, rgb):
        self.rgb = rgb

    def as_dict(self):
        return {"rgb": self.rgb}


def test_stratified_psnr_puts_edge_error_in_the_hard_stratum():
    # a photo with one sharp vertical edge; the "render" is exact except for an error on the edge's columns:
    # the hard stratum (top 10 % of W, which peaks at the edge) holds that error
    h = w = 40
    img = torch.full((3, h, w), 0.2)
    img[:, :, w // 2:] = 0.8
    pred = img + 0.01  # a small error everywhere (40 dB) ...
    pred[:, :, w // 2 - 1:w // 2 + 1] += 0.1  # ... and a large one on the two columns at the edge

    class _Scene(SimpleNamespace):
        def __len__(self):
            return 1

    scene = _Scene(extras_available=lambda: [], cameras=None, srgb=False, load_image=lambda i: img)
    run = SimpleNamespace(load_split=lambda split: scene, render=lambda cams, i, chunk: _Out(pred.permute(1, 2, 0)))
    out = bench.stratified_psnr(run, every=1)
    assert out["views"] == 1 and out["w_inputs"] == "test photo (G)"
    assert out["flat"] == pytest.approx(40.0, abs=0.01)  # the flat half holds none of the edge error
    assert out["hard"] < out["all"] < out["flat"]
    # the top 10 % (160 px) holds the 80 edge pixels: MSE ≈ (80 * 0.11² + 80 * 0.01²) / 160
    assert out["hard"] == pytest.approx(-10 * math.log10((0.11 ** 2 + 0.01 ** 2) / 2), abs=0.5)


def test_collect_runs_pairs_folders_and_refuses_duplicates(tmp_path):
    def folder(name, seeds):
        d = tmp_path / name
        d.mkdir()
        variants = [{"name": v, "seeds": seeds, "run": f"/r/{name}/{v}",
                     "runs": [{"seed": s, "run": f"/r/{name}/{v}/seed_{s}"} for s in seeds]}
                    for v in ("full", "no_dars")]
        (d / "ablation.json").write_text(json.dumps({"scene": str(tmp_path / "scene"), "variants": variants}))
        return d

    runs = bench.collect_runs([folder("a", [0, 1]), folder("b", [2])])
    assert sorted((r["variant"], r["seed"]) for r in runs) == [("full", 0), ("full", 1), ("full", 2),
                                                                 ("no_dars", 0), ("no_dars", 1), ("no_dars", 2)]
    with pytest.raises(SystemExit, match="two folders"):
        bench.collect_runs([tmp_path / "a", folder("c", [1])])
    with pytest.raises(SystemExit, match="no ablation.json"):
        bench.collect_runs([tmp_path])
