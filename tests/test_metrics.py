import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from conftest import shared
from toolkit._checks import DarsError, ShapeError
from toolkit.metrics import (
    LPIPS_ENV_VAR,
    MetricUnavailable,
    albedo_mae,
    albedo_mae_aligned,
    chamfer_distance,
    env_light_l2,
    flip,
    fscore,
    load_lpips_weights,
    lpips,
    luminance,
    material_mask,
    mean_iou,
    metallic_mae,
    normal_mae_deg,
    patch_masks,
    psnr,
    roughness_rmse,
    sample_mesh_surface,
    ssim,
    uniform_view_indices,
    view_consistency,
)
from toolkit.pinhole import look_at
from toolkit.scene import Cameras, generate_rays

VENV_BIN = Path(sys.executable).parent


def _rand(*shape, seed=0, dtype=torch.float64):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def _noisy(x, sigma, seed=1):
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(seed), dtype=x.dtype)
    return (x + sigma * noise).clamp(0, 1)


def _structured(h=48, w=64, dtype=torch.float64):
    """Checkerboard + ramp + disk per channel: edges, flats and gradients."""
    yy, xx = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    checker = (((yy // 8) + (xx // 8)) % 2)
    ramp = xx / (w - 1)
    disk = (((yy - h / 2) ** 2 + (xx - w / 3) ** 2) < (h / 4) ** 2).to(dtype)
    return torch.stack([0.7 * checker + 0.2 * ramp, ramp, 0.5 * disk + 0.3 * checker])


# ====================================================================== PSNR
def test_psnr_known_values():
    x = _rand(2, 3, 16, 20)
    y = x + 0.1  # constant offset: MSE = 0.01 -> 20 dB exactly (values beyond 1 are fine for the formula)
    out = psnr(y, x)
    assert out.shape == (2,)
    torch.testing.assert_close(out, torch.full((2,), 20.0, dtype=torch.float64))
    # max_val scales the peak: 255-range images with offset 25.5 -> also 20 dB
    torch.testing.assert_close(psnr(y * 255, x * 255, max_val=255.0), torch.full((2,), 20.0, dtype=torch.float64))
    assert math.isinf(float(psnr(x[0], x[0])))  # identical -> inf, unbatched -> 0-dim
    assert psnr(x[0], y[0]).shape == ()


def test_psnr_matches_skimage_per_image_and_mean_convention():
    from skimage.metrics import peak_signal_noise_ratio

    x = _rand(3, 3, 24, 32)
    y = _noisy(x, torch.tensor([0.02, 0.1, 0.3], dtype=torch.float64).view(3, 1, 1, 1))
    ours = psnr(y, x)
    ref = [peak_signal_noise_ratio(x[i].numpy(), y[i].numpy(), data_range=1.0) for i in range(3)]
    np.testing.assert_allclose(ours.numpy(), ref, rtol=0, atol=1e-10)
    # mean of per-image PSNR (what we report) is above the PSNR of the mean MSE when errors differ
    mse_all = float(((y - x) ** 2).mean())
    assert float(ours.mean()) > 10 * math.log10(1 / mse_all) + 1.0


def test_psnr_mask_respected():
    x = _rand(2, 3, 10, 12)
    y = x.clone()
    mask = torch.zeros(2, 10, 12, dtype=torch.bool)
    mask[:, :5] = True
    y[:, :, :5] += 0.1  # error only inside the mask
    y[:, :, 5:] = 1 - y[:, :, 5:]  # garbage outside the mask must not count
    torch.testing.assert_close(psnr(y, x, mask=mask), torch.full((2,), 20.0, dtype=torch.float64))
    empty = torch.zeros(2, 10, 12, dtype=torch.bool)
    assert torch.isnan(psnr(y, x, mask=empty)).all()


def test_psnr_errors():
    x = torch.rand(1, 3, 8, 8)
    with pytest.raises(ShapeError, match=r"psnr: pred and target must have the same shape, got \[1, 3, 8, 8\] and \[1, 3, 8, 9\]"):
        psnr(x, torch.rand(1, 3, 8, 9))
    with pytest.raises(ShapeError, match=r"mask must have shape \[1, 8, 8\]"):
        psnr(x, x, mask=torch.ones(8, 8, dtype=torch.bool))
    with pytest.raises(DarsError, match="mask must be a bool tensor"):
        psnr(x, x, mask=torch.ones(1, 8, 8))
    with pytest.raises(DarsError, match="floating-point"):
        psnr(x.to(torch.uint8), x.to(torch.uint8))


# ====================================================================== SSIM
def _sk_ssim(a, b, full=False):
    from skimage.metrics import structural_similarity

    return structural_similarity(a.numpy(), b.numpy(), gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                 data_range=1.0, channel_axis=0, full=full)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_matches_skimage_random_and_structured(dtype):
    rnd = _rand(3, 40, 52, seed=3, dtype=dtype)
    st = _structured(40, 52, dtype)
    pairs = [(rnd, _noisy(rnd, 0.1)), (st, _noisy(st, 0.05)), (st, torch.roll(st, 2, dims=-1)), (st, 0.8 * st + 0.1)]
    pred = torch.stack([b for _, b in pairs])
    target = torch.stack([a for a, _ in pairs])
    ours = ssim(pred, target)
    assert ours.shape == (4,) and ours.dtype == dtype
    ref = np.array([_sk_ssim(b.double(), a.double()) for a, b in pairs])
    err = np.abs(ours.double().numpy() - ref).max()
    assert err <= (1e-4 if dtype == torch.float32 else 1e-10), err
    assert float(ssim(st, st)) == pytest.approx(1.0, abs=1e-6)


def test_ssim_matches_skimage_on_real_photo():
    from toolkit.io import read_image

    img = torch.as_tensor(read_image(shared("nerf_synthetic", "lego", "train", "r_0.png")))[..., :3]
    a = img.permute(2, 0, 1).double()[:, 100:228, 120:248].contiguous()
    b = _noisy(a, 0.05)
    assert abs(float(ssim(b.float(), a.float())) - _sk_ssim(b, a)) <= 1e-4


def test_ssim_mask_averages_skimage_map_over_centres():
    a = _structured(30, 36)
    b = _noisy(a, 0.1)
    mask = torch.zeros(30, 36, dtype=torch.bool)
    mask[8:20, 6:30] = True
    _, smap = _sk_ssim(b, a, full=True)  # [3, H, W]
    # only centres where the window fits (5 px from each side) count in the "valid" convention
    inner = np.zeros_like(mask.numpy())
    inner[5:-5, 5:-5] = True
    ref = smap.mean(axis=0)[mask.numpy() & inner].mean()
    assert float(ssim(b, a, mask=mask)) == pytest.approx(ref, abs=1e-10)


def test_ssim_reflect_padding_small_patches():
    from scipy.ndimage import gaussian_filter

    a = _rand(2, 3, 16, 16, seed=5)
    b = _noisy(a, 0.1)
    out = ssim(b, a, padding="reflect")
    assert out.shape == (2,) and bool((out < 1).all())
    # independent: scipy's "mirror" mode is torch's reflect; statistics at every pixel, then the SSIM formula
    for i in range(2):
        vals = []
        for c in range(3):
            x, y = b[i, c].numpy(), a[i, c].numpy()
            f = lambda z: gaussian_filter(z, 1.5, truncate=3.5, mode="mirror")
            mx, my = f(x), f(y)
            vx, vy, cxy = f(x * x) - mx**2, f(y * y) - my**2, f(x * y) - mx * my
            c1, c2 = 0.01**2, 0.03**2
            vals.append(((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
        assert float(out[i]) == pytest.approx(np.mean(vals), abs=1e-10)
    with pytest.raises(ShapeError, match="smaller than the 11x11 window; use padding='reflect'"):
        ssim(a[:, :, :8, :8], a[:, :, :8, :8])
    with pytest.raises(DarsError, match="padding='same' is not valid"):
        ssim(a, a, padding="same")


def test_ssim_gradcheck():
    a = _rand(1, 1, 12, 12, seed=7)
    b = _noisy(a, 0.2).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: ssim(x, a), (b,), eps=1e-6, atol=1e-5)
    c = _rand(1, 1, 8, 8, seed=8).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: ssim(x, a[:, :1, :8, :8], padding="reflect"), (c,), eps=1e-6, atol=1e-5)


def test_ssim_errors():
    with pytest.raises(ShapeError, match=r"ssim: pred and target must have the same shape"):
        ssim(torch.rand(3, 16, 16), torch.rand(1, 3, 16, 16))
    with pytest.raises(DarsError, match="window=10"):
        ssim(torch.rand(3, 16, 16), torch.rand(3, 16, 16), window=10)


# ====================================================================== FLIP
def _flip_cli(ref_png: Path, test_png: Path, out_dir: Path) -> float:
    exe = VENV_BIN / "flip"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "flip_evaluator.flip_python_api"]
    res = subprocess.run(cmd + ["-r", str(ref_png), "-t", str(test_png), "-nerm", "-v", "1", "-d", str(out_dir)],
                         capture_output=True, text=True, timeout=120, check=True)
    m = re.search(r"Mean:\s*([0-9.eE+-]+)", res.stdout)
    assert m, res.stdout + res.stderr
    return float(m.group(1))


def test_flip_matches_cli(tmp_path):
    from toolkit.io import write_png

    ref = _structured(40, 56, torch.float32)
    tests = [_noisy(ref, 0.08), torch.roll(ref, 1, dims=-1), 0.7 * ref]
    def u8(x):
        return (x * 255).round().to(torch.uint8)

    ref_u8 = u8(ref).float() / 255  # what the PNG holds
    write_png(tmp_path / "ref.png", u8(ref).permute(1, 2, 0).numpy())
    cli, preds = [], []
    for k, t in enumerate(tests):
        t_u8 = u8(t).float() / 255
        write_png(tmp_path / f"test{k}.png", u8(t).permute(1, 2, 0).numpy())
        cli.append(_flip_cli(tmp_path / "ref.png", tmp_path / f"test{k}.png", tmp_path))
        preds.append(t_u8)
    ours = flip(torch.stack(preds), ref_u8.expand(3, -1, -1, -1))
    assert ours.shape == (3,)
    # the CLI prints 6 decimals
    np.testing.assert_allclose(ours.numpy(), cli, rtol=0, atol=1e-6)
    assert all(v > 0.01 for v in cli)
    assert float(flip(ref_u8, ref_u8)) == 0.0


def test_flip_mask_and_range():
    a = _structured(32, 32, torch.float32)
    b = _noisy(a, 0.1)
    full = torch.ones(32, 32, dtype=torch.bool)
    assert float(flip(b, a, mask=full)) == pytest.approx(float(flip(b, a)), abs=1e-6)
    half = torch.zeros(32, 32, dtype=torch.bool)
    half[:, :16] = True
    b2 = b.clone()
    b2[:, :, 24:] = 1 - b2[:, :, 24:]  # large errors outside the mask
    assert float(flip(b2, a, mask=half)) < float(flip(b2, a))
    with pytest.raises(DarsError, match=r"LDR-FLIP needs sRGB values in \[0, 1\]"):
        flip(a * 2, a)


# ====================================================================== LPIPS
_ALEX = [(0, 64, 3, 11), (3, 192, 64, 5), (6, 384, 192, 3), (8, 256, 384, 3), (10, 256, 256, 3)]


def _synthetic_lpips_state(seed=0):
    """Random tensors with the exact keys/shapes of torchvision alexnet + lpips v0.1 lin layers (test only)."""
    g = torch.Generator().manual_seed(seed)
    tv, lin = {}, {}
    for k, (idx, cout, cin, ks) in enumerate(_ALEX):
        tv[f"features.{idx}.weight"] = torch.randn(cout, cin, ks, ks, generator=g) * (2.0 / (cin * ks * ks)) ** 0.5
        tv[f"features.{idx}.bias"] = torch.randn(cout, generator=g) * 0.01
        lin[f"lin{k}.model.1.weight"] = torch.rand(1, cout, 1, 1, generator=g) * 0.1
    tv["classifier.1.weight"] = torch.randn(8, 8, generator=g)  # ignored
    return tv, lin


class _RefLPIPS(nn.Module):
    """Independent re-statement of lpips v0.1 'alex' with nn modules laid out like torchvision + lpips."""

    def __init__(self):
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(), nn.MaxPool2d(3, 2))
        for k, c in enumerate([64, 192, 384, 256, 256]):
            lin = nn.Module()
            lin.model = nn.Sequential(nn.Dropout(), nn.Conv2d(c, 1, 1, bias=False))  # lpips NetLinLayer
            setattr(self, f"lin{k}", lin)
        self.register_buffer("shift", torch.tensor([-.030, -.088, -.188])[None, :, None, None])
        self.register_buffer("scale", torch.tensor([.458, .448, .450])[None, :, None, None])

    def forward(self, a, b):
        taps = [1, 4, 7, 9, 11]
        outs = []
        for x in (a, b):
            x = ((2 * x - 1) - self.shift) / self.scale
            feats = []
            for i, layer in enumerate(self.features):
                x = layer(x)
                if i in taps:
                    feats.append(x)
            outs.append(feats)
        val = 0
        for k in range(5):
            f0 = outs[0][k] / (torch.sqrt(torch.sum(outs[0][k] ** 2, dim=1, keepdim=True)) + 1e-10)
            f1 = outs[1][k] / (torch.sqrt(torch.sum(outs[1][k] ** 2, dim=1, keepdim=True)) + 1e-10)
            val = val + getattr(self, f"lin{k}").model((f0 - f1) ** 2).mean([2, 3], keepdim=True)
        return val.flatten()


@pytest.fixture
def lpips_files(tmp_path):
    tv, lin = _synthetic_lpips_state()
    torch.save(tv, tmp_path / "alexnet-owt-synthetic.pth")
    torch.save(lin, tmp_path / "alex.pth")
    return tmp_path, tv, lin


def test_lpips_architecture_with_synthetic_weights(lpips_files):
    folder, tv, lin = lpips_files
    a = _rand(2, 3, 64, 72, seed=11, dtype=torch.float32)
    b = _noisy(a, 0.1)
    d = lpips(b, a, weights_path=folder)
    assert d.shape == (2,) and bool((d > 0).all())
    assert torch.allclose(lpips(a, a, weights_path=folder), torch.zeros(2))
    ref = _RefLPIPS().eval()
    ref.load_state_dict({k: v for k, v in (tv | lin).items() if not k.startswith("classifier")} |
                        {"shift": ref.shift, "scale": ref.scale}, strict=True)  # the synthetic keys fit the layout
    with torch.no_grad():
        torch.testing.assert_close(d, ref(b, a), rtol=1e-5, atol=1e-7)
    # files listed explicitly, unbatched input, and the env var give the same numbers
    files = [folder / "alexnet-owt-synthetic.pth", folder / "alex.pth"]
    torch.testing.assert_close(lpips(b[0], a[0], weights_path=files), d[0])
    # differentiable
    x = b.clone().requires_grad_(True)
    lpips(x, a, weights_path=folder).sum().backward()
    assert torch.isfinite(x.grad).all() and float(x.grad.abs().sum()) > 0


def test_lpips_env_var_and_module_layout(lpips_files, monkeypatch, tmp_path):
    folder, tv, lin = lpips_files
    a = _rand(1, 3, 40, 40, seed=12, dtype=torch.float32)
    b = _noisy(a, 0.2)
    expected = lpips(b, a, weights_path=folder)
    monkeypatch.setenv(LPIPS_ENV_VAR, str(folder))
    torch.testing.assert_close(lpips(b, a), expected)
    # an lpips.LPIPS() module state dict (net.sliceK.N.*) in one file
    slice_of = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}
    merged = {f"net.slice{slice_of[int(k.split('.')[1])]}.{k.split('.', 1)[1]}": v
              for k, v in tv.items() if k.startswith("features")} | lin
    one = tmp_path / "lpips_module.pt"
    torch.save(merged, one)
    torch.testing.assert_close(lpips(b, a, weights_path=one), expected)


def test_lpips_never_runs_without_weights(monkeypatch, tmp_path):
    monkeypatch.delenv(LPIPS_ENV_VAR, raising=False)
    a = torch.rand(1, 3, 64, 64)
    with pytest.raises(MetricUnavailable, match=LPIPS_ENV_VAR):
        lpips(a, a)
    with pytest.raises(MetricUnavailable, match="weights file not found"):
        lpips(a, a, weights_path=tmp_path / "nope.pth")
    tv, lin = _synthetic_lpips_state()
    torch.save(tv, tmp_path / "alexnet_only.pth")
    with pytest.raises(MetricUnavailable, match=r"lack \['lin0.weight'"):
        load_lpips_weights(tmp_path / "alexnet_only.pth")
    lin["lin2.model.1.weight"] = torch.rand(1, 100, 1, 1)
    torch.save(tv | lin, tmp_path / "bad_shape.pth")
    with pytest.raises(MetricUnavailable, match=r"lin2.weight .* has shape \[1, 100, 1, 1\], expected \[1, 384, 1, 1\]"):
        load_lpips_weights(tmp_path / "bad_shape.pth")
    assert issubclass(MetricUnavailable, DarsError)


def test_lpips_small_image_error(lpips_files):
    folder, _, _ = lpips_files
    with pytest.raises(ShapeError, match="at least 31x31"):
        lpips(torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16), weights_path=folder)


