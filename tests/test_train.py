import json
import math

import pytest
import torch

from synthetic import make_scene
from toolkit._checks import ConfigError, DarsError
from toolkit.io import linear_to_srgb
from toolkit.metrics import psnr
from toolkit.pipeline import RenderConfig, RenderInputs, render_image
from toolkit.scene import load_scene
from toolkit.evaluate import training_info
from toolkit.train import TrainingDiverged, field_steps, is_light_step, load_run, make_config, train


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("tiny"))


def _small(**kw):
    base = dict(batch_rays=512, ssim_patches=1, log_every=5, checkpoint_every=5, occupancy_resolution=24,
                occupancy_warmup=16)
    base.update(kw)
    return make_config("fast", **base)


def _test_psnr(run_dir):
    run = load_run(run_dir)
    sc = load_scene(run.scene_path, "test")
    vals = []
    for i in range(len(sc)):
        o = render_image(run.field, sc.cameras, i,
                         RenderConfig(sampler=run.cfg.render_sampler, shading=run.cfg.shading, deferred=True),
                         RenderInputs(run.occupancy, run.l_env, run.background, sc.aabb,
                                      run.dars_for(sc.cameras.c2w[i])))
        vals.append(float(psnr(linear_to_srgb(o.rgb.clamp(0, 1)).permute(2, 0, 1), sc.load_image(i))))
    return sum(vals) / len(vals)


def test_resume_reproduces_uninterrupted_run(tiny, tmp_path):
    cfg = _small(steps=24, pretrain_fraction=0.25, light_period=6, light_steps=2)
    a = train(tiny, tmp_path / "a", cfg, progress_bar=False, log=lambda m: None)
    train(tiny, tmp_path / "b", cfg, progress_bar=False, log=lambda m: None, stop_at=11)
    assert torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)["step"] == 11
    b = train(tiny, tmp_path / "b", make_config("fast"), resume=True, progress_bar=False, log=lambda m: None)
    ca, cb = torch.load(a, weights_only=False), torch.load(b, weights_only=False)
    assert ca["step"] == cb["step"] == 24
    for k, v in ca["field"].items():
        assert torch.equal(v, cb["field"][k]), f"parameter {k} differs after resume"
    assert torch.equal(ca["l_env"], cb["l_env"])
    assert torch.equal(ca["occupancy"]["density"], cb["occupancy"]["density"])
    # eq. 22's l_env steps are taken from the field's: 6 of the 24 here (steps 6, 7, 12, 13, 18, 19)
    assert [k for k in range(24) if is_light_step(cfg, k)] == [6, 7, 12, 13, 18, 19]
    assert field_steps(cfg) == 18 and field_steps(make_config("fast", steps=600)) == 560
    assert field_steps(make_config("fast", steps=600, fixed_light=True)) == 600
    assert field_steps(make_config("fast", steps=600, baseline="nerf")) == 600
    light_adam = next(iter(ca["light_optimizer"]["state"].values()))
    assert int(light_adam["step"]) == 24 - field_steps(cfg)  # the trainer took exactly those light steps
    assert training_info(load_run(tmp_path / "a"))["field_steps"] == 18


def test_smoke_training_psnr_rises(tiny, tmp_path):
    run = tmp_path / "run"
    train(tiny, run, _small(steps=10), progress_bar=False, log=lambda m: None)
    early = _test_psnr(run)
    train(tiny, run, _small(steps=300), resume=True, progress_bar=False, log=lambda m: None)
    late = _test_psnr(run)
    assert late > early + 3.0 and late > 18.0, (early, late)
    rows = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 300 and "psnr" in rows[-1]
    assert (run / "loss_curves.png").is_file()


def test_baseline_and_ablation_switches_train(tiny, tmp_path):
    for name, kw in {"nerf": dict(baseline="nerf"), "nodars": dict(dars=False), "nosem": dict(semantics=False),
                     "fixed": dict(fixed_light=True), "nomat": dict(mat_loss=False)}.items():
        ck = train(tiny, tmp_path / name, _small(steps=8, **kw), progress_bar=False, log=lambda m: None)
        assert ck.is_file()
    cfg = json.loads((tmp_path / "nerf" / "config.json").read_text())["config"]
    assert cfg["shading"] == "radiance" and cfg["sampler"]["dars"] is False and cfg["losses"]["mat"] == 0.0


def test_sampler_default_and_explicit_switch():
    """``dars`` not given (or None) takes the measured default; True/False and ``--dars``/``--no-dars`` override it,
    and the ablation's full model is DARS whatever the default."""
    from toolkit.ablation import VARIANTS
    from toolkit.cli import build_parser
    from toolkit.defaults import DARS_DEFAULT

    for kw, want in (({}, DARS_DEFAULT), ({"dars": None}, DARS_DEFAULT), ({"dars": True}, True),
                     ({"dars": False}, False)):
        cfg = make_config("fast", **kw)
        assert cfg.sampler.dars is want and cfg.render_sampler.dars is want, kw
    assert make_config("fast", dars=True, baseline="nerf").sampler.dars is False
    assert VARIANTS["full"] == {"dars": True} and VARIANTS["no_dars"] == {"dars": False}
    assert all(sw.get("dars") is True for name, sw in VARIANTS.items() if name not in ("no_dars", "nerf"))
    p = build_parser()
    a, b = (p.parse_args(["train", "s", "--out", "o", "--steps", "1", flag]) for flag in ("--dars", "--no-dars"))
    assert (a.dars, b.dars, p.parse_args(["train", "s", "--out", "o", "--steps", "1"]).dars) == (True, False, None)
    with pytest.raises(SystemExit):
        p.parse_args(["train", "s", "--out", "o", "--steps", "1", "--dars", "--no-dars"])


def test_bad_configs_rejected():
    with pytest.raises(ConfigError, match="batch_rays=8"):
        make_config("fast", batch_rays=8)
    with pytest.raises(ConfigError, match="preset='huge'"):
        make_config("huge")
    with pytest.raises(ConfigError, match="baseline='mip'"):
        make_config("fast", baseline="mip")
    with pytest.raises(ConfigError, match="light_steps=60 must be < light_period=50"):
        make_config("fast", light_steps=60)
    with pytest.raises(ConfigError, match="ssim patches use"):
        make_config("fast", batch_rays=512, ssim_patches=4)


def test_existing_run_not_overwritten_and_length_required(tiny, tmp_path):
    train(tiny, tmp_path / "r", _small(steps=2), progress_bar=False, log=lambda m: None)
    with pytest.raises(DarsError, match="already holds a run.*--resume"):
        train(tiny, tmp_path / "r", _small(steps=2), progress_bar=False, log=lambda m: None)
    with pytest.raises(ConfigError, match="training length"):
        train(tiny, tmp_path / "s", make_config("fast"), progress_bar=False, log=lambda m: None)


