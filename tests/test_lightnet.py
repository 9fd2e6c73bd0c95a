"""Tests of toolkit/lightnet.py (stage 4), its ONNX export, ``dars priors light`` and samples/render_lightings.py."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from toolkit._checks import ConfigError, ShapeError
from toolkit.lightnet import (DEFAULT_WEIGHTS, SH_BAND_BOUNDS, LightDataset, LightNet, LightNetError,
                              TrainLightNetConfig, aggregate_sh, evaluate_lightnet, lightnet_config,
                              load_light_dataset, load_lightnet, logits_from_sh, mean_colour_sh, predict_sh,
                              save_lightnet, sh_from_logits, train_lightnet)

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "gallery"
BAND = [0, 1, 1, 1, 2, 2, 2, 2, 2]


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _small(**kw) -> LightNet:
    torch.manual_seed(0)
    return LightNet(lightnet_config("small", **kw)).eval()


# ============================================================================ architecture
def test_small_forward_shapes_any_size():
    net = _small()
    assert net(torch.rand(2, 3, 64, 64)).shape == (2, 9, 3)
    assert net(torch.rand(1, 3, 48, 80)).shape == (1, 9, 3)
    assert predict_sh(net, torch.rand(3, 3, 128, 96)).shape == (3, 9, 3)
    assert predict_sh(net, torch.rand(0, 3, 64, 64)).shape == (0, 9, 3)


def test_resnet34_is_the_papers_architecture():
    net = LightNet(lightnet_config("resnet34"))
    cfg = net.cfg
    assert cfg.blocks == (3, 4, 6, 3) and cfg.widths == (64, 128, 256, 512)
    t = net.trunk
    assert [len(getattr(t, f"layer{i}")) for i in range(1, 5)] == [3, 4, 6, 3]
    assert [getattr(t, f"layer{i}")[-1].conv2.out_channels for i in range(1, 5)] == [64, 128, 256, 512]
    assert tuple(t.conv1.weight.shape) == (64, 3, 7, 7)
    # torchvision resnet34 has 21,797,672 parameters, 513,000 of them in its 1000-way fc: the trunk is the rest
    assert sum(p.numel() for p in t.parameters()) == 21_797_672 - 513_000
    lin = [m for m in net.head if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in lin] == [(512, 256), (256, 27)], "FC must be 512 -> 256 -> 27"
    assert net.num_parameters() == 21_284_672 + 512 * 256 + 256 + 256 * 27 + 27
    with torch.no_grad():
        assert net.eval()(torch.rand(1, 3, 64, 64)).shape == (1, 9, 3)


def test_small_fc_input_is_trunk_width_and_config_errors():
    net = _small()
    assert net.head[0].in_features == 128 and net.head[-1].out_features == 27
    with pytest.raises(ConfigError, match="unknown light-network preset 'resnet50'"):
        lightnet_config("resnet50")
    with pytest.raises(ConfigError, match="4 positive entries"):
        lightnet_config("small", blocks=(1, 1, 1))
    with pytest.raises(ConfigError, match="output_range='relative'"):
        lightnet_config("small", output_range="relative")


# ============================================================================ output range
def test_output_range_mapping_bounds_and_inverse():
    g = torch.Generator().manual_seed(0)
    z = torch.randn(64, 27, generator=g) * 8  # many saturated logits
    sh = sh_from_logits(z, 4.0)
    dc = sh[:, 0]
    assert bool((dc >= 0).all()) and bool((dc <= 4.0).all())
    for k in range(1, 9):
        assert bool((sh[:, k].abs() <= SH_BAND_BOUNDS[BAND[k]] * dc + 1e-6).all())
    # extremes: sigmoid -> 1 gives the bounds exactly
    top = sh_from_logits(torch.full((1, 27), 50.0), 2.0)[0]
    assert torch.allclose(top[0], torch.full((3,), 2.0))
    assert torch.allclose(top[1], torch.full((3,), 2.0 * math.sqrt(3.0)))
    assert torch.allclose(top[4], torch.full((3,), 2.0 * math.sqrt(5.0)))
    # inverse
    sh2 = sh_from_logits(torch.randn(8, 27, generator=g), 4.0)
    assert torch.allclose(sh_from_logits(logits_from_sh(sh2, 4.0), 4.0), sh2, atol=1e-5)


def test_band_bounds_hold_for_non_negative_environments():
    """The range is physical: any non-negative radiance has |L_lm| <= sqrt(2l+1) L00 (tight for a point light)."""
    from toolkit.sh import fit_sh_probe, sh_basis

    rng = np.random.default_rng(1)
    for _ in range(5):
        env = rng.random((32, 64, 3)) ** 8 * 50  # spiky, non-negative
        c = fit_sh_probe(env).coeffs.double()
        for k in range(1, 9):
            assert bool((c[k].abs() <= SH_BAND_BOUNDS[BAND[k]] * c[0] + 1e-9).all())
    y = sh_basis(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))[0]  # point light at +z
    assert math.isclose(float(y[6] / y[0]), math.sqrt(5.0), rel_tol=1e-6)
    assert math.isclose(float(y[2] / y[0]), math.sqrt(3.0), rel_tol=1e-6)


def test_image_output_range_follows_exposure():
    net = _small(output_range="image", dc_max=8.0)
    x = torch.full((1, 3, 32, 32), 0.3)
    r1 = net.dc_range(x)
    from toolkit.io import linear_to_srgb, srgb_to_linear

    x2 = linear_to_srgb(srgb_to_linear(x) * 2)
    assert torch.allclose(net.dc_range(x2), 2 * r1, rtol=1e-4)
    sh = net(x)
    assert bool((sh[:, 0] <= r1 + 1e-6).all())


# ============================================================================ baselines, aggregation, inputs
def test_mean_colour_sh_known_value():
    img = torch.full((2, 3, 8, 8), 0.5)
    img[1, 0] = 1.0
    sh = mean_colour_sh(img)
    lin = ((0.5 + 0.055) / 1.055) ** 2.4
    assert sh.shape == (2, 9, 3)
    assert math.isclose(float(sh[0, 0, 1]), lin / 0.282095, rel_tol=1e-5)
    assert math.isclose(float(sh[1, 0, 0]), 1.0 / 0.282095, rel_tol=1e-5)
    assert float(sh[:, 1:].abs().max()) == 0.0


def test_aggregate_and_predict_errors():
    per = torch.arange(3 * 27, dtype=torch.float32).reshape(3, 9, 3)
    assert torch.equal(aggregate_sh(per, "mean"), per[1])
    assert torch.equal(aggregate_sh(per, "median"), per[1])
    with pytest.raises(ConfigError, match="reduce='max'"):
        aggregate_sh(per, "max")
    with pytest.raises(LightNetError, match="no per-image estimates"):
        aggregate_sh(per[:0])
    net = _small()
    with pytest.raises(LightNetError, match=r"sRGB in \[0, 1\].*linear_to_srgb"):
        predict_sh(net, torch.rand(1, 3, 32, 32) * 5)
    with pytest.raises(ShapeError):
        predict_sh(net, torch.rand(3, 32, 32))


# ============================================================================ training on a tiny synthetic set
def _ball_dataset(n: int = 48, size: int = 32, seed: int = 0) -> LightDataset:
    """Diffuse grey balls (albedo 0.8) lit by random SH: each image determines its SH's bands 0-1 exactly."""
    from toolkit.sh import irradiance_sh

    g = torch.Generator().manual_seed(seed)
    u = (torch.arange(size) + 0.5) / size * 2 - 1
    yy, xx = torch.meshgrid(-u, u, indexing="ij")
    rr = xx**2 + yy**2
    inside = rr < 1
    normals = torch.stack([xx, (1 - rr).clamp_min(0).sqrt(), yy], -1)  # the ball seen from -y (world z up)
    sh = torch.zeros(n, 9, 3)
    sh[:, 0] = 0.5 + torch.rand(n, 3, generator=g)
    sh[:, 1:4] = (torch.rand(n, 3, 3, generator=g) * 2 - 1) * 0.5 * sh[:, :1]
    rad = torch.stack([irradiance_sh(s, normals.reshape(-1, 3)).reshape(size, size, 3) for s in sh]) * 0.8 / math.pi
    rad = (rad.clamp_min(0) * inside[..., None]).permute(0, 3, 1, 2).contiguous()
    test = torch.zeros(n, dtype=torch.bool)
    test[-8:] = True
    return LightDataset(radiance=rad, sh=sh, lighting=torch.arange(n), test=test, sources=tuple(["ball"] * n))


