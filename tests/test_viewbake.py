"""toolkit.viewbake: a texel takes the field's render from the views that see it (not occluded, not translucent)."""

import numpy as np
import pytest
import torch

from toolkit._checks import ConfigError, ShapeError
from toolkit.cameras import cameras_from_pinholes
from toolkit.mesh import Mesh
from toolkit.pinhole import PinholeCamera, look_at
from toolkit.viewbake import ViewMaps, face_texture_blur, project_views, vertex_texture_blur, view_projected

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
    assert 1.0 < stats["texture_blur"]["median"] <= stats["texture_blur"]["p90"] < 20.0, stats["texture_blur"]
    uvm, tex, stats = bake_mesh(quad, _blue, cfg)
    assert stats["bake_from"] == "points" and "views" not in stats and uvm.texture_blur is None
    assert np.allclose(srgb_to_linear(tex.base_color[tex.mask] / 255.0).mean(0), [0.0, 0.0, 1.0], atol=0.01)


def test_face_texture_blur_is_a_view_pixel_over_a_texel():
    """A 1 m floor quad mapped onto the whole 64² atlas (a texel 1/64 m) seen from 2 m by cameras of 20 px focal
    length (a pixel 0.1 m there): 6.4 texels, over views A and B only (C is occluded, D translucent); it scales with
    the texture's side and slant lengthens it by 1 / cos θ; a face no view sees has none; at the vertices it is the
    mean of the faces that have one."""
    v = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], np.float32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    b = face_texture_blur(v, f, uv, _maps(), 64)
    assert b.shape == (2,) and torch.allclose(b, torch.full((2,), 6.4), rtol=0.02), b
    assert torch.allclose(face_texture_blur(v, f, uv, _maps(), 128), 2 * b, rtol=1e-4)
    tilt = np.array([[1, 0, 0], [0, np.cos(0.6), 0], [0, np.sin(0.6), 0]], np.float32)  # about x, 0.6 rad
    maps = _maps()
    tilted = maps.depth.clone()
    ratio = face_texture_blur(v @ tilt.T, f, uv, ViewMaps(maps.cameras, tilted, maps.opacity, maps.values), 64) / b
    assert float(ratio.min()) > 1.0  # seen at a slant: longer; the depth test drops what moved off the maps
    far = v + np.array([0, 0, -5.0], np.float32)  # under the floor every view sees: occluded everywhere
    assert torch.equal(face_texture_blur(far, f, uv, _maps(), 64), torch.zeros(2))
    assert torch.allclose(vertex_texture_blur(f, torch.tensor([2.0, 0.0]), 5), torch.tensor([2.0, 2.0, 2.0, 0.0, 0.0]))
    assert torch.allclose(vertex_texture_blur(f, torch.tensor([2.0, 4.0]), 4), torch.tensor([3.0, 2.0, 3.0, 4.0]))


def test_view_projected_light_gain_defaults_to_no_change():
    """``light_gain`` (no material key) is the views' mean where they see a point and 1 elsewhere."""
    m = _maps()
    gain = torch.tensor([0.5, 1.0, 2.0, 2.0])[:, None, None].expand(4, SIZE, SIZE).clone()
    maps = ViewMaps(m.cameras, m.depth, m.opacity, {**m.values, "light_gain": gain})
    out = view_projected(_blue, maps, keys=("albedo", "light_gain"))(torch.tensor([[0.1, 0.1, 0.0], [9.0, 9, 0]]))
    assert torch.allclose(out["light_gain"], torch.tensor([0.75, 1.0]))  # A and B see the floor; nobody the other


def test_light_gain_map():
    from toolkit.train.run import LIGHT_GAIN_MAX, light_gain_map

    shaded = torch.tensor([[0.2, 0.4, 0.6], [0.2, 0.4, 0.6], [1.0, 1.0, 1.0], [9.0, 9.0, 9.0], [0.3, 0.3, 0.3]])
    glob = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.8, 1.2], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.1, 0.1, 0.1]])
    opacity = torch.tensor([1.0, 0.9, 1.0, 1.0, 0.3])
    gain = light_gain_map(shaded, glob, opacity)
    # brighter x2, darker /2, black under the global light: 1, clamped, too translucent: 1
    assert torch.allclose(gain, torch.tensor([2.0, 0.5, 1.0, LIGHT_GAIN_MAX, 1.0]))


def _floor_quad():
    v = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], np.float32)
    up = np.tile([[0, 0, 1.0]], (4, 1)).astype(np.float32)
    return Mesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int64), normals=up)


