"""Stage 13d — the backdrop: what a GLB's viewer draws where the mesh is not (what the field drew there).

The GLB holds the room's surfaces; the sky over a gallery without a ceiling, the view out of a window and the
white behind an object photographed on a transparent background are not surfaces, and the mesh region leaves them
out on purpose. The field drew them with its learned background (:class:`toolkit.pipeline.Background`, a
lat-long radiance map), and a preview without it drew the SH light's radiance there instead: on validation gallery
1000000 the pixels the mesh does not cover held 65 % of the preview's squared error (README, "The GLB against its
field").

The background map is trained only along the directions in which the training rays left the scene. In a closed
room almost no ray does, and its texels keep their start value. So the backdrop carries, beside the radiance, a
**visibility** per texel: the mean transmittance (1 − rendered opacity) of the training pixels whose ray points into
that texel (:func:`background_visibility`, from the same renders as the view-projected bake); texels no training
pixel points into get 0. A viewer draws ``visibility · backdrop + (1 − visibility) · SH radiance`` behind the mesh:
the learned background where the photos saw it, the light's radiance elsewhere (as before).

That map is not all the field draws beyond the mesh, though: over an open gallery the field also puts density far
out in its contracted shell (clouds, the sun's glow), and wherever the mesh has a hole the field is opaque behind
it. So when the GLB's mesh is known (:func:`mesh_coverage`: which training pixels a one-sided viewer would draw it
on) and the renders carry the field's colour, every texel that some uncovered training pixel points into takes the
mean rendered colour of those pixels (averaged as photos are shown: clamped, sRGB-encoded), at visibility 1
(:func:`backdrop_from_views`, a 32×64 map). The other texels take the colour of the nearest texel that was seen,
keeping the background map's visible share, also at visibility 1: a test view looks through a hole in the mesh in
directions no training view did, and what the field drew behind it is nearer that colour than the light's radiance
(on validation gallery 1000007, +1.4 dB preview over three seeds; README). On the validation galleries the
uncovered pixels were 7-15 % of the test views but 30-53 % of the preview's squared error before this.

The GLB stores it in its root ``extras.dars.backdrop`` (:meth:`Backdrop.to_json`); :func:`export.gltf.load_glb`
reads it back, :mod:`viewers.preview` draws it (``PreviewConfig.background``).

Example:
    >>> maps = field.views(depth_cameras(field.cameras, 300_000))     # doctest: +SKIP
    >>> covered = mesh_coverage(mesh.vertices, mesh.faces, maps.cameras)  # doctest: +SKIP
    >>> backdrop = backdrop_from_views(field.background, maps, covered)   # doctest: +SKIP
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ._checks import SceneError, ShapeError
from .bake import ray_scene
from .cameras import generate_rays
from .io import linear_to_srgb, srgb_to_linear
from .sh import latlong_angles, latlong_directions, lookup_latlong

__all__ = ["Backdrop", "background_visibility", "backdrop_from_views", "front_hits", "mesh_coverage"]

CONVENTION = ("lat-long, world frame (+z up): row 0 at +z, pixel centres at theta = pi (row + 0.5) / h and "
              "phi = atan2(x, y) = 2 pi (col + 0.5) / w; bilinear, wrapping in phi, clamped in theta; radiance linear")

CONSTANT_SHAPE = (16, 32)
"""Lat-long size of the backdrop of a constant (one-colour) background: the visibility's resolution."""

UNCOVERED_SHAPE = (32, 64)
"""Lat-long size of a backdrop made from the field's colour where the mesh is not (:func:`backdrop_from_views`)."""


