"""Stage 13 — a trained field → a baked PBR asset: extract → clean → simplify → colour → unwrap → bake.

:func:`build_asset` runs the whole chain with one frozen :class:`AssetConfig` (what ``dars export-asset`` does before
it writes the GLB with :func:`export.gltf.export_gltf`); :func:`build_mesh` and :func:`bake_mesh` are its two halves
(``dars mesh``, ``dars bake``). The field comes as callables (:class:`toolkit.train.run.FieldCallables`: density,
materials, box, SH light, training cameras), so these functions never own the model.

Example:
    >>> asset = build_asset("out/run", AssetConfig(resolution=128, texture=512))   # doctest: +SKIP
    >>> asset.mesh.num_faces, asset.textures.base_color.shape                     # doctest: +SKIP
"""

from __future__ import annotations

import inspect
import io
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ._checks import ConfigError, DarsError, ShapeError
from .bake import PBRTextures, UVMesh
from .defaults import SNAP_LAYOUT_DEFAULT
from .io import atomic_write, write_png
from .mesh import Mesh
from .scene import SEMANTIC_CLASSES
from .train.run import FieldCallables, Run, run_field_callables

__all__ = ["AssetConfig", "Asset", "build_asset", "build_mesh", "bake_mesh", "view_maps", "build_backdrop",
           "depth_cameras", "asset_field", "write_textures", "write_uv_obj"]


SEEN_RADIUS_VOXELS = 3.0
"""A training ray's half-transmittance point counts for the mesh component whose nearest vertex lies within this
many marching-cubes voxels (the iso-surface sits at or before the crossing, a sample spacing or two away)."""
SNAP_CLASSES = (SEMANTIC_CLASSES.index("wall"), SEMANTIC_CLASSES.index("floor"))
"""The classes whose vertices :attr:`AssetConfig.snap_layout` may move onto the room's box (the field's own labels):
on the real fox capture the field labels the fox and its stand 'painting', and moving every vertex near the wall
behind it cost its GLB preview 1.59 dB (README, "Walls and floor flattened onto the room's box")."""