def test_bake_mesh_puts_the_light_gain_in_the_occlusion_channel():
    """With views holding ``light_gain``, ORM red is the texel's gain over the scale s (the gain's 0.99 quantile over
    opaque pixels: 2 here, view D is translucent) and the statistics give s; off, red is 1 and s is 1."""
    from toolkit.asset import AssetConfig, bake_mesh, light_scale

    m = _maps()
    gain = torch.tensor([0.5, 1.0, 2.0, 6.0])[:, None, None].expand(4, SIZE, SIZE).clone()
    maps = ViewMaps(m.cameras, m.depth, m.opacity, {**m.values, "light_gain": gain})
    assert light_scale(maps) == pytest.approx(2.0)
    _, tex, stats = bake_mesh(_floor_quad(), _blue, AssetConfig(texture=64), views=maps)
    red = tex.orm[tex.mask][:, 0].astype(np.float64) / 255.0
    assert np.allclose(red, 0.75 / 2.0, atol=1.5 / 255) and stats["light_scale"] == pytest.approx(2.0)
    _, tex, stats = bake_mesh(_floor_quad(), _blue, AssetConfig(texture=64, light_occlusion=False), views=maps)
    assert (tex.orm[tex.mask][:, 0] == 255).all() and stats["light_scale"] == 1.0
    _, tex, stats = bake_mesh(_floor_quad(), _blue, AssetConfig(texture=64), views=_maps())  # no gain in the views
    assert (tex.orm[tex.mask][:, 0] == 255).all() and stats["light_scale"] == 1.0
    dim = ViewMaps(m.cameras, m.depth, m.opacity, {**m.values, "light_gain": gain * 0.1})
    assert light_scale(dim) == 1.0  # never below 1: a field that only darkens keeps its SH


def test_render_view_maps_light_gain_follows_the_residual(tmp_path):
    """A run's renders carry ``light_gain`` only when asked for and when the field has a light residual: 1 where the
    residual is zero, ≥ 1 where it only adds light; the residual head is left in place."""
    from synthetic import make_scene
    from toolkit.train import load_run, make_config, train
    from toolkit.train.run import render_view_maps

    scene = make_scene(tmp_path / "s", n_train=4, n_test=1, size=16)
    train(scene, tmp_path / "r", make_config("fast", steps=30, batch_rays=256), progress_bar=False,
          log=lambda m: None)
    run = load_run(tmp_path / "r", with_weights=False)
    cams = run.train_scene.cameras
    assert "light_gain" not in render_view_maps(run, cams, progress=False).values
    head = run.field.light_head
    last = head[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
    maps = render_view_maps(run, cams, progress=False, light_gain=True)
    assert run.field.light_head is head
    assert maps.values["light_gain"].shape == maps.opacity.shape
    assert torch.allclose(maps.values["light_gain"], torch.ones(()), atol=1e-4)
    with torch.no_grad():
        last.bias[:3] = 3.0  # Δl on L00 only, positive: more light everywhere
    gain = render_view_maps(run, cams, progress=False, light_gain=True).values["light_gain"]
    opaque = maps.opacity >= 0.5
    assert opaque.any() and (gain >= 1 - 1e-4).all() and (gain[opaque] > 1.2).all()


def test_bake_mesh_takes_the_normal_map_from_the_views_when_asked():
    """``normals_from="views"`` (the default): the normal map holds the mean of the rendered normals of the views that
    see a texel (tilted 37° here); ``points``: the point query's, none here (the flat map); a texel no view sees keeps
    the mesh normal."""
    from toolkit.asset import AssetConfig, bake_mesh

    m = _maps()
    tilt = torch.tensor([0.6, 0.0, 0.8]).expand(4, SIZE, SIZE, 3).clone()
    maps = ViewMaps(m.cameras, m.depth, m.opacity, {**m.values, "normal": tilt})
    _, tex, _ = bake_mesh(_floor_quad(), _blue, AssetConfig(texture=64, normals_from="views"), views=maps)
    nt = tex.normal[tex.mask].astype(np.float64) / 255.0 * 2.0 - 1.0
    assert np.allclose(nt[:, 2], 0.8, atol=0.02) and np.allclose(np.hypot(nt[:, 0], nt[:, 1]), 0.6, atol=0.02)
    _, flat, _ = bake_mesh(_floor_quad(), _blue, AssetConfig(texture=64, normals_from="points"), views=maps)
    assert np.allclose(flat.normal[flat.mask].astype(np.float64) / 255.0 * 2.0 - 1.0, [0, 0, 1], atol=0.01)
    far = Mesh(_floor_quad().vertices + np.float32([20, 0, 0]), _floor_quad().faces, normals=_floor_quad().normals)
    _, unseen, _ = bake_mesh(far, _blue, AssetConfig(texture=64), views=maps)  # views: the default
    assert np.allclose(unseen.normal[unseen.mask].astype(np.float64) / 255.0 * 2.0 - 1.0, [0, 0, 1], atol=0.01)


def test_light_tint_map():
    """The colour the luminance gain drops: per channel, shaded over globally shaded, over the luminance gain."""
    from toolkit.metrics import REC709_LUMA
    from toolkit.train.run import light_gain_map, light_tint_map

    glob = torch.tensor([[0.2, 0.2, 0.2], [0.2, 0.2, 0.2], [0.2, 0.0, 0.2], [0.2, 0.2, 0.2], [0.1, 0.1, 0.1]])
    shaded = torch.tensor([[0.4, 0.4, 0.4], [0.3, 0.2, 0.1], [0.3, 0.5, 0.1], [0.2, 0.2, 1.0], [0.3, 0.1, 0.1]])
    opacity = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.3])
    tint = light_tint_map(shaded, glob, opacity)
    assert torch.allclose(tint[0], torch.ones(3))  # a grey change of light: no tint
    per = torch.tensor([1.5, 1.0, 0.5])
    lum = float(per @ torch.tensor(REC709_LUMA))
    assert torch.allclose(tint[1], per / lum, atol=1e-5)  # warmer, of luminance 1
    assert float(tint[1] @ torch.tensor(REC709_LUMA)) == pytest.approx(1.0, abs=1e-5)
    assert tint[2, 1] == 1.0  # a channel black under the global light: 1 there
    assert tint[3, 2] == 2.0  # clamped at the texture's range
    assert torch.allclose(tint[4], torch.ones(3))  # too translucent
    gain = light_gain_map(shaded, glob, opacity)
    assert torch.allclose((gain[:2, None] * tint[:2]) * glob[:2], shaded[:2], atol=1e-5)  # gain x tint = the field


