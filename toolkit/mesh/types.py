"""The mesh record (:class:`Mesh`, numpy, CPU), vertex normals and the field-callable types."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
import torch

from .._checks import ShapeError, check_shape

__all__ = ["Mesh", "DensityFn", "MaterialFn", "compute_vertex_normals"]

DensityFn = Callable[[torch.Tensor], "torch.Tensor | np.ndarray"]
"""``density_fn(points float [N, 3]) -> float [N]``: σ in 1/metre at world points (a torch tensor in; a tensor or an
array out)."""
MaterialFn = Callable[[torch.Tensor, "torch.Tensor | None"], Mapping[str, "torch.Tensor | np.ndarray"]]
"""``material_fn(points [N, 3], normals [N, 3] | None) -> {"albedo", "roughness", "metallic", "normal",
"semantic"}`` (see :func:`toolkit.train.field_callables`)."""


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh (numpy, CPU).

    Attributes:
        vertices: float32 [V, 3] world positions, metres.
        faces: int64 [F, 3] vertex indices, counter-clockwise seen from outside.
        normals: float32 [V, 3] unit vertex normals (outward), or None.
        colors: float32 [V, 3] vertex colours in [0, 1] (linear albedo when they come from ``material_fn``), or None.
        labels: uint8 [V] semantic class ids (0-6, SPEC; 255 unlabelled), or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    labels: np.ndarray | None = None

    def __post_init__(self) -> None:
        kind = type(self).__name__  # Mesh, or a subclass (toolkit.bake.UVMesh) checking the same fields
        check_shape(self.vertices, "V 3", f"{kind}.vertices")
        check_shape(self.faces, "F 3", f"{kind}.faces")
        v = self.vertices.shape[0]
        for name in ("normals", "colors"):
            a = getattr(self, name)
            if a is not None and a.shape != (v, 3):
                raise ShapeError(f"{kind}.{name}: expected shape [{v}, 3], got {list(a.shape)}")
        if self.labels is not None and self.labels.shape != (v,):
            raise ShapeError(f"{kind}.labels: expected shape [{v}], got {list(self.labels.shape)}")

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def bounds(self) -> np.ndarray:
        """float64 [2, 3] min and max corner (zeros for an empty mesh)."""
        if self.num_vertices == 0:
            return np.zeros((2, 3))
        return np.stack([self.vertices.min(0), self.vertices.max(0)]).astype(np.float64)

    @property
    def diagonal(self) -> float:
        """Length of the bounding-box diagonal, metres."""
        b = self.bounds
        return float(np.linalg.norm(b[1] - b[0]))

    def area(self) -> float:
        """Total surface area, square metres."""
        return float(_face_areas(self.vertices, self.faces).sum())

    def submesh(self, face_mask: np.ndarray) -> "Mesh":
        """The faces where ``face_mask`` (bool [F]) is true, with unreferenced vertices dropped."""
        faces = self.faces[np.asarray(face_mask, dtype=bool)]
        used = np.unique(faces)
        remap = np.full(self.num_vertices, -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        pick = lambda a: None if a is None else a[used]  # noqa: E731
        return Mesh(self.vertices[used], remap[faces], pick(self.normals), pick(self.colors), pick(self.labels))


def _as_mesh(vertices, faces, **kw) -> Mesh:
    return Mesh(np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int64), **kw)


def _face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    v = vertices.astype(np.float64)
    return 0.5 * np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1)


def compute_vertex_normals(vertices: np.ndarray, faces: np.ndarray, chunk: int = 1 << 16) -> np.ndarray:
    """Area-weighted vertex normals (faces processed in chunks, so temporaries stay small for big meshes).

    Args:
        vertices: float [V, 3].
        faces: int [F, 3], counter-clockwise.
        chunk: faces per chunk.

    Returns:
        float32 [V, 3] unit normals (vertices on no face, or only on degenerate faces, get (0, 0, 1)).
    """
    v = np.asarray(vertices)
    f = np.asarray(faces)
    n = np.zeros((v.shape[0], 3), dtype=np.float64)
    for s in range(0, f.shape[0], chunk):
        fc = f[s:s + chunk]
        p0 = v[fc[:, 0]].astype(np.float64)
        fn = np.cross(v[fc[:, 1]] - p0, v[fc[:, 2]] - p0)  # length = 2·area: area weighting
        for k in range(3):
            for c in range(3):
                n[:, c] += np.bincount(fc[:, k], weights=fn[:, c], minlength=v.shape[0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    out = np.where(length > 1e-30, n / np.maximum(length, 1e-30), np.array([0.0, 0.0, 1.0]))
    return out.astype(np.float32)
