"""Stage 13b — UV atlas (xatlas) and PBR texture baking from the field's material head.

Conventions:

* **UVs follow glTF**: ``u`` to the right, ``v`` *down*, origin at the top-left of the image; texel (row ``r``,
  column ``c``) has its centre at ``((c + ½)/W, (r + ½)/H)``, and row 0 is the first row of the stored image. A UV
  ``(u, v)`` is ``(u, 1 − v)`` in OBJ/Blender/OpenGL-texture convention. Baking rasterises in this space with a
  numpy rasteriser, so there is no GL framebuffer and no y flip anywhere (a GL bake would have to flip rows).
* **Textures** (:class:`PBRTextures`, glTF 2.0 channel layout): ``base_color`` sRGB-encoded linear albedo;
  ``orm`` linear, R = occlusion (1 unless there is some, below), G = roughness, B = metallic
  (glTF's ``metallicRoughnessTexture`` reads G and B, ``occlusionTexture`` reads R of the same image);
  ``normal`` tangent-space normal map ``(n_t + 1)/2``, +x = tangent (increasing u), +y = green = bitangent
  (decreasing glTF v, i.e. "up" in the image, as glTF/OpenGL expect), +z = the interpolated vertex normal.
* **Tangents** (:func:`compute_tangents`): per-vertex, from UV derivatives accumulated over faces (area-weighted,
  MikkTSpace-like), Gram–Schmidt against the vertex normal, handedness in w (bitangent = w · cross(n, t), glTF's
  rule). The bake encodes with the very frame a glTF renderer rebuilds per fragment from the exported NORMAL and
  TANGENT attributes (interpolated n, t re-orthogonalised), so the map decodes back to the field normal.

Field interface: ``material_fn(points float [N, 3], normals float [N, 3] | None) -> dict`` with keys ``albedo``
[N, 3] linear in [0, 1], ``roughness`` [N], ``metallic`` [N], ``normal`` [N, 3] (unit, world space), ``semantic``
[N] int class ids; missing keys are baked with :data:`DEFAULT_MATERIAL` and listed in ``PBRTextures.defaults``.
An optional ``occlusion`` [N] in [0, 1] is baked into ORM red (times the ray-cast ambient occlusion when
``BakeConfig.ao_samples`` > 0); without it, red is that ambient occlusion alone (1 when there is none). An optional
``light_tint`` [N, 3] in [0, :data:`LIGHT_TINT_SCALE`] (the colour of the field's per-point light,
:func:`toolkit.train.run.light_tint_map`) is baked into ``PBRTextures.light_tint``, linear, as tint / that scale.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from typing import Literal, Mapping

import numpy as np

from ._checks import ConfigError, DarsError, ShapeError, check_shape
from .mesh import MaterialFn, Mesh, compute_vertex_normals
from .mesh._field import _call_field, _progress, _to_numpy

__all__ = [
    "UVMesh",
    "UnwrapConfig",
    "BakeConfig",
    "PBRTextures",
    "DEFAULT_MATERIAL",
    "LIGHT_TINT_SCALE",
    "unwrap_uv",
    "ray_scene",
    "compute_tangents",
    "fold_normals",
    "chart_consistent_normals",
    "rasterize_triangles",
    "sample_texture",
    "bake_pbr_textures",
    "label_faces",
    "fill_background",
]

LIGHT_TINT_SCALE = 2.0
"""``PBRTextures.light_tint`` stores tint / this (8 bits, linear): tints up to 2 per channel, 1 at 128/255."""

DEFAULT_MATERIAL: dict[str, object] = {"albedo": (0.5, 0.5, 0.5), "roughness": 1.0, "metallic": 0.0}
"""Baked where ``material_fn`` lacks a key: mid-grey linear albedo, fully rough (glTF's default roughness),
dielectric. A missing ``normal`` bakes the flat map (0.5, 0.5, 1) (the interpolated mesh normal)."""


# ============================================================================================================ UVMesh
@dataclass(frozen=True, init=False)
class UVMesh(Mesh):
    """A :class:`~toolkit.mesh.Mesh` with a UV atlas (vertices split along chart seams).

    Constructed as ``UVMesh(vertices, faces, uvs, normals, tangents, vmapping, face_labels=None,
    texture_blur=None)``; the mesh's
    ``colors`` and ``labels`` are None (labels are per face here).

    Attributes:
        vertices: float32 [V, 3] world positions, metres (+z up).
        faces: int64 [F, 3] counter-clockwise seen from outside.
        uvs: float32 [V, 2] texture coordinates in glTF convention (origin top-left, v down), in [0, 1].
        normals: float32 [V, 3] unit vertex normals (taken from the source mesh, so continuous across seams, except
            where the mesh folds: :func:`chart_consistent_normals`).
        tangents: float32 [V, 4] unit tangent (xyz, ⟂ normal, along increasing u) and handedness w = ±1.
        vmapping: int64 [V] index of each vertex in the source :class:`~toolkit.mesh.Mesh`.
        face_labels: uint8 [F] semantic class per face (0-6, 255 unlabelled), or None.
        texture_blur: float32 [V] how blurred the baked textures are around each vertex, in texels
            (:func:`toolkit.viewbake.face_texture_blur`; the GLB's ``_TEXTURE_BLUR`` attribute), or None.
    """

    colors: None = dc_field(default=None, init=False, repr=False)
    labels: None = dc_field(default=None, init=False, repr=False)
    uvs: np.ndarray = None
    tangents: np.ndarray = None
    vmapping: np.ndarray = None
    face_labels: np.ndarray | None = None
    texture_blur: np.ndarray | None = None

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, normals: np.ndarray,
                 tangents: np.ndarray, vmapping: np.ndarray, face_labels: np.ndarray | None = None,
                 texture_blur: np.ndarray | None = None):
        for name, value in (("vertices", vertices), ("faces", faces), ("normals", normals), ("colors", None),
                            ("labels", None), ("uvs", uvs), ("tangents", tangents), ("vmapping", vmapping),
                            ("face_labels", face_labels), ("texture_blur", texture_blur)):
            object.__setattr__(self, name, value)
        self.__post_init__()

    def __post_init__(self) -> None:
        super().__post_init__()  # vertices, faces, normals
        v = self.num_vertices
        check_shape(self.normals, f"{v} 3", "UVMesh.normals")  # required here
        for name, spec in (("uvs", f"{v} 2"), ("tangents", f"{v} 4"), ("vmapping", f"{v}")):
            check_shape(getattr(self, name), spec, f"UVMesh.{name}")
        if self.face_labels is not None:
            check_shape(self.face_labels, f"{self.num_faces}", "UVMesh.face_labels")
        if self.texture_blur is not None:
            check_shape(self.texture_blur, f"{v}", "UVMesh.texture_blur")

    def to_mesh(self) -> Mesh:
        """Geometry only (split vertices kept)."""
        return Mesh(self.vertices, self.faces, normals=self.normals)


@dataclass(frozen=True)
class UnwrapConfig:
    """xatlas chart generation and packing.

    Attributes:
        texture_size: texture resolution the atlas is packed for (texels), sets the padding's scale.
        padding: texels between charts (at ``texture_size``); keep ≥ 2 so bilinear filtering and the first mip
            levels stay inside a chart.
        max_iterations: xatlas chart-growing iterations (more = fewer, better charts; slower).
        max_chart_faces: cap chart size at about this many faces (passed to xatlas as a maximum chart *area* of
            total_area · max_chart_faces / F); None = unlimited. xatlas's chart growing is superlinear in chart size:
            on a 100k-face mesh an uncapped unwrap took 57 s, a cap of 500 faces ~7-15 s, with the same atlas
            utilisation (~0.58) but more, smaller charts (more seams).
        rotate_charts: let the packer rotate charts.
        brute_force: slower, tighter packing.
        max_piece_faces: meshes larger than this are cut into spatial pieces of at most this many faces (median
            splits of the face centroids along the longest side), handed to xatlas as separate meshes of one atlas;
            None = one piece. xatlas merges charts in a time superlinear in the charts of a piece, and a room's
            noisy surface makes tens of thousands of them: gallery 1000000's 100k-face mesh took 17-24 minutes as
            one piece, 11-16 s as 32 pieces (2026-11-28). The cuts become chart seams; faces keep their order.
    """

    texture_size: int = 1024
    padding: int = 4
    max_iterations: int = 1
    max_chart_faces: int | None = 500
    rotate_charts: bool = True
    brute_force: bool = False
    max_piece_faces: int | None = 5000


def unwrap_uv(mesh: Mesh, cfg: UnwrapConfig = UnwrapConfig()) -> UVMesh:
    """Compute a UV atlas with xatlas (CPU). Vertices are split along chart seams; ``vmapping`` keeps the link.

    Args:
        mesh: input mesh (normals used if present, else area-weighted ones).
        cfg: :class:`UnwrapConfig`.

    Returns:
        :class:`UVMesh` with glTF-convention UVs, source normals (:func:`chart_consistent_normals`) and tangents;
        ``face_labels`` from the source's vertex labels (majority of a face's three vertices) when the mesh has them.

    Raises:
        DarsError: empty mesh, or xatlas produced more than one atlas page.
    """
    import xatlas

    if mesh.num_faces == 0:
        raise DarsError("unwrap_uv: the mesh has no faces")
    if not (isinstance(cfg.texture_size, int) and cfg.texture_size >= 16):
        raise ConfigError(f"UnwrapConfig.texture_size={cfg.texture_size!r} must be an integer ≥ 16")
    if cfg.max_piece_faces is not None and not (isinstance(cfg.max_piece_faces, int) and cfg.max_piece_faces >= 1):
        raise ConfigError(f"UnwrapConfig.max_piece_faces={cfg.max_piece_faces!r} must be None or an integer ≥ 1")
    normals = mesh.normals if mesh.normals is not None else compute_vertex_normals(mesh.vertices, mesh.faces)
    atlas = xatlas.Atlas()
    pieces = _spatial_pieces(mesh.vertices, mesh.faces, cfg.max_piece_faces)
    verts_of = []  # per piece: its vertices' indices in the mesh
    for idx in pieces:
        used, local = np.unique(mesh.faces[idx], return_inverse=True)
        verts_of.append(used)
        atlas.add_mesh(np.ascontiguousarray(mesh.vertices[used], dtype=np.float32),
                       np.ascontiguousarray(local.reshape(-1, 3), dtype=np.uint32),
                       np.ascontiguousarray(normals[used], dtype=np.float32))
    co = xatlas.ChartOptions()
    co.max_iterations = int(cfg.max_iterations)
    if cfg.max_chart_faces is not None and mesh.num_faces > cfg.max_chart_faces:
        co.max_chart_area = float(mesh.area() * cfg.max_chart_faces / mesh.num_faces)
    po = xatlas.PackOptions()
    po.resolution = int(cfg.texture_size)
    po.padding = int(cfg.padding)
    po.bilinear = True
    po.rotate_charts = bool(cfg.rotate_charts)
    po.bruteForce = bool(cfg.brute_force)
    atlas.generate(co, po)
    if atlas.atlas_count != 1:
        raise DarsError(f"unwrap_uv: xatlas packed {atlas.atlas_count} atlas pages; expected 1 (lower the padding or raise texture_size)")
    vmaps, uv_list, faces, n = [], [], np.zeros((mesh.num_faces, 3), np.int64), 0
    for k, idx in enumerate(pieces):
        vm, ind, uv = atlas[k]
        vmaps.append(verts_of[k][vm.astype(np.int64)])
        uv_list.append(uv)
        faces[idx] = ind.astype(np.int64).reshape(-1, 3) + n  # back in the mesh's face order
        n += len(vm)
    vmapping = np.concatenate(vmaps)
    uvs = np.concatenate(uv_list)
    vertices = mesh.vertices[vmapping].astype(np.float32)
    vnormals = chart_consistent_normals(vertices, faces, normals[vmapping])
    uvs = np.clip(uvs.astype(np.float32), 0.0, 1.0)
    tangents = compute_tangents(vertices, faces, uvs, vnormals)
    face_labels = None
    if mesh.labels is not None:
        face_labels = _majority(mesh.labels[mesh.faces]).astype(np.uint8)
    return UVMesh(vertices, faces, uvs, vnormals, tangents, vmapping, face_labels)


def chart_consistent_normals(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Vertex normals of an unwrapped mesh that face the same way as every face round them.

    A vertex keeps its source normal (continuous across chart seams) unless a face of its chart round it faces the
    other way (normal · face normal < 0: the mesh folds there, and the source normal, summed over both sides of the
    fold, points anywhere). Such a vertex takes the area-weighted normal of its chart's faces round it instead, so
    the tangent frames a viewer interpolates over those faces do not turn over inside them: on validation gallery
    1000001 the faces under the preview's speckles (a pixel of wrong shading on a flat wall) held such a vertex 11x
    as often as the rest (one test view; README, "No turned-over shading frames in the GLB"). The normal map is
    baked in these frames, so the field's normal is what a viewer shows.

    Args:
        vertices: float [V, 3] the unwrapped (seam-split) vertices; faces: int [F, 3]; normals: float [V, 3] the
            source normals.

    Returns:
        float32 [V, 3]: the source normals as given, those remade unit.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    out = np.array(normals, dtype=np.float32)
    if not len(f):
        return out
    fn = _unit(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]))  # degenerate faces: zero, never against
    against = np.zeros(len(v), bool)
    for k in range(3):
        against[f[(out[f[:, k]] * fn).sum(1) < 0, k]] = True
    if against.any():
        out[against] = compute_vertex_normals(v, f)[against]
    return out


def _spatial_pieces(vertices: np.ndarray, faces: np.ndarray, max_faces: int | None) -> list[np.ndarray]:
    """Face indices cut into pieces of at most ``max_faces`` by median splits of the centroids (longest side)."""
    if max_faces is None or len(faces) <= max_faces:
        return [np.arange(len(faces))]
    cen = vertices[faces].mean(1)
    out, todo = [], [np.arange(len(faces))]
    while todo:
        idx = todo.pop()
        if len(idx) <= max_faces:
            out.append(idx)
            continue
        c = cen[idx]
        order = np.argsort(c[:, int(np.argmax(c.max(0) - c.min(0)))], kind="stable")
        todo += [idx[order[len(idx) // 2:]], idx[order[:len(idx) // 2]]]
    return out


def _majority(lab3: np.ndarray) -> np.ndarray:
    a, b, c = lab3[:, 0], lab3[:, 1], lab3[:, 2]
    return np.where((b == c), b, a)


# ========================================================================================================= tangents
def _any_perpendicular(n: np.ndarray) -> np.ndarray:
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t = helper - n * np.sum(helper * n, 1, keepdims=True)
    return t / np.linalg.norm(t, axis=1, keepdims=True)


def compute_tangents(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Per-vertex tangent frames from UV derivatives (glTF convention).

    Per face, T = ∂p/∂u and B = ∂p/∂(−v) (glTF's v points down, the normal map's +y up), each normalised and
    weighted by the face's area, summed at its vertices; then t = normalise(T − n(n·T)) and
    w = sign(dot(cross(n, t), B)) (+1 when undecided). Vertices with no usable UV gradient get an arbitrary
    perpendicular tangent.

    Args:
        vertices: float [V, 3].
        faces: int [F, 3].
        uvs: float [V, 2] glTF-convention UVs.
        normals: float [V, 3] unit vertex normals.

    Returns:
        float32 [V, 4]: unit xyz ⟂ normal, w ∈ {−1, +1}.
    """
    p = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    uv = np.asarray(uvs, dtype=np.float64) * np.array([1.0, -1.0])  # (u, v_up)
    n = np.asarray(normals, dtype=np.float64)
    e1, e2 = p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]]
    d1, d2 = uv[f[:, 1]] - uv[f[:, 0]], uv[f[:, 2]] - uv[f[:, 0]]
    r = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(r) > 1e-20
    rs = np.where(ok, 1.0 / np.where(ok, r, 1.0), 0.0)[:, None]
    tf = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * rs
    bf = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * rs
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1, keepdims=True)

    def unit(x):
        length = np.linalg.norm(x, axis=1, keepdims=True)
        return np.where(length > 1e-30, x / np.maximum(length, 1e-30), 0.0)

    tf, bf = unit(tf) * area, unit(bf) * area
    T = np.zeros_like(p)
    B = np.zeros_like(p)
    for k in range(3):
        np.add.at(T, f[:, k], tf)
        np.add.at(B, f[:, k], bf)
    t = T - n * np.sum(n * T, 1, keepdims=True)
    length = np.linalg.norm(t, axis=1, keepdims=True)
    bad = length[:, 0] < 1e-12
    t = np.where(bad[:, None], 0.0, t / np.maximum(length, 1e-30))
    if bad.any():
        t[bad] = _any_perpendicular(n[bad])
    w = np.sign(np.sum(np.cross(n, t) * B, 1))
    w = np.where(w == 0, 1.0, w)
    return np.concatenate([t, w[:, None]], 1).astype(np.float32)


