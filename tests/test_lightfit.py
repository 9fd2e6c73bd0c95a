"""An object's light from its shading (toolkit.lightfit): the fit recovers a known light's directions on analytic
normals, keeps the light where the shading says nothing, and the trainer runs it once, at the switch to stage (b),
recorded in the run and checked on resume."""
import json

import pytest
import torch

from toolkit.lightfit import fit_sh_to_shading
from toolkit.sh import irradiance_sh, rotation_z, sh_basis
from toolkit.train.config import TrainConfig, make_config
from toolkit.train.step import stage_b_starts, wants_light_fit


def _sphere_views(n_views: int = 6, size: int = 48) -> tuple[torch.Tensor, torch.Tensor]:
    """World normals of a sphere seen orthographically from ``n_views`` directions around it: [V, S, S, 3], and the
    disc [V, S, S]."""
    u = (torch.arange(size) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(-u, u, indexing="ij")
    disc = x * x + y * y < 0.95
    z = torch.sqrt((1 - x * x - y * y).clamp_min(0))
    local = torch.stack([x, y, z], -1)  # camera frame: x right, y up, toward the camera
    views = []
    for k in range(n_views):
        rot = rotation_z(360.0 * k / n_views).float() @ torch.tensor([[1.0, 0, 0], [0, 0, 1], [0, 1, 0]])
        views.append(local @ rot.T)  # cameras around the sphere, looking along the horizontal plane
    return torch.stack(views), disc.expand(n_views, -1, -1).clone()


def _light() -> torch.Tensor:
    sh = torch.zeros(9, 3)
    sh[0] = torch.tensor([1.6, 1.5, 1.4])
    sh[1:4] = torch.tensor([[0.4, 0.4, 0.5], [0.9, 0.9, 0.8], [-0.3, -0.3, -0.2]])  # light mostly from +z, then +y
    sh[4:] = torch.tensor([[0.1, 0.1, 0.1], [-0.2, -0.2, -0.1], [0.25, 0.2, 0.2], [0.05, 0.0, 0.0], [-0.1, -0.1, 0.0]])
    return sh


def test_fit_recovers_a_lights_directions_under_a_two_tone_albedo():
    normals, disc = _sphere_views()
    sh = _light()
    albedo = torch.where((normals[..., 0] > 0.3)[..., None], torch.tensor([0.8, 0.3, 0.2]), torch.tensor([0.4, 0.5, 0.6]))
    photo = albedo * irradiance_sh(sh, normals).clamp_min(0) / torch.pi
    grey = sh.clone()
    grey[1:] = 0
    res = fit_sh_to_shading(normals, photo, disc, grey)
    assert res.used and res.tv_after < 0.5 * res.tv_before
    assert torch.equal(res.sh[0], sh[0])  # the level is kept
    err = float((res.sh - sh).norm())
    assert err < 0.25 * float((grey - sh).norm()), (err, res.sh)


def test_fit_keeps_the_light_where_the_shading_does_not_vary():
    normals, disc = _sphere_views()
    sh = _light()
    sh[1:] = 0  # an ambient light: the photo's colour is the albedo's, whatever the normal
    photo = torch.full(normals.shape, 0.5) * irradiance_sh(sh, normals) / torch.pi
    res = fit_sh_to_shading(normals, photo, disc, sh)
    assert not res.used and "less than" in res.reason and torch.equal(res.sh, sh)
    few = torch.zeros_like(disc)
    few[0, :10, :10] = True
    res = fit_sh_to_shading(normals, photo, few, sh)
    assert not res.used and "fewer than" in res.reason


def test_when_the_light_is_fitted():
    """``auto``: an object whose light starts grey; ``on``: any run with a light stage; never with a fixed light or
    radiance shading; once, at the first step of stage (b); a run saved before the option loads as ``off``."""
    obj = make_config("fast", steps=100, scene_type="object")
    room = make_config("fast", steps=100, scene_type="unbounded")
    assert wants_light_fit(obj, "grey ambient of the object pixels")
    assert not wants_light_fit(obj, "light network (x.pt)")
    assert not wants_light_fit(room, "grey ambient")
    assert wants_light_fit(make_config("fast", steps=100, light_fit="on"), "light network (x.pt)")
    assert not wants_light_fit(make_config("fast", steps=100, scene_type="object", light_fit="off"), "grey ambient")
    assert not wants_light_fit(make_config("fast", steps=100, scene_type="object", fixed_light=True), "grey ambient")
    assert [s for s in range(100) if stage_b_starts(obj, s)] == [30]
    assert not any(stage_b_starts(make_config("fast", steps=100, pretrain_fraction=0.0), s) for s in range(100))
    d = obj.to_dict()
    assert d["light_fit"] == "auto"
    d.pop("light_fit")
    assert TrainConfig.from_dict(d).light_fit == "off"
    with pytest.raises(Exception, match="light_fit"):
        make_config("fast", steps=1, light_fit="sometimes")


def test_trainer_fits_the_light_once_and_resume_checks_the_option(tmp_path, capsys):
    from synthetic import make_scene

    from toolkit.cli import main

    scene = make_scene(tmp_path / "scene")
    run = tmp_path / "run"
    assert main(["train", str(scene), "--out", str(run), "--steps", "4", "--batch-rays", "256", "--quiet",
                 "--no-auto-priors", "--light-fit", "on"]) == 0
    assert json.loads((run / "config.json").read_text())["config"]["light_fit"] == "on"
    recs = [json.loads(ln) for ln in (run / "log.jsonl").read_text().splitlines()]
    fits = [r for r in recs if r["kind"] == "light_fit"]
    assert len(fits) == 1 and fits[0]["step"] == 2 and isinstance(fits[0]["used"], bool)
    assert len(fits[0]["l_env"]) == 9
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--steps", "5", "--resume", "--light-fit", "off", "--quiet"]) == 2
    assert "--light-fit off (the run's: on)" in capsys.readouterr().err
    # a room on its own light: auto does not fit
    bare = tmp_path / "bare"
    assert main(["train", str(scene), "--out", str(bare), "--steps", "4", "--batch-rays", "256", "--quiet",
                 "--no-auto-priors", "--scene-type", "room"]) == 0
    assert not any(json.loads(ln)["kind"] == "light_fit" for ln in (bare / "log.jsonl").read_text().splitlines())
