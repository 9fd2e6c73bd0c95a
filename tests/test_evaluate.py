import json
import math

import numpy as np
import pytest
import torch

from _eval_scene import GT_SH, add_ground_truth, small_config
from synthetic import make_scene
from toolkit._checks import DarsError
from toolkit.evaluate import (JSON_SECTIONS, METRIC_KEYS, EvalConfig, choose_patch, evaluate_run,
                              training_sample_counts, variant_of)
from toolkit.io import linear_to_srgb, srgb_to_linear
from toolkit.metrics import (MetricUnavailable, _lpips_expected, env_light_l2, luminance, patch_masks, psnr,
                             uniform_view_indices)
from toolkit.scene import Cameras, load_scene
from toolkit.train import load_run, make_config, train


@pytest.fixture(scope="module")
def scene_gt(tmp_path_factory):
    return add_ground_truth(make_scene(tmp_path_factory.mktemp("evalscene")))


@pytest.fixture(scope="module")
def run_dir(scene_gt, tmp_path_factory):
    out = tmp_path_factory.mktemp("evalrun") / "run"
    # DARS whatever the default sampler: the tests below read its per-ray sample counts and render path
    train(scene_gt, out, small_config(steps=12, dars=True), progress_bar=False, log=lambda m: None)
    return out


@pytest.fixture(scope="module")
def lpips_file(tmp_path_factory):
    g = torch.Generator().manual_seed(0)
    sd = {}
    for k, shape in _lpips_expected().items():
        t = torch.randn(shape, generator=g) * 0.05
        if k.startswith("lin"):  # LPIPS v0.1 layout: linK.model.1.weight, non-negative
            sd[k.replace(".weight", ".model.1.weight")] = t.abs()
        else:
            sd[k] = t
    p = tmp_path_factory.mktemp("lpips") / "lpips_synthetic.pth"
    torch.save(sd, p)
    return p


SPHERE_TOP = dict(patch_centre=(0.0, 0.0, 0.5), patch_normal=(0.0, 0.0, 1.0), patch_size=0.5)


@pytest.fixture(scope="module")
def full_eval(run_dir, lpips_file):
    return evaluate_run(load_run(run_dir), "test", EvalConfig(lpips_weights=str(lpips_file), **SPHERE_TOP),
                        log=lambda m: None)


def test_every_metric_computed_when_data_supports_it(full_eval, run_dir):
    res = full_eval
    doc = res.to_json()
    assert list(doc)[:len(METRIC_KEYS)] == list(METRIC_KEYS)
    assert set(doc) == set(METRIC_KEYS) | set(JSON_SECTIONS)
    missing = {k: doc["unavailable"].get(k) for k in METRIC_KEYS if doc[k] is None}
    assert not missing, missing
    assert doc["unavailable"] == {}
    for k in METRIC_KEYS:
        assert isinstance(doc[k], float) and math.isfinite(doc[k]), (k, doc[k])
    assert len(doc["per_view"]) == 8 and all(r["lpips"] is not None for r in doc["per_view"])
    # known values: the dataset PSNR is the mean of per-view PSNRs, each reproducible from one render
    assert doc["psnr"] == pytest.approx(np.mean([r["psnr"] for r in doc["per_view"]]))
    run = load_run(run_dir)
    sc = load_scene(run.scene_path, "test")
    o = run.render(sc.cameras, 3)  # the run's own settings, as dars eval renders
    own = float(psnr(linear_to_srgb(o.rgb.clamp(0, 1)).permute(2, 0, 1), sc.load_image(3)))
    assert doc["per_view"][3]["psnr"] == pytest.approx(own, abs=1e-4)
    assert doc["env_light_l2"] == pytest.approx(float(env_light_l2(run.l_env, torch.tensor(GT_SH))), rel=1e-5)
    assert 0.0 <= doc["miou"] <= 1.0 and 0.0 <= doc["normal_mae"] <= 180.0
    mat = doc["details"]["materials"]  # beside the table: the albedo error left after a per-channel scale
    assert 0.0 <= mat["albedo_mae_aligned"] <= 1.0 and len(mat["albedo_scale"]) == 3
    assert all(s > 0 for s in mat["albedo_scale"])
    assert mat["metallic_mae"] is None or 0.0 <= mat["metallic_mae"] <= 1.0
    # roughness per GT class: the classes pool back to the overall RMSE over the pixels they cover
    by, n_by = mat["roughness_rmse_by_class"], mat["roughness_pixels_by_class"]
    assert by and set(by) == set(n_by) and len(by) >= 2, by
    assert sum(n_by.values()) == doc["details"]["pixels"]["roughness_rmse"]
    pooled = math.sqrt(sum(by[k] ** 2 * n_by[k] for k in by) / sum(n_by.values()))
    assert pooled == pytest.approx(doc["roughness_rmse"], rel=1e-5)
    # albedo per GT class: the classes pool back to the overall MAE; the level is predicted / GT mean albedo
    by, n_by, level = mat["albedo_mae_by_class"], mat["albedo_pixels_by_class"], mat["albedo_level_by_class"]
    assert by and set(by) == set(n_by) == set(level) and len(by) >= 2, by
    assert sum(n_by.values()) == doc["details"]["pixels"]["albedo_mae"]
    assert sum(by[k] * n_by[k] for k in by) / sum(n_by.values()) == pytest.approx(doc["albedo_mae"], rel=1e-5)
    assert all(v > 0 for v in level.values())
    # no ground truth: the normals against the rendered depth, per view as a direct computation gives it
    from toolkit.evaluate import normal_depth_agreement
    ang, _ = normal_depth_agreement(sc.cameras, 3, o.depth, o.normal, o.opacity)
    v3 = doc["per_view"][3]["normal_vs_depth_deg"]
    assert (v3 is None) if ang.numel() == 0 else v3 == pytest.approx(float(ang.mean()), abs=1e-3)
    nvd = doc["details"]["normal_vs_depth"]
    views = [r["normal_vs_depth_deg"] for r in doc["per_view"] if r["normal_vs_depth_deg"] is not None]
    assert (nvd is None) == (not views)
    if nvd is not None:
        assert min(views) <= nvd["angle_mean_deg"] <= max(views) and 0.0 <= nvd["back_facing_share"] <= 1.0


