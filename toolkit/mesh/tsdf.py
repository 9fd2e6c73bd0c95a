"""Depth maps rendered from the density (:func:`render_depth`) and their TSDF fusion (:func:`fuse_tsdf`, Open3D)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from .._checks import ConfigError, DarsError, ShapeError, check_range, check_shape
from ._field import _check_aabb, _density, _iter_progress, _progress, _to_numpy
from .types import DensityFn, Mesh, _as_mesh, compute_vertex_normals


@dataclass(frozen=True)
class DepthRenderConfig:
    """Depth maps from a density field (for TSDF fusion of a trained field).

    Attributes:
        samples: uniform samples per ray between the ray's AABB entry and exit.
        opacity: a pixel's depth is where the accumulated opacity first reaches this value (0.5: the median
            termination depth of an opaque ray).
        min_opacity: a ray that gathers less than ``opacity`` inside the box but at least this much gives the
            median of its own termination (where it has gathered half its opacity): a translucent wall still
            gives its depth. Rays that gather less get depth 0 (no measurement): they see through (windows, the
            sky). Equal to ``opacity`` (the default): only rays that reach ``opacity`` count.
        batch: rays per chunk (``batch × samples`` points per ``density_fn`` call).
        device: device the points are sent to.
        progress: show a progress bar (stderr).
    """

    samples: int = 256
    opacity: float = 0.5
    min_opacity: float = 0.5
    batch: int = 4096
    device: str = "cpu"
    progress: bool = True


def render_depth(density_fn: DensityFn, cameras, aabb: torch.Tensor | np.ndarray,
                 cfg: DepthRenderConfig = DepthRenderConfig()) -> np.ndarray:
    """Render depth maps of a density field by volume rendering (median termination depth).

    Args:
        density_fn: σ(points float [N, 3]) -> float [N], 1/metre.
        cameras: :class:`toolkit.scene.Cameras` (all must have the same image size).
        aabb: float [2, 3] box the rays are clipped to, metres.
        cfg: :class:`DepthRenderConfig`.

    Returns:
        float32 [K, H, W] depth along the camera axis, metres; 0 where the ray gathers less than
        ``min(cfg.opacity, cfg.min_opacity)``.
    """
    from ..cameras import generate_rays

    box = torch.as_tensor(_check_aabb(aabb), dtype=torch.float32)
    check_range(cfg.opacity, 1e-6, 1 - 1e-6, "DepthRenderConfig.opacity")
    check_range(cfg.min_opacity, 1e-6, 1 - 1e-6, "DepthRenderConfig.min_opacity")
    hs, ws = cameras.height.tolist(), cameras.width.tolist()
    if len(set(hs)) != 1 or len(set(ws)) != 1:
        raise DarsError(f"render_depth: cameras must share one image size, got heights {sorted(set(hs))} widths {sorted(set(ws))}")
    K, H, W = len(cameras), int(hs[0]), int(ws[0])
    out = np.zeros((K, H * W), dtype=np.float32)
    min_tau = -math.log1p(-cfg.min_opacity)  # optical depth of the least opacity that counts as a surface
    target_tau = -math.log1p(-cfg.opacity)
    bar = _progress(K * H * W, "depth", cfg.progress, unit="ray")
    try:
        cams = cameras.to("cpu")
        for k in range(K):
            rays = generate_rays(cams, [k], aabb=box)
            for s in range(0, len(rays), cfg.batch):
                r = rays[s:s + cfg.batch]
                hit = r.far > r.near
                t = torch.linspace(0, 1, cfg.samples + 1, dtype=torch.float32)
                mids = 0.5 * (t[1:] + t[:-1])
                span = (r.far - r.near).clamp_min(0)[:, None]
                ts = r.near[:, None] + mids[None] * span  # [n, S]
                pts = r.origins[:, None] + r.directions[:, None] * ts[..., None]
                sigma = _density(density_fn, pts.reshape(-1, 3).numpy(), cfg.device).reshape(ts.shape)
                tau = np.cumsum(np.maximum(sigma, 0) * (span.numpy() / cfg.samples), axis=1)  # optical depth
                # where the opacity reaches cfg.opacity, or half the ray's own total (1 - e^-τ_end) when it never does
                tau_end = tau[:, -1]
                target = np.where(tau_end >= target_tau, target_tau, -np.log1p(0.5 * np.expm1(-tau_end)))
                reached = tau >= target[:, None]
                any_hit = (tau_end >= min(min_tau, target_tau)) & hit.numpy()
                first = reached.argmax(1)
                # linear interpolation of the crossing inside the first sample that reaches the target
                i = np.arange(ts.shape[0])
                tau_prev = np.where(first > 0, tau[i, np.maximum(first - 1, 0)], 0.0)
                frac = np.clip((target - tau_prev) / np.maximum(tau[i, first] - tau_prev, 1e-12), 0, 1)
                step = span.numpy()[:, 0] / cfg.samples
                t_hit = r.near.numpy() + (first + frac) * step
                depth = np.where(any_hit, t_hit * r.z_scale.numpy(), 0.0)
                out[k, s:s + len(r)] = depth
                bar.update(len(r))
    finally:
        bar.close()
    return out.reshape(K, H, W)


@dataclass(frozen=True)
class TsdfConfig:
    """TSDF fusion (Open3D ``ScalableTSDFVolume``; always runs on the CPU).

    Attributes:
        voxel_size: TSDF voxel edge, metres.
        sdf_trunc: truncation distance, metres; None = 4 × ``voxel_size``.
        depth_max: depths beyond this (metres) are ignored.
        progress: show a progress bar (stderr).
    """

    voxel_size: float = 0.01
    sdf_trunc: float | None = None
    depth_max: float = 10.0
    progress: bool = True


def opengl_c2w_to_opencv_w2c(c2w: np.ndarray) -> np.ndarray:
    """Our OpenGL camera-to-world (x right, y up, looking down −z) → OpenCV world-to-camera (y down, z forward).

    Args:
        c2w: float [4, 4] (or [K, 4, 4]).

    Returns:
        float64 of the same shape: ``inv(c2w · diag(1, −1, −1, 1))``.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    return np.linalg.inv(c2w @ flip)


