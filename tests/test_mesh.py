"""toolkit.mesh: marching cubes (level rule, slab stitching, memory), TSDF fusion, clean-up, simplification, I/O."""

import math
import tracemalloc

import numpy as np
import pytest
import torch

from conftest import shared
from toolkit._checks import ConfigError, DarsError, ShapeError
from toolkit.mesh import (DepthRenderConfig, Mesh, MeshConfig, SimplifyConfig, TsdfConfig, extract_mesh, fuse_tsdf,
                          load_mesh, mesh_distance, opacity_level, opengl_c2w_to_opencv_w2c, remove_floaters,
                          remove_unseen_faces, render_depth, save_mesh, simplify_mesh)
from toolkit.pinhole import look_at
from toolkit.scene import Cameras, generate_rays

torch.set_num_threads(1)
BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def volsdf_density(sdf, beta):
    """VolSDF density: Laplace CDF of −sdf, divided by β (1/metre). Works on torch tensors and numpy arrays."""
    lib = torch if isinstance(sdf, torch.Tensor) else np
    return lib.where(sdf > 0, 0.5 * lib.exp(-lib.clip(sdf, 0, None) / beta), 1 - 0.5 * lib.exp(lib.clip(sdf, None, 0) / beta)) / beta


def sphere_density(radius=0.5, centre=(0.0, 0.0, 0.0), beta=0.01):
    c = torch.tensor(centre)
    return lambda p: volsdf_density((p - c).norm(dim=-1) - radius, beta)


def edges_shared_twice(mesh: Mesh) -> bool:
    e = np.sort(np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return bool((counts == 2).all())


def make_cameras(c2ws, size=64, focal=60.0, cx=None, cy=None) -> Cameras:
    k = len(c2ws)
    full = lambda v: torch.full((k,), float(v))  # noqa: E731
    return Cameras(torch.tensor(np.stack(c2ws), dtype=torch.float32), full(focal), full(focal),
                   full(size / 2 if cx is None else cx), full(size / 2 if cy is None else cy), full(size), full(size))


def ring_cameras(n=12, dist=2.0, size=64, focal=60.0, centre=(0, 0, 0), cx=None, cy=None) -> Cameras:
    c2ws = []
    for k in range(n):
        a = 2 * math.pi * k / n
        el = 0.5 * math.sin(3 * a)
        eye = np.array(centre) + dist * np.array([math.cos(a) * math.cos(el), math.sin(a) * math.cos(el), math.sin(el)])
        c2ws.append(look_at(eye, centre))
    return make_cameras(c2ws, size, focal, cx, cy)


def sphere_depths(cams: Cameras, radius: float, centre) -> np.ndarray:
    """Analytic depth (metres along the optical axis) of a sphere; 0 where the ray misses."""
    rays = generate_rays(cams)
    o = rays.origins.double().numpy() - np.asarray(centre)
    d = rays.directions.double().numpy()
    b = (o * d).sum(1)
    disc = b * b - ((o * o).sum(1) - radius**2)
    t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), 0.0)
    h, w = int(cams.height[0]), int(cams.width[0])
    return (t * rays.z_scale.double().numpy()).reshape(len(cams), h, w).astype(np.float32)


# ------------------------------------------------------------------------------------------------ level rule
def test_opacity_level_known_values():
    assert opacity_level(0.01) == pytest.approx(math.log(2) / 0.01)
    assert opacity_level(0.02, opacity=0.9) == pytest.approx(-math.log(0.1) / 0.02)
    # a layer of thickness δ at density σ* really has opacity α*
    s = opacity_level(0.005, 0.3)
    assert 1 - math.exp(-s * 0.005) == pytest.approx(0.3)
    with pytest.raises(ConfigError, match="opacity"):
        opacity_level(0.01, opacity=1.0)
    with pytest.raises(ConfigError, match="voxel_size"):
        opacity_level(0.0)