def test_training_reduces_loss_and_beats_mean_baseline():
    ds = _ball_dataset()
    cfg = TrainLightNetConfig(arch=lightnet_config("small", input_size=32), steps=80, batch_size=16, lr=3e-3,
                              shift_px=0, exposure_jitter=0.0, seed=0, progress=False)
    net, hist = train_lightnet(ds, cfg)
    assert len(hist.losses) == 80 and hist.views == 40
    first, last = np.mean(hist.losses[:10]), np.mean(hist.losses[-10:])
    assert last < 0.5 * first, f"loss went from {first:.4f} to {last:.4f}"
    assert hist.train_mean_sh.shape == (9, 3)
    ev = evaluate_lightnet(net, ds.split("train"), hist.train_mean_sh)
    assert ev.network < ev.train_mean_sh, ev
    assert set(ev.per_source) == {"ball"} and ev.images == 40
    # seeded: the same run gives the same losses
    _, hist2 = train_lightnet(ds, TrainLightNetConfig(**{**cfg.__dict__, "steps": 5}))
    _, hist3 = train_lightnet(ds, TrainLightNetConfig(**{**cfg.__dict__, "steps": 5}))
    assert hist2.losses == hist3.losses


def _look(forward, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """c2w [4, 4] of an OpenGL camera looking along ``forward`` with ``up`` roughly up."""
    f = torch.tensor(forward, dtype=torch.float64)
    f = f / f.norm()
    r = torch.linalg.cross(f, torch.tensor(up, dtype=torch.float64))
    r = r / r.norm()
    u = torch.linalg.cross(r, f)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 0], m[:3, 1], m[:3, 2] = r, u, -f
    return m


