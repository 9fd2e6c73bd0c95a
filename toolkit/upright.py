"""World up from posed cameras (and sparse points), the rotation that makes a scene upright, and pose comparison.

SPEC: world up is +z and cameras are OpenGL camera-to-world (x right, y up, looking down -z), so a photo's "up"
in the world is column 1 of its ``c2w``. An SfM frame (COLMAP) has an arbitrary orientation; everything after
it (SH light frame, lat-long background, room prior, glTF axes) assumes +z up. :func:`estimate_world_up` finds the
up direction in three steps:

1. **camera consensus**: the camera up vectors (``c2w[:, :3, 1]``) are averaged robustly: the seed is the up
   vector with the most others within 30 deg (so a minority of photos held sideways, or stored without applying
   their EXIF rotation, cannot drag it), then the mean of those within 45 deg of it, iterated;
2. **right-axis refinement**: people hold cameras level (little roll) but tilt them freely (pitch), and pitch
   turns the up vector about the camera's x axis. The x axes of the consensus cameras are therefore nearly
   horizontal whatever the pitch: the direction most perpendicular to all of them (the smallest eigenvector of
   ``sum x x^T``) is the up direction, unbiased by a capture that looks down at the floor. When the x axes do not
   span the horizontal plane (a forward-facing capture: all cameras face the same way), the consensus up is only
   made perpendicular to the mean x axis;
3. **dominant plane** (where sparse points are given): RANSAC over planes whose normal lies within
   ``max_plane_angle_deg`` of the camera up (so walls and paintings, perpendicular to it, never win); the
   largest such plane (floor, table top, ceiling — all horizontal) with enough support, refined by least
   squares, gives the final up, oriented to agree with the cameras — **if** it agrees with the cameras within
   what their own spread allows: ``max(plane_agree_deg, plane_agree_roll_factor * roll)``, where ``roll`` is the
   RMS angle of the consensus cameras' x axes out of the horizontal plane of the camera up. Level cameras (roll
   near 0) fix up to a fraction of a degree, and a "plane" several degrees off is not horizontal: on the
   procedural validation galleries (few hundred sparse points), RANSAC's largest slab was a band of wall and frame
   points at similar heights, 3.4 and 4.2 deg off the (exact) camera up, and the room box fitted in that frame
   put walls up to 15 cm and the floor and ceiling up to 18 cm from the truth (README, "Up from level cameras").
   Where the x axes do not span the horizontal plane (a forward-facing capture) the cameras cannot fix the pitch,
   and the plane is used whenever it is found.
   A rejected plane is still reported (``plane_normal``, ``plane_angle_deg``; ``source`` stays ``cameras``).

:func:`upright_rotation` returns the smallest rotation taking that up to +z (the heading about z is left as it
was). Nothing here changes scale or centre. :func:`plan_upright_rotation` is what :func:`toolkit.scene.load_scene` does
with a posed input of arbitrary orientation: estimate the tilt and rotate only when it exceeds
:data:`LOAD_TILT_TOLERANCE_DEG`.

:func:`align_similarity` (Umeyama) and :func:`compare_poses` measure a pose estimate against reference poses
given in another frame (rotation errors in degrees, centre errors as a fraction of the camera spread).

All functions take NumPy arrays (or anything ``np.asarray`` accepts, e.g. CPU tensors) and return float64 NumPy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ._checks import ConfigError, ShapeError, check_shape

__all__ = [
    "UprightConfig",
    "WorldUp",
    "estimate_world_up",
    "upright_rotation",
    "rotation_between",
    "LOAD_TILT_TOLERANCE_DEG",
    "PLANE_MAX_REPROJ_PX",
    "plan_upright_rotation",
    "align_similarity",
    "compare_poses",
]


@dataclass(frozen=True)
class UprightConfig:
    """How world up is estimated (see the module docstring)."""

    seed_angle_deg: float = 30.0
    """Camera ups within this angle of each other vote for the consensus seed."""
    inlier_angle_deg: float = 45.0
    """Camera ups further than this from the consensus are outliers (sideways photos)."""
    use_right_axes: bool = True
    """Refine the camera up with the level-horizon constraint on the cameras' x axes."""
    use_plane: bool = True
    """Use the dominant near-horizontal plane of the sparse points when there is one."""
    max_plane_angle_deg: float = 25.0
    """Only planes whose normal is within this angle of the camera up are candidates (walls never are)."""
    plane_threshold: float = 0.01
    """RANSAC inlier distance, as a fraction of the points' median distance to their median."""
    min_plane_fraction: float = 0.1
    """A plane needs at least this fraction of the points (and ``min_plane_points``) to be used."""
    min_plane_points: int = 30
    """A plane needs at least this many points."""
    ransac_iterations: int = 1000
    """RANSAC trials (three points each)."""
    max_points: int = 50_000
    """Points are subsampled to this many (deterministically) before RANSAC."""
    seed: int = 0
    """Random seed of the subsampling and of RANSAC."""
    plane_agree_deg: float = 1.5
    """A plane further than ``max(plane_agree_deg, plane_agree_roll_factor * camera roll)`` from the camera up is not
    used (level cameras already fix up; see the module docstring)."""
    plane_agree_roll_factor: float = 2.0
    """See ``plane_agree_deg``."""


