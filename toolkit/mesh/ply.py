"""Mesh files: PLY with vertex colours and per-vertex semantic labels (:func:`save_mesh`, :func:`load_mesh`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._checks import ConfigError
from .types import Mesh, _as_mesh


def save_mesh(mesh: Mesh, path: str | Path) -> Path:
    """Write a mesh as PLY (binary; with normals, colours as uint8 RGB and a ``label`` vertex property when present)
    or OBJ (positions, normals; no colours), atomically.

    Args:
        mesh: the mesh.
        path: ``.ply`` or ``.obj`` file.

    Returns:
        the path written.

    Raises:
        ConfigError: unsupported suffix.
    """
    import trimesh

    from ..io import atomic_write

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".obj"):
        raise ConfigError(f"save_mesh: {path} must end in .ply or .obj")
    tm = trimesh.Trimesh(mesh.vertices.astype(np.float64), mesh.faces, process=False,
                         vertex_normals=mesh.normals if mesh.normals is not None else None)
    if mesh.colors is not None:
        rgba = np.concatenate([np.clip(mesh.colors * 255 + 0.5, 0, 255), np.full((mesh.num_vertices, 1), 255)], 1)
        tm.visual.vertex_colors = rgba.astype(np.uint8)
    if suffix == ".ply":
        if mesh.labels is not None:
            tm.vertex_attributes["label"] = mesh.labels.astype(np.uint8)
        data = trimesh.exchange.ply.export_ply(tm, encoding="binary", vertex_normal=mesh.normals is not None,
                                               include_attributes=True)
    else:
        data = trimesh.exchange.obj.export_obj(tm, include_normals=mesh.normals is not None, include_color=False,
                                               include_texture=False).encode()
    with atomic_write(path) as f:
        f.write(data)
    return path


def load_mesh(path: str | Path) -> Mesh:
    """Read a PLY/OBJ/… mesh with trimesh (no processing: vertex order kept; multi-part files are concatenated).

    Raises:
        SceneError: missing or unreadable file.
    """
    import trimesh

    from .._checks import SceneError

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"mesh file not found: {path}")
    try:
        tm = trimesh.load(path, process=False, force="mesh")
    except Exception as e:  # noqa: BLE001 - any decode failure is a corrupt file
        raise SceneError(f"mesh file {path} could not be read ({type(e).__name__}: {e}): it is damaged or not a mesh; "
                         "give a PLY/OBJ/GLB mesh (e.g. RUN/mesh/mesh.ply from `dars mesh RUN`)") from e
    colors = None
    if tm.visual.kind == "vertex":
        colors = np.asarray(tm.visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    labels = normals = None
    raw = (tm.metadata.get("_ply_raw") or {}).get("vertex", {}).get("data")  # PLY: the file's own vertex properties
    names = tuple(raw.keys()) if isinstance(raw, dict) else (raw.dtype.names or ()) if raw is not None else ()
    n = len(tm.vertices)
    prop = lambda k: np.asarray(raw[k]).reshape(-1)  # noqa: E731
    if "label" in names and prop("label").size == n:
        labels = prop("label").astype(np.uint8)
    if all(k in names for k in ("nx", "ny", "nz")) and prop("nx").size == n:
        normals = np.stack([prop("nx"), prop("ny"), prop("nz")], 1).astype(np.float32)
    return _as_mesh(tm.vertices, tm.faces, normals=normals, colors=colors, labels=labels)