def test_camera_heading_through_every_pitch():
    from toolkit.lightnet import camera_heading

    c2w = torch.stack([_look((1, 0, 0)), _look((0, -2, 1)), _look((0, -1, -3)), _look((1, 1, 0)),
                       _look((0, 0, -1), up=(0, 1, 0)), _look((0, 0, 1), up=(-1, 0, 0))])
    h = camera_heading(c2w)
    want = torch.tensor([[1, 0], [0, -1], [0, -1], [2 ** -0.5, 2 ** -0.5], [0, 1], [1, 0]], dtype=torch.float64)
    assert torch.allclose(h, want, atol=1e-6), h
    # straight down, the heading is where the top of the photo points; 3x4 matrices work too
    assert torch.allclose(camera_heading(c2w[:, :3]), h)
    with pytest.raises(LightNetError, match="c2w must be"):
        camera_heading(torch.eye(4))


def test_rotate_sh_heading_is_rotate_sh_about_z_and_mirror_signs():
    from toolkit.lightnet import MIRROR_Y_SIGNS, rotate_sh_heading
    from toolkit.sh import eval_sh, rotate_sh, rotation_z

    g = torch.Generator().manual_seed(1)
    c = torch.randn(5, 9, 3, generator=g, dtype=torch.float64)
    for deg in (0.0, 37.0, 180.0, -101.0):
        a = math.radians(deg)
        h = torch.tensor([[math.cos(a), math.sin(a)]], dtype=torch.float64).expand(5, 2)
        got = rotate_sh_heading(c, h)
        assert torch.allclose(got, rotate_sh(c, rotation_z(deg)), atol=1e-9), deg
        assert torch.allclose(rotate_sh_heading(got, h, inverse=True), c, atol=1e-9)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    mirrored = c[0] * torch.tensor(MIRROR_Y_SIGNS, dtype=torch.float64)[:, None]
    assert torch.allclose(eval_sh(mirrored, d * torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)), eval_sh(c[0], d))


