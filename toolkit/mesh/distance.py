"""Surface sampling and the symmetric mesh distance (Chamfer / Hausdorff) between two meshes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._checks import DarsError
from .types import Mesh, _face_areas


@dataclass(frozen=True)
class MeshDistance:
    """Symmetric surface distance between two meshes (point samples → exact point-to-triangle distance).

    Attributes:
        mean: symmetric Chamfer distance, metres: ½(mean d(A→B) + mean d(B→A)).
        max: symmetric Hausdorff distance estimate, metres: max over both directions.
        mean_ab, mean_ba, max_ab, max_ba: the one-sided terms, metres.
        diagonal: bounding-box diagonal of the reference mesh B, metres.
        mean_fraction, max_fraction: ``mean`` and ``max`` as fractions of ``diagonal``.
        samples: points sampled on each mesh.
    """

    mean: float
    max: float
    mean_ab: float
    mean_ba: float
    max_ab: float
    max_ba: float
    diagonal: float
    mean_fraction: float
    max_fraction: float
    samples: int

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def sample_surface(mesh: Mesh, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points uniformly distributed over the surface (area-weighted). float64 [n, 3]."""
    rng = np.random.default_rng(seed)
    areas = _face_areas(mesh.vertices, mesh.faces)
    if areas.sum() <= 0:
        raise DarsError("cannot sample a mesh with zero surface area")
    fi = rng.choice(mesh.num_faces, size=n, p=areas / areas.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    tri = mesh.vertices[mesh.faces[fi]].astype(np.float64)
    return np.einsum("nk,nkd->nd", bary, tri)


def _distance_to(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)


def mesh_distance(mesh: Mesh, reference: Mesh, samples: int = 100_000, seed: int = 0) -> MeshDistance:
    """Chamfer (mean) and Hausdorff (max) distance between two surfaces, in metres and as a fraction of the
    reference's bounding-box diagonal.

    ``samples`` points are drawn area-uniformly on each mesh and their exact distance to the *other surface*
    (point-to-triangle, Open3D's BVH, CPU) is measured, so there is no sampling bias from point-to-point matching;
    the max is an estimate from below of the Hausdorff distance.

    Args:
        mesh: mesh A (e.g. the reconstruction).
        reference: mesh B (e.g. ground truth or the un-simplified mesh).
        samples: points per mesh.
        seed: sampling seed.

    Returns:
        :class:`MeshDistance`.
    """
    if mesh.num_faces == 0 or reference.num_faces == 0:
        raise DarsError(f"mesh_distance needs two non-empty meshes (got {mesh.num_faces} and {reference.num_faces} faces)")
    d_ab = _distance_to(reference, sample_surface(mesh, samples, seed))
    d_ba = _distance_to(mesh, sample_surface(reference, samples, seed + 1))
    diag = reference.diagonal
    mean = 0.5 * (d_ab.mean() + d_ba.mean())
    mx = max(d_ab.max(), d_ba.max())
    return MeshDistance(float(mean), float(mx), float(d_ab.mean()), float(d_ba.mean()), float(d_ab.max()),
                        float(d_ba.max()), diag, float(mean / diag), float(mx / diag), samples)