# ======================================================================================================= rasteriser
def rasterize_triangles(xy: np.ndarray, faces: np.ndarray, height: int, width: int, depth: np.ndarray | None = None,
                        max_candidates: int = 1 << 20) -> tuple[np.ndarray, np.ndarray]:
    """Rasterise triangles at pixel centres (vectorised numpy; CPU).

    A pixel (row r, column c) is covered by a triangle when its centre (c + ½, r + ½) lies inside it (edges
    inclusive). Triangles are grouped by bounding-box size and processed in batches of at most ``max_candidates``
    candidate pixels, so memory stays bounded. Without ``depth`` an arbitrary covering triangle wins (fine for
    non-overlapping UV charts); with ``depth`` the nearest (smallest depth) wins.

    Args:
        xy: float [V, 2] vertex positions in pixels, x = column direction, y = row direction (continuous, pixel
            (r, c) spans [c, c+1) x [r, r+1)).
        faces: int [F, 3].
        height, width: image size in pixels.
        depth: optional float [V] per-vertex depth for the z-test (interpolated linearly in screen space).
        max_candidates: candidate pixels per batch.

    Returns:
        (face_id, bary): int32 [H, W] covering face or −1, and float32 [H, W, 3] screen-space barycentrics.
    """
    xy = np.asarray(xy, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    H, W = int(height), int(width)
    face_id = np.full(H * W, -1, dtype=np.int32)
    bary = np.zeros((H * W, 3), dtype=np.float32)
    zbuf = np.full(H * W, np.inf) if depth is not None else None
    if faces.shape[0] == 0:
        return face_id.reshape(H, W), bary.reshape(H, W, 3)
    tri = xy[faces]  # [F, 3, 2]
    lo = np.ceil(tri.min(1) - 0.5 - 1e-9).astype(np.int64)  # first pixel whose centre ≥ min
    hi = np.floor(tri.max(1) - 0.5).astype(np.int64)  # last pixel whose centre ≤ max
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [W - 1, H - 1])
    size = hi - lo + 1
    valid = (size > 0).all(1)
    x0, y0 = tri[:, 0, 0], tri[:, 0, 1]
    ax, ay = tri[:, 1, 0] - x0, tri[:, 1, 1] - y0
    bx, by = tri[:, 2, 0] - x0, tri[:, 2, 1] - y0
    det = ax * by - ay * bx
    valid &= np.abs(det) > 1e-18
    idx = np.nonzero(valid)[0]
    if idx.size == 0:
        return face_id.reshape(H, W), bary.reshape(H, W, 3)
    bucket = np.stack([_ceil_pow2(size[idx, 0]), _ceil_pow2(size[idx, 1])], 1)
    keys = bucket[:, 0] * 65536 + bucket[:, 1]
    order = np.argsort(keys, kind="stable")
    idx, keys, bucket = idx[order], keys[order], bucket[order]
    starts = np.nonzero(np.r_[True, keys[1:] != keys[:-1]])[0]
    ends = np.r_[starts[1:], keys.size]
    for s, e in zip(starts, ends):
        bw, bh = int(bucket[s, 0]), int(bucket[s, 1])
        per = max(1, max_candidates // (bw * bh))
        oy, ox = np.meshgrid(np.arange(bh), np.arange(bw), indexing="ij")
        ox, oy = ox.reshape(-1), oy.reshape(-1)
        for a in range(s, e, per):
            fi = idx[a:min(a + per, e)]
            px = lo[fi, 0][:, None] + ox[None]  # [n, bw*bh]
            py = lo[fi, 1][:, None] + oy[None]
            inb = (px <= hi[fi, 0][:, None]) & (py <= hi[fi, 1][:, None])
            cx = px + 0.5 - x0[fi][:, None]
            cy = py + 0.5 - y0[fi][:, None]
            inv = 1.0 / det[fi][:, None]
            b1 = (cx * by[fi][:, None] - cy * bx[fi][:, None]) * inv
            b2 = (ax[fi][:, None] * cy - ay[fi][:, None] * cx) * inv
            b0 = 1.0 - b1 - b2
            eps = -1e-7
            inside = inb & (b0 >= eps) & (b1 >= eps) & (b2 >= eps)
            ii, jj = np.nonzero(inside)
            if ii.size == 0:
                continue
            pix = py[ii, jj] * W + px[ii, jj]
            fsel = fi[ii]
            bsel = np.stack([b0[ii, jj], b1[ii, jj], b2[ii, jj]], 1)
            if zbuf is None:
                face_id[pix] = fsel
                bary[pix] = bsel
                continue
            z = (bsel * depth[faces[fsel]]).sum(1)
            o = np.lexsort((z, pix))  # by pixel, then depth: the first of each pixel is the nearest
            pix, z, fsel, bsel = pix[o], z[o], fsel[o], bsel[o]
            first = np.r_[True, pix[1:] != pix[:-1]]
            pix, z, fsel, bsel = pix[first], z[first], fsel[first], bsel[first]
            win = z < zbuf[pix]
            pix, z, fsel, bsel = pix[win], z[win], fsel[win], bsel[win]
            zbuf[pix] = z
            face_id[pix] = fsel
            bary[pix] = bsel
    return face_id.reshape(H, W), bary.reshape(H, W, 3)


def _ceil_pow2(x: np.ndarray) -> np.ndarray:
    return (1 << np.ceil(np.log2(np.maximum(x, 1))).astype(np.int64)).astype(np.int64)


def sample_texture(image_hwc: np.ndarray, uvs: np.ndarray, wrap: Literal["clamp", "repeat"] = "clamp") -> np.ndarray:
    """Bilinear texture lookup at glTF-convention UVs (origin top-left): texel centres at ((c+½)/W, (r+½)/H).

    Args:
        image_hwc: [H, W, C] (any numeric dtype; returned as float32 in the same units).
        uvs: float [N, 2].
        wrap: "clamp" (to edge) or "repeat".

    Returns:
        float32 [N, C].
    """
    img = np.asarray(image_hwc)
    if img.ndim == 2:
        img = img[..., None]
    H, W = img.shape[:2]
    x = np.asarray(uvs[:, 0], dtype=np.float64) * W - 0.5
    y = np.asarray(uvs[:, 1], dtype=np.float64) * H - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)

    def fix(i, n):
        return np.mod(i, n) if wrap == "repeat" else np.clip(i, 0, n - 1)

    xa, xb, ya, yb = fix(x0, W), fix(x0 + 1, W), fix(y0, H), fix(y0 + 1, H)
    f = img.astype(np.float32)
    top = f[ya, xa] * (1 - fx) + f[ya, xb] * fx
    bot = f[yb, xa] * (1 - fx) + f[yb, xb] * fx
    return (top * (1 - fy) + bot * fy).astype(np.float32)


