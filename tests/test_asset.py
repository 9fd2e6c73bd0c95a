"""toolkit.asset: AssetConfig checks (named like the options, before any work) and build_asset on callables."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from toolkit._checks import ConfigError, DarsError
from toolkit.asset import AssetConfig, build_asset
from toolkit.train import FieldCallables


@pytest.mark.parametrize("kw, message", [
    ({"texture": 3}, "--texture 3 must be ≥ 16"),
    ({"resolution": 4}, "--resolution 4 is too small"),
    ({"method": "poisson"}, "--method 'poisson'"),
    ({"faces": -1}, "--faces -1 must be ≥ 0"),
    ({"simplify": "slow"}, "--simplify 'slow'"),
    ({"level_quantile": 1.5}, "--level-quantile 1.5"),
    ({"min_component": -0.1}, "--min-component -0.1"),
    ({"min_seen": 1.5}, "--min-seen 1.5"),
    ({"depth_samples": 0}, "--depth-samples 0"),
    ({"depth_rays": 10}, "--depth-rays 10"),
    ({"depth_min_opacity": 0.0}, "--depth-min-opacity 0.0"),
    ({"depth_min_opacity": 0.7}, "--depth-min-opacity 0.7"),
    ({"method": "marching"}, "choose auto, mc or tsdf"),
    ({"supersample": 3}, "--supersample 3"),
    ({"ao_samples": -1}, "--ao-samples -1"),
    ({"level": math.inf}, "--level inf"),
    ({"bake_from": "rays"}, "--bake-from 'rays'"),
    ({"view_rays": 10}, "--view-rays 10"),
    ({"view_tolerance": 0.0}, "--view-tolerance 0.0"),
])
def test_asset_config_names_the_option(kw, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        AssetConfig(**kw)


@pytest.mark.parametrize("argv", [["mesh", "RUN"], ["bake", "RUN"], ["export-asset", "RUN", "--out", "DIR"]])
def test_cli_defaults_are_asset_config_defaults(argv):
    """The mesh / bake / export-asset options repeat AssetConfig's defaults as literals: they must agree, so the
    Python API and the CLI build the same asset."""
    from dataclasses import fields

    from toolkit.cli import build_parser
    from toolkit.cli.asset import asset_config

    args = build_parser().parse_args(argv)
    cli, api = asset_config(args), AssetConfig()
    differ = {f.name: (getattr(cli, f.name), getattr(api, f.name)) for f in fields(AssetConfig)
              if getattr(cli, f.name) != getattr(api, f.name)}
    assert not differ, f"`dars {argv[0]}` defaults (CLI, AssetConfig) differ: {differ}"
    if argv[0] == "export-asset":  # mesh and bake each have their own stage's options; export-asset has all
        assert {f.name for f in fields(AssetConfig)} <= set(vars(args)), "an AssetConfig field has no option"


def _sphere(radius=0.5):
    def density(p):
        return 1e3 * torch.sigmoid((radius - p.norm(dim=-1)) * 400)

    def material(p, normals=None):
        n = p.shape[0]
        return {"albedo": torch.full((n, 3), 0.6), "roughness": torch.full((n,), 0.4), "metallic": torch.zeros(n),
                "normal": torch.nn.functional.normalize(p, dim=-1), "semantic": torch.full((n,), 3, dtype=torch.long)}

    sh = torch.zeros(9, 3)
    sh[0] = 1.0
    return FieldCallables(density, material, torch.tensor([[-1.0] * 3, [1.0] * 3]), sh, None)


def test_build_asset_from_callables():
    lines = []
    asset = build_asset(_sphere(), AssetConfig(resolution=32, faces=600, texture=64, level=100.0), log=lines.append)
    assert lines[0].startswith("[dars] --bake-from views: the field has no renderer")  # callables: point queries
    assert [m.split(" faces")[0] for m in lines[1:2]] == [f"[dars] UV atlas of {asset.mesh.num_faces}"]  # xatlas
    assert len(lines) == 3 and lines[2].startswith("[dars] UV atlas done in")
    assert asset.stats["bake"]["bake_from"] == "points"
    assert 0 < asset.mesh.num_faces <= 600 * 1.02 and asset.uvmesh.num_faces == asset.mesh.num_faces
    assert abs(np.median(np.linalg.norm(asset.mesh.vertices, axis=1)) - 0.5) < 2 / 32
    assert asset.textures.base_color.shape[:2] == (64, 64) and set(np.unique(asset.uvmesh.face_labels)) == {3}
    assert asset.stats["bake"]["texture"] == 64 and asset.stats["method"] == "mc"
    assert asset.gltf_extras()["mesh_stats"]["faces"] == asset.mesh.num_faces
    assert torch.equal(asset.sh, _sphere().sh)
    with pytest.raises(DarsError, match="RUN directory not found"):
        build_asset("/nonexistent/run")


def _ring(n=8, size=(32, 24), radius=2.0):
    """``n`` cameras on a circle of ``radius`` around the origin, looking at it (world up +z)."""
    from toolkit.cameras import cameras_from_pinholes
    from toolkit.pinhole import PinholeCamera, look_at

    w, h = size
    cams = []
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = np.array([radius * math.cos(a), radius * math.sin(a), 0.4])
        cams.append(PinholeCamera(look_at(eye, np.zeros(3)), 30.0, 30.0, w / 2, h / 2, w, h))
    return cameras_from_pinholes(cams)


def test_resized_cameras_see_the_same_frustum():
    from toolkit.cameras import Cameras, generate_rays

    base = _ring(2, size=(40, 20))
    size = torch.tensor([40, 30]), torch.tensor([20, 30])  # two sizes, two aspects
    cams = Cameras(base.c2w, base.fx, base.fy, size[0] / 2.0, size[1] / 2.0, *size)
    small = cams.resized(10, 6)
    assert small.width.tolist() == [10, 10] and small.height.tolist() == [6, 6]
    for k in range(2):  # the image's corner rays (pixel edges, not centres) are the same before and after
        corner = lambda c, u, v: ((u - c.cx[k]) / c.fx[k], (v - c.cy[k]) / c.fy[k])  # noqa: E731
        for (u, v), (su, sv) in [((0, 0), (0, 0)), ((cams.width[k], cams.height[k]), (10, 6))]:
            assert torch.allclose(torch.stack(corner(cams, u, v)), torch.stack(corner(small, su, sv)))
    rays = generate_rays(small, [1])
    assert len(rays) == 60
    with pytest.raises(ValueError, match="0x6"):
        cams.resized(0, 6)


def test_depth_cameras_fit_the_ray_budget():
    from toolkit.asset import depth_cameras

    cams = _ring(6, size=(64, 48))
    assert depth_cameras(cams, 6 * 64 * 48) is cams  # within the budget: as they are
    small = depth_cameras(cams, 6 * 64 * 48 // 4)
    assert small.width.tolist() == [32] * 6 and small.height.tolist() == [24] * 6
    assert len(small) == 6 and torch.allclose(small.fx, cams.fx / 2)


def test_auto_method_fuses_depth_for_an_unbounded_field():
    """``auto`` meshes a contracted field (rooms, captures) by TSDF fusion of its depth maps at the training
    cameras, rendered on the smaller pixel grid ``depth_rays`` allows, and a bounded one by marching cubes."""
    from toolkit.space import SceneSpace

    sphere = _sphere()
    cams = _ring(8, size=(32, 24))
    unbounded = FieldCallables(sphere.density_fn, sphere.material_fn, sphere.aabb, sphere.sh, cams,
                               SceneSpace(sphere.aabb, contraction=True))
    cfg = AssetConfig(resolution=48, faces=0, depth_samples=96, depth_rays=8 * 16 * 12, min_component=0)
    from toolkit.asset import build_mesh

    mesh, stats = build_mesh(unbounded, cfg)
    assert stats["method"] == "tsdf" and stats["method_option"] == "auto"
    dm = stats["depth_maps"]
    assert dm == {"views": 8, "width": 16, "height": 12, "samples": 96, "min_opacity": 0.5,
                  "pixels_with_depth": dm["pixels_with_depth"]}
    assert 0.1 < dm["pixels_with_depth"] < 0.6  # the sphere fills part of each view
    assert mesh.num_faces > 0 and abs(np.median(np.linalg.norm(mesh.vertices, axis=1)) - 0.5) < 0.05
    for field in (unbounded._replace(space=None), unbounded):  # bounded, or an explicit iso-level: marching cubes
        _, stats = build_mesh(field, replace(cfg, level=100.0))
        assert stats["method"] == "mc" and "depth_maps" not in stats