def test_extract_sphere_level_rule_and_orientation():
    """For a VolSDF density the σ* = ln2/δ level set sits at d = β ln(δ / (2β ln 2)) (module docstring)."""
    res, R = 96, 0.5
    delta = 2.0 / res
    beta = 0.5 * delta
    mesh = extract_mesh(sphere_density(R, beta=beta), BOX, MeshConfig(resolution=res, progress=False))
    r = np.linalg.norm(mesh.vertices, axis=1)
    predicted = beta * math.log(delta / (2 * beta * math.log(2)))
    assert 0 < predicted < 0.27 * delta
    assert abs((r.mean() - R) - predicted) < 0.1 * delta  # measured: 0.05 voxel (MC's linear interpolation bias)
    assert np.abs(r - R - predicted).max() < 0.25 * delta
    assert edges_shared_twice(mesh)  # closed 2-manifold
    radial = mesh.vertices / r[:, None]
    assert np.mean(np.sum(mesh.normals * radial, 1)) > 0.99  # outward normals (faces wind CCW from outside)
    v = mesh.vertices[mesh.faces].astype(np.float64)
    signed_volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6
    assert signed_volume == pytest.approx(4 / 3 * math.pi * (R + predicted) ** 3, rel=0.02)
    # the level is scale-aware: the same scene in millimetres gives the same surface (×1000)
    mm = extract_mesh(lambda p: sphere_density(R, beta=beta)(p / 1000.0) / 1000.0, BOX * 1000,
                      MeshConfig(resolution=res, progress=False))
    assert mm.num_faces == mesh.num_faces
    assert np.abs(mm.vertices / 1000.0 - mesh.vertices).max() < 1e-5


def test_level_from_rays_keeps_a_soft_object_and_caps_a_sharp_one():
    """A soft ball (σ = 8 /m inside r = 0.5: opaque to the cameras, but below ln 2/δ = 34.7 /m at δ = 2 cm) vanishes
    under the opacity rule and is recovered at the rays' level; a sharp ball keeps the opacity rule (the cap)."""
    from toolkit.mesh import level_from_rays, opacity_level

    res, R = 100, 0.5
    voxel = 2.0 / res
    soft = lambda p: 8.0 * torch.sigmoid((R - torch.as_tensor(p).norm(dim=-1)) / 0.005)  # noqa: E731
    cams = ring_cameras(n=6, dist=2.5)
    level, rep = level_from_rays(soft, cams, BOX, voxel, n_rays=2048)
    assert level == pytest.approx(8.0, rel=0.02) and rep["cap"] == pytest.approx(opacity_level(voxel))
    assert 0 < rep["rays_opaque"] < rep["rays"]                      # some rays miss the ball
    assert extract_mesh(soft, BOX, MeshConfig(resolution=res, progress=False)).num_faces == 0
    mesh = extract_mesh(soft, BOX, MeshConfig(resolution=res, level=level, progress=False))
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert R - 1.5 * voxel < r.mean() < R  # the level is near the ramp's top: ~4.5 ramp widths (2.3 cm) inside
    sharp = sphere_density(R, beta=0.002)
    level, rep = level_from_rays(sharp, cams, BOX, voxel, n_rays=1024)
    assert level == rep["cap"] == pytest.approx(opacity_level(voxel))
    empty, rep = level_from_rays(lambda p: torch.zeros(len(p)), cams, BOX, voxel, n_rays=256)
    assert empty == rep["cap"] and rep["rays_opaque"] == 0
    with pytest.raises(ValueError, match="quantile"):
        level_from_rays(soft, cams, BOX, voxel, quantile=0.0)


def test_extract_chunked_equals_unchunked():
    box = np.array([[-0.9, -0.6, -0.5], [0.8, 0.7, 0.6]])  # anisotropic box, sphere cut by slab planes
    fn = sphere_density(0.45, centre=(0.07, -0.03, 0.02), beta=0.02)
    full = extract_mesh(fn, box, MeshConfig(resolution=64, chunk=4096, progress=False))
    for chunk in (1, 5, 16):
        part = extract_mesh(fn, box, MeshConfig(resolution=64, chunk=chunk, batch=777, progress=False))
        assert (part.num_vertices, part.num_faces) == (full.num_vertices, full.num_faces)
        a = full.vertices[np.lexsort(full.vertices.T)]
        b = part.vertices[np.lexsort(part.vertices.T)]
        assert np.abs(a - b).max() < 1e-6
        assert edges_shared_twice(part)  # seams stitched: still closed
    assert mesh_distance(part, full, samples=5000).max < 1e-6