# ====================================================================== materials and light
def test_material_mask_and_albedo_roughness():
    labels = torch.tensor([[[0, 1, 2, 3], [4, 5, 6, 255]]], dtype=torch.uint8)  # [1, 2, 4]
    depth = torch.ones(1, 2, 4)
    depth[0, 1, 0] = 0.0  # wall pixel with no GT surface
    m = material_mask(labels, depth=depth)
    assert m.tolist() == [[[True, True, False, True], [False, True, True, False]]]
    assert material_mask(labels).sum() == 6
    gt = torch.zeros(1, 3, 2, 4)
    pred = gt.clone()
    pred[:, :, m[0]] = torch.tensor([0.1, 0.2, 0.3]).view(1, 3, 1)
    pred[:, :, ~m[0]] = 0.9  # outside the mask: must not count
    assert float(albedo_mae(pred, gt, m)) == pytest.approx(0.2, abs=1e-7)
    r_gt = torch.full((1, 1, 2, 4), 0.5)
    r_pred = r_gt.clone()
    r_pred[0, 0][m[0]] = torch.tensor([0.5, 0.6, 0.3, 0.5, 0.9])  # errors 0, .1, .2, 0, .4
    expected = math.sqrt((0.01 + 0.04 + 0.16) / 5)
    assert float(roughness_rmse(r_pred, r_gt, m)) == pytest.approx(expected, abs=1e-6)
    assert float(roughness_rmse(r_pred[:, 0], r_gt[:, 0], m)) == pytest.approx(expected, abs=1e-6)  # [B, H, W] maps
    with pytest.raises(MetricUnavailable, match="selects no pixels"):
        albedo_mae(pred, gt, torch.zeros_like(m))
    with pytest.raises(DarsError, match="ids outside 0-6 and 255, e.g. 9"):
        material_mask(torch.tensor([[9]], dtype=torch.uint8))
    with pytest.raises(ShapeError, match=r"albedo_mae: pred must be \[B, 3, H, W\]"):
        albedo_mae(r_pred, r_gt, m)


