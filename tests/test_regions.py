"""Textureless regions of a photo and the planarity loss built on them (``losses.planar``)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from toolkit._checks import ConfigError
from toolkit.losses import planarity_loss
from toolkit.regions import TexturelessConfig, textureless_regions


def _half_plain_half_textured(size: int = 128, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    img = torch.full((3, size, size), 0.6)
    tex = torch.rand(1, 1, size // 8, size // 8, generator=g)
    img[:, :, size // 2:] = F.interpolate(tex, size=(size, size), mode="nearest")[0, :, :, size // 2:]
    return img


def test_a_plain_half_is_one_region_and_texture_none():
    img = _half_plain_half_textured()
    reg = textureless_regions(img)
    assert reg.dtype == np.int32 and reg.shape == (128, 128)
    assert reg.max() == 1  # one region: the plain half
    left, right = reg[:, :64], reg[:, 64:]
    assert (left > 0).mean() > 0.9  # all of it but the eroded edge
    assert (right[:, 4:] > 0).mean() < 0.05  # the blocks are 16 px wide: a few lie inside the blur, most not


def test_small_plain_patches_are_dropped_and_size_is_judged_at_128_px():
    img = _half_plain_half_textured()
    assert textureless_regions(img, TexturelessConfig(min_fraction=0.6)).max() == 0  # the half is < 60 % of it
    big = F.interpolate(img[None], size=(512, 512), mode="nearest")[0]
    cov_small, cov_big = (textureless_regions(img) > 0).mean(), (textureless_regions(big) > 0).mean()
    assert cov_big == pytest.approx(cov_small, abs=0.05)  # the same photo at 4x the pixels gives the same regions


def test_bad_texture_config_and_image_raise():
    with pytest.raises(ConfigError):
        TexturelessConfig(grad_threshold=0)
    with pytest.raises(ConfigError):
        TexturelessConfig(min_fraction=1.5)
    with pytest.raises(ValueError, match="expected a \\[3, H, W\\] image"):
        textureless_regions(torch.zeros(8, 8))


def _plane_points(k: int, m: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(k, m, 2, generator=g) * 2 - 1
    normal = F.normalize(torch.randn(k, 3, generator=g), dim=-1)
    a = F.normalize(torch.cross(normal, torch.tensor([[0.3, 0.5, 0.8]]).expand(k, 3), dim=-1), dim=-1)
    b = torch.cross(normal, a, dim=-1)
    centre = torch.randn(k, 1, 3, generator=g) * 3
    return centre + uv[..., :1] * a[:, None] + uv[..., 1:] * b[:, None], normal


def test_planarity_loss_is_zero_on_planes_and_moves_points_onto_them():
    pts, normal = _plane_points(4, 64)
    w = torch.ones(4, 64)
    assert float(planarity_loss(pts, w, torch.ones(4))) == pytest.approx(0.0, abs=1e-5)
    g = torch.Generator().manual_seed(1)
    bumpy = (pts + 0.05 * torch.randn(pts.shape, generator=g) * normal[:, None]).requires_grad_(True)
    loss = planarity_loss(bumpy, w, torch.ones(4))
    assert 0.02 < loss.item() < 0.06  # mean |N(0, 0.05)| = 0.04
    loss.backward()
    moved = (bumpy - 0.5 * bumpy.grad * bumpy.shape[0] * bumpy.shape[1] * 0.01).detach()
    assert float(planarity_loss(moved, w, torch.ones(4))) < loss.item()
    # relative to the region's distance: the same room at 10x the scale costs the same
    assert float(planarity_loss(bumpy.detach() * 10, w, torch.full((4,), 10.0))) == pytest.approx(loss.item(), rel=1e-4)
    # a point with no weight (no surface rendered there) neither counts nor moves
    wz = w.clone()
    wz[0, 0] = 0.0
    far = bumpy.detach().clone()
    far[0, 0] += 100 * normal[0]
    far.requires_grad_(True)
    planarity_loss(far, wz, torch.ones(4)).backward()
    assert float(far.grad[0, 0].abs().sum()) == 0.0
    assert float(planarity_loss(torch.zeros(0, 8, 3), torch.zeros(0, 8), torch.zeros(0))) == 0.0


def test_planar_option_trains_logs_and_is_recorded(sample_scene_path, tmp_path, capsys):
    """`dars train --planar-loss W`: regions found in the photos, the term logged each step, the weight in
    config.json; --resume with another weight is refused. Off by default."""
    from toolkit.cli import main

    run = tmp_path / "p"
    assert main(["train", str(sample_scene_path), "--out", str(run), "--steps", "3", "--batch-rays", "256",
                 "--quiet", "--no-auto-priors", "--planar-loss", "0.3"]) == 0
    out = capsys.readouterr().out + capsys.readouterr().err
    losses = json.load(open(run / "config.json"))["config"]["losses"]
    assert losses["planar"] == 0.3
    rows = [json.loads(line) for line in open(run / "log.jsonl")]
    vals = [r["planar"] for r in rows if r.get("kind") == "train" and "planar" in r]
    assert vals and all(math.isfinite(v) and 0 <= v < 1 for v in vals), (vals, out[-2000:])
    assert main(["train", "--out", str(run), "--steps", "4", "--resume", "--planar-loss", "0.5", "--quiet"]) == 2
    assert "--planar-loss" in capsys.readouterr().err
    default = tmp_path / "d"
    assert main(["train", str(sample_scene_path), "--out", str(default), "--steps", "1", "--batch-rays", "256",
                 "--quiet", "--no-auto-priors"]) == 0
    assert json.load(open(default / "config.json"))["config"]["losses"]["planar"] == 0.0
    assert not any("planar" in json.loads(line) for line in open(default / "log.jsonl"))
