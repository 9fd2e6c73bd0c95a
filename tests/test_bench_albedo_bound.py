"""bench/bench_albedo_bound.py: the albedo a global SH light implies from the photos' radiance, scored on the truth."""

import importlib.util
import math
from pathlib import Path

import pytest
import torch

from toolkit.sh import irradiance_sh

_PATH = Path(__file__).resolve().parents[1] / "bench" / "bench_albedo_bound.py"
_spec = importlib.util.spec_from_file_location("bench_albedo_bound", _PATH)
bab = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bab)


def _room(n: int = 3000, seed: int = 0):
    """Random normals, albedos and classes, and a light from above: float [n, 3] x 3, int [n], [9, 3]."""
    g = torch.Generator().manual_seed(seed)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    albedo = 0.1 + 0.7 * torch.rand(n, 3, generator=g)
    labels = torch.randint(0, 7, (n,), generator=g)
    sh = torch.zeros(9, 3)
    sh[0] = 2.0
    sh[2] = 0.9  # the z lobe (band 1 in (y, z, x) order)
    return normals, albedo, labels, sh


def test_a_lambertian_room_under_its_own_light_is_recovered_exactly():
    normals, albedo, labels, sh = _room()
    radiance = albedo * irradiance_sh(sh, normals) / math.pi
    r = bab.albedo_bound(radiance, albedo, normals, labels, sh)
    assert r["true_sh"] == pytest.approx(0.0, abs=1e-5) and r["true_sh_aligned"] == pytest.approx(0.0, abs=1e-5)
    assert r["best_sh"] == pytest.approx(0.0, abs=1e-4)
    assert torch.tensor(r["best_sh_coeffs"]) == pytest.approx(sh, abs=1e-3)
    assert all(v == pytest.approx(1.0, abs=1e-3) for v in r["best_sh_level_by_class"].values())
    assert sum(r["true_sh_damped"].values()) > 0.01  # a damped light is no longer the room's own


def test_light_that_varies_across_the_room_leaves_an_error_no_global_light_removes():
    normals, albedo, labels, sh = _room()
    gain = torch.where(labels == 4, 2.0, 1.0)[:, None]  # the walls get twice the light: a spot, a window
    radiance = gain * albedo * irradiance_sh(sh, normals) / math.pi
    r = bab.albedo_bound(radiance, albedo, normals, labels, sh)
    assert r["true_sh"] > 0.03  # the walls' albedo doubles (clamped at 1)
    assert r["best_sh_level_by_class"]["wall"] > 1.2 > r["best_sh_level_by_class"]["floor"]
    assert 0.005 < r["best_sh"] <= r["true_sh"] + 1e-6  # the search starts from the true light, never above it
    assert max(r["best_sh_share_by_class"], key=r["best_sh_share_by_class"].get) == "wall"
    assert sum(r["best_sh_share_by_class"].values()) == pytest.approx(1.0, abs=1e-4)


def test_a_wrong_light_level_is_what_the_alignment_removes():
    normals, albedo, labels, sh = _room()
    radiance = albedo * irradiance_sh(sh, normals) / math.pi
    dim = bab.albedo_bound(radiance, albedo, normals, labels, sh * 2.0)  # the light twice too bright
    assert dim["true_sh"] > 0.1 and dim["true_sh_aligned"] == pytest.approx(0.0, abs=1e-4)


def test_damping_keeps_the_level_and_scales_the_direction():
    _, _, _, sh = _room()
    d = bab.damp_sh(sh, 0.5)
    assert d[0] == pytest.approx(sh[0]) and d[2] == pytest.approx(0.5 * sh[2])
    assert sh[2, 0] == pytest.approx(0.9)  # the input is not modified


def test_too_few_pixels_is_an_error():
    normals, albedo, labels, sh = _room(5)
    with pytest.raises(ValueError, match="5 pixels"):
        bab.albedo_bound(albedo, albedo, normals, labels, sh)