def test_albedo_mae_aligned_removes_a_per_channel_scale_only():
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(2, 3, 8, 8, generator=g) * 0.8 + 0.1
    m = torch.ones(2, 8, 8, dtype=torch.bool)
    m[1, :4] = False
    k = torch.tensor([2.5, 0.5, 1.25]).view(1, 3, 1, 1)
    v, s = albedo_mae_aligned(gt / k, gt, m)  # a pure per-channel scale: aligned error 0, scale recovered
    assert float(v) == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(s.numpy(), [2.5, 0.5, 1.25], rtol=1e-5)
    assert float(albedo_mae(gt / k, gt, m)) > 0.1  # the raw MAE sees the scale
    noisy = gt / k + 0.05 * torch.randn(gt.shape, generator=g)  # structure error stays after alignment
    v2, s2 = albedo_mae_aligned(noisy, gt, m)
    a, b = noisy.permute(0, 2, 3, 1)[m].double(), gt.permute(0, 2, 3, 1)[m].double()
    ls = (a * b).sum(0) / (a * a).sum(0)  # independent least-squares fit
    np.testing.assert_allclose(s2.numpy(), ls.numpy(), rtol=1e-5)
    assert float(v2) == pytest.approx(float((a * ls - b).abs().mean()), rel=1e-5) and float(v2) > 0.02
    with pytest.raises(MetricUnavailable, match="selects no pixels"):
        albedo_mae_aligned(gt, gt, torch.zeros_like(m))