def _headed(ds: LightDataset, seed: int = 3) -> LightDataset:
    """``ds`` with a random heading per view, its SH (what the image shows) turned into the world by it."""
    from dataclasses import replace

    from toolkit.lightnet import rotate_sh_heading

    a = torch.rand(len(ds), generator=torch.Generator().manual_seed(seed)) * 2 * math.pi
    h = torch.stack([a.cos(), a.sin()], 1)
    return replace(ds, sh=rotate_sh_heading(ds.sh, h), heading=h)


def test_heading_network_learns_what_a_world_network_cannot():
    """Balls whose light turns with an unseen camera heading: the photo shows the light relative to the camera, so
    a network answering in the heading frame (then turned by the pose) fits it and a world-frame one cannot."""
    ds = _headed(_ball_dataset(n=64))
    errs = {}
    for frame in ("world", "heading"):
        cfg = TrainLightNetConfig(arch=lightnet_config("small", input_size=32, frame=frame), steps=150, batch_size=16,
                                  lr=3e-3, shift_px=0, exposure_jitter=0.0, seed=0,
                                  progress=False)
        net, hist = train_lightnet(ds, cfg)
        errs[frame] = evaluate_lightnet(net, ds.split("test"), hist.train_mean_sh).network
    # held-out balls: 0.76-0.85 against 0.96-1.00 over 2 seeds and 1-2 threads
    assert errs["heading"] < 0.9 * errs["world"], errs
    net = _small(frame="heading")
    x = torch.rand(2, 3, 64, 64)
    with pytest.raises(LightNetError, match="camera poses"):
        predict_sh(net, x)
    c2w = torch.stack([_look((1, 0, 0)), _look((0, 1, 0))])
    a, b = predict_sh(net, x[:1].expand(2, -1, -1, -1), c2w=c2w)
    from toolkit.sh import rotate_sh, rotation_z

    assert torch.allclose(rotate_sh(a, rotation_z(90.0)), b, atol=1e-5)  # the same photo, turned with its camera
    assert torch.allclose(net(x), predict_sh(net, x, heading=torch.tensor([[1.0, 0.0]] * 2)), atol=1e-5)
    with pytest.raises(LightNetError, match="headings"):
        evaluate_lightnet(net, _ball_dataset(n=4), torch.zeros(9, 3))
    with pytest.raises(ConfigError, match="hflip"):
        TrainLightNetConfig(hflip=True)
    with pytest.raises(LightNetError, match="camera headings"):
        train_lightnet(_ball_dataset(n=16), TrainLightNetConfig(arch=lightnet_config("small", frame="heading"), steps=1,
                                                               progress=False))


def test_train_needs_training_views():
    ds = _ball_dataset(n=8)
    allt = LightDataset(ds.radiance, ds.sh, ds.lighting, torch.ones(8, dtype=torch.bool))
    with pytest.raises(LightNetError, match="no training views"):
        train_lightnet(allt, TrainLightNetConfig(steps=1, progress=False))
    with pytest.raises(ShapeError):
        LightDataset(ds.radiance, ds.sh[:, :4], ds.lighting, ds.test)


# ============================================================================ persistence
def test_save_load_roundtrip_and_errors(tmp_path):
    net = _small()
    net.meta = {"train_mean_sh": torch.ones(9, 3).tolist()}
    p = save_lightnet(tmp_path / "w.pt", net, {"note": "x"})
    back = load_lightnet(p)
    x = torch.rand(2, 3, 64, 64)
    assert torch.allclose(back(x), net(x), atol=1e-6)
    assert back.meta["note"] == "x" and back.cfg == net.cfg and not back.training
    half = load_lightnet(save_lightnet(tmp_path / "h.pt", net, {"half": True}))
    assert torch.allclose(half(x), net(x), atol=5e-2)
    with pytest.raises(LightNetError, match=r"light-network weights not found: .*nope\.pt"):
        load_lightnet(tmp_path / "nope.pt")
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    with pytest.raises(LightNetError, match=r"bad\.pt is not a readable light-network file"):
        load_lightnet(tmp_path / "bad.pt")
    torch.save({"format": "something-else"}, tmp_path / "other.pt")
    with pytest.raises(LightNetError, match="not a dars light-network file"):
        load_lightnet(tmp_path / "other.pt")


