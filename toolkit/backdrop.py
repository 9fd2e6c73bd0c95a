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

**Box projection.** A lat-long map keyed by direction alone is a backdrop at infinity: right for a sky, wrong for a
floor seen through a hole in the mesh, whose colour depends on where the camera stands as much as on where it looks
(every camera that looked down into one texel saw a different patch of floor, and the texel holds their average).
When the run has a room box (:func:`toolkit.layout.fit_room_layout`), the backdrop carries a second map keyed by
where each ray leaves the box (:class:`BoxProjection`, the parallax-corrected cube maps of real-time rendering): a
ray that leaves through a face the layout is confident of looks the map up in the direction from the box's centre
to its exit point; one that leaves through any other face (an open top, a window wall nothing confirmed) keeps the
direction map. The box map is built from the same uncovered training pixels, at 64×128, with a per-texel weight: 1
where its colour explains the training pixels keyed to it at least as well as the direction map does (squared error
of the shown colours), else 0 — so sky seen over a low wall stays on the direction map. On the mesh holes of the
test views of three validation galleries, the bundled sample without its box and the real fox, it lowered the
squared error against the photos by 17-57 % (README, "A backdrop on the room's box").

The GLB stores it in its root ``extras.dars.backdrop`` (:meth:`Backdrop.to_json`); :func:`export.gltf.load_glb`
reads it back, :mod:`viewers.preview` draws it (``PreviewConfig.background``).

Example:
    >>> maps = field.views(depth_cameras(field.cameras, 300_000))     # doctest: +SKIP
    >>> covered = mesh_coverage(mesh.vertices, mesh.faces, maps.cameras)  # doctest: +SKIP
    >>> backdrop = backdrop_from_views(field.background, maps, covered)   # doctest: +SKIP
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from ._checks import SceneError, ShapeError
from .bake import ray_scene
from .cameras import generate_rays
from .io import linear_to_srgb, srgb_to_linear
from .sh import latlong_angles, latlong_directions, lookup_latlong

__all__ = ["Backdrop", "BoxProjection", "background_visibility", "backdrop_from_views", "front_hits", "mesh_coverage"]

CONVENTION = ("lat-long, world frame (+z up): row 0 at +z, pixel centres at theta = pi (row + 0.5) / h and "
              "phi = atan2(x, y) = 2 pi (col + 0.5) / w; bilinear, wrapping in phi, clamped in theta; radiance linear")

CONSTANT_SHAPE = (16, 32)
"""Lat-long size of the backdrop of a constant (one-colour) background: the visibility's resolution."""

UNCOVERED_SHAPE = (32, 64)
"""Lat-long size of a backdrop made from the field's colour where the mesh is not (:func:`backdrop_from_views`)."""

BOX_SHAPE = (64, 128)
"""Lat-long size of the box-projected map (:class:`BoxProjection`): a texel spans about 0.3 m of a 6 m room's wall."""

BOX_CONVENTION = ("a ray from the eye o along d leaves the box {origin + axes^T q : lo <= q <= hi} (axes: rows, "
                  "world) at p = o + t d, t the least of the slabs' far distances (the ray meets the box when it "
                  "exceeds the greatest near distance and 0); when the face it leaves by (order -a, +a, -b, +b, floor, "
                  "ceiling: axis k = index // 2, hi when index is odd) is in faces, the box map is read in the "
                  "direction normalize(p - centre) (lat-long as the backdrop) and its rgb mixed over the "
                  "direction map's colour by its weight; otherwise the direction map alone")


