import json

import pytest
import torch

from synthetic import make_scene
from toolkit._checks import ConfigError
from toolkit.field import FieldOutputs
from toolkit.pipeline import RenderConfig, RenderInputs, render_image
from toolkit.relight import MaterialEdit, apply_material_edits, parse_material_edit, relight_hook
from toolkit.scene import load_scene
from toolkit.train import load_run, make_config, train


def test_parse_material_edit():
    e = parse_material_edit("frame:metallic=0,roughness=0.8")
    assert (e.class_id, e.metallic, e.roughness, e.albedo) == (1, 0.0, 0.8, None)
    assert parse_material_edit("0:albedo=0.8,0.1,0.2").albedo == (0.8, 0.1, 0.2)
    assert parse_material_edit("wall:albedo=0.5").albedo == (0.5, 0.5, 0.5)
    with pytest.raises(ConfigError, match="unknown class 'statue'"):
        parse_material_edit("statue:roughness=0.1")
    with pytest.raises(ConfigError, match="roughness=1.5 must be in"):
        parse_material_edit("frame:roughness=1.5")
    with pytest.raises(ConfigError, match="unknown key 'shine'"):
        parse_material_edit("frame:shine=1")
    with pytest.raises(ConfigError, match="expected CLASS:KEY=VALUE"):
        parse_material_edit("roughness=0.3")


def test_apply_edits_blends_by_class_probability():
    a, r, m = torch.full((3, 3), 0.5), torch.full((3,), 0.5), torch.zeros(3)
    probs = torch.zeros(3, 7)
    probs[0, 1], probs[1, 1], probs[1, 4], probs[2, 4] = 1.0, 0.5, 0.5, 1.0
    a2, r2, m2 = apply_material_edits(a, r, m, probs, [MaterialEdit(1, albedo=(1.0, 0.0, 0.0), metallic=1.0)])
    assert torch.allclose(a2[0], torch.tensor([1.0, 0, 0])) and float(m2[0]) == 1.0
    assert torch.allclose(a2[1], torch.tensor([0.75, 0.25, 0.25])) and float(m2[1]) == 0.5
    assert torch.allclose(a2[2], a[2]) and float(m2[2]) == 0.0 and torch.equal(r2, r)


def test_hook_swaps_light():
    old = torch.zeros(9, 3)
    old[0] = 2.0
    new = torch.zeros(9, 3)
    new[0] = 4.0
    res = torch.full((2, 9, 3), 0.1)
    out = FieldOutputs(density=torch.ones(2), light=old + res, light_residual=res)
    assert torch.allclose(relight_hook(old, new, residual="scale")(out).light, new + 2 * res)
    out = FieldOutputs(density=torch.ones(2), light=old + res, light_residual=res)
    assert torch.allclose(relight_hook(old, new, residual="drop")(out).light, new.expand(2, 9, 3))


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = make_scene(tmp_path_factory.mktemp("relight_scene"), n_train=16, n_test=2, size=24)
    run = tmp_path_factory.mktemp("relight_run") / "run"
    cfg = make_config("fast", steps=80, batch_rays=512, occupancy_resolution=16, occupancy_warmup=8)
    train(root, run, cfg, progress_bar=False, log=lambda m: None)
    return run


def test_doubling_the_light_doubles_linear_radiance(tiny_run):
    run = load_run(tiny_run)
    sc = load_scene(run.scene_path, "test")
    args = (run.field, sc.cameras, 0, RenderConfig(sampler=run.cfg.render_sampler, shading="pbr", deferred=True),
            RenderInputs(run.occupancy, run.l_env, run.background, sc.aabb))
    base = render_image(*args)
    two = render_image(*args, outputs_hook=relight_hook(run.l_env, 2 * run.l_env, residual="scale"))
    op = base.opacity
    lit = base.rgb - (1 - op)[..., None] * run.background(torch.tensor([[0.0, 0, 1.0]]))[0]
    lit2 = two.rgb - (1 - op)[..., None] * run.background(torch.tensor([[0.0, 0, 1.0]]))[0]
    sel = op > 0.05  # linearity holds at any opacity: the lit part is sum_i w_i c_i
    assert sel.any()
    assert torch.allclose(lit2[sel], 2 * lit[sel], rtol=1e-3, atol=1e-4)


def test_cli_relight(tiny_run, tmp_path, capsys):
    from toolkit.cli import main

    shf = tmp_path / "sh.json"
    shf.write_text(json.dumps({"coeffs": (torch.eye(9, 3) * 3).tolist()}))
    assert main(["relight", str(tiny_run), "--sh", str(shf), "--edit", "painting:albedo=0.9,0.1,0.1",
                 "--out", str(tmp_path / "re"), "--limit", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["views"] == 1 and any(f.endswith("_rgb.png") for f in out["files"])
    rec = json.loads((tmp_path / "re" / "relight.json").read_text())
    assert rec["edits"][0]["class_id"] == 0 and rec["residual"] == "scale"
    assert main(["relight", str(tiny_run), "--out", str(tmp_path / "x")]) == 2
    assert "give a new light" in capsys.readouterr().err