def test_shipped_weights_load():
    if not DEFAULT_WEIGHTS.is_file():
        pytest.fail(f"shipped weights missing: {DEFAULT_WEIGHTS} (bench/bench_lightnet.py --save {DEFAULT_WEIGHTS})")
    net = load_lightnet()
    assert net.cfg.name == "small" and "train_mean_sh" in net.meta
    assert DEFAULT_WEIGHTS.stat().st_size < 2_000_000
    info = json.loads(DEFAULT_WEIGHTS.with_suffix(".json").read_text())
    # trained on procedural galleries; a whole probe and two unseen validation galleries held out (issue 17 part 2)
    g = info["galleries"]
    assert g["holdout_probes"] and all(not g["train_seeds_by_probe"].get(p) for p in g["holdout_probes"]), g
    assert len(g["heldout_galleries"]) >= 2 and g["train_galleries"] >= 30, g
    s = info["heldout_gallery_sources"]
    assert set(g["holdout_probes"]) | {Path(d).name for d in g["heldout_galleries"]} == set(s["sources"]), s
    # measured: better than zero light on every held-out source (all 3 training seeds) and ~10 % below the grey
    # ambient on average (the 30 % target is not met); see the card's seed_spread
    assert s["beats_zero_on_every_source"] and s["network_over_grey"] < 0.95, s
    assert all(info["seed_spread"]["beats_zero_on_every_source"]), info["seed_spread"]


def test_load_light_dataset(tmp_path):
    with pytest.raises(LightNetError, match="render_lightings.py"):
        load_light_dataset(tmp_path / "missing.npz")
    rad = np.full((4, 8, 8, 3), 0.1, np.float16)
    sh = np.ones((4, 9, 3), np.float32)
    np.savez(tmp_path / "d.npz", radiance=rad, sh=sh, exposure=np.array([1, 2, 1, 2], np.float32),
             lighting=np.array([0, 0, 1, 1], np.int32), test=np.array([0, 0, 1, 1], bool), sources=np.array(["a", "b"]),
             meta=np.array(json.dumps({"seed": 0})))
    ds = load_light_dataset(tmp_path / "d.npz")
    assert ds.radiance.shape == (4, 3, 8, 8)
    assert math.isclose(float(ds.radiance[1].mean()), 0.2, rel_tol=1e-3) and float(ds.sh[1, 0, 0]) == 2.0
    assert len(ds.split("train")) == 2 and ds.split("test").source_of() == ["b", "b"]
    np.savez(tmp_path / "e.npz", radiance=rad)
    with pytest.raises(LightNetError, match=r"lacks arrays \['sh'"):
        load_light_dataset(tmp_path / "e.npz")


# ============================================================================ ONNX
def test_onnx_parity(tmp_path):
    pytest.importorskip("onnxruntime")
    from export.onnx import read_onnx_metadata, run_onnx
    from export.onnx_light import export_lightnet_onnx

    net = _small()
    with torch.no_grad():  # non-trivial BN statistics
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
    rep = export_lightnet_onnx(net, tmp_path / "light.onnx")
    assert rep.max_abs_err <= 1e-4 and rep.opset == 17
    assert set(rep.errors) == {"example", "random_b5"}
    x = torch.rand(3, 3, 48, 80)
    got = run_onnx(rep.path, {"images": x})["sh"]
    assert got.shape == (3, 9, 3)
    assert np.abs(got - net(x).detach().numpy()).max() <= 1e-4
    meta = read_onnx_metadata(rep.path)
    assert meta["dars.kind"] == "lightnet" and meta["dars.input_size"] == "64" and meta["dars.frame"] == "world"
    with pytest.raises(ConfigError, match="expects a toolkit.lightnet.LightNet"):
        export_lightnet_onnx(torch.nn.Linear(2, 2), tmp_path / "x.onnx")
    # a heading network takes each photo's heading and answers in the world frame, as predict_sh does with poses
    from export.infer import camera_heading_np, infer_light
    from toolkit.lightnet import camera_heading

    hnet = _small(frame="heading")
    rep = export_lightnet_onnx(hnet, tmp_path / "h" / "light.onnx")
    assert rep.max_abs_err <= 1e-4 and read_onnx_metadata(rep.path)["dars.frame"] == "heading"
    c2w = torch.stack([_look((1, 0, 0)), _look((0, 1, -0.5)), _look((-1, 1, 0.3))])
    h = camera_heading(c2w)
    assert np.allclose(camera_heading_np(c2w.numpy()), h.numpy(), atol=1e-6)
    got = run_onnx(rep.path, {"images": x, "heading": h.float()})["sh"]
    assert np.abs(got - hnet(x, h.float()).detach().numpy()).max() <= 1e-4
    photos = [x[i].permute(1, 2, 0).numpy() for i in range(3)]
    assert np.abs(infer_light(rep.path, photos, threads=1, c2w=c2w.numpy())
                  - predict_sh(hnet, x, c2w=c2w).numpy()).max() <= 1e-4
    from export.infer import InferError

    with pytest.raises(InferError, match="--poses"):
        infer_light(rep.path, photos, threads=1)