@dataclass(frozen=True)
class BoxProjection:
    """The box a backdrop's second map is projected on (module docstring, "Box projection"): a room box in the
    world frame and the faces whose exit points key the map.

    Attributes:
        origin: float [3] the box frame's origin (world).
        axes: float [3, 3] rows: the box's axes (world, orthonormal).
        lo, hi: float [3] the faces' coordinates along the axes.
        faces: bool [6] the faces that key the box map (order -a, +a, -b, +b, floor, ceiling).
        centre: float [3] world point the map's directions are taken from.
    """

    origin: np.ndarray
    axes: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    faces: np.ndarray
    centre: np.ndarray

    def __post_init__(self):
        arrays = {"origin": (self.origin, (3,)), "axes": (self.axes, (3, 3)), "lo": (self.lo, (3,)),
                  "hi": (self.hi, (3,)), "centre": (self.centre, (3,))}
        for name, (a, shape) in arrays.items():
            a = np.asarray(a, np.float64)
            if a.shape != shape or not np.isfinite(a).all():
                raise ShapeError(f"BoxProjection.{name} has shape {a.shape} (or is not finite); expected {shape}")
            object.__setattr__(self, name, a)
        f = np.asarray(self.faces, bool).reshape(-1)
        if f.shape != (6,):
            raise ShapeError(f"BoxProjection.faces has {f.size} entries; expected 6")
        object.__setattr__(self, "faces", f)
        if not (self.hi > self.lo).all():
            raise SceneError(f"BoxProjection: hi {self.hi.tolist()} must exceed lo {self.lo.tolist()} on every axis")

    @classmethod
    def from_layout(cls, layout) -> "BoxProjection | None":
        """The projection on a :class:`toolkit.layout.RoomLayout`'s confident faces, centred in its box; None when
        no face is confident."""
        faces = np.asarray(layout.confident, bool)
        if not faces.any():
            return None
        axes = np.asarray(layout.axes, np.float64)
        centre = np.asarray(layout.origin, np.float64) + axes.T @ ((np.asarray(layout.lo) + np.asarray(layout.hi)) / 2)
        return cls(layout.origin, axes, layout.lo, layout.hi, faces, centre)

    def keys(self, origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(unit map directions float [R, 3], on_box bool [R]) of rays ``origins`` / ``directions`` (world, [R, 3];
        directions of any length): where each ray leaves the box, seen from :attr:`centre`, and whether it leaves
        through one of :attr:`faces` (:data:`BOX_CONVENTION`). An eye outside the box looks through it: the exit
        is where the ray leaves it after entering; a ray that misses the box is not on it."""
        o = origins.double()
        d = directions.double()
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        as_t = functools.partial(torch.as_tensor, dtype=o.dtype, device=o.device)
        axes = as_t(self.axes)
        ob = (o - as_t(self.origin)) @ axes.T
        q = d @ axes.T
        q = torch.where(q.abs() < 1e-12, torch.full_like(q, 1e-12), q)
        t1, t2 = (as_t(self.lo) - ob) / q, (as_t(self.hi) - ob) / q      # the slabs
        t_far, k = torch.maximum(t1, t2).min(-1)
        t_near = torch.minimum(t1, t2).max(-1).values
        face = 2 * k + torch.gather((q > 0).long(), -1, k[..., None])[..., 0]
        on = (t_far > t_near.clamp_min(0.0)) & torch.from_numpy(self.faces).to(face.device)[face]
        p = o + torch.where(on, t_far, torch.zeros_like(t_far))[:, None] * d
        key = torch.where(on[:, None], p - as_t(self.centre), d)
        return (key / key.norm(dim=-1, keepdim=True).clamp_min(1e-12)).to(directions.dtype), on

    def to_json(self) -> dict:
        return {"convention": BOX_CONVENTION, "origin": self.origin.tolist(), "axes": self.axes.tolist(),
                "lo": self.lo.tolist(), "hi": self.hi.tolist(), "faces": [bool(x) for x in self.faces],
                "centre": self.centre.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> "BoxProjection":
        return cls(np.asarray(d["origin"], np.float64), np.asarray(d["axes"], np.float64).reshape(3, 3),
                   np.asarray(d["lo"], np.float64), np.asarray(d["hi"], np.float64),
                   np.asarray(d["faces"], bool), np.asarray(d["centre"], np.float64))


@dataclass(frozen=True)
class Backdrop:
    """The background a viewer draws behind the mesh (module docstring).

    Attributes:
        radiance: float32 [h, w, 3] linear radiance, lat-long (:data:`CONVENTION`).
        visibility: float32 [h, w] in [0, 1]: how much of the training photos' light came from beyond the mesh in
            each texel's direction (1 where the field's colour was taken; 0: never seen, the viewer draws the SH
            radiance there).
        box: the :class:`BoxProjection` of ``box_radiance``, or None (a backdrop at infinity only).
        box_radiance: float32 [h2, w2, 3] linear radiance keyed by where a ray leaves the box (lat-long from its
            centre), or None.
        box_weight: float32 [h2, w2] in [0, 1]: how much of the box map a viewer mixes over the direction map.
    """

    radiance: np.ndarray
    visibility: np.ndarray
    box: BoxProjection | None = None
    box_radiance: np.ndarray | None = None
    box_weight: np.ndarray | None = None

    def __post_init__(self):
        r, v = _checked_map(self.radiance, self.visibility, "radiance", "visibility")
        object.__setattr__(self, "radiance", r)
        object.__setattr__(self, "visibility", v)
        parts = (self.box is None, self.box_radiance is None, self.box_weight is None)
        if len(set(parts)) != 1:
            raise ShapeError("Backdrop: box, box_radiance and box_weight come together (all or none)")
        if self.box is not None:
            br, bw = _checked_map(self.box_radiance, self.box_weight, "box_radiance", "box_weight")
            object.__setattr__(self, "box_radiance", br)
            object.__setattr__(self, "box_weight", bw)

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w)."""
        return int(self.radiance.shape[0]), int(self.radiance.shape[1])

    def rgba(self, box: bool = False) -> np.ndarray:
        """float32 [h, w, 4]: the direction map's radiance and visibility, or (``box``) the box map's radiance and
        weight — as a viewer uploads them."""
        rgb, alpha = (self.box_radiance, self.box_weight) if box else (self.radiance, self.visibility)
        return np.ascontiguousarray(np.concatenate([rgb, alpha[..., None]], 2), np.float32)

    def sample(self, directions: torch.Tensor, origins: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(radiance [R, 3], visibility [R]) along unit world directions [R, 3], filtered as a viewer does; with the
        rays' ``origins`` (world [R, 3], the eye) and a box map, the box map mixed in where a ray leaves the box
        through one of its faces (:data:`BOX_CONVENTION`). A viewer draws ``visibility · radiance + (1 −
        visibility) · SH radiance``."""
        v = lookup_latlong(torch.from_numpy(self.rgba()).to(directions), directions)
        rad, vis = v[:, :3], v[:, 3]
        if self.box is None or origins is None:
            return rad, vis
        keys, on = self.box.keys(origins, directions)
        b = lookup_latlong(torch.from_numpy(self.rgba(box=True)).to(directions), keys)
        w = torch.where(on, b[:, 3], torch.zeros_like(vis))
        # mix(mix(sky, far, vis), box, w) as one (radiance, visibility) pair
        vis_out = w + (1 - w) * vis
        rad_out = (w[:, None] * b[:, :3] + ((1 - w) * vis)[:, None] * rad) / vis_out.clamp_min(1e-12)[:, None]
        return torch.where(vis_out[:, None] > 0, rad_out, rad), vis_out

    def to_json(self) -> dict:
        """The GLB's ``extras.dars.backdrop`` (lossless to float32 within JSON's decimal digits)."""
        out = {"convention": CONVENTION, **_map_json(self.radiance, self.visibility, "visibility")}
        if self.box is not None:
            out["box"] = {**self.box.to_json(), **_map_json(self.box_radiance, self.box_weight, "weight")}
        return out

    @classmethod
    def from_json(cls, d: dict, source: str = "extras.dars.backdrop") -> "Backdrop":
        """Read :meth:`to_json`'s dict back.

        Raises:
            SceneError: missing keys or sizes that do not match (naming ``source``).
        """
        r, v = _read_map(d, "visibility", source, "not a backdrop")
        if "box" not in d:
            return cls(r, v)
        try:
            box = BoxProjection.from_json(d["box"])
        except (KeyError, TypeError, ValueError, ShapeError, SceneError) as e:
            raise SceneError(f"{source}.box: not a box projection ({type(e).__name__}: {e}); re-export the "
                             "asset") from e
        br, bw = _read_map(d["box"], "weight", f"{source}.box", "not a box projection")
        return cls(r, v, box, br, bw)


def _checked_map(rgb, alpha, rgb_name: str, alpha_name: str) -> tuple[np.ndarray, np.ndarray]:
    """A lat-long map's float32 radiance [h, w, 3] (clipped at 0) and its alpha [h, w] (visibility or weight,
    clipped to [0, 1]), checked for shape and finite values (:class:`Backdrop`'s two maps)."""
    r, a = np.asarray(rgb), np.asarray(alpha)
    if r.ndim != 3 or r.shape[2] != 3 or r.shape[0] < 1 or r.shape[1] < 1:
        raise ShapeError(f"Backdrop.{rgb_name} has shape {r.shape}; expected [h, w, 3]")
    if a.shape != r.shape[:2]:
        raise ShapeError(f"Backdrop.{alpha_name} has shape {a.shape}; expected {r.shape[:2]} like the {rgb_name}")
    if not (np.isfinite(r).all() and np.isfinite(a).all()):
        raise SceneError(f"Backdrop: non-finite {rgb_name} or {alpha_name}")
    return (np.ascontiguousarray(np.clip(r, 0.0, None), np.float32),
            np.ascontiguousarray(np.clip(a, 0.0, 1.0), np.float32))


def _map_json(rgb: np.ndarray, alpha: np.ndarray, alpha_key: str) -> dict:
    """One of :class:`Backdrop`'s maps as JSON: its size, ``radiance`` and ``alpha_key`` (flat, row-major)."""
    return {"height": int(rgb.shape[0]), "width": int(rgb.shape[1]),
            "radiance": [round(float(x), 6) for x in rgb.reshape(-1)],
            alpha_key: [round(float(x), 4) for x in alpha.reshape(-1)]}


def _read_map(d: dict, alpha_key: str, source: str, what: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_map_json`'s dict back as (radiance [h, w, 3], alpha [h, w]).

    Raises:
        SceneError: missing keys (``what``) or sizes that do not match, naming ``source``."""
    try:
        h, w = int(d["height"]), int(d["width"])
        r = np.asarray(d["radiance"], np.float32)
        a = np.asarray(d[alpha_key], np.float32)
    except (KeyError, TypeError, ValueError) as e:
        raise SceneError(f"{source}: {what} ({type(e).__name__}: {e}); re-export the asset") from e
    if h < 1 or w < 1 or r.size != h * w * 3 or a.size != h * w:
        raise SceneError(f"{source}: {r.size} radiance and {a.size} {alpha_key} values for a {h}x{w} map; "
                         "re-export the asset")
    return r.reshape(h, w, 3), a.reshape(h, w)


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


def _uncovered_pixels(views, covered: torch.Tensor, box: BoxProjection | None = None):
    """Per training view with uncovered pixels: (view index, unit key directions [N, 3], shown colours float64
    [N, 3]: clamped, sRGB-encoded) of the pixels of ``views`` that ``covered`` leaves out — keyed by direction, or
    with ``box`` by where they leave the box (only the pixels that leave through one of its faces)."""
    cams = views.cameras.to("cpu")
    for i in range(len(cams)):
        keep = ~covered[i].reshape(-1)
        if not bool(keep.any()):
            continue
        rays = generate_rays(cams, [i])
        d = rays.directions[keep]
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        shown = linear_to_srgb(views.values["rgb"][i].reshape(-1, 3)[keep].double().clamp(0.0, 1.0))
        if box is None:
            yield i, d, shown, None
            continue
        k, on = box.keys(rays.origins[keep], d)
        if bool(on.any()):
            yield i, k[on], shown[on], (rays.origins[keep][on], d[on])


def _uncovered_radiance(views, covered: torch.Tensor, height: int, width: int,
                        box: BoxProjection | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(mean rendered colour [height, width, 3], pixel count [height, width]) per lat-long texel of the pixels of
    ``views`` (which must hold ``rgb``) that ``covered`` (bool [V, H, W]) leaves out (with ``box``: keyed by where
    they leave the box, those that leave through one of its faces; :func:`_uncovered_pixels`).

    The mean is taken as the photos are shown and scored: each colour clamped to [0, 1] and sRGB-encoded, the mean
    decoded back to linear radiance. A linear mean lets a few very bright pixels own the texel: in a room, one
    texel sees the dark ceiling from most cameras and a skylight or a lamp from a few, and the linear mean drew the
    whole ceiling pale. The cost: a texel's radiance is at most 1, so a viewer that lowers the exposure shows a
    bright sky grey instead of keeping its HDR level."""
    total = torch.zeros(height * width, 3, dtype=torch.float64)
    count = torch.zeros(height * width, dtype=torch.float64)
    for _, keys, shown, _ in _uncovered_pixels(views, covered, box):
        t = _texel_of(keys, height, width)
        total.index_add_(0, t, shown)
        count.index_add_(0, t, torch.ones_like(t, dtype=torch.float64))
    mean = srgb_to_linear(total / count.clamp_min(1.0)[:, None])
    return mean.reshape(height, width, 3).float().numpy(), count.reshape(height, width).numpy()


def backdrop_from_views(radiance: torch.Tensor | np.ndarray, views, covered: torch.Tensor | None = None,
                        shape: tuple[int, int] = UNCOVERED_SHAPE, box: BoxProjection | None = None,
                        box_shape: tuple[int, int] = BOX_SHAPE) -> Backdrop:
    """The :class:`Backdrop` of a field: its learned background map (float [h, w, 3] linear radiance:
    :meth:`toolkit.pipeline.Background.radiance_map`) with its visibility from ``views``
    (:func:`background_visibility`).

    With ``covered`` (bool [V, H, W], :func:`mesh_coverage` of the GLB's mesh at ``views``' cameras) and the field's
    colour in ``views`` (``values["rgb"]``): each texel of a ``shape`` map that some training pixel the mesh leaves
    out points into holds the mean field colour of those pixels, at visibility 1 — everything the field drew there,
    far-away density (clouds, a skyline) and the holes in the mesh included, not only its background map; the other
    texels keep the background map and its visibility, resampled to ``shape``.

    With ``box`` as well (:class:`BoxProjection`, the room's box), the backdrop also gets a ``box_shape`` map of the
    same pixels keyed by where they leave the box, and its per-texel weight (:func:`_box_map`)."""
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
    far = Backdrop(out_rad, np.ones((h, w), np.float32))
    if box is None:
        return far
    return _box_map(far, views, covered, box, box_shape)


def _box_map(far: Backdrop, views, covered: torch.Tensor, box: BoxProjection, shape: tuple[int, int]) -> Backdrop:
    """``far`` with a box-projected map (module docstring, "Box projection"): each texel the uncovered training
    pixels that leave through ``box``'s faces key holds their mean colour (as :func:`_uncovered_radiance`), the
    others their nearest seen texel's; its weight is 1 where the map's colour is at least as close to those pixels
    (summed squared error of the shown, sRGB colours) as ``far``'s direction map, and at texels no pixel keyed
    (the neighbours' colour stands in), else 0. ``far`` alone when no pixel leaves through the faces."""
    h, w = shape
    colour, count = _uncovered_radiance(views, covered, h, w, box)
    seen = count > 0
    if not seen.any():
        return far
    box_map = _fill_from_neighbours(colour, seen)
    table = torch.from_numpy(box_map.astype(np.float64))
    err_box = torch.zeros(h * w, dtype=torch.float64)
    err_far = torch.zeros(h * w, dtype=torch.float64)
    for _, keys, shown, (origins, dirs) in _uncovered_pixels(views, covered, box):
        t = _texel_of(keys, h, w)
        b = linear_to_srgb(lookup_latlong(table, keys.double()).clamp(0.0, 1.0))
        f, _ = far.sample(dirs)
        f = linear_to_srgb(f.double().clamp(0.0, 1.0))
        err_box.index_add_(0, t, ((b - shown) ** 2).sum(-1))
        err_far.index_add_(0, t, ((f - shown) ** 2).sum(-1))
    weight = (err_box <= err_far).reshape(h, w).numpy().astype(np.float32)
    return Backdrop(far.radiance, far.visibility, box, box_map, weight)


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