@dataclass(frozen=True)
class AssetConfig:
    """Options of the mesh and bake stages (the ``dars mesh`` / ``bake`` / ``export-asset`` options, same defaults).

    Every value is checked here, before any work, and errors name the command-line option.
    """

    method: Literal["auto", "mc", "tsdf"] = "auto"
    """``mc``: marching cubes on density; ``tsdf``: TSDF fusion of depth maps rendered at the training cameras
    (each pixel's half-transmittance depth); ``auto``: ``tsdf`` for an unbounded (contracted) field that has its
    training cameras — rooms and real captures, whose walls are a soft layer of density that no single iso-level
    fits (README, "Meshing a room") — and ``mc`` otherwise (objects on a transparent background, or when ``level``
    is given)."""
    resolution: int = 256
    """Grid cells along the longest box edge (mc), or the TSDF voxel = edge / resolution (tsdf)."""
    level: float | None = None
    """Density iso-level in 1/m (None: from the training rays, see ``level_quantile``)."""
    level_quantile: float = 0.1
    """Without ``level``: the quantile of σ where the training rays cross half-transmittance, capped at ln 2 / voxel
    (0: the plain half-opacity rule ln 2 / voxel)."""
    faces: int = 100_000
    """Simplify to this many faces (0: keep all)."""
    simplify: Literal["fast", "quality"] = "fast"
    """fast-simplification, or pymeshlab quadric edge collapse."""
    min_component: float = 0.05
    """Drop connected components smaller than this fraction of the largest (0: keep all), unless the photos see
    them (``min_seen``)."""
    min_seen: float = 0.005
    """Keep a component whatever its size when at least this fraction of the training rays' half-transmittance
    points (what the photos see) lies on it (1: size alone decides)."""
    keep_unseen: bool = False
    """Keep faces that no training camera sees."""
    snap_layout: float = SNAP_LAYOUT_DEFAULT
    """``tsdf`` with the room's box the run trained with (``room_layout``, fitted from the photos by
    :func:`toolkit.layout.fit_room_layout`): after simplification, the mesh's vertices that the field labels wall or
    floor (:data:`SNAP_CLASSES`) and that lie within this fraction of the depth maps' median depth of a confident
    face of the box are moved onto its plane, along its normal (:func:`toolkit.mesh.snap_to_planes`): the walls and
    floor come out flat where the fused field leaves them bumpy (README, "Walls and floor flattened onto the room's
    box"). 0: off."""
    depth_samples: int = 128
    """Samples per ray of the ``tsdf`` depth maps (uniform between the ray's entry and exit of the meshed region;
    the crossing is interpolated inside its sample)."""
    depth_min_opacity: float = 0.5
    """``tsdf``: a pixel's depth is where its ray reaches half opacity; below 0.5, a ray that never does but
    gathers at least this opacity in the meshed region gives the median of its own termination, so walls the field
    left translucent are meshed too: more of the room is covered, but their baked colour is poor (README, "Faster
    depth maps, and translucent walls"). Rays that gather less see through (windows, sky) and give none."""
    depth_rays: int = 1_000_000
    """``tsdf``: at most this many depth rays over all training cameras; every camera is kept and the depth maps
    are rendered on one smaller pixel grid when the photos hold more pixels (:func:`depth_cameras`)."""
    texture: int = 2048
    """Texture size in texels (square). 2048: a room's mesh of ~100k faces unwraps into thousands of small charts,
    and their padding leaves 30-40 % of the atlas covered, ~15 % at 1024 (README, "Detail and light fitted to the
    viewer")."""
    supersample: int = 1
    """Bake at this multiple of ``texture`` and box-filter down (1 or 2)."""
    ao_samples: int = 0
    """Rays per texel for ambient occlusion (0: none)."""
    bake_from: Literal["views", "points"] = "views"
    """``views``: the albedo of a texel is the mean of the field's own composited render over the training views
    that see it (:mod:`toolkit.viewbake`: what the photos were fitted to, where the mesh point alone reads the field
    off its surface; README, "The GLB against its field: the view-projected bake"); texels no view sees, and
    fields without a renderer, fall back to ``points``. ``points``: the field's materials queried at each texel's
    surface point."""
    view_rays: int = 2_000_000
    """``views``: at most this many rendered pixels over all training views (larger photos are rendered on a
    smaller pixel grid, :func:`depth_cameras`): every pixel of 120 photos of 128 x 128. The texels take their
    detail from these renders, and ``light_fit`` its targets."""
    view_tolerance: float = 0.1
    """``views``: a view sees a texel when the texel's depth is within this fraction of the rendered depth."""
    normals_from: Literal["views", "points"] = "views"
    """``bake_from="views"``: ``views``: a texel's normal (the normal map) is the mean of the field's rendered normals
    over the views that see it, like the albedo (the mesh normal where no view sees it and the field gives none);
    ``points``: the field's normal at the texel's surface point (the GLB of earlier versions)."""
    light_occlusion: bool = True
    """``views``, for a field with a per-point light residual Δl(x): carry it in the GLB's occlusion channel. Each
    texel's occlusion is its light gain (how much Δl(x) brightens or darkens the field's shaded colour there, mean
    over the views that see it, :func:`toolkit.train.run.light_gain_map`) over a scale ``s`` (the gain's
    :data:`LIGHT_SCALE_QUANTILE` quantile over the rendered pixels, at least 1), and the GLB's SH is the run's times
    ``s``: a viewer that multiplies its SH lighting by the occlusion (ours, three.js) shades each texel with gain ×
    the run's light. Off: occlusion 1 and the run's SH (the GLB of earlier versions)."""
    light_tint: bool = True
    """With ``light_occlusion``: also bake the colour of Δl(x) that the grey occlusion drops (each texel's
    :func:`toolkit.train.run.light_tint_map`, mean over the views that see it) into a light-tint texture that the
    GLB names in ``extras.dars.light_tint``; our viewers (``dars view``, the WebXR page) multiply the shaded colour
    by it, other glTF viewers ignore it. Off: no tint texture (the GLB of earlier versions)."""
    light_fit: bool = True
    """With ``light_occlusion``: fit each texel's occlusion and light tint so that the viewer's own shading of the
    baked textures reproduces the field's colour at the views that see it (:func:`toolkit.viewbake.fit_light`),
    instead of taking the field's light gain and tint as they are: the texture's mean albedo and the viewer's SH
    shading differ from the field's composited ones, and the fit takes up that mean difference. Off: the field's
    gain and tint (the GLB of earlier versions)."""
    backdrop: bool = True
    """Store a backdrop in the GLB (:mod:`toolkit.backdrop`: what the viewers draw where the mesh is not — a
    gallery's sky, the white behind an object, the holes in the mesh): the field's rendered colour in the directions
    where the mesh leaves training pixels uncovered, elsewhere its learned background weighted by how much of it the
    training renders saw. Needs the renders of ``bake_from="views"`` (rendered for it alone with ``points``)."""
    backdrop_box: bool = True
    """With ``backdrop`` and a run with a room box (``room_layout``): also a backdrop map projected on the box's
    confident faces (:class:`toolkit.backdrop.BoxProjection`), so that a floor or wall seen through a hole in the
    mesh shows the colour of that place rather than the mean of everything seen in that direction. Off: the
    direction map alone (the GLB of earlier versions)."""
    viewer_fit: int = 1
    """With ``light_fit``: after the bake, render the GLB with our viewer at the views it was baked from, fit one
    RGB light factor per mesh vertex that brings what the viewer shows to the field's colour there
    (:func:`viewers.refit.viewer_light_correction`: where the mesh and the field's depth part, and where the
    viewer's filter averages texels), and re-bake with the light times that factor; repeated this many times (0:
    off). Needs the viewer passed to :func:`build_asset` (``viewer_correction``: ``dars export-asset`` passes
    :func:`viewers.refit.viewer_correction`) and a headless OpenGL context; without either the bake is kept as it
    is and ``mesh_stats.json`` says why (README, "The GLB refitted at its own views")."""
    device: str = "cpu"
    """Device the field is queried on."""

    def __post_init__(self):
        if self.method not in ("auto", "mc", "tsdf"):
            raise ConfigError(f"--method {self.method!r}: choose auto, mc or tsdf")
        if self.resolution < 8:
            raise ConfigError(f"--resolution {self.resolution} is too small (use ≥ 8)")
        if self.level is not None and not math.isfinite(self.level):
            raise ConfigError(f"--level {self.level} must be a finite density (1/m)")
        if not 0.0 <= self.level_quantile <= 1.0:
            raise ConfigError(f"--level-quantile {self.level_quantile} must be in [0, 1]")
        if self.faces < 0:
            raise ConfigError(f"--faces {self.faces} must be ≥ 0 (0 keeps every face)")
        if self.simplify not in ("fast", "quality"):
            raise ConfigError(f"--simplify {self.simplify!r}: choose fast or quality")
        if not 0.0 <= self.min_component <= 1.0:
            raise ConfigError(f"--min-component {self.min_component} must be in [0, 1]")
        if not 0.0 <= self.min_seen <= 1.0:
            raise ConfigError(f"--min-seen {self.min_seen} must be in [0, 1]")
        if not 0.0 <= self.snap_layout <= 0.5:
            raise ConfigError(f"--snap-layout {self.snap_layout} must be in [0, 0.5] (a fraction of the median depth; "
                              "0 turns it off)")
        if self.depth_samples < 1:
            raise ConfigError(f"--depth-samples {self.depth_samples} must be ≥ 1")
        if not 0.0 < self.depth_min_opacity <= 0.5:
            raise ConfigError(f"--depth-min-opacity {self.depth_min_opacity} must be in (0, 0.5]")
        if self.depth_rays < 64:
            raise ConfigError(f"--depth-rays {self.depth_rays} must be ≥ 64")
        if not 16 <= self.texture <= 16384:
            raise ConfigError(f"--texture {self.texture} must be ≥ 16 and ≤ 16384 (texels)")
        if self.supersample not in (1, 2):
            raise ConfigError(f"--supersample {self.supersample}: choose 1 or 2")
        if self.ao_samples < 0:
            raise ConfigError(f"--ao-samples {self.ao_samples} must be ≥ 0")
        if self.bake_from not in ("views", "points"):
            raise ConfigError(f"--bake-from {self.bake_from!r}: choose views or points")
        if self.normals_from not in ("views", "points"):
            raise ConfigError(f"--normals-from {self.normals_from!r}: choose views or points")
        if self.view_rays < 64:
            raise ConfigError(f"--view-rays {self.view_rays} must be ≥ 64")
        if not 0.0 < self.view_tolerance <= 0.5:
            raise ConfigError(f"--view-tolerance {self.view_tolerance} must be in (0, 0.5]")
        if not 0 <= self.viewer_fit <= 8:
            raise ConfigError(f"--viewer-fit {self.viewer_fit} must be in 0..8 (passes; 0 = off)")