def test_extract_memory_is_bounded_by_the_slab():
    """Peak numpy allocation with thin slabs ~ one slab + a few copies of the output mesh, never the whole grid
    (tracemalloc sees numpy buffers; the density callable below is numpy so its temporaries count too)."""
    res, chunk = 160, 8
    beta = 0.5 * 2.0 / res
    grid_bytes = (res + 1) ** 3 * 4
    slab_bytes = (chunk + 1) * (res + 1) ** 2 * 4

    def fn(p):
        return volsdf_density(np.linalg.norm(p.numpy(), axis=1) - 0.6, beta).astype(np.float32)

    peaks, meshes = {}, {}
    for c in (chunk, 4096):
        tracemalloc.start()
        meshes[c] = extract_mesh(fn, BOX, MeshConfig(resolution=res, chunk=c, batch=1 << 14, compute_normals=False,
                                                     progress=False))
        peaks[c] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    mesh_bytes = meshes[chunk].vertices.nbytes + meshes[chunk].faces.nbytes
    assert peaks[4096] > grid_bytes  # the unchunked run holds the whole grid
    assert peaks[chunk] < 2 * slab_bytes + 4 * mesh_bytes, (peaks, slab_bytes, mesh_bytes)  # measured 10.8 < 12.4 MB
    assert peaks[chunk] < 0.5 * peaks[4096]


def test_extract_level_override_empty_and_errors():
    fn = sphere_density(0.5, beta=0.05)  # max density 1/β = 20 /m
    empty = extract_mesh(fn, BOX, MeshConfig(resolution=32, level=100.0, progress=False))
    assert empty.num_faces == 0 and empty.num_vertices == 0
    # a voxel of 2/32 m needs σ* = 11.1 /m: the surface exists; with a thinner voxel (finer grid) it needs more
    assert extract_mesh(fn, BOX, MeshConfig(resolution=32, progress=False)).num_faces > 0
    assert extract_mesh(fn, BOX, MeshConfig(resolution=256, opacity_thickness=2 / 32, chunk=64, progress=False)).num_faces > 0
    lvl = extract_mesh(fn, BOX, MeshConfig(resolution=32, level=10.0, progress=False))  # σ = 10 = 0.5/β: d = 0
    assert np.linalg.norm(lvl.vertices, axis=1).mean() == pytest.approx(0.5, abs=0.01)
    with pytest.raises(ConfigError, match="resolution"):
        extract_mesh(fn, BOX, MeshConfig(resolution=1))
    with pytest.raises(DarsError, match="aabb"):
        extract_mesh(fn, np.array([[0, 0, 0], [1, -1, 1.0]]), MeshConfig(resolution=8, progress=False))
    with pytest.raises(ShapeError, match="density_fn returned shape"):
        extract_mesh(lambda p: torch.zeros(p.shape[0], 2), BOX, MeshConfig(resolution=8, progress=False))