def test_view_consistency_patch_matches_independent_computation(full_eval, scene_gt):
    vc = full_eval.details["view_consistency"]
    sc = load_scene(scene_gt, "test")
    assert vc["patch"]["source"].startswith("given") and vc["occlusion"] == "GT depth"
    depths = torch.stack([sc.load_extra(i, "depth") for i in range(8)])
    all_masks = patch_masks(sc.cameras, range(8), (0, 0, 0.5), (0, 0, 1), 0.5, depths=depths)
    seen = [i for i in range(8) if int(all_masks[i].sum()) >= 4]  # K = every view that sees >= 4 px of the patch
    assert len(seen) >= 4 and vc["k"] == len(seen) and vc["views"] == seen
    masks = all_masks[seen]
    gts = torch.stack([srgb_to_linear(sc.load_image(i)) for i in vc["views"]])
    means = (luminance(gts) * masks).sum((1, 2)) / masks.sum((1, 2))
    assert vc["pixels"] == masks.sum((1, 2)).tolist()
    np.testing.assert_allclose(vc["gt_means"], means.numpy(), rtol=1e-5)
    assert vc["gt_value"] == pytest.approx(float(means.std()), rel=1e-5)
    assert full_eval.metrics["view_consistency"] == vc["value"]
    assert "relative luminance" in vc["units"]


def test_lux_factor_scales_view_consistency(run_dir):
    res = evaluate_run(load_run(run_dir), "test", EvalConfig(limit=4, lux_factor=200.0, weight_views=0,
                                                             figure_views=0, **SPHERE_TOP), log=lambda m: None)
    ref = evaluate_run(load_run(run_dir), "test", EvalConfig(limit=4, weight_views=0, figure_views=0, **SPHERE_TOP),
                       log=lambda m: None)
    assert res.metrics["view_consistency"] == pytest.approx(200.0 * ref.metrics["view_consistency"], rel=1e-5)
    assert res.details["view_consistency"]["units"].startswith("lux")


def test_plain_scene_nulls_have_reasons(run_dir, monkeypatch):
    monkeypatch.delenv("DARS_LPIPS_WEIGHTS", raising=False)
    res = evaluate_run(load_run(run_dir), "train", EvalConfig(limit=3, weight_views=1, figure_views=1),
                       log=lambda m: None)
    doc = res.to_json()
    assert set(doc) == set(METRIC_KEYS) | set(JSON_SECTIONS)
    for k in ("psnr", "ssim", "flip", "miou"):
        assert doc[k] is not None, (k, doc["unavailable"].get(k))
    assert "DARS_LPIPS_WEIGHTS" in doc["unavailable"]["lpips"]
    assert "albedo_path" in doc["unavailable"]["albedo_mae"]
    assert "roughness_path" in doc["unavailable"]["roughness_rmse"]
    assert "normal_path" in doc["unavailable"]["normal_mae"]
    assert "ground-truth SH" in doc["unavailable"]["env_light_l2"]
    assert {k for k in METRIC_KEYS if doc[k] is None} == set(doc["unavailable"])
    assert doc["eval"]["views"] == 3 and doc["eval"]["view_indices"] == uniform_view_indices(40, 3)