@dataclass
class Asset:
    """A baked asset (:func:`build_asset`).

    Attributes:
        mesh: the cleaned, simplified mesh with vertex colours (linear albedo) and labels (``mesh.ply``).
        uvmesh: the unwrapped mesh with per-face labels (what the GLB stores).
        textures: base colour, ORM and normal maps.
        sh: float [9, 3] the run's SH light (SPEC convention), or None.
        stats: ``mesh_stats.json``: the mesh half's statistics, with the bake's under ``bake`` (and the backdrop's
            under ``backdrop``).
        backdrop: what the viewers draw where the mesh is not (:mod:`toolkit.backdrop`), or None.
    """

    mesh: Mesh
    uvmesh: UVMesh
    textures: PBRTextures
    sh: Any
    stats: dict
    backdrop: Any = None

    def gltf_extras(self) -> dict:
        """What the GLB stores in its ``extras.dars``: the mesh statistics and the backdrop (when there is one)."""
        extras: dict = {"mesh_stats": {k: self.stats[k] for k in ("vertices", "faces", "area_m2", "method")}}
        scale = self.stats.get("bake", {}).get("light_scale", 1.0)
        if scale != 1.0:  # the SH is the run's times this; the occlusion channel carries the light gain over it
            extras["light_scale"] = scale
        if self.backdrop is not None:
            extras["backdrop"] = self.backdrop.to_json()
        return extras


def asset_field(run: str | Path | Run | FieldCallables) -> FieldCallables:
    """The field callables of a run directory, a loaded :class:`~toolkit.train.run.Run`, or callables as they are.

    Raises:
        DarsError: ``run`` is a path that is not a directory (or not a training run).
    """
    if isinstance(run, FieldCallables):
        return run
    if isinstance(run, Run):
        return run_field_callables(run)
    run_dir = Path(run)
    if not run_dir.is_dir():
        raise DarsError(f"RUN directory not found: {run_dir} (give the --out directory of `dars train`)")
    from .train import run as run_module  # looked up at call time: tests stand a fake field in for it

    return FieldCallables(*run_module.load_field_callables(run_dir))


def depth_cameras(cameras, max_rays: int):
    """The training cameras on one pixel grid of at most ``max_rays`` pixels in all (the ``tsdf`` depth maps): the
    median aspect ratio of the photos, never more pixels per view than the largest photo has; the cameras as they
    are when they already share a size within the budget."""
    if bool((cameras.width == cameras.width[0]).all() and (cameras.height == cameras.height[0]).all()) \
            and int(cameras.width[0] * cameras.height[0]) * len(cameras) <= max_rays:
        return cameras
    w, h = cameras.width.double(), cameras.height.double()
    aspect = float((w / h).median())
    per_view = min(float((w * h).max()), max_rays / len(cameras))
    width = max(8, round(math.sqrt(per_view * aspect)))
    return cameras.resized(width, max(8, round(width / aspect)))