def bunny_density(gt: Mesh, beta: float):
    """VolSDF density of the bunny: exact distance near the surface (Open3D BVH), inside/outside by ray parity,
    saturated beyond 5β (where the density is within 0.3 % of 0 or 1/β anyway)."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    from toolkit.mesh import sample_surface

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(gt.vertices), o3d.core.Tensor(gt.faces.astype(np.uint32)))
    tree = cKDTree(sample_surface(gt, 200_000))  # dense samples: a cheap "is it near the surface" test
    band = 5 * beta
    gap = 2e-3  # ≥ the largest hole between samples (hole-filling triangles are long)

    def fn(p):
        p = p.numpy()
        inside = scene.compute_occupancy(o3d.core.Tensor(p), nsamples=3).numpy() > 0.5
        dist = np.full(p.shape[0], band, np.float32)
        near = np.isfinite(tree.query(p, distance_upper_bound=band + gap)[0])
        if near.any():
            dist[near] = np.minimum(scene.compute_distance(o3d.core.Tensor(p[near])).numpy(), band)
        return volsdf_density(np.where(inside, -dist, dist), beta)

    return fn


def test_extract_bunny_chamfer():
    """Stanford bunny (holes in its base closed with pymeshlab) → VolSDF density → marching cubes at 96 cells.

    Bound: Chamfer < 0.35 % of the bbox diagonal (measured 0.18 %; the voxel is 0.71 % of the diagonal and the
    level rule puts the surface ~0.2 voxel outside), Hausdorff < 1.5 % (measured ~1 voxel) after floater removal.
    """
    import pymeshlab

    raw = load_mesh(shared("meshes", "stanford_bunny", "bun_zipper.ply"))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(raw.vertices.astype(np.float64), raw.faces.astype(np.int32)))
    ms.meshing_close_holes(maxholesize=200)
    gt = Mesh(ms.current_mesh().vertex_matrix().astype(np.float32), ms.current_mesh().face_matrix().astype(np.int64))
    b = gt.bounds
    box = np.stack([b[0] - 0.05 * (b[1] - b[0]).max(), b[1] + 0.05 * (b[1] - b[0]).max()])
    res = 96
    delta = (box[1] - box[0]).max() / res
    mesh = extract_mesh(bunny_density(gt, 0.5 * delta), box, MeshConfig(resolution=res, progress=False))
    mesh = remove_floaters(mesh, min_fraction=0.01)  # parity-sign errors below the base leave a few specks
    d = mesh_distance(mesh, gt, samples=40_000)
    print(f"bunny: chamfer {d.mean_fraction:.4%} hausdorff {d.max_fraction:.4%} of diagonal; voxel {delta / gt.diagonal:.4%}")
    assert d.mean_fraction < 0.0035
    assert d.max_fraction < 0.015


# ------------------------------------------------------------------------------------------------ depth + TSDF
def test_opengl_to_opencv_extrinsic():
    c2w = look_at([0.0, -3.0, 0.5], [0.0, 0.0, 0.5])
    w2c = opengl_c2w_to_opencv_w2c(c2w)
    p = w2c @ np.array([0.0, 0.0, 0.5, 1.0])  # the target: straight ahead, 3 m
    assert np.allclose(p[:3], [0, 0, 3.0])
    up = w2c @ np.array([0.0, 0.0, 1.5, 1.0])  # world up is image up: OpenCV y is negative
    assert up[1] < 0 and up[2] == pytest.approx(3.0)
    right = w2c @ np.array([1.0, 0.0, 0.5, 1.0])  # camera at −y looking +y: world +x is image right
    assert right[0] > 0


def test_tsdf_fusion_recovers_sphere_radius():
    R, centre, vox = 0.6, (0.1, -0.05, 0.02), 0.03
    cams = ring_cameras(n=10, size=64, focal=55.0, centre=centre, cx=35.0, cy=29.0)  # off-centre principal point
    depths = sphere_depths(cams, R, centre)
    colours = torch.zeros(len(cams), 3, 64, 64)
    colours[:, 0] = 1.0  # red
    mesh = fuse_tsdf(depths, cams, colours, TsdfConfig(voxel_size=vox, progress=False))
    r = np.linalg.norm(mesh.vertices - np.array(centre), axis=1)
    print(f"tsdf: mean radius error {abs(r.mean() - R) / vox:.3f} voxel, max {np.abs(r - R).max() / vox:.3f} voxel")
    assert abs(r.mean() - R) < 0.25 * vox  # measured 0.05 voxel
    assert np.abs(r - R).max() < vox  # within a voxel everywhere
    assert np.mean(np.sum(mesh.normals * (mesh.vertices - np.array(centre)) / r[:, None], 1)) > 0.95
    assert np.allclose(mesh.colors.mean(0), [1, 0, 0], atol=0.02)
    # a half-pixel principal-point error would show: shifting cx by 1 px moves the surface sideways
    with pytest.raises(ShapeError, match="cameras"):
        fuse_tsdf(depths[:3], cams, cfg=TsdfConfig(voxel_size=vox, progress=False))
    with pytest.raises(ShapeError, match="colours"):
        fuse_tsdf(depths, cams, colours[:, :, :10], TsdfConfig(voxel_size=vox, progress=False))


def test_render_depth_matches_analytic_sphere():
    R, centre = 0.5, (0.0, 0.1, -0.05)
    cams = ring_cameras(n=2, size=48, focal=45.0, centre=centre)
    fn = sphere_density(R, centre=centre, beta=0.002)
    depth = render_depth(fn, cams, BOX, DepthRenderConfig(samples=192, progress=False))
    ref = sphere_depths(cams, R, centre)
    both = (depth > 0) & (ref > 0)
    assert both.sum() > 0.9 * (ref > 0).sum()
    step = float(np.linalg.norm(BOX[1] - BOX[0])) / 192
    assert np.median(np.abs(depth[both] - ref[both])) < 0.5 * step
    assert np.abs(depth[both] - ref[both]).max() < 3 * step
    # and the depth maps fuse back to the sphere
    mesh = fuse_tsdf(depth, cams, cfg=TsdfConfig(voxel_size=0.03, progress=False))
    assert mesh.num_faces > 0


def test_render_depth_translucent_ray_gives_its_median_depth():
    """A ray that gathers opacity 0.3 (a translucent ball, uniform σ) measures where it has gathered half of that
    (α = 0.15) when ``min_opacity`` allows it, and nothing when ``min_opacity`` asks for more."""
    R, alpha = 0.4, 0.3
    sigma0 = -math.log1p(-alpha) / (2 * R)  # through the centre: opacity 0.3
    fn = lambda p: torch.where(p.norm(dim=-1) < R, sigma0, 0.0)  # noqa: E731
    cams = ring_cameras(n=2, size=33, focal=30.0)  # odd size: the centre pixel's ray passes through the centre
    depth = render_depth(fn, cams, BOX, DepthRenderConfig(samples=400, min_opacity=0.2, progress=False))
    expected = 2.0 - R + -math.log1p(-alpha / 2) / sigma0  # distance to the ball, then until α = 0.15
    assert depth[:, 16, 16] == pytest.approx([expected] * 2, abs=0.01)
    assert (depth[:, 0, 0] == 0).all()  # a ray that misses the ball
    none = render_depth(fn, cams, BOX, DepthRenderConfig(samples=400, min_opacity=0.5, progress=False))
    assert (none == 0).all()
    with pytest.raises(ConfigError, match="min_opacity"):
        render_depth(fn, cams, BOX, DepthRenderConfig(min_opacity=1.0, progress=False))


# ------------------------------------------------------------------------------------------------ clean-up
def two_spheres() -> Mesh:
    big = extract_mesh(sphere_density(0.5, beta=0.02), BOX, MeshConfig(resolution=48, progress=False))
    small = extract_mesh(sphere_density(0.1, centre=(0.8, 0.8, 0.8), beta=0.02), BOX, MeshConfig(resolution=48, progress=False))
    return Mesh(np.concatenate([big.vertices, small.vertices]), np.concatenate([big.faces, small.faces + big.num_vertices]),
                labels=np.concatenate([np.zeros(big.num_vertices, np.uint8), np.ones(small.num_vertices, np.uint8)]))


def test_remove_floaters():
    mesh = two_spheres()
    kept = remove_floaters(mesh)  # default: components < 5 % of the largest go
    assert kept.labels is not None and (kept.labels == 0).all()
    assert kept.num_faces == int((mesh.labels[mesh.faces[:, 0]] == 0).sum())
    assert remove_floaters(mesh, min_faces=1).num_faces == mesh.num_faces
    assert remove_floaters(mesh, min_faces=10**9).num_faces == 0
    with pytest.raises(ConfigError, match="min_fraction"):
        remove_floaters(mesh, min_fraction=2.0)


def test_a_small_component_the_photos_see_is_not_a_floater():
    """A room's painting whose wall stayed fog is a separate component of a few percent of the floor's faces:
    size alone drops it, the training rays' surface points keep it; points elsewhere, or too few, do not."""
    mesh = two_spheres()
    small = mesh.labels[mesh.faces[:, 0]] == 1
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    on_small = np.array([0.8, 0.8, 0.8]) + 0.1 * d / np.linalg.norm(d, axis=1, keepdims=True)
    on_big = 0.5 * d / np.linalg.norm(d, axis=1, keepdims=True)
    seen = np.concatenate([on_big, on_small[:40]])  # 40 of 440 points (9 %) lie on the small sphere
    assert small.sum() < 0.05 * (~small).sum()  # the size test alone drops it
    kept = remove_floaters(mesh, seen_points=seen, radius=0.05)
    assert kept.num_faces == mesh.num_faces
    assert remove_floaters(mesh, seen_points=seen, radius=0.05, min_seen=0.2).num_faces == int((~small).sum())
    assert remove_floaters(mesh, seen_points=on_big, radius=0.05).num_faces == int((~small).sum())  # unseen
    far = on_small[:40] + np.array([0.0, 0.0, 0.5])  # seen points off the sphere by more than the radius
    assert remove_floaters(mesh, seen_points=np.concatenate([on_big, far]), radius=0.05).num_faces == int((~small).sum())
    with pytest.raises(ConfigError, match="min_seen"):
        remove_floaters(mesh, seen_points=seen, radius=0.05, min_seen=1.5)
    with pytest.raises(ConfigError, match="positive radius"):
        remove_floaters(mesh, seen_points=seen)


