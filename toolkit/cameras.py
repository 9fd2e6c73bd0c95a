"""Cameras and rays: the batched torch camera type, pixel → world rays, projection, box intersection, orbits.

Conventions (SPEC): camera-to-world 4x4 in OpenGL convention (x right, y up, camera looks down −z); world up +z.
Pixel ``(u, v)`` = (column, row) has its centre at ``(u + 0.5, v + 0.5)`` in the pixel coordinates that ``cx, cy``
use, so the camera-space ray through it is ``((u + 0.5 − cx) / fx, −(v + 0.5 − cy) / fy, −1)``.

:class:`Cameras` is the batch that scenes, training and rendering use; one numpy camera for inference and the viewers
is :class:`toolkit.pinhole.PinholeCamera` (:meth:`~toolkit.pinhole.PinholeCamera.from_cameras`,
:func:`cameras_from_pinholes`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ._checks import check_shape
from .pinhole import PinholeCamera, look_at

__all__ = ["Cameras", "RayBundle", "generate_rays", "project_points", "intersect_aabb", "orbit_cameras",
           "cameras_from_pinholes"]


@dataclass(frozen=True)
class Cameras:
    """A batch of pinhole cameras (after any undistortion and downscaling).

    Attributes:
        c2w: float [N, 4, 4] camera-to-world, OpenGL convention, metres.
        fx, fy: float [N] focal lengths in pixels.
        cx, cy: float [N] principal point in pixels (pixel centres at +0.5).
        width, height: int [N] image size in pixels.
    """

    c2w: torch.Tensor
    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    def __getitem__(self, idx) -> "Cameras":
        if isinstance(idx, int):
            idx = [idx]
        return Cameras(*(getattr(self, f)[idx] for f in ("c2w", "fx", "fy", "cx", "cy", "width", "height")))

    def to(self, device: torch.device | str) -> "Cameras":
        return Cameras(*(getattr(self, f).to(device) for f in ("c2w", "fx", "fy", "cx", "cy", "width", "height")))

    @property
    def device(self) -> torch.device:
        return self.c2w.device

    @property
    def origins(self) -> torch.Tensor:
        """float [N, 3] camera centres in world space."""
        return self.c2w[:, :3, 3]

    def intrinsics(self) -> torch.Tensor:
        """float [N, 3, 3] intrinsic matrices K (pixel-centre convention of the module docstring)."""
        K = torch.zeros(len(self), 3, 3, dtype=self.fx.dtype, device=self.fx.device)
        K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = self.fx, self.fy, self.cx, self.cy, 1.0
        return K

    def resized(self, width: int, height: int) -> "Cameras":
        """The same cameras seeing the same frustums on one ``width`` x ``height`` pixel grid (every camera, whatever
        its own size): focal lengths and principal points scale by ``width / w`` and ``height / h`` per axis (pixel
        centres stay at +0.5), so a camera of another aspect gets non-square pixels, not a cropped view. The batch
        form of :meth:`toolkit.pinhole.PinholeCamera.resized`."""
        if width < 1 or height < 1:
            raise ValueError(f"Cameras.resized: size {width}x{height} must be at least 1x1 px")
        sx = width / self.width.to(self.fx.dtype)
        sy = height / self.height.to(self.fy.dtype)
        size = lambda n: torch.full_like(self.width, n)  # noqa: E731
        return Cameras(self.c2w, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, size(width), size(height))



# ====================================================================== rays
@dataclass(frozen=True)
class RayBundle:
    """A batch of camera rays.

    Attributes:
        origins: float [N, 3] world-space ray origins, metres.
        directions: float [N, 3] unit world-space directions.
        camera_indices: int64 [N] camera index within the :class:`Cameras` the rays came from.
        pixels: int64 [N, 2] (u, v) = (column, row) of each ray's pixel.
        near, far: float [N] ray-parameter bounds (metres along ``directions``); ``far <= near`` means the ray
            misses the scene box.
        z_scale: float [N] cosine between the ray and the camera's optical axis (depth = t * z_scale).
    """

    origins: torch.Tensor
    directions: torch.Tensor
    camera_indices: torch.Tensor
    pixels: torch.Tensor
    near: torch.Tensor
    far: torch.Tensor
    z_scale: torch.Tensor

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def __getitem__(self, idx) -> "RayBundle":
        return RayBundle(*(getattr(self, f)[idx] for f in
                           ("origins", "directions", "camera_indices", "pixels", "near", "far", "z_scale")))

    def to(self, device) -> "RayBundle":
        return RayBundle(*(getattr(self, f).to(device) for f in
                           ("origins", "directions", "camera_indices", "pixels", "near", "far", "z_scale")))


def intersect_aabb(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor,
                   near_min: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test of rays against an axis-aligned box.

    Args:
        origins: float [N, 3] ray origins.
        directions: float [N, 3] ray directions (need not be unit; t is in their units).
        aabb: float [2, 3] box min and max.
        near_min: lower clamp for the entry distance (rays starting inside the box start here).

    Returns:
        (near, far) float [N] each; ``far <= near`` where the ray misses the box.
    """
    aabb = aabb.to(origins)
    inv = 1.0 / torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    near = torch.minimum(t0, t1).amax(-1).clamp_min(near_min)
    far = torch.maximum(t0, t1).amin(-1)
    return near, far