def test_metallic_mae():
    gt = torch.zeros(1, 2, 2)
    gt[0, 0, 0] = 1.0
    pred = torch.tensor([[[0.75, 0.5], [0.0, 1.0]]])
    m = torch.tensor([[[True, True], [True, False]]])
    assert float(metallic_mae(pred, gt, m)) == pytest.approx((0.25 + 0.5 + 0.0) / 3)


def test_env_light_l2():
    gt = torch.zeros(9, 3)
    assert float(env_light_l2(gt + 1, gt)) == pytest.approx(math.sqrt(27))
    pred = gt.clone()
    pred[0] = torch.tensor([3.0, 0.0, 4.0])
    assert float(env_light_l2(pred, gt)) == pytest.approx(5.0)
    assert env_light_l2(torch.ones(4, 9, 3), torch.zeros(4, 9, 3)).shape == (4,)
    with pytest.raises(ShapeError, match=r"pred_sh: expected shape \[... 9 3\], got \[27\]"):
        env_light_l2(torch.zeros(27), torch.zeros(27))


def test_normal_mae_known_angles():
    gt = torch.zeros(1, 3, 2, 2)
    gt[:, 2] = 1.0  # +z everywhere
    pred = torch.zeros(1, 3, 2, 2)
    pred[0, :, 0, 0] = torch.tensor([1.0, 0, 0])  # 90 deg
    pred[0, :, 0, 1] = torch.tensor([0, 0, 5.0])  # 0 deg, not unit length
    pred[0, :, 1, 0] = torch.tensor([1.0, 0, 1.0])  # 45 deg
    pred[0, :, 1, 1] = torch.tensor([0, 0, -1.0])  # 180 deg
    assert float(normal_mae_deg(pred, gt)) == pytest.approx((90 + 0 + 45 + 180) / 4, abs=1e-4)
    only = torch.tensor([[[True, False], [False, False]]])
    assert float(normal_mae_deg(pred, gt, only)) == pytest.approx(90.0, abs=1e-4)
    gt[0, :, 1, 1] = 0.0  # no GT surface: excluded by the default mask
    assert float(normal_mae_deg(pred, gt)) == pytest.approx(45.0, abs=1e-4)