def test_build_mesh_keeps_a_small_object_the_cameras_look_at():
    """End to end through toolkit.asset.build_mesh: a small sphere (< 5 % of the big one's faces) that four of
    sixteen cameras see from close is kept by default and dropped when size alone decides (min_seen 1)."""
    from toolkit.asset import AssetConfig, build_mesh
    from toolkit.train import FieldCallables

    big, small_c = sphere_density(0.5), (0.0, 0.0, 0.8)
    small = sphere_density(0.08, centre=small_c)
    density = lambda p: torch.maximum(big(p), small(p))  # noqa: E731
    close = [look_at(np.array(small_c) + 0.4 * np.array(v), small_c) for v in ((1, 0, 0.3), (0, 1, 0.3), (-1, 0, 0.3), (0, -1, 0.3))]
    ring = ring_cameras(12, dist=2.0)
    cams = make_cameras(list(ring.c2w.numpy()) + close)
    def material(p, normals=None):
        n = p.shape[0]
        return {"albedo": torch.full((n, 3), 0.5), "roughness": torch.full((n,), 0.5), "metallic": torch.zeros(n),
                "normal": torch.nn.functional.normalize(p, dim=-1), "semantic": torch.zeros(n, dtype=torch.long)}

    f = FieldCallables(density, material, torch.tensor([[-1.0] * 3, [1.0] * 3]), None, cams)
    on_small = lambda m: int((np.linalg.norm(m.vertices - np.array(small_c), axis=1) < 0.15).sum())  # noqa: E731
    kept, st = build_mesh(f, AssetConfig(resolution=48, faces=0, level=20.0))
    dropped, _ = build_mesh(f, AssetConfig(resolution=48, faces=0, level=20.0, min_seen=1.0))
    assert on_small(kept) > 0 and on_small(dropped) == 0
    assert st["floaters"]["seen_points"] > 500 and st["floaters"]["min_seen"] == 0.005


