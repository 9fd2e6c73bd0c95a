"""bench/bench_layout.py: the fitted room box scored against ground-truth depth."""

import importlib.util
from pathlib import Path

import pytest

from toolkit.layout import LayoutConfig

_PATH = Path(__file__).resolve().parents[1] / "bench" / "bench_layout.py"
_spec = importlib.util.spec_from_file_location("bench_layout", _PATH)
bl = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bl)


def test_a_scene_without_depth_maps_is_refused_before_any_fit(sample_without_depth):
    """Scoring needs ground-truth depth: a scene without it stops with its name and the reason."""
    with pytest.raises(SystemExit, match="nodepth.*ground-truth depth"):
        bl.score_scene(str(sample_without_depth), LayoutConfig())