# ============================================================================================================ baking
@dataclass(frozen=True)
class BakeConfig:
    """PBR texture baking.

    Attributes:
        size: texture edge in texels (square textures; a power of two is best for mip-mapping).
        supersample: render the atlas at ``supersample × size`` and box-filter down (1 or 2; 2 costs 4× queries).
        fill: how texels outside the charts are filled so mip-maps and bilinear filtering don't pull in
            background: "pushpull" (whole background, smooth pyramid fill), "dilate" (``dilate_px`` rings of
            neighbour averages, the rest left at 0) or "none".
        dilate_px: rings for ``fill="dilate"``.
        batch: texels per ``material_fn`` call.
        device: device the points are sent to.
        ao_samples: rays per texel for the ambient-occlusion channel (ORM red); 0 = no occlusion (R = 1).
        ao_distance: occluders farther than this (metres) don't count; None = 10 % of the mesh diagonal.
        seed: seed of the AO ray directions.
        progress: show a progress bar (stderr).
    """

    size: int = 1024
    supersample: int = 1
    fill: Literal["pushpull", "dilate", "none"] = "pushpull"
    dilate_px: int = 16
    batch: int = 1 << 16
    device: str = "cpu"
    ao_samples: int = 0
    ao_distance: float | None = None
    seed: int = 0
    progress: bool = True


