"""``dars mesh``, ``dars bake`` and ``dars export-asset``: trained field → mesh → baked PBR textures → GLB.

The commands parse their options into a :class:`toolkit.asset.AssetConfig` (checked before any work), call
:mod:`toolkit.asset` and write the files; the GLB is written by :func:`export.gltf.export_gltf`.

Outputs:

* ``dars mesh RUN [--out DIR]`` (default ``RUN/mesh``): ``mesh.ply`` (vertex colours = linear albedo, ``label``
  property = semantic class) and ``mesh_stats.json``.
* ``dars bake RUN [--mesh FILE] [--out DIR]`` (default ``RUN/bake``): ``base_color.png``, ``orm.png``,
  ``normal.png``, ``mesh_uv.obj`` (the unwrapped mesh; OBJ UV convention, v up) and ``bake_stats.json``.
* ``dars export-asset RUN --out DIR``: ``DIR/scene.glb`` (+ ``DIR/textures/*.png``, ``DIR/mesh.ply``,
  ``DIR/mesh_stats.json``).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from .._checks import DarsError
from ..defaults import SNAP_LAYOUT_DEFAULT
from ._common import COUNT, POSITIVE, log, number, print_json

MESH_FILES = ("mesh.ply", "mesh_stats.json")
BAKE_FILES = ("base_color.png", "orm.png", "normal.png", "mesh_uv.obj", "bake_stats.json")
ASSET_FILES = ("scene.glb", "mesh.ply", "mesh_stats.json", "textures/base_color.png", "textures/orm.png",
               "textures/normal.png")


def add_mesh_options(q: argparse.ArgumentParser) -> None:
    q.add_argument("--method", choices=("auto", "mc", "tsdf"), default="auto",
                   help="marching cubes on density, or TSDF fusion of depth maps rendered at the training cameras; "
                        "auto (default): tsdf for an unbounded field (rooms, captures), mc for an object or with "
                        "--level")
    q.add_argument("--resolution", type=number(int, min=8, max=4096), default=256,
                   help="grid cells along the longest box edge (mc), or the TSDF voxel = edge / resolution (tsdf)")
    q.add_argument("--level", type=number(float, above=0), default=None,
                   help="density iso-level in 1/m (default: from the training rays, see --level-quantile)")
    q.add_argument("--level-quantile", type=number(float, min=0, max=1), default=0.1,
                   help="without --level: the quantile of σ where the training rays cross half-transmittance, "
                        "capped at ln 2 / voxel (0 = the plain half-opacity rule ln 2 / voxel)")
    q.add_argument("--faces", type=COUNT, default=100_000, help="simplify to this many faces (0 = keep all)")
    q.add_argument("--simplify", choices=("fast", "quality"), default="fast",
                   help="fast-simplification (default) or pymeshlab quadric edge collapse")
    q.add_argument("--min-component", type=number(float, min=0, max=1), default=0.05,
                   help="drop connected components smaller than this fraction of the largest (0 = keep all), "
                        "unless the photos see them (--min-seen)")
    q.add_argument("--min-seen", type=number(float, min=0, max=1), default=0.005,
                   help="keep a component whatever its size when at least this fraction of the training rays' "
                        "half-transmittance points lies on it (1 = size alone decides)")
    q.add_argument("--keep-unseen", action="store_true", help="keep faces that no training camera sees")
    q.add_argument("--snap-layout", type=number(float, min=0, max=0.5), default=SNAP_LAYOUT_DEFAULT,
                   help="tsdf, for a run with a room box: move the mesh's vertices the field labels wall or floor "
                        "that lie within this fraction of the median depth of a confident face of the box onto "
                        "its plane "
                        f"(default {SNAP_LAYOUT_DEFAULT}; 0 = off)")
    q.add_argument("--depth-samples", type=POSITIVE, default=128, help="samples per ray for --method tsdf depth maps")
    q.add_argument("--depth-min-opacity", type=number(float, above=0, max=0.5), default=0.5,
                   help="tsdf: below 0.5, a ray that never reaches half opacity but gathers at least this much in the "
                        "meshed region gives the median of its own termination (translucent walls are meshed too, "
                        "with poor colour); default 0.5: only rays that reach half opacity")
    q.add_argument("--depth-rays", type=number(int, min=64), default=1_000_000,
                   help="tsdf: at most this many depth rays over all training views (larger photos are rendered "
                        "on a smaller pixel grid)")
    q.add_argument("--device", default="cpu", help="device the field is queried on")


def add_bake_options(q: argparse.ArgumentParser, backdrop: bool = True) -> None:
    """The bake options; ``backdrop``: also ``--no-backdrop`` and ``--no-light-occlusion`` (commands that write a
    GLB)."""
    q.add_argument("--texture", type=number(int, min=16, max=16384), default=2048,
                   help="texture size in texels (square, 16-16384)")
    q.add_argument("--supersample", type=int, default=1, choices=(1, 2), help="bake at 2x and box-filter down")
    q.add_argument("--ao-samples", type=COUNT, default=0, help="rays per texel for ambient occlusion (0 = none)")
    q.add_argument("--bake-from", choices=("views", "points"), default="views",
                   help="views (default): a texel's albedo is the mean of the field's own render over the training "
                        "views that see it (what the photos were fitted to); points: the field queried at the "
                        "texel's surface point (also used where no view sees a texel)")
    q.add_argument("--view-rays", type=number(int, min=64), default=2_000_000,
                   help="--bake-from views: at most this many rendered pixels over all training views")
    q.add_argument("--normals-from", choices=("views", "points"), default="views",
                   help="--bake-from views: views (default): the normal map is the mean of the field's rendered "
                        "normals over the views that see a texel; points: the field's normal at the texel's surface "
                        "point")
    q.add_argument("--view-tolerance", type=number(float, above=0, max=0.5), default=0.1,
                   help="--bake-from views: a view sees a texel when its depth is within this fraction of the "
                        "rendered depth")
    if backdrop:
        q.add_argument("--no-light-occlusion", dest="light_occlusion", action="store_false",
                       help="--bake-from views: leave the field's per-point light out of the GLB's occlusion channel "
                            "(occlusion 1, the run's own SH); by default each texel's occlusion is its light gain "
                            "over a scale s and the GLB's SH is the run's times s")
        q.add_argument("--no-light-tint", dest="light_tint", action="store_false",
                       help="--bake-from views: store no light-tint texture (the colour of the field's per-point "
                            "light, which the grey occlusion channel cannot hold; read by dars view and the WebXR "
                            "page, ignored by other glTF viewers)")
        q.add_argument("--no-light-fit", dest="light_fit", action="store_false",
                       help="--bake-from views: take the occlusion and light tint from the field's light gain and "
                            "tint as they are, instead of fitting them so that the viewer's shading of the baked "
                            "textures reproduces the field's colour at the training views")
        q.add_argument("--viewer-fit", type=number(int, min=0, max=8), default=1, metavar="PASSES",
                       help="with the light fit: render the GLB with dars view's renderer at the views it was baked "
                            "from, fit a per-vertex light factor that brings what the viewer shows to the field's "
                            "colour, and re-bake; this many passes (default 1; 0 = off; needs headless OpenGL)")
        q.add_argument("--no-backdrop", dest="backdrop", action="store_false",
                       help="store no backdrop in the GLB (what the viewers draw where the mesh is not — a gallery's "
                            "sky, the white behind an object, holes in the mesh — taken from the field's renders)")
        q.add_argument("--no-backdrop-box", dest="backdrop_box", action="store_false",
                       help="keep the backdrop at infinity (one map keyed by direction) instead of also projecting "
                            "it on the room box's confident faces, where a hole in the mesh shows the floor or wall "
                            "behind it from where the camera stands")


def add_parser(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("mesh", help="extract a mesh from a trained field (marching cubes or TSDF fusion)")
    q.add_argument("run", help="RUN directory (output of `dars train`)")
    q.add_argument("--out", default=None, help="output directory (default RUN/mesh)")
    add_mesh_options(q)
    q.add_argument("--force", action="store_true", help="write into a non-empty folder beside its files")
    q.add_argument("--json", action="store_true", help="machine-readable statistics on stdout")
    q.set_defaults(func=cmd_mesh)

    q = sub.add_parser("bake", help="UV-unwrap a mesh and bake PBR textures (base colour, ORM, normal) from the field")
    q.add_argument("run", help="RUN directory (output of `dars train`)")
    q.add_argument("--mesh", default=None, help="mesh to bake (default RUN/mesh/mesh.ply; run `dars mesh` first)")
    q.add_argument("--out", default=None, help="output directory (default RUN/bake)")
    add_bake_options(q, backdrop=False)
    q.add_argument("--device", default="cpu", help="device the field is queried on")
    q.add_argument("--force", action="store_true", help="write into a non-empty folder beside its files")
    q.add_argument("--json", action="store_true", help="machine-readable statistics on stdout")
    q.set_defaults(func=cmd_bake)

    q = sub.add_parser("export-asset", help="field -> mesh -> baked textures -> DIR/scene.glb (glTF 2.0)")
    q.add_argument("run", help="RUN directory (output of `dars train`)")
    q.add_argument("--out", required=True, help="output directory (writes scene.glb, textures/, mesh stats)")
    add_mesh_options(q)
    add_bake_options(q)
    q.add_argument("--no-sh", action="store_true", help="do not store the SH lighting in the GLB")
    q.add_argument("--force", action="store_true", help="write into a non-empty folder beside its files")
    q.add_argument("--json", action="store_true", help="machine-readable statistics on stdout")
    q.set_defaults(func=cmd_export_asset)


def asset_config(args: argparse.Namespace):
    """The :class:`toolkit.asset.AssetConfig` of the mesh / bake options (those a command has keep their defaults).

    Raises:
        ConfigError: an option is out of range (naming it), before any work.
    """
    from ..asset import AssetConfig

    names = ("method", "resolution", "level", "level_quantile", "faces", "simplify", "min_component", "min_seen",
             "keep_unseen", "snap_layout", "depth_samples", "depth_min_opacity", "depth_rays", "texture", "supersample",
             "ao_samples", "bake_from", "view_rays", "normals_from", "view_tolerance", "light_occlusion", "light_tint",
             "light_fit", "viewer_fit", "backdrop", "backdrop_box", "device")
    return AssetConfig(**{k: getattr(args, k) for k in names if hasattr(args, k)})


def export_glb(asset, path: Path, sh=None) -> Path:
    """Write ``asset`` as a GLB with ``sh`` (float [9, 3] or None) and its mesh statistics."""
    from export.gltf import export_gltf

    return export_gltf(asset.uvmesh, asset.textures, path, sh=sh, extras=asset.gltf_extras())


def _finish(args, stats: dict, human: str) -> int:
    if args.json:
        print_json(stats)
    else:
        print(human)
    return 0


def _out(args, default: str, planned):
    """The command's output folder (``--out`` or ``RUN/<default>``), checked before any work."""
    from ..outputs import OutputDir

    path = Path(args.out) if args.out else Path(args.run) / default
    option = "--out" if args.out else f"the default output folder (RUN/{default}; --out picks another)"
    return OutputDir(path, args.command, force=args.force, option=option).check(planned)


