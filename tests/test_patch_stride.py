"""Training patches measured on the object (TrainConfig.patch_stride): why (the depth-normal targets of a strided
patch see through depth noise), the rule that picks the stride from L_eikonal's step and the pixel footprint, the
patches the sampler draws with it, and the option's life in a run (recorded, loaded as 1 for older runs, checked on
resume)."""
import dataclasses
import json
from types import SimpleNamespace

import pytest
import torch

from toolkit.cameras import Cameras
from toolkit._checks import ConfigError
from toolkit.losses import depth_normal_loss
from toolkit.train.config import TrainConfig, make_config, patch_stride


def _plane_patch(s: int, noise: float = 0.0, seed: int = 0):
    """Points of the plane n·p = 2 on an s x s pixel grid seen from the origin, with Gaussian depth noise; the
    plane's unit normal toward the camera and the view directions."""
    v, u = torch.meshgrid(torch.arange(s, dtype=torch.float32), torch.arange(s, dtype=torch.float32), indexing="ij")
    n_true = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 1.0]), dim=0)
    x, y = 0.01 * u, -0.01 * v
    z = (2.0 - n_true[0] * x - n_true[1] * y) / n_true[2]
    pts = torch.stack([x, y, z], -1)[None]
    dirs = torch.nn.functional.normalize(pts, dim=-1)
    g = torch.Generator().manual_seed(seed)
    pts = pts + dirs * noise * torch.randn(pts.shape[:-1] + (1,), generator=g)
    return pts, (-n_true).expand(1, s, s, 3), dirs


def test_strided_patches_see_the_surface_through_depth_noise():
    """Depth noise of a pixel's width (a training render's at 1000 px) makes the ±1 pixel targets of a dense patch
    nearly random; the same loss on every 6th pixel (a patch of stride 6) recovers the plane: the loss of the true
    normal falls by more than 5x."""
    pts, facing, dirs = _plane_patch(96, noise=0.01)
    dense = [t[:, 40:56, 40:56] for t in (pts, facing, dirs)]
    strided = [t[:, ::6, ::6] for t in (pts, facing, dirs)]
    w = torch.ones(1, 16, 16)
    at1 = float(depth_normal_loss(*dense, w))
    at6 = float(depth_normal_loss(*strided, w))
    assert at1 > 0.15 and at6 < at1 / 5
    assert float(depth_normal_loss(*_plane_patch(16), w)) == pytest.approx(0.0, abs=1e-5)  # no noise: exact


def _scene(fx: float, distance: float = 4.0):
    """Six cameras at ``distance`` around the box [-1, 1]^3 (focal ``fx`` px, 256 px images)."""
    c2w = []
    for a in torch.linspace(0, 2 * torch.pi, 7)[:-1]:
        m = torch.eye(4)
        m[:3, 3] = torch.tensor([torch.cos(a), torch.sin(a), 0.0]) * distance
        c2w.append(m)
    n = len(c2w)
    full = lambda v: torch.full((n,), float(v))  # noqa: E731
    cams = Cameras(torch.stack(c2w), full(fx), full(fx), full(128), full(128), torch.full((n,), 256),
                   torch.full((n,), 256))
    return SimpleNamespace(cameras=cams, aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))


def test_the_stride_is_eikonals_step_over_the_pixel_footprint():
    """step x mean edge / (distance / fx): 1/64 x 2 / (4 / fx) rounds to 1 at fx 100 (a 128 px capture), 2 at 300
    and 8 at 1000, and stops where a 16 px patch still fits in the 256 px photo (16 at fx 5000); a room's 1/512
    keeps 1."""
    assert [patch_stride(_scene(fx), 1 / 64, 16) for fx in (100, 300, 1000, 5000)] == [1, 2, 8, 16]
    assert patch_stride(_scene(300), 1 / 512, 16) == 1


def test_the_sampler_spaces_the_patch_pixels_by_the_stride(sample_scene_path):
    """Each patch of a batch is a 16 x 16 grid whose neighbours are ``patch_stride`` photo pixels apart, inside its
    photo."""
    from toolkit.scene import load_scene
    from toolkit.train import resolve_config
    from toolkit.train.data import prepare_data
    from toolkit.train.step import init_state, sample_batch

    scene = load_scene(sample_scene_path, "train")
    for r in (1, 3):
        cfg, sc = resolve_config(make_config("fast", steps=1, batch_rays=1024, patch_stride=r), scene)
        data = prepare_data(sc, cfg, lambda *a, **k: None, None)
        state = init_state(cfg, data)
        batch = sample_batch(state, data)
        s, P = cfg.ssim_patch_size, cfg.ssim_patches
        flat = batch.pixels[batch.n_random:].reshape(P, s, s)
        views, rows, cols = data.weights.locate(flat.reshape(-1))
        rows, cols, views = rows.reshape(P, s, s), cols.reshape(P, s, s), views.reshape(P, s, s)
        assert bool((views == views[:, :1, :1]).all())
        assert bool((rows[:, 1:] - rows[:, :-1] == r).all()) and bool((cols[:, :, 1:] - cols[:, :, :-1] == r).all())
        assert bool((rows[:, :1] == rows[:, :1, :1]).all())


def test_the_option_is_resolved_recorded_and_checked(sample_scene_path):
    from toolkit.scene import load_scene
    from toolkit.train import resolve_config

    assert make_config("fast", steps=1).patch_stride is None
    cfg, _ = resolve_config(make_config("fast", steps=1), load_scene(sample_scene_path, "train"))
    assert cfg.patch_stride == 1  # the sample gallery: a room at 128 px
    d = cfg.to_dict()
    assert TrainConfig.from_dict(json.loads(json.dumps(d))).patch_stride == 1
    del d["patch_stride"]  # a run saved before the option trained on dense patches
    assert TrainConfig.from_dict(d).patch_stride == 1
    with pytest.raises(ConfigError, match="patch_stride=0"):
        dataclasses.replace(cfg, patch_stride=0)
    with pytest.raises(ConfigError, match="patch_stride=9: a 16 px patch then spans 136 photo pixels, but the smallest "
                                          r"photo is 128 px across; give --patch-stride 8 or less"):
        resolve_config(make_config("fast", steps=1, patch_stride=9), load_scene(sample_scene_path, "train"))


def test_cli_records_the_stride_and_refuses_another_on_resume(tmp_path, capsys):
    from synthetic import make_scene

    from toolkit.cli import main

    scene = make_scene(tmp_path / "scene")
    run = tmp_path / "run"
    assert main(["train", str(scene), "--out", str(run), "--steps", "2", "--batch-rays", "256", "--quiet",
                 "--no-auto-priors", "--patch-stride", "2"]) == 0
    assert json.loads((run / "config.json").read_text())["config"]["patch_stride"] == 2
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--steps", "3", "--resume", "--patch-stride", "1", "--quiet"]) == 2
    assert "--patch-stride 1 (the run's: 2)" in capsys.readouterr().err