# ====================================================================== view consistency
def test_view_consistency_constructed_images():
    k = 5
    levels = torch.tensor([0.2, 0.25, 0.3, 0.1, 0.4], dtype=torch.float64)
    imgs = torch.rand(k, 3, 12, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    masks = torch.zeros(k, 12, 16, dtype=torch.bool)
    for i in range(k):
        masks[i, 2 + i:6 + i, 3:9] = True  # the region moves between views
        imgs[i][:, masks[i]] = levels[i]  # grey: luminance = level
    std, means = view_consistency(imgs, masks)
    torch.testing.assert_close(means, levels)
    assert float(std) == pytest.approx(float(np.std(levels.numpy(), ddof=1)), abs=1e-12)
    std_lux, means_lux = view_consistency(imgs, masks, lux_factor=500.0)
    assert float(std_lux) == pytest.approx(500 * float(std))
    # sRGB input is decoded first: sRGB 0.5 -> linear 0.21404
    s = torch.full((2, 3, 4, 4), 0.5, dtype=torch.float64)
    s[1] = 1.0
    _, m2 = view_consistency(s, torch.ones(2, 4, 4, dtype=torch.bool), space="srgb")
    torch.testing.assert_close(m2, torch.tensor([0.21404114, 1.0], dtype=torch.float64), atol=1e-7, rtol=0)
    # Rec. 709 weights on linear RGB
    assert float(luminance(torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1))) == pytest.approx(0.2126)
    masks[3] = False
    with pytest.raises(MetricUnavailable, match=r"not visible in view\(s\) \[3\]"):
        view_consistency(imgs, masks)


