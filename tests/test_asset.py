"""toolkit.asset: AssetConfig checks (named like the options, before any work) and build_asset on callables."""

import math

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
    ({"supersample": 3}, "--supersample 3"),
    ({"ao_samples": -1}, "--ao-samples -1"),
    ({"level": math.inf}, "--level inf"),
])
def test_asset_config_names_the_option(kw, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        AssetConfig(**kw)


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
    assert [m.split(" faces")[0] for m in lines[:1]] == [f"[dars] UV atlas of {asset.mesh.num_faces}"]  # xatlas is silent
    assert len(lines) == 2 and lines[1].startswith("[dars] UV atlas done in")
    assert 0 < asset.mesh.num_faces <= 600 * 1.02 and asset.uvmesh.num_faces == asset.mesh.num_faces
    assert abs(np.median(np.linalg.norm(asset.mesh.vertices, axis=1)) - 0.5) < 2 / 32
    assert asset.textures.base_color.shape[:2] == (64, 64) and set(np.unique(asset.uvmesh.face_labels)) == {3}
    assert asset.stats["bake"]["texture"] == 64 and asset.stats["method"] == "mc"
    assert asset.gltf_extras()["mesh_stats"]["faces"] == asset.mesh.num_faces
    assert torch.equal(asset.sh, _sphere().sh)
    with pytest.raises(DarsError, match="RUN directory not found"):
        build_asset("/nonexistent/run")
