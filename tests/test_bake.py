"""toolkit.bake: rasteriser, UV atlas, tangent frames, PBR baking (spot round trip), fill, AO, labels."""

import math
import warnings

import numpy as np
import pytest
import torch

from conftest import shared
from toolkit._checks import ConfigError, ShapeError
from toolkit.bake import (BakeConfig, UnwrapConfig, UVMesh, bake_pbr_textures, chart_consistent_normals,
                          compute_tangents, fill_background, label_faces, rasterize_triangles, sample_texture,
                          unwrap_uv)
from toolkit.io import linear_to_srgb, read_image, srgb_to_linear
from toolkit.mesh import Mesh, MeshConfig, extract_mesh
from toolkit.pinhole import look_at
from toolkit.scene import Cameras, project_points

torch.set_num_threads(1)
# tests that leave material keys out on purpose; test_bake_defaults_supersample_and_errors checks the warning itself
pytestmark = pytest.mark.filterwarnings("ignore:bake_pbr_textures. material_fn provided no:UserWarning")


def sphere_mesh(res=32) -> Mesh:
    fn = lambda p: 1e3 * torch.sigmoid((0.5 - p.norm(dim=-1)) * 60)  # noqa: E731
    return extract_mesh(fn, np.array([[-1.0] * 3, [1.0] * 3]), MeshConfig(resolution=res, progress=False))


def psnr(a, b) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def decode_normal_map(nmap_u8: np.ndarray) -> np.ndarray:
    return nmap_u8.astype(np.float64) / 255.0 * 2.0 - 1.0


def texel_lookup(uvmesh: UVMesh, size: int):
    """Per covered texel: face id and barycentrics of the texel centre (the same rasterisation a GPU does)."""
    fid, bary = rasterize_triangles(uvmesh.uvs.astype(np.float64) * size, uvmesh.faces, size, size)
    cov = fid >= 0
    return cov, fid[cov], bary[cov].astype(np.float64)