# ============================================================================ CLI
def _run(argv, capsys):
    from toolkit.cli import main

    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.skipif(not (SAMPLE / "transforms_train.json").is_file(), reason=f"sample scene not rendered at {SAMPLE}")
def test_cli_light_on_sample(tmp_path, capsys):
    out_dir = tmp_path / "light"
    rc, out, err = _run(["priors", "light", str(SAMPLE), "--out", str(out_dir)], capsys)
    assert rc == 0, err
    assert "Env-light L2 vs GT" in out and "baseline image mean colour" in out
    d = json.loads((out_dir / "light.json").read_text())
    assert d["source"] == "lightnet" and d["reduce"] == "mean"
    coeffs = torch.tensor(d["coeffs"])
    assert coeffs.shape == (9, 3)  # what toolkit.train reads to initialise l_env
    assert len(d["per_image"]) == 80 and {"key", "coeffs"} <= set(d["per_image"][0])
    per = torch.tensor([p["coeffs"] for p in d["per_image"]])
    assert torch.allclose(per.mean(0), coeffs, atol=1e-5)
    ev = d["evaluation"]
    assert ev["env_light_l2"] < ev["baseline_mean_colour"] and ev["env_light_l2"] < ev["baseline_train_mean_sh"], ev
    assert "light.json" in json.loads((out_dir / "dars_manifest.json").read_text())["files"]
    # JSON mode: only JSON on stdout; median; a second run may overwrite its own file
    rc, out, err = _run(["priors", "light", str(SAMPLE), "--out", str(out_dir), "--json", "--reduce", "median",
                         "--split", "test"], capsys)
    assert rc == 0, err
    j = json.loads(out)
    assert j["reduce"] == "median" and j["split"] == "test" and len(j["per_image"]) == 20


def test_cli_light_without_gt_and_bad_inputs(tmp_path, capsys):
    sys.path.insert(0, str(REPO / "tests"))
    from synthetic import make_scene

    scene = make_scene(tmp_path / "scene", n_train=4, n_test=2, size=32)
    w = save_lightnet(tmp_path / "w.pt", _small())
    rc, out, err = _run(["priors", "light", str(scene), "--weights", str(w), "--json"], capsys)
    assert rc == 0, err
    d = json.loads(out)
    assert d["evaluation"] is None and len(d["per_image"]) == 4
    assert (scene / "priors" / "light" / "light.json").is_file()
    rc, out, err = _run(["priors", "light", str(scene), "--weights", str(tmp_path / "missing.pt")], capsys)
    assert rc == 2 and "light-network weights not found" in err and "missing.pt" in err and out == ""
    (scene / "priors" / "light2").mkdir()
    (scene / "priors" / "light2" / "light.json").write_text("{}")  # the user's file
    rc, out, err = _run(["priors", "light", str(scene), "--weights", str(w), "--out", str(scene / "priors" / "light2")],
                        capsys)
    assert rc == 2 and "refusing to write" in err and "light.json" in err
    assert (scene / "priors" / "light2" / "light.json").read_text() == "{}"
    rc, out, err = _run(["priors", "light", str(tmp_path / "nowhere"), "--weights", str(w)], capsys)
    assert rc == 2 and "nowhere" in err