def test_uniform_view_indices():
    assert uniform_view_indices(100, 10) == [0, 11, 22, 33, 44, 55, 66, 77, 88, 99]
    assert uniform_view_indices(10, 10) == list(range(10))
    assert uniform_view_indices(7, 3) == [0, 3, 6]
    with pytest.raises(DarsError, match="at most 8"):
        uniform_view_indices(8, 10)


def _c2w(eye, target):
    return torch.from_numpy(look_at(eye, target))  # float64 [4, 4]


def _cameras(c2ws, f=100.0, size=64):
    k = len(c2ws)
    return Cameras(torch.stack(c2ws).double(), torch.full((k,), f, dtype=torch.float64),
                   torch.full((k,), f, dtype=torch.float64), torch.full((k,), size / 2, dtype=torch.float64),
                   torch.full((k,), size / 2, dtype=torch.float64), torch.full((k,), size), torch.full((k,), size))


def _raycast_patch(cams, i, centre, normal, size):
    """Independent mask + plane depth by casting a ray per pixel and testing the hit in 3D."""
    rays = generate_rays(cams, [i])
    c, n = torch.tensor(centre, dtype=torch.float64), torch.tensor(normal, dtype=torch.float64)
    t = ((c - rays.origins) @ n) / (rays.directions @ n)
    hit = rays.origins + t[:, None] * rays.directions
    eu = torch.linalg.cross(torch.tensor([0.0, 0, 1], dtype=torch.float64), n)
    eu = eu / eu.norm()
    ev = torch.linalg.cross(n, eu)
    rel = hit - c
    inside = ((rel @ eu).abs() <= size / 2) & ((rel @ ev).abs() <= size / 2) & (t > 0)
    h, w = int(cams.height[i]), int(cams.width[i])
    return inside.view(h, w), (t * rays.z_scale).view(h, w)


