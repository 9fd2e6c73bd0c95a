"""Stage 13c — the view-projected bake: a texel takes the field's own render from the training views that see it.

The mesh is one fused surface; the field's render at a pixel is a weighted average along the ray, and that average
is what training fitted to the photos. Asking the field for its albedo at the mesh point reads another place: on the
demo run the point albedo at the mesh scores 18 dB against the field's composited albedo along the same rays, and the
GLB's preview sat 6.5 dB below the field (README, "The GLB against its field: the view-projected bake").

So :func:`view_projected` wraps a material callable: each surface point is projected into every view of a
:class:`ViewMaps` (the field's composited outputs rendered at the training cameras). A view counts where the point is
in front of the camera, inside the image, on a pixel the field renders opaque enough, and within ``tolerance``
(relative) of that pixel's rendered depth: not occluded, not behind a translucent layer. The point takes the mean of
those pixels' values, key by key; points no view sees keep the point query.

Example:
    >>> maps = field.views(depth_cameras(field.cameras, 300_000))        # doctest: +SKIP
    >>> material = view_projected(field.material_fn, maps)                # doctest: +SKIP
    >>> textures = bake_pbr_textures(uvmesh, material)                    # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from ._checks import ConfigError, ShapeError
from .bake import DEFAULT_MATERIAL, fold_normals, ray_scene
from .cameras import Cameras, project_points

__all__ = ["ViewMaps", "sightings", "project_views", "view_projected", "fit_light", "face_texture_blur",
           "vertex_texture_blur", "VertexValues", "FIT_WEIGHT_EXPONENT", "VIEW_DEFAULTS"]

VIEW_DEFAULTS: dict[str, object] = {**DEFAULT_MATERIAL, "light_gain": 1.0, "light_tint": (1.0, 1.0, 1.0)}
"""What a point no view sees gets for a key the material callable lacks: the bake's defaults, and no change of
light (``light_gain`` 1 and a white ``light_tint``: :func:`toolkit.train.run.light_gain_map`,
:func:`~toolkit.train.run.light_tint_map`)."""


@dataclass(frozen=True)
class ViewMaps:
    """The field's composited outputs at a set of cameras (what :func:`view_projected` reads).

    Attributes:
        cameras: V cameras on one H x W pixel grid.
        depth: float [V, H, W] the rendered depth along each camera's axis (metres; the opacity-normalised expected
            depth of :class:`toolkit.pipeline.RenderedImage`).
        opacity: float [V, H, W] accumulated opacity.
        values: name -> float [V, H, W] or [V, H, W, C] composited outputs (``albedo`` linear [.., 3],
            ``roughness``, ``metallic``), keyed like the material callable's dict.
    """

    cameras: Cameras
    depth: torch.Tensor
    opacity: torch.Tensor
    values: dict[str, torch.Tensor]

    def __post_init__(self):
        v = len(self.cameras)
        if self.depth.dim() != 3 or self.depth.shape[0] != v:
            raise ShapeError(f"ViewMaps.depth has shape {tuple(self.depth.shape)}; expected [{v}, H, W]")
        hw = tuple(self.depth.shape[1:])
        sizes = {(int(hh), int(ww)) for hh, ww in zip(self.cameras.height, self.cameras.width)}
        if sizes != {hw}:
            raise ShapeError(f"ViewMaps: the cameras are not all {hw[1]}x{hw[0]} like the maps")
        for name, t in {"opacity": self.opacity, **self.values}.items():
            if tuple(t.shape[:3]) != (v, *hw) or t.dim() > 4:
                raise ShapeError(f"ViewMaps.{name} has shape {tuple(t.shape)}; expected [{v}, {hw[0]}, {hw[1]}(, C)]")


def project_views(points: torch.Tensor, maps: ViewMaps, tolerance: float = 0.1, min_opacity: float = 0.5,
                  keys: tuple[str, ...] | None = None,
                  looks: list | None = None) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """The mean of ``maps``' values over the views that see each point.

    Args:
        points: float [N, 3] world points, metres.
        maps: the views.
        tolerance: a view sees a point when |point depth − rendered depth| < tolerance × rendered depth (depth
            floored at 0.1 m).
        min_opacity: ... and the pixel's rendered opacity is at least this.
        keys: which values (default: all).
        looks: these points' :func:`sightings` at ``maps`` (with the same ``tolerance`` and ``min_opacity``), when a
            caller that projects them again (:func:`fit_light`) computed them once for both; None: computed here.

    Returns:
        (means, count): name -> float [N(, C)] means (0 where no view sees the point) and int [N] how many views do.
    """
    if not 0 < tolerance < 1:
        raise ConfigError(f"view-bake tolerance {tolerance} must be in (0, 1)")
    keys = tuple(maps.values) if keys is None else keys
    p = torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3)
    n = p.shape[0]
    sums = {k: p.new_zeros(n, *maps.values[k].shape[3:]) for k in keys}
    count = torch.zeros(n, dtype=torch.long)
    for i, idx, r, c, _ in (sightings(p, maps, tolerance, min_opacity) if looks is None else looks):
        for k in keys:
            sums[k].index_add_(0, idx, maps.values[k][i, r, c].to(p))
        count.index_add_(0, idx, torch.ones_like(idx))
    seen = count.clamp_min(1).to(p)
    return {k: v / (seen if v.dim() == 1 else seen[:, None]) for k, v in sums.items()}, count


def sightings(points: torch.Tensor, maps: ViewMaps, tolerance: float = 0.1, min_opacity: float = 0.5) -> list:
    """Which views see which of ``points`` [N, 3] (:func:`project_views`' test), as a list with one ``(i, idx, row,
    col, depth)`` per view ``i`` that sees any: the indices of the points it sees, their pixels and their depths
    along the camera's axis. Computed once, it serves both :func:`project_views` and :func:`fit_light` (``looks``)."""
    return list(_sightings(torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3), maps, tolerance, min_opacity))


