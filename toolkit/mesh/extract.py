"""Marching cubes on density (:func:`extract_mesh`), the iso-level rules (:func:`opacity_level`,
:func:`level_from_rays`) and per-vertex material attributes (:func:`query_vertex_attributes`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from .._checks import ConfigError, check_range
from ._field import _call_field, _check_aabb, _density, _progress, _to_numpy
from .types import DensityFn, MaterialFn, Mesh, _as_mesh, compute_vertex_normals

__all__ = ["MeshConfig", "opacity_level", "level_from_rays", "seen_surface_points", "grid_spec", "extract_mesh",
           "query_vertex_attributes"]


@dataclass(frozen=True)
class MeshConfig:
    """Marching cubes on a density field.

    Attributes:
        resolution: grid cells along the longest AABB edge; the voxel is a cube of edge
            δ = longest_edge / resolution, and the other axes get as many cells as cover the box (the grid may
            overhang the box's max corner by less than one voxel).
        level: iso-level σ* in 1/metre; None = the opacity rule σ* = −ln(1 − opacity)/δ (module docstring).
        opacity: α* of the opacity rule, in (0, 1).
        opacity_thickness: δ of the opacity rule in metres; None = the voxel size.
        chunk: slab thickness in voxels along x. The grid is evaluated and triangulated one slab at a time
            (consecutive slabs share one sample plane and their seam vertices are merged), so peak memory is
            ~ (chunk + 1)·ny·nz·4 bytes for the slab plus ~2x the output mesh, never the full grid
            (bench/bench_asset.py: a gallery room at 513x415x218 samples, 2.3M faces, peaks at 160 MB of numpy
            allocations, the mesh itself being 83 MB).
        batch: maximum points per ``density_fn`` call.
        device: device the points are sent to.
        compute_normals: attach area-weighted vertex normals.
        progress: show a progress bar (stderr).
    """

    resolution: int = 256
    level: float | None = None
    opacity: float = 0.5
    opacity_thickness: float | None = None
    chunk: int = 64
    batch: int = 1 << 18
    device: str = "cpu"
    compute_normals: bool = True
    progress: bool = True


def opacity_level(voxel_size: float, opacity: float = 0.5) -> float:
    """The density σ* (1/metre) at which a layer ``voxel_size`` thick has opacity ``opacity``: −ln(1−α)/δ.

    Example:
        >>> round(opacity_level(0.01), 3)  # ln 2 / 1 cm
        69.315
    """
    check_range(opacity, 1e-6, 1 - 1e-6, "opacity")
    if not (voxel_size > 0 and math.isfinite(voxel_size)):
        raise ConfigError(f"voxel_size={voxel_size!r} must be a positive number of metres")
    return -math.log1p(-opacity) / voxel_size


def _training_rays(cameras, n_rays: int, seed: int, aabb):
    """``n_rays`` rays through training pixels drawn uniformly over all pixels of all views (seeded), bounded by
    ``aabb`` (a box tensor or a :class:`toolkit.space.SceneSpace`), on the CPU."""
    from ..cameras import generate_rays

    cams = cameras.to("cpu")
    g = torch.Generator().manual_seed(seed)
    n_pix = (cams.height * cams.width).long()
    view = torch.multinomial(n_pix.double(), n_rays, replacement=True, generator=g)
    pix = (torch.rand(n_rays, generator=g, dtype=torch.float64) * n_pix[view]).long()
    width = cams.width[view].long()
    return generate_rays(cams, view, pixels=torch.stack([pix % width, pix // width], -1), aabb=aabb)


def _half_transmittance(density_fn: DensityFn, rays, edges_fn, device: str) -> tuple[torch.Tensor, np.ndarray]:
    """March ``rays`` (256 at a time) over the sample edges ``edges_fn(rays) -> float [R, S + 1]`` (distances
    along each ray); return the points where each ray's transmittance first falls to ½ (float [M, 3], the
    surfaces the photos see) and σ there (float [M]); rays that stay more than half transparent give nothing."""
    pts_all, sig_all = [], []
    for s in range(0, len(rays), 256):
        r = rays[s:s + 256]
        edges = edges_fn(r)
        mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
        delta = (edges[:, 1:] - edges[:, :-1]).numpy()
        pts = r.origins[:, None] + r.directions[:, None] * mids[..., None]
        sigma = np.maximum(_density(density_fn, pts.reshape(-1, 3).numpy(), device).reshape(mids.shape), 0.0)
        reached = np.cumsum(sigma * delta, axis=1) >= math.log(2.0)
        ok = np.nonzero(reached.any(1))[0]
        first = reached.argmax(1)[ok]
        pts_all.append(pts[torch.from_numpy(ok), torch.from_numpy(first)])
        sig_all.append(sigma[ok, first])
    if not pts_all:
        return torch.zeros(0, 3), np.zeros(0)
    return torch.cat(pts_all), np.concatenate(sig_all)


def seen_surface_points(density_fn: DensityFn, cameras, aabb, n_rays: int = 4096, samples: int = 256,
                        seed: int = 0, device: str = "cpu", with_sigma: bool = False):
    """Points where ``n_rays`` training rays (pixels drawn uniformly over all views, seeded) reach half
    transmittance: what the photos see of the field. ``aabb`` is a float [2, 3] box (``samples`` uniform samples
    between entry and exit) or a contracted :class:`toolkit.space.SceneSpace` (samples uniform in contracted arc
    length, out to its far radius). Returns float64 [M, 3], M ≤ ``n_rays``; with ``with_sigma`` also σ there
    (float [M]: what :func:`level_from_rays` takes as ``sigma_at`` for the same box and arguments)."""
    from ..space import contracted_edges

    if hasattr(aabb, "contraction"):
        sp = aabb.to("cpu")
        rays = _training_rays(cameras, n_rays, seed, sp)
        edges_fn = lambda r: contracted_edges(r.origins, r.directions, r.near, r.far, sp, samples, perturb=False)  # noqa: E731
    else:
        box = torch.as_tensor(_check_aabb(aabb), dtype=torch.float32)
        rays = _training_rays(cameras, n_rays, seed, box)
        rays = rays[torch.nonzero(rays.far > rays.near).squeeze(-1)]
        edges_fn = lambda r: _uniform_edges(r, samples)  # noqa: E731
    pts, sigma = _half_transmittance(density_fn, rays, edges_fn, device)
    return (pts.double().numpy(), sigma) if with_sigma else pts.double().numpy()


def _uniform_edges(r, samples: int) -> torch.Tensor:
    span = (r.far - r.near)[:, None]
    return r.near[:, None] + span * torch.arange(samples + 1, dtype=torch.float32)[None] / samples


def level_from_rays(density_fn: DensityFn, cameras, aabb: torch.Tensor | np.ndarray, voxel_size: float,
                    quantile: float = 0.1, n_rays: int = 4096, samples: int = 256, seed: int = 0,
                    device: str = "cpu", sigma_at: np.ndarray | None = None) -> tuple[float, dict]:
    """Iso-level from the training rays (module docstring): the ``quantile`` of σ at each ray's half-transmittance
    crossing, capped at :func:`opacity_level` of ``voxel_size``.

    Args:
        density_fn: σ(points float [N, 3]) -> float [N], 1/metre.
        cameras: :class:`toolkit.scene.Cameras` whose rays are marched (``n_rays`` pixels drawn uniformly, seeded).
        aabb: float [2, 3] box the rays are clipped to, metres.
        voxel_size: marching-cubes voxel edge, metres (the cap is ln 2 / voxel_size).
        quantile: in (0, 1]; lower keeps softer surfaces.
        n_rays, samples: rays marched and uniform samples per ray between box entry and exit.
        sigma_at: σ at the crossings when already marched (:func:`seen_surface_points` with ``with_sigma`` on the
            same box and arguments); the rays are then not marched again.

    Returns:
        (level σ* in 1/metre, report ``{"level", "cap", "quantile", "rays", "rays_opaque", "sigma_quantiles"}``).
        With no ray reaching half-transmittance the level is the cap.
    """
    check_range(quantile, 1e-6, 1.0, "quantile")
    cap = opacity_level(voxel_size)
    if sigma_at is not None:
        vals = np.asarray(sigma_at)
    else:
        _, vals = seen_surface_points(density_fn, cameras, aabb, n_rays, samples, seed, device, with_sigma=True)
    rep = {"cap": cap, "quantile": quantile, "rays": int(n_rays), "rays_opaque": int(vals.size)}
    if vals.size == 0:
        return cap, {**rep, "level": cap, "sigma_quantiles": None}
    level = float(min(cap, np.quantile(vals, quantile)))
    rep["sigma_quantiles"] = {str(q): float(np.quantile(vals, q)) for q in (0.05, 0.1, 0.25, 0.5)}
    return level, {**rep, "level": level}


def surface_region(density_fn: DensityFn, cameras, space, n_rays: int = 4096, samples: int = 256,
                   quantile: float = 0.01, pad: float = 0.02, max_radius: float = 8.0, seed: int = 0,
                   device: str = "cpu", points: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """The region worth meshing in an unbounded (contracted) field: where the training rays reach half
    transmittance.

    ``n_rays`` training pixels are marched through all of space with ``samples`` samples uniform in contracted arc
    length (:func:`toolkit.space.contracted_edges`); each ray's half-transmittance point is a surface the photos
    see. Points beyond ``max_radius`` box half-sizes (sky, scenery through windows) are left out; the region is
    the per-axis ``[quantile, 1 − quantile]`` range of the rest, padded by ``pad`` of its extent. Walls, floor and
    objects become the mesh, the sky does not.

    Args:
        density_fn: σ(points float [N, 3]) -> float [N], 1/metre.
        cameras: :class:`toolkit.cameras.Cameras` (the training views).
        space: :class:`toolkit.space.SceneSpace` of the field (contracted).
        n_rays, samples, quantile, pad, max_radius, seed, device: see above.
        points: the :func:`seen_surface_points` of these arguments when already computed (not marched again).

    Returns:
        (box float64 [2, 3] metres, report ``{"rays", "rays_opaque", "points_kept", "box"}``). Without any opaque
        ray the scene box itself.
    """
    from ..space import box_radius

    sp = space.to("cpu")
    if points is None:
        points = seen_surface_points(density_fn, cameras, sp, n_rays, samples, seed, device)
    pts = torch.as_tensor(points, dtype=torch.float64)
    rep = {"rays": int(n_rays), "rays_opaque": int(len(pts))}
    pts = pts[box_radius(pts, sp.aabb.double()) <= max_radius].numpy()
    rep["points_kept"] = int(len(pts))
    if len(pts) < 16:
        box = sp.aabb.double().numpy()
    else:
        lo, hi = np.quantile(pts, quantile, axis=0), np.quantile(pts, 1.0 - quantile, axis=0)
        ext = np.maximum(hi - lo, 1e-6)
        box = np.stack([lo - pad * ext, hi + pad * ext])
    rep["box"] = box.tolist()
    return box, rep


def grid_spec(aabb: np.ndarray, resolution: int) -> tuple[float, tuple[int, int, int]]:
    """(voxel edge δ in metres, samples per axis) of the marching-cubes grid over ``aabb`` float [2, 3] with
    ``resolution`` cells along the longest edge (what :func:`extract_mesh` uses)."""
    extent = aabb[1] - aabb[0]
    delta = float(extent.max()) / resolution
    dims = tuple(int(math.ceil(e / delta - 1e-6)) + 1 for e in extent)
    return delta, dims  # samples per axis (cells + 1)


def extract_mesh(density_fn: DensityFn, aabb: torch.Tensor | np.ndarray, cfg: MeshConfig = MeshConfig()) -> Mesh:
    """Marching cubes on the density field over an axis-aligned box, slab by slab.

    Samples σ on a regular grid (corner-aligned: sample ``(i, j, k)`` is at ``aabb[0] + (i, j, k)·δ``), triangulates
    the σ = σ* level set (scikit-image's Lewiner marching cubes, degenerate triangles dropped) with faces oriented
    toward decreasing density (outward), and stitches the slabs by merging the vertices of their shared plane. The
    result equals the unchunked one (same vertices and faces up to order).

    Args:
        density_fn: ``density_fn(points float [N, 3]) -> float [N]``, σ in 1/metre.
        aabb: float [2, 3] box min and max corner, metres.
        cfg: :class:`MeshConfig`.

    Returns:
        :class:`Mesh` in world metres (normals if ``cfg.compute_normals``). Empty (0 faces) if σ never crosses σ*.

    Raises:
        ConfigError: bad resolution/chunk/level.
        ShapeError: ``density_fn`` returns the wrong shape.

    Example:
        >>> sphere = lambda p: 1e3 * torch.sigmoid((0.5 - p.norm(dim=-1)) * 100)
        >>> mesh = extract_mesh(sphere, torch.tensor([[-1.0] * 3, [1.0] * 3]), MeshConfig(resolution=64))
    """
    from skimage.measure import marching_cubes

    aabb = _check_aabb(aabb)
    if not (isinstance(cfg.resolution, int) and 2 <= cfg.resolution <= 4096):
        raise ConfigError(f"MeshConfig.resolution={cfg.resolution!r} must be an integer in [2, 4096]")
    if not (isinstance(cfg.chunk, int) and cfg.chunk >= 1):
        raise ConfigError(f"MeshConfig.chunk={cfg.chunk!r} must be a positive integer (voxels per slab)")
    delta, (nx, ny, nz) = grid_spec(aabb, cfg.resolution)
    if cfg.level is not None:
        if not math.isfinite(cfg.level):
            raise ConfigError(f"MeshConfig.level={cfg.level!r} must be finite")
        level = float(cfg.level)
    else:
        level = opacity_level(cfg.opacity_thickness or delta, cfg.opacity)

    ys = (aabb[0, 1] + np.arange(ny) * delta).astype(np.float32)
    zs = (aabb[0, 2] + np.arange(nz) * delta).astype(np.float32)
    yz = np.stack(np.meshgrid(ys, zs, indexing="ij"), -1).reshape(-1, 2)  # [ny*nz, 2]
    planes_per_call = max(1, cfg.batch // (ny * nz))

    def eval_planes(out: np.ndarray, i0: int) -> None:
        """Fill ``out`` [k, ny, nz] with the density on sample planes i0 .. i0 + k − 1."""
        i1 = i0 + out.shape[0]
        for a in range(i0, i1, planes_per_call):
            b = min(a + planes_per_call, i1)
            xs = (aabb[0, 0] + np.arange(a, b) * delta).astype(np.float32)
            pts = np.concatenate([np.repeat(xs, ny * nz)[:, None], np.tile(yz, (b - a, 1))], 1)
            if ny * nz > cfg.batch:  # one plane is bigger than a batch: split it
                vals = np.concatenate([_density(density_fn, pts[s:s + cfg.batch], cfg.device)
                                       for s in range(0, pts.shape[0], cfg.batch)])
            else:
                vals = _density(density_fn, pts, cfg.device)
            out[a - i0:b - i0] = vals.reshape(b - a, ny, nz)
            bar.update(b - a)

    verts, faces, n_verts = [], [], 0
    seam_keys: list[tuple[int, np.ndarray, np.ndarray]] = []  # (x plane, vertex ids (global), their yz)
    bar = _progress(nx, "marching cubes", cfg.progress, unit="plane")
    try:
        slab = np.empty((min(cfg.chunk, nx - 1) + 1, ny, nz), dtype=np.float32)  # reused for every slab
        start = 0
        while start < nx - 1:
            stop = min(start + cfg.chunk, nx - 1)  # this slab covers sample planes start..stop (inclusive)
            view = slab[:stop - start + 1]
            if start == 0:
                eval_planes(view, 0)
            else:
                view[0] = slab[last]  # the shared plane: the previous slab's last one
                eval_planes(view[1:], start + 1)
            last = stop - start
            v, f = _mc_slab(marching_cubes, view, level)
            if f.shape[0]:
                v[:, 0] += start
                for plane in (start, stop):
                    if 0 < plane < nx - 1:
                        on = np.nonzero(v[:, 0] == plane)[0]
                        seam_keys.append((plane, on + n_verts, v[on, 1:]))
                verts.append(v)
                faces.append((f + n_verts).astype(np.int32 if n_verts + v.shape[0] < 2**31 else np.int64))
                n_verts += v.shape[0]
            start = stop
    finally:
        bar.close()
    if not faces:
        return _as_mesh(np.zeros((0, 3)), np.zeros((0, 3)))
    v = np.concatenate(verts)
    del verts
    f = np.concatenate(faces)
    del faces
    v, f = _merge_seams(v, f, seam_keys)
    vertices = v
    vertices *= np.float32(delta)
    vertices += aabb[0].astype(np.float32)  # float32 is exact enough: |aabb| / 2^24 ≪ a voxel
    normals = compute_vertex_normals(vertices, f) if cfg.compute_normals else None
    return _as_mesh(vertices, f, normals=normals)


def _mc_slab(marching_cubes, slab: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes on one slab in index coordinates; faces oriented toward decreasing density."""
    if slab.shape[0] < 2 or not (slab.min() < level < slab.max()):
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)
    v, f, _, _ = marching_cubes(slab, level=level, gradient_direction="ascent", allow_degenerate=False,
                                method="lewiner")
    return v.astype(np.float32, copy=False), f


