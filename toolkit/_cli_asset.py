"""``dars mesh``, ``dars bake`` and ``dars export-asset``: trained field → mesh → baked PBR textures → GLB.

The commands only parse, call stages (:mod:`toolkit.mesh`, :mod:`toolkit.bake`, :mod:`export.gltf`) and write
files. The trained field is loaded through ``toolkit.field.load_field_callables(run_dir)``, which returns
``(density_fn, material_fn, aabb, sh, cameras)`` (``sh`` and ``cameras`` may be None). Heavy modules are imported
inside the handlers so ``dars --help`` stays fast.

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
import json
import sys
import time
from pathlib import Path

from ._checks import DarsError

__all__ = ["add_parser"]


def _log(msg: str) -> None:
    print(msg, file=sys.stderr)


def _load_field(run: str):
    run_dir = Path(run)
    if not run_dir.is_dir():
        raise DarsError(f"RUN directory not found: {run_dir} (give the --out directory of `dars train`)")
    try:
        from .field import load_field_callables  # type: ignore[attr-defined]
    except ImportError as e:
        raise DarsError("loading a trained field needs toolkit.field.load_field_callables(run_dir), which this "
                        f"installation does not provide yet ({e})") from e
    density_fn, material_fn, aabb, sh, cameras = load_field_callables(run_dir)
    return density_fn, material_fn, aabb, sh, cameras


def _add_mesh_options(q: argparse.ArgumentParser) -> None:
    q.add_argument("--method", choices=("mc", "tsdf"), default="mc",
                   help="marching cubes on density (default) or TSDF fusion of rendered depth maps")
    q.add_argument("--resolution", type=int, default=256,
                   help="grid cells along the longest box edge (mc), or the TSDF voxel = edge / resolution (tsdf)")
    q.add_argument("--level", type=float, default=None,
                   help="density iso-level in 1/m (default: from the training rays, see --level-quantile)")
    q.add_argument("--level-quantile", type=float, default=0.1,
                   help="without --level: the quantile of σ where the training rays cross half-transmittance, "
                        "capped at ln 2 / voxel (0 = the plain half-opacity rule ln 2 / voxel)")
    q.add_argument("--faces", type=int, default=100_000, help="simplify to this many faces (0 = keep all)")
    q.add_argument("--simplify", choices=("fast", "quality"), default="fast",
                   help="fast-simplification (default) or pymeshlab quadric edge collapse")
    q.add_argument("--min-component", type=float, default=0.05,
                   help="drop connected components smaller than this fraction of the largest (0 = keep all)")
    q.add_argument("--keep-unseen", action="store_true", help="keep faces that no training camera sees")
    q.add_argument("--depth-samples", type=int, default=256, help="samples per ray for --method tsdf depth maps")
    q.add_argument("--device", default="cpu", help="device the field is queried on")


def _add_bake_options(q: argparse.ArgumentParser) -> None:
    q.add_argument("--texture", type=int, default=1024, help="texture size in texels (square)")
    q.add_argument("--supersample", type=int, default=1, choices=(1, 2), help="bake at 2x and box-filter down")
    q.add_argument("--ao-samples", type=int, default=0, help="rays per texel for ambient occlusion (0 = none)")


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``mesh``, ``bake`` and ``export-asset`` on the ``dars`` subparsers."""
    q = sub.add_parser("mesh", help="extract a mesh from a trained field (marching cubes or TSDF fusion)")
    q.add_argument("run", help="RUN directory (output of `dars train`)")
    q.add_argument("--out", default=None, help="output directory (default RUN/mesh)")
    _add_mesh_options(q)
    q.add_argument("--json", action="store_true", help="machine-readable statistics on stdout")
    q.set_defaults(func=cmd_mesh)

    q = sub.add_parser("bake", help="UV-unwrap a mesh and bake PBR textures (base colour, ORM, normal) from the field")
    q.add_argument("run", help="RUN directory (output of `dars train`)")
    q.add_argument("--mesh", default=None, help="mesh to bake (default RUN/mesh/mesh.ply; run `dars mesh` first)")
    q.add_argument("--out", default=None, help="output directory (default RUN/bake)")
    _add_bake_options(q)
    q.add_argument("--device", default="cpu", help="device the field is queried on")
    q.add_argument("--json", action="store_true", help="machine-readable statistics on stdout")
    q.set_defaults(func=cmd_bake)

    q = sub.add_parser("export-asset", help="field -> mesh -> baked textures -> DIR/scene.glb (glTF 2.0)")
    q.add_argument("run", help="RUN directory (output of `dars train`)")
    q.add_argument("--out", required=True, help="output directory (writes scene.glb, textures/, mesh stats)")
    _add_mesh_options(q)
    _add_bake_options(q)
    q.add_argument("--no-sh", action="store_true", help="do not store the SH lighting in the GLB")
    q.add_argument("--json", action="store_true", help="machine-readable statistics on stdout")
    q.set_defaults(func=cmd_export_asset)