def test_remove_unseen_faces():
    mesh = extract_mesh(sphere_density(0.5, beta=0.02), BOX, MeshConfig(resolution=40, progress=False))
    cams = make_cameras([look_at([0.0, -3.0, 0.0], [0.0, 0.0, 0.0])], size=64, focal=80.0)
    # without depths: everything projecting into the image counts as seen (the sphere fits in the view)
    assert remove_unseen_faces(mesh, cams).num_faces == mesh.num_faces
    # with depths: the back half is occluded
    depths = sphere_depths(cams, 0.5, (0, 0, 0))
    front = remove_unseen_faces(mesh, cams, depths, depth_tolerance=0.02)
    assert 0.3 * mesh.num_faces < front.num_faces < 0.6 * mesh.num_faces
    assert front.vertices[:, 1].max() < 0.2  # camera at −y sees y < 0 (plus the silhouette rim)
    # a camera looking away sees nothing
    away = make_cameras([look_at([0.0, -3.0, 0.0], [0.0, -6.0, 0.0])])
    assert remove_unseen_faces(mesh, away).num_faces == 0


# ------------------------------------------------------------------------------------------------ simplification
@pytest.fixture(scope="module")
def dense_sphere() -> Mesh:
    return extract_mesh(sphere_density(0.5, beta=0.01), BOX, MeshConfig(resolution=96, progress=False))