@dataclass(frozen=True)
class PBRTextures:
    """Baked glTF metallic-roughness textures (H-W-C, row 0 = top = glTF v 0).

    Attributes:
        base_color: uint8 [H, W, 3] sRGB-encoded linear albedo (glTF ``baseColorTexture``).
        orm: uint8 [H, W, 3] linear; R occlusion, G roughness, B metallic.
        normal: uint8 [H, W, 3] tangent-space normal map, (n + 1)/2, +y = green = up.
        mask: bool [H, W] texels inside a chart (before the background fill).
        defaults: material keys ``material_fn`` did not provide (baked from :data:`DEFAULT_MATERIAL`).
        light_tint: uint8 [H, W, 3] linear tint / :data:`LIGHT_TINT_SCALE` (module docstring), or None when
            ``material_fn`` gave none.
    """

    base_color: np.ndarray
    orm: np.ndarray
    normal: np.ndarray
    mask: np.ndarray
    defaults: tuple[str, ...] = ()
    light_tint: np.ndarray | None = None

    @property
    def size(self) -> int:
        return int(self.base_color.shape[0])


def _interp(attr: np.ndarray, faces: np.ndarray, fid: np.ndarray, bary: np.ndarray) -> np.ndarray:
    return np.einsum("nk,nkc->nc", bary, attr[faces[fid]].astype(np.float64))