def test_patch_masks_facing_square_and_occlusion():
    centre, normal, size = (0.0, 0.0, 0.0), (0.0, -1.0, 0.0), 0.4  # a wall patch facing -y
    front = _c2w((0.0, -2.0, 0.0), (0.0, 0.0, 0.0))
    cams = _cameras([front])
    m = patch_masks(cams, [0], centre, normal, size)
    assert m.shape == (1, 64, 64) and m.dtype == torch.bool
    # 0.4 m at 2 m with f = 100 px -> 20 px square centred on the principal point
    rows, cols = m[0].nonzero(as_tuple=True)
    assert int(m.sum()) == 400
    assert (int(rows.min()), int(rows.max()), int(cols.min()), int(cols.max())) == (22, 41, 22, 41)
    # depth map at the patch depth keeps everything; an occluder in front of the left half removes it
    depth = torch.full((1, 64, 64), 2.0, dtype=torch.float64)
    assert int(patch_masks(cams, [0], centre, normal, size, depths=depth).sum()) == 400
    depth[0, :, :32] = 1.0
    depth[0, :, 40:] = 0.0  # no hit: no evidence of occlusion
    occ = patch_masks(cams, [0], centre, normal, size, depths=depth)
    assert int(occ.sum()) == 200 and not bool(occ[0, :, :32].any())
    # seen from behind, or the patch behind the camera: empty
    back = _c2w((0.0, 2.0, 0.0), (0.0, 0.0, 0.0))
    away = _c2w((0.0, -2.0, 0.0), (0.0, -5.0, 0.0))
    both = patch_masks(_cameras([back, away]), [0, 1], centre, normal, size)
    assert int(both.sum()) == 0
    assert int(patch_masks(_cameras([back]), [0], centre, normal, size, cull_backfacing=False).sum()) == 400