def test_bake_mesh_bakes_the_light_tint_texture():
    """With views holding ``light_tint`` (and ``light_gain``), the bake writes the tint / 2 texture (the views' mean
    where they see a texel); ``light_tint=False`` or no occlusion: no texture."""
    from toolkit.asset import AssetConfig, bake_mesh
    from toolkit.bake import LIGHT_TINT_SCALE

    m = _maps()
    gain = torch.ones(4, SIZE, SIZE)
    tint = torch.tensor([[1.2, 1.0, 0.6], [1.4, 1.0, 0.8], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]])[:, None, None, :]
    tint = tint.expand(4, SIZE, SIZE, 3).clone()
    maps = ViewMaps(m.cameras, m.depth, m.opacity, {**m.values, "light_gain": gain, "light_tint": tint})
    _, tex, _ = bake_mesh(_floor_quad(), _blue, AssetConfig(texture=64), views=maps)
    assert tex.light_tint is not None and tex.light_tint.shape == (64, 64, 3) and tex.light_tint.dtype == np.uint8
    got = tex.light_tint[tex.mask].astype(np.float64) / 255.0 * LIGHT_TINT_SCALE
    assert np.allclose(got.mean(0), [1.3, 1.0, 0.7], atol=0.01)  # A and B see the floor
    for cfg in (AssetConfig(texture=64, light_tint=False), AssetConfig(texture=64, light_occlusion=False)):
        assert bake_mesh(_floor_quad(), _blue, cfg, views=maps)[1].light_tint is None


def _lit_maps(rgb_a, rgb_b=None):
    """:func:`_maps` with the field's colour and a grey albedo: view A shows ``rgb_a`` everywhere; B shows ``rgb_b``
    (None: B, like C and D, sees nothing: opacity 0). Light gain and tint 1 (the field's light adds nothing)."""
    m = _maps()
    opacity = m.opacity.clone()
    opacity[2:] = 0.0
    if rgb_b is None:
        opacity[1] = 0.0
    rgb = torch.zeros(4, SIZE, SIZE, 3)
    rgb[0] = torch.tensor(rgb_a)
    rgb[1] = torch.tensor(rgb_b if rgb_b is not None else (0.0, 0.0, 0.0))
    albedo = torch.full((4, SIZE, SIZE, 3), 0.5)
    return ViewMaps(m.cameras, m.depth, opacity, {**m.values, "albedo": albedo, "rgb": rgb,
                                                   "light_gain": torch.ones(4, SIZE, SIZE),
                                                   "light_tint": torch.ones(4, SIZE, SIZE, 3)})