# ------------------------------------------------------------------------------------------------ rasteriser
def test_rasterize_square_and_depth_test():
    xy = np.array([[2.0, 1.0], [10.0, 1.0], [10.0, 7.0], [2.0, 7.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    fid, bary = rasterize_triangles(xy, faces, 9, 12)
    cov = fid >= 0
    expected = np.zeros((9, 12), bool)
    expected[1:7, 2:10] = True  # pixel centres (c + .5, r + .5) inside [2, 10] x [1, 7]
    assert np.array_equal(cov, expected)
    assert np.allclose(bary[cov].sum(1), 1.0, atol=1e-6)
    # interpolating x with the barycentrics gives the pixel centre back
    x = np.einsum("nk,nk->n", bary[cov], xy[faces[fid[cov]], 0])
    assert np.allclose(x, (np.nonzero(cov)[1] + 0.5), atol=1e-5)
    # depth test: a nearer triangle over the same pixels wins regardless of order
    xy2 = np.concatenate([xy, xy])
    faces2 = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    depth = np.array([2.0] * 4 + [1.0] * 4)
    fid2, _ = rasterize_triangles(xy2, faces2, 9, 12, depth=depth, max_candidates=7)  # tiny batches too
    assert set(np.unique(fid2[cov])) == {2, 3}
    fid3, _ = rasterize_triangles(xy2, faces2, 9, 12, depth=depth[::-1].copy())
    assert set(np.unique(fid3[cov])) == {0, 1}


def test_sample_texture_gltf_convention():
    img = np.zeros((2, 4, 1), np.float32)
    img[0, :, 0] = 1.0  # top row
    # uv (·, 0.25) is the centre of row 0 (top): glTF's v points down
    assert sample_texture(img, np.array([[0.5, 0.25]]))[0, 0] == pytest.approx(1.0)
    assert sample_texture(img, np.array([[0.5, 0.75]]))[0, 0] == pytest.approx(0.0)
    assert sample_texture(img, np.array([[0.5, 0.5]]))[0, 0] == pytest.approx(0.5)


# ------------------------------------------------------------------------------------------------ unwrap + tangents
@pytest.mark.parametrize("pieces", [None, 150])  # one mesh, or cut into spatial pieces of <= 150 faces
def test_unwrap_uv_atlas_properties(pieces):
    mesh = sphere_mesh()
    mesh = Mesh(mesh.vertices, mesh.faces, mesh.normals, labels=(mesh.vertices[:, 2] > 0).astype(np.uint8) * 5)
    uvm = unwrap_uv(mesh, UnwrapConfig(texture_size=256, max_piece_faces=pieces))
    assert uvm.num_faces == mesh.num_faces and uvm.num_vertices >= mesh.num_vertices
    assert np.array_equal(uvm.vertices[uvm.faces], mesh.vertices[mesh.faces])  # every face kept, in its order
    if pieces:
        with pytest.raises(ConfigError, match="max_piece_faces=0"):
            unwrap_uv(mesh, UnwrapConfig(max_piece_faces=0))
    assert uvm.uvs.min() >= 0 and uvm.uvs.max() <= 1
    assert np.array_equal(uvm.vertices, mesh.vertices[uvm.vmapping])  # split vertices keep their source
    assert np.array_equal(uvm.normals, mesh.normals[uvm.vmapping])  # normals continuous across seams (none folds)
    assert set(np.unique(uvm.face_labels)) == {0, 5}
    # charts do not overlap: rasterised coverage equals the summed UV area of the triangles
    size = 256
    uv = uvm.uvs.astype(np.float64)[uvm.faces]
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum() * size * size
    cov, _, _ = texel_lookup(uvm, size)
    assert cov.sum() == pytest.approx(area, rel=0.03)
    assert 0.3 < cov.mean() < 0.95
    # tangents: unit, perpendicular to the normal, w = ±1
    t = uvm.tangents
    assert np.allclose(np.linalg.norm(t[:, :3], axis=1), 1, atol=1e-5)
    assert np.abs(np.sum(t[:, :3] * uvm.normals, 1)).max() < 1e-4
    assert set(np.unique(t[:, 3])) <= {-1.0, 1.0}


def test_compute_tangents_known_frames_and_handedness():
    """Plane z = 0 facing +z; glTF v grows downward = −y: T = +x, bitangent = +y, w = +1. Mirrored u: w = −1."""
    p = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    n = np.tile([0.0, 0.0, 1.0], (4, 1))
    uv = np.stack([p[:, 0], 1 - p[:, 1]], 1)
    t = compute_tangents(p, f, uv, n)
    assert np.allclose(t, [[1, 0, 0, 1]] * 4, atol=1e-6)
    b = np.cross(n, t[:, :3]) * t[:, 3:]
    assert np.allclose(b, [[0, 1, 0]] * 4)  # +y = "up" in the image = green
    mirrored = compute_tangents(p, f, np.stack([1 - p[:, 0], 1 - p[:, 1]], 1), n)
    assert np.allclose(mirrored, [[-1, 0, 0, -1]] * 4, atol=1e-6)
    assert np.allclose(np.cross(n, mirrored[:, :3]) * mirrored[:, 3:], [[0, 1, 0]] * 4)


# ------------------------------------------------------------------------------------------------ normal maps
@pytest.fixture(scope="module")
def sphere_uv() -> UVMesh:
    return unwrap_uv(sphere_mesh(), UnwrapConfig(texture_size=128))


def test_normal_map_flat_when_field_normal_is_geometric(sphere_uv):
    tex = bake_pbr_textures(sphere_uv, lambda p, n: {"normal": n, "albedo": torch.full_like(p, 0.25)},
                            BakeConfig(size=128, progress=False))
    nm = tex.normal[tex.mask].astype(np.float64)
    assert np.abs(nm - [127.5, 127.5, 255]).max() <= 1.0  # (0.5, 0.5, 1) to 8-bit rounding
    # the fill gives flat normals outside the charts too
    assert np.abs(tex.normal[~tex.mask].astype(np.float64) - [127.5, 127.5, 255]).max() <= 1.0
    assert tex.defaults == ("metallic", "roughness")


def test_normal_map_decodes_rotated_field_normal(sphere_uv):
    """The field normal is the geometric normal tilted 25° about a fixed world axis; decoding the map with the
    interpolated vertex frame (what a glTF renderer does with NORMAL + TANGENT) gives it back."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    ang = math.radians(25)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = torch.tensor(np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K, dtype=torch.float32)

    def field_normal(p):
        return (p / p.norm(dim=-1, keepdim=True)) @ rot.T

    size = 128
    tex = bake_pbr_textures(sphere_uv, lambda p, n: {"normal": field_normal(p)}, BakeConfig(size=size, progress=False))
    cov, fid, bary = texel_lookup(sphere_uv, size)
    f = sphere_uv.faces[fid]
    pos = np.einsum("nk,nkc->nc", bary, sphere_uv.vertices[f].astype(np.float64))
    n = np.einsum("nk,nkc->nc", bary, sphere_uv.normals[f].astype(np.float64))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = np.einsum("nk,nkc->nc", bary, sphere_uv.tangents[f, :3].astype(np.float64))
    t -= n * np.sum(n * t, 1, keepdims=True)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t) * sphere_uv.tangents[f[:, 0], 3:4]
    c = decode_normal_map(tex.normal[cov])
    decoded = c[:, :1] * t + c[:, 1:2] * b + c[:, 2:3] * n
    decoded /= np.linalg.norm(decoded, axis=1, keepdims=True)
    expected = field_normal(torch.tensor(pos, dtype=torch.float32)).double().numpy()
    err = np.degrees(np.arccos(np.clip(np.sum(decoded * expected, 1), -1, 1)))
    assert np.median(err) < 0.5 and np.percentile(err, 99) < 1.5, (np.median(err), err.max())  # 8-bit quantisation
    # a wrong convention (green flipped, as DirectX maps) would be far off
    wrong = c[:, :1] * t - c[:, 1:2] * b + c[:, 2:3] * n
    wrong /= np.linalg.norm(wrong, axis=1, keepdims=True)
    assert np.median(np.degrees(np.arccos(np.clip(np.sum(wrong * expected, 1), -1, 1)))) > 5


# ------------------------------------------------------------------------------------------------ spot round trip
def render_unlit(vertices, faces, uvs, texture, c2w, size=256, focal=300.0):
    """Flat unlit rendering of a textured mesh (numpy rasteriser, z-buffer, perspective-correct UVs)."""
    t = lambda x: torch.tensor([x], dtype=torch.float64)  # noqa: E731
    cams = Cameras(torch.tensor(c2w[None]), t(focal), t(focal), t(size / 2), t(size / 2), t(size), t(size))
    pix, z = project_points(cams, 0, torch.from_numpy(np.asarray(vertices, np.float64)))
    pix, z = pix.numpy(), z.numpy()
    fid, bary = rasterize_triangles(pix, faces, size, size, depth=z)
    cov = fid >= 0
    b = bary[cov].astype(np.float64) / z[faces[fid[cov]]]
    b /= b.sum(1, keepdims=True)
    uv = np.einsum("nk,nkc->nc", b, np.asarray(uvs, np.float64)[faces[fid[cov]]])
    img = np.zeros((size, size, 3), np.float32)
    img[cov] = sample_texture(texture, uv)[:, :3]
    return img, cov


@pytest.fixture(scope="module")
def spot():
    import trimesh

    tm = trimesh.load(shared("meshes", "spot", "spot.obj"), process=False)
    uv_obj = np.asarray(tm.visual.uv, np.float64)
    return {
        "vertices": np.asarray(tm.vertices, np.float32),
        "faces": np.asarray(tm.faces, np.int64),
        "uvs": np.stack([uv_obj[:, 0], 1 - uv_obj[:, 1]], 1),  # OBJ (v up) -> glTF (v down)
        "texture": read_image(shared("meshes", "spot", "spot_texture.png")),  # sRGB float
    }


def test_spot_bake_round_trip_psnr(spot):
    """Re-unwrap spot with xatlas, bake its albedo texture through a closest-point material_fn, render both.

    Requirement: PSNR ≥ 30 dB on every view (measured ≈ 45-54 dB at 1024²). Control: the same bake rendered with
    the v axis flipped (the classic GL/glTF mistake) must fail the bound.
    """
    import open3d as o3d

    V, F, UV, tex = spot["vertices"], spot["faces"], spot["uvs"], spot["texture"]
    tex_linear = srgb_to_linear(tex)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F.astype(np.uint32)))

    def material_fn(points, normals):
        hit = scene.compute_closest_points(o3d.core.Tensor(points.numpy()))
        fid = hit["primitive_ids"].numpy().astype(np.int64)
        buv = hit["primitive_uvs"].numpy().astype(np.float64)
        bary = np.stack([1 - buv[:, 0] - buv[:, 1], buv[:, 0], buv[:, 1]], 1)
        uv = np.einsum("nk,nkc->nc", bary, UV[F[fid]])
        return {"albedo": torch.from_numpy(sample_texture(tex_linear, uv)), "roughness": torch.full((len(fid),), 0.6),
                "metallic": torch.zeros(len(fid))}

    uvm = unwrap_uv(Mesh(V, F), UnwrapConfig(texture_size=1024))
    baked = bake_pbr_textures(uvm, material_fn, BakeConfig(size=1024, progress=False))
    assert baked.defaults == ("normal",)
    assert np.all(baked.orm[..., 1][baked.mask] == 153) and np.all(baked.orm[..., 0] == 255)  # G = 0.6, R = 1
    ctr = V.mean(0)
    scores, controls = [], []
    for k in range(4):
        a = 2 * math.pi * k / 4 + 0.4
        c2w = look_at(ctr + 2.4 * np.array([math.cos(a), 0.5, math.sin(a)]), ctr, up=(0.0, 1.0, 0.0))  # spot is +y up
        ref, cov_a = render_unlit(V, F, UV, tex, c2w)
        out, cov_b = render_unlit(uvm.vertices, uvm.faces, uvm.uvs, baked.base_color / 255.0, c2w)
        assert (cov_a != cov_b).sum() <= 0.002 * cov_a.sum()  # same geometry
        both = cov_a & cov_b
        scores.append(psnr(ref[both], out[both]))
        flipped = np.stack([uvm.uvs[:, 0], 1 - uvm.uvs[:, 1]], 1)
        wrong, _ = render_unlit(uvm.vertices, uvm.faces, flipped, baked.base_color / 255.0, c2w)
        controls.append(psnr(ref[both], wrong[both]))
    print(f"spot round trip PSNR per view: {[round(s, 1) for s in scores]} dB; v-flipped control: "
          f"{[round(s, 1) for s in controls]} dB")
    assert min(scores) >= 30.0
    assert max(controls) < 25.0


# ------------------------------------------------------------------------------------------------ baking details
def test_bake_defaults_supersample_and_errors(sphere_uv):
    with pytest.warns(UserWarning, match="baked defaults"):
        tex = bake_pbr_textures(sphere_uv, lambda p, n: {}, BakeConfig(size=64, progress=False))
    assert tex.defaults == ("albedo", "metallic", "normal", "roughness")
    srgb_half = round(float(linear_to_srgb(np.array(0.5))) * 255)
    assert np.all(tex.base_color == srgb_half)  # default albedo 0.5, filled everywhere
    assert np.all(tex.orm == [255, 255, 0])  # occlusion 1, roughness 1, metallic 0
    # supersampling: a smooth field gives nearly the same texture, a chart-edge-aware mask, same size
    fn = lambda p, n: {"albedo": (p * 0.5 + 0.5).clamp(0, 1)}  # noqa: E731
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t1 = bake_pbr_textures(sphere_uv, fn, BakeConfig(size=128, progress=False))
        t2 = bake_pbr_textures(sphere_uv, fn, BakeConfig(size=128, supersample=2, progress=False))
    assert t2.base_color.shape == (128, 128, 3) and t2.mask.sum() >= t1.mask.sum()
    both = t1.mask & t2.mask
    assert np.abs(t1.base_color[both].astype(int) - t2.base_color[both]).mean() < 2.0
    with pytest.raises(ConfigError, match="supersample"):
        bake_pbr_textures(sphere_uv, fn, BakeConfig(size=64, supersample=5))
    with pytest.raises(ConfigError, match="fill"):
        bake_pbr_textures(sphere_uv, fn, BakeConfig(size=64, fill="blur"))
    with pytest.raises(ShapeError, match="albedo"):
        bake_pbr_textures(sphere_uv, lambda p, n: {"albedo": p[:, :2]}, BakeConfig(size=64, progress=False))


def test_fill_background_keeps_charts_and_fills_everything():
    rng = np.random.default_rng(0)
    img = rng.random((64, 64, 3)).astype(np.float32)
    mask = np.zeros((64, 64), bool)
    mask[10:20, 5:30] = True
    mask[40:60, 40:50] = True
    out = fill_background(img * mask[..., None], mask, "pushpull")
    assert np.array_equal(out[mask], img[mask])
    assert (out[~mask].sum(-1) > 0).all()  # no black background left for mip-maps to pull in
    # filled texels next to a chart take values close to the chart's
    assert np.abs(out[20, 5:30] - img[19, 5:30]).mean() < 0.4
    dil = fill_background(img * mask[..., None], mask, "dilate", dilate_px=3)
    grown = (dil.sum(-1) > 0) & ~mask
    assert grown.any() and not (dil.sum(-1) > 0).all()  # 3 rings, not the whole image
    assert np.array_equal(dil[mask], img[mask])
    assert np.array_equal(fill_background(img, mask, "none"), img)


def test_ambient_occlusion_darkens_the_inner_corner():
    """Floor (z = 0) meeting a wall (x = 0): floor texels near the wall are occluded, far ones are not."""
    n = 12
    g = np.linspace(0, 1, n + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    floor = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    wall = np.stack([np.zeros(X.size), Y.ravel(), X.ravel()], 1)
    quads = [(i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1)
             for i in range(n) for j in range(n)]
    f = np.array([[a, b, c] for a, b, c, d in quads] + [[a, c, d] for a, b, c, d in quads])
    off = floor.shape[0]
    faces = np.concatenate([f, f[:, ::-1] + off])  # floor faces +z, wall faces +x
    mesh = Mesh(np.concatenate([floor, wall]).astype(np.float32), faces)
    uvm = unwrap_uv(mesh, UnwrapConfig(texture_size=64))
    tex = bake_pbr_textures(uvm, lambda p, nn: {"albedo": torch.full_like(p, 0.5)},
                            BakeConfig(size=64, ao_samples=32, ao_distance=0.5, progress=False))
    cov, fid, bary = texel_lookup(uvm, 64)
    pos = np.einsum("nk,nkc->nc", bary, uvm.vertices[uvm.faces[fid]].astype(np.float64))
    ao = tex.orm[..., 0][cov] / 255.0
    on_floor = pos[:, 2] < 1e-6
    near = on_floor & (pos[:, 0] < 0.1)
    far = on_floor & (pos[:, 0] > 0.7)
    assert ao[far].mean() > 0.97
    assert ao[near].mean() < 0.85


def test_label_faces(sphere_uv):
    out = label_faces(sphere_uv, lambda p, n: {"semantic": (p[:, 2] > 0).long() * 3})
    cen = sphere_uv.vertices[sphere_uv.faces].mean(1)
    assert np.array_equal(out.face_labels, (cen[:, 2] > 0).astype(np.uint8) * 3)
    with pytest.warns(UserWarning, match="semantic"):
        same = label_faces(sphere_uv, lambda p, n: {})
    assert same.face_labels is None


def test_a_vertex_normal_that_faces_against_a_face_round_it_is_remade_from_its_faces():
    # a flat quad facing +z; the source normals: vertex 2 points down (a fold elsewhere in the source mesh summed
    # into it), the others lean a little (continuous across seams, kept as they are)
    v = np.float64([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    f = np.int64([[0, 1, 2], [0, 2, 3]])
    lean = np.float64([0, 0.1, 1]) / np.linalg.norm([0, 0.1, 1])
    src = np.stack([lean, lean, [0, 0, -1.0], lean])
    out = chart_consistent_normals(v, f, src)
    np.testing.assert_allclose(out[2], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(out[[0, 1, 3]], src[[0, 1, 3]], atol=1e-6)
    assert out.dtype == np.float32 and np.linalg.norm(out[2]) == pytest.approx(1, abs=1e-6)
    # nothing against any face: returned as given
    np.testing.assert_allclose(chart_consistent_normals(v, f, np.stack([lean] * 4)), np.stack([lean] * 4), atol=1e-6)
