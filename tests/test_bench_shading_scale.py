"""bench/bench_shading_scale.py: irradiance at rendered vs true normals, and the albedo level it implies."""

import importlib.util
from pathlib import Path

import pytest
import torch

from toolkit.losses import depth_normals

_PATH = Path(__file__).resolve().parents[1] / "bench" / "bench_shading_scale.py"
_spec = importlib.util.spec_from_file_location("bench_shading_scale", _PATH)
bss = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bss)


def _light_from_above() -> torch.Tensor:
    """A grey ambient term plus a strong band-1 z lobe (light from +z)."""
    sh = torch.zeros(9, 3)
    sh[0] = 1.0
    sh[2] = 0.8  # Y_1,0 ~ z in the (y, z, x) band-1 order
    return sh


def test_normals_facing_away_from_the_light_lower_the_irradiance_and_need_a_brighter_albedo():
    up = torch.tensor([[0.0, 0.0, 1.0]]).repeat(50, 1)
    side = torch.tensor([[1.0, 0.0, 0.0]]).repeat(50, 1)
    down = torch.tensor([[0.0, 0.0, -1.0]]).repeat(50, 1)
    a = torch.full((50, 3), 0.2)
    sh = _light_from_above()
    same = bss.shading_scale(sh, up, up, a, a, sh)
    assert same["E_pred"] == pytest.approx(same["E_true"]) and same["normal_mae"] == pytest.approx(0.0, abs=1e-3)
    away = bss.shading_scale(sh, down, up, a * 3, a, sh * 2)
    assert away["E_pred"] < 0.5 * away["E_true"]  # the rendered normal faces away from the light
    assert away["normal_mae"] == pytest.approx(180.0, abs=1e-3)
    assert away["E_truth"] == pytest.approx(2 * away["E_true"])
    tilted = bss.shading_scale(sh, side, up, a, a)
    assert tilted["E_truth"] is None and tilted["normal_mae"] == pytest.approx(90.0, abs=1e-3)
    assert away["E_pred"] < tilted["E_pred"] < tilted["E_true"]


def test_pooled_weights_views_by_pixels_and_forms_the_ratios():
    rows = [{"E_pred": 1.0, "E_true": 2.0, "E_truth": 4.0, "albedo_pred": 0.4, "albedo_true": 0.2, "normal_mae": 10.0,
             "pixels": 30},
            {"E_pred": 3.0, "E_true": 2.0, "E_truth": 4.0, "albedo_pred": 0.2, "albedo_true": 0.2, "normal_mae": 50.0,
             "pixels": 10}]
    p = bss.pooled(rows)
    assert p["pixels"] == 40
    assert p["E_pred"] == pytest.approx(1.5) and p["E_pred_over_true"] == pytest.approx(0.75)
    assert p["albedo_pred_over_true"] == pytest.approx(0.35 / 0.2)
    assert p["normal_mae"] == pytest.approx(20.0) and p["E_truth_over_true"] == pytest.approx(2.0)
    rows[1]["E_truth"] = None
    assert bss.pooled(rows)["E_truth_over_true"] is None


def test_no_pixels_is_an_error():
    with pytest.raises(ValueError, match="no pixels"):
        bss.shading_scale(torch.zeros(9, 3), torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 3))


def test_main_without_runs_skips_and_a_missing_run_is_a_clear_error(capsys, tmp_path):
    assert bss.main([]) == 0  # `make bench` runs it without arguments
    assert "skipped" in capsys.readouterr().out
    assert bss.main([str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "nope" in capsys.readouterr().err


def test_depth_normals_of_a_plane_face_the_camera():
    h = w = 9
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    d = torch.nn.functional.normalize(torch.stack([(u - 4) / 8, (v - 4) / 8, torch.ones_like(u)], -1), dim=-1)
    pts = d * (2.0 / d[..., 2:])  # the plane z = 2 seen from the origin
    for k in (1, 2):
        n = depth_normals(pts, d, k)
        assert n.shape == (h - 2 * k, w - 2 * k, 3)
        assert torch.allclose(n, torch.tensor([0.0, 0.0, -1.0]).expand_as(n), atol=1e-5)
    bumpy = pts + 0.05 * torch.randn(h, w, 1, generator=torch.Generator().manual_seed(0)) * d
    assert bss._mae_deg(depth_normals(bumpy, d, 1), torch.tensor([0.0, 0.0, -1.0])) > \
        bss._mae_deg(depth_normals(bumpy, d, 3), torch.tensor([0.0, 0.0, -1.0]))  # a wider stencil smooths noise