def build_mesh(field: FieldCallables, cfg: AssetConfig = AssetConfig()) -> tuple[Mesh, dict]:
    """The mesh half: extract (marching cubes or TSDF), drop floaters and unseen faces, simplify, colour the vertices.

    Returns:
        (mesh, statistics): ``method``, ``resolution``, ``level`` / ``level_from_rays`` (mc), timings, face counts
        after each step, ``simplify`` (when simplified), ``vertices``, ``faces``, ``bounds``, ``area_m2``.

    Raises:
        DarsError: the field gives an empty mesh, or ``tsdf`` without training cameras.
    """
    from .mesh import (DepthRenderConfig, MeshConfig, TsdfConfig, extract_mesh, fuse_tsdf, grid_spec, level_from_rays,
                       query_vertex_attributes, remove_floaters, remove_unseen_faces, render_depth,
                       seen_surface_points, simplify_mesh, surface_region)

    density_fn, material_fn, aabb, _, cameras = field[:5]
    space = field.space if isinstance(field, FieldCallables) else None
    method = cfg.method
    if method == "auto":  # an explicit iso-level asks for marching cubes
        method = "tsdf" if space is not None and space.contraction and cameras is not None and cfg.level is None \
            else "mc"
    stats: dict = {"method": method, "method_option": cfg.method, "resolution": cfg.resolution}
    t0 = time.perf_counter()
    box = np.asarray(aabb.detach().cpu().numpy() if hasattr(aabb, "detach") else aabb, dtype=np.float64)
    median_depth = None  # of the tsdf depth maps: the scale of AssetConfig.snap_layout
    seen = seen_sigma = None  # where the training rays reach half transmittance (what the photos see) and σ there
    if space is not None and space.contraction and cameras is not None:
        # unbounded field: mesh where the photos' rays find surfaces (walls, floor, objects), not the sky
        seen = seen_surface_points(density_fn, cameras, space, device=cfg.device)
        box, stats["region"] = surface_region(density_fn, cameras, space, device=cfg.device, points=seen)
    elif cameras is not None and (cfg.min_component > 0 or (method == "mc" and cfg.level is None
                                                            and cfg.level_quantile > 0)):
        # bounded: the same box rays give the floater test and the iso-level (one march for both)
        seen, seen_sigma = seen_surface_points(density_fn, cameras, box, device=cfg.device, with_sigma=True)
    voxel = grid_spec(box, cfg.resolution)[0]  # marching cubes' (and the TSDF's) voxel: iso-level cap, floater radius
    if method == "mc":
        level = cfg.level
        if level is None and cfg.level_quantile > 0 and cameras is not None:
            level, stats["level_from_rays"] = level_from_rays(density_fn, cameras, box, voxel,
                                                              quantile=cfg.level_quantile, device=cfg.device,
                                                              sigma_at=seen_sigma)
        mesh = extract_mesh(density_fn, box, MeshConfig(resolution=cfg.resolution, level=level, device=cfg.device))
        stats["level"] = level
    else:
        if cameras is None:
            raise DarsError("--method tsdf needs the training cameras, but the RUN's field loader returned none")
        cams = depth_cameras(cameras, cfg.depth_rays)
        stats["depth_maps"] = {"views": len(cams), "width": int(cams.width[0]), "height": int(cams.height[0]),
                               "samples": cfg.depth_samples, "min_opacity": cfg.depth_min_opacity}
        depths = render_depth(density_fn, cams, box, DepthRenderConfig(samples=cfg.depth_samples,
                                                                       min_opacity=cfg.depth_min_opacity,
                                                                       device=cfg.device))
        stats["depth_maps"]["pixels_with_depth"] = round(float((depths > 0).mean()), 4)
        median_depth = float(np.median(depths[depths > 0])) if (depths > 0).any() else None
        depth_max = float(np.linalg.norm(box[1] - box[0])) * 4
        mesh = fuse_tsdf(depths, cams, cfg=TsdfConfig(voxel_size=voxel, depth_max=depth_max))
    stats["extract_seconds"] = round(time.perf_counter() - t0, 3)
    stats["faces_extracted"] = mesh.num_faces
    if mesh.num_faces == 0:
        raise DarsError("the field produced an empty mesh (density never reaches the iso-level inside the box); "
                        "try a lower --level or check the RUN")
    if cfg.min_component > 0:
        faces_before, radius = mesh.num_faces, SEEN_RADIUS_VOXELS * voxel
        mesh = remove_floaters(mesh, min_fraction=cfg.min_component, seen_points=seen, radius=radius,
                               min_seen=cfg.min_seen)
        stats["floaters"] = {"faces_removed": faces_before - mesh.num_faces,
                             "seen_points": 0 if seen is None else len(seen), "radius_m": radius,
                             "min_seen": cfg.min_seen}
    if cameras is not None and not cfg.keep_unseen:
        mesh = remove_unseen_faces(mesh, cameras)
    stats["faces_cleaned"] = mesh.num_faces
    if cfg.faces and mesh.num_faces > cfg.faces:
        mesh, report = simplify_mesh(mesh, cfg.faces, method=cfg.simplify)
        stats["simplify"] = report.to_dict()
    if cfg.snap_layout > 0:
        # after the simplification: quadric collapses on a mesh whose walls were made exactly planar run away across
        # the flat regions (validation gallery 1000007: max error 0.44 m against 0.07, a pedestal and its statuette
        # torn; preview 2.4 dB below the unsnapped GLB); snapping the simplified mesh moves vertices and nothing else
        mesh, stats["snap_layout"] = _snap_to_layout(mesh, field, cfg.snap_layout, median_depth, cfg.device)
    mesh = query_vertex_attributes(mesh, material_fn, device=cfg.device)
    stats.update(vertices=mesh.num_vertices, faces=mesh.num_faces, bounds=mesh.bounds.tolist(),
                 area_m2=round(mesh.area(), 6))
    return mesh, stats