@dataclass(frozen=True)
class Backdrop:
    """The background a viewer draws behind the mesh (module docstring).

    Attributes:
        radiance: float32 [h, w, 3] linear radiance, lat-long (:data:`CONVENTION`).
        visibility: float32 [h, w] in [0, 1]: how much of the training photos' light came from beyond the mesh in
            each texel's direction (1 where the field's colour was taken; 0: never seen, the viewer draws the SH
            radiance there).
    """

    radiance: np.ndarray
    visibility: np.ndarray

    def __post_init__(self):
        r, v = np.asarray(self.radiance), np.asarray(self.visibility)
        if r.ndim != 3 or r.shape[2] != 3 or r.shape[0] < 1 or r.shape[1] < 1:
            raise ShapeError(f"Backdrop.radiance has shape {r.shape}; expected [h, w, 3]")
        if v.shape != r.shape[:2]:
            raise ShapeError(f"Backdrop.visibility has shape {v.shape}; expected {r.shape[:2]} like the radiance")
        if not (np.isfinite(r).all() and np.isfinite(v).all()):
            raise SceneError("Backdrop: non-finite radiance or visibility")
        object.__setattr__(self, "radiance", np.ascontiguousarray(np.clip(r, 0.0, None), np.float32))
        object.__setattr__(self, "visibility", np.ascontiguousarray(np.clip(v, 0.0, 1.0), np.float32))

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w)."""
        return int(self.radiance.shape[0]), int(self.radiance.shape[1])

    def sample(self, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(radiance [R, 3], visibility [R]) along unit world directions [R, 3], filtered as a viewer does."""
        both = torch.cat([torch.from_numpy(self.radiance), torch.from_numpy(self.visibility)[..., None]], -1)
        v = lookup_latlong(both.to(directions), directions)
        return v[:, :3], v[:, 3]

    def to_json(self) -> dict:
        """The GLB's ``extras.dars.backdrop`` (lossless to float32 within JSON's decimal digits)."""
        h, w = self.shape
        return {"convention": CONVENTION, "height": h, "width": w,
                "radiance": [round(float(x), 6) for x in self.radiance.reshape(-1)],
                "visibility": [round(float(x), 4) for x in self.visibility.reshape(-1)]}

    @classmethod
    def from_json(cls, d: dict, source: str = "extras.dars.backdrop") -> "Backdrop":
        """Read :meth:`to_json`'s dict back.

        Raises:
            SceneError: missing keys or sizes that do not match (naming ``source``).
        """
        try:
            h, w = int(d["height"]), int(d["width"])
            r = np.asarray(d["radiance"], np.float32)
            v = np.asarray(d["visibility"], np.float32)
        except (KeyError, TypeError, ValueError) as e:
            raise SceneError(f"{source}: not a backdrop ({type(e).__name__}: {e}); re-export the asset") from e
        if h < 1 or w < 1 or r.size != h * w * 3 or v.size != h * w:
            raise SceneError(f"{source}: {r.size} radiance and {v.size} visibility values for a {h}x{w} map; "
                             "re-export the asset")
        return cls(r.reshape(h, w, 3), v.reshape(h, w))


def _view_texels(cams, i: int, h: int, w: int) -> torch.Tensor:
    """int [H·W] the lat-long texel each pixel of view ``i`` of ``cams`` (on the CPU) looks into, row-major."""
    d = generate_rays(cams, [i]).directions
    return _texel_of(d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12), h, w)


