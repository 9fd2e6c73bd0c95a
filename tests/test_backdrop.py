"""toolkit.backdrop: the field's learned background travels in the GLB, weighted by how much of it the training renders
saw, and the moderngl preview draws it behind the mesh."""

import json
import math

import numpy as np
import pytest
import torch

from _viewer_assets import CUBE_SH, textured_cube
from export.gltf import load_glb
from toolkit._checks import ConfigError, SceneError, ShapeError
from toolkit.asset import AssetConfig, build_asset
from toolkit.backdrop import Backdrop, background_visibility, backdrop_from_views
from toolkit.cameras import cameras_from_pinholes
from toolkit.io import linear_to_srgb
from toolkit.pinhole import PinholeCamera, look_at
from toolkit.pipeline import Background
from toolkit.scene import Cameras, generate_rays
from toolkit.sh import eval_sh, latlong_directions
from toolkit.viewbake import ViewMaps

SIZE = 16
RNG = np.random.default_rng(5)


def _views(opacities, eyes_targets, f=40.0):
    """ViewMaps of cameras at ``(eye, target)`` pairs, each with one constant opacity."""
    cams = cameras_from_pinholes([PinholeCamera(look_at(e, t, up=(0.0, 1.0, 0.0) if abs(t[2] - e[2]) > 0.5
                                                        else (0.0, 0.0, 1.0)), f, f, SIZE / 2, SIZE / 2, SIZE, SIZE)
                                  for e, t in eyes_targets])
    v = len(eyes_targets)
    opacity = torch.tensor(opacities, dtype=torch.float32)[:, None, None].expand(v, SIZE, SIZE).clone()
    return ViewMaps(cams, torch.ones(v, SIZE, SIZE), opacity, {"albedo": torch.zeros(v, SIZE, SIZE, 3)})


UP = ([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])          # looks at the zenith (rows 0-1 of a 16-row map)
ALONG_Y = ([0.0, 0.0, 0.0], [0.0, 1.0, 0.0])     # looks at the horizon at phi = 0 (rows 7-8, columns 31 and 0)


def test_visibility_is_the_mean_transmittance_per_direction():
    vis = background_visibility(_views([0.0, 0.25], [UP, ALONG_Y]), 16, 32)
    assert vis.shape == (16, 32) and vis.dtype == np.float32
    assert vis[0].min() == 1.0  # every texel of the zenith row: seen through nothing
    np.testing.assert_allclose(vis[7:9][:, [31, 0]], 0.75, atol=1e-6)  # through opacity 0.25
    assert vis[12:].max() == 0.0  # below the horizon no ray went: 0, the viewer draws the SH there
    assert vis[4].max() == 0.0 and vis[7:9, 8:24].max() == 0.0
    closed = background_visibility(_views([1.0, 1.0], [UP, ALONG_Y]), 16, 32)
    assert closed.max() == 0.0  # a closed room: the background was never seen


def test_backdrop_from_views_and_its_sampling():
    bg = Background("env")
    with torch.no_grad():
        bg.raw.copy_(torch.randn_like(bg.raw))
    views = _views([0.0, 0.25], [UP, ALONG_Y])
    bd = backdrop_from_views(bg.radiance_map(), views)
    np.testing.assert_allclose(bd.radiance, bg.env_map().detach().numpy(), rtol=1e-6)
    d = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    rad, vis = bd.sample(d)
    torch.testing.assert_close(rad, bg(d).detach(), rtol=1e-5, atol=1e-6)  # filtered as the field renders it
    assert vis.shape == (500,) and float(vis.min()) >= 0.0 and float(vis.max()) <= 1.0
    # a one-colour background (an object on white): the visibility keeps its directions
    white = backdrop_from_views(Background("constant").radiance_map(), views)
    assert white.shape == (16, 32) and np.allclose(white.radiance, 1.0)
    assert white.visibility[0].min() == 1.0 and white.visibility[12:].max() == 0.0