def _merge_seams(v: np.ndarray, f: np.ndarray, seam_keys) -> tuple[np.ndarray, np.ndarray]:
    """Merge the vertices two neighbouring slabs created on their shared sample plane."""
    if not seam_keys:
        return v, f
    remap = np.arange(v.shape[0], dtype=np.int64)
    by_plane: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for plane, ids, yz in seam_keys:
        by_plane.setdefault(plane, []).append((ids, yz))
    for plane, parts in by_plane.items():
        if len(parts) < 2:
            continue
        ids = np.concatenate([p[0] for p in parts])
        yz = np.concatenate([p[1] for p in parts])
        # both slabs interpolate the same two samples of the same edge: positions agree to float rounding
        keys = np.round(yz.astype(np.float64) * 65536.0).astype(np.int64)
        _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        remap[ids] = ids[first[inverse.reshape(-1)]]
    keep = remap == np.arange(v.shape[0])
    new_index = (np.cumsum(keep) - 1).astype(f.dtype)
    f = remap.astype(f.dtype)[f]
    f = new_index[f]
    return v[keep], f


def query_vertex_attributes(mesh: Mesh, material_fn: MaterialFn, batch: int = 1 << 16, device: str = "cpu") -> Mesh:
    """Colour and label the vertices from the field's material head.

    Args:
        mesh: input mesh (its normals, or area-weighted ones, are passed to ``material_fn``).
        material_fn: ``material_fn(points [N, 3], normals [N, 3] | None) -> dict`` with optional ``albedo`` [N, 3]
            (linear, [0, 1]) and ``semantic`` [N] (int class ids).
        batch: points per call.
        device: device the points are sent to.

    Returns:
        :class:`Mesh` with ``colors`` (linear albedo) and ``labels`` where the field provides them (left as they
        were otherwise).
    """
    if mesh.num_vertices == 0:
        return mesh
    normals = mesh.normals if mesh.normals is not None else compute_vertex_normals(mesh.vertices, mesh.faces)
    albedo, labels = [], []
    for s in range(0, mesh.num_vertices, batch):
        out = _call_field(material_fn, mesh.vertices[s:s + batch], device, normals[s:s + batch])
        if "albedo" in out:
            albedo.append(np.clip(_to_numpy(out["albedo"], "albedo").reshape(-1, 3), 0, 1).astype(np.float32))
        if "semantic" in out:
            labels.append(_to_numpy(out["semantic"], "semantic").reshape(-1).astype(np.uint8))
    kw = {}
    if albedo:
        kw["colors"] = np.concatenate(albedo)
    if labels:
        kw["labels"] = np.concatenate(labels)
    return replace(mesh, **kw)