def _snap_to_layout(mesh: Mesh, field, fraction: float, median_depth: float | None,
                    device: str = "cpu") -> tuple[Mesh, dict]:
    """:attr:`AssetConfig.snap_layout`: the mesh's walls and floor onto the confident faces of the run's room box
    (statistics say why not where it is left as it is). Only the vertices the field's semantics call wall or floor
    move (:data:`SNAP_CLASSES`): an exhibit near a wall, a real capture's object by its backdrop, stays as it is."""
    from .mesh import PlaneSnapConfig, query_vertex_attributes, snap_to_planes

    layout = getattr(field, "room_layout", None)
    if layout is None:
        return mesh, {"skipped": "the run has no room box (an object, or trained with --layout-depth 0)"}
    if median_depth is None:
        return mesh, {"skipped": "needs the tsdf depth maps (the tolerance is a fraction of their median depth)"}
    normals, offsets, names = layout.planes()
    if not len(names):
        return mesh, {"skipped": "no face of the room box is confident"}
    labels = query_vertex_attributes(mesh, field.material_fn, device=device).labels
    movable = None if labels is None else np.isin(labels, SNAP_CLASSES)
    out, stats = snap_to_planes(mesh, normals, offsets, PlaneSnapConfig(tolerance=fraction * median_depth), names,
                                movable=movable)
    return out, {"fraction": fraction, "median_depth_m": round(median_depth, 4),
                 "movable": ("every vertex (the field gives no labels)" if movable is None else
                             f"{int(movable.sum())} of {len(movable)} vertices the field labels wall or floor"),
                 **stats}


def _wants_backdrop(field, cfg: AssetConfig) -> bool:
    return cfg.backdrop and isinstance(field, FieldCallables) and field.background is not None


def _takes(fn, keyword: str) -> bool:
    """Whether the callable ``fn`` accepts ``keyword`` (False where its signature cannot be read)."""
    try:
        return keyword in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def view_maps(field: FieldCallables, cfg: AssetConfig = AssetConfig(), log=None):
    """The field's renders at its training cameras for the view-projected bake (``cfg.bake_from == "views"``) and
    the backdrop's visibility (``cfg.backdrop``), on one pixel grid of at most ``cfg.view_rays`` pixels; None when
    neither wants them, or when the field has no renderer or no cameras (which ``log`` is told: the bake queries
    points, the GLB gets no backdrop)."""
    if cfg.bake_from != "views" and not _wants_backdrop(field, cfg):
        return None
    views = field.views if isinstance(field, FieldCallables) else None
    if views is None or field.cameras is None:
        if log is not None and cfg.bake_from == "views":
            log("[dars] --bake-from views: the field has no renderer or no training cameras; baking point queries")
        return None
    cams = depth_cameras(field.cameras, cfg.view_rays)
    gain = cfg.light_occlusion and cfg.bake_from == "views" and _takes(views, "light_gain")
    if log is not None:
        why = "the view-projected bake" if cfg.bake_from == "views" else "the backdrop's visibility"
        log(f"[dars] rendering the {len(cams)} training views at {int(cams.width[0])}x{int(cams.height[0])} for {why}"
            + (" (twice where the field has a light residual: its light gain, for the occlusion)" if gain else ""))
    return views(cams, light_gain=True) if gain else views(cams)


def build_backdrop(field: FieldCallables, views, cfg: AssetConfig = AssetConfig(), mesh=None):
    """The GLB's :class:`toolkit.backdrop.Backdrop`, or None: ``cfg.backdrop`` off, or a field without a background
    or without renders. From the field's learned background and its visibility in ``views`` (:func:`view_maps`);
    given the GLB's ``mesh`` (anything with ``vertices`` and ``faces``) and views holding the field's colour, the
    field's colour wherever the mesh leaves a training pixel uncovered (:func:`toolkit.backdrop.backdrop_from_views`)."""
    if not _wants_backdrop(field, cfg) or views is None:
        return None
    from .backdrop import BoxProjection, backdrop_from_views, mesh_coverage

    covered = None
    if mesh is not None and "rgb" in views.values:
        covered = mesh_coverage(mesh.vertices, mesh.faces, views.cameras)
    layout = getattr(field, "room_layout", None)
    box = BoxProjection.from_layout(layout) if cfg.backdrop_box and layout is not None else None
    return backdrop_from_views(field.background, views, covered, box=box)