def test_training_info_and_variants(full_eval):
    t = full_eval.training
    assert t["steps"] == 12 and t["preset"] == "fast" and t["variant"] == "full"
    assert t["switches"] == {"dars": True, "semantics": True, "mat_labels": True, "fixed_light": False,
                             "mat_loss": True, "baseline": None, "shading": "pbr"}
    assert t["priors"]["labels"] == "provided" and t["albedo_supervision"] is False
    assert variant_of(make_config("fast", baseline="nerf")) == "nerf"
    assert variant_of(make_config("fast", dars=False)) == "no_dars"
    assert variant_of(make_config("fast", dars=False, mat_loss=False)) == "custom"


def test_choose_patch_recovers_plane_point():
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.3, -0.2, 2.0])
    cams = Cameras(c2w[None], torch.tensor([40.0]), torch.tensor([40.0]), torch.tensor([16.0]), torch.tensor([16.0]),
                   torch.tensor([32]), torch.tensor([32]))
    depth = torch.full((32, 32), 2.0)
    normal = torch.zeros(32, 32, 3)
    normal[..., 2] = -1.0  # facing away: must be flipped toward the camera
    centre, n, size, pix = choose_patch(cams, 0, depth, normal, torch.ones(32, 32))
    assert pix == [15, 15]  # one of the four pixels nearest the centre of an even-sized image (the first)
    np.testing.assert_allclose(centre, [0.3 - 0.5 / 40 * 2, -0.2 + 0.5 / 40 * 2, 0.0], atol=1e-6)
    assert n == [0.0, 0.0, 1.0]
    assert size == pytest.approx(0.125 * 32 * 2.0 / 40.0)
    opacity = torch.zeros(32, 32)
    opacity[2, 30] = 1.0  # only one opaque pixel: it is used
    assert choose_patch(cams, 0, depth, normal, opacity)[3] == [30, 2]
    with pytest.raises(MetricUnavailable, match="renders no surface"):
        choose_patch(cams, 0, depth, normal, torch.zeros(32, 32))


def test_normal_depth_agreement_on_analytic_planes():
    """The ground-truth-free normal check: a plane's own normal scores 0°, a normal turned about the view axis scores
    its turn, an inward normal 180° and back-facing; the silhouette (non-opaque neighbours) is left out."""
    from toolkit.evaluate import normal_depth_agreement
    from toolkit.scene import generate_rays

    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.0, 0.0, 2.0])
    cams = Cameras(c2w[None], torch.tensor([40.0]), torch.tensor([40.0]), torch.tensor([16.0]), torch.tensor([16.0]),
                   torch.tensor([32]), torch.tensor([32]))
    # a plane through the origin with normal m (tilted 30° about x), seen by a camera at z = 2 looking down -z
    a = math.radians(30.0)
    m = torch.tensor([0.0, math.sin(a), math.cos(a)])
    rays = generate_rays(cams, [0])
    t = -(rays.origins @ m) / (rays.directions @ m)
    depth = (t * rays.z_scale).reshape(32, 32)
    opacity = torch.ones(32, 32)
    opacity[:, :4] = 0.0  # a silhouette: columns 0-3 empty, so interior columns up to 4 are dropped
    ang, back = normal_depth_agreement(cams, 0, depth, m.expand(32, 32, 3), opacity)
    assert ang.numel() == 30 * (30 - 4) and float(ang.max()) < 0.05 and not bool(back.any())
    turned = torch.tensor([0.0, 0.0, 1.0])  # 30° off the plane's normal
    ang, _ = normal_depth_agreement(cams, 0, depth, turned.expand(32, 32, 3), opacity)
    assert float(ang.mean()) == pytest.approx(30.0, abs=0.05)
    ang, back = normal_depth_agreement(cams, 0, depth, (-m).expand(32, 32, 3), opacity)
    assert float(ang.min()) > 179.9 and bool(back.all())
    ang, back = normal_depth_agreement(cams, 0, depth, m.expand(32, 32, 3), torch.zeros(32, 32))
    assert ang.numel() == 0 and back.numel() == 0