@dataclass(frozen=True)
class WorldUp:
    """The estimated world up direction and how it was found.

    Attributes:
        up: float [3] unit vector, world up in the input frame.
        source: ``"cameras"`` or ``"cameras+plane"``.
        camera_up: float [3] the up from the cameras alone (after the right-axis refinement).
        camera_inliers: number of cameras whose up agreed with the consensus.
        plane_normal: float [3] or None, the dominant plane's normal (oriented like ``camera_up``).
        plane_fraction: fraction of the points on that plane (0 when none was found).
        plane_angle_deg: angle between ``plane_normal`` and ``camera_up`` (degrees; nan when no plane).
        camera_roll_deg: RMS angle of the consensus cameras' x axes out of the camera up's horizontal plane (nan for
            a forward-facing capture, whose x axes cannot fix the pitch).
        plane_tolerance_deg: the largest ``plane_angle_deg`` at which the plane is used (inf: forward-facing).
    """

    up: np.ndarray
    source: Literal["cameras", "cameras+plane"]
    camera_up: np.ndarray
    camera_inliers: int
    plane_normal: np.ndarray | None = None
    plane_fraction: float = 0.0
    plane_angle_deg: float = float("nan")
    camera_roll_deg: float = float("nan")
    plane_tolerance_deg: float = float("nan")


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(_unit(a), _unit(b)), -1.0, 1.0))))


def _camera_up(c2w: np.ndarray, cfg: UprightConfig) -> tuple[np.ndarray, int, float]:
    """(up, consensus cameras, roll RMS in degrees — nan when the x axes cannot fix the pitch)."""
    ups = c2w[:, :3, 1] / np.linalg.norm(c2w[:, :3, 1], axis=1, keepdims=True).clip(1e-12)
    rights = c2w[:, :3, 0] / np.linalg.norm(c2w[:, :3, 0], axis=1, keepdims=True).clip(1e-12)
    n = len(ups)
    sub = ups if n <= 500 else ups[np.linspace(0, n - 1, 500).round().astype(int)]
    votes = (sub @ ups.T > np.cos(np.radians(cfg.seed_angle_deg))).sum(1)
    up = sub[int(np.argmax(votes))]
    cos_in = np.cos(np.radians(cfg.inlier_angle_deg))
    for _ in range(5):
        inl = ups @ up > cos_in
        up = _unit(ups[inl].mean(0))
    inl = ups @ up > cos_in
    roll = float("nan")
    if cfg.use_right_axes and inl.sum() >= 2:
        x = rights[inl]
        evals, evecs = np.linalg.eigh(x.T @ x / len(x))  # ascending
        if evals[1] > 0.02:  # the x axes span a plane: up is its normal
            v = evecs[:, 0] * np.sign(evecs[:, 0] @ up)
            if _angle_deg(v, up) < cfg.inlier_angle_deg:
                up = v
                roll = float(np.degrees(np.sqrt(np.mean(np.arcsin(np.clip(x @ up, -1, 1)) ** 2))))
        else:  # all cameras face one way: only remove the roll component along the common x axis
            e = evecs[:, 2]
            up = _unit(up - (up @ e) * e)
    return up, int(inl.sum()), roll