LIGHT_SCALE_QUANTILE = 0.99
"""The light gain quantile (over the opaque rendered pixels) the GLB's SH is scaled by
(``AssetConfig.light_occlusion``): texels brighter than it are clipped at occlusion 1."""


def light_scale(views) -> float:
    """The scale ``s`` of ``AssetConfig.light_occlusion``: the :data:`LIGHT_SCALE_QUANTILE` quantile of the views'
    ``light_gain`` over pixels at least half opaque, at least 1 (1 when no pixel is)."""
    import torch

    gain = views.values["light_gain"][views.opacity >= 0.5].float()
    if gain.numel() == 0:
        return 1.0
    if gain.numel() > 1_000_000:  # torch.quantile's limit: an even subsample
        gain = gain[torch.linspace(0, gain.numel() - 1, 1_000_000).long()]
    return round(max(1.0, float(torch.quantile(gain, LIGHT_SCALE_QUANTILE))), 4)


def _with_occlusion(texel_fn, scale: float):
    """``texel_fn`` with its ``light_gain`` turned into ``occlusion`` = gain / ``scale`` clamped to [0, 1]."""
    import torch

    def fn(points, normals=None, looks=None):
        out = dict(texel_fn(points, normals, looks))
        gain = torch.as_tensor(out.pop("light_gain"), dtype=torch.float32)
        out["occlusion"] = (gain / scale).clamp(0.0, 1.0)
        return out

    return fn


def _with_fitted_light(texel_fn, views, sh, scale: float, tolerance: float, tint: bool, correction=None):
    """``texel_fn`` (after :func:`_with_occlusion`) with the occlusion (and, with ``tint``, the light tint) of every
    texel a view sees replaced by the light the viewer needs there (:func:`toolkit.viewbake.fit_light`): the fitted
    multiplier m is split into occlusion = luminance(m) / ``scale`` clamped to [0, 1] and tint = m / (occlusion ×
    ``scale``) clamped to [0, LIGHT_TINT_SCALE] (the tint takes up what the occlusion clamps). The points are
    projected into the views once, for both (:func:`toolkit.viewbake.sightings`). ``correction``: a callable
    points -> float [N, 3] that multiplies m (:func:`build_asset`'s viewer fit)."""
    import torch

    from .bake import DEFAULT_MATERIAL, LIGHT_TINT_SCALE
    from .train.run import _luminance
    from .viewbake import fit_light, sightings

    def fn(points, normals=None):
        looks = sightings(points, views, tolerance)
        out = dict(texel_fn(points, normals, looks))
        n = torch.as_tensor(points).reshape(-1, 3).shape[0]
        material = {k: out[k] if k in out else torch.as_tensor(DEFAULT_MATERIAL[k], dtype=torch.float32).expand(n)
                    for k in ("roughness", "metallic")}
        material["albedo"] = out["albedo"]
        material["normal"] = out["normal"] if "normal" in out else normals
        m, count = fit_light(points, material, views, sh, tolerance, mesh_normals=normals, looks=looks)
        if correction is not None:
            m = m * correction(points)
        seen = count > 0
        occ = (_luminance(m) / scale).clamp(0.0, 1.0)
        out["occlusion"] = torch.where(seen, occ, torch.as_tensor(out["occlusion"], dtype=torch.float32).reshape(n))
        if tint:
            t = torch.where(occ[:, None] > 1e-4, m / (occ * scale).clamp_min(1e-4)[:, None], torch.ones_like(m))
            base = torch.as_tensor(out.get("light_tint", torch.ones(n, 3)), dtype=torch.float32).reshape(n, 3)
            out["light_tint"] = torch.where(seen[:, None], t.clamp(0.0, LIGHT_TINT_SCALE), base)
        return out

    return fn