# ------------------------------------------------------------------------------------------------------- pipeline
def build_mesh(density_fn, material_fn, aabb, cameras, args) -> tuple[object, dict]:
    """The mesh half of the pipeline with the CLI's options: extract, clean, simplify, colour. Returns (mesh, stats)."""
    import numpy as np

    from .mesh import (DepthRenderConfig, MeshConfig, TsdfConfig, _grid_spec, extract_mesh, fuse_tsdf, level_from_rays,
                       query_vertex_attributes, remove_floaters, remove_unseen_faces, render_depth, simplify_mesh)

    if args.resolution < 8:
        raise DarsError(f"--resolution {args.resolution} is too small (use ≥ 8)")
    stats: dict = {"method": args.method, "resolution": args.resolution}
    t0 = time.perf_counter()
    box = np.asarray(aabb.detach().cpu().numpy() if hasattr(aabb, "detach") else aabb, dtype=np.float64)
    if args.method == "mc":
        level = args.level
        if level is None and args.level_quantile > 0 and cameras is not None:
            voxel, _ = _grid_spec(box, args.resolution)  # the voxel extract_mesh will use
            level, stats["level_from_rays"] = level_from_rays(density_fn, cameras, box, voxel,
                                                              quantile=args.level_quantile, device=args.device)
        mesh = extract_mesh(density_fn, box, MeshConfig(resolution=args.resolution, level=level, device=args.device))
        stats["level"] = level
    else:
        if cameras is None:
            raise DarsError("--method tsdf needs the training cameras, but the RUN's field loader returned none")
        depths = render_depth(density_fn, cameras, box, DepthRenderConfig(samples=args.depth_samples, device=args.device))
        voxel = float((box[1] - box[0]).max()) / args.resolution
        mesh = fuse_tsdf(depths, cameras, cfg=TsdfConfig(voxel_size=voxel, depth_max=float(np.linalg.norm(box[1] - box[0])) * 4))
    stats["extract_seconds"] = round(time.perf_counter() - t0, 3)
    stats["faces_extracted"] = mesh.num_faces
    if mesh.num_faces == 0:
        raise DarsError("the field produced an empty mesh (density never reaches the iso-level inside the box); "
                        "try a lower --level or check the RUN")
    if args.min_component > 0:
        mesh = remove_floaters(mesh, min_fraction=args.min_component)
    if cameras is not None and not args.keep_unseen:
        mesh = remove_unseen_faces(mesh, cameras)
    stats["faces_cleaned"] = mesh.num_faces
    if args.faces and mesh.num_faces > args.faces:
        mesh, report = simplify_mesh(mesh, args.faces, method=args.simplify)
        stats["simplify"] = report.to_dict()
    mesh = query_vertex_attributes(mesh, material_fn, device=args.device)
    stats.update(vertices=mesh.num_vertices, faces=mesh.num_faces, bounds=mesh.bounds.tolist(),
                 area_m2=round(mesh.area(), 6))
    return mesh, stats


def bake_mesh(mesh, material_fn, args) -> tuple[object, object, dict]:
    """Unwrap, label and bake with the CLI's options. Returns (uvmesh, textures, stats)."""
    from .bake import BakeConfig, UnwrapConfig, bake_pbr_textures, label_faces, unwrap_uv

    t0 = time.perf_counter()
    uvmesh = unwrap_uv(mesh, UnwrapConfig(texture_size=args.texture))
    t1 = time.perf_counter()
    uvmesh = label_faces(uvmesh, material_fn, device=args.device)
    textures = bake_pbr_textures(uvmesh, material_fn, BakeConfig(size=args.texture, supersample=args.supersample,
                                                                  ao_samples=args.ao_samples, device=args.device))
    stats = {"texture": args.texture, "supersample": args.supersample, "uv_vertices": uvmesh.num_vertices,
             "unwrap_seconds": round(t1 - t0, 3), "bake_seconds": round(time.perf_counter() - t1, 3),
             "chart_coverage": round(float(textures.mask.mean()), 4), "defaults": list(textures.defaults)}
    return uvmesh, textures, stats


