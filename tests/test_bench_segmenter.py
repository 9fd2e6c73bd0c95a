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


def test_extra_rooms_are_brought_to_the_prior_views_size():
    """--extra-dir rooms (64 px) join the 160 px prior views: images bilinear in [0, 1], labels and masks nearest
    (the ignore id 255 and the class ids survive unchanged, no blended ids)."""
    import torch

    img = torch.rand(2, 3, 4, 4)
    lab = torch.tensor([[0, 1], [255, 6]]).repeat_interleave(2, 0).repeat_interleave(2, 1)[None].expand(2, 4, 4)
    met = lab == 6
    out_img = bs._resize_to(img, (10, 10), nearest=False)
    out_lab = bs._resize_to(lab, (10, 10), nearest=True)
    out_met = bs._resize_to(met, (10, 10), nearest=True)
    assert out_img.shape == (2, 3, 10, 10) and 0.0 <= float(out_img.min()) and float(out_img.max()) <= 1.0
    assert out_lab.dtype == lab.dtype and set(out_lab.unique().tolist()) == {0, 1, 6, 255}
    assert out_met.dtype == torch.bool and bool((out_met == (out_lab == 6)).all())
    assert bs._resize_to(img, (4, 4), nearest=False) is img


def test_holdout_seeds_pick_the_held_out_galleries(tmp_path):
    """--holdout-seeds holds exactly those seeds out (wherever they sort), the card's seed list reads back as ranges,
    and a held-out seed that is not rendered stops with the command that renders it."""
    import pytest

    dirs = [tmp_path / f"seed_{s}" for s in (0, 1, 2, 5, 6, 9, 10)]
    train, held = bs.split_holdout(dirs, 8, "1-2,9")
    assert [d.name for d in held] == ["seed_1", "seed_2", "seed_9"]
    assert [d.name for d in train] == ["seed_0", "seed_5", "seed_6", "seed_10"]
    train, held = bs.split_holdout(dirs, 2)
    assert [d.name for d in held] == ["seed_9", "seed_10"] and len(train) == 5
    assert bs.seed_ranges([10, 0, 1, 2, 5, 6, 9]) == "0-2,5-6,9-10"
    with pytest.raises(SystemExit, match="--seeds 3-4"):
        bs.split_holdout(dirs, 8, "2-4")
