"""bench/bench_light_probe.py's quadrature: the cube map of six 90° cameras covers the sphere once, so a constant
radiance projects onto band 0 alone and a known SH light comes back through it."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import bench_light_probe as blp  # noqa: E402
from toolkit.sh import eval_sh  # noqa: E402


def test_cube_map_covers_the_sphere_once():
    cams, w = blp.cube_cameras(np.array([0.5, -1.0, 1.6]), 16)
    assert float(w.sum()) * 6 == pytest.approx(4 * math.pi, rel=2e-3)
    d = blp.cube_directions(cams).reshape(6, -1, 3)
    for k, axis in enumerate(blp.FACES):  # each camera looks along its axis
        assert torch.allclose(d[k].mean(0) / d[k].mean(0).norm(), torch.tensor(axis, dtype=torch.float64), atol=1e-6)


def test_projection_recovers_an_sh_light_and_the_belts():
    cams, w = blp.cube_cameras(np.zeros(3), 24)
    d, w = blp.cube_directions(cams), w.repeat(6)
    const = blp.project_sh(d, torch.ones(len(d), 3, dtype=torch.float64), w)
    assert float(const[0, 0]) == pytest.approx(math.sqrt(4 * math.pi), rel=2e-3)
    assert const[1:].abs().max() < 2e-2
    coeffs = torch.randn(9, 3, generator=torch.Generator().manual_seed(0))
    back = blp.project_sh(d, eval_sh(coeffs, d.float()).double(), w)
    assert torch.allclose(back, coeffs, atol=3e-2), (back - coeffs).abs().max()
    up = torch.where(d[:, 2:] > 0.5, 3.0, 1.0).expand(-1, 3)  # a bright ceiling
    belts = blp.belt_means(d, up, w)
    assert belts["up"] == pytest.approx([3.0] * 3) and belts["horizon"] == pytest.approx([1.0] * 3)