def fold_normals(normals, surface):
    """Field normals that face away from the surface folded onto its tangent plane: n − (n · m) m where n · m < 0
    (m the unit surface normal; not renormalised). A tangent-space normal map stores no normal below the surface, so
    :func:`bake_pbr_textures` writes these, and :func:`toolkit.viewbake.fit_light` shades with what the map will
    hold. numpy arrays or torch tensors [N, 3], returned as the same type."""
    back = (normals * surface).sum(-1)[..., None]
    return normals - (back < 0) * back * surface


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def _texel_frames(uvmesh: UVMesh, fid: np.ndarray, bary: np.ndarray):
    """Position, normal, tangent, bitangent at texels, as a glTF renderer rebuilds them per fragment."""
    pos = _interp(uvmesh.vertices, uvmesh.faces, fid, bary)
    n = _unit(_interp(uvmesh.normals, uvmesh.faces, fid, bary))
    t = _interp(uvmesh.tangents[:, :3], uvmesh.faces, fid, bary)
    t = t - n * np.sum(n * t, 1, keepdims=True)
    tl = np.linalg.norm(t, axis=1, keepdims=True)
    bad = tl[:, 0] < 1e-9
    t = t / np.maximum(tl, 1e-12)
    if bad.any():
        t[bad] = _any_perpendicular(n[bad])
    w = np.sign(uvmesh.tangents[uvmesh.faces[fid], 3].astype(np.float64).sum(1))
    w = np.where(w == 0, 1.0, w)
    b = np.cross(n, t) * w[:, None]
    return pos, n, t, b


