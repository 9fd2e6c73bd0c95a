"""bench/bench_segmenter.py: how a metal IoU of 0 is reported."""

import importlib.util
from pathlib import Path

_PATH = Path(__file__).resolve().parents[1] / "bench" / "bench_segmenter.py"
_spec = importlib.util.spec_from_file_location("bench_segmenter", _PATH)
bs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bs)


def _row(metal_iou, gt, pred):
    return {"miou": 0.66, "metal_iou": metal_iou, "metal_pixels_gt": gt, "metal_pixels_pred": pred,
            "per_class": {}}


def test_a_zero_metal_iou_without_true_metal_is_called_false_positives(capsys):
    """Views with no true metal pixel score metal IoU 0 for any prediction: the table says it counts false positives,
    and a scene with true metal it missed gets no such note."""
    bs._print_scores([("no metal", _row(0.0, 0, 1234)), ("missed metal", _row(0.0, 50, 0))])
    out = capsys.readouterr().out
    assert "no true metal pixel in these views: metal IoU 0 counts the 1234 pixels predicted metal" in out
    assert out.count("no true metal pixel") == 1
