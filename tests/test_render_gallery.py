"""Tests of samples/render_gallery.py and of the committed sample scene samples/gallery/.

Mitsuba tests skip with a reason when mitsuba is not installed; ``llvm_*`` variants only run when libLLVM 19 exists
(without it the first llvm render aborts the whole Python process).
"""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "gallery"


def _load_renderer():
    spec = importlib.util.spec_from_file_location("render_gallery", REPO / "samples" / "render_gallery.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("render_gallery", module)
    spec.loader.exec_module(module)
    return module


rg = _load_renderer()
HAS_MITSUBA = importlib.util.find_spec("mitsuba") is not None
needs_mitsuba = pytest.mark.skipif(not HAS_MITSUBA, reason="mitsuba is not installed (pip install 'dars-toolkit[render]')")
VARIANTS = ["scalar_rgb"] + (["llvm_ad_rgb"] if rg.llvm_available() else [])
needs_sample = pytest.mark.skipif(not (SAMPLE / "transforms_train.json").is_file(), reason=f"sample scene not rendered at {SAMPLE}")


def _project(c2w: np.ndarray, f: float, c: float, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Toolkit pinhole convention: pixel-index coordinates (u, v) and depth along −z_cam."""
    w2c = np.linalg.inv(c2w)
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    depth = -p[:, 2]
    u = f * p[:, 0] / depth + c - 0.5
    v = -f * p[:, 1] / depth + c - 0.5
    return np.stack([u, v], -1), depth


# --------------------------------------------------------------------------------------------------- camera helpers
def test_c2w_to_mitsuba_axes():
    c2w = rg.look_at(np.array([1.0, -3.0, 1.5]), np.array([0.0, 0.5, 1.0]))
    to_world = rg.c2w_to_mitsuba(c2w)
    forward_gl = c2w[:3, :3] @ np.array([0.0, 0.0, -1.0])
    np.testing.assert_allclose(to_world[:3, :3] @ np.array([0.0, 0.0, 1.0]), forward_gl)  # mitsuba looks +z
    np.testing.assert_allclose(to_world[:3, :3] @ np.array([1.0, 0.0, 0.0]), -c2w[:3, 0])  # mitsuba x is left
    np.testing.assert_allclose(to_world[:3, :3] @ np.array([0.0, 1.0, 0.0]), c2w[:3, 1])
    np.testing.assert_allclose(to_world[:3, 3], c2w[:3, 3])
    np.testing.assert_allclose(rg.c2w_to_mitsuba(np.eye(4)), np.diag([-1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="4x4"):
        rg.c2w_to_mitsuba(np.eye(3))


def test_pixel_rays_follow_toolkit_convention():
    c2w = rg.look_at(np.array([0.5, -2.0, 1.0]), np.array([0.0, 0.0, 1.2]))
    size, fov = 16, math.radians(45)
    f = rg.focal_from_fov(fov, size)
    o, d, scale = rg.pixel_rays(c2w, fov, size)
    for row, col in [(0, 0), (3, 11), (15, 15)]:
        d_cam = np.array([(col + 0.5 - size / 2) / f, -(row + 0.5 - size / 2) / f, -1.0])
        np.testing.assert_allclose(d[0, row, col], c2w[:3, :3] @ d_cam / np.linalg.norm(d_cam), atol=1e-12)
        assert scale[0, row, col] == pytest.approx(1.0 / np.linalg.norm(d_cam))
    # a point 2 m along a pixel's ray projects back onto that pixel centre
    pts = o[0, 3, 11] + d[0, 3, 11] * 2.0
    uv, depth = _project(c2w, f, size / 2, pts[None])
    np.testing.assert_allclose(uv[0], [11.0, 3.0], atol=1e-9)
    assert depth[0] == pytest.approx(2.0 * scale[0, 3, 11])


def test_sampled_cameras_are_rigid_and_in_front():
    cams = rg.sample_cameras(40, seed=3)
    for c2w in cams:
        R = c2w[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        eye = c2w[:3, 3]
        assert eye[1] < 0.6 and 1.0 < np.linalg.norm(eye - np.array([0.05, 0.55, 1.0])) < 4.0  # in front of the wall
        forward = -R[:, 2]
        assert forward @ (np.array([0.05, 0.55, 1.0]) - eye) > 0  # looks at the scene
        assert abs(R[2, 0]) < 1e-9  # no roll: camera x stays horizontal


# --------------------------------------------------------------------------------------------- (a) camera convention
@needs_mitsuba
@pytest.mark.parametrize("variant", VARIANTS)
def test_mitsuba_render_matches_pinhole_projection(variant):
    mi, _, _ = rg.import_mitsuba(variant)
    centres = np.array([[0.3, 0.1, 0.2], [-0.4, 0.25, -0.1], [0.1, -0.35, 0.3], [-0.2, -0.2, -0.3]])
    scene_dict = {"type": "scene"}
    for k, c in enumerate(centres):
        scene_dict[f"s{k}"] = {"type": "sphere", "center": c.tolist(), "radius": 0.04,
                               "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}
    scene = mi.load_dict(scene_dict)
    size, fov = 64, math.radians(40.0)
    c2w = rg.look_at(np.array([0.8, -2.5, 1.0]), np.array([0.05, 0.0, 0.05]))
    sensor = mi.load_dict({
        "type": "perspective", "fov": math.degrees(fov), "fov_axis": "x", "to_world": mi.ScalarTransform4f(rg.c2w_to_mitsuba(c2w).tolist()),
        "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": 16},
    })
    img = np.array(mi.render(scene, sensor=sensor, integrator=mi.load_dict({"type": "direct"}), spp=16)).mean(-1)
    uv, _ = _project(c2w, rg.focal_from_fov(fov, size), size / 2, centres)
    for (u, v) in uv:
        r0, c0 = int(round(v)), int(round(u))
        rows, cols = np.mgrid[r0 - 5 : r0 + 6, c0 - 5 : c0 + 6]
        win = img[r0 - 5 : r0 + 6, c0 - 5 : c0 + 6]
        assert win.sum() > 1.0, f"sphere not found near ({u:.1f}, {v:.1f})"
        centroid = np.array([(cols * win).sum(), (rows * win).sum()]) / win.sum()
        assert np.abs(centroid - [u, v]).max() < 0.5, f"{variant}: centroid {centroid} vs projection ({u:.2f}, {v:.2f})"
    assert img.sum() == pytest.approx(sum(img[int(round(v)) - 5 : int(round(v)) + 6, int(round(u)) - 5 : int(round(u)) + 6].sum() for u, v in uv), rel=1e-3)


# ------------------------------------------------------------------------------------------ environment orientation
def _feature_env(H: int = 64, W: int = 128) -> np.ndarray:
    """Distinct coloured lobes (red toward +x, green toward +y, blue up, white down-left) on a grey floor."""
    from toolkit.sh import latlong_directions

    d = latlong_directions(H, W, dtype=torch.float64).numpy()
    out = np.full((H, W, 3), 0.1)
    for axis, colour in [((1, 0, 0.2), (4, 0.2, 0.2)), ((0, 1, 0.2), (0.2, 4, 0.2)), ((0.3, 0, 1), (0.2, 0.2, 4)), ((-0.6, -0.5, -0.6), (3, 3, 3))]:
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        out += np.exp(8.0 * (d @ a - 1.0))[..., None] * np.asarray(colour)
    return out.astype(np.float32)


@needs_mitsuba
@pytest.mark.parametrize("variant", VARIANTS)
def test_environment_orientation_matches_spec_latlong(variant):
    from toolkit.sh import lookup_latlong, rotation_z

    mi, dr, _ = rg.import_mitsuba(variant)
    env = rg.Environment(latlong=_feature_env(), rotate_z_deg=30.0, source="test")
    scene = mi.load_dict({"type": "scene", "env": {"type": "envmap", "bitmap": mi.Bitmap(rg._mitsuba_env_bitmap(env.latlong)),
                                                   "to_world": mi.ScalarTransform4f().rotate([0, 0, 1], 30.0).rotate([1, 0, 0], 90)}})
    size, fov = 24, math.radians(70.0)
    rz = rotation_z(30.0).numpy()
    latlong = torch.as_tensor(env.latlong, dtype=torch.float64)
    for target in [(1.0, 0.3, 0.2), (-0.2, 1.0, 0.4), (0.1, -1.0, -0.5), (0.2, 0.1, 1.0)]:
        c2w = rg.look_at(np.zeros(3), np.asarray(target), up=(0.0, 0.0, 1.0) if abs(target[2]) < 0.9 else (0.0, 1.0, 0.0))
        sensor = mi.load_dict({
            "type": "perspective", "fov": math.degrees(fov), "fov_axis": "x", "to_world": mi.ScalarTransform4f(rg.c2w_to_mitsuba(c2w).tolist()),
            "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        })
        img = np.array(mi.render(scene, sensor=sensor, integrator=mi.load_dict({"type": "path"}), spp=16))
        _, d, _ = rg.pixel_rays(c2w, fov, size)
        ref = lookup_latlong(latlong, torch.as_tensor(d[0] @ rz)).numpy()  # world direction → map direction: R⁻¹ d
        mirrored = lookup_latlong(latlong, torch.as_tensor((d[0] * [-1, 1, 1]) @ rz)).numpy()
        err = np.abs(img - ref).mean() / ref.mean()
        assert err < 0.05, f"rendered environment differs from the SPEC lat-long lookup by {err:.3f} (target {target})"
        assert np.abs(img - mirrored).mean() / ref.mean() > 2 * err + 0.05 or np.allclose(ref, mirrored, rtol=0.05)
    # querying the loaded emitter reproduces the input map at SPEC pixel centres
    scene0 = mi.load_dict({"type": "scene", "env": {"type": "envmap", "bitmap": mi.Bitmap(rg._mitsuba_env_bitmap(env.latlong)),
                                                    "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 90)}})
    built = rg._Built(scene=scene0, shapes=[], info=[], meta={})
    used = rg.environment_as_used(mi, dr, built, *env.latlong.shape[:2])
    assert np.abs(used - env.latlong).mean() / env.latlong.mean() < 0.02


# ----------------------------------------------------------------------------------------------- render_views smoke
@needs_mitsuba
def test_render_views_smoke():
    env = rg.Environment(latlong=_feature_env(32, 64), source="test")
    cams = rg.sample_cameras(2, seed=5)
    res = rg.render_views(rg.GalleryConfig(), cams, env, 24, 4, settings=rg.RenderSettings(progress=False, gt_subsamples=2))
    assert res["radiance"].shape == (2, 24, 24, 3) and res["radiance"].dtype == np.float32
    assert np.isfinite(res["radiance"]).all() and res["radiance"].mean() > 0
    for key, shape, dtype in [("depth", (2, 24, 24), np.float32), ("normal", (2, 24, 24, 3), np.float32), ("albedo", (2, 24, 24, 3), np.float32),
                              ("roughness", (2, 24, 24), np.float32), ("metallic", (2, 24, 24), np.float32),
                              ("semantic", (2, 24, 24), np.uint8), ("metal", (2, 24, 24), np.uint8)]:
        assert res[key].shape == shape and res[key].dtype == dtype, key
    sem = res["semantic"]
    assert set(np.unique(sem)) <= {0, 1, 2, 3, 4, 5, 6, 255} and (sem == 4).any()
    assert ((res["depth"] > 0) == (sem != 255)).mean() > 0.99
    with pytest.raises(ValueError, match="spp"):
        rg.render_views(rg.GalleryConfig(), cams, env, 24, 0)


# ------------------------------------------------------------------------------------------- (b) the committed sample
def _load_split(split: str) -> dict:
    return json.loads((SAMPLE / f"transforms_{split}.json").read_text())


def _read(path: Path) -> np.ndarray:
    from toolkit.io import read_map

    return read_map(path)


@needs_sample
@pytest.mark.parametrize("split", ["train", "test"])
def test_sample_files_and_header(split):
    meta = _load_split(split)
    for key in ("camera_angle_x", "fl_x", "fl_y", "cx", "cy", "w", "h", "aabb", "sh", "envmap", "depth_unit_scale_factor", "render", "scene"):
        assert key in meta, key
    assert np.asarray(meta["sh"]).shape == (9, 3) and meta["depth_unit_scale_factor"] == 0.001
    assert meta["fl_x"] == pytest.approx(0.5 * meta["w"] / math.tan(0.5 * meta["camera_angle_x"]))
    assert len(meta["frames"]) == {"train": 80, "test": 20}[split]
    keys = ("file_path", "radiance_path", "depth_file_path", "normal_path", "albedo_path", "roughness_path", "metallic_path", "semantic_path", "metal_path")
    for frame in meta["frames"][:5] + meta["frames"][-2:]:
        for key in keys:
            assert (SAMPLE / frame[key]).is_file(), frame[key]
        sem = _read(SAMPLE / frame["semantic_path"])
        assert sem.shape == (meta["h"], meta["w"]) and sem.dtype == np.uint8
        assert set(np.unique(sem)) <= {0, 1, 2, 3, 4, 5, 6, 255}
        metal = _read(SAMPLE / frame["metal_path"])
        np.testing.assert_array_equal(metal == 255, np.isin(sem, [1, 6]))
        assert _read(SAMPLE / frame["depth_file_path"]).dtype == np.uint16


@needs_sample
def test_sample_known_points_land_on_their_labels():
    checked_corners = checked_sculpture = 0
    for split in ("train", "test"):
        meta = _load_split(split)
        scene = meta["scene"]
        f, c, size = meta["fl_x"], meta["cx"], meta["w"]
        corners = np.asarray(scene["painting_corners"])
        centre = np.asarray(scene["sculpture_center"])[None]
        for frame in meta["frames"]:
            c2w = np.asarray(frame["transform_matrix"])
            sem = _read(SAMPLE / frame["semantic_path"])
            depth = _read(SAMPLE / frame["depth_file_path"]).astype(np.float64) * meta["depth_unit_scale_factor"]
            uv, z = _project(c2w, f, c, corners)
            for (u, v), zc in zip(uv, z):
                col, row = int(round(u)), int(round(v))
                if not (4 <= col < size - 4 and 4 <= row < size - 4):
                    continue
                if depth[row, col] < zc - 0.10 or sem[row, col] == 2:  # hidden behind the pedestal, or seen through the case
                    continue
                assert sem[row, col] in (0, 1), f"{frame['file_path']}: painting corner at ({u:.1f}, {v:.1f}) has label {sem[row, col]}"
                assert (sem[row - 4 : row + 5, col - 4 : col + 5] == 0).any(), f"{frame['file_path']}: no painting label near its corner"
                checked_corners += 1
            uv_s, z_s = _project(c2w, f, c, centre)
            (u, v), zc = uv_s[0], z_s[0]
            col, row = int(round(u)), int(round(v))
            if 0 <= col < size and 0 <= row < size:
                assert sem[row, col] == 6, f"{frame['file_path']}: sculpture centre at ({u:.1f}, {v:.1f}) has label {sem[row, col]}"
                assert zc - 0.25 < depth[row, col] < zc, f"{frame['file_path']}: depth {depth[row, col]:.3f} at the sculpture centre ({zc:.3f} m away)"
                checked_sculpture += 1
    assert checked_corners >= 100 and checked_sculpture >= 80


def _interior(mask: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood shares the mask (away from anti-aliased edges)."""
    m = np.pad(mask, 1)
    out = np.ones_like(mask)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            out &= m[1 + dr : 1 + dr + mask.shape[0], 1 + dc : 1 + dc + mask.shape[1]]
    return out


@needs_sample
def test_sample_depth_normals_and_materials_are_consistent():
    from toolkit.io import read_image

    meta = _load_split("test")
    scene = meta["scene"]
    f, c, size = meta["fl_x"], meta["cx"], meta["w"]
    canvas_y = scene["painting_plane"]["point"][1]
    corners = np.asarray(scene["painting_corners"])
    wall_y = scene["wall_plane"]["point"][1]
    from toolkit.losses import PAINTING_ROUGHNESS

    painting_roughness = scene["paintings"][0]["roughness"]  # not L_mat's painting target: no circular score
    assert abs(painting_roughness - PAINTING_ROUGHNESS) > 0.1
    rows, cols = np.mgrid[0:size, 0:size]
    d_cam = np.stack([(cols + 0.5 - c) / f, -(rows + 0.5 - c) / f, -np.ones((size, size))], -1)
    for frame in meta["frames"]:
        c2w = np.asarray(frame["transform_matrix"])
        sem = _read(SAMPLE / frame["semantic_path"])
        depth = _read(SAMPLE / frame["depth_file_path"]).astype(np.float64) * meta["depth_unit_scale_factor"]
        points = (d_cam * depth[..., None]) @ c2w[:3, :3].T + c2w[:3, 3]
        paint = sem == 0
        assert paint.sum() > 50
        np.testing.assert_allclose(points[paint][:, 1], canvas_y, atol=3e-3)
        assert (points[paint][:, 0] > corners[:, 0].min() - 0.01).all() and (points[paint][:, 0] < corners[:, 0].max() + 0.01).all()
        assert (points[paint][:, 2] > corners[:, 2].min() - 0.01).all() and (points[paint][:, 2] < corners[:, 2].max() + 0.01).all()
        np.testing.assert_allclose(points[sem == 5][:, 2], 0.0, atol=3e-3)
        np.testing.assert_allclose(points[sem == 4][:, 1], wall_y, atol=3e-3)
        normal = read_image(SAMPLE / frame["normal_path"]) * 2.0 - 1.0
        for label, expected in [(4, (0.0, -1.0, 0.0)), (5, (0.0, 0.0, 1.0)), (0, (0.0, -1.0, 0.0))]:
            inner = _interior(sem == label)
            if inner.any():
                assert np.abs(normal[inner] - expected).max() < 0.02, f"{frame['file_path']}: normals of label {label}"
        albedo = read_image(SAMPLE / frame["albedo_path"])
        wall = _interior(sem == 4)
        wall_colour = scene["config"]["room"]["wall_materials"][0]["base_color"]
        np.testing.assert_allclose(albedo[wall], np.broadcast_to(wall_colour, albedo[wall].shape), atol=1.0 / 255)
        rough = read_image(SAMPLE / frame["roughness_path"])[..., 0]
        metallic = read_image(SAMPLE / frame["metallic_path"])[..., 0]
        np.testing.assert_allclose(rough[_interior(paint)], painting_roughness, atol=1.0 / 255)
        np.testing.assert_allclose(metallic[_interior(paint)], 0.0, atol=1.0 / 255)
        sculpt = _interior(sem == 6)
        np.testing.assert_allclose(metallic[sculpt], 1.0, atol=1.0 / 255)
        np.testing.assert_allclose(rough[sculpt], 0.2, atol=1.0 / 255)


@needs_sample
def test_sample_images_are_well_exposed():
    from toolkit.io import read_image

    meta = _load_split("train")
    means = [read_image(SAMPLE / fr["file_path"]).mean() for fr in meta["frames"][::8]]
    assert 0.3 < float(np.mean(means)) < 0.55
    hdr = read_image(SAMPLE / meta["frames"][0]["radiance_path"])
    png = read_image(SAMPLE / meta["frames"][0]["file_path"])
    from toolkit.io import linear_to_srgb

    assert np.abs(linear_to_srgb(np.clip(hdr, 0, 1)) - png).mean() < 0.01


# ------------------------------------------------------------------------------------------------------- (c) GT SH
@needs_sample
def test_sample_sh_equals_projection_of_envmap():
    from toolkit.sh import fit_sh_probe, read_envmap

    meta = _load_split("train")
    sh = torch.as_tensor(meta["sh"], dtype=torch.float64)
    fresh = fit_sh_probe(read_envmap(SAMPLE / meta["envmap"])).coeffs.double()
    assert (sh[0] > 0).all()
    torch.testing.assert_close(fresh, sh, atol=0.02 * float(sh[0].max()), rtol=0)
    assert _load_split("test")["sh"] == meta["sh"]


# ================================================================================================ procedural galleries
import procedural as pg  # noqa: E402  (samples/ is on sys.path once render_gallery is loaded)
import galleries  # noqa: E402

needs_probes = pytest.mark.skipif(not (rg.ENVMAPS / "probulator_pisa_256x128.hdr").is_file(),
                                  reason=f"HDR probes not found in {rg.ENVMAPS} (set DARS_ENVMAPS or DARS_SHARED_DATA)")
TINY_SEED = 109
"""A gallery whose tiny render (2 + 1 views at 24 px) shows paintings, walls, floor and metal, with RGBA PNGs, a
glass-covered painting, a display case and lamps (checked in test_tiny_gallery_render)."""


def test_random_gallery_is_deterministic_and_json_round_trips():
    a, b = pg.random_gallery(7), pg.random_gallery(7)
    assert a == b and json.dumps(a.to_dict(), sort_keys=True) == json.dumps(b.to_dict(), sort_keys=True)
    assert a.digest() == b.digest() and pg.random_gallery(8).digest() != a.digest()
    assert pg.random_gallery(8) != a
    for cfg in (a, pg.GalleryConfig.sample(), pg.GalleryConfig.sample(3)):
        assert pg.GalleryConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    cams_a, kinds_a = pg.gallery_cameras(a, 12, "train")
    cams_b, kinds_b = pg.gallery_cameras(b, 12, "train")
    np.testing.assert_array_equal(cams_a, cams_b)
    assert kinds_a == kinds_b
    with pytest.raises(ValueError, match="non-negative"):
        pg.random_gallery(-1)


def test_random_galleries_obey_the_constraints():
    seen: dict[str, set] = {"frame": set(), "format": set(), "lamp": set(), "top": set(), "kind": set(), "floor": set()}
    roughness = []
    for seed in range(40):
        cfg = pg.random_gallery(seed)
        pg.check_config(cfg)  # closed room, sizes, paintings on their walls, objects inside and apart, lamps inside
        room = cfg.room
        for p in cfg.paintings:
            roughness.append(p.canvas.roughness)
            assert 0.5 <= p.canvas.roughness <= 0.95
            assert {"gilt": 1.0, "wood": 0.0}.get(p.frame, p.frame_material.metallic) == p.frame_material.metallic
            seen["frame"].add(p.frame)
        seen["format"].add(cfg.image_format)
        seen["lamp"] |= {lamp.kind for lamp in cfg.lighting.lamps}
        seen["top"].add("skylights" if room.openings else ("closed" if room.ceiling else "open"))
        seen["floor"].add(room.floor.texture_args[0])
        train, kinds = pg.gallery_cameras(cfg, 30, "train")
        test, _ = pg.gallery_cameras(cfg, 10, "test")
        seen["kind"] |= set(kinds)
        for cams in (train, test):
            pg.check_cameras(cfg, cams)  # rigid, inside the room, >= 0.3 m from walls and object footprints
            eyes = cams[:, :3, 3]
            assert (eyes[:, 0] > room.x[0]).all() and (eyes[:, 0] < room.x[1]).all() and (eyes[:, 2] < room.height).all()
            for box in pg.obstacle_boxes(cfg):
                inside = ((eyes[:, :2] > box[0, :2]) & (eyes[:, :2] < box[1, :2])).all(1)
                assert not inside.any(), f"seed {seed}: a camera stands inside an object"
            np.testing.assert_allclose(cams[:, 2, 0], 0.0, atol=1e-9)  # no roll
        walks = [c for c, k in zip(train, kinds) if k == "walk"]
        assert all(1.3 <= c[2, 3] <= 1.8 for c in walks)
        dist = np.linalg.norm(train[:, None, :3, 3] - test[None, :, :3, 3], axis=-1)
        assert dist.min() > 1e-3, f"seed {seed}: a test camera repeats a train camera"
    assert seen["frame"] == {"gilt", "wood", "glass"} and seen["format"] == {"rgb", "rgba"}
    assert seen["lamp"] == {"spot", "point", "area"} and seen["top"] == {"skylights", "closed", "open"}
    assert seen["kind"] == {"walk", "arc", "closeup"} and seen["floor"] == {"planks", "stone", "concrete", "carpet"}
    assert np.std(roughness) > 0.08 and abs(np.mean(roughness) - 0.725) < 0.05  # drawn from U(0.5, 0.95), not 0.8


def test_constraint_checks_reject_bad_configs():
    from dataclasses import replace

    cfg = pg.random_gallery(3)
    p = cfg.paintings[0]
    off = replace(cfg, paintings=(replace(p, center=(p.center[0] + 50.0, p.center[1])),) + cfg.paintings[1:])
    with pytest.raises(ValueError, match="not on its wall"):
        pg.check_config(off)
    with pytest.raises(ValueError, match="roughness"):
        pg.check_config(replace(cfg, paintings=(replace(p, canvas=replace(p.canvas, roughness=0.99)),) + cfg.paintings[1:]))
    cams, _ = pg.gallery_cameras(cfg, 2, "train")
    bad = cams.copy()
    bad[0, :3, 3] = [cfg.room.x[0] + 0.05, np.mean(cfg.room.y), 1.5]  # 5 cm from a wall
    with pytest.raises(ValueError, match="clearance"):
        pg.check_cameras(cfg, bad)


def test_sample_preset_reproduces_the_sample_geometry_and_cameras():
    cfg = pg.GalleryConfig.sample()
    names = [p.name for p in pg.scene_parts(cfg)]
    assert names == ["wall", "floor", "painting", "frame_top", "frame_bottom", "frame_left", "frame_right", "pedestal", "sculpture",
                     "case_front", "case_back", "case_left", "case_right", "case_top"]
    if not (SAMPLE / "transforms_train.json").is_file():
        pytest.skip(f"sample scene not rendered at {SAMPLE}")
    for split, n in (("train", 80), ("test", 20)):
        meta = _load_split(split)
        cams, _ = pg.gallery_cameras(cfg, n, split)
        np.testing.assert_allclose(cams, [f["transform_matrix"] for f in meta["frames"]], atol=1e-12)
    meta = _load_split("train")
    got = rg.scene_meta(cfg)
    for key in ("painting_corners", "frame_box", "pedestal_box", "case_box", "sculpture_center", "sculpture_box"):
        np.testing.assert_allclose(got[key], meta["scene"][key], atol=1e-9, err_msg=key)
    assert got["painting_plane"] == meta["scene"]["painting_plane"] and got["wall_plane"] == meta["scene"]["wall_plane"]


@needs_mitsuba
@needs_sample
def test_sample_preset_ground_truth_equals_the_committed_maps():
    """The scene the sample preset builds traces to the committed labels, metal masks and depths (bit for bit)."""
    import tempfile

    mi, dr, _ = rg.import_mitsuba(VARIANTS[-1])
    meta = _load_split("test")
    frame = meta["frames"][3]
    cfg = pg.GalleryConfig.sample()
    with tempfile.TemporaryDirectory() as tmp:
        built = rg.build_scene(mi, cfg, rg.Environment(latlong=np.ones((8, 16, 3), np.float32)), Path(tmp))
    gt = rg.render_gt(mi, dr, built, np.asarray(frame["transform_matrix"]), meta["camera_angle_x"], meta["w"], subsamples=1)
    np.testing.assert_array_equal(gt["semantic"], _read(SAMPLE / frame["semantic_path"]))
    np.testing.assert_array_equal(gt["metal"], _read(SAMPLE / frame["metal_path"]))
    depth_mm = np.clip(np.round(gt["depth"] * 1000.0), 0, 65535).astype(np.uint16)
    np.testing.assert_array_equal(depth_mm, _read(SAMPLE / frame["depth_file_path"]))


def test_cube_pixel_solid_angles_cover_the_sphere():
    for n in (1, 7, 32):
        assert 6 * rg.cube_pixel_solid_angles(n).sum() == pytest.approx(4 * math.pi, rel=1e-12)
    cams = rg.cube_face_cameras(np.array([1.0, 2.0, 3.0]))
    forwards = -cams[:, :3, 2]
    np.testing.assert_allclose(forwards, np.asarray(rg.CUBE_FACES, float), atol=1e-12)


@needs_mitsuba
@needs_probes
def test_cube_map_sh_matches_the_probe_sh():
    """The cube-map projection reproduces the environment's own SH when nothing occludes it (0.2 % of the DC term
    at 16 px faces); in the sample's open corner the directions that escape see the probe itself, and the SH differs
    from the probe's by ≤ 0.11 of the DC term (measured 0.10: the floor replaces the lower hemisphere and the wall a
    slice of the +y side, which moves the z and y bands)."""
    import tempfile

    from toolkit.sh import fit_sh_probe, lookup_latlong, rotation_z

    mi, dr, variant = rg.import_mitsuba(VARIANTS[-1])
    env = rg.load_environment(str(rg.ENVMAPS / "probulator_pisa_256x128.hdr"), 30.0)
    settings = rg.RenderSettings(variant=variant, integrator="path")
    scene = mi.load_dict({"type": "scene", "env": {"type": "envmap", "bitmap": mi.Bitmap(rg._mitsuba_env_bitmap(env.latlong)),
                                                   "to_world": mi.ScalarTransform4f().rotate([0, 0, 1], 30.0).rotate([1, 0, 0], 90)}})
    empty = rg._Built(scene=scene, shapes=[], info=[], meta={})
    ref = fit_sh_probe(torch.as_tensor(rg.environment_as_used(mi, dr, empty, 256, 512), dtype=torch.float64)).coeffs.numpy()
    probe = rg.render_light_probe(mi, dr, empty, np.zeros(3), 16, 16, settings)
    assert np.abs(probe["sh"] - ref).max() < 0.005 * ref[0].max()
    assert probe["delta_lamps"] == 0 and probe["latlong"].shape == (64, 128, 3)
    cfg = pg.GalleryConfig.sample()
    point = pg.probe_point(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        built = rg.build_scene(mi, cfg, env, Path(tmp))
    face = 16
    probe = rg.render_light_probe(mi, dr, built, point, face, 64, settings)
    assert np.abs(probe["sh"] - ref).max() < 0.11 * ref[0].max()
    # where the room occludes nothing the panorama is the probe: project both onto SH over the escaping directions only
    from toolkit.sh import latlong_directions, latlong_solid_angles, sh_basis

    d = latlong_directions(64, 128, dtype=torch.float64).numpy().reshape(-1, 3)
    hit = rg._trace(mi, dr, built, np.broadcast_to(point, d.shape).copy(), d)
    sky = hit["shape"] < 0
    lookup = lookup_latlong(torch.as_tensor(env.latlong, dtype=torch.float64), torch.as_tensor(d[sky] @ rotation_z(30.0).numpy())).numpy()
    w = (sh_basis(torch.as_tensor(d[sky])).numpy() * latlong_solid_angles(64, 128, dtype=torch.float64).numpy().reshape(-1)[sky, None])
    sh_pano, sh_look = w.T @ probe["latlong"].reshape(-1, 3)[sky], w.T @ lookup
    assert sky.mean() > 0.3 and np.abs(sh_pano - sh_look).max() < 0.03 * sh_look[0].max()


@pytest.fixture(scope="module")
def tiny_gallery(tmp_path_factory):
    if not HAS_MITSUBA:
        pytest.skip("mitsuba is not installed (pip install 'dars-toolkit[render]')")
    if not (rg.ENVMAPS / "probulator_pisa_256x128.hdr").is_file():
        pytest.skip(f"HDR probes not found in {rg.ENVMAPS} (set DARS_ENVMAPS or DARS_SHARED_DATA)")
    out = tmp_path_factory.mktemp("gallery") / f"seed_{TINY_SEED}"
    summary = rg.render_gallery(pg.random_gallery(TINY_SEED), out, rg.PROFILES["tiny"])
    return out, summary


def test_tiny_gallery_render(tiny_gallery):
    from toolkit.scene import load_scene

    out, summary = tiny_gallery
    cfg = pg.random_gallery(TINY_SEED)
    assert cfg.image_format == "rgba" and any(p.frame == "glass" for p in cfg.paintings) and any(p.case_half > 0 for p in cfg.pedestals)
    labels, metal_px = set(), 0
    for split, n in (("train", 2), ("test", 1)):
        meta = json.loads((out / f"transforms_{split}.json").read_text())
        assert "aabb" not in meta  # real captures carry no box
        scene = load_scene(out, split)
        assert len(scene) == n and tuple(scene.image_size) == (24, 24) and scene.sh is not None
        assert np.asarray(meta["sh"]).shape == (9, 3) and np.asarray(meta["sh_env"]).shape == (9, 3)
        assert meta["envmap"] == "light.hdr" and (out / "light.hdr").is_file() and (out / "env.hdr").is_file()
        assert "incident radiance" in meta["render"]["sh_definition"] and len(meta["render"]["sh_point"]) == 3
        assert pg.GalleryConfig.from_dict(meta["scene"]["config"]) == cfg
        for frame in meta["frames"]:
            import cv2

            png = cv2.imread(str(out / frame["file_path"]), cv2.IMREAD_UNCHANGED)
            assert png.shape == (24, 24, 4) and (png[..., 3] == 255).all()
            sem = _read(out / frame["semantic_path"])
            metal = _read(out / frame["metal_path"])
            labels |= set(np.unique(sem).tolist())
            metal_px += int((metal == 255).sum())
            assert set(np.unique(metal).tolist()) <= {0, 255} and np.isin(sem[metal == 255], [1, 3, 6]).all()
            depth = _read(out / frame["depth_file_path"])
            assert ((depth > 0) == (sem != 255)).all()
            assert frame["view_kind"] in ("walk", "arc", "closeup") and frame["spp"] == 8
    assert {0, 4, 5} <= labels and labels <= {0, 1, 2, 3, 4, 5, 6, 255}
    assert metal_px > 0  # gilt frames / metal exhibits in view
    assert set(summary["seconds"]) >= {"exposure", "radiance", "gt", "probe", "total"}
    assert np.isfinite(summary["noise"]["psnr_db_mean"])


def test_room_aabb_encloses_room_and_cameras():
    cfg = pg.random_gallery(TINY_SEED)
    box = np.asarray(rg.room_aabb(cfg))
    cams, _ = pg.gallery_cameras(cfg, 20, "train")
    assert (cams[:, :3, 3] > box[0]).all() and (cams[:, :3, 3] < box[1]).all()
    assert box[0, 2] < 0 < cfg.room.height < box[1, 2] and box[1, 0] - box[0, 0] < cfg.room.x[1] - cfg.room.x[0] + 0.2


def test_gallery_cache_renders_once_and_atomically(tmp_path, monkeypatch):
    calls = []

    def fake_render(cfg, out_dir, opts):
        calls.append(cfg.seed)
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True)
        (out_dir / "transforms_train.json").write_text("{}")
        return {"seconds": {"total": 0.0}, "noise": {"spp_mean": 1, "spp_min": 1, "spp_max": 1}}

    monkeypatch.setattr(rg, "render_gallery", fake_render)
    monkeypatch.setitem(sys.modules, "render_gallery", rg)
    d = galleries.ensure_gallery(5, "tiny", root=tmp_path)
    assert d == tmp_path / "tiny" / "seed_5" and (d / "transforms_train.json").is_file() and calls == [5]
    assert galleries.is_cached(5, "tiny", root=tmp_path)
    assert galleries.ensure_gallery(5, "tiny", root=tmp_path) == d and calls == [5]  # cached: not rendered again
    stamp = json.loads((d / "stamp.json").read_text())
    stamp["hash"] = "0" * 16  # the generator changed
    (d / "stamp.json").write_text(json.dumps(stamp))
    assert not galleries.is_cached(5, "tiny", root=tmp_path)
    galleries.ensure_gallery(5, "tiny", root=tmp_path)
    assert calls == [5, 5] and galleries.is_cached(5, "tiny", root=tmp_path)
    assert sorted(p.name for p in (tmp_path / "tiny").iterdir() if not p.name.startswith(".lock")) == ["seed_5"]  # no temp dirs left
    monkeypatch.setenv("DARS_CACHE", str(tmp_path / "c"))
    assert galleries.cache_root() == tmp_path / "c" / "galleries"


def test_seed_lists_are_disjoint_and_validation_is_held_out():
    assert len(galleries.VALIDATION_SEEDS) >= 8
    assert not set(galleries.VALIDATION_SEEDS) & set(galleries.PRIOR_TRAIN_SEEDS)
    assert galleries.parse_seeds("0-2,7", "prior") == [0, 1, 2, 7]
    assert galleries.parse_seeds("all", "validation") == list(galleries.VALIDATION_SEEDS)
    with pytest.raises(ValueError, match="held out"):
        galleries.parse_seeds(str(galleries.VALIDATION_SEEDS[0]), "prior")
    with pytest.raises(ValueError, match="unknown profile"):
        galleries.config_hash(0, "nope")


def test_wall_patterns_paper_some_rooms_and_leave_the_rest_as_they_were():
    from gallery_assets import WALL_PATTERNS, wall_texture

    for kind in WALL_PATTERNS:
        a = wall_texture(kind, 3, (0.8, 0.75, 0.7), size=64)
        assert a.shape == (64, 64, 3) and a.dtype == np.float32 and 0.0 <= a.min() and a.max() <= 1.0, kind
        assert np.array_equal(a, wall_texture(kind, 3, (0.8, 0.75, 0.7), size=64)), kind  # seeded
        if kind != "plaster":  # a pattern, not a plain wall: some texels differ from the ground by a visible step
            assert (np.abs(a - np.median(a.reshape(-1, 3), 0)).max(-1) > 0.05).mean() > 0.02, kind
    with pytest.raises(ValueError, match="unknown wall pattern"):
        wall_texture("tartan", 0, (0.5, 0.5, 0.5))
    # 0 draws nothing: every seed's room (and so the cached validation galleries' hashes) stays as it was
    for seed in (0, 5, 1000000):
        assert pg.random_gallery(seed, wall_patterns=0.0) == pg.random_gallery(seed)
    import hashlib
    from dataclasses import asdict, replace

    opts = asdict(replace(rg.PROFILES["prior"], progress=True, variant=None))
    del opts["wall_patterns"]  # the hash as it was computed before the option existed
    old = json.dumps({"generator": pg.GENERATOR_VERSION, "config": pg.random_gallery(3).to_dict(), "options": opts}, sort_keys=True)
    assert galleries.config_hash(3, "prior") == hashlib.sha256(old.encode()).hexdigest()[:16]
    assert galleries.config_hash(7, "walls") != galleries.config_hash(7, "prior")
    papered = 0
    for seed in range(30):
        cfg = pg.random_gallery(seed, wall_patterns=1.0)
        pg.check_config(cfg)
        base = pg.random_gallery(seed)
        assert cfg.paintings == base.paintings and cfg.lighting == base.lighting  # only the walls change
        walls = [m for m in cfg.room.wall_materials if m.texture == "wall"]
        assert walls, seed  # p = 1: every room is papered (all four walls or one accent wall)
        papered += len(walls) == 4
        for m, wall in zip(cfg.room.wall_materials, cfg.room.walls):
            if m.texture != "wall":
                continue
            length = np.ptp(cfg.room.x) if wall in ("north", "south") else np.ptp(cfg.room.y)
            assert m.texture_args[0] in WALL_PATTERNS and 0.3 <= length / m.uv_scale[0] <= 1.2 + 1e-9  # square tiles of 0.3-1.2 m
    assert 10 <= papered <= 28  # accent walls are the minority
    with pytest.raises(ValueError, match="probability"):
        pg.random_gallery(0, wall_patterns=1.5)


def test_procedural_assets():
    from gallery_assets import canvas_texture, floor_texture, lathe_mesh, vase_profile

    for style in ("strokes", "bands", "blocks", "portrait"):
        img = canvas_texture(3, style, aspect=1.25, width=64)
        assert img.shape == (80, 64, 3) and img.dtype == np.float32 and 0.0 <= img.min() and img.max() <= 1.0
    for kind in ("planks", "stone", "concrete", "carpet"):
        tex = floor_texture(kind, 1, (0.5, 0.4, 0.3), size=64)
        assert tex.shape == (64, 64, 3) and 0.0 < tex.min() and tex.max() <= 1.0
        if kind in ("concrete", "carpet"):  # tileable noise: the wrap-around step is like any neighbour step
            for axis in (0, 1):
                seam = np.abs(np.take(tex, 0, axis) - np.take(tex, -1, axis)).mean()
                assert seam < 1.5 * np.abs(np.diff(tex, axis=axis)).mean() + 1e-3, kind
    verts, faces, normals = lathe_mesh(*vase_profile(np.random.default_rng(0), 0.1, 0.3))
    side = (verts[:, 2] > 0.02) & (verts[:, 2] < 0.28)
    assert (np.sum(normals[side, :2] * verts[side, :2], 1) > 0).mean() > 0.95  # outward
    assert faces.max() < len(verts) and np.linalg.norm(verts[:, :2], axis=1).max() <= 0.1 + 1e-6
