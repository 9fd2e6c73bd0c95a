"""Stage 13a — field → triangle mesh: marching cubes on density, TSDF fusion, clean-up, simplification, errors.

Modules: :mod:`~toolkit.mesh.types` (:class:`Mesh`), :mod:`~toolkit.mesh.extract` (marching cubes, iso-levels, vertex
attributes), :mod:`~toolkit.mesh.tsdf` (depth maps, TSDF fusion), :mod:`~toolkit.mesh.clean`,
:mod:`~toolkit.mesh.simplify`, :mod:`~toolkit.mesh.distance` (Chamfer), :mod:`~toolkit.mesh.ply` (files); every
public name is importable from :mod:`toolkit.mesh`.

Everything here runs on the CPU with numpy arrays (the field callables may run on any torch device: points are sent
to ``device`` and results brought back). Meshes are :class:`Mesh` records: ``vertices`` float32 [V, 3] in world
metres (+z up, SPEC), ``faces`` int64 [F, 3] counter-clockwise seen from outside (outward normals).

Field interface (callables, so this module never owns the model — as nerfacc's ``sigma_fn``):

* ``density_fn(points: float [N, 3]) -> float [N]``: volume density σ in 1/metre at world points. It is called
  with a float32 torch tensor under ``torch.no_grad()``; it may return a torch tensor or a numpy array.

**The iso-level (opacity rule).** A slab of thickness δ with density σ has opacity α = 1 − exp(−σδ). Marching cubes
on a grid of voxel size δ can only represent what is opaque *at that scale*, so the default level is the density at
which one voxel-thick layer is half opaque::

    σ* = −ln(1 − α*) / δ,   α* = 0.5  →  σ* = ln 2 / δ.

It is scale-aware (metres or millimetres give the same surface) and has a sharp meaning for SDF-like fields: for a
VolSDF/NeuS-style density σ = Ψ_β(−d)/β (Laplace CDF of the signed distance d, sharpness β) the σ* level set lies
at d = β·ln(δ / (2β ln 2)) for β ≤ δ/(2 ln 2): never more than δ/(2e ln 2) ≈ 0.27 voxel outside the true surface,
whatever β, and exactly on it for β = δ/(2 ln 2). Material that never reaches σ* (fog, faint floaters) is not
opaque at this resolution and produces no surface. ``MeshConfig.opacity_thickness`` fixes δ in metres instead of
the voxel size (a resolution-independent level); ``MeshConfig.level`` overrides σ* outright.

**The level from the photos' rays** (:func:`level_from_rays`, what ``dars export-asset`` uses). A field trained for
minutes on a CPU is not SDF-like everywhere: some objects end up as a soft volume whose density never reaches
ln 2/δ although it stops the rays that see it (the sample's pedestal: σ ≈ 2–10 /m where its rays cross
half-transmittance, against σ* = 29 /m at 256³). :func:`level_from_rays` marches the training cameras' rays and
takes a low quantile (default 10 %) of σ where each ray's transmittance crosses ½ — the surfaces the photos see —
capped at the opacity rule, so sharp fields keep σ* and soft objects are not lost.
"""

from .clean import face_components, remove_floaters, remove_unseen_faces
from .distance import MeshDistance, mesh_distance, sample_surface
from .extract import (MeshConfig, extract_mesh, grid_spec, level_from_rays, opacity_level, query_vertex_attributes,
                      seen_surface_points, surface_region)
from .planes import PlaneSnapConfig, snap_to_planes
from .ply import load_mesh, save_mesh
from .simplify import SimplifyConfig, SimplifyReport, simplify_mesh
from .tsdf import DepthRenderConfig, TsdfConfig, fuse_tsdf, opengl_c2w_to_opencv_w2c, render_depth
from .types import DensityFn, MaterialFn, Mesh, compute_vertex_normals

__all__ = [
    "Mesh",
    "DensityFn",
    "MaterialFn",
    "MeshConfig",
    "TsdfConfig",
    "DepthRenderConfig",
    "SimplifyConfig",
    "SimplifyReport",
    "MeshDistance",
    "opacity_level",
    "level_from_rays",
    "seen_surface_points",
    "surface_region",
    "grid_spec",
    "extract_mesh",
    "render_depth",
    "fuse_tsdf",
    "remove_floaters",
    "remove_unseen_faces",
    "simplify_mesh",
    "PlaneSnapConfig",
    "snap_to_planes",
    "mesh_distance",
    "sample_surface",
    "face_components",
    "opengl_c2w_to_opencv_w2c",
    "compute_vertex_normals",
    "query_vertex_attributes",
    "save_mesh",
    "load_mesh",
]