def test_training_sample_counts_follow_w(run_dir):
    run = load_run(run_dir)
    c = training_sample_counts(run, 0)
    counts, fine = c["samples"], c["fine"]
    assert counts.shape == fine.shape == (32, 32) and bool((fine <= counts).all())
    sc, w = run.cfg.sampler, run.weight_maps[0]
    hit = fine > 0  # rays with occupied coarse samples share a fixed total of n_fine fine samples each
    assert float(fine[hit].sum()) == pytest.approx(sc.n_fine * int(hit.sum()))
    assert int(fine.max()) <= sc.budget_max and int(fine[hit].min()) >= sc.budget_min
    assert bool((fine[hit & (w <= sc.tau)] <= sc.n_fine).all())  # more than the uniform share only where W > tau
    hi = hit & (w > sc.tau)
    if hi.any():
        assert float(fine[hi].mean()) > sc.n_fine
    small = training_sample_counts(run, 0, chunk=100)  # chunks bound the memory, not the budgets
    assert torch.equal(small["samples"], counts) and torch.equal(small["fine"], fine)
    with pytest.raises(DarsError, match="out of range"):
        training_sample_counts(run, 999)
    with pytest.raises(DarsError, match="chunk"):
        training_sample_counts(run, 0, chunk=0)


def test_bad_inputs():
    with pytest.raises(DarsError, match="expected a loaded run"):
        evaluate_run("not a run")
    with pytest.raises(DarsError, match="limit"):
        EvalConfig(limit=-1)
    with pytest.raises(DarsError, match="together"):
        EvalConfig(patch_centre=(0, 0, 0))
    with pytest.raises(DarsError, match="k_views"):
        EvalConfig(k_views=1)


def test_missing_split_is_a_clear_error(run_dir):
    with pytest.raises(DarsError, match="val|split"):
        evaluate_run(load_run(run_dir), "val", log=lambda m: None)


def test_cli_eval_json_only_on_stdout(run_dir, capsys, monkeypatch):
    from toolkit.cli import main

    monkeypatch.delenv("DARS_LPIPS_WEIGHTS", raising=False)
    assert main(["eval", str(run_dir), "--json", "--limit", "2", "--threads", "1"]) == 0
    cap = capsys.readouterr()
    doc = json.loads(cap.out)  # the whole of stdout is one JSON document
    assert set(doc) == set(METRIC_KEYS) | set(JSON_SECTIONS)
    assert doc["lpips"] is None and "lpips" in doc["unavailable"]
    assert json.loads((run_dir / "eval" / "metrics.json").read_text())["psnr"] == doc["psnr"]
    assert (run_dir / "eval" / "report.md").is_file()
    # the human-readable mode prints the headline and the reasons
    assert main(["eval", str(run_dir), "--limit", "2", "--quiet", "--out", str(run_dir / "eval2")]) == 0
    out = capsys.readouterr().out
    assert "PSNR (dB)" in out and "View consistency" in out and "unavailable:" in out and "lpips:" in out


def test_cli_eval_device(run_dir, capsys, monkeypatch):
    """--device picks where the run is loaded and rendered; CUDA on a machine without it, or an unknown device, is a
    clear error before any work."""
    import torch

    import toolkit.train.run as run_module
    from toolkit.cli import main

    seen = []
    real = run_module.load_run
    monkeypatch.setattr(run_module, "load_run", lambda *a, **k: seen.append(k.get("device")) or real(*a, **k))
    assert main(["eval", str(run_dir), "--json", "--limit", "1", "--threads", "1", "--device", "cpu",
                 "--out", str(run_dir / "eval_cpu")]) == 0
    assert seen == ["cpu"] and json.loads(capsys.readouterr().out)["psnr"] is not None
    assert main(["eval", str(run_dir), "--device", "tpu7", "--out", str(run_dir / "eval_x")]) == 2
    assert "--device 'tpu7'" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main(["eval", str(run_dir), "--device", "cuda", "--out", str(run_dir / "eval_c")]) == 2
        assert "CUDA is not available" in capsys.readouterr().err
    assert seen == ["cpu"]  # the refused calls loaded nothing


def test_cli_eval_rejects_non_runs(tmp_path, capsys):
    from toolkit.cli import main

    assert main(["eval", str(tmp_path)]) == 2
    assert "is not a training run" in capsys.readouterr().err
    assert main(["eval", str(tmp_path / "nope")]) == 2
    assert "is not a directory" in capsys.readouterr().err
    assert main(["eval", str(tmp_path), "--limit", "-3"]) == 2
    assert "--limit" in capsys.readouterr().err