def generate_rays(
    cameras: Cameras,
    camera_indices: torch.Tensor | Sequence[int] | None = None,
    pixels: torch.Tensor | None = None,
    aabb=None,
    near: float | None = None,
    far: float | None = None,
    near_min: float = 0.05,
) -> RayBundle:
    """Pixel -> world ray, for all pixels of some cameras or for a sampled subset.

    Either give ``pixels`` (int [N, 2] (u, v)) together with ``camera_indices`` (int [N]), or give only
    ``camera_indices`` (a list of cameras; every pixel of each, row-major) or nothing (every pixel of every
    camera). Rays are allocated on the cameras' device.

    Ray bounds: the intersection with ``aabb`` (entry clamped to ``near_min``) — a float [2, 3] box, or a
    :class:`toolkit.space.SceneSpace` (contracted: out to its far radius) —, further limited to ``[near, far]``
    when those are given (the file's); without a box ``[near, far]`` or ``[near_min, 1e3]``.

    Example:
        >>> rays = generate_rays(scene.cameras, [0], aabb=scene.aabb)  # all pixels of camera 0
    """
    device = cameras.device
    if pixels is None:
        cams = range(len(cameras)) if camera_indices is None else [int(c) for c in camera_indices]
        idx_list, pix_list = [], []
        for c in cams:
            h, w = int(cameras.height[c]), int(cameras.width[c])
            v, u = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
            pix_list.append(torch.stack([u.reshape(-1), v.reshape(-1)], -1))
            idx_list.append(torch.full((h * w,), c, dtype=torch.long, device=device))
        pixels = torch.cat(pix_list) if pix_list else torch.zeros(0, 2, dtype=torch.long, device=device)
        cam_idx = torch.cat(idx_list) if idx_list else torch.zeros(0, dtype=torch.long, device=device)
    else:
        check_shape(pixels, "N 2", "pixels")
        if camera_indices is None:
            raise ValueError("generate_rays: pixels given without camera_indices")
        cam_idx = torch.as_tensor(camera_indices, dtype=torch.long, device=device).expand(pixels.shape[0])
        pixels = pixels.to(device)
    c2w = cameras.c2w[cam_idx]
    fx, fy, cx, cy = (getattr(cameras, k)[cam_idx] for k in ("fx", "fy", "cx", "cy"))
    pu = pixels[:, 0].to(c2w.dtype) + 0.5
    pv = pixels[:, 1].to(c2w.dtype) + 0.5
    d_cam = torch.stack([(pu - cx) / fx, -(pv - cy) / fy, -torch.ones_like(pu)], -1)
    d_world = (c2w[:, :3, :3] @ d_cam.unsqueeze(-1)).squeeze(-1)
    norm = d_world.norm(dim=-1, keepdim=True)
    directions = d_world / norm
    z_scale = 1.0 / norm.squeeze(-1)
    origins = c2w[:, :3, 3].expand_as(directions).contiguous()
    if aabb is not None and hasattr(aabb, "ray_bounds"):  # a SceneSpace
        n, f = aabb.ray_bounds(origins, directions, near_min)
        if near is not None and far is not None:
            n, f = torch.maximum(n, torch.full_like(n, float(near))), torch.minimum(f, torch.full_like(f, float(far)))
    elif near is not None and far is not None:
        n = torch.full_like(pu, float(near))
        f = torch.full_like(pu, float(far))
        if aabb is not None:  # the file's bounds, clipped to the scene box (nothing is modelled outside it)
            bn, bf = intersect_aabb(origins, directions, aabb, near_min)
            n, f = torch.maximum(n, bn), torch.minimum(f, bf)
    elif aabb is not None:
        n, f = intersect_aabb(origins, directions, aabb, near_min)
    else:
        n, f = torch.full_like(pu, near_min), torch.full_like(pu, 1e3)
    return RayBundle(origins, directions, cam_idx, pixels.long(), n, f, z_scale)


