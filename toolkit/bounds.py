"""Scene bounds from the data: sparse points triangulated from the posed photos, and the scene box they give.

No stage needs a hand-set box. Where a scene has no ``aabb`` (every real capture), the region the field resolves
finely — the *scene box*; everything beyond it is still modelled, in the contracted shell (:mod:`toolkit.space`)
— is fitted to where the photos show surfaces:

1. :func:`triangulate_sparse_points`: SIFT features of each training view are matched with its nearest other
   views (ratio test); every match is triangulated with the *known* poses (closest points of the two rays) and
   kept when both rays point at it, the rays meet at ≥ ``min_angle_deg`` and it reprojects within
   ``max_reproj_px`` in both views. Scenes that come with sparse points (COLMAP, ``dars poses``) use theirs.
2. :func:`scene_box_from_points`: robust per-axis quantiles of the points, padded; the box is made to hold the
   cameras' near surroundings where the photos see little (a textureless room still gets its walls).

Falls back to the camera-frustum estimate (the point closest to all optical axes) when too few points survive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ._checks import ConfigError

__all__ = ["SparsePointsConfig", "SparsePoints", "triangulate_sparse_points", "sparse_depth_targets",
           "camera_point_distance",
           "SceneBoxConfig", "SceneBox",
           "scene_box_from_points", "box_from_cameras"]


@dataclass(frozen=True)
class SparsePointsConfig:
    """Options of :func:`triangulate_sparse_points`."""

    max_views: int = 60
    """Views used (evenly spaced over the split); more only adds points of the same surfaces."""
    neighbours: int = 4
    """Each view is matched with this many nearest other views (camera distance + viewing direction)."""
    max_side: int = 640
    """Images are reduced to this longest side for feature detection (full-resolution SIFT adds nothing here)."""
    min_side: int = 1
    """Images whose longest side is shorter are enlarged (bicubic) to it for detection (1: never). SIFT finds few
    keypoints in a 128-pixel photo: with ``min_side=256``, 100 views and 8 neighbours, validation galleries
    1000000-1000002 and the bundled sample (128 px) gave 8-12x more points (9.6k-55k) and more accurate ones
    (median depth error 0.4-1.1 %, 2.4-7.5 % off by > 10 %, against 0.8-1.5 % and 6.8-12 % with the defaults).
    It is not the default because training on them did not pay (2026-11-27, 600 steps, sparse-depth weight 0.1,
    against the defaults, same seed): test PSNR -1.0 and -0.6 dB on 1000001 (seeds 0, 1) and -0.18 dB on 1000000
    (seed 0); median rendered-depth error (``dars eval``, ``details.geometry``) -0.01, -0.08 and -0.04 m; albedo
    MAE -0.06, -0.03 and +0.01. The reprojection test stays in detection pixels, so it is stricter in the photo's
    own pixels. Never above ``max_side``."""
    max_features: int = 1500
    """SIFT keypoints per view."""
    ratio: float = 0.8
    """Lowe's ratio test."""
    min_angle_deg: float = 2.0
    """Smallest angle between the two rays of a triangulated point (near-parallel rays give no depth)."""
    max_reproj_px: float = 1.5
    """Largest reprojection error (in the detection image's pixels) in either view."""

    def __post_init__(self):
        if self.max_views < 2 or self.neighbours < 1 or self.max_side < 32 or self.max_features < 16:
            raise ConfigError("SparsePointsConfig: need max_views >= 2, neighbours >= 1, max_side >= 32, "
                              "max_features >= 16")
        if self.min_side < 1:
            raise ConfigError(f"SparsePointsConfig: need min_side >= 1, got {self.min_side}")
        if not 0 < self.ratio < 1 or self.min_angle_deg <= 0 or self.max_reproj_px <= 0:
            raise ConfigError("SparsePointsConfig: need 0 < ratio < 1, min_angle_deg > 0, max_reproj_px > 0")