def test_chamfer_against_reference_mesh(run_dir, tmp_path):
    import trimesh

    ref = tmp_path / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=2, radius=0.5).export(ref)
    res = evaluate_run(load_run(run_dir), "test", EvalConfig(limit=1, figure_views=0, weight_views=0,
                                                             reference_mesh=str(ref), mesh_resolution=32,
                                                             chamfer_samples=2000), log=lambda m: None)
    ch = res.to_json()["details"]["chamfer"]
    assert ch["reference"] == str(ref)
    if ch["value"] is None:  # a 12-step field may have no opaque surface yet: then the reason says so
        assert "empty mesh" in ch["reason"]
    else:
        assert ch["value"] > 0 and ch["units"].startswith("metres") and ch["faces"] > 0


def test_chamfer_of_an_analytic_sphere_is_small(run_dir, tmp_path, monkeypatch):
    import trimesh

    import toolkit.train.run as T
    from toolkit.evaluate import chamfer_to_reference

    ref = tmp_path / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=4, radius=0.5).export(ref)

    def sphere_density(points):  # an opaque ball of radius 0.5 (density 1000 / m inside)
        return 1000.0 * (points.norm(dim=-1) < 0.5).float()

    monkeypatch.setattr(T, "field_callables", lambda run, chunk=65536: (sphere_density, None))
    ch = chamfer_to_reference(load_run(run_dir), ref, resolution=64, samples=5000)
    voxel = 3.2 / 64
    assert ch["faces"] > 100 and ch["value"] < 0.5 * voxel, ch


def test_geometry_by_class_matches_a_direct_render(full_eval, run_dir):
    """details.geometry: median |rendered − GT depth| and mean opacity on the GT-depth pixels, recomputed here."""
    geo = full_eval.details["geometry"]
    run = load_run(run_dir)
    sc = run.load_split("test")
    dz, op = [], []
    for i in full_eval.info["view_indices"]:
        with torch.no_grad():
            o = run.render(sc.cameras, i)
        gt = sc.load_extra(i, "depth").reshape(-1)
        m = gt > 0
        dz.append((o.depth.reshape(-1)[m] - gt[m]).abs())
        op.append(o.opacity.reshape(-1)[m])
    dz, op = torch.cat(dz), torch.cat(op)
    assert geo["all"]["pixels"] == dz.numel() > 0
    assert geo["all"]["depth_error_median_m"] == pytest.approx(float(dz.median()), rel=1e-4, abs=1e-5)
    assert geo["all"]["opacity_mean"] == pytest.approx(float(op.mean()), rel=1e-4, abs=1e-5)
    if geo["by_class"] is not None:
        assert sum(v["pixels"] for v in geo["by_class"].values()) <= geo["all"]["pixels"]
        assert all(0.0 <= v["opacity_mean"] <= 1.0 + 1e-6 for v in geo["by_class"].values())
    from toolkit.report import write_eval_report

    write_eval_report(full_eval, run_dir / "eval_geo")
    report = (run_dir / "eval_geo" / "report.md").read_text()
    assert "Rendered depth against the ground truth" in report and "Roughness RMSE per ground-truth class" in report


def test_unreadable_training_labels_cost_the_w_figure_not_the_evaluation(scene_gt, tmp_path, monkeypatch):
    """A training view whose label file is missing: W is recomputed without it for the figure, the report says so,
    and every test-view metric is still there (it used to stop the whole `dars eval` after rendering)."""
    from toolkit.scene import SceneError

    out = tmp_path / "uniform"
    train(scene_gt, out, small_config(steps=3, dars=False), progress_bar=False, log=lambda m: None)
    run = load_run(out)
    tr = run.train_scene
    real = type(tr).load_extra

    def no_labels(self, i, name):
        if self is tr and name == "semantic":
            raise SceneError(f"semantic map of frame {i} not found: gone.png")
        return real(self, i, name)

    monkeypatch.setattr(type(tr), "load_extra", no_labels)
    res = evaluate_run(run, "test", EvalConfig(limit=2, weight_views=2, figure_views=0), log=lambda m: None)
    assert res.metrics["psnr"] is not None
    w = res.details["sampling"]["w_source"]
    assert w.startswith("recomputed") and "2 unreadable label/metal map(s)" in w and "gone.png" in w