def test_backdrop_json_round_trip_and_errors():
    bd = Backdrop(RNG.uniform(0, 3, (4, 8, 3)), RNG.uniform(0, 1, (4, 8)))
    back = Backdrop.from_json(json.loads(json.dumps(bd.to_json())))
    np.testing.assert_allclose(back.radiance, bd.radiance, atol=1e-6)
    np.testing.assert_allclose(back.visibility, bd.visibility, atol=1e-4)
    d = bd.to_json()
    with pytest.raises(SceneError, match="where.glb: 31 radiance"):
        Backdrop.from_json({**d, "radiance": d["radiance"][:-65]}, "where.glb")
    with pytest.raises(SceneError, match="not a backdrop"):
        Backdrop.from_json({"height": 4}, "where.glb")
    with pytest.raises(ShapeError, match="expected \\(4, 8\\)"):
        Backdrop(np.zeros((4, 8, 3)), np.zeros((8, 4)))
    with pytest.raises(SceneError, match="non-finite"):
        Backdrop(np.full((1, 1, 3), np.nan), np.zeros((1, 1)))
    clipped = Backdrop(np.full((1, 1, 3), -1.0), np.full((1, 1), 2.0))
    assert clipped.radiance.min() == 0.0 and clipped.visibility.max() == 1.0


def _sphere_field(calls):
    from test_asset import _sphere

    def views(cams):  # nothing opaque anywhere: every texel of the bake falls back to points, the sky is all seen
        calls.append(len(cams))
        v, h, w = len(cams), int(cams.height[0]), int(cams.width[0])
        return ViewMaps(cams, torch.ones(v, h, w), torch.zeros(v, h, w), {"albedo": torch.zeros(v, h, w, 3)})

    ring = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    cams = cameras_from_pinholes([PinholeCamera(look_at([2 * np.cos(a), 2 * np.sin(a), 0.3], [0, 0, 0]), 20.0, 20.0,
                                                8.0, 6.0, 16, 12) for a in ring])
    return _sphere()._replace(cameras=cams, views=views, background=torch.rand(16, 32, 3))


def test_build_asset_stores_the_backdrop_in_the_glb(tmp_path):
    from toolkit.cli.asset import export_glb

    calls = []
    field = _sphere_field(calls)
    cfg = AssetConfig(method="mc", resolution=32, faces=600, texture=64, level=100.0)
    asset = build_asset(field, cfg)
    assert calls == [6] and asset.backdrop is not None  # one render of the views, for the bake and the backdrop
    np.testing.assert_allclose(asset.backdrop.radiance, field.background.numpy(), rtol=1e-6)
    st = asset.stats["backdrop"]
    assert st["height"] == 16 and st["width"] == 32 and 0 < st["texels_seen"] < 1 and st["mean_visibility"] > 0
    glb = export_glb(asset, tmp_path / "scene.glb", sh=asset.sh)
    loaded = load_glb(glb)
    np.testing.assert_allclose(loaded.backdrop.radiance, asset.backdrop.radiance, atol=1e-6)
    np.testing.assert_allclose(loaded.backdrop.visibility, asset.backdrop.visibility, atol=1e-4)
    # --no-backdrop with the point bake renders no views at all; --no-backdrop alone keeps the views bake
    calls.clear()
    none = build_asset(field, AssetConfig(**{**cfg.__dict__, "backdrop": False, "bake_from": "points"}))
    assert calls == [] and none.backdrop is None and "backdrop" not in none.stats
    assert "backdrop" not in none.gltf_extras()
    points = build_asset(field, AssetConfig(**{**cfg.__dict__, "bake_from": "points"}))
    assert calls == [6] and points.backdrop is not None and points.stats["bake"]["bake_from"] == "points"
    assert load_glb(textured_cube(tmp_path / "plain.glb")).backdrop is None