def _write_textures(textures, out: Path) -> None:
    from .io import write_png

    write_png(out / "base_color.png", textures.base_color)
    write_png(out / "orm.png", textures.orm)
    write_png(out / "normal.png", textures.normal)


def _finish(args, stats: dict, human: str) -> int:
    if args.json:
        sys.stdout.write(json.dumps(stats, indent=2) + "\n")
    else:
        print(human)
    return 0


# ------------------------------------------------------------------------------------------------------- commands
def cmd_mesh(args: argparse.Namespace) -> int:
    from .io import write_json
    from .mesh import save_mesh

    density_fn, material_fn, aabb, _, cameras = _load_field(args.run)
    out = Path(args.out) if args.out else Path(args.run) / "mesh"
    mesh, stats = build_mesh(density_fn, material_fn, aabb, cameras, args)
    save_mesh(mesh, out / "mesh.ply")
    stats["mesh"] = str(out / "mesh.ply")
    write_json(out / "mesh_stats.json", stats)
    return _finish(args, stats, f"wrote {out / 'mesh.ply'} ({stats['vertices']} vertices, {stats['faces']} faces)")


def cmd_bake(args: argparse.Namespace) -> int:
    from .io import atomic_write, write_json
    from .mesh import load_mesh

    _, material_fn, _, _, _ = _load_field(args.run)
    mesh_path = Path(args.mesh) if args.mesh else Path(args.run) / "mesh" / "mesh.ply"
    if not mesh_path.is_file():
        raise DarsError(f"mesh not found: {mesh_path} (run `dars mesh {args.run}` first or pass --mesh FILE)")
    mesh = load_mesh(mesh_path)
    out = Path(args.out) if args.out else Path(args.run) / "bake"
    uvmesh, textures, stats = bake_mesh(mesh, material_fn, args)
    _write_textures(textures, out)
    with atomic_write(out / "mesh_uv.obj", "w") as f:
        f.write(_uv_obj_text(uvmesh))
    stats["out"] = str(out)
    write_json(out / "bake_stats.json", stats)
    return _finish(args, stats, f"wrote {out}/base_color.png, orm.png, normal.png, mesh_uv.obj")


def cmd_export_asset(args: argparse.Namespace) -> int:
    from export.gltf import export_gltf

    from .io import write_json
    from .mesh import save_mesh

    density_fn, material_fn, aabb, sh, cameras = _load_field(args.run)
    out = Path(args.out)
    mesh, stats = build_mesh(density_fn, material_fn, aabb, cameras, args)
    uvmesh, textures, bake_stats = bake_mesh(mesh, material_fn, args)
    stats["bake"] = bake_stats
    save_mesh(mesh, out / "mesh.ply")
    _write_textures(textures, out / "textures")
    glb = export_gltf(uvmesh, textures, out / "scene.glb", sh=None if args.no_sh else sh,
                      extras={"mesh_stats": {k: stats[k] for k in ("vertices", "faces", "area_m2", "method")}})
    stats["glb"] = str(glb)
    stats["glb_bytes"] = glb.stat().st_size
    write_json(out / "mesh_stats.json", stats)
    return _finish(args, stats, f"wrote {glb} ({stats['faces']} faces, {args.texture}² textures, "
                                f"{stats['glb_bytes'] / 1e6:.1f} MB)")


def _uv_obj_text(uvmesh) -> str:
    import io

    import numpy as np

    buf = io.StringIO()
    buf.write("# dars bake: world +z up, metres; vt in OBJ convention (v up)\n")
    np.savetxt(buf, uvmesh.vertices, fmt="v %.6f %.6f %.6f")
    uv = np.stack([uvmesh.uvs[:, 0], 1.0 - uvmesh.uvs[:, 1]], 1)
    np.savetxt(buf, uv, fmt="vt %.6f %.6f")
    np.savetxt(buf, uvmesh.normals, fmt="vn %.6f %.6f %.6f")
    f = uvmesh.faces + 1
    np.savetxt(buf, np.repeat(f, 3, axis=1), fmt="f %d/%d/%d %d/%d/%d %d/%d/%d")
    return buf.getvalue()
