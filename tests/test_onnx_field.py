"""ONNX export of a trained run (export/field_onnx.py): checker, parity on random and real inputs, the rendered
sample test view within 0.05 dB of torch, reduced precision, segmenter/light networks, errors and the CLI."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")

from _onnx_bundle import ROOT, SAMPLE, build_bundle, light_available, small_config  # noqa: E402
from export.field_onnx import (PBR_OUTPUTS, RADIANCE_OUTPUTS, FieldExportConfig, FieldOnnxModule,  # noqa: E402
                               _TorchHashGrid, export_onnx_models)
from export.onnx import OnnxParityError  # noqa: E402
from toolkit._checks import ConfigError, DarsError  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def bundle(tmp_path_factory):
    if not (SAMPLE / "transforms_train.json").is_file():
        pytest.skip("bundled sample not rendered yet (samples/gallery)")
    return build_bundle(tmp_path_factory.getbasetemp() / "onnx_gallery")


@pytest.fixture(scope="module")
def radiance_run(tmp_path_factory):
    """A standard-NeRF (radiance head) run on the tiny synthetic scene, a few steps."""
    from synthetic import make_scene
    from toolkit.train import train

    root = tmp_path_factory.mktemp("onnx_tiny")
    scene = make_scene(root / "scene", n_train=8, n_test=2, size=24)
    run = root / "run"
    train(scene, run, small_config(steps=12, batch_rays=512, occupancy_resolution=16, occupancy_warmup=4,
                                   baseline="nerf"), progress_bar=False, log=lambda m: None)
    return run


@pytest.fixture(scope="module")
def bounded_export(tmp_path_factory):
    """A bounded (``scene_type="object"``: no contraction) PBR run shaded at every sample (an object's default in the
    fast preset, pinned here with ``deferred=False`` since the tests below are about the bundle without
    ``heads.onnx``) on the tiny synthetic scene, a few steps, exported with the render check."""
    from synthetic import make_scene
    from toolkit.train import train

    root = tmp_path_factory.mktemp("onnx_bounded")
    scene = make_scene(root / "scene", n_train=8, n_test=2, size=24)
    run = root / "run"
    train(scene, run, small_config(steps=16, batch_rays=512, occupancy_resolution=16, occupancy_warmup=4,
                                   scene_type="object", deferred=False), progress_bar=False, log=lambda m: None)
    rep = export_onnx_models(run, root / "onnx", cfg=FieldExportConfig(threads=1))
    return {"run": run, "out": root / "onnx", "report": rep,
            "meta": json.loads((root / "onnx" / "metadata.json").read_text())}


@pytest.fixture(scope="module")
def deferred_export(tmp_path_factory):
    """A run shaded once per ray (``deferred``, ``dars train --shade rays``) on the tiny synthetic scene, exported
    with the render check (contracted: the scene is RGB)."""
    from synthetic import make_scene
    from toolkit.train import train

    root = tmp_path_factory.mktemp("onnx_deferred")
    scene = make_scene(root / "scene", n_train=8, n_test=2, size=24)
    run = root / "run"
    train(scene, run, small_config(steps=16, batch_rays=512, occupancy_resolution=16, occupancy_warmup=4,
                                   deferred=True), progress_bar=False, log=lambda m: None)
    rep = export_onnx_models(run, root / "onnx", precision=("fp32", "fp16"), cfg=FieldExportConfig(threads=1))
    return {"run": run, "out": root / "onnx", "report": rep,
            "meta": json.loads((root / "onnx" / "metadata.json").read_text())}


def _assert_render_parity(r: dict, contracted: bool, view: str = "test:0") -> None:
    """The rendered-view bars, the same for contracted and bounded runs (see
    test_sample_test_view_within_005_db_of_torch) but one: the largest depth difference. At a pixel whose fine
    sample flips across a CDF knot (float32 rounding, below) the sample moves by up to a stratum, and contracted
    strata far out are metres long (seen: 1 pixel of 16,384 at 0.33 m, opacity 0.2); bounded strata are
    centimetres. And depth sums weights times distances that reach tens of metres in the contracted shell, so float32
    differences of 1e-5 in a weight move it by ~1e-4 m (seen: 0.23 % of pixels over 1e-4 m, largest 0.4 mm, with
    identical samples). Depth agrees within 1e-4 m at all but 0.1 % of the pixels of a bounded run. In a contracted
    run the share grows with the weight the field keeps far out: since the learned background starts from the
    photos' border colour and the occupancy grid keeps thin density (issue 16), the sample's run showed 6 % of pixels
    over 1e-4 m, the largest 2.2 mm, with identical samples and 0.00 dB PSNR difference — so a contracted run is held
    to 10 % of pixels over 1e-4 m and every pixel within 1 cm."""
    assert r["view"] == view
    assert r["delta_db"] <= 0.05, f"onnx {r['psnr_onnx']:.4f} dB vs torch {r['psnr_torch']:.4f} dB"
    assert r["psnr_onnx_vs_torch"] > 60.0, r
    assert r["max_abs_diff"]["samples"] == 0.0, "the numpy sampler must pick the same samples as torch"
    for k in ("rgb", "albedo", "diffuse", "specular", "opacity", "normal", "roughness", "metallic",
              "semantic_logits", "depth"):
        bar = 1e-1 if (k == "depth" and contracted) else 1e-3
        assert r["frac_pixels_over_1e-4"][k] <= bar, (k, r["frac_pixels_over_1e-4"][k], r["max_abs_diff"][k])
        if k != "depth":
            assert r["max_abs_diff"][k] < 1e-2, (k, r["max_abs_diff"][k])
    assert r["max_abs_diff"]["depth"] < 1e-2


# ------------------------------------------------------------------------------------------------ bundle + checker
def test_bundle_files_checker_opset_and_metadata(bundle):
    out, meta = bundle["out"], bundle["meta"]
    for name in ("field.onnx", "field_fp16.onnx", "field_int8.onnx", "segment.onnx", "occupancy.npz",
                 "background.npz", "metadata.json"):
        assert (out / name).is_file(), f"{name} missing from {sorted(p.name for p in out.iterdir())}"
    for f in sorted(out.glob("*.onnx")):
        model = onnx.load(str(f))
        onnx.checker.check_model(model, full_check=True)
        opset = next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))
        assert opset <= 17, f"{f.name} has opset {opset}"
    field = onnx.load(str(out / "field.onnx"))
    ops = {n.op_type for n in field.graph.node}
    assert "GridSample" not in ops and {"Gather", "Mod"} <= ops, sorted(ops)
    props = {p.key: p.value for p in field.metadata_props}
    for k in ("dars.conventions", "dars.l_env", "dars.aabb", "dars.density_scale", "dars.version", "dars.opset",
              "dars.inputs", "dars.outputs", "dars.sh_order", "dars.sh_constants"):
        assert k in props, f"metadata_props lacks {k}"
    assert "OpenGL" in props["dars.conventions"] and "+z up" in props["dars.conventions"]
    assert np.asarray(json.loads(props["dars.l_env"])).shape == (9, 3)
    assert [i.name for i in field.graph.input] == ["points", "view_dirs", "sh"]
    assert [o.name for o in field.graph.output] == list(PBR_OUTPUTS)
    n_dim = field.graph.input[0].type.tensor_type.shape.dim[0]
    assert n_dim.dim_param == "N", "the batch axis must be dynamic"
    assert meta["opset"] == 17 and meta["shading"] == "pbr" and meta["render_sampler"]["dars_on_device"] is False
    occ = np.load(out / "occupancy.npz")
    r = int(occ["resolution"])
    assert np.unpackbits(occ["mask_bits"], count=r ** 3).shape == (r ** 3,)
    assert str(np.load(out / "background.npz")["mode"]) in ("env", "constant", "learned")
    # the sample is RGB, so its run is unbounded (contracted) although its file has an aabb
    sp = meta["space"]
    assert sp["contraction"] is True and sp["far_radius"] == 64.0 and sp["edge_candidates"] >= 2
    assert np.allclose(sp["aabb"], meta["aabb"]) and np.allclose(sp["grid_aabb"], [[-2.0] * 3, [2.0] * 3])
    assert bool(occ["contraction"]) and float(occ["far_radius"]) == 64.0
    assert meta["occupancy"]["contraction"] is True
    assert json.loads(props["dars.contraction"]) is True and float(props["dars.far_radius"]) == 64.0


def test_bounded_run_bundle_and_render_parity(bounded_export):
    """A bounded field: no contraction anywhere (metadata, occupancy grid over the box, rays clipped to the box) and
    the same render bars as the contracted sample run."""
    from export.infer import load_model
    from toolkit.train import load_run

    meta, out = bounded_export["meta"], bounded_export["out"]
    assert meta["space"]["contraction"] is False and np.allclose(meta["space"]["grid_aabb"], meta["aabb"])
    assert not bool(np.load(out / "occupancy.npz")["contraction"])
    m = load_model(out, threads=1)
    assert not m.space.contraction and not m.occupancy_contraction
    run = load_run(bounded_export["run"], with_weights=False)
    assert not run.field.cfg.contraction and not run.occupancy.contraction
    lo, hi = run.occupancy.aabb
    pts = lo - 0.5 + torch.rand(5000, 3, generator=torch.Generator().manual_seed(2)) * (hi - lo + 1.0)
    assert np.array_equal(m.occupied(pts.numpy()), run.occupancy.occupied(pts).numpy())
    f = bounded_export["report"].field
    for check in ("random", "real"):
        for k, v in f[check].items():
            assert (f[f"{check}_scaled"][k] if k == "density" else v) <= 1e-4, (check, k, v)
    _assert_render_parity(bounded_export["report"].render, contracted=False)


def test_deferred_run_bundle_renders_per_ray(deferred_export):
    """A run shaded once per ray ships heads.onnx; the device renderer composites the field's feature and runs the
    heads per ray, matching torch's deferred render with the same bars as the per-sample runs. A per-sample run's
    bundle has no heads graph."""
    from export.field_onnx import HEADS_FILE
    from export.infer import load_model, render_view
    from toolkit.pinhole import PinholeCamera
    from toolkit.train import load_run

    out, meta, rep = deferred_export["out"], deferred_export["meta"], deferred_export["report"]
    assert meta["deferred_in_run"] is True and meta["heads"]["file"] == HEADS_FILE
    heads = onnx.load(str(out / HEADS_FILE))
    onnx.checker.check_model(heads, full_check=True)
    assert [i.name for i in heads.graph.input] == ["feature", "view_dirs", "sh"]
    assert "colour" in [o.name for o in heads.graph.output] and "density" not in [o.name for o in heads.graph.output]
    assert rep.field["heads"]["max_abs_err"] <= 1e-4 and rep.field["heads"]["n_real"] > 0
    assert "deferred=True" in rep.render["torch_reference"]
    _assert_render_parity(rep.render, contracted=True)
    m = load_model(out, threads=1)
    assert m.deferred
    run = load_run(deferred_export["run"], with_weights=False)
    sc = run.load_split("test")
    per_sample = run.render(sc.cameras, 0, deferred=False).rgb.numpy()
    got = render_view(m, PinholeCamera.from_cameras(sc.cameras, 0))["rgb"]
    ref = run.render(sc.cameras, 0).rgb.numpy()  # the run's own (deferred) render
    assert np.abs(got - ref).max() < 1e-3 < np.abs(per_sample - ref).max()
    # per sample, a deferred render asks the field graph cut to density and feature: the same values, and the same
    # render, as the whole graph
    assert m.geometry_session is not None and len(m.geometry_session.get_outputs()) == 2
    pts = np.random.default_rng(0).uniform(-1.0, 1.0, (3000, 3)).astype(np.float32)
    dirs = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    cut = m.query(pts, dirs, outputs=("density", "feature"))
    whole = m.query(pts, dirs)
    for k in ("density", "feature"):
        assert np.allclose(cut[k], whole[k], rtol=1e-5, atol=1e-6), k
    m.geometry_session = None
    assert np.allclose(render_view(m, PinholeCamera.from_cameras(sc.cameras, 0))["rgb"], got, atol=1e-5)
    assert rep.variants["fp16"]["status"] == "exported" and rep.variants["fp16"]["psnr_vs_fp32"] > 30.0


def test_per_sample_bundle_has_no_heads_graph(bounded_export):
    from export.field_onnx import HEADS_FILE

    assert bounded_export["meta"]["heads"] is None and not (bounded_export["out"] / HEADS_FILE).exists()


# ------------------------------------------------------------------------------------------------ parity
def test_field_parity_random_and_real_inputs(bundle):
    f = bundle["meta"]["parity"]["field"]
    assert f["n_random"] >= 4096 and f["n_real"] > 500
    for check in ("random", "real"):
        assert set(f[check]) == set(PBR_OUTPUTS)
        for k, v in f[check].items():
            bound = f[f"{check}_scaled"][k] if k == "density" else v
            assert bound <= 1e-4, f"{check}/{k}: onnxruntime vs torch {v:.3g}"


def test_field_parity_fresh_batch_against_torch(bundle):
    """Independent of the report: a new batch size (dynamic N) through ORT vs the torch module."""
    from export.infer import make_session
    from toolkit.train import load_run

    run = load_run(bundle["run"], with_weights=False)
    module = FieldOnnxModule(run.field, "pbr").eval()
    g = torch.Generator().manual_seed(5)
    lo, hi = run.train_scene.aabb
    pts = lo + torch.rand(777, 3, generator=g) * (hi - lo)
    # the contracted shell, out past the far radius (σ = 0 there): the graph contracts and rescales σ itself
    r = torch.exp(torch.rand(300, 1, generator=g) * np.log(1.5 * run.field.cfg.far_radius))
    pts[:300] = (lo + hi) / 2 + torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=-1) * r * (hi - lo)
    dirs = torch.nn.functional.normalize(torch.randn(777, 3, generator=g), dim=-1)
    sh = run.l_env.reshape(9, 3) * 1.3  # relit: the sh input is live, not baked in
    with torch.no_grad(), _TorchHashGrid(run.field):
        ref = module(pts, dirs, sh)
    got = make_session(bundle["out"] / "field.onnx", 1).run(None, {"points": pts.numpy(), "view_dirs": dirs.numpy(),
                                                                   "sh": sh.numpy()})
    for name, r, o in zip(PBR_OUTPUTS, ref, got):
        err = np.abs(o - r.numpy()) / np.maximum(1.0, np.abs(r.numpy())) if name == "density" else np.abs(o - r.numpy())
        assert err.max() <= 1e-4, f"{name}: {err.max():.3g}"
    assert run.field.cfg.contraction
    beyond = (run.field.space.inside(pts) == 0).numpy()
    assert beyond.any() and np.all(got[0][beyond] == 0.0), "no density beyond the far radius"
    assert np.allclose(got[PBR_OUTPUTS.index("colour")], got[PBR_OUTPUTS.index("diffuse")]
                       + got[PBR_OUTPUTS.index("specular")], atol=1e-6)


def test_sample_test_view_within_005_db_of_torch(bundle):
    """The rendered view of the (contracted) sample run: within 0.05 dB (the issue's bar), and per pixel within 1e-4
    everywhere but at rays whose inverse-CDF draw lands within float32 rounding of a CDF plateau (a run of empty
    strata between two occupied ones): the density the two renderers feed the CDF differs by ~1e-7, so such a fine
    sample may go to the far side of the gap in one and the near side in the other (seen once: 1 pixel of 16,384,
    opacity off by 1.7e-4). Contracted strata come from an arc-length table whose float32 pow and linspace differ
    from torch's by an ulp here and there, so edges agree to ~1e-6 relative, not bit for bit."""
    assert bundle["meta"]["space"]["contraction"] is True
    r = bundle["meta"]["parity"]["render"]
    _assert_render_parity(r, contracted=True)
    assert "psnr_torch_dars" in r, "a DARS run reports the torch render with DARS on as well"


def test_reduced_precision_variants_measured(bundle):
    v = bundle["meta"]["parity"]["variants"]
    size32 = (bundle["out"] / "field.onnx").stat().st_size
    for p, max_ratio in (("fp16", 0.6), ("int8", 0.35)):
        assert v[p]["status"] == "exported", v[p]
        assert v[p]["bytes"] < max_ratio * size32, (p, v[p]["bytes"], size32)
        assert v[p]["psnr_vs_fp32"] > 40.0, (p, v[p]["psnr_vs_fp32"])
        assert abs(v[p]["delta_db"]) < 0.5, (p, v[p]["delta_db"])
    # fp16 keeps the hash-grid addressing in float32 (points are not rounded to 11 bits) and stores the table in fp16
    m = onnx.load(str(bundle["out"] / "field_fp16.onnx"))
    table = max(m.graph.initializer, key=lambda t: int(np.prod(t.dims)))
    assert table.data_type == onnx.TensorProto.FLOAT16
    users = [n for n in m.graph.node if "points" in n.input]
    assert users and all(n.op_type != "Cast" for n in users), "points must reach the encoding in float32"
    # int8 quantises the MLPs' MatMuls; the hash grid (a gather and three lerps) has no MatMul and stays float
    m8 = onnx.load(str(bundle["out"] / "field_int8.onnx"))
    grid_q = [n.name for n in m8.graph.node if n.op_type in ("MatMul", "MatMulInteger") and "grid" in n.name.split("/")]
    assert not grid_q, grid_q
    assert any(n.op_type == "MatMulInteger" for n in m8.graph.node), "the MLP layers are quantised"


def test_segmenter_and_light_networks(bundle):
    from export.infer import infer_segment
    from toolkit.scene import load_scene
    from toolkit.segment import load_segmenter

    meta = bundle["meta"]
    assert meta["segment"]["status"] == "exported" and meta["segment"]["max_abs_err"] <= 1e-4
    sc = load_scene(SAMPLE, "test")
    img = sc.load_image(1)
    lab = infer_segment(bundle["out"], [(img.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)], threads=1)[0]
    with torch.no_grad():
        ref = load_segmenter(bundle["segmenter"])((img * 255).round()[None] / 255).argmax(1)[0].numpy()
    assert lab.shape == ref.shape and (lab == ref).mean() > 0.999
    if not light_available():
        assert meta["light"]["status"] == "unavailable" and meta["light"]["reason"]
        return
    from export.infer import infer_light
    from toolkit.lightnet import load_lightnet, predict_sh

    assert meta["light"]["status"] == "exported", meta["light"]
    photos = [sc.load_image(i) for i in (0, 2)]
    got = infer_light(bundle["out"], [p.permute(1, 2, 0).numpy() for p in photos], threads=1)
    ref = predict_sh(load_lightnet(bundle["light"]), torch.stack(photos)).numpy()
    assert np.abs(got - ref).max() < 1e-4, np.abs(got - ref).max()


def test_segment_onnx_is_always_in_the_bundle(radiance_run, tmp_path):
    """A run whose priors hold no fine-tuned segmenter ships the shipped one (which labelled its photos); a named
    --segmenter that does not exist is reported with its reason."""
    from toolkit.segment import DEFAULT_SEGMENTER

    rep = export_onnx_models(radiance_run, tmp_path / "o", cfg=FieldExportConfig(threads=1, check_render=False))
    assert rep.segment["status"] == "exported" and rep.segment["source"] == str(DEFAULT_SEGMENTER)
    assert rep.segment["max_abs_err"] <= 1e-4 and (tmp_path / "o" / "segment.onnx").is_file()
    rep = export_onnx_models(radiance_run, tmp_path / "p", cfg=FieldExportConfig(
        threads=1, check_render=False, segmenter=str(tmp_path / "nope.pt")))
    assert rep.segment["status"] == "unavailable" and "nope.pt" in rep.segment["reason"]
    assert not (tmp_path / "p" / "segment.onnx").exists()


# ------------------------------------------------------------------------------------------------ radiance runs
def test_radiance_run_exports_radiance_graph(radiance_run, tmp_path):
    rep = export_onnx_models(radiance_run, tmp_path / "o", cfg=FieldExportConfig(threads=1))
    m = onnx.load(str(tmp_path / "o" / "field.onnx"))
    assert [i.name for i in m.graph.input] == ["points", "view_dirs"]
    assert [o.name for o in m.graph.output] == list(RADIANCE_OUTPUTS)
    assert max(v for k, v in rep.field["real"].items() if k != "density") <= 1e-4
    assert rep.render["delta_db"] <= 0.05, rep.render


# ------------------------------------------------------------------------------------------------ errors
def test_parity_failure_raises_loudly(radiance_run, tmp_path):
    with pytest.raises(OnnxParityError, match="differs from torch"):
        export_onnx_models(radiance_run, tmp_path / "o", cfg=FieldExportConfig(tol=1e-12, threads=1))
    assert (tmp_path / "o" / "field.onnx").is_file(), "the file is kept for inspection"
    assert not (tmp_path / "o" / "metadata.json").exists(), "a failed export must not look complete"


def test_bad_inputs(tmp_path, radiance_run):
    with pytest.raises(DarsError, match="RUN directory not found"):
        export_onnx_models(tmp_path / "nope", tmp_path / "o")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DarsError, match="is not a training run"):
        export_onnx_models(tmp_path / "empty", tmp_path / "o")
    with pytest.raises(ConfigError, match=r"precision \['bf16'\]"):
        export_onnx_models(radiance_run, tmp_path / "o", precision=("fp32", "bf16"))
    with pytest.raises(ConfigError, match="parity view test:9"):
        export_onnx_models(radiance_run, tmp_path / "o", cfg=FieldExportConfig(parity_index=9, threads=1))
    with pytest.raises(ConfigError, match="tol=0"):
        FieldExportConfig(tol=0)


def test_cli_export_onnx_json_and_errors(radiance_run, tmp_path):
    exe = [sys.executable, "-m", "toolkit.cli"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(exe + ["export-onnx", str(radiance_run), "--out", str(tmp_path / "o"), "--json",
                              "--threads", "1", "--precision", "int8"], capture_output=True, text=True, cwd=ROOT,
                       env=env, timeout=600)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)  # only JSON on stdout
    assert d["opset"] == 17 and d["render"]["delta_db"] <= 0.05 and d["variants"]["int8"]["status"] == "exported"
    r = subprocess.run(exe + ["export-onnx", str(tmp_path / "missing"), "--out", str(tmp_path / "o2")],
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    assert r.returncode == 2 and "RUN directory not found" in r.stderr, r.stderr
    r = subprocess.run(exe + ["export-onnx", str(radiance_run), "--out", str(tmp_path / "o3"), "--view", "test"],
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    assert r.returncode == 2 and "expected SPLIT:INDEX" in r.stderr, r.stderr