def _fit_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    centre = points.mean(0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    return vt[2], centre


def _dominant_plane(points: np.ndarray, camera_up: np.ndarray, cfg: UprightConfig):
    """Largest near-horizontal plane: (normal oriented like camera_up, inlier fraction) or (None, 0)."""
    pts = points[np.isfinite(points).all(1)]
    if len(pts) < max(cfg.min_plane_points, 3):
        return None, 0.0
    rng = np.random.default_rng(cfg.seed)
    if len(pts) > cfg.max_points:
        pts = pts[rng.choice(len(pts), cfg.max_points, replace=False)]
    med = np.median(pts, 0)
    scale = float(np.median(np.linalg.norm(pts - med, axis=1)))
    if not np.isfinite(scale) or scale <= 0:
        return None, 0.0
    thr = cfg.plane_threshold * scale
    cos_max = np.cos(np.radians(cfg.max_plane_angle_deg))
    idx = rng.integers(0, len(pts), size=(cfg.ransac_iterations, 3))
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-12 * scale * scale
    normals[ok] /= norm[ok, None]
    ok &= np.abs(normals @ camera_up) > cos_max
    best, best_count = None, 0
    for k in np.flatnonzero(ok):
        d = np.abs((pts - a[k]) @ normals[k])
        count = int((d < thr).sum())
        if count > best_count:
            best, best_count = k, count
    if best is None:
        return None, 0.0
    inl = np.abs((pts - a[best]) @ normals[best]) < thr
    normal = normals[best]
    for _ in range(3):  # least-squares refinement on the inliers
        normal, centre = _fit_plane(pts[inl])
        inl = np.abs((pts - centre) @ normal) < thr
        if inl.sum() < 3:
            return None, 0.0
    frac = float(inl.mean())
    if inl.sum() < cfg.min_plane_points or frac < cfg.min_plane_fraction:
        return None, frac
    normal = normal * np.sign(normal @ camera_up)
    if normal @ camera_up < cos_max:
        return None, frac
    return normal, frac


def estimate_world_up(c2w, points=None, cfg: UprightConfig = UprightConfig()) -> WorldUp:
    """Estimate the world up direction of a posed scene.

    Args:
        c2w: float [N, 4, 4] (or [N, 3, 4]) OpenGL camera-to-world matrices (column 1 = camera up), N >= 1.
        points: optional float [P, 3] sparse scene points in the same frame (e.g. SfM points).
        cfg: see :class:`UprightConfig`.

    Returns:
        :class:`WorldUp` with the unit up vector and its provenance.

    Raises:
        ShapeError: on badly shaped input. ConfigError: on non-finite poses.

    Example:
        >>> c2w = np.tile(np.eye(4), (3, 1, 1))  # cameras looking down -z with +y up
        >>> estimate_world_up(c2w).up.round(3).tolist()
        [0.0, 1.0, 0.0]
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)) or len(c2w) == 0:
        raise ShapeError(f"c2w: expected shape [N, 4, 4] or [N, 3, 4] with N >= 1, got {list(c2w.shape)}")
    if not np.isfinite(c2w).all():
        raise ConfigError("c2w contains NaN or inf")
    camera_up, n_in, roll = _camera_up(c2w, cfg)
    tol = float("inf") if not np.isfinite(roll) else max(cfg.plane_agree_deg, cfg.plane_agree_roll_factor * roll)
    cams = dict(camera_up=camera_up, camera_inliers=n_in, camera_roll_deg=roll, plane_tolerance_deg=tol)
    if points is None or not cfg.use_plane:
        return WorldUp(up=camera_up, source="cameras", **cams)
    points = np.asarray(points, dtype=np.float64)
    check_shape(points, "P 3", name="points")
    normal, frac = _dominant_plane(points, camera_up, cfg)
    if normal is None:
        return WorldUp(up=camera_up, source="cameras", plane_fraction=frac, **cams)
    angle = _angle_deg(normal, camera_up)
    plane = dict(plane_normal=normal, plane_fraction=frac, plane_angle_deg=angle)
    if angle > tol:  # not horizontal: level cameras disagree (see the module docstring)
        return WorldUp(up=camera_up, source="cameras", **plane, **cams)
    return WorldUp(up=normal, source="cameras+plane", **plane, **cams)


def rotation_between(a, b) -> np.ndarray:
    """The smallest rotation R (float [3, 3]) with ``R @ unit(a) = unit(b)`` (a half turn about a perpendicular axis
    when they are opposite)."""
    a, b = _unit(np.asarray(a, np.float64)), _unit(np.asarray(b, np.float64))
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:
        axis = _unit(np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0]))
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def upright_rotation(c2w, points=None, cfg: UprightConfig = UprightConfig()) -> np.ndarray:
    """Rotation (float [3, 3]) that takes the scene's estimated world up to +z (SPEC world up).

    Apply it to world points as ``R @ x`` and to cameras as ``c2w' = [[R, 0], [0, 1]] @ c2w``. The heading about z
    is left unchanged (smallest rotation); no scale or centre change.

    Args:
        c2w: float [N, 4, 4] OpenGL camera-to-world matrices.
        points: optional float [P, 3] sparse points in the same frame.
        cfg: see :class:`UprightConfig`.
    """
    return rotation_between(estimate_world_up(c2w, points, cfg).up, [0.0, 0.0, 1.0])


PLANE_MAX_REPROJ_PX = 4.0
"""Sparse points with a larger reprojection error (pixels) are left out of the plane fit of :func:`estimate_world_up`
(badly triangulated points lie off the floor): ``dars poses`` and the COLMAP loader drop them alike."""

LOAD_TILT_TOLERANCE_DEG = 2.0
"""Smallest estimated tilt (degrees) at which :func:`toolkit.scene.load_scene` rotates a scene upright.

Below the estimator's own accuracy a rotation would only perturb an input that is already upright (a Blender or
nerfstudio/instant-ngp transforms file is +z up by construction). Measured tilts of inputs known to be upright:
synthetic NeRF Lego and our rendered galleries give exactly 0 deg; the real fox capture (instant-ngp, oriented by its
mean camera up) gives 5.8 deg, so it is rotated. An SfM frame (COLMAP) is typically tens of degrees off or upside down
(y down)."""


def plan_upright_rotation(c2w, points=None, tolerance_deg: float = LOAD_TILT_TOLERANCE_DEG,
                          cfg: UprightConfig = UprightConfig()) -> dict:
    """Decide whether a posed scene needs rotating upright, and by what (the record :func:`load_scene` keeps).

    Args:
        c2w: float [N, 4, 4] OpenGL camera-to-world matrices (all frames of the scene, every split).
        points: optional float [P, 3] sparse points in the same frame.
        tolerance_deg: rotate only when the estimated tilt (angle between the estimated up and +z) exceeds this.
        cfg: see :class:`UprightConfig`.

    Returns:
        A JSON-ready dict: ``rotation`` (float [3, 3] as nested lists: the rotation applied, ``x_new = rotation @ x``;
        the identity when not applied), ``tilt_deg`` (estimated tilt of the input, degrees), ``source``
        (``"cameras"`` or ``"cameras+plane"``), ``applied`` (tilt > tolerance), ``up`` (the estimated up in the input
        frame), ``camera_inliers`` and ``tolerance_deg``.

    Raises:
        ShapeError, ConfigError: as :func:`estimate_world_up`.
    """
    up = estimate_world_up(c2w, points, cfg)
    tilt = _angle_deg(up.up, np.array([0.0, 0.0, 1.0]))
    applied = bool(tilt > tolerance_deg)
    rot = rotation_between(up.up, [0.0, 0.0, 1.0]) if applied else np.eye(3)
    return {"rotation": rot.tolist(), "tilt_deg": round(tilt, 4), "source": up.source, "applied": applied,
            "up": up.up.tolist(), "camera_inliers": up.camera_inliers, "tolerance_deg": float(tolerance_deg)}


def align_similarity(src, dst) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s * R @ src + t`` (Umeyama 1991).

    Args:
        src: float [N, 3] points (e.g. estimated camera centres), N >= 3, not collinear.
        dst: float [N, 3] corresponding points (e.g. reference camera centres).

    Returns:
        ``(s, R, t)``: scale, float [3, 3] rotation (det +1), float [3] translation.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    check_shape(src, "N 3", name="src")
    if dst.shape != src.shape or len(src) < 3:
        raise ShapeError(f"src and dst must both be [N, 3] with N >= 3, got {list(src.shape)} and {list(dst.shape)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    R = u @ np.diag(sign) @ vt
    var_s = float((xs ** 2).sum() / len(src))
    s = float((d * sign).sum() / max(var_s, 1e-300))
    return s, R, mu_d - s * R @ mu_s


def compare_poses(c2w_est, c2w_ref) -> dict:
    """Errors of estimated camera poses against reference poses in another (similarity-related) frame.

    The estimate is aligned to the reference by :func:`align_similarity` on the camera centres; then per camera the
    rotation error is the angle of ``R_aligned^T R_ref`` and the centre error is the distance between the aligned
    and reference centres divided by the camera spread (RMS distance of the reference centres to their mean).

    Args:
        c2w_est: float [N, 4, 4] estimated camera-to-world (OpenGL), N >= 3.
        c2w_ref: float [N, 4, 4] reference camera-to-world (same convention, same cameras in the same order).

    Returns:
        dict with ``rotation_error_deg`` (median, mean, max, per_camera), ``centre_error_rel`` (median, mean, max,
        per_camera), ``scale``, ``rotation`` (float [3, 3] list) and ``translation`` of the alignment, and
        ``relative_rotation_error_deg``: the rotation errors once the common rotation offset left by the centre
        alignment (``rotation_offset_deg``, the chordal mean of the per-camera errors) is removed too — the errors
        of the cameras relative to each other.
    """
    est, ref = np.asarray(c2w_est, np.float64), np.asarray(c2w_ref, np.float64)
    if est.shape != ref.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ShapeError(f"c2w_est and c2w_ref must both be [N, 4, 4], got {list(est.shape)} and {list(ref.shape)}")
    s, R, t = align_similarity(est[:, :3, 3], ref[:, :3, 3])
    rot_al = R[None] @ est[:, :3, :3]
    rel = np.swapaxes(rot_al, 1, 2) @ ref[:, :3, :3]
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot_err = np.degrees(np.arccos(cos))
    u, _, vt = np.linalg.svd(rel.sum(0))
    offset = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    cos_rel = np.clip((np.trace(offset.T[None] @ rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    centres = s * est[:, :3, 3] @ R.T + t
    spread = float(np.sqrt(((ref[:, :3, 3] - ref[:, :3, 3].mean(0)) ** 2).sum(1).mean()))
    cen_err = np.linalg.norm(centres - ref[:, :3, 3], axis=1) / max(spread, 1e-300)

    def stats(x: np.ndarray) -> dict:
        return {"median": float(np.median(x)), "mean": float(x.mean()), "max": float(x.max()),
                "per_camera": [float(v) for v in x]}

    return {"rotation_error_deg": stats(rot_err), "centre_error_rel": stats(cen_err), "scale": s,
            "rotation": R.tolist(), "translation": t.tolist(), "camera_spread": spread,
            "relative_rotation_error_deg": stats(np.degrees(np.arccos(cos_rel))),
            "rotation_offset_deg": float(np.degrees(np.arccos(np.clip((np.trace(offset) - 1) / 2, -1, 1))))}