def fuse_tsdf(depths: torch.Tensor | np.ndarray, cameras, colours: torch.Tensor | np.ndarray | None = None,
              cfg: TsdfConfig = TsdfConfig()) -> Mesh:
    """Fuse depth maps into a mesh with a truncated signed distance volume (Open3D, CPU).

    Our cameras are OpenGL camera-to-world with pixel centres at +0.5; Open3D wants OpenCV world-to-camera
    (y down, z forward) and pixel centres at integers, so the extrinsic is ``inv(c2w · diag(1, −1, −1, 1))`` and
    the principal point is shifted by −0.5 px.

    Args:
        depths: float [K, H, W] depth along the camera axis, metres; 0 (or non-finite) = no measurement.
        cameras: :class:`toolkit.scene.Cameras` with K cameras of size H x W.
        colours: optional float [K, 3, H, W] in [0, 1] (stored at 8 bits per channel, in the space given).
        cfg: :class:`TsdfConfig`.

    Returns:
        :class:`Mesh` with outward vertex normals (and ``colors`` if ``colours`` were given).

    Raises:
        ShapeError: depth/colour/camera sizes disagree.
    """
    import open3d as o3d

    d = _to_numpy(depths, "depths").astype(np.float32)
    dims = check_shape(d, "K H W", "depths")
    if len(cameras) != dims["K"]:
        raise ShapeError(f"depths has {dims['K']} maps but cameras has {len(cameras)}")
    if not (cfg.voxel_size > 0):
        raise ConfigError(f"TsdfConfig.voxel_size={cfg.voxel_size!r} must be positive (metres)")
    col = None
    if colours is not None:
        col = _to_numpy(colours, "colours").astype(np.float32)
        check_shape(col, f"{dims['K']} 3 {dims['H']} {dims['W']}", "colours")
        col = np.clip(col.transpose(0, 2, 3, 1) * 255 + 0.5, 0, 255).astype(np.uint8)
    ctype = o3d.pipelines.integration.TSDFVolumeColorType
    volume = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=float(cfg.voxel_size), sdf_trunc=float(cfg.sdf_trunc or 4 * cfg.voxel_size),
        color_type=ctype.RGB8 if col is not None else ctype.NoColor)
    c2w = cameras.c2w.detach().cpu().double().numpy()
    for k in _iter_progress(range(dims["K"]), "TSDF fusion", cfg.progress):
        h, w = int(cameras.height[k]), int(cameras.width[k])
        if (h, w) != (dims["H"], dims["W"]):
            raise ShapeError(f"camera {k} is {w}x{h} px but depths are {dims['W']}x{dims['H']}")
        dk = np.where(np.isfinite(d[k]), d[k], 0.0).astype(np.float32)
        ck = col[k] if col is not None else np.zeros((h, w, 3), np.uint8)
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(ck)), o3d.geometry.Image(np.ascontiguousarray(dk)),
            depth_scale=1.0, depth_trunc=float(cfg.depth_max), convert_rgb_to_intensity=False)
        intr = o3d.camera.PinholeCameraIntrinsic(w, h, float(cameras.fx[k]), float(cameras.fy[k]),
                                                 float(cameras.cx[k]) - 0.5, float(cameras.cy[k]) - 0.5)
        volume.integrate(rgbd, intr, opengl_c2w_to_opencv_w2c(c2w[k]))
    tm = volume.extract_triangle_mesh()
    v = np.asarray(tm.vertices)
    f = np.asarray(tm.triangles)
    if f.shape[0] == 0:
        return _as_mesh(np.zeros((0, 3)), np.zeros((0, 3)))
    colors = np.asarray(tm.vertex_colors, dtype=np.float32) if col is not None and tm.has_vertex_colors() else None
    mesh = _as_mesh(v, f, colors=colors)
    return replace(mesh, normals=compute_vertex_normals(mesh.vertices, mesh.faces))