def _texel_of(directions: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """int [R] the lat-long texel (row-major) a unit direction falls in."""
    theta, phi = latlong_angles(directions)
    r = (theta / math.pi * h).long().clamp(0, h - 1)
    c = (phi / (2 * math.pi) * w).long().clamp(0, w - 1)
    return r * w + c


def background_visibility(views, height: int, width: int) -> np.ndarray:
    """float32 [height, width]: per lat-long texel, the mean transmittance (1 − opacity) of the pixels of ``views``
    (:class:`toolkit.viewbake.ViewMaps`, the field's renders at its training cameras) whose ray points into it;
    0 where no pixel does."""
    if height < 1 or width < 1:
        raise ShapeError(f"background_visibility: a {height}x{width} map")
    total = torch.zeros(height * width, dtype=torch.float64)
    count = torch.zeros(height * width, dtype=torch.float64)
    cams = views.cameras.to("cpu")
    for i in range(len(cams)):
        t = _view_texels(cams, i, height, width)
        total.index_add_(0, t, (1.0 - views.opacity[i].reshape(-1).double()).clamp(0.0, 1.0))
        count.index_add_(0, t, torch.ones_like(t, dtype=torch.float64))
    vis = torch.where(count > 0, total / count.clamp_min(1.0), torch.zeros_like(total))
    return vis.reshape(height, width).float().numpy()


def front_hits(scene, origins: np.ndarray, directions: np.ndarray, extent: float,
               passes: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The first front-facing (counter-clockwise) triangle each ray meets, as a viewer that culls back faces (the
    GLB's default) draws it: a ray that meets a back face first goes on through it, up to ``passes`` times.

    Args:
        scene: :func:`toolkit.bake.ray_scene` of the mesh.
        origins, directions: float [N, 3] rays (any length of direction).
        extent: the mesh's size (m); a ray restarts 1e-5 of it behind a back face.

    Returns:
        (face index int64 [N], -1 where no front face is met; barycentric (u, v) float32 [N, 2] of the hit on that
        face, Open3D's convention: the point is (1 - u - v) a + u b + v c).
    """
    import open3d as o3d

    o = np.asarray(origins, np.float32).copy()
    d = np.asarray(directions, np.float32)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    prim = np.full(o.shape[0], -1, np.int64)
    bary = np.zeros((o.shape[0], 2), np.float32)
    eps = 1e-5 * (float(extent) + 1e-6)
    idx = np.arange(o.shape[0])
    for _ in range(passes):
        ans = scene.cast_rays(o3d.core.Tensor(np.concatenate([o[idx], d[idx]], 1)))
        t = ans["t_hit"].numpy()
        hit = np.isfinite(t)
        front = hit & ((ans["primitive_normals"].numpy() * d[idx]).sum(1) < 0)
        prim[idx[front]] = ans["primitive_ids"].numpy()[front].astype(np.int64)
        bary[idx[front]] = ans["primitive_uvs"].numpy()[front]
        on = hit & ~front                                      # a back face: look behind it
        o[idx[on]] = o[idx[on]] + (t[on, None] + eps) * d[idx[on]]
        idx = idx[on]
        if idx.size == 0:
            break
    return prim, bary


def mesh_coverage(vertices: np.ndarray, faces: np.ndarray, cameras, passes: int = 4) -> torch.Tensor:
    """bool [V, H, W]: the pixels of ``cameras`` (one pixel grid) on which a one-sided mesh is drawn — the ray meets
    a triangle from its front (counter-clockwise) side, as in a viewer that culls back faces (the GLB's default;
    :func:`front_hits`). Open3D's ray casting, CPU."""
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.uint32)
    cams = cameras.to("cpu")
    hw = (int(cams.height[0]), int(cams.width[0]))
    out = torch.zeros(len(cams), *hw, dtype=torch.bool)
    if f.size == 0:
        return out
    scene = ray_scene(v, f)
    extent = float(np.linalg.norm(v.max(0) - v.min(0)))
    for i in range(len(cams)):
        rays = generate_rays(cams, [i])
        prim, _ = front_hits(scene, rays.origins.numpy(), rays.directions.numpy(), extent, passes)
        out[i] = torch.from_numpy((prim >= 0).reshape(hw))
    return out


def _uncovered_radiance(views, covered: torch.Tensor, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean rendered colour [height, width, 3], pixel count [height, width]) per lat-long texel of the pixels of
    ``views`` (which must hold ``rgb``) that ``covered`` (bool [V, H, W]) leaves out.

    The mean is taken as the photos are shown and scored: each colour clamped to [0, 1] and sRGB-encoded, the mean
    decoded back to linear radiance. A linear mean lets a few very bright pixels own the texel: in a room, one
    texel sees the dark ceiling from most cameras and a skylight or a lamp from a few, and the linear mean drew the
    whole ceiling pale. The cost: a texel's radiance is at most 1, so a viewer that lowers the exposure shows a
    bright sky grey instead of keeping its HDR level."""
    total = torch.zeros(height * width, 3, dtype=torch.float64)
    count = torch.zeros(height * width, dtype=torch.float64)
    cams = views.cameras.to("cpu")
    for i in range(len(cams)):
        keep = ~covered[i].reshape(-1)
        if not bool(keep.any()):
            continue
        t = _view_texels(cams, i, height, width)[keep]
        shown = linear_to_srgb(views.values["rgb"][i].reshape(-1, 3)[keep].double().clamp(0.0, 1.0))
        total.index_add_(0, t, shown)
        count.index_add_(0, t, torch.ones_like(t, dtype=torch.float64))
    mean = srgb_to_linear(total / count.clamp_min(1.0)[:, None])
    return mean.reshape(height, width, 3).float().numpy(), count.reshape(height, width).numpy()


def backdrop_from_views(radiance: torch.Tensor | np.ndarray, views, covered: torch.Tensor | None = None,
                        shape: tuple[int, int] = UNCOVERED_SHAPE) -> Backdrop:
    """The :class:`Backdrop` of a field: its learned background map (float [h, w, 3] linear radiance:
    :meth:`toolkit.pipeline.Background.radiance_map`) with its visibility from ``views``
    (:func:`background_visibility`).

    With ``covered`` (bool [V, H, W], :func:`mesh_coverage` of the GLB's mesh at ``views``' cameras) and the field's
    colour in ``views`` (``values["rgb"]``): each texel of a ``shape`` map that some training pixel the mesh leaves
    out points into holds the mean field colour of those pixels, at visibility 1 — everything the field drew there,
    far-away density (clouds, a skyline) and the holes in the mesh included, not only its background map; the other
    texels keep the background map and its visibility, resampled to ``shape``."""
    rad = torch.as_tensor(radiance).detach().float().cpu().numpy()
    if rad.ndim != 3 or rad.shape[2] != 3:
        raise ShapeError(f"backdrop_from_views: radiance has shape {rad.shape}; expected [h, w, 3]")
    if rad.shape[:2] == (1, 1):  # a constant background: the visibility still varies with direction
        rad = np.repeat(np.repeat(rad, CONSTANT_SHAPE[0], 0), CONSTANT_SHAPE[1], 1)
    base = Backdrop(rad, background_visibility(views, rad.shape[0], rad.shape[1]))
    if covered is None or "rgb" not in views.values:
        return base
    h, w = shape
    if tuple(covered.shape) != tuple(views.opacity.shape):
        raise ShapeError(f"backdrop_from_views: covered has shape {tuple(covered.shape)}; expected "
                         f"{tuple(views.opacity.shape)} like the views")
    centres = latlong_directions(h, w).reshape(-1, 3)
    base_rad, base_vis = base.sample(centres)
    colour, count = _uncovered_radiance(views, covered, h, w)
    seen = count > 0
    base_rad = base_rad.reshape(h, w, 3).numpy()
    base_vis = base_vis.reshape(h, w).numpy()
    if not seen.any():
        return Backdrop(base_rad, base_vis)
    # texels no uncovered training pixel looked into: a test view can still look there through a hole in the mesh.
    # Behind a hole is what the field drew in the nearest direction that was seen, not the light arriving (the SH
    # radiance a viewer draws at visibility 0: in a room, the bright light from above over a dark ceiling). Where the
    # learned background was visible it keeps its share.
    near = _fill_from_neighbours(colour, seen)
    fill = base_vis[..., None] * base_rad + (1.0 - base_vis[..., None]) * near
    out_rad = np.where(seen[..., None], colour, fill)
    return Backdrop(out_rad, np.ones((h, w), np.float32))


def _fill_from_neighbours(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """float [h, w, C] lat-long ``values`` with every texel outside ``known`` (bool [h, w], at least one True) set
    to the mean of its known 4-neighbours, grown ring by ring from the known texels (wrapping in phi, clamped in
    theta)."""
    v = np.where(known[..., None], values, 0.0).astype(np.float64)
    k = known.copy()
    while not k.all():
        total = np.zeros_like(v)
        n = np.zeros(k.shape, np.float64)
        for shifted_v, shifted_k in ((np.roll(v, 1, 1), np.roll(k, 1, 1)), (np.roll(v, -1, 1), np.roll(k, -1, 1)),
                                     (np.concatenate([v[:1], v[:-1]]), np.concatenate([k[:1], k[:-1]])),
                                     (np.concatenate([v[1:], v[-1:]]), np.concatenate([k[1:], k[-1:]]))):
            total += np.where(shifted_k[..., None], shifted_v, 0.0)
            n += shifted_k
        grow = ~k & (n > 0)
        v[grow] = total[grow] / n[grow][:, None]
        k = k | grow
    return v.astype(np.float32)