def _require_run(run: str) -> None:
    """A RUN that is not a run folder (or has a corrupt config.json) fails here, before any work."""
    from ..train.folder import find_run

    find_run(run)


def cmd_mesh(args: argparse.Namespace) -> int:
    from ..asset import asset_field, build_mesh
    from ..io import write_json
    from ..mesh import save_mesh

    cfg = asset_config(args)
    _require_run(args.run)
    out = _out(args, "mesh", MESH_FILES)
    field = asset_field(args.run)
    mesh, stats = build_mesh(field, cfg)
    with out:
        save_mesh(mesh, out.path / "mesh.ply")
        stats["mesh"] = str(out.path / "mesh.ply")
        write_json(out.path / "mesh_stats.json", stats)
    return _finish(args, stats, f"wrote {out.path / 'mesh.ply'} ({stats['vertices']} vertices, {stats['faces']} faces)")


def cmd_bake(args: argparse.Namespace) -> int:
    from ..asset import asset_field, bake_mesh, view_maps, write_textures, write_uv_obj
    from ..io import write_json
    from ..mesh import load_mesh

    # textures and an OBJ: no GLB to carry a backdrop, nor the SH scale the light occlusion needs
    cfg = replace(asset_config(args), backdrop=False, light_occlusion=False)
    _require_run(args.run)
    mesh_path = Path(args.mesh) if args.mesh else Path(args.run) / "mesh" / "mesh.ply"
    if not mesh_path.is_file():
        raise DarsError(f"mesh not found: {mesh_path} (run `dars mesh {args.run}` first or pass --mesh FILE)")
    out = _out(args, "bake", BAKE_FILES)
    mesh = load_mesh(mesh_path)
    field = asset_field(args.run)
    uvmesh, textures, stats = bake_mesh(mesh, field.material_fn, cfg, log=log, views=view_maps(field, cfg, log))
    with out:
        write_textures(textures, out.path)
        write_uv_obj(uvmesh, out.path / "mesh_uv.obj")
        stats["out"] = str(out.path)
        write_json(out.path / "bake_stats.json", stats)
    return _finish(args, stats, f"wrote {out.path}/base_color.png, orm.png, normal.png, mesh_uv.obj")


def cmd_export_asset(args: argparse.Namespace) -> int:
    from ..asset import build_asset, write_textures
    from ..io import write_json
    from ..mesh import save_mesh

    cfg = asset_config(args)
    _require_run(args.run)
    out = _out(args, "", ASSET_FILES)
    from viewers.refit import viewer_correction

    asset = build_asset(args.run, cfg, log=log, viewer_correction=viewer_correction)
    stats = asset.stats
    with out:
        save_mesh(asset.mesh, out.path / "mesh.ply")
        write_textures(asset.textures, out.path / "textures")
        glb = export_glb(asset, out.path / "scene.glb", sh=None if args.no_sh else asset.sh)
        stats["glb"] = str(glb)
        stats["glb_bytes"] = glb.stat().st_size
        write_json(out.path / "mesh_stats.json", stats)
    return _finish(args, stats, f"wrote {glb} ({stats['faces']} faces, {args.texture}² textures, "
                                f"{stats['glb_bytes'] / 1e6:.1f} MB)")