# ============================================================================ the data-set generator
def _load_generator():
    spec = importlib.util.spec_from_file_location("render_lightings", REPO / "samples" / "render_lightings.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("render_lightings", mod)
    spec.loader.exec_module(mod)
    return mod


def test_plan_holds_out_lightings_not_views():
    rl = _load_generator()
    specs = rl.plan_lightings(rl.LightingPlan(seed=0))
    assert specs == rl.plan_lightings(rl.LightingPlan(seed=0))  # seeded
    train = [s for s in specs if not s.test]
    test = [s for s in specs if s.test]
    assert all(s.source != "pisa" for s in train) and any(s.source == "pisa" for s in test)
    sky_train = {s.seed for s in train if s.source == "sky"}
    sky_test = {s.seed for s in test if s.source == "sky"}
    assert sky_train and sky_test and not (sky_train & sky_test)
    assert all(0.28 <= s.exposure_target <= 0.56 for s in specs)
    assert {s.label for s in train} >= {"sky", "sky+sun", "wells", "wells+sky"} and {s.label for s in test} == {"pisa", "sky"}
    # the held-out lightings do not depend on how many training lightings there are
    fewer = rl.plan_lightings(rl.LightingPlan(seed=0, rotations_per_probe=1, train_skies=0, mixtures=0, suns=0))
    assert [s for s in fewer if s.test] == test
    sun = rl.environment_of(next(s for s in train if s.sun_fraction > 0))
    assert sun.latlong.shape == (128, 256, 3) and float(sun.latlong.min()) > 0
    with pytest.raises(ConfigError, match="--holdout-probe 'paris'"):
        rl.plan_lightings(rl.LightingPlan(holdout_probe="paris"))


@pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason="mitsuba is not installed")
def test_environment_swap_matches_a_fresh_scene_and_the_samples_gt():
    rl = _load_generator()
    if not rl.rg.llvm_available():
        pytest.skip("needs libLLVM 19 for llvm_ad_rgb (scalar_rgb is too slow for the dense emitter query)")
    d = rl.self_check("llvm_ad_rgb")
    assert d["emitter"] < 1e-4 and d["render"] < 1e-4, d
    if not math.isnan(d["sample_sh"]):
        assert d["sample_sh"] < 1e-5, d


def _fake_gallery(root: Path, seed: int, probe: str, n: int = 2, stamp: bool = True) -> Path:
    from toolkit.io import write_hdr

    d = root / f"seed_{seed}"
    (d / "train").mkdir(parents=True)
    frames = []
    for i in range(n):
        write_hdr(d / "train" / f"r_{i:03d}.hdr", np.full((20, 20, 3), 0.1 * (i + 1), np.float32))
        frames.append({"file_path": f"train/r_{i:03d}.png", "radiance_path": f"train/r_{i:03d}.hdr",
                       "transform_matrix": np.eye(4).tolist()})
    sh = np.zeros((9, 3))
    sh[0] = seed + 1.0
    (d / "transforms_train.json").write_text(json.dumps(
        {"sh": sh.tolist(), "frames": frames, "render": {"env": f"probulator_{probe}_256x128.hdr", "gallery_seed": seed,
                                                         "profile": "prior"}}))
    if stamp:
        (d / "stamp.json").write_text("{}")
    return d