def bake_pbr_textures(uvmesh: UVMesh, material_fn: MaterialFn, cfg: BakeConfig = BakeConfig()) -> PBRTextures:
    """Bake base colour, ORM and a tangent-space normal map by querying ``material_fn`` at every texel's surface point.

    The atlas is rasterised in UV space (numpy, pixel centres); each covered texel maps to a surface point (and the
    interpolated vertex normal, passed as ``normals``). The field normal is encoded in the texel's tangent frame
    (module docstring). With ``supersample = 2`` the atlas is rendered at twice the size and box-filtered (albedo
    averaged in linear space, normals re-normalised). Empty texels are then filled (``cfg.fill``).

    Args:
        uvmesh: the unwrapped mesh (:func:`unwrap_uv`).
        material_fn: the field's material callable (module docstring).
        cfg: :class:`BakeConfig`.

    Returns:
        :class:`PBRTextures`.

    Raises:
        ConfigError: bad size/supersample/fill.
        ShapeError: ``material_fn`` returns arrays of the wrong shape.
    """
    if not (isinstance(cfg.size, int) and 8 <= cfg.size <= 16384):
        raise ConfigError(f"BakeConfig.size={cfg.size!r} must be an integer in [8, 16384]")
    if cfg.supersample not in (1, 2, 3, 4):
        raise ConfigError(f"BakeConfig.supersample={cfg.supersample!r} must be 1, 2, 3 or 4")
    if cfg.fill not in ("pushpull", "dilate", "none"):
        raise ConfigError(f"BakeConfig.fill={cfg.fill!r} is not valid: choose 'pushpull', 'dilate' or 'none'")
    S = cfg.size * cfg.supersample
    xy = uvmesh.uvs.astype(np.float64) * S
    fid_img, bary_img = rasterize_triangles(xy, uvmesh.faces, S, S)
    covered = np.nonzero(fid_img.reshape(-1) >= 0)[0]
    fid = fid_img.reshape(-1)[covered]
    bary = bary_img.reshape(-1, 3)[covered]
    del fid_img, bary_img
    n_tex = covered.size

    albedo = np.empty((n_tex, 3), np.float32)
    rough = np.empty(n_tex, np.float32)
    metal = np.empty(n_tex, np.float32)
    nmap = np.empty((n_tex, 3), np.float32)
    occl = np.ones(n_tex, np.float32)
    tint: np.ndarray | None = None
    missing: set[str] = set()
    ao_scene = ray_scene(uvmesh.vertices, uvmesh.faces) if cfg.ao_samples > 0 else None
    ao_dist = cfg.ao_distance or 0.1 * uvmesh.to_mesh().diagonal
    bar = _progress(n_tex, "baking textures", cfg.progress, unit="texel")
    try:
        for s in range(0, n_tex, cfg.batch):
            e = min(s + cfg.batch, n_tex)
            pos, n, t, b = _texel_frames(uvmesh, fid[s:e], bary[s:e].astype(np.float64))
            out = _call_field(material_fn, pos, cfg.device, n)
            m = e - s
            albedo[s:e] = _get(out, "albedo", (m, 3), missing)
            rough[s:e] = _get(out, "roughness", (m,), missing)
            metal[s:e] = _get(out, "metallic", (m,), missing)
            if "normal" in out:
                nf = fold_normals(_unit(_to_numpy(out["normal"], "normal").reshape(m, 3).astype(np.float64)), n)
                nt = np.stack([np.sum(nf * t, 1), np.sum(nf * b, 1), np.maximum(np.sum(nf * n, 1), 0.0)], 1)
                nmap[s:e] = _unit(nt)
            else:
                missing.add("normal")
                nmap[s:e] = (0.0, 0.0, 1.0)
            if "occlusion" in out:
                occl[s:e] = _get(out, "occlusion", (m,), missing)
            if "light_tint" in out:
                if tint is None:
                    tint = np.ones((n_tex, 3), np.float32)
                tint[s:e] = np.clip(_shaped(out, "light_tint", (m, 3)), 0.0, LIGHT_TINT_SCALE)
            if cfg.ao_samples > 0:
                occl[s:e] *= _ambient_occlusion(ao_scene, pos, n, cfg.ao_samples, ao_dist, seed=cfg.seed + s)
            bar.update(m)
    finally:
        bar.close()
    if missing:
        warnings.warn(f"bake_pbr_textures: material_fn provided no {sorted(missing)}; baked defaults "
                      f"{ {k: DEFAULT_MATERIAL.get(k, 'flat normal') for k in sorted(missing)} }", stacklevel=2)

    from .io import linear_to_srgb

    k = cfg.supersample
    cover = np.zeros(S * S, np.uint8)
    cover[covered] = 1
    cover = cover.reshape(S, S)
    weight = cover.reshape(cfg.size, k, cfg.size, k).sum((1, 3), dtype=np.float32) if k > 1 else None
    mask = weight > 0 if k > 1 else cover.astype(bool)

    def finish(values: np.ndarray, kind: str) -> np.ndarray:
        """Scatter texel values into an image, box-filter the supersamples, fill the background, quantise.
        One layer at a time, so only one full-size float image is alive."""
        img = np.zeros((S * S, 3), np.float32)
        img[covered] = values
        img = img.reshape(S, S, 3)
        if k > 1:  # uncovered subsamples are 0: the block sum over covered ones / their count
            img = img.reshape(cfg.size, k, cfg.size, k, 3).sum((1, 3))
            img /= np.maximum(weight, 1e-12)[..., None]
        if kind == "normal":
            img = np.where(mask[..., None], _unit(img), np.array([0.0, 0.0, 1.0], np.float32)).astype(np.float32)
            img = (img + 1.0) * 0.5
        img = fill_background(img, mask, cfg.fill, cfg.dilate_px)
        if kind == "albedo":
            img = linear_to_srgb(np.clip(img, 0.0, 1.0))
        return np.clip(np.rint(np.nan_to_num(img) * 255.0), 0, 255).astype(np.uint8)

    base_color = finish(albedo, "albedo")
    del albedo
    orm = finish(np.stack([occl, rough, metal], 1), "orm")
    del occl, rough, metal
    normal = finish(nmap, "normal")
    del nmap
    light_tint = None if tint is None else finish(tint / LIGHT_TINT_SCALE, "tint")
    return PBRTextures(base_color=base_color, orm=orm, normal=normal, mask=mask, defaults=tuple(sorted(missing)),
                       light_tint=light_tint)