def _sh():
    from toolkit.sh import SH_C0

    sh = torch.zeros(9, 3)
    sh[0] = torch.tensor([1.2, 1.0, 0.8]) / SH_C0  # a warm constant radiance
    sh[2] = torch.tensor([0.3, 0.3, 0.3])  # brighter from above (+z)
    return sh


def test_fit_light_makes_the_viewer_shading_show_the_field_colour():
    """With one view, m × the viewer's shading towards that camera is the field's colour there, channel by channel;
    with two, m lies between the two one-view fits; points no view sees get 1."""
    from toolkit.shading import shade_pbr
    from toolkit.viewbake import FIT_WEIGHT_EXPONENT, fit_light

    pts = torch.tensor([[0.0, 0.0, 0.0], [0.2, -0.3, 0.0], [9.0, 9.0, 0.0]])
    n = len(pts)
    material = {"albedo": torch.tensor([0.5, 0.4, 0.3]).expand(n, 3), "roughness": torch.full((n,), 0.6),
                "metallic": torch.zeros(n), "normal": torch.tensor([0.0, 0.0, 1.0]).expand(n, 3)}
    maps = _lit_maps((0.3, 0.2, 0.1))
    m, count = fit_light(pts, material, maps, _sh())
    assert count.tolist() == [1, 1, 0]
    v = torch.nn.functional.normalize(maps.cameras.origins[0] - pts[:2], dim=-1)
    shaded = shade_pbr(material["albedo"][:2], material["roughness"][:2], material["metallic"][:2],
                       material["normal"][:2], v, _sh()).colour
    assert torch.allclose(m[:2] * shaded, torch.tensor([0.3, 0.2, 0.1]).expand(2, 3), atol=1e-5)
    assert torch.equal(m[2], torch.ones(3))
    m_b = fit_light(pts, material, _lit_maps((0.6, 0.4, 0.2), (0.6, 0.4, 0.2)), _sh())[0]  # as if B alone
    both = fit_light(pts, material, _lit_maps((0.3, 0.2, 0.1), (0.6, 0.4, 0.2)), _sh())[0]
    assert ((both[:2] > m[:2]) & (both[:2] < m_b[:2])).all()
    # weighted by the sRGB slope at each view's colour: the darker view counts more than in a plain least squares
    two = _lit_maps((0.3, 0.2, 0.1), (0.6, 0.4, 0.2))
    p_v = [shade_pbr(material["albedo"][:2], material["roughness"][:2], material["metallic"][:2],
                     material["normal"][:2], torch.nn.functional.normalize(two.cameras.origins[i] - pts[:2], dim=-1),
                     _sh()).colour
           for i in (0, 1)]
    f_v = [torch.tensor([0.3, 0.2, 0.1]), torch.tensor([0.6, 0.4, 0.2])]
    plain = sum(p * f for p, f in zip(p_v, f_v)) / sum(p * p for p in p_v)
    weighted = (sum(f ** FIT_WEIGHT_EXPONENT * p * f for p, f in zip(p_v, f_v))
                / sum(f ** FIT_WEIGHT_EXPONENT * p * p for p, f in zip(p_v, f_v)))
    assert torch.allclose(both[:2], weighted, atol=1e-5) and (both[:2] < plain - 1e-3).all()
    # a field normal facing away from the mesh is folded onto its tangent plane, as the normal map stores it
    down = dict(material, normal=torch.tensor([0.6, 0.0, -0.8]).expand(n, 3))
    folded = dict(material, normal=torch.tensor([1.0, 0.0, 0.0]).expand(n, 3))
    up = torch.tensor([0.0, 0.0, 1.0]).expand(n, 3)
    assert torch.allclose(fit_light(pts, down, maps, _sh(), mesh_normals=up)[0],
                          fit_light(pts, folded, maps, _sh())[0], atol=1e-5)
    with pytest.raises(ConfigError, match="colour"):
        fit_light(pts, material, _maps(), _sh())