def bake_mesh(mesh: Mesh, material_fn, cfg: AssetConfig = AssetConfig(), log=None,
              views=None, sh=None, light_correction=None, uvmesh: UVMesh | None = None
              ) -> tuple[UVMesh, PBRTextures, dict]:
    """The bake half: UV-unwrap ``mesh``, label its faces and bake PBR textures from ``material_fn``; ``log``: an
    optional callable told when the unwrap (xatlas, which reports no progress) starts and ends.

    Args:
        views: :class:`toolkit.viewbake.ViewMaps` (:func:`view_maps`): the albedo comes from the views that see each
            texel (:func:`toolkit.viewbake.view_projected`), and, when they hold ``light_gain`` and
            ``cfg.light_occlusion`` is on, the occlusion too; None: point queries only.
        sh: float [9, 3] the run's SH light: with ``cfg.light_fit`` and views holding the field's colour, the
            occlusion and tint are fitted to it (:func:`_with_fitted_light`).
        light_correction: with that fit, a callable points -> float [N, 3] the fitted light is multiplied by
            (:func:`build_asset`'s ``viewer_fit``); None: none.
        uvmesh: an earlier bake's unwrap of this ``mesh`` with the same ``material_fn`` (its atlas and face labels
            are reused: a re-bake skips the unwrap and the labelling); None: unwrap and label here.

    Returns:
        (uvmesh, textures, statistics ``texture``, ``supersample``, ``uv_vertices``, timings, ``chart_coverage``,
        ``defaults``, ``bake_from`` and, from views, ``views`` (count, size, tolerance, share of texels seen),
        ``texture_blur`` (median and 90th percentile over the faces views see, texels,
        :func:`toolkit.viewbake.face_texture_blur`, which the uvmesh carries per vertex; None when none) and
        ``light_scale``: the factor the GLB's SH must be scaled by, 1 without the occlusion).
    """
    from .bake import BakeConfig, UnwrapConfig, bake_pbr_textures, label_faces, unwrap_uv
    from .viewbake import view_projected

    t0 = time.perf_counter()
    if uvmesh is None:
        if log is not None:
            log(f"[dars] UV atlas of {mesh.num_faces} faces (xatlas, which shows no progress) ...")
        uvmesh = unwrap_uv(mesh, UnwrapConfig(texture_size=cfg.texture))
        t1 = time.perf_counter()
        if log is not None:
            log(f"[dars] UV atlas done in {t1 - t0:.0f} s")
        uvmesh = label_faces(uvmesh, material_fn, device=cfg.device)
    else:
        if uvmesh.num_vertices == 0 or int(uvmesh.vmapping.max()) >= mesh.num_vertices:
            raise ShapeError(f"bake_mesh: the uvmesh given ({uvmesh.num_vertices} vertices) is not an unwrap of this "
                             f"mesh ({mesh.num_vertices} vertices)")
        t1 = t0
    seen: dict = {}
    scale = 1.0
    fitted = False
    if views is None:
        texel_fn = material_fn
    else:
        keys = ("albedo", *(("normal",) if cfg.normals_from == "views" and "normal" in views.values else ()))
        if cfg.light_occlusion and "light_gain" in views.values:
            scale = light_scale(views)
            keys = (*keys, "light_gain")
            if cfg.light_tint and "light_tint" in views.values:
                keys = (*keys, "light_tint")
        texel_fn = view_projected(material_fn, views, cfg.view_tolerance, keys=keys, stats=seen)
        if "light_gain" in keys:
            texel_fn = _with_occlusion(texel_fn, scale)
            fitted = cfg.light_fit and sh is not None and "rgb" in views.values
            if fitted:
                texel_fn = _with_fitted_light(texel_fn, views, sh, scale, cfg.view_tolerance, "light_tint" in keys,
                                              light_correction)
    textures = bake_pbr_textures(uvmesh, texel_fn, BakeConfig(size=cfg.texture, supersample=cfg.supersample,
                                                               ao_samples=cfg.ao_samples, device=cfg.device))
    stats = {"texture": cfg.texture, "supersample": cfg.supersample, "uv_vertices": uvmesh.num_vertices,
             "unwrap_seconds": round(t1 - t0, 3), "bake_seconds": round(time.perf_counter() - t1, 3),
             "chart_coverage": round(float(textures.mask.mean()), 4), "defaults": list(textures.defaults),
             "bake_from": "points" if views is None else "views", "light_scale": round(scale, 4),
             "light_fit": fitted}
    if views is not None:
        from .viewbake import face_texture_blur, vertex_texture_blur

        face_blur = face_texture_blur(uvmesh.vertices, uvmesh.faces, uvmesh.uvs, views, cfg.texture,
                                      cfg.view_tolerance)
        uvmesh = replace(uvmesh, texture_blur=vertex_texture_blur(uvmesh.faces, face_blur, uvmesh.num_vertices).numpy())
        blurred = face_blur[face_blur > 0].numpy()
        stats["texture_blur"] = ({"median": round(float(np.median(blurred)), 3),
                                  "p90": round(float(np.percentile(blurred, 90)), 3)} if blurred.size else None)
        stats["views"] = {"count": len(views.cameras), "width": int(views.cameras.width[0]),
                          "height": int(views.cameras.height[0]), "tolerance": cfg.view_tolerance,
                          "texels_seen": round(seen.get("seen", 0) / max(1, seen.get("points", 0)), 4)}
    return uvmesh, textures, stats


def _glb_sh(sh, bake_stats: dict):
    """The SH a GLB of this bake carries: the run's times the bake's ``light_scale`` (the occlusion channel holds
    the light gain over it), or None without an SH."""
    scale = bake_stats["light_scale"]
    return sh * scale if sh is not None and scale != 1.0 else sh