def _get(out: Mapping, key: str, shape: tuple[int, ...], missing: set[str]) -> np.ndarray:
    if key not in out:
        missing.add(key)
        return np.broadcast_to(np.asarray(DEFAULT_MATERIAL[key], np.float32), shape)
    return np.clip(_shaped(out, key, shape), 0.0, 1.0)


def _shaped(out: Mapping, key: str, shape: tuple[int, ...]) -> np.ndarray:
    """``out[key]`` as float32 of ``shape``; ShapeError naming the key when its size differs."""
    a = _to_numpy(out[key], key).astype(np.float32)
    if a.size != math.prod(shape):
        raise ShapeError(f"material_fn()['{key}']: expected shape {list(shape)}, got {list(a.shape)}")
    return a.reshape(shape)


def _ambient_occlusion(scene, pos: np.ndarray, n: np.ndarray, samples: int, distance: float, seed: int) -> np.ndarray:
    """Fraction of cosine-weighted hemisphere rays that escape within ``distance`` (Open3D ray casting, CPU)."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    m, k = pos.shape[0], samples
    u1, u2 = rng.random((m, k)), rng.random((m, k))
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - u1, 0))], -1)  # [m, k, 3]
    t1 = _any_perpendicular(n)
    t2 = np.cross(n, t1)
    dirs = local[..., 0:1] * t1[:, None] + local[..., 1:2] * t2[:, None] + local[..., 2:3] * n[:, None]
    origins = pos[:, None] + n[:, None] * (1e-4 * distance)
    rays = np.concatenate([np.broadcast_to(origins, dirs.shape), dirs], -1).reshape(-1, 6).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(m, k)
    return 1.0 - (hit < distance).mean(1).astype(np.float32)


def ray_scene(vertices: np.ndarray, faces: np.ndarray):
    """An Open3D ray-casting scene of a triangle mesh (float [V, 3], int [F, 3]): the bake's ambient occlusion, the
    backdrop's coverage and the viewer fit's pixels (:func:`toolkit.backdrop.front_hits`) cast rays against it."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    return scene