def _sightings(p: torch.Tensor, maps: ViewMaps, tolerance: float, min_opacity: float):
    """:func:`sightings`, one view at a time."""
    h, w = maps.depth.shape[1:]
    for i in range(len(maps.cameras)):
        uv, z = project_points(maps.cameras, i, p)
        col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        idx = torch.nonzero((z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)).squeeze(-1)
        r, c = row[idx], col[idx]
        d = maps.depth[i, r, c]
        ok = ((z[idx] - d).abs() < tolerance * d.clamp_min(0.1)) & (maps.opacity[i, r, c] >= min_opacity)
        if bool(ok.any()):
            yield i, idx[ok], r[ok], c[ok], z[idx[ok]]


FIT_WEIGHT_EXPONENT = 1 / 2.4 - 1
""":func:`fit_light` weighs a sighting of colour F by F ** this (−0.583: the sRGB encoding's slope). Chosen between
0 (a linear least-squares error) and twice this (the error on displayed colour) on two scenes, one seed each, and
checked on a third (README, "Detail and light fitted to the viewer"): w = 1 lets the bright sightings decide and
costs gallery 1000007 0.6 dB; the displayed error lets the darkest ones (a neighbour's shadow, an edge) decide and
costs the bundled sample 0.3 dB."""


def fit_light(points: torch.Tensor, material: dict, maps: ViewMaps, sh: torch.Tensor, tolerance: float = 0.1,
              min_opacity: float = 0.5, mesh_normals: torch.Tensor | None = None,
              looks: list | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The per-point RGB light multiplier ``m`` that makes a viewer's own shading reproduce the field's colour at
    the views that see each point.

    A GLB viewer shows ``clamp(m · shade_pbr(albedo, roughness, metallic, n, v, SH).colour)`` (``dars view``, the
    WebXR page: occlusion × light tint). Per point and channel, ``m`` minimises Σ_v w_v (m P_v − F_v)² over the
    views ``v`` that see it (:func:`project_views`' test), with ``P_v`` that shading towards camera ``v``, ``F_v``
    the field's rendered linear colour (``maps.values["rgb"]``) there and ``w_v`` = F_v^:data:`FIT_WEIGHT_EXPONENT`
    (F clamped to [1e-3, 1]): ``m = Σ w P F / Σ w P²``. That weight is the slope of the sRGB encoding at F (up to a
    constant), halfway between a linear error (w = 1) and a displayed one (the slope squared); see
    :data:`FIT_WEIGHT_EXPONENT` for why. It takes up whatever the grey occlusion gain and the field's light tint
    leave: the light the field fitted that the SH cannot express, and the mean difference between the texture's
    shading and the field's composited one.

    Args:
        points: float [N, 3] world points, metres.
        material: the texel's ``albedo`` [N, 3] (linear), ``roughness`` [N], ``metallic`` [N] and ``normal``
            [N, 3] (world), as the viewer will read them.
        maps: the views, holding ``rgb``.
        sh: float [9, 3] the SH light the viewer shades with (SPEC frame), before the multiplier.
        tolerance, min_opacity: :func:`project_views`.
        mesh_normals: float [N, 3] the mesh normals: a field normal facing away from one is folded onto its tangent
            plane, as the normal map stores it (:func:`toolkit.bake.bake_pbr_textures`).
        looks: :func:`project_views`' ``looks``.

    Returns:
        (m, count): float [N, 3] (1 where no view sees the point or the shading is black), int [N] views.
    """
    from .shading import shade_pbr

    if "rgb" not in maps.values:
        raise ConfigError(f"fit_light needs the field's colour in the view maps; they hold only {sorted(maps.values)}")
    p = torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3)
    n = p.shape[0]
    albedo = torch.as_tensor(material["albedo"], dtype=torch.float32).reshape(n, 3).clamp(0.0, 1.0)
    rough = torch.as_tensor(material["roughness"], dtype=torch.float32).reshape(n).clamp(0.0, 1.0)
    metal = torch.as_tensor(material["metallic"], dtype=torch.float32).reshape(n).clamp(0.0, 1.0)
    nrm = torch.as_tensor(material["normal"], dtype=torch.float32).reshape(n, 3)
    if mesh_normals is not None:
        mn = torch.nn.functional.normalize(torch.as_tensor(mesh_normals, dtype=torch.float32).reshape(n, 3), dim=-1)
        nrm = fold_normals(nrm, mn)
    nrm = torch.nn.functional.normalize(nrm, dim=-1, eps=1e-8)
    sh = torch.as_tensor(sh, dtype=torch.float32).reshape(9, 3)
    num, den = p.new_zeros(n, 3), p.new_zeros(n, 3)
    count = torch.zeros(n, dtype=torch.long)
    origins = maps.cameras.origins.to(p)
    for i, idx, r, c, _ in (sightings(p, maps, tolerance, min_opacity) if looks is None else looks):
        v = torch.nn.functional.normalize(origins[i] - p[idx], dim=-1, eps=1e-8)
        shaded = shade_pbr(albedo[idx], rough[idx], metal[idx], nrm[idx], v, sh).colour
        target = maps.values["rgb"][i, r, c].to(p)
        wt = target.clamp(1e-3, 1.0) ** FIT_WEIGHT_EXPONENT
        num.index_add_(0, idx, wt * shaded * target)
        den.index_add_(0, idx, wt * shaded * shaded)
        count.index_add_(0, idx, torch.ones_like(idx))
    ok = den > 1e-8
    m = torch.where(ok, num / den.clamp_min(1e-8), torch.ones_like(num)).clamp_min(0.0)
    return m, count


def view_projected(material_fn: Callable, maps: ViewMaps, tolerance: float = 0.1, min_opacity: float = 0.5,
                   keys: tuple[str, ...] = ("albedo",), stats: dict[str, Any] | None = None) -> Callable:
    """``material_fn`` with ``keys`` taken from the views that see each point (:func:`project_views`); points no
    view sees keep ``material_fn``'s value. ``stats`` (a dict) accumulates ``points`` and ``seen`` (points at least
    one view saw) over the calls. The callable takes ``(points, normals=None, looks=None)``: ``looks``, the points'
    :func:`sightings`, when the caller needs them too (:func:`toolkit.asset.bake_mesh`'s light fit)."""
    missing = [k for k in keys if k not in maps.values]
    if missing:
        raise ConfigError(f"view-projected bake of {missing}: the view maps hold only {sorted(maps.values)}")

    def fn(points, normals=None, looks=None):
        out = dict(material_fn(points, normals))
        means, count = project_views(points, maps, tolerance, min_opacity, keys, looks)
        seen = count > 0
        for k in keys:
            if k in out:
                base = torch.as_tensor(out[k]).to(torch.float32).clone()
            elif k == "normal" and normals is not None:  # no field normal: the interpolated mesh normal
                base = torch.as_tensor(normals, dtype=torch.float32).reshape(-1, 3).clone()
            else:  # the callable lacks the key: unseen points get the bake's default
                base = torch.as_tensor(VIEW_DEFAULTS[k], dtype=torch.float32).expand_as(means[k]).clone()
            base[seen] = means[k][seen]
            out[k] = base
        if stats is not None:
            stats["points"] = stats.get("points", 0) + int(count.numel())
            stats["seen"] = stats.get("seen", 0) + int(seen.sum())
        return out

    return fn


def face_texture_blur(vertices, faces, uvs, maps: ViewMaps, texture_size: int, tolerance: float = 0.1,
                      min_opacity: float = 0.5) -> torch.Tensor:
    """How blurred the view-projected texture is on each face, in texels: the footprint of a view pixel on the
    face along its longer axis, over a texel's side, root mean square over the views that see the face.

    A texel takes the pixel it falls in at each view that sees it, so the baked detail is no finer than those
    pixels: a 2048² atlas of a room photographed at 128 px holds from ~4 texels per view pixel on a near wall seen
    square-on to tens on the floor seen at a grazing angle. A viewer's mip-map blurs a second time what the bake
    already blurred once; ``dars view`` and the WebXR page narrow their texture filter by this blur (the GLB's
    ``_TEXTURE_BLUR`` vertex attribute; :mod:`viewers.preview`).

    Per face (centroid, its world area over its UV area × ``texture_size``²: a texel's side ``s``), at every view
    that sees the centroid (:func:`project_views`' test) the pixel's longer side on the face is z / (f · |cos θ|)
    (z the depth along the camera's axis, f = √(fx · fy), θ between the view ray and the face normal, |cos θ| ≥
    0.2) — the axis a viewer's isotropic mip selection measures too.

    Args:
        vertices: float [V, 3] world positions, metres; faces: int [F, 3]; uvs: float [V, 2] atlas coordinates.
        maps: the views the texture was baked from (their own pixel grid and intrinsics).
        texture_size: the atlas's side in texels.
        tolerance, min_opacity: :func:`project_views`.

    Returns:
        float32 [F] texels; 0 where no view sees the face or its UV area is empty.
    """
    v = torch.as_tensor(vertices, dtype=torch.float32).reshape(-1, 3)
    f = torch.as_tensor(faces, dtype=torch.long).reshape(-1, 3)
    uv = torch.as_tensor(uvs, dtype=torch.float32).reshape(-1, 2)
    p = v[f]
    cross = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = 0.5 * cross.norm(dim=1)
    normal = cross / (2.0 * area).clamp_min(1e-12)[:, None]
    t = uv[f] * float(texture_size)
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    texels = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).abs()
    ok = (texels > 1e-6) & (area > 1e-12)
    side2 = area / texels.clamp_min(1e-6)  # a texel's side², m²
    centre = p.mean(1)
    k2_sum = torch.zeros(len(f))
    n_views = torch.zeros(len(f))
    origins = maps.cameras.origins.to(centre)
    for i, idx, _, _, z in _sightings(centre, maps, tolerance, min_opacity):
        ray = centre[idx] - origins[i]
        cos = ((ray * normal[idx]).sum(1).abs() / ray.norm(dim=1).clamp_min(1e-9)).clamp_min(0.2)
        focal2 = float(maps.cameras.fx[i]) * float(maps.cameras.fy[i])
        k2_sum[idx] += z ** 2 / (focal2 * cos ** 2 * side2[idx])
        n_views[idx] += 1
    keep = ok & (n_views > 0)
    out = torch.zeros(len(f))
    out[keep] = (k2_sum[keep] / n_views[keep]).sqrt()
    return out


def vertex_texture_blur(faces, face_blur, num_vertices: int) -> torch.Tensor:
    """:func:`face_texture_blur` at the vertices (what a GLB stores and a viewer interpolates): the mean over the
    faces around each vertex that have one (0 where none has)."""
    f = torch.as_tensor(faces, dtype=torch.long).reshape(-1, 3)
    b = torch.as_tensor(face_blur, dtype=torch.float32).reshape(-1)
    has = (b > 0).float()
    total = torch.zeros(num_vertices).index_add_(0, f.reshape(-1), b.repeat_interleave(3))
    count = torch.zeros(num_vertices).index_add_(0, f.reshape(-1), has.repeat_interleave(3))
    return torch.where(count > 0, total / count.clamp_min(1.0), torch.zeros(num_vertices))


class VertexValues:
    """``values`` [V, C] of ``mesh``'s vertices, read at any points by barycentric interpolation on the closest
    face (the texels of a bake lie on the mesh, so that is their own face): how :func:`toolkit.asset.build_asset`'s
    viewer fit carries its per-vertex light factor to the texels.

    Example:
        >>> VertexValues(mesh, np.ones((mesh.num_vertices, 3)))(points).shape      # doctest: +SKIP
        torch.Size([N, 3])
    """

    def __init__(self, mesh, values: np.ndarray) -> None:
        self.faces = np.asarray(mesh.faces, np.int64)
        self.values = np.asarray(values, np.float32)
        if self.values.shape[0] != len(np.asarray(mesh.vertices)):
            raise ValueError(f"VertexValues: {self.values.shape[0]} values for {len(np.asarray(mesh.vertices))} "
                             "vertices")
        self.scene = ray_scene(mesh.vertices, self.faces)

    def __call__(self, points) -> torch.Tensor:
        import open3d as o3d

        p = torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3).cpu().numpy()
        q = self.scene.compute_closest_points(o3d.core.Tensor(p))
        prim = q["primitive_ids"].numpy().astype(np.int64)
        b = q["primitive_uvs"].numpy()
        bary = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], 1)
        v = self.values[self.faces[prim]]  # [N, 3 corners, C]
        return torch.as_tensor((v * bary[:, :, None]).sum(1), dtype=torch.float32)