def _viewer_fit(mesh, field, maps, cfg: AssetConfig, uvmesh, textures, bake_stats: dict, log, correction,
                mesh_stats: dict):
    """``cfg.viewer_fit`` passes of: the per-vertex light factor the viewer still needs at the bake's views
    (``correction(mesh, uvmesh, textures, sh, gltf_extras, maps)``: :func:`viewers.refit.viewer_correction`),
    multiplied into the running one, then a re-bake with the light times it. Returns the last bake; its statistics
    gain ``viewer_fit`` (passes, the share of vertices corrected, the factor's 5/50/95 % quantiles over them), or
    the reason it was skipped (no viewer given, no headless OpenGL). ``mesh_stats``: :func:`build_mesh`'s, for the
    draft GLB's extras."""
    from .viewbake import VertexValues

    if correction is None:
        return uvmesh, textures, {**bake_stats, "viewer_fit": {
            "skipped": "build_asset was given no viewer_correction (viewers.refit.viewer_correction; "
                       "dars export-asset passes it)"}}
    total = np.ones((mesh.num_vertices, 3), np.float32)
    for k in range(cfg.viewer_fit):
        if log is not None:
            log(f"[dars] viewer fit {k + 1}/{cfg.viewer_fit}: rendering the GLB at the {len(maps.cameras)} views")
        sh = _glb_sh(field.sh, bake_stats)
        draft = Asset(mesh, uvmesh, textures, sh, {**mesh_stats, "bake": bake_stats})
        try:
            factor = correction(mesh, uvmesh, textures, sh, draft.gltf_extras(), maps)
        except DarsError as e:  # no OpenGL here: keep the bake as it is, and say so
            if log is not None:
                log(f"[dars] viewer fit skipped: {e}")
            return uvmesh, textures, {**bake_stats, "viewer_fit": {"skipped": str(e)}}
        total = total * np.asarray(factor, np.float32)
        uvmesh, textures, bake_stats = bake_mesh(mesh, field.material_fn, cfg, log=log, views=maps, sh=field.sh,
                                                 light_correction=VertexValues(mesh, total), uvmesh=uvmesh)
    moved = np.abs(total - 1.0).max(1) > 0
    q = np.quantile(total[moved], [0.05, 0.5, 0.95], axis=0).mean(1) if moved.any() else np.ones(3)
    return uvmesh, textures, {**bake_stats, "viewer_fit": {"passes": cfg.viewer_fit,
                                                           "vertices_corrected": round(float(moved.mean()), 4),
                                                           "factor_q05_q50_q95": [round(float(x), 4) for x in q]}}


def build_asset(run: str | Path | Run | FieldCallables, cfg: AssetConfig = AssetConfig(), log=None,
                viewer_correction=None) -> Asset:
    """Field → mesh → baked textures: :func:`build_mesh`, then :func:`bake_mesh` (from the field's renders at the
    training views, :func:`view_maps`, by default).

    Args:
        run: a run directory, a loaded :class:`~toolkit.train.run.Run` or :class:`~toolkit.train.run.FieldCallables`.
        cfg: the options.
        log: optional callable for progress lines (:func:`bake_mesh`).
        viewer_correction: for ``cfg.viewer_fit``, the viewer that draws the draft GLB and returns its per-vertex
            light factor: :func:`viewers.refit.viewer_correction` (what ``dars export-asset`` passes; ``toolkit``
            never imports the viewers itself). None: no viewer fit, and the statistics say so.

    Raises:
        DarsError: no such run, or an empty mesh.
    """
    field = asset_field(run)
    mesh, stats = build_mesh(field, cfg)
    maps = view_maps(field, cfg, log)
    uvmesh, textures, bake_stats = bake_mesh(mesh, field.material_fn, cfg, log=log,
                                             views=maps if cfg.bake_from == "views" else None, sh=field.sh)
    if bake_stats["light_fit"] and cfg.viewer_fit > 0:
        uvmesh, textures, bake_stats = _viewer_fit(mesh, field, maps, cfg, uvmesh, textures, bake_stats, log,
                                                   viewer_correction, stats)
    stats["bake"] = bake_stats
    backdrop = build_backdrop(field, maps, cfg, uvmesh)
    if backdrop is not None:
        from .layout import FACE_NAMES

        vis = backdrop.visibility
        stats["backdrop"] = {"height": backdrop.shape[0], "width": backdrop.shape[1],
                             "texels_seen": round(float((vis > 0).mean()), 4),
                             "mean_visibility": round(float(vis.mean()), 4)}
        if backdrop.box is not None:
            stats["backdrop"]["box"] = {"height": int(backdrop.box_weight.shape[0]),
                                        "width": int(backdrop.box_weight.shape[1]),
                                        "faces": [n for n, f in zip(FACE_NAMES, backdrop.box.faces) if f],
                                        "weight_mean": round(float(backdrop.box_weight.mean()), 4)}
    return Asset(mesh, uvmesh, textures, _glb_sh(field.sh, bake_stats), stats, backdrop)


def write_textures(textures: PBRTextures, out: str | Path) -> None:
    """Write ``base_color.png``, ``orm.png`` and ``normal.png`` into ``out``."""
    out = Path(out)
    write_png(out / "base_color.png", textures.base_color)
    write_png(out / "orm.png", textures.orm)
    write_png(out / "normal.png", textures.normal)


def write_uv_obj(uvmesh: UVMesh, path: str | Path) -> None:
    """Write the unwrapped mesh as OBJ (world +z up, metres; ``vt`` in OBJ convention, v up), atomically."""
    buf = io.StringIO()
    buf.write("# dars bake: world +z up, metres; vt in OBJ convention (v up)\n")
    np.savetxt(buf, uvmesh.vertices, fmt="v %.6f %.6f %.6f")
    uv = np.stack([uvmesh.uvs[:, 0], 1.0 - uvmesh.uvs[:, 1]], 1)
    np.savetxt(buf, uv, fmt="vt %.6f %.6f")
    np.savetxt(buf, uvmesh.normals, fmt="vn %.6f %.6f %.6f")
    f = uvmesh.faces + 1
    np.savetxt(buf, np.repeat(f, 3, axis=1), fmt="f %d/%d/%d %d/%d/%d %d/%d/%d")
    with atomic_write(path, "w") as fh:
        fh.write(buf.getvalue())