# ============================================================================================================ labels
def label_faces(uvmesh: UVMesh, material_fn: MaterialFn, batch: int = 1 << 16, device: str = "cpu") -> UVMesh:
    """Set ``face_labels`` from the field's ``semantic`` output at face centroids.

    Returns:
        the :class:`UVMesh` with ``face_labels`` (uint8 [F]), or unchanged (with a warning) if ``material_fn`` has
        no ``semantic`` key.
    """
    v = uvmesh.vertices[uvmesh.faces].astype(np.float64)
    centroids = v.mean(1)
    normals = _unit(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]))
    labels = []
    for s in range(0, centroids.shape[0], batch):
        out = _call_field(material_fn, centroids[s:s + batch], device, normals[s:s + batch])
        if "semantic" not in out:
            warnings.warn("label_faces: material_fn provided no 'semantic'; faces left unlabelled", stacklevel=2)
            return uvmesh
        labels.append(_to_numpy(out["semantic"], "semantic").reshape(-1))
    lab = np.concatenate(labels)
    if lab.shape != (uvmesh.num_faces,):
        raise ShapeError(f"material_fn()['semantic']: expected {uvmesh.num_faces} labels, got {lab.shape}")
    return replace(uvmesh, face_labels=np.clip(lab, 0, 255).astype(np.uint8))


# ============================================================================================================== fill
def fill_background(image: np.ndarray, mask: np.ndarray, method: Literal["pushpull", "dilate", "none"] = "pushpull",
                    dilate_px: int = 16) -> np.ndarray:
    """Fill texels outside the charts so filtering and mip-mapping don't bleed background into the charts.

    Args:
        image: float [H, W, C]; values inside ``mask`` are kept exactly.
        mask: bool [H, W] valid texels.
        method: "pushpull" (pyramid: average valid texels down to 1x1, then fill holes from the coarser level on
            the way up — every texel gets a smooth extension of its nearest charts), "dilate" (``dilate_px``
            rings of 3x3 neighbour averages) or "none".
        dilate_px: rings for "dilate".

    Returns:
        float32 [H, W, C].
    """
    img = np.asarray(image, dtype=np.float32)
    m = np.asarray(mask, dtype=bool)
    if method == "none" or m.all() or not m.any():
        return img
    if method == "dilate":
        return _dilate(img, m, dilate_px)
    if method != "pushpull":
        raise ConfigError(f"fill method {method!r} is not valid: choose 'pushpull', 'dilate' or 'none'")
    return _pushpull(img.copy(), m)


def _pushpull(img: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill ``img`` (float32 [H, W, C]) where ``valid`` (bool [H, W]) is false, in place, from a 2x2 pyramid."""
    H, W = valid.shape
    if (H <= 1 and W <= 1) or valid.all() or not valid.any():
        return img
    h2, w2 = (H + 1) // 2, (W + 1) // 2
    wv = valid.astype(np.float32)
    num = img * wv[..., None]
    if H % 2 or W % 2:  # pad odd sizes with invalid texels
        num = np.pad(num, ((0, 2 * h2 - H), (0, 2 * w2 - W), (0, 0)))
        wv = np.pad(wv, ((0, 2 * h2 - H), (0, 2 * w2 - W)))
    num = num.reshape(h2, 2, w2, 2, -1).sum((1, 3))
    den = wv.reshape(h2, 2, w2, 2).sum((1, 3))
    del wv
    coarse_valid = den > 0
    num /= np.maximum(den, 1e-12)[..., None]
    coarse = _pushpull(num, coarse_valid)
    rows, cols = np.nonzero(~valid)
    img[rows, cols] = coarse[rows // 2, cols // 2]
    return img


def _dilate(img: np.ndarray, m: np.ndarray, rings: int) -> np.ndarray:
    import cv2

    out = img.copy()
    w = m.astype(np.float32)
    for _ in range(max(0, int(rings))):
        if w.all():
            break
        num = cv2.boxFilter(out * w[..., None], -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        den = cv2.boxFilter(w, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        if num.ndim == 2:
            num = num[..., None]
        grow = (den > 0) & (w == 0)
        out[grow] = num[grow] / den[grow][:, None]
        w = np.where(grow, 1.0, w).astype(np.float32)
    return out