@pytest.mark.parametrize("method", ["fast", "quality"])
def test_simplify_hits_target_and_reports_error(dense_sphere, method):
    target = 4000
    out, rep = simplify_mesh(dense_sphere, target, method=method, cfg=SimplifyConfig(error_samples=20_000))
    assert abs(out.num_faces - target) <= 0.02 * target, out.num_faces
    assert rep.faces_in == dense_sphere.num_faces and rep.faces_out == out.num_faces and rep.target_faces == target
    e = rep.error
    assert 0 < e.mean <= e.max and e.max_fraction == pytest.approx(e.max / e.diagonal)
    assert e.mean_fraction < 0.002 and e.max_fraction < 0.01  # a sphere at 4k faces is still a sphere
    assert edges_shared_twice(out)
    assert out.normals.shape == out.vertices.shape
    ratio_out, _ = simplify_mesh(dense_sphere, ratio=0.1, method=method, cfg=SimplifyConfig(error_samples=0))
    assert abs(ratio_out.num_faces - 0.1 * dense_sphere.num_faces) <= 0.02 * 0.1 * dense_sphere.num_faces


def test_simplify_quality_preserves_boundary():
    """Open hemisphere: with boundary preservation the rim stays on the original circle."""
    full = extract_mesh(sphere_density(0.5, beta=0.01), BOX, MeshConfig(resolution=80, progress=False))
    cen = full.vertices[full.faces].mean(1)
    half = full.submesh(cen[:, 2] > 0.0)

    def rim(mesh):
        e = np.sort(np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]]), axis=1)
        u, c = np.unique(e, axis=0, return_counts=True)
        return np.unique(u[c == 1])

    z_rim = half.vertices[rim(half), 2].max()
    out, rep = simplify_mesh(half, 2000, method="quality", cfg=SimplifyConfig(preserve_boundary=True, error_samples=5000))
    rim_out = out.vertices[rim(out)]
    assert len(rim_out) > 0.9 * len(rim(half))  # the rim keeps its vertices ...
    assert rim_out[:, 2].max() <= z_rim + 1e-6  # ... in place
    loose, _ = simplify_mesh(half, 2000, method="quality", cfg=SimplifyConfig(preserve_boundary=False, error_samples=0))
    assert len(rim(loose)) < 0.7 * len(rim(half))  # without it the rim is decimated too
    fast, _ = simplify_mesh(half, 2000, method="fast", cfg=SimplifyConfig(preserve_boundary=True, error_samples=0))
    assert len(rim(fast)) >= len(rim(half))


def test_simplify_errors(dense_sphere):
    with pytest.raises(ConfigError, match="exactly one"):
        simplify_mesh(dense_sphere)
    with pytest.raises(ConfigError, match="exactly one"):
        simplify_mesh(dense_sphere, 100, ratio=0.5)
    with pytest.raises(ConfigError, match="method"):
        simplify_mesh(dense_sphere, 100, method="best")
    with pytest.raises(ConfigError, match="ratio"):
        simplify_mesh(dense_sphere, ratio=1.5)
    same, rep = simplify_mesh(dense_sphere, 10**9, cfg=SimplifyConfig(error_samples=100))
    assert same.num_faces == dense_sphere.num_faces and rep.error.max < 1e-6


# ------------------------------------------------------------------------------------------------ I/O
def test_save_load_roundtrip(tmp_path):
    mesh = two_spheres()
    mesh = Mesh(mesh.vertices, mesh.faces, colors=np.tile(np.array([[0.2, 0.4, 0.8]], np.float32), (mesh.num_vertices, 1)),
                labels=mesh.labels)
    save_mesh(mesh, tmp_path / "m.ply")
    back = load_mesh(tmp_path / "m.ply")
    assert np.array_equal(back.faces, mesh.faces) and np.allclose(back.vertices, mesh.vertices)
    assert np.allclose(back.colors, mesh.colors, atol=1 / 255) and np.array_equal(back.labels, mesh.labels)
    save_mesh(mesh, tmp_path / "m.obj")
    obj = load_mesh(tmp_path / "m.obj")
    assert obj.num_faces == mesh.num_faces and np.allclose(np.sort(obj.vertices, 0), np.sort(mesh.vertices, 0), atol=1e-6)
    with pytest.raises(ConfigError, match=r"\.ply or \.obj"):
        save_mesh(mesh, tmp_path / "m.stl")
    with pytest.raises(DarsError, match="not found"):
        load_mesh(tmp_path / "missing.ply")
