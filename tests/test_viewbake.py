"""toolkit.viewbake: a texel takes the field's render from the views that see it (not occluded, not translucent)."""

import numpy as np
import pytest
import torch

from toolkit._checks import ConfigError, ShapeError
from toolkit.cameras import cameras_from_pinholes
from toolkit.mesh import Mesh
from toolkit.pinhole import PinholeCamera, look_at
from toolkit.viewbake import ViewMaps, project_views, view_projected

SIZE = 32


def _down(x, height):
    """A camera ``height`` m above (x, 0, 0) looking straight down at the floor z = 0 (every pixel's axis depth =
    ``height``)."""
    return PinholeCamera(look_at([x, 0.0, height], [x, 0.0, 0.0], up=(0.0, 1.0, 0.0)), 20.0, 20.0, SIZE / 2, SIZE / 2,
                         SIZE, SIZE)


def _maps():
    """Four views of the floor. A (red 1.0) and B (red 0.8) see it; C's pixels hold a surface 0.5 m nearer (an
    occluder, green); D sees the floor only through a translucent layer (opacity 0.2, green)."""
    cams = cameras_from_pinholes([_down(0.0, 2.0), _down(0.3, 2.0), _down(0.0, 3.0), _down(0.1, 3.0)])
    depth = torch.tensor([2.0, 2.0, 2.5, 3.0])[:, None, None].expand(4, SIZE, SIZE).clone()
    opacity = torch.tensor([1.0, 1.0, 1.0, 0.2])[:, None, None].expand(4, SIZE, SIZE).clone()
    colours = torch.tensor([[1.0, 0, 0], [0.8, 0, 0], [0, 1.0, 0], [0, 1.0, 0]])
    albedo = colours[:, None, None, :].expand(4, SIZE, SIZE, 3).clone()
    rough = torch.tensor([0.2, 0.4, 1.0, 1.0])[:, None, None].expand(4, SIZE, SIZE).clone()
    return ViewMaps(cams, depth, opacity, {"albedo": albedo, "roughness": rough})


def _blue(points, normals=None):
    n = len(points)
    return {"albedo": torch.tensor([0.0, 0.0, 1.0]).expand(n, 3), "roughness": torch.full((n,), 0.9),
            "metallic": torch.zeros(n)}


def test_project_views_averages_the_views_that_see_a_point():
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.2, -0.3, 0.0], [9.0, 9.0, 0.0], [0.0, 0.0, 1.0]])
    means, count = project_views(pts, _maps(), tolerance=0.1)
    # floor points: A and B see them; C is occluded (depth 2.5 m against 3), D is translucent (opacity 0.2)
    assert count.tolist() == [2, 2, 0, 0]  # far outside every frustum; 1 m above the floor matches no depth
    assert torch.allclose(means["albedo"][:2], torch.tensor([0.9, 0.0, 0.0]).expand(2, 3))
    assert torch.allclose(means["roughness"][:2], torch.tensor([0.3, 0.3]))
    # D counts once its translucent pixels are allowed, and a looser tolerance lets C's occluder in
    assert project_views(pts[:1], _maps(), tolerance=0.1, min_opacity=0.1)[1].tolist() == [3]
    assert project_views(pts[:1], _maps(), tolerance=0.25)[1].tolist() == [3]
    with pytest.raises(ConfigError, match="tolerance 1.5"):
        project_views(pts, _maps(), tolerance=1.5)


def test_view_projected_replaces_only_what_the_views_saw():
    stats = {}
    fn = view_projected(_blue, _maps(), stats=stats)
    out = fn(torch.tensor([[0.1, 0.1, 0.0], [9.0, 9.0, 0.0]]), None)
    assert torch.allclose(out["albedo"], torch.tensor([[0.9, 0.0, 0.0], [0.0, 0.0, 1.0]]))  # unseen: point query
    assert torch.allclose(out["roughness"], torch.tensor([0.9, 0.9]))  # only the albedo is projected by default
    assert stats == {"points": 2, "seen": 1}
    with pytest.raises(ConfigError, match="metallic"):
        view_projected(_blue, _maps(), keys=("metallic",))


def test_view_maps_check_their_shapes():
    m = _maps()
    with pytest.raises(ShapeError, match="depth"):
        ViewMaps(m.cameras, m.depth[:3], m.opacity, m.values)
    with pytest.raises(ShapeError, match="albedo"):
        ViewMaps(m.cameras, m.depth, m.opacity, {"albedo": m.values["albedo"][:, :8]})
    with pytest.raises(ShapeError, match="cameras"):
        ViewMaps(m.cameras.resized(16, 16), m.depth, m.opacity, m.values)


def test_bake_mesh_from_views_bakes_what_the_views_show():
    """A floor quad baked from the views is the views' red (A and B's mean) where the point query says blue; the
    statistics say how it was baked."""
    from toolkit.asset import AssetConfig, bake_mesh
    from toolkit.io import srgb_to_linear

    v = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], np.float32)
    up = np.tile([[0, 0, 1.0]], (4, 1)).astype(np.float32)
    quad = Mesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int64), normals=up)
    cfg = AssetConfig(texture=64)
    _, tex, stats = bake_mesh(quad, _blue, cfg, views=_maps())
    colour = srgb_to_linear(tex.base_color[tex.mask].astype(np.float64) / 255.0)
    assert np.allclose(colour.mean(0), [0.9, 0.0, 0.0], atol=0.01)
    assert stats["bake_from"] == "views" and stats["views"]["texels_seen"] == 1.0 and stats["views"]["count"] == 4
    _, tex, stats = bake_mesh(quad, _blue, cfg)
    assert stats["bake_from"] == "points" and "views" not in stats
    assert np.allclose(srgb_to_linear(tex.base_color[tex.mask] / 255.0).mean(0), [0.0, 0.0, 1.0], atol=0.01)
