"""bench/bench_light_level.py: the signed level ratio tells a dim estimate from a bright one."""

import importlib.util
import math
from pathlib import Path

import numpy as np

_PATH = Path(__file__).resolve().parents[1] / "bench" / "bench_light_level.py"
_spec = importlib.util.spec_from_file_location("bench_light_level", _PATH)
bl = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bl)


def test_signed_log_ratio_keeps_the_direction_that_log_error_drops():
    truth = np.array([2.0, 2.0, 2.0])
    dim, bright = truth / 2, truth * 2
    assert math.isclose(bl.signed_log_ratio(dim, truth), -math.log(2))
    assert math.isclose(bl.signed_log_ratio(bright, truth), math.log(2))
    assert math.isclose(bl.log_error(dim, truth), bl.log_error(bright, truth))