@dataclass(frozen=True)
class SparsePoints:
    """Triangulated points.

    Attributes:
        points: float64 [P, 3] world positions, metres.
        views: int64 [P, 2] the two views (split indices) each point was triangulated from.
        n_pairs: view pairs matched.
        source: ``"triangulated"`` or the file the points came from.
    """

    points: np.ndarray
    views: np.ndarray
    n_pairs: int
    source: str = "triangulated"

    def __len__(self) -> int:
        return int(self.points.shape[0])


def _grey_u8(image_chw: torch.Tensor, max_side: int, min_side: int = 1) -> tuple[np.ndarray, float]:
    """8-bit grey image for detection, its longest side brought into [min_side, max_side], and the scale applied."""
    import cv2

    img = image_chw.clamp(0, 1).mul(255).round().byte().permute(1, 2, 0).numpy()
    grey = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    h, w = grey.shape
    s = min(1.0, max_side / max(h, w))
    if max(h, w) < min_side:
        s = min_side / max(h, w)
    if s != 1.0:
        size = (max(1, round(w * s)), max(1, round(h * s)))
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA if s < 1.0 else cv2.INTER_CUBIC)
    return grey, s


def _pixel_rays(c2w: np.ndarray, K: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Unit world directions [N, 3] through pixel positions ``uv`` [N, 2] (pixel-centre-at-0.5 convention)."""
    d_cam = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], -(uv[:, 1] - K[1, 2]) / K[1, 1], -np.ones(len(uv))], -1)
    d = d_cam @ c2w[:3, :3].T
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _project(c2w: np.ndarray, K: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rel = (pts - c2w[:3, 3]) @ c2w[:3, :3]
    depth = -rel[:, 2]
    safe = np.where(np.abs(depth) < 1e-9, 1e-9, depth)
    u = K[0, 0] * rel[:, 0] / safe + K[0, 2]
    v = -K[1, 1] * rel[:, 1] / safe + K[1, 2]
    return np.stack([u, v], -1), depth


def triangulate_sparse_points(scene, cfg: SparsePointsConfig = SparsePointsConfig(), log=None) -> SparsePoints:
    """Sparse 3D points of a posed scene from matched SIFT features and the known camera poses.

    Args:
        scene: a :class:`toolkit.scene.Scene` (its images are decoded one at a time).
        cfg: options.
        log: optional callable for one progress line.

    Returns:
        :class:`SparsePoints` (possibly empty: a scene without texture gives none).

    Example:
        >>> pts = triangulate_sparse_points(load_scene("samples/gallery", "train"))
        >>> box = scene_box_from_points(pts.points, scene.cameras)
    """
    import cv2

    from .sampling import neighbour_views

    V = len(scene)
    views = np.unique(np.linspace(0, V - 1, min(V, cfg.max_views)).round().astype(int))
    cams = scene.cameras[views.tolist()]
    nb = neighbour_views(cams, min(cfg.neighbours, len(views) - 1)).numpy()
    sift = cv2.SIFT_create(nfeatures=cfg.max_features, contrastThreshold=0.01)
    feats = []
    for i in views:
        grey, s = _grey_u8(scene.load_image(int(i)), cfg.max_side, min(cfg.min_side, cfg.max_side))
        kps, desc = sift.detectAndCompute(grey, None)
        uv = (np.array([k.pt for k in kps], np.float64).reshape(-1, 2) + 0.5) / s  # full-resolution pixel coordinates
        keep = scene.valid_mask(int(i))
        if keep is not None and len(uv) and desc is not None:  # no feature on what the photo's mask leaves out
            px = np.floor(uv).astype(np.int64)
            px[:, 0] = px[:, 0].clip(0, keep.shape[1] - 1)
            px[:, 1] = px[:, 1].clip(0, keep.shape[0] - 1)
            ok = keep.numpy()[px[:, 1], px[:, 0]]
            uv, desc = uv[ok], desc[ok]
        feats.append((uv, desc, s))
    c2w = cams.c2w.double().numpy()
    Ks = cams.intrinsics().double().numpy()
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    pairs = sorted({(min(a, int(b)), max(a, int(b))) for a in range(len(views)) for b in nb[a]})
    all_pts, all_views = [], []
    cos_min = math.cos(math.radians(cfg.min_angle_deg))
    for a, b in pairs:
        (uva, da, sa), (uvb, db, sb) = feats[a], feats[b]
        if da is None or db is None or len(da) < 2 or len(db) < 2:
            continue
        m = [p[0] for p in matcher.knnMatch(da, db, k=2) if len(p) == 2 and p[0].distance < cfg.ratio * p[1].distance]
        if not m:
            continue
        ia = np.array([x.queryIdx for x in m])
        ib = np.array([x.trainIdx for x in m])
        pa, pb = uva[ia], uvb[ib]
        oa, ob = c2w[a, :3, 3], c2w[b, :3, 3]
        ra, rb = _pixel_rays(c2w[a], Ks[a], pa), _pixel_rays(c2w[b], Ks[b], pb)
        # closest points of the two rays o_a + s r_a and o_b + t r_b
        w0 = oa - ob
        bb = (ra * rb).sum(-1)
        d = ra @ w0
        e = rb @ w0
        den = 1.0 - bb * bb
        ok = den > 1e-9
        den = np.where(ok, den, 1.0)
        s_ = (bb * e - d) / den
        t_ = (e - bb * d) / den
        X = 0.5 * ((oa + s_[:, None] * ra) + (ob + t_[:, None] * rb))
        ok &= (s_ > 0) & (t_ > 0) & (bb < cos_min)
        for (ci, p, sc) in ((a, pa, sa), (b, pb, sb)):
            uv, depth = _project(c2w[ci], Ks[ci], X)
            ok &= (depth > 0) & (np.linalg.norm(uv - p, axis=-1) * sc < cfg.max_reproj_px)
        if ok.any():
            all_pts.append(X[ok])
            all_views.append(np.tile([[views[a], views[b]]], (int(ok.sum()), 1)))
    pts = np.concatenate(all_pts) if all_pts else np.zeros((0, 3))
    vv = np.concatenate(all_views) if all_views else np.zeros((0, 2), np.int64)
    if log is not None:
        log(f"[dars] sparse points: {len(pts)} triangulated from {len(pairs)} view pairs of {len(views)} views")
    return SparsePoints(points=pts, views=vv.astype(np.int64), n_pairs=len(pairs))


def sparse_depth_targets(scene, points: SparsePoints) -> dict[str, torch.Tensor]:
    """Pixels with a known depth: each sparse point projected into the two views it was triangulated from.

    Returns ``{"views", "rows", "cols"}`` (int64 [K]) and ``"depth"`` (float32 [K], metres along the camera axis, the
    convention of rendered depth); points that land outside their view or behind it are dropped (K may be 0).
    """
    cams = scene.cameras
    c2w = cams.c2w.double().numpy()
    Ks = cams.intrinsics().double().numpy()
    W = cams.width.numpy()
    H = cams.height.numpy()
    views, rows, cols, depths = [], [], [], []
    for j in (0, 1):
        for v in np.unique(points.views[:, j]) if len(points) else []:
            sel = points.views[:, j] == v
            uv, d = _project(c2w[v], Ks[v], points.points[sel])
            c, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            ok = (d > 0) & (c >= 0) & (r >= 0) & (c < W[v]) & (r < H[v])
            views.append(np.full(int(ok.sum()), v, np.int64))
            rows.append(r[ok])
            cols.append(c[ok])
            depths.append(d[ok])
    if not views:
        return {"views": torch.zeros(0, dtype=torch.int64), "rows": torch.zeros(0, dtype=torch.int64),
                "cols": torch.zeros(0, dtype=torch.int64), "depth": torch.zeros(0)}
    return {"views": torch.from_numpy(np.concatenate(views)), "rows": torch.from_numpy(np.concatenate(rows)),
            "cols": torch.from_numpy(np.concatenate(cols)),
            "depth": torch.from_numpy(np.concatenate(depths).astype(np.float32))}


def camera_point_distance(points: np.ndarray, origins: np.ndarray) -> float:
    """Median distance between the points [P, 3] and (up to 32 evenly spaced of) the camera centres [N, 3]: the
    scene's scale as the cameras see it."""
    return float(np.median(np.linalg.norm(points[:, None, :] - origins[None, ::max(1, len(origins) // 32)], axis=-1)))


def box_from_cameras(c2w: np.ndarray, fx: np.ndarray, width: np.ndarray) -> np.ndarray:
    """The camera-only estimate [2, 3]: the point closest (least squares) to all optical axes is the centre; the
    half-size is what the median camera sees at that distance, median(dist) · tan(half horizontal FOV)."""
    origins = c2w[:, :3, 3]
    axes = -c2w[:, :3, 2]
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for o, d in zip(origins, axes):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ o
    if np.linalg.cond(A) < 1e6:
        centre = np.linalg.solve(A, b)
    else:  # parallel axes (forward-facing capture): look 1 median spacing ahead of the mean camera
        centre = origins.mean(0) + axes.mean(0)
    dist = np.linalg.norm(origins - centre, axis=1)
    half = float(np.median(dist) * np.tan(np.median(np.arctan(0.5 * width / fx))))
    if not np.isfinite(half) or half <= 0:
        half = 1.0
    return np.stack([centre - half, centre + half])


@dataclass(frozen=True)
class SceneBoxConfig:
    """Options of :func:`scene_box_from_points`."""

    quantile: float = 0.02
    """Per-axis quantiles [q, 1 − q] of the points (stray matches and distant sky points fall outside)."""
    pad: float = 0.1
    """Padding on each side as a fraction of the box extent (surfaces just beyond the outermost points)."""
    min_points: int = 50
    """Fewer points than this: fall back to the camera-frustum estimate (:func:`box_from_cameras`)."""
    camera_margin: float = 0.25
    """The box also holds every camera's surroundings up to this fraction of the median camera–point distance
    (inside a room the space around the cameras must be fine too)."""

    def __post_init__(self):
        if not 0.0 <= self.quantile < 0.5 or self.pad < 0 or self.camera_margin < 0 or self.min_points < 1:
            raise ConfigError("SceneBoxConfig: need 0 <= quantile < 0.5, pad >= 0, camera_margin >= 0, min_points >= 1")


@dataclass(frozen=True)
class SceneBox:
    """The scene box and where it came from.

    Attributes:
        aabb: float64 [2, 3] (min, max) in metres.
        source: ``"sparse points (N)"``, ``"cameras"`` or ``"file"``.
    """

    aabb: np.ndarray
    source: str


def scene_box_from_points(points: np.ndarray, c2w: np.ndarray, fx: np.ndarray, width: np.ndarray,
                          cfg: SceneBoxConfig = SceneBoxConfig()) -> SceneBox:
    """Robust bounds [2, 3] of sparse points (padded), grown to hold the cameras' near surroundings.

    Args:
        points: float [P, 3] world points.
        c2w: float [V, 4, 4] camera-to-world poses (all splits).
        fx, width: float [V] focal lengths and image widths in pixels (for the fallback).
        cfg: options.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(-1)]
    if len(pts) < cfg.min_points:
        return SceneBox(box_from_cameras(c2w, fx, width), "cameras")
    lo = np.quantile(pts, cfg.quantile, axis=0)
    hi = np.quantile(pts, 1.0 - cfg.quantile, axis=0)
    ext = np.maximum(hi - lo, 1e-6)
    lo, hi = lo - cfg.pad * ext, hi + cfg.pad * ext
    origins = c2w[:, :3, 3]
    dist = camera_point_distance(pts, origins)
    inside = ((origins >= lo) & (origins <= hi)).all(-1)
    if inside.mean() > 0.5:  # cameras inside the scene (a room): their surroundings belong to it too
        m = cfg.camera_margin * dist
        lo = np.minimum(lo, origins.min(0) - m)
        hi = np.maximum(hi, origins.max(0) + m)
    return SceneBox(np.stack([lo, hi]), f"sparse points ({len(pts)})")
