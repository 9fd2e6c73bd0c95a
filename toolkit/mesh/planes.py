"""Flatten a mesh's walls and floor onto the room's planes (:func:`snap_to_planes`).

A room's textureless walls are where the field's geometry is least fixed by the photos: on validation gallery
1000002 the fused mesh's wall points scatter ±9-18 cm about the room box that :func:`toolkit.layout.fit_room_layout`
fits from the same photos, while that box's confident faces lie within 0.3-4.7 cm of the true walls (scoring only,
2026-12-03). Projecting the mesh's vertices that lie near a confident face onto that face's plane takes the bumps
out; :func:`toolkit.asset.build_mesh` lets only the vertices the field labels wall or floor move, so an exhibit
standing near a wall keeps its shape. No ground truth is read here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._checks import ConfigError, check_shape
from .types import Mesh, _face_areas, compute_vertex_normals

__all__ = ["PlaneSnapConfig", "snap_to_planes"]


@dataclass(frozen=True)
class PlaneSnapConfig:
    """Options of :func:`snap_to_planes`."""

    tolerance: float
    """Vertices within this distance of a plane (metres) may move onto it."""
    min_cos: float = 0.0
    """... and only where the vertex normal is within acos(min_cos) of the plane's normal (either side; 0: any
    normal). A vertex moves along the plane's normal, so a surface square to the plane (a pedestal's side on the
    floor) stays where it is whatever this is; above 0 a bump's steep flanks stay while its top goes, and the mesh
    folds there (3 % of the faces of validation gallery 1000002's GLB at 0.5)."""
    max_disagreement: float = 1 / 3
    """A plane is left alone where the area-weighted median signed distance of its candidate vertices exceeds this
    share of ``tolerance``: the mesh puts that wall elsewhere, and the mesh is trusted over the box."""

    def __post_init__(self) -> None:
        if not (self.tolerance > 0 and np.isfinite(self.tolerance)):
            raise ConfigError(f"PlaneSnapConfig.tolerance={self.tolerance!r} must be a positive number of metres")
        if not 0.0 <= self.min_cos < 1.0:
            raise ConfigError(f"PlaneSnapConfig.min_cos={self.min_cos!r} must be in [0, 1)")
        if not 0.0 < self.max_disagreement <= 1.0:
            raise ConfigError(f"PlaneSnapConfig.max_disagreement={self.max_disagreement!r} must be in (0, 1]")


def snap_to_planes(mesh: Mesh, normals: np.ndarray, offsets: np.ndarray, cfg: PlaneSnapConfig,
                   names: list[str] | None = None, movable: np.ndarray | None = None) -> tuple[Mesh, dict]:
    """Project the vertices near each plane ``n · x = c`` onto it, along its normal.

    A vertex moves onto the nearest plane it qualifies for: within ``cfg.tolerance``, with ``|n_vertex · n| ≥
    cfg.min_cos``, and the plane not left alone by ``cfg.max_disagreement``. Faces, colours and labels are kept;
    the normals are recomputed.

    Args:
        mesh: the mesh.
        normals: float [P, 3] unit plane normals (world).
        offsets: float [P] plane offsets ``c`` (metres).
        cfg: :class:`PlaneSnapConfig`.
        names: optional [P] plane names for the statistics.
        movable: optional bool [V]: only these vertices may move (and only they count for the median); None: all.

    Returns:
        (mesh, statistics): ``tolerance_m``, ``vertices_moved``, and per plane ``vertices`` (moved onto it),
        ``median_shift_m`` (the area-weighted median signed distance of its candidates, metres) and ``skipped``
        (why it was left alone, or None).
    """
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    c = np.asarray(offsets, np.float64).reshape(-1)
    check_shape(c, f"{len(n)}", "offsets")
    names = list(names) if names is not None else [f"plane {i}" for i in range(len(n))]
    if len(names) != len(n):
        raise ConfigError(f"snap_to_planes: {len(names)} names for {len(n)} planes")
    v = mesh.vertices.astype(np.float64)
    if movable is not None:
        movable = np.asarray(movable, bool)
        check_shape(movable, f"{len(v)}", "movable")
    per = {name: {"vertices": 0, "median_shift_m": None, "skipped": None} for name in names}
    target = np.full(len(v), -1)
    if len(n) and mesh.num_faces:
        vn = compute_vertex_normals(mesh.vertices, mesh.faces).astype(np.float64) if cfg.min_cos > 0 else None
        area = _vertex_areas(v, mesh.faces)
        d_all = v @ n.T - c  # [V, P] signed distances
        best = np.full(len(v), np.inf)
        for p in range(len(n)):
            d = d_all[:, p]
            ok = np.abs(d) < cfg.tolerance
            if movable is not None:
                ok &= movable
            if vn is not None:
                ok &= np.abs(vn @ n[p]) >= cfg.min_cos
            if not ok.any() or area[ok].sum() <= 0:
                per[names[p]]["skipped"] = "no vertex of the mesh lies near it"
                continue
            med = _weighted_median(d[ok], area[ok])
            per[names[p]]["median_shift_m"] = round(med, 4)
            if abs(med) > cfg.max_disagreement * cfg.tolerance:
                per[names[p]]["skipped"] = (f"the mesh's surface near it lies {med:+.3f} m off it on the median "
                                            f"(more than {cfg.max_disagreement:.2f} of the tolerance)")
                continue
            ok &= np.abs(d) < best
            best[ok] = np.abs(d[ok])
            target[ok] = p
        for p in range(len(n)):
            per[names[p]]["vertices"] = int((target == p).sum())
        sel = target >= 0
        v[sel] -= d_all[sel, target[sel]][:, None] * n[target[sel]]
    verts = v.astype(np.float32)
    out = Mesh(verts, mesh.faces, compute_vertex_normals(verts, mesh.faces) if mesh.normals is not None else None,
               mesh.colors, mesh.labels)
    return out, {"tolerance_m": round(float(cfg.tolerance), 4), "vertices_moved": int((target >= 0).sum()),
                 "planes": per}


def _vertex_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """float [V] a third of the area of the faces round each vertex."""
    return np.bincount(f.ravel(), np.repeat(_face_areas(v, f) / 3, 3), minlength=len(v))


def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cw, 0.5 * cw[-1])])