def test_nan_guard_keeps_last_good_checkpoint(tiny, tmp_path, monkeypatch):
    import toolkit.train.step as T

    real = T.rgb_l1
    calls = {"n": 0}

    def poisoned(*a, **k):
        calls["n"] += 1
        out = real(*a, **k)
        return out * float("nan") if calls["n"] > 12 else out

    monkeypatch.setattr(T, "rgb_l1", poisoned)
    with pytest.raises(TrainingDiverged, match="last good checkpoint is kept"):
        train(tiny, tmp_path / "n", _small(steps=40, pretrain_fraction=1.0), progress_bar=False, log=lambda m: None)
    ck = torch.load(tmp_path / "n" / "checkpoint.pt", weights_only=False)
    assert ck["step"] == 10  # checkpoint_every=5: the last one before the NaN at step 13
    assert all(torch.isfinite(v).all() for v in ck["field"].values())


def test_non_finite_gradients_are_skipped_then_stop_the_run(tiny, tmp_path, monkeypatch):
    """A finite loss with NaN gradients: the step is skipped (parameters untouched); MAX_BAD_STEPS in a row stop the
    run with a clear message and the last good checkpoint."""
    import toolkit.train.step as T

    class NanGrad(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.clone()

        @staticmethod
        def backward(ctx, g):
            return g * float("nan")

    real, calls = T.rgb_l1, {"n": 0}

    def poisoned(*a, **k):
        calls["n"] += 1
        out = real(*a, **k)
        return NanGrad.apply(out) if calls["n"] in (3,) or calls["n"] > 12 else out

    monkeypatch.setattr(T, "rgb_l1", poisoned)
    with pytest.raises(TrainingDiverged, match=r"non-finite gradients .* for 5 steps in a row"):
        train(tiny, tmp_path / "g", _small(steps=40, pretrain_fraction=1.0), progress_bar=False, log=lambda m: None)
    ck = torch.load(tmp_path / "g" / "checkpoint.pt", weights_only=False)
    assert ck["step"] == 15  # the single bad step 3 was skipped and the run went on; steps 13-17 stopped it
    assert all(torch.isfinite(v).all() for v in ck["field"].values())


def test_cli_train_and_render(tiny, tmp_path, capsys):
    from toolkit.cli import main

    assert main(["train", str(tiny), "--out", str(tmp_path / "c"), "--steps", "4", "--batch-rays", "512",
                 "--quiet"]) == 0
    assert main(["render", str(tmp_path / "c"), "--out", str(tmp_path / "img"), "--limit", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    names = {p.rsplit("_", 1)[-1] for p in out["files"]}
    assert {"rgb.png", "albedo.png", "roughness.png", "metallic.png", "normal.png", "semantic.png",
            "depth.png"} <= names
    assert main(["train", str(tiny), "--out", str(tmp_path / "d")]) == 2
    assert "training length" in capsys.readouterr().err


def test_cli_loss_options_are_recorded_and_checked_on_resume(tiny, tmp_path, capsys):
    """--sparse-depth, --opacity-loss, --depth-normal, --eikonal and --eikonal-step reach the run's config; --resume with another
    value is refused."""
    from toolkit.cli import main

    run = tmp_path / "l"
    assert main(["train", str(tiny), "--out", str(run), "--steps", "2", "--batch-rays", "256", "--quiet",
                 "--no-auto-priors", "--sparse-depth", "0.25", "--opacity-loss", "0.05", "--depth-normal", "0",
                 "--eikonal", "0.2", "--eikonal-step", "0.01"]) == 0
    losses = json.load(open(run / "config.json"))["config"]["losses"]
    assert losses["sparse_depth"] == 0.25 and losses["opacity"] == 0.05 and losses["depth_normal"] == 0.0
    assert losses["eikonal"] == 0.2 and losses["eikonal_step"] == 0.01
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--steps", "3", "--resume", "--sparse-depth", "0.5", "--quiet"]) == 2
    assert "--sparse-depth" in capsys.readouterr().err
    assert main(["train", "--out", str(run), "--steps", "3", "--resume", "--depth-normal", "0.3", "--quiet"]) == 2
    assert "--depth-normal 0.3 (the run's: 0.0)" in capsys.readouterr().err
    assert main(["train", "--out", str(run), "--steps", "3", "--resume", "--eikonal", "0.1", "--quiet"]) == 2
    assert "--eikonal 0.1 (the run's: 0.2)" in capsys.readouterr().err
    assert main(["train", "--out", str(run), "--steps", "3", "--resume", "--eikonal-step", "0.02", "--quiet"]) == 2
    assert "--eikonal-step 0.02 (the run's: 0.01)" in capsys.readouterr().err
    for bad, why in (("0", "must be > 0"), ("1.5", "must be ≤ 1")):
        assert main(["train", "--out", str(run), "--steps", "3", "--eikonal-step", bad, "--quiet"]) == 2
        assert f"argument --eikonal-step: {why}, got {bad}" in capsys.readouterr().err


def test_cli_train_computes_its_priors_from_the_photos(tmp_path, capsys):
    """`dars train` on photos + poses with no priors computes labels, metal masks and light with the shipped networks
    into <out>/priors, trains with them (never the scene's ground truth) and records which models produced them;
    --no-auto-priors trains without; a scene's own priors are used as they are."""
    from _synthetic_gallery import write_scene

    from toolkit.cli import main

    scene = write_scene(tmp_path / "scene", n_train=4, n_test=1, size=32)
    run = tmp_path / "run"
    assert main(["train", str(scene), "--out", str(run), "--steps", "2", "--batch-rays", "256", "--quiet"]) == 0
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["priors_root"] == str((run / "priors").resolve())
    assert cfg["priors"]["labels"].startswith("predicted") and cfg["priors"]["metal"].startswith("predicted")
    assert cfg["priors"]["weights"] == "computed (G+E+M)" and "ground_truth_inputs" not in cfg["priors"]
    assert cfg["l_env_source"].startswith("light network")
    rec = json.loads((run / "priors" / "priors.json").read_text())
    assert rec["ground_truth_inputs"] == "none" and rec["segment"]["model"].endswith("segmenter_small.pt")
    assert rec["light"]["model"].endswith(".pt") and len(rec["light"]["coeffs"]) == 9
    assert "out_of_domain" not in json.loads((run / "priors" / "light" / "light.json").read_text())
    assert (run / "priors" / "segment" / "train__r_000_metal.png").is_file()
    man = json.loads((run / "dars_manifest.json").read_text())
    assert "priors/" in man["files"] and "checkpoint.pt" in man["files"]
    # --force restarts the run in the same folder (the priors are recomputed over dars's own files)
    assert main(["train", str(scene), "--out", str(run), "--steps", "1", "--batch-rays", "256", "--quiet",
                 "--force"]) == 0
    # without
    assert main(["train", str(scene), "--out", str(tmp_path / "bare"), "--steps", "1", "--batch-rays", "256",
                 "--quiet", "--no-auto-priors"]) == 0
    cfg = json.loads((tmp_path / "bare" / "config.json").read_text())
    assert cfg["priors_root"] is None and cfg["priors"]["labels"] == "none" and not (tmp_path / "bare" / "priors").exists()
    # --light-init ambient: the same light estimate, band 0 only
    full = json.loads((run / "config.json").read_text())["l_env_init"]
    assert main(["train", str(scene), "--out", str(tmp_path / "amb"), "--steps", "1", "--batch-rays", "256", "--quiet",
                 "--priors", str(run / "priors"), "--light-init", "ambient"]) == 0
    cfg = json.loads((tmp_path / "amb" / "config.json").read_text())
    assert cfg["config"]["light_init"] == "ambient" and "band 0 only" in cfg["l_env_source"]
    assert cfg["l_env_init"][0] == full[0] and all(v == 0.0 for row in cfg["l_env_init"][1:] for v in row)
    assert any(v != 0.0 for row in full[1:] for v in row)
    capsys.readouterr()


def test_normal_losses_point_normals_out_of_the_surface():
    """Orientation loss: zero for normals facing the camera, (n·d)² for back-facing ones; L_eikonal: zero when the
    normal equals −∇σ/‖∇σ‖ and maximal (4) when it is the opposite."""
    from toolkit.losses import normal_consistency_loss, orientation_loss

    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])       # rays looking down −z at a floor (normal +z)
    w = torch.tensor([1.0, 3.0])
    up, down = torch.tensor([[0.0, 0.0, 1.0]] * 2), torch.tensor([[0.0, 0.0, -1.0]] * 2)
    assert float(orientation_loss(up, d, w)) == 0.0
    assert float(orientation_loss(down, d, w)) == pytest.approx(1.0)
    tilted = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, -1.0], [0.0, 0.0, 1.0]]), dim=-1)
    assert float(orientation_loss(tilted, d, w)) == pytest.approx(0.5 * 1.0 / 4.0)   # (cos 45°)² with weight 1 of 4
    grad = torch.tensor([[0.0, 0.0, -5.0]] * 2)                    # density grows downwards into the floor
    assert float(normal_consistency_loss(up, grad, w)) == pytest.approx(0.0)
    assert float(normal_consistency_loss(down, grad, w)) == pytest.approx(4.0)
    # a descent step turns the back-facing normal towards the camera (+z)
    n = down.clone().requires_grad_(True)
    orientation_loss(n, d, w).backward()
    assert (-n.grad[:, 2] > 0).all()