def test_light_dataset_from_galleries(tmp_path):
    from toolkit.lightnet import concat_light_datasets, gallery_dirs, light_dataset_from_galleries

    prof = tmp_path / "prior"
    _fake_gallery(prof, 0, "pisa")
    _fake_gallery(prof, 2, "grace_new")
    _fake_gallery(prof, 10, "wells")
    _fake_gallery(prof, 3, "wells", stamp=False)  # still rendering: skipped
    val = _fake_gallery(tmp_path / "validation", 7, "wells", n=3)
    dirs = gallery_dirs(prof)
    assert [d.name for d in dirs] == ["seed_0", "seed_2", "seed_10"]
    ds = light_dataset_from_galleries(dirs, size=8, holdout_probes=("pisa",), heldout_galleries=(val,))
    assert ds.radiance.shape == (9, 3, 8, 8) and ds.sh.shape == (9, 9, 3)
    assert math.isclose(float(ds.radiance[1].mean()), 0.2, rel_tol=1e-2)  # linear .hdr, no exposure factor
    assert ds.sources == ("pisa", "grace_new", "wells", "seed_7")
    assert ds.test.tolist() == [True, True, False, False, False, False, True, True, True]
    assert float(ds.sh[2, 0, 0]) == 3.0 and float(ds.sh[-1, 0, 0]) == 8.0
    assert sorted(set(ds.split("test").source_of())) == ["pisa", "seed_7"]
    both = concat_light_datasets(ds, ds)
    assert len(both) == 18 and both.lighting.max() == 7 and both.sources == ds.sources * 2
    with pytest.raises(LightNetError, match="not found"):
        gallery_dirs(tmp_path / "nope")


def test_bench_score_only_scores_unseen_galleries_and_sets_aside_the_trained_ones(tmp_path, capsys):
    """bench_lightnet --score-only: the weights' card decides which galleries were trained on; those are left out,
    every other one is scored per source and per room against zero light and grey ambient."""
    import importlib.util as ilu

    from toolkit.lightnet import LightNet, lightnet_config, save_lightnet

    spec = ilu.spec_from_file_location("bench_lightnet", Path(__file__).resolve().parents[1] / "bench" / "bench_lightnet.py")
    bench = ilu.module_from_spec(spec)
    spec.loader.exec_module(bench)
    prof = tmp_path / "prior"
    for seed, probe in ((0, "pisa"), (2, "grace_new"), (10, "wells")):
        _fake_gallery(prof, seed, probe)
    torch.manual_seed(0)
    w = save_lightnet(tmp_path / "net.pt", LightNet(lightnet_config("small")))
    (tmp_path / "net.json").write_text(json.dumps({"galleries": {"train_seeds_by_probe": {"pisa": [0]}}}))
    assert bench.main(["--score-only", "--galleries", str(prof), "--weights", str(w), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [Path(p).name for p in out["skipped_trained_on"]] == ["seed_0"]
    assert out["galleries"] == 2 and sorted(r["seed"] for r in out["per_gallery"]) == [2, 10]
    assert sorted(out["heldout"]["per_source"]) == ["grace_new", "wells"]
    for r in out["per_gallery"]:
        assert math.isclose(r["zero_light"], (r["seed"] + 1) * math.sqrt(3), rel_tol=1e-5)
        assert (r["gallery"] in out["worse_than_zero_light"]) == (r["network"] > r["zero_light"])
    # the level diagnosis: the room estimate times true/predicted level has the true level, and its L2 is scored
    from toolkit.lightnet import light_dataset_from_galleries, load_lightnet, predict_sh
    from toolkit.metrics import env_light_l2

    net = load_lightnet(w)
    for r in out["per_gallery"]:
        ds = light_dataset_from_galleries([Path(r["gallery"])], net.cfg.input_size)
        room = predict_sh(net, ds.images(), heading=ds.heading).mean(0)
        scaled = room * r["true_over_network_level"]
        assert math.isclose(float(scaled[0].mean()), r["seed"] + 1.0, rel_tol=1e-4)
        assert math.isclose(r["network_true_level"], float(env_light_l2(scaled, ds.sh[0])), rel_tol=1e-4)
    ratios = sorted(r["true_over_network_level"] for r in out["per_gallery"])
    assert math.isclose(out["level"]["ratio_p50"], sum(ratios) / 2, rel_tol=1e-6)
    assert math.isclose(out["level"]["network_true_level_over_grey"],
                        sum(r["network_true_level"] for r in out["per_gallery"])
                        / sum(r["grey_ambient"] for r in out["per_gallery"]), rel_tol=1e-6)
    (tmp_path / "net.json").write_text(json.dumps({"galleries": {"train_seeds_by_probe": {"pisa": [0, 2, 10]}}}))
    assert bench.main(["--score-only", "--galleries", str(prof), "--weights", str(w), "--json"]) == 2
    assert "training set" in capsys.readouterr().err
