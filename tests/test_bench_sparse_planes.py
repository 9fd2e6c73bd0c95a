"""bench/bench_sparse_planes.py: RANSAC planes through sparse points, scored against ground-truth depth."""

import importlib.util
import types
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[1] / "bench" / "bench_sparse_planes.py"
_spec = importlib.util.spec_from_file_location("bench_sparse_planes", _PATH)
bsp = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bsp)


def test_ransac_finds_the_wall_among_points_in_front_of_it():
    """60 % of the points on the wall x = 3, the rest scattered in front of it: the plane is the wall's."""
    rng = np.random.default_rng(0)
    wall = np.stack([np.full(120, 3.0), rng.uniform(-2, 2, 120), rng.uniform(0, 3, 120)], -1)
    front = rng.uniform([0.5, -2, 0], [2.5, 2, 3], (80, 3))
    X = np.concatenate([wall, front])
    z = X[:, 0]  # depth from a camera at x = 0 looking along +x
    c, n, inl = bsp.ransac_plane(X, z, tau=0.01, rng=rng)
    assert abs(abs(n[0]) - 1.0) < 1e-3 and abs(c[0] - 3.0) < 1e-3
    assert inl[:120].all() and inl[120:].mean() < 0.1


def test_collinear_points_give_no_plane():
    X = np.stack([np.linspace(0, 1, 10)] * 3, -1)
    assert bsp.ransac_plane(X, np.ones(10), tau=0.01, rng=np.random.default_rng(0), iters=20) is None


def test_a_scene_without_depth_maps_is_refused(sample_without_depth):
    """Scoring needs ground-truth depth: a scene without it stops with its name and the reason."""
    args = types.SimpleNamespace(dilate=3, tau=0.015, min_inliers=8, min_spread=0.15)
    with pytest.raises(SystemExit, match="nodepth.*ground-truth depth"):
        bsp.score_scene(str(sample_without_depth), args)