def test_sparse_depth_loss_wants_the_weight_at_the_known_depth():
    """Zero for an opaque ray whose weight sits at t*; a fog spread around t* and a transparent ray both cost; the
    gradient moves weight toward t*."""
    from toolkit.losses import sparse_depth_loss

    t = torch.tensor([1.0, 2.0, 3.0, 1.0, 2.0, 3.0, 1.0, 2.0, 3.0])
    ri = torch.tensor([0, 0, 0, 1, 1, 1, 2, 2, 2])
    target = torch.tensor([2.0, 2.0, 2.0])
    at = torch.tensor([0.0, 1.0, 0.0])
    fog = torch.tensor([1 / 3, 1 / 3, 1 / 3])
    empty = torch.zeros(3)
    assert float(sparse_depth_loss(torch.cat([at, at, at]), t, ri, target, 3)) == pytest.approx(0.0)
    # fog: 2 x (1/3 x 1/2) on its ray -> 1/3, mean over 3 rays
    assert float(sparse_depth_loss(torch.cat([at, fog, at]), t, ri, target, 3)) == pytest.approx(1 / 9)
    assert float(sparse_depth_loss(torch.cat([at, at, empty]), t, ri, target, 3)) == pytest.approx(1 / 3)
    w = torch.cat([fog, fog, fog]).requires_grad_(True)
    sparse_depth_loss(w, t, ri, target, 3).backward()
    assert (w.grad[1::3] < w.grad[0::3]).all() and (w.grad[1::3] < w.grad[2::3]).all()
    assert float(sparse_depth_loss(torch.zeros(0), torch.zeros(0), torch.zeros(0, dtype=torch.long), target[:0], 0)) == 0


def test_depth_normal_loss_follows_the_rendered_depth_not_the_head():
    """A tilted plane seen by a camera: a head normal equal to the plane's normal costs 0, the opposite one 2; the
    gradient reaches the normals and never the points (the geometry is the target)."""
    from toolkit.losses import depth_normal_loss

    s = 5
    v, u = torch.meshgrid(torch.arange(s, dtype=torch.float32), torch.arange(s, dtype=torch.float32), indexing="ij")
    n_true = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 1.0]), dim=0)
    # points on the plane n·p = 2, spread over (u, v); the camera at the origin looks along +z
    x, y = 0.1 * u, -0.1 * v
    z = (2.0 - n_true[0] * x - n_true[1] * y) / n_true[2]
    pts = torch.stack([x, y, z], -1)[None].requires_grad_(True)
    dirs = torch.nn.functional.normalize(pts.detach(), dim=-1)
    w = torch.ones(1, s, s)
    facing = (-n_true).expand(1, s, s, 3)  # toward the camera
    assert float(depth_normal_loss(pts, facing, dirs, w)) == pytest.approx(0.0, abs=1e-5)
    assert float(depth_normal_loss(pts, -facing, dirs, w)) == pytest.approx(2.0, abs=1e-5)
    side = torch.nn.functional.normalize(torch.cross(n_true, torch.tensor([1.0, 0.0, 0.0]), dim=0), dim=0)
    n = side.expand(1, s, s, 3).clone().requires_grad_(True)
    loss = depth_normal_loss(pts, n, dirs, w)
    assert float(loss.detach()) == pytest.approx(1.0, abs=1e-5)  # perpendicular: 1 - cos 90°
    loss.backward()
    assert pts.grad is None or float(pts.grad.abs().max()) == 0.0
    assert float(n.grad[0, 1:-1, 1:-1].abs().sum()) > 0 and float(n.grad[0, 0].abs().sum()) == 0  # interior only
    assert float(depth_normal_loss(pts, facing, dirs, torch.zeros(1, s, s))) == 0.0