def test_preview_draws_the_backdrop_behind_the_mesh(gl, tmp_path):
    from viewers.preview import OffscreenPreview, PreviewConfig

    bd = Backdrop(RNG.uniform(0, 1.2, (8, 16, 3)), RNG.uniform(0, 1, (8, 16)))
    glb = textured_cube(tmp_path / "cube.glb", extras={"backdrop": bd.to_json()})
    loaded = load_glb(glb).backdrop
    cam = PinholeCamera(look_at([1.4, -2.2, 1.3], [0, 0, 0]), 90.0, 90.0, 80.0, 60.0, 160, 120)
    c = Cameras(torch.tensor(cam.c2w, dtype=torch.float32)[None], torch.tensor([cam.fx]), torch.tensor([cam.fy]),
                torch.tensor([cam.cx]), torch.tensor([cam.cy]), torch.tensor([cam.width]), torch.tensor([cam.height]))
    d = generate_rays(c, [0]).directions.double()
    rad, vis = loaded.sample(d)
    sky = eval_sh(torch.as_tensor(CUBE_SH), d).clamp_min(0.0)
    expected = linear_to_srgb((vis[:, None] * rad + (1 - vis[:, None]) * sky).clamp(0, 1)).reshape(120, 160, 3)
    expected = np.round(expected.numpy() * 255)
    with OffscreenPreview(glb, ctx=gl) as view:
        auto = view.render(cam)
        sh_only = view.render(cam, PreviewConfig(background="sh"))
        explicit = view.render(cam, PreviewConfig(background="backdrop"))
        miss = ~auto.mask
        assert 0.3 < miss.mean() < 0.95
        err = np.abs(auto.image.astype(float) - expected)[miss]
        assert err.max() <= 3 and err.mean() < 0.5, f"backdrop off by {err.max()}/255 (mean {err.mean():.2f})"
        assert np.array_equal(explicit.image, auto.image)
        assert np.array_equal(auto.image[auto.mask], sh_only.image[auto.mask])  # the mesh is drawn the same
        assert np.abs(auto.image.astype(int) - sh_only.image.astype(int))[miss].max() > 20  # the sky is not
        view.renderer.set_sh(CUBE_SH * 1.5)  # relit: the captured sky does not belong to the new light
        relit, relit_sh = view.render(cam), view.render(cam, PreviewConfig(background="sh"))
        assert np.array_equal(relit.image, relit_sh.image)
    with OffscreenPreview(textured_cube(tmp_path / "plain.glb"), ctx=gl) as view:
        with pytest.raises(ConfigError, match="carries no backdrop"):
            view.render(cam, PreviewConfig(background="backdrop"))
        assert np.array_equal(view.render(cam).image, view.render(cam, PreviewConfig(background="sh")).image)
    with pytest.raises(ConfigError, match="background='sky'"):
        PreviewConfig(background="sky")


def _quad(z: float, flip: bool = False, r: float = 0.2):
    """Two triangles covering x, y in [-r, r] at height z, front side facing down (-z) unless ``flip``."""
    v = np.array([[-r, -r, z], [r, -r, z], [r, r, z], [-r, r, z]], np.float32)
    f = np.array([[0, 2, 1], [0, 3, 2]], np.int64)  # clockwise seen from above: the front faces -z
    return v, (f[:, ::-1] if flip else f)