def test_bake_mesh_fits_the_occlusion_and_tint_to_the_field_colour():
    """Given the run's SH and views holding the field's colour, the baked occlusion × tint make the viewer's shading
    of the baked floor show that colour (here darker and warmer than the SH shades it, while the field's own gain and
    tint say 1); without the SH, or with ``light_fit=False``, the field's gain and tint are baked."""
    from toolkit.asset import AssetConfig, bake_mesh
    from toolkit.bake import LIGHT_TINT_SCALE
    from toolkit.io import srgb_to_linear
    from toolkit.shading import shade_pbr

    target = torch.tensor([0.12, 0.06, 0.02])
    maps = _lit_maps(tuple(target.tolist()))
    _, tex, stats = bake_mesh(_floor_quad(), _blue, AssetConfig(texture=64), views=maps, sh=_sh())
    assert stats["light_fit"] is True and stats["light_scale"] == 1.0
    texels = tex.mask
    albedo = torch.as_tensor(srgb_to_linear(tex.base_color[texels] / 255.0), dtype=torch.float32)
    orm = torch.as_tensor(tex.orm[texels] / 255.0, dtype=torch.float32)
    tint = torch.as_tensor(tex.light_tint[texels] / 255.0 * LIGHT_TINT_SCALE, dtype=torch.float32)
    k = len(albedo)
    v = torch.nn.functional.normalize(maps.cameras.origins[0] - torch.zeros(3), dim=-1).expand(k, 3)  # ~ 14° off
    shaded = shade_pbr(albedo, orm[:, 1], orm[:, 2], torch.tensor([0.0, 0.0, 1.0]).expand(k, 3), v, _sh()).colour
    shown = shaded * orm[:, :1] * tint
    assert torch.allclose(shown.mean(0), target, rtol=0.06)
    assert orm[:, 0].max() < 0.5 and (tint[:, 0] > tint[:, 2]).all()
    for kw, cfg in (({}, AssetConfig(texture=64)), ({"sh": _sh()}, AssetConfig(texture=64, light_fit=False))):
        _, tex, stats = bake_mesh(_floor_quad(), _blue, cfg, views=maps, **kw)
        assert stats["light_fit"] is False and (tex.orm[tex.mask][:, 0] == 255).all()
        assert np.allclose(tex.light_tint[tex.mask] / 255.0 * LIGHT_TINT_SCALE, 1.0, atol=1 / 255)


def test_the_light_fit_projects_the_texels_once():
    """bake_mesh's light fit reuses the view projection of the albedo (``looks``): the bake projects points into the
    views as often with the fit as without it, and the shared projection gives what a fresh one does."""
    import toolkit.viewbake as vb
    from toolkit.asset import AssetConfig, bake_mesh
    from toolkit.viewbake import fit_light, sightings

    maps = _lit_maps((0.12, 0.06, 0.02))
    calls = []
    real = vb._sightings

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    counts = {}
    for fit in (True, False):
        calls.clear()
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(vb, "_sightings", counting)
            _, _, stats = bake_mesh(_floor_quad(), _blue, AssetConfig(texture=64, light_fit=fit), views=maps, sh=_sh())
        assert stats["light_fit"] is fit
        counts[fit] = len(calls)
    assert counts[True] == counts[False] > 0
    pts = torch.tensor([[0.1, 0.1, 0.0], [-0.2, 0.05, 0.0], [9.0, 9.0, 0.0]])
    material = {"albedo": torch.full((3, 3), 0.5), "roughness": torch.full((3,), 0.5), "metallic": torch.zeros(3),
                "normal": torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)}
    looks = sightings(pts, maps)
    for a, b in zip(fit_light(pts, material, maps, _sh(), looks=looks), fit_light(pts, material, maps, _sh())):
        assert torch.equal(a, b)
    for a, b in zip(project_views(pts, maps, looks=looks)[0].values(), project_views(pts, maps)[0].values()):
        assert torch.equal(a, b)


def test_bake_mesh_multiplies_the_fitted_light_by_the_correction():
    """``light_correction`` (the viewer fit's per-vertex factor) scales the fitted occlusion x tint, channel by
    channel, and leaves the albedo alone."""
    from toolkit.asset import AssetConfig, bake_mesh
    from toolkit.bake import LIGHT_TINT_SCALE

    maps = _lit_maps((0.12, 0.06, 0.02))
    light = {}
    for name, corr in (("plain", None), ("corrected", lambda p: torch.tensor([0.5, 1.0, 2.0]).expand(len(p), 3))):
        _, tex, _ = bake_mesh(_floor_quad(), _blue, AssetConfig(texture=64), views=maps, sh=_sh(),
                              light_correction=corr)
        occ = tex.orm[tex.mask][:, :1] / 255.0
        light[name] = (occ * tex.light_tint[tex.mask] / 255.0 * LIGHT_TINT_SCALE).mean(0), tex.base_color[tex.mask]
    ratio = light["corrected"][0] / light["plain"][0]
    assert np.allclose(ratio, [0.5, 1.0, 2.0], rtol=0.05), ratio
    assert np.array_equal(light["corrected"][1], light["plain"][1])
