"""bench/bench_preview_gap.py: the preview's error split by group, and what each group would give back."""

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[1] / "bench" / "bench_preview_gap.py"
_spec = importlib.util.spec_from_file_location("bench_preview_gap", _PATH)
bpg = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bpg)


def test_each_group_gets_its_share_and_the_db_its_field_like_error_would_give_back():
    # three channels summed per pixel: group "a" 10 px with preview SSE 3.0 (MSE 0.1) and field 0.3; "b" 30 px
    # with 1.0 and 1.0; an empty group is left out
    rows = bpg._groups(np.array([3.0, 1.0, 0.0]), np.array([0.3, 1.0, 0.0]), np.array([10, 30, 0]), ["a", "b", "c"])
    assert [r["group"] for r in rows] == ["a", "b"]
    a, b = rows
    assert a["pixels"] == pytest.approx(0.25) and a["preview_mse"] == pytest.approx(0.1)
    assert a["field_mse"] == pytest.approx(0.01) and a["share_of_preview_error"] == pytest.approx(0.75)
    assert a["db_if_field_like"] == pytest.approx(10 * math.log10(4.0 / 1.3))
    assert b["db_if_field_like"] == pytest.approx(0.0)  # already as good as the field: nothing to give back
    assert sum(r["share_of_preview_error"] for r in rows) == pytest.approx(1.0)


def test_bad_arguments_are_refused(tmp_path):
    with pytest.raises(SystemExit):
        bpg.main([str(tmp_path), str(tmp_path), "--every", "0"])