def test_mesh_coverage_is_what_a_one_sided_viewer_draws():
    from toolkit.backdrop import mesh_coverage

    cams = _views([0.0], [UP]).cameras  # at the origin, looking up (+z); the quad fills the middle of the view
    v, f = _quad(2.0)
    cov = mesh_coverage(v, f, cams)
    assert cov.shape == (1, SIZE, SIZE) and cov.dtype == torch.bool
    assert bool(cov[0, SIZE // 2, SIZE // 2]) and bool(cov[0, 0, 0]) is False  # ±0.2 m at 2 m: ±4 px of 16
    assert 0.2 < float(cov.float().mean()) < 0.95
    vb, fb = _quad(2.0, flip=True)
    assert not bool(mesh_coverage(vb, fb, cams).any())  # seen from behind: culled, nothing drawn
    # a back face in front of a front face: the ray goes on through it and the far quad is drawn
    v2, f2 = _quad(3.0)
    both_v, both_f = np.concatenate([vb, v2]), np.concatenate([fb, f2 + 4])
    torch.testing.assert_close(mesh_coverage(both_v, both_f, cams), mesh_coverage(v2, f2, cams))
    assert not bool(mesh_coverage(np.zeros((0, 3)), np.zeros((0, 3), np.int64), cams).any())


def test_front_hits_name_the_face_a_one_sided_viewer_draws():
    """front_hits: through a back face to the front face behind it, with that face's index and barycentrics (the
    point they give is where the ray meets the far quad); -1 where no front face is met."""
    from toolkit.backdrop import front_hits
    from toolkit.bake import ray_scene

    vb, fb = _quad(2.0, flip=True)          # seen from below: a back face, first on the ray
    v2, f2 = _quad(3.0)                      # behind it, facing the camera
    v, f = np.concatenate([vb, v2]), np.concatenate([fb, f2 + 4])
    o = np.zeros((3, 3), np.float32)
    d = np.array([[0.03, 0.05, 1.0], [-0.04, 0.02, 2.0], [1.0, 0.0, 0.1]], np.float32)  # two into the quads, one off
    prim, bary = front_hits(ray_scene(v, f), o, d, extent=1.0)
    assert prim.dtype == np.int64 and list(prim >= 2) == [True, True, False] and prim[2] == -1
    tri = v[f[prim[:2]]]
    point = (1 - bary[:2, :1] - bary[:2, 1:]) * tri[:, 0] + bary[:2, :1] * tri[:, 1] + bary[:2, 1:] * tri[:, 2]
    expect = d[:2] / d[:2, 2:] * 3.0        # the ray at z = 3
    np.testing.assert_allclose(point, expect, atol=1e-5)
    prim1, _ = front_hits(ray_scene(v, f), o, d, extent=1.0, passes=1)
    assert (prim1 == -1).all()              # one pass stops at the back face


def test_backdrop_takes_the_field_colour_where_the_mesh_is_not():
    bg = Background("env")
    with torch.no_grad():
        bg.raw.copy_(torch.randn_like(bg.raw))
    views = _views([0.0, 1.0], [UP, ALONG_Y])
    colour = torch.tensor([0.2, 0.4, 0.6])
    views.values["rgb"] = colour.expand(2, SIZE, SIZE, 3).clone()
    covered = torch.zeros(2, SIZE, SIZE, dtype=torch.bool)
    covered[0] = True                                       # the zenith view is all mesh: nothing of it in the map
    bd = backdrop_from_views(bg.radiance_map(), views, covered)
    assert bd.shape == (32, 64)
    np.testing.assert_allclose(bd.radiance[15:17][:, [63, 0]], np.broadcast_to(colour.numpy(), (2, 2, 3)), atol=1e-6)
    assert bd.visibility[15:17][:, [63, 0]].min() == 1.0    # the horizon at phi = 0: the colour, at visibility 1
    # where no uncovered pixel looked and no training ray saw through (-y here): the colour of the nearest direction
    # that was seen, at visibility 1, not the light a viewer draws at visibility 0; the zenith, seen through nothing
    # (visibility 1 in the background map), keeps the learned background
    base = backdrop_from_views(bg.radiance_map(), views)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    assert float(base.sample(d[1:])[1][0]) == 0.0
    rad, vis = bd.sample(d[1:])
    torch.testing.assert_close(rad[0], colour, atol=1e-5, rtol=0)
    assert float(vis[0]) == 1.0
    assert bd.visibility[0].min() == 1.0 and np.allclose(bd.radiance[0], base.sample(
        __import__("toolkit.sh", fromlist=["latlong_directions"]).latlong_directions(32, 64)[0])[0].numpy(), atol=1e-5)
    with pytest.raises(ShapeError, match="covered has shape"):
        backdrop_from_views(bg.radiance_map(), views, covered[:1])
    # views without the field's colour (an older renderer): the background map alone
    del views.values["rgb"]
    assert backdrop_from_views(bg.radiance_map(), views, covered).shape == (16, 32)


def test_build_asset_backdrop_holds_the_field_colour_around_the_mesh():
    # views that carry the field's colour: the backdrop takes it where the sphere's mesh leaves a pixel uncovered
    from toolkit.backdrop import _texel_of

    calls = []
    field = _sphere_field(calls)
    plain = field.views
    colour = torch.tensor([0.2, 0.4, 0.6])

    def views(cams):
        m = plain(cams)
        m.values["rgb"] = colour.expand(*m.opacity.shape, 3).clone()
        return m

    asset = build_asset(field._replace(views=views), AssetConfig(method="mc", resolution=32, faces=600, texture=64,
                                                                 level=100.0))
    bd = asset.backdrop
    assert bd.shape == (32, 64) and asset.stats["backdrop"]["height"] == 32
    rad = bd.radiance.reshape(-1, 3)
    is_colour = np.abs(rad - colour.numpy()).max(1) < 1e-6
    ray = generate_rays(field.cameras, [0])
    d = torch.nn.functional.normalize(ray.directions, dim=-1)
    corner, centre = _texel_of(d[:1], 32, 64), _texel_of(d[6 * 16 + 8:6 * 16 + 9], 32, 64)
    assert is_colour[int(corner)] and bd.visibility.reshape(-1)[int(corner)] == 1.0  # past the sphere: the colour
    # at the sphere no uncovered pixel looked: the learned background's visible share, the rest the colour seen
    # nearest to it (not the light), at visibility 1
    base = backdrop_from_views(field.background, views(field.cameras))  # the background map and its visibility
    base_rad, base_vis = base.sample(latlong_directions(32, 64).reshape(-1, 3)[int(centre)][None])
    want = float(base_vis[0]) * base_rad[0].numpy() + (1.0 - float(base_vis[0])) * colour.numpy()
    np.testing.assert_allclose(rad[int(centre)], want, atol=1e-4)
    assert not is_colour[int(centre)] or float(base_vis[0]) < 1e-6
    assert bd.visibility.reshape(-1)[int(centre)] == 1.0
    assert is_colour.mean() > 0.02 and (bd.visibility == 1.0).all()  # no texel is left to the light


def test_build_asset_carries_the_light_gain_as_occlusion_and_scales_the_sh(tmp_path):
    """A views callable that takes ``light_gain`` is asked for it; every opaque pixel brightened x2 gives the scale
    s = 2: the GLB's SH is twice the run's (and says so in its extras), and a texel no view sees keeps the run's
    light (occlusion 1/s). ``light_occlusion=False`` leaves occlusion 1 and the run's SH."""
    from toolkit.cli.asset import export_glb

    calls = []
    field = _sphere_field([])

    def views(cams, light_gain=False):  # opaque everywhere but 50 m away: no texel is seen, the scale is set
        calls.append(light_gain)
        v, h, w = len(cams), int(cams.height[0]), int(cams.width[0])
        vals = {"albedo": torch.zeros(v, h, w, 3)}
        if light_gain:
            vals["light_gain"] = torch.full((v, h, w), 2.0)
        return ViewMaps(cams, torch.full((v, h, w), 50.0), torch.ones(v, h, w), vals)

    cfg = AssetConfig(method="mc", resolution=32, faces=600, texture=64, level=100.0, backdrop=False)
    asset = build_asset(field._replace(views=views), cfg)
    assert calls == [True] and asset.stats["bake"]["light_scale"] == 2.0
    np.testing.assert_allclose(np.asarray(asset.sh), 2.0 * field.sh.numpy())
    red = asset.textures.orm[asset.textures.mask][:, 0]
    assert np.abs(red.astype(int) - 128).max() <= 1
    assert asset.gltf_extras()["light_scale"] == 2.0
    loaded = load_glb(export_glb(asset, tmp_path / "scene.glb", sh=asset.sh))
    np.testing.assert_allclose(loaded.sh, 2.0 * field.sh.numpy(), atol=1e-6)
    calls.clear()
    off = build_asset(field._replace(views=views), AssetConfig(**{**cfg.__dict__, "light_occlusion": False}))
    assert calls == [False] and off.stats["bake"]["light_scale"] == 1.0 and "light_scale" not in off.gltf_extras()
    assert (off.textures.orm[off.textures.mask][:, 0] == 255).all()
    np.testing.assert_allclose(np.asarray(off.sh), field.sh.numpy())


def test_unseen_texels_take_the_nearest_seen_colour_and_keep_the_visible_background_share():
    from toolkit.backdrop import _fill_from_neighbours

    vals = np.zeros((4, 8, 3), np.float32)
    known = np.zeros((4, 8), bool)
    vals[1, 0], known[1, 0] = (1.0, 0.0, 0.0), True
    vals[1, 4], known[1, 4] = (0.0, 0.0, 1.0), True
    out = _fill_from_neighbours(vals, known)
    np.testing.assert_allclose(out[1, 7], (1.0, 0.0, 0.0))   # wraps in phi: col 7 is next to col 0
    np.testing.assert_allclose(out[3, 4], (0.0, 0.0, 1.0))   # two rings down from the blue texel
    np.testing.assert_allclose(out[1, 2], (0.5, 0.0, 0.5))   # halfway: both reach it in the same ring
    assert np.isfinite(out).all() and out.shape == vals.shape
    np.testing.assert_array_equal(out[known], vals[known])   # known texels are kept


# ---------------------------------------------------------------------------------------------- the box projection
ROOM = dict(origin=np.zeros(3), axes=np.eye(3), lo=np.array([-2.0, -2.0, 0.0]), hi=np.array([2.0, 2.0, 3.0]))


def _box(faces=(False, False, False, False, True, False)):
    from toolkit.backdrop import BoxProjection

    return BoxProjection(**ROOM, faces=np.array(faces), centre=np.array([0.0, 0.0, 1.5]))


def _floor_colour(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """A floor whose linear colour changes across the room (rgb [..., 3])."""
    return torch.stack([0.45 + 0.35 * torch.sin(1.5 * x), 0.45 + 0.35 * torch.cos(1.3 * y),
                        0.3 + 0.1 * x.sign()], -1)


SKY = torch.tensor([0.2, 0.5, 0.9])


def _room_views(eyes, size: int = 24, f: float = 10.0):
    """ViewMaps of cameras at ``eyes`` looking 45° down toward the room's centre, rendering the floor of ``ROOM``
    (z = 0) in :func:`_floor_colour` and the sky where a ray goes up; nothing covered by a mesh."""
    pins = [PinholeCamera(look_at(e, [0.3 * e[0], 0.3 * e[1], 0.0], up=(0.0, 0.0, 1.0)), f, f, size / 2, size / 2,
                          size, size) for e in eyes]
    cams = cameras_from_pinholes(pins)
    rgb = []
    for i in range(len(eyes)):
        r = generate_rays(cams, [i])
        d = r.directions / r.directions.norm(dim=-1, keepdim=True)
        t = -r.origins[:, 2] / d[:, 2].clamp(max=-1e-6)
        p = r.origins + t[:, None] * d
        rgb.append(torch.where((d[:, 2] < 0)[:, None], _floor_colour(p[:, 0], p[:, 1]), SKY).reshape(size, size, 3))
    v = len(eyes)
    return ViewMaps(cams, torch.ones(v, size, size), torch.ones(v, size, size), {"rgb": torch.stack(rgb).float()})


def test_box_projection_keys_a_ray_by_where_it_leaves_the_box():
    box = _box((True, True, True, True, True, False))
    o = torch.tensor([[0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -2.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    keys, on = box.keys(o, d)
    assert on.tolist() == [True, True, True, False]   # the ceiling is not a face of the projection
    # straight down from (1, 1, 1) leaves by the floor at (1, 1, 0): seen from the centre (0, 0, 1.5)
    torch.testing.assert_close(keys[1], torch.nn.functional.normalize(torch.tensor([1.0, 1.0, -1.5]), dim=0))
    torch.testing.assert_close(keys[2], torch.nn.functional.normalize(torch.tensor([2.0, 0.0, -0.5]), dim=0))
    torch.testing.assert_close(keys[3], torch.tensor([0.0, 0.0, 1.0]))  # off the box's faces: the direction
    # an eye outside the box looks through it: the ray from (5, 0, 1) along -x leaves by -a at (-2, 0, 1); one that
    # points away from the box, or passes beside it, is not on it
    keys, on = box.keys(torch.tensor([[5.0, 0.0, 1.0], [5.0, 0.0, 1.0], [5.0, 3.0, 1.0]]),
                        torch.tensor([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]))
    assert on.tolist() == [True, False, False]
    torch.testing.assert_close(keys[0], torch.nn.functional.normalize(torch.tensor([-2.0, 0.0, -0.5]), dim=0))
    from toolkit.layout import RoomLayout

    layout = RoomLayout(origin=np.array([0.0, 0.0, 1.0]), axes=np.eye(3), lo=np.array([-2.0, -2.0, -1.0]),
                        hi=np.array([2.0, 2.0, 2.0]), confident=np.array([False] * 4 + [True, False]),
                        contrast=np.zeros(6), coverage=np.zeros(6))
    from toolkit.backdrop import BoxProjection

    p = BoxProjection.from_layout(layout)
    np.testing.assert_allclose(p.centre, [0.0, 0.0, 1.5]) and np.testing.assert_array_equal(p.faces, _box().faces)
    layout.confident[:] = False
    assert BoxProjection.from_layout(layout) is None
    with pytest.raises(SceneError, match="must exceed lo"):
        BoxProjection(**{**ROOM, "hi": np.array([2.0, -3.0, 3.0])}, faces=np.ones(6, bool), centre=np.zeros(3))


def test_box_map_shows_the_floor_behind_a_hole_from_where_the_camera_stands():
    """Through a hole in the mesh a new camera sees the floor: the box map gives the colour of that patch of floor,
    the direction map only the mean of what the training cameras saw in that direction."""
    ring = [[2.0 * math.cos(a), 2.0 * math.sin(a), h] for a in np.linspace(0, 2 * math.pi, 12, endpoint=False)
            for h in (1.2, 2.0)]
    ring = [[0.8 * x, 0.8 * y, z] for x, y, z in ring] + [[0.3 * x, 0.3 * y, z] for x, y, z in ring[::3]]
    views = _room_views(ring)
    covered = torch.zeros(views.opacity.shape, dtype=torch.bool)
    bg = Background("constant")
    far = backdrop_from_views(bg.radiance_map(), views, covered)
    bd = backdrop_from_views(bg.radiance_map(), views, covered, box=_box())
    assert far.box is None and bd.box is not None and bd.box_radiance.shape == (64, 128, 3)
    assert bd.box_weight.mean() > 0.9
    test = _room_views([[0.7, -0.9, 1.6], [-1.1, 0.4, 1.0]])
    err_far, err_box, n = 0.0, 0.0, 0
    for i in range(2):
        r = generate_rays(test.cameras, [i])
        d = r.directions / r.directions.norm(dim=-1, keepdim=True)
        floor = d[:, 2] < -0.2
        truth = test.values["rgb"][i].reshape(-1, 3)[floor]
        err_far += float(((far.sample(d[floor])[0] - truth) ** 2).sum())
        rad, vis = bd.sample(d[floor], r.origins[floor])
        assert float(vis.min()) == pytest.approx(1.0)
        err_box += float(((rad - truth) ** 2).sum())
        n += int(floor.sum())
    assert err_box < 0.25 * err_far, f"box map MSE {err_box / n:.5f} against the direction map's {err_far / n:.5f}"
    # sky rays leave by the ceiling, no face of the projection: the direction map, as without the box
    up = torch.tensor([[0.1, 0.2, 1.0], [-0.3, 0.1, 0.8]])
    eyes = torch.tensor([[0.5, 0.5, 1.5], [-1.0, 0.0, 1.0]])
    torch.testing.assert_close(bd.sample(up / up.norm(dim=-1, keepdim=True), eyes)[0],
                               far.sample(up / up.norm(dim=-1, keepdim=True))[0])


def test_box_map_weight_keeps_the_direction_map_where_it_explains_the_pixels_better():
    """Sky seen through the box's wall (a room with a low wall): the box map cannot hold what lies at infinity, so
    its weight drops to 0 there and the viewer keeps the direction map."""
    from toolkit.backdrop import BoxProjection

    ring = [[1.5 * math.cos(a), 1.5 * math.sin(a), 1.5] for a in np.linspace(0, 2 * math.pi, 16, endpoint=False)]
    size, f = 24, 8.0
    pins = [PinholeCamera(look_at(e, [-3 * e[0], -3 * e[1], 3.5], up=(0.0, 0.0, 1.0)), f, f, size / 2, size / 2,
                          size, size) for e in ring]
    cams = cameras_from_pinholes(pins)
    rgb = []
    for i in range(len(ring)):  # a sky that changes with the direction only (at infinity)
        d = generate_rays(cams, [i]).directions
        d = d / d.norm(dim=-1, keepdim=True)
        rgb.append(torch.stack([0.5 + 0.4 * d[:, 0], 0.5 + 0.4 * d[:, 1], 0.4 + 0.5 * d[:, 2]], -1).reshape(size, size, 3))
    views = ViewMaps(cams, torch.ones(len(ring), size, size), torch.ones(len(ring), size, size),
                     {"rgb": torch.stack(rgb).float()})
    walls = BoxProjection(**ROOM, faces=np.array([True] * 4 + [False, False]), centre=np.array([0.0, 0.0, 1.5]))
    covered = torch.zeros(views.opacity.shape, dtype=torch.bool)
    bd = backdrop_from_views(Background("constant").radiance_map(), views, covered, box=walls)
    keys = torch.cat([walls.keys(generate_rays(cams, [i]).origins, generate_rays(cams, [i]).directions)[0]
                      for i in range(len(ring))])
    from toolkit.backdrop import _texel_of

    seen = torch.unique(_texel_of(keys, 64, 128))
    assert float(bd.box_weight.reshape(-1)[seen].mean()) < 0.5  # the direction map wins where the sky was seen


def test_box_backdrop_json_round_trip(tmp_path):
    bd = Backdrop(RNG.uniform(0, 3, (4, 8, 3)), np.ones((4, 8)), _box(), RNG.uniform(0, 2, (6, 12, 3)),
                  RNG.uniform(0, 1, (6, 12)))
    back = Backdrop.from_json(json.loads(json.dumps(bd.to_json())))
    np.testing.assert_allclose(back.box_radiance, bd.box_radiance, atol=1e-6)
    np.testing.assert_allclose(back.box_weight, bd.box_weight, atol=1e-4)
    np.testing.assert_array_equal(back.box.faces, bd.box.faces)
    np.testing.assert_allclose(back.box.centre, bd.box.centre)
    bad = bd.to_json()
    bad["box"]["weight"] = bad["box"]["weight"][:-1]
    with pytest.raises(SceneError, match="box: .* weight values"):
        Backdrop.from_json(bad)
    del bad["box"]["lo"]
    with pytest.raises(SceneError, match="not a box projection"):
        Backdrop.from_json(bad)
    with pytest.raises(ShapeError, match="come together"):
        Backdrop(bd.radiance, bd.visibility, _box())


def test_preview_draws_the_box_map_where_a_ray_leaves_by_a_keyed_face(gl, tmp_path):
    from viewers.preview import OffscreenPreview

    bd = Backdrop(RNG.uniform(0, 1.2, (8, 16, 3)), RNG.uniform(0, 1, (8, 16)),
                  _box((True, False, True, True, True, False)), RNG.uniform(0, 1.2, (16, 32, 3)),
                  RNG.uniform(0, 1, (16, 32)))
    glb = textured_cube(tmp_path / "cube.glb", extras={"backdrop": bd.to_json()})
    loaded = load_glb(glb).backdrop
    assert loaded.box is not None
    for eye in ([1.4, -1.7, 1.3], [-1.2, 1.5, 2.5], [3.5, -3.0, 2.0]):  # the last outside the box
        cam = PinholeCamera(look_at(eye, [0, 0, 0.5]), 60.0, 60.0, 80.0, 60.0, 160, 120)
        c = cameras_from_pinholes([cam])
        r = generate_rays(c, [0])
        d = (r.directions / r.directions.norm(dim=-1, keepdim=True)).double()
        rad, vis = loaded.sample(d, r.origins.double())
        sky = eval_sh(torch.as_tensor(CUBE_SH), d).clamp_min(0.0)
        expected = linear_to_srgb((vis[:, None] * rad + (1 - vis[:, None]) * sky).clamp(0, 1)).reshape(120, 160, 3)
        expected = np.round(expected.numpy() * 255)
        _, on = loaded.box.keys(r.origins, r.directions)
        with OffscreenPreview(glb, ctx=gl) as view:
            shown = view.render(cam)
        miss = ~shown.mask
        assert on.reshape(120, 160)[miss].float().mean() > 0.15  # the box map is drawn on part of the background
        err = np.abs(shown.image.astype(float) - expected)[miss]
        assert np.quantile(err, 0.99) <= 3 and err.mean() < 0.5, f"box backdrop off by {err.max()}/255 (mean {err.mean():.2f})"


def test_build_asset_projects_the_backdrop_on_the_room_box_when_the_run_has_one():
    from toolkit.layout import RoomLayout

    field = _sphere_field([])
    plain = field.views

    def views(cams):
        m = plain(cams)
        m.values["rgb"] = torch.full((*m.opacity.shape, 3), 0.3)
        return m

    layout = RoomLayout(origin=np.zeros(3), axes=np.eye(3), lo=np.full(3, -3.0), hi=np.full(3, 3.0),
                        confident=np.array([True, True, False, True, True, False]), contrast=np.zeros(6),
                        coverage=np.zeros(6))
    cfg = AssetConfig(method="mc", resolution=32, faces=600, texture=64, level=100.0)
    asset = build_asset(field._replace(views=views, room_layout=layout), cfg)
    assert asset.backdrop.box is not None and asset.backdrop.box_radiance.shape == (64, 128, 3)
    assert asset.stats["backdrop"]["box"]["faces"] == ["-a", "+a", "+b", "floor"]
    assert "box" in asset.gltf_extras()["backdrop"]
    off = build_asset(field._replace(views=views, room_layout=layout), AssetConfig(**{**cfg.__dict__,
                                                                                      "backdrop_box": False}))
    assert off.backdrop.box is None and "box" not in off.stats["backdrop"]