def test_patch_masks_oblique_views_match_raycast_and_cv2():
    import cv2

    centre, normal, size = (0.3, 0.0, 1.2), (0.0, -1.0, 0.0), 0.5
    c2ws = [_c2w((x, -2.5, 1.5), (0.0, 0.0, 1.2)) for x in (-1.5, 0.0, 1.0)]
    cams = _cameras(c2ws, f=60.0, size=64)
    masks = patch_masks(cams, [0, 1, 2], centre, normal, size)
    for k in range(3):
        ref, plane_depth = _raycast_patch(cams, k, centre, normal, size)
        assert int(ref.sum()) > 50
        assert int((masks[k] ^ ref).sum()) <= 1, k  # exact up to ties on an edge
        # cv2.fillPoly of the projected corners agrees up to its one-pixel boundary band
        from toolkit.scene import project_points

        n, c = torch.tensor(normal, dtype=torch.float64), torch.tensor(centre, dtype=torch.float64)
        eu = torch.tensor([1.0, 0, 0], dtype=torch.float64)
        ev = torch.linalg.cross(n, eu)
        corners = torch.stack([c + s * size / 2 * eu + r * size / 2 * ev for s, r in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
        uv, _ = project_points(cams, k, corners)
        poly = np.zeros((64, 64), np.uint8)
        cv2.fillPoly(poly, [np.round((uv.numpy() - 0.5) * 256).astype(np.int32)], 1, shift=8)
        poly = torch.from_numpy(poly.astype(bool))
        assert not bool((masks[k] & ~poly).any())  # cv2 is a superset ...
        grown = F.max_pool2d(masks[k][None, None].float(), 3, 1, 1)[0, 0].bool()
        assert not bool((poly & ~grown).any())  # ... within one pixel
        # the exact plane depth is "not occluded"; 10 cm nearer everywhere is "occluded"
        d = torch.where(ref, plane_depth, torch.full_like(plane_depth, 10.0))[None]
        assert torch.equal(patch_masks(cams, [k], centre, normal, size, depths=d)[0], masks[k])
        assert int(patch_masks(cams, [k], centre, normal, size, depths=plane_depth[None] - 0.1).sum()) == 0


def test_patch_masks_errors():
    cams = _cameras([_c2w((0.0, -2.0, 0.0), (0.0, 0.0, 0.0))])
    with pytest.raises(ShapeError, match=r"centre: expected shape \[3\], got \[2\]"):
        patch_masks(cams, [0], (0.0, 0.0), (0.0, -1.0, 0.0), 0.4)
    with pytest.raises(DarsError, match="size=-1"):
        patch_masks(cams, [0], (0.0, 0.0, 0.0), (0.0, -1.0, 0.0), -1)
    with pytest.raises(ShapeError, match=r"depths: expected shape \[1 64 64\]"):
        patch_masks(cams, [0], (0.0, 0.0, 0.0), (0.0, -1.0, 0.0), 0.4, depths=torch.ones(64, 64))


# ====================================================================== geometry
def test_chamfer_matches_open3d():
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(0)
    a = rng.normal(size=(2000, 3))
    b = rng.normal(size=(1500, 3)) * 1.1 + 0.05
    ours = chamfer_distance(torch.from_numpy(a), b)
    pa, pb = o3d.geometry.PointCloud(), o3d.geometry.PointCloud()
    pa.points, pb.points = o3d.utility.Vector3dVector(a), o3d.utility.Vector3dVector(b)
    ab = float(np.mean(np.asarray(pa.compute_point_cloud_distance(pb))))
    ba = float(np.mean(np.asarray(pb.compute_point_cloud_distance(pa))))
    assert ours["a_to_b"] == pytest.approx(ab, rel=1e-6)
    assert ours["b_to_a"] == pytest.approx(ba, rel=1e-6)
    assert ours["chamfer"] == pytest.approx((ab + ba) / 2, rel=1e-6)
    assert chamfer_distance(a, a)["chamfer"] == 0.0


def test_fscore_known_case():
    a = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    b = np.array([[0.0, 0.05, 0], [1, 0.2, 0], [10, 0, 0]])
    out = fscore(a, b, 0.1)
    assert out["precision"] == pytest.approx(1 / 4)
    assert out["recall"] == pytest.approx(1 / 3)
    assert out["fscore"] == pytest.approx(2 / 7)
    assert fscore(a, a + 5, 0.1)["fscore"] == 0.0
    with pytest.raises(ShapeError, match=r"points_b: expected shape \[N, 3\], got \[3, 2\]"):
        fscore(a, b[:, :2], 0.1)
    with pytest.raises(MetricUnavailable, match="points_a is empty"):
        chamfer_distance(np.zeros((0, 3)), b)


def test_sample_mesh_surface_is_area_uniform():
    from scipy.stats import chisquare

    # unit square at z = 0.5 split into three triangles of areas 1/8, 3/8, 1/2
    v = torch.tensor([[0, 0, .5], [.25, 0, .5], [1, 0, .5], [1, 1, .5], [0, 1, .5]], dtype=torch.float32)
    f = torch.tensor([[0, 1, 4], [1, 2, 3], [1, 3, 4]])
    pts = sample_mesh_surface(v, f, 16000, seed=0)
    assert pts.shape == (16000, 3) and pts.dtype == torch.float32
    assert torch.allclose(pts[:, 2], torch.tensor(0.5))
    assert bool(((pts[:, :2] >= 0) & (pts[:, :2] <= 1)).all())
    counts = np.histogram2d(pts[:, 0].numpy(), pts[:, 1].numpy(), bins=4, range=[[0, 1], [0, 1]])[0].ravel()
    assert chisquare(counts).pvalue > 1e-3
    assert torch.equal(pts, sample_mesh_surface(v, f, 16000, seed=0))  # seeded
    with pytest.raises(DarsError, match="zero"):
        sample_mesh_surface(v, torch.tensor([[0, 1, 2]]), 10)  # collinear triangle


# ====================================================================== semantics
def test_mean_iou_known_case():
    from toolkit import segment

    assert mean_iou is segment.mean_iou  # re-exported, not duplicated
    pred = torch.tensor([[0, 1, 2], [3, 3, 6]])
    target = torch.tensor([[0, 1, 1], [3, 255, 255]])
    miou, per_class = mean_iou(pred, target, num_classes=7, ignore=255)
    # class 0: 1/1, class 1: 1/2, class 2: 0/1 (predicted, absent in target), class 3: 1/1; others absent -> NaN
    assert per_class[:4] == [1.0, 0.5, 0.0, 1.0]
    assert all(math.isnan(v) for v in per_class[4:])
    assert float(miou) == pytest.approx(2.5 / 4)