def project_points(cameras: Cameras, index: int, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Project world points into camera ``index``.

    Args:
        cameras: the cameras.
        index: which camera.
        points: float [N, 3] world points, metres.

    Returns:
        (uv, depth): float [N, 2] continuous pixel coordinates in the convention of the module docstring
        (pixel (u, v)'s centre is at (u + 0.5, v + 0.5); ``floor(uv)`` is the pixel index), and float [N]
        depth along the optical axis (positive in front of the camera).
    """
    check_shape(points, "N 3", "points")
    c2w = cameras.c2w[index].to(points)
    rel = points - c2w[:3, 3]
    p_cam = rel @ c2w[:3, :3]  # R^T (p - o)
    depth = -p_cam[:, 2]
    safe = torch.where(depth.abs() < 1e-9, torch.full_like(depth, 1e-9), depth)
    u = cameras.fx[index].to(points) * p_cam[:, 0] / safe + cameras.cx[index].to(points)
    v = -cameras.fy[index].to(points) * p_cam[:, 1] / safe + cameras.cy[index].to(points)
    return torch.stack([u, v], -1), depth


# ====================================================================== camera paths and conversions
def orbit_cameras(cameras: Cameras, aabb: torch.Tensor, n: int) -> Cameras:
    """``n`` cameras on a circle around the box centre, looking at it (world up +z), at the mean distance and
    height of ``cameras`` (the training cameras); intrinsics of the first camera.

    Args:
        cameras: the cameras whose distance, height and intrinsics the orbit takes.
        aabb: float [2, 3] scene box, metres.
        n: number of views.

    Returns:
        float32 :class:`Cameras` of ``n`` views.
    """
    centre = aabb.mean(0)
    rel = cameras.origins - centre
    radius = float(rel[:, :2].norm(dim=-1).mean())
    height = float(rel[:, 2].mean())
    c = centre.detach().cpu().double().numpy()
    c2ws = []
    for k in range(n):
        a = 2 * np.pi * k / n
        pos = c + np.array([radius * np.cos(a), radius * np.sin(a), height])
        c2ws.append(torch.from_numpy(look_at(pos, c)).float())
    rep = lambda t: t[:1].repeat(n)  # noqa: E731
    return Cameras(torch.stack(c2ws), rep(cameras.fx), rep(cameras.fy), rep(cameras.cx), rep(cameras.cy),
                   rep(cameras.width), rep(cameras.height))


def cameras_from_pinholes(pinholes: Sequence[PinholeCamera], dtype: torch.dtype = torch.float32) -> Cameras:
    """A :class:`Cameras` batch from numpy :class:`~toolkit.pinhole.PinholeCamera` s (near/far are dropped)."""
    t = lambda k: torch.tensor([getattr(p, k) for p in pinholes], dtype=dtype)  # noqa: E731
    return Cameras(torch.tensor(np.stack([p.c2w for p in pinholes]), dtype=dtype), t("fx"), t("fy"), t("cx"), t("cy"),
                   torch.tensor([p.width for p in pinholes]), torch.tensor([p.height for p in pinholes]))