def test_albedo_smoothness_leaves_photo_edges_free_and_flattens_the_rest():
    """A lamp pool on a plain wall (the photo brightens smoothly) must not be in the albedo: an albedo that follows it
    costs more than a flat one; an albedo edge where the photo has one costs nothing; the gradient reaches only the
    albedo; the term is trained and logged through ``dars train --albedo-smooth``."""
    from toolkit.losses import albedo_smoothness_loss

    s = 8
    ramp = torch.linspace(0.3, 0.45, s)  # 5 % brighter per pixel: a smooth pool of light
    photo = ramp.view(1, 1, s, 1).expand(1, s, s, 3).clone()
    w = torch.ones(1, s, s)
    flat = torch.full((1, s, s, 3), 0.5)
    follows = (flat * ramp.view(1, 1, s, 1) / 0.3).clamp(0, 1)
    assert float(albedo_smoothness_loss(flat, photo, w)) == 0.0
    assert float(albedo_smoothness_loss(follows, photo, w)) > 0.01
    edge_photo = torch.where(torch.arange(s).view(1, 1, s, 1) < s // 2, 0.1, 0.6).expand(1, s, s, 3).float()
    edge_albedo = torch.where(torch.arange(s).view(1, 1, s, 1) < s // 2, 0.1, 0.6).expand(1, s, s, 3).float()
    assert float(albedo_smoothness_loss(edge_albedo, edge_photo, w)) == pytest.approx(0.0, abs=1e-6)
    assert float(albedo_smoothness_loss(edge_albedo, photo, w)) > 0.0  # the same step where the photo is smooth
    a = follows.clone().requires_grad_(True)
    p = photo.clone().requires_grad_(True)
    albedo_smoothness_loss(a, p, w).backward()
    assert float(a.grad.abs().sum()) > 0 and (p.grad is None or float(p.grad.abs().max()) == 0.0)
    assert float(albedo_smoothness_loss(follows, photo, torch.zeros(1, s, s))) == 0.0


def test_albedo_smooth_option_trains_and_is_logged(tiny, tmp_path):
    import dataclasses

    cfg = _small(steps=6)
    cfg = dataclasses.replace(cfg, losses=dataclasses.replace(cfg.losses, albedo_smooth=0.2))  # tiny is an object
    train(tiny, tmp_path / "run", cfg, progress_bar=False, log=lambda m: None)
    rows = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert any("albedo_smooth" in r for r in rows)
    saved = json.loads((tmp_path / "run" / "config.json").read_text())["config"]["losses"]
    assert saved["albedo_smooth"] == 0.2


def test_sparse_depth_option_trains_and_is_recorded(sample_scene_path, tmp_path):
    """`losses.sparse_depth` > 0: targets triangulated from the photos, the term is logged, the weight recorded."""
    import dataclasses

    cfg = _small(steps=6, pretrain_fraction=0.5)
    cfg = dataclasses.replace(cfg, losses=dataclasses.replace(cfg.losses, sparse_depth=0.1))
    lines = []
    train(sample_scene_path, tmp_path / "r", cfg, progress_bar=False, log=lines.append)
    assert any("sparse depth:" in m and "pixels with a triangulated depth" in m for m in lines), lines
    rows = [json.loads(l) for l in open(tmp_path / "r" / "log.jsonl")]
    vals = [r["sparse_depth"] for r in rows if r.get("kind") == "train" and "sparse_depth" in r]
    assert vals and all(math.isfinite(v) and v >= 0 for v in vals)
    saved = json.load(open(tmp_path / "r" / "config.json"))["config"]["losses"]
    assert saved["sparse_depth"] == 0.1


def test_depth_normal_runs_without_ssim_and_needs_patches(sample_scene_path, tmp_path):
    """The depth-normal term draws its own image patches when L_ssim is off (no silent no-op); with no patches at
    all, a weight the user set is refused and the room default is turned off, saying so."""
    import dataclasses

    from toolkit._checks import ConfigError
    from toolkit.train import resolve_config

    cfg = _small(steps=4, pretrain_fraction=0.5, log_every=1)
    cfg = dataclasses.replace(cfg, losses=dataclasses.replace(cfg.losses, ssim=0.0, depth_normal=0.5))
    train(sample_scene_path, tmp_path / "r", cfg, progress_bar=False, log=lambda m: None)
    rows = [json.loads(l) for l in open(tmp_path / "r" / "log.jsonl")]
    train_rows = [r for r in rows if r.get("kind") == "train"]
    assert train_rows and all("depth_normal" in r and math.isfinite(r["depth_normal"]) for r in train_rows)
    assert not any("ssim" in r for r in train_rows)
    scene = load_scene(sample_scene_path, "train")
    nopatch = dataclasses.replace(make_config("fast", steps=1), ssim_patches=0)
    with pytest.raises(ConfigError, match="ssim_patches=0"):
        resolve_config(dataclasses.replace(nopatch, losses=dataclasses.replace(nopatch.losses, depth_normal=0.5)),
                       scene)
    lines = []
    room, _ = resolve_config(nopatch, scene, lines.append)
    assert room.losses.depth_normal == 0.0 and any("depth_normal off" in m for m in lines), lines


# ------------------------------------------------------------------------------------------------ room prior
def test_scene_type_auto_unbounded_for_the_gallery_object_for_lego(sample_scene_path):
    """Photos with no transparent pixel (the sample's RGBA PNGs are opaque everywhere; the tiny Lego's RGB on white)
    → unbounded: contracted field; photos with real transparency (NeRF Lego's RGBA) → object, bounded. No room layer
    in either (retired)."""
    from conftest import shared
    from toolkit.train import resolve_config
    from toolkit.train.config import photos_have_transparency

    assert photos_have_transparency(load_scene(shared("nerf_synthetic", "lego"), "train"))
    assert not photos_have_transparency(load_scene(sample_scene_path, "train"))

    cfg, scene = resolve_config(make_config("fast", steps=1), load_scene(sample_scene_path, "train"))
    assert cfg.scene_type == "unbounded" and cfg.field.contraction and cfg.field.shell == 0.0
    assert scene.aabb is not None and cfg.scene_box_source
    tiny, _ = resolve_config(make_config("fast", steps=1), load_scene(shared("tiny_lego", "tiny_lego_100.npz"), "train"))
    assert tiny.scene_type == "unbounded" and tiny.field.contraction
    forced, _ = resolve_config(make_config("fast", steps=1, scene_type="object"), load_scene(sample_scene_path, "train"))
    assert forced.scene_type == "object" and not forced.field.contraction
    room, _ = resolve_config(make_config("fast", steps=1, scene_type="room"), load_scene(sample_scene_path, "train"))
    assert room.scene_type == "unbounded" and room.field.contraction and room.field.shell == 0.0
    with pytest.raises(ConfigError, match="scene_type"):
        make_config("fast", steps=1, scene_type="hall")


def test_room_geometry_losses_follow_the_scene_type(sample_scene_path):
    """Weights left None become ROOM_LOSSES for a room and OBJECT_LOSSES or 0 for an object (the orientation loss:
    1.0 in a room, 0.1 on an object); a weight the user set is kept; the NeRF baseline has none of them."""
    import dataclasses

    from toolkit.train import resolve_config
    from toolkit.train.config import OBJECT_LOSSES, ROOM_LOSSES

    scene = load_scene(sample_scene_path, "train")
    keys = tuple(ROOM_LOSSES)
    assert set(keys) == {"sparse_depth", "opacity", "depth_normal", "layout_depth", "orientation", "layout_normal",
                         "albedo_smooth"}
    assert make_config("fast", steps=1).losses.orientation is None and OBJECT_LOSSES == {"orientation": 0.1,
                                                                                        "depth_normal": 0.5}
    assert all(v > 0 for v in ROOM_LOSSES.values())
    room, _ = resolve_config(make_config("fast", steps=1), scene)
    assert {k: getattr(room.losses, k) for k in keys} == ROOM_LOSSES
    obj, _ = resolve_config(make_config("fast", steps=1, scene_type="object"), scene)
    assert all(getattr(obj.losses, k) == OBJECT_LOSSES.get(k, 0.0) for k in keys)
    assert (room.losses.orientation, obj.losses.orientation) == (1.0, 0.1)
    assert (room.losses.depth_normal, obj.losses.depth_normal, obj.losses.opacity) == (0.5, 0.5, 0.0)
    cfg = make_config("fast", steps=1)
    cfg = dataclasses.replace(cfg, losses=dataclasses.replace(cfg.losses, depth_normal=0.0, opacity=0.3))
    mixed, _ = resolve_config(cfg, scene)
    assert (mixed.losses.depth_normal, mixed.losses.opacity, mixed.losses.sparse_depth) == (0.0, 0.3,
                                                                                             ROOM_LOSSES["sparse_depth"])
    nerf, _ = resolve_config(make_config("fast", steps=1, baseline="nerf", scene_type="room"), scene)
    assert all(getattr(nerf.losses, k) == 0.0 for k in keys)


def test_eikonal_follows_the_scene_type(sample_scene_path):
    """L_eikonal left None: Table 1's 0.01 over 1/512 of the box in a room, 0.1 over 1/64 on an object; the paper
    preset and the NeRF baseline keep 0.01 and 1/512 whatever the scene; a value the user set is kept; a run saved
    before the step was an option loads with 1/512."""
    import dataclasses

    from toolkit.train import TrainConfig, resolve_config
    from toolkit.train.config import EIKONAL

    scene = load_scene(sample_scene_path, "train")
    assert EIKONAL == {"unbounded": (0.01, 1 / 512), "object": (0.1, 1 / 64)}
    assert (make_config("fast", steps=1).losses.eikonal, make_config("fast", steps=1).losses.eikonal_step) == (None, None)
    got = {}
    for name, cfg in (("room", make_config("fast", steps=1)), ("object", make_config("fast", steps=1, scene_type="object")),
                      ("paper", make_config("paper", steps=1, scene_type="object")),
                      ("nerf", make_config("fast", steps=1, baseline="nerf", scene_type="object"))):
        r, _ = resolve_config(cfg, scene)
        got[name] = (r.losses.eikonal, r.losses.eikonal_step)
    assert got == {"room": (0.01, 1 / 512), "object": (0.1, 1 / 64), "paper": (0.01, 1 / 512), "nerf": (0.01, 1 / 512)}
    cfg = make_config("fast", steps=1, scene_type="object")
    cfg = dataclasses.replace(cfg, losses=dataclasses.replace(cfg.losses, eikonal=0.0))
    r, _ = resolve_config(cfg, scene)
    assert (r.losses.eikonal, r.losses.eikonal_step) == (0.0, 1 / 64)
    d = r.to_dict()
    d["losses"].pop("eikonal_step")
    assert TrainConfig.from_dict(d).losses.eikonal_step == 1 / 512


def test_shading_follows_the_scene_type(sample_scene_path):
    """The fast preset leaves ``deferred`` None: a room shades once per ray, an object at every sample (NeRF Lego lost
    2 dB per ray at a 15-minute budget; README "Shading once per ray"); --shade wins over the scene type; the paper
    preset and the NeRF baseline shade every sample whatever the scene."""
    from toolkit.train import resolve_config

    scene = load_scene(sample_scene_path, "train")
    assert make_config("fast", steps=1).deferred is None
    room, _ = resolve_config(make_config("fast", steps=1), scene)
    assert room.scene_type == "unbounded" and room.deferred is True
    obj, _ = resolve_config(make_config("fast", steps=1, scene_type="object"), scene)
    assert obj.deferred is False
    asked, _ = resolve_config(make_config("fast", steps=1, scene_type="object", deferred=True), scene)
    assert asked.deferred is True
    for cfg in (make_config("paper", steps=1), make_config("fast", steps=1, baseline="nerf", scene_type="room")):
        assert resolve_config(cfg, scene)[0].deferred is False


def test_retiming_keeps_the_schedule_continuous():
    """A re-timed budget's progress runs through its knots without a jump, ends at 1 on the new last step, and the
    learning-rate decay follows it; an on-time run is left alone; a late one loses at most half its remaining steps
    per check."""
    from toolkit.train.step import _progress_at, lr_progress, retime_steps

    base = make_config("fast", minutes=1.0, steps=1000)
    assert retime_steps(base, 250, 15.0, (96, 5.76), log=lambda m: None) is None  # 0.06 s/step: 60 s
    steps, knots = retime_steps(base, 250, 30.0, (96, 5.76), log=lambda m: None)  # 0.157 s/step: 148 s
    assert knots == ((250, 1000),) and steps == 250 + 375  # half the remaining 750 at most
    fast = retime_steps(base, 250, 7.0, (96, 5.76), log=lambda m: None)  # 0.008 s/step: twice the rest at most
    assert fast[0] == 250 + 1500
    cfg = make_config("fast", minutes=1.0, steps=steps, schedule_knots=knots)
    p = [_progress_at(cfg, k) for k in range(steps + 1)]
    assert p[:251] == [_progress_at(base, k) for k in range(251)]  # nothing already run changes
    assert all(b > a for a, b in zip(p, p[1:])) and p[-1] == 1.0
    assert max(b - a for a, b in zip(p, p[1:])) < 2.5 / 1000  # no jump
    from types import SimpleNamespace

    lr = [lr_progress(SimpleNamespace(cfg=cfg, step=k)) for k in range(steps + 1)]
    assert lr[96] == 0.0 and lr[-1] == pytest.approx(1.0) and all(b >= a for a, b in zip(lr, lr[1:]))
    with pytest.raises(ConfigError, match="schedule knots"):
        make_config("fast", steps=200, schedule_knots=((250, 1000),))
    with pytest.raises(ConfigError, match="increasing"):
        make_config("fast", steps=2000, schedule_knots=((400, 1000), (250, 800)))
    with pytest.raises(ConfigError, match="beyond"):
        make_config("fast", steps=2000, schedule_knots=((400, 300),))


def test_minutes_budget_retimes_when_steps_get_slower_and_the_log_replays_it(tiny, tmp_path, monkeypatch):
    """A ``minutes`` budget whose steps triple in cost after the calibration (an occupancy grid filling up, a busier
    machine) checks its clock at 25/50/75 % and cuts its step count, recorded in ``config.json``; ``--steps N`` with
    the logged knots replays the run to the same parameters."""
    import toolkit.train.loop as loop

    real = loop.train_step

    clock = [0.0]  # the loop's clock, advanced by the steps alone: the same run however busy the machine is

    def slower(state, data):  # 1 s a step, three times that from step 12 on
        out = real(state, data)
        clock[0] += 1.0 if state.step < 12 else 3.0
        return out

    monkeypatch.setattr(loop, "train_step", slower)
    monkeypatch.setattr(loop.time, "monotonic", lambda: clock[0])
    cfg = _small(minutes=0.3, calibration_steps=8, checkpoint_every=1000)  # so short that steps 6-7 of a replay
    logs = []                                                               # would be in stage b without its 8:0 knot
    a = train(tiny, tmp_path / "a", cfg, progress_bar=False, log=logs.append)
    meta = json.loads((tmp_path / "a" / "config.json").read_text())
    cal, knots = meta["calibration"], meta["config"]["schedule_knots"]
    assert cal["retimed"] and knots and cal["steps"] == meta["config"]["steps"] == cal["retimed"][-1]["steps"]
    assert knots[0][1] == 0 and 0 < knots[0][0] <= 8  # the calibration: no step count (progress 0) before it
    assert f"--schedule-knots {knots[0][0]}:0)" in next(m for m in logs if "timing calibration" in m)
    first = int(next(m for m in logs if "timing calibration" in m).split("-> ")[1].split()[0])
    assert meta["config"]["steps"] < first  # the slower steps cost steps, not minutes
    replay = [m for m in logs if "--schedule-knots" in m][-1].split("--steps ")[-1].rstrip(")")  # the last check
    steps, knot_text = replay.split(" --schedule-knots ")
    assert int(steps) == meta["config"]["steps"]
    monkeypatch.undo()  # the real step and clock again for the replay, which has no budget to time
    from toolkit.train.config import parse_knots

    b = train(tiny, tmp_path / "b", _small(steps=int(steps), schedule_knots=parse_knots(knot_text),
                                           calibration_steps=8, checkpoint_every=1000),
              progress_bar=False, log=lambda m: None)
    ca, cb = torch.load(a, weights_only=False), torch.load(b, weights_only=False)
    assert ca["step"] == cb["step"] == int(steps)
    for k, v in ca["field"].items():
        assert torch.equal(v, cb["field"][k]), f"parameter {k} differs in the replay"


def test_a_minutes_budget_s_calibration_knot_keeps_its_first_steps_in_stage_a():
    """Before its calibration a minutes budget has no step count, so its progress is 0 (stage a, no light steps)
    whatever count it then gets; the replay's first knot (c, 0) keeps it so, and bends nothing after c."""
    from toolkit.train.config import parse_knots
    from toolkit.train.step import _progress_at, is_light_step

    light = dict(light_period=2, light_steps=1, shading="pbr", fixed_light=False)
    plain = make_config("fast", steps=20, calibration_steps=8, **light)
    replay = make_config("fast", steps=20, calibration_steps=8, schedule_knots=parse_knots("8:0"), **light)
    assert _progress_at(plain, 7) == 7 / 20 and _progress_at(replay, 7) == 0.0
    assert [_progress_at(replay, s) for s in range(8, 21)] == [_progress_at(plain, s) for s in range(8, 21)]
    assert not any(is_light_step(replay, s) for s in range(8)) and any(is_light_step(plain, s) for s in range(8))
    bent = make_config("fast", steps=40, calibration_steps=8, schedule_knots=parse_knots("8:0,12:20"))
    assert _progress_at(bent, 12) == 12 / 20 and _progress_at(bent, 5) == 0.0
    for bad in ("8:0,4:10", "4:10,8:0"):
        with pytest.raises(ConfigError, match="only the first may be STEP:0"):
            make_config("fast", steps=40, schedule_knots=parse_knots(bad))


def test_room_layer_density_on_enabled_faces_only():
    from toolkit.field import DarsField, FieldConfig

    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    faces = (True, True, True, True, True, False)                  # no layer on the top face (z max)
    fld = DarsField(FieldConfig(shell=0.05, shell_faces=faces), aabb)
    eps = 0.05 * float((aabb[1] - aabb[0]).norm())
    pts = torch.tensor([[0.0, 0.0, 0.0],                           # centre: transparent start
                        [0.0, 1.0 - 0.1 * eps, 0.0],               # just inside y max: opaque
                        [0.0, 0.0, -1.0 + 0.1 * eps],              # just inside z min: opaque
                        [0.0, 0.0, 1.0 - 0.1 * eps],               # just inside z max: no layer
                        [0.0, 1.0 - 1.5 * eps, 0.0]])              # deeper than the layer: transparent
    with torch.no_grad():
        sigma = fld.density(pts)
        assert float(sigma[1]) * eps > 20 and float(sigma[2]) * eps > 20, sigma
        assert float(sigma[0]) * eps < 0.1 and float(sigma[3]) * eps < 0.1 and float(sigma[4]) * eps < 0.1, sigma
        fld.shell_weight.fill_(0.0)                                # faded out: transparent everywhere
        assert float(fld.density(pts).max()) * eps < 0.1
    assert "shell_weight" in fld.state_dict() and "shell_weight" not in DarsField(FieldConfig(), aabb).state_dict()
    with pytest.raises(ConfigError, match="shell"):
        FieldConfig(shell=0.7)


# ------------------------------------------------------------------------------------------------ photos in, memory
def _mixed_sizes(src, dst):
    """A copy of the tiny scene whose training photos come in three sizes: every third cropped to portrait 24x32,
    the next to landscape 32x20 (per-frame w, h, fl_x, cx, cy), the rest 32x32; labels and metal masks cropped too."""
    import shutil

    import cv2

    shutil.copytree(src, dst)
    meta = json.loads((dst / "transforms_train.json").read_text())
    focal = 0.5 * 32 / math.tan(0.5 * meta["camera_angle_x"])
    for k, fm in enumerate(meta["frames"]):
        r0, r1, c0, c1 = {0: (0, 32, 4, 28), 1: (6, 26, 0, 32)}.get(k % 3, (0, 32, 0, 32))
        for key in ("file_path", "semantic_path", "metal_path"):
            p = str(dst / fm[key])
            cv2.imwrite(p, cv2.imread(p, cv2.IMREAD_UNCHANGED)[r0:r1, c0:c1])
        fm.update(w=c1 - c0, h=r1 - r0, fl_x=focal, fl_y=focal, cx=16.0 - c0, cy=16.0 - r0)
    (dst / "transforms_train.json").write_text(json.dumps(meta))
    return dst


def _on_transparent_background(src, dst):
    """A copy of the tiny scene as RGBA photos of the sphere and floor on a transparent background (alpha 0 where
    the labels say background), like NeRF-synthetic renders."""
    import shutil

    import numpy as np
    from PIL import Image

    shutil.copytree(src, dst)
    for split in ("train", "test"):
        for fm in json.loads((dst / f"transforms_{split}.json").read_text())["frames"]:
            rgb = np.asarray(Image.open(dst / fm["file_path"]).convert("RGB"))
            alpha = np.where(np.asarray(Image.open(dst / fm["semantic_path"])) == 255, 0, 255).astype(np.uint8)
            Image.fromarray(np.dstack([rgb, alpha]), "RGBA").save(dst / fm["file_path"])
    return dst


def test_an_object_grid_prunes_thin_fog_that_a_room_grid_keeps(tiny, tmp_path):
    """An object on a transparent background (bounded box) counts a cell empty against Instant-NGP's fine step
    (box diagonal / 1024); a room (contracted) against its coarse sample spacing. Around a dense ball, a fog whose
    coarse-sample opacity is 4 % and whose fine-step opacity is 0.1 % is empty for the object grid (only the ball's
    cells stay) and occupied for the room grid."""
    from toolkit.train import init_state, prepare_data, resolve_config
    from toolkit.train.step import OBJECT_OCCUPANCY_STEPS

    grids = {}
    for name, root in (("object", _on_transparent_background(tiny, tmp_path / "rgba")), ("room", tiny)):
        cfg, scene = resolve_config(_small(steps=1), load_scene(root, "train"))
        assert cfg.scene_type == ("object" if name == "object" else "unbounded")
        st = init_state(cfg, prepare_data(scene, cfg, log=lambda m: None, priors_root=tmp_path / "none"))
        extent = float((scene.aabb[1] - scene.aabb[0]).norm())
        sigma = 0.04 / (extent / cfg.sampler.n_coarse)
        st.occupancy.update(lambda p: torch.where(p.norm(dim=-1) < 0.4, 1e3, sigma), all_cells=True)
        grids[name] = (st.occupancy, extent, cfg.sampler.n_coarse)
    ball = torch.zeros(3, 1)
    occ, extent, _ = grids["object"]
    assert occ.step == pytest.approx(extent / OBJECT_OCCUPANCY_STEPS)
    assert 0.0 < occ.occupancy_fraction() < 0.1 and bool(occ.occupied(ball.T)[0])
    occ, extent, n = grids["room"]
    assert occ.step == pytest.approx(extent / n) and occ.occupancy_fraction() == 1.0


def test_an_object_on_a_known_background_starts_from_its_own_ambient(tiny, tmp_path, capsys):
    """On RGBA photos with transparency the light network's estimate (trained on whole photos of rooms; here most
    pixels are the compositing colour) is computed but not used: the light starts from the object pixels' grey
    ambient, and config.json says why. Opaque photos keep the network's estimate
    (test_cli_train_computes_its_priors_from_the_photos)."""
    from toolkit.cli import main
    from toolkit.io import srgb_to_linear
    from toolkit.train import grey_ambient_sh

    scene_dir = _on_transparent_background(tiny, tmp_path / "rgba")
    run = tmp_path / "run"
    assert main(["train", str(scene_dir), "--out", str(run), "--steps", "1", "--batch-rays", "256", "--quiet"]) == 0
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["config"]["scene_type"] == "object" and (run / "priors" / "light" / "light.json").is_file()
    assert cfg["l_env_source"].startswith("grey ambient of the object pixels (light network (")
    assert cfg["priors"]["light"] == cfg["l_env_source"]
    light = json.loads((run / "priors" / "light" / "light.json").read_text())
    assert "out of its domain" in light["out_of_domain"] and "out of its domain" in capsys.readouterr().err
    scene = load_scene(scene_dir, "train")
    tot, n = 0.0, 0
    for i in range(len(scene)):
        rgba = scene.load_image(i, with_alpha=True)
        obj = rgba[3] > 0.5
        tot, n = tot + float(srgb_to_linear(rgba[:3])[:, obj].sum(dtype=torch.float64)), n + 3 * int(obj.sum())
    want = grey_ambient_sh(tot / n)
    got = torch.tensor(cfg["l_env_init"])
    assert torch.allclose(got, want.to(got), rtol=0.02, atol=1e-4), (got[0], want[0])
    capsys.readouterr()


@pytest.mark.parametrize("normalise", ["quantile", "none"])
def test_prepare_data_stores_w_once_at_8_bits(tiny, tmp_path, normalise):
    """W computed by the trainer is normalised at full precision and stored as uint8 (1 byte a pixel): every view
    reads back as the float map (rank-normalised for ``quantile``) within half a quantisation step."""
    from dataclasses import replace

    from toolkit.edges import WeightMapConfig, quantile_normalise, weight_map
    from toolkit.train import prepare_data

    scene = load_scene(tiny, "train").subset([0, 5, 11])
    cfg = make_config("fast", labels="ground-truth")
    cfg = replace(cfg, sampler=replace(cfg.sampler, normalise=normalise))
    data = prepare_data(scene, cfg, log=lambda m: None, priors_root=tmp_path / "no_priors")
    assert data.priors_used["weights"] == "computed (G+E+M)"
    assert data.weights.data.dtype == torch.uint8 and data.weights.quantised
    assert data.weights.nbytes == data.weights.n_pixels  # 1 byte a pixel
    for i in range(len(scene)):
        lab, metal = scene.load_extra(i, "semantic"), scene.load_extra(i, "metal")
        w = weight_map(scene.load_image(i)[None], lab[None], metal[None], WeightMapConfig()).weights.clamp(0, 1)
        want = quantile_normalise(w)[0] if normalise == "quantile" else w[0]
        got = data.weights[i]
        assert got.dtype == torch.float32 and got.shape == want.shape
        assert float((got - want).abs().max()) <= 0.5 / 255 + 1e-6
        flat = torch.arange(int(data.weights.offsets[i]), int(data.weights.offsets[i + 1]))
        assert torch.equal(data.weights.gather(flat), got.reshape(-1))  # the sampler's reads: the same floats


def test_training_on_photos_of_different_sizes(tiny, tmp_path):
    """Portrait, landscape and square photos end to end: the prior stages (builtin segmenter trained on the photos
    of one size, light network, W maps) and a run with packed pixels, labels, metal and W maps of each view's own
    size; the DARS sampler and renderer read each view at its size."""
    from toolkit.priors import priors_light, priors_segment, priors_weights
    from toolkit.segment import TrainSegmenterConfig

    scene = _mixed_sizes(tiny, tmp_path / "mixed")
    sc = load_scene(scene, "train")
    assert {(int(h), int(w)) for h, w in zip(sc.cameras.height, sc.cameras.width)} == {(32, 24), (20, 32), (32, 32)}
    info = priors_segment(sc, None, "builtin", train_every=2, train_cfg=TrainSegmenterConfig(steps=3, crop=16))
    assert len(info["train_views"]) == 7 and 0.0 <= info["miou_heldout"] <= 1.0  # the 32x24 ones of every 2nd
    assert len(priors_light(sc, None)["per_image"]) == len(sc)
    priors_weights(sc, None)
    train(scene, tmp_path / "r", _small(steps=30, labels="ground-truth", dars=True), progress_bar=False,
          log=lambda m: None)  # DARS: its W maps are read per view size
    run = load_run(tmp_path / "r")
    assert run.weight_maps[0].shape == (32, 24) and run.weight_maps[1].shape == (20, 32)
    assert run.weight_maps[2].shape == (32, 32)
    assert run.weight_maps.data.dtype == torch.uint8 and run.weight_maps.quantised
    out = run.render(run.train_scene.cameras, 1)
    assert out.rgb.shape[:2] == (20, 32) and bool(torch.isfinite(out.rgb).all())
    priors = json.loads((tmp_path / "r" / "config.json").read_text())["priors"]
    assert priors["labels"] == "provided" and priors["metal"] == "provided"
    assert priors["weights"].startswith("loaded") and priors["light"].startswith("light network")


def test_downscale_is_recorded_and_used_by_render_and_resume(tiny, tmp_path, capsys):
    from toolkit.cli import main

    run_dir = tmp_path / "d"
    train(tiny, run_dir, _small(steps=4, dars=True), progress_bar=False, log=lambda m: None, downscale=2)  # W maps too
    assert json.loads((run_dir / "config.json").read_text())["downscale"] == 2
    run = load_run(run_dir)
    assert run.downscale == 2 and run.train_scene.image_size == (16, 16) and run.weight_maps[0].shape == (16, 16)
    assert run.load_split("test").image_size == (16, 16)
    with pytest.raises(DarsError, match="--downscale 2, not 4"):
        train(tiny, run_dir, _small(steps=8), resume=True, progress_bar=False, log=lambda m: None, downscale=4)
    train(tiny, run_dir, _small(steps=6), resume=True, progress_bar=False, log=lambda m: None)
    assert load_run(run_dir).step == 6 and json.loads((run_dir / "config.json").read_text())["downscale"] == 2
    # a run folder written before --downscale existed (no key) loads at full size
    meta = json.loads((run_dir / "config.json").read_text())
    del meta["downscale"]
    (run_dir / "config.json").write_text(json.dumps(meta))
    assert load_run(run_dir).train_scene.image_size == (32, 32)
    try:
        rc = main(["train", str(tiny), "--out", str(tmp_path / "z"), "--steps", "2", "--downscale", "0"])
    except SystemExit as e:
        rc = e.code
    assert rc == 2
    assert "--downscale: must be ≥ 1, got 0" in capsys.readouterr().err


def test_upright_is_recorded_and_used_by_load_run_and_resume(tiny, tmp_path, capsys, monkeypatch):
    import shutil

    import numpy as np

    from toolkit.cli import main
    from toolkit.sh import rotation_x

    tilted = tmp_path / "tilted"  # the tiny scene turned 30 deg about x, without its box: made upright on load
    shutil.copytree(tiny, tilted)
    turn = np.eye(4)
    turn[:3, :3] = rotation_x(30.0).numpy()
    for split in ("train", "test"):
        meta = json.loads((tilted / f"transforms_{split}.json").read_text())
        del meta["aabb"]
        for fr in meta["frames"]:
            fr["transform_matrix"] = (turn @ np.asarray(fr["transform_matrix"])).tolist()
        (tilted / f"transforms_{split}.json").write_text(json.dumps(meta))
    file_c2w = load_scene(tilted, "train", upright="off").cameras.c2w
    auto, off = tmp_path / "auto", tmp_path / "off"
    train(tilted, auto, _small(steps=1), progress_bar=False, log=lambda m: None)
    assert json.loads((auto / "config.json").read_text())["upright"] == "auto"
    run = load_run(auto, with_weights=False)
    assert run.train_scene.meta["upright"]["applied"] and run.load_split("test").meta["upright"]["applied"]
    assert not torch.allclose(run.train_scene.cameras.c2w, file_c2w, atol=1e-3)
    with pytest.raises(DarsError, match="made upright on load, not with --no-upright"):
        train(tilted, auto, _small(steps=2), resume=True, progress_bar=False, log=lambda m: None, upright="off")
    # a run folder written before upright-on-load (no key) trained in the file's frame and loads in it
    meta = json.loads((auto / "config.json").read_text())
    del meta["upright"]
    (auto / "config.json").write_text(json.dumps(meta))
    assert torch.equal(load_run(auto, with_weights=False).train_scene.cameras.c2w, file_c2w)
    seen = []  # `dars train --no-upright` is train(..., upright="off")
    monkeypatch.setattr("toolkit.train.train", lambda *a, **kw: seen.append(kw["upright"]) or off / "checkpoint.pt")
    for flag in ([], ["--no-upright"]):
        assert main(["train", str(tilted), "--out", str(off), "--steps", "1", "--quiet", *flag]) == 0
    assert seen == ["auto", "off"]
    monkeypatch.undo()
    capsys.readouterr()
    train(tilted, off, _small(steps=1), progress_bar=False, log=lambda m: None, upright="off")
    assert json.loads((off / "config.json").read_text())["upright"] == "off"
    train(tilted, off, _small(steps=2), resume=True, progress_bar=False, log=lambda m: None)
    assert json.loads((off / "config.json").read_text())["upright"] == "off"
    run = load_run(off, with_weights=False)
    assert run.step == 2 and torch.equal(run.train_scene.cameras.c2w, file_c2w)
    assert run.load_split("test").meta["upright"]["kept"] == "upright='off'"


def test_light_head_folds_the_global_light_into_its_bias():
    # the light head's 27 l_env inputs are the same for every point: DarsField.heads adds them to the first layer's
    # bias instead of concatenating them to h; the residual, and the gradients it sends back, must not change
    from toolkit.field import DarsField, FieldConfig

    torch.manual_seed(0)
    fld = DarsField(FieldConfig(), torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    for p in fld.light_head.parameters():                          # the last layer starts at zero: make it not
        torch.nn.init.normal_(p, std=0.3)
    h = torch.randn(64, fld.feature_dim, requires_grad=True)
    l_env = torch.randn(9, 3)
    folded = fld._light_head(h, l_env)
    ref = fld.light_head(torch.cat([h, l_env.reshape(1, 27).expand(64, 27)], -1))
    assert torch.allclose(folded, ref, atol=1e-5), float((folded - ref).abs().max())
    w = torch.randn_like(ref)
    params = [h] + list(fld.light_head.parameters())
    g_folded = torch.autograd.grad((folded * w).sum(), params)
    g_ref = torch.autograd.grad((ref * w).sum(), params)
    for a, b in zip(g_folded, g_ref):
        assert torch.allclose(a, b, atol=1e-4, rtol=1e-4)
    out = fld.heads(h.detach(), l_env=l_env)
    assert out.light_residual.shape == (64, 9, 3) and torch.isfinite(out.light).all()


def test_grey_light_residual_shades_but_does_not_tint():
    # light_residual_colour='grey': one factor per SH coefficient, shared by the channels as a fraction of each
    # channel's ambient, so Δl_c / ½|L00_c| is the same for r, g and b; 'rgb' keeps a factor per channel
    from toolkit.field import DarsField, FieldConfig
    from toolkit.train.config import TrainConfig

    torch.manual_seed(0)
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    l_env = torch.randn(9, 3)
    h = torch.randn(32, FieldConfig().feature_dim)
    ratios = {}
    for colour in ("rgb", "grey"):
        torch.manual_seed(1)
        fld = DarsField(FieldConfig(light_residual_colour=colour), box)
        for p in fld.light_head.parameters():
            torch.nn.init.normal_(p, std=0.3)
        res = fld.heads(h, l_env=l_env).light_residual
        assert res.shape == (32, 9, 3)
        ratios[colour] = res / (0.5 * l_env[:1].abs() + 1e-3)          # tanh(g_kc)
        z = fld._light_head(h, l_env).reshape(-1, 9, 3)
        want = torch.tanh(z.mean(-1, keepdim=True) if colour == "grey" else z).expand(-1, -1, 3)
        assert torch.allclose(ratios[colour], want, atol=1e-4)  # grey: the tanh of the channels' mean output
    assert torch.allclose(ratios["grey"], ratios["grey"][..., :1].expand(-1, -1, 3), atol=1e-5)
    assert (ratios["rgb"] - ratios["rgb"][..., :1]).abs().max() > 0.05
    with pytest.raises(ConfigError, match="light_residual_colour"):
        FieldConfig(light_residual_colour="red")
    # runs saved before the option had the coloured residual
    d = TrainConfig().to_dict()
    del d["field"]["light_residual_colour"]
    assert TrainConfig.from_dict(d).field.light_residual_colour == "rgb"
