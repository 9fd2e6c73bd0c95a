"""Mesh clean-up: connected components, floater removal, faces no camera sees."""

from __future__ import annotations

import math

import numpy as np
import torch

from .._checks import ConfigError, ShapeError, check_range, check_shape
from ._field import _to_numpy
from .types import Mesh


def _weld_ids(vertices: np.ndarray) -> np.ndarray:
    """Index of the first vertex at the same position, per vertex (so split seams count as connected)."""
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)]


def face_components(mesh: Mesh) -> np.ndarray:
    """Connected-component id per face (faces sharing a vertex position are connected). int64 [F]."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if mesh.num_faces == 0:
        return np.zeros(0, dtype=np.int64)
    f = _weld_ids(mesh.vertices)[mesh.faces]
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    n = mesh.num_vertices
    graph = coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    return comp[f[:, 0]].astype(np.int64)


def remove_floaters(mesh: Mesh, min_faces: int | None = None, min_fraction: float | None = None,
                    seen_points: np.ndarray | None = None, radius: float = 0.0, min_seen: float = 0.005) -> Mesh:
    """Drop connected components with fewer faces than a threshold, unless the photos see them.

    Size alone misjudges a room: its floor and walls are one component of hundreds of thousands of faces, and a
    painting the field renders opaque but whose wall it left as fog is a separate component of a few percent of
    that. With ``seen_points`` (where training rays reach half transmittance,
    :func:`toolkit.mesh.seen_surface_points`) a component is also kept when at least ``min_seen`` of those points
    lie within ``radius`` of its vertices: a floater is what few rays see, not what is small.

    Args:
        mesh: input mesh.
        min_faces: keep components with at least this many faces.
        min_fraction: keep components with at least this fraction of the largest component's faces.
            With neither given, ``min_fraction=0.05``. With both, a component must pass both.
        seen_points: float [M, 3] surface points the photos see (world metres), or None (size test only).
        radius: metres; a seen point belongs to the component of its nearest vertex within this distance.
        min_seen: fraction of the M points a component must hold to be kept whatever its size.

    Returns:
        :class:`Mesh` without the small, unseen components (unreferenced vertices dropped).
    """
    if mesh.num_faces == 0:
        return mesh
    if min_fraction is not None:
        check_range(min_fraction, 0.0, 1.0, "min_fraction")
    check_range(min_seen, 0.0, 1.0, "min_seen")
    if min_faces is None and min_fraction is None:
        min_fraction = 0.05
    comp = face_components(mesh)
    sizes = np.bincount(comp)
    keep_comp = np.ones(sizes.size, dtype=bool)
    if min_faces is not None:
        keep_comp &= sizes >= int(min_faces)
    if min_fraction is not None:
        keep_comp &= sizes >= min_fraction * sizes.max()
    if seen_points is not None and len(seen_points):
        if not (math.isfinite(radius) and radius > 0):
            raise ConfigError(f"radius={radius!r}: seen_points need a positive radius in metres (a few voxels)")
        keep_comp |= seen_component_counts(mesh, comp, seen_points, radius) >= max(1.0, min_seen * len(seen_points))
    return mesh.submesh(keep_comp[comp])


def seen_component_counts(mesh: Mesh, comp: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """How many of ``points`` (float [M, 3]) have their nearest vertex within ``radius`` in each component of
    ``comp`` (int [F], :func:`face_components`). int64 [number of components]."""
    from scipy.spatial import cKDTree

    check_shape(np.asarray(points), "M 3", "seen_points")
    vert_comp = np.full(mesh.num_vertices, -1, dtype=np.int64)
    vert_comp[mesh.faces.reshape(-1)] = np.repeat(comp, 3)
    dist, idx = cKDTree(mesh.vertices).query(np.asarray(points, dtype=np.float64), distance_upper_bound=radius)
    hit = np.isfinite(dist)
    c = vert_comp[idx[hit]]
    return np.bincount(c[c >= 0], minlength=int(comp.max()) + 1 if comp.size else 0)


def remove_unseen_faces(mesh: Mesh, cameras, depths: torch.Tensor | np.ndarray | None = None,
                        depth_tolerance: float | None = None) -> Mesh:
    """Drop faces no camera sees: their centroid projects outside every image (or behind every camera) or,
    with ``depths``, lies farther than the depth map in every view where it projects (occluded).

    Args:
        mesh: input mesh.
        cameras: :class:`toolkit.scene.Cameras`.
        depths: optional float [K, H, W] depth maps along the camera axis, metres (0 = no measurement, which
            counts as "not occluded").
        depth_tolerance: a centroid is visible if its depth ≤ map depth + this (metres); None = 1 % of the
            mesh's bounding-box diagonal.

    Returns:
        :class:`Mesh` with only the faces seen by at least one camera.
    """
    from ..cameras import project_points

    if mesh.num_faces == 0:
        return mesh
    tol = float(depth_tolerance) if depth_tolerance is not None else 0.01 * mesh.diagonal
    d = None
    if depths is not None:
        d = _to_numpy(depths, "depths").astype(np.float32)
        check_shape(d, f"{len(cameras)} H W", "depths")
    centroids = torch.from_numpy(mesh.vertices[mesh.faces].astype(np.float64).mean(1))
    cams = cameras.to("cpu")
    cams = type(cams)(*(getattr(cams, f).double() if getattr(cams, f).is_floating_point() else getattr(cams, f)
                        for f in ("c2w", "fx", "fy", "cx", "cy", "width", "height")))
    seen = np.zeros(mesh.num_faces, dtype=bool)
    for k in range(len(cams)):
        uv, z = project_points(cams, k, centroids)
        uv, z = uv.numpy(), z.numpy()
        w, h = int(cams.width[k]), int(cams.height[k])
        inside = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        if d is not None:
            if d.shape[1:] != (h, w):
                raise ShapeError(f"depths are {d.shape[2]}x{d.shape[1]} px but camera {k} is {w}x{h}")
            idx = np.nonzero(inside)[0]
            px = np.clip(uv[idx].astype(np.int64), 0, [w - 1, h - 1])
            dm = d[k, px[:, 1], px[:, 0]]
            visible = (dm <= 0) | ~np.isfinite(dm) | (z[idx] <= dm + tol)
            inside[idx] = visible
        seen |= inside
    return mesh.submesh(seen)
