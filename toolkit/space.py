"""Unbounded scenes: the scene box, scene contraction and sample spacing that follows it.

A gallery has no natural bounding box: walls, floor, ceiling, windows and the sky behind them are all seen. As in
mip-NeRF 360 / nerfacto, space is *contracted*: a point x is first normalised to the scene box (its centre at 0, its
faces at ±1 on each axis), ``n = (x − c) / h``; inside the box it stays, beyond it is squashed into a shell,

    contract(n) = n                              if ‖n‖∞ ≤ 1
                  (2 − 1/‖n‖∞) · n / ‖n‖∞        otherwise,

so the whole of space fits in [−2, 2]³ (the L∞ norm, as nerfacto uses for grids, keeps a box-shaped room a cube).
The hash grid and the occupancy grid live in contracted space; the box gets half of each grid axis, and the
resolution beyond it falls off as 1/‖n‖∞² — walls just outside the box keep detail, the sky gets little.

Rays run from the camera to ``far_radius`` (‖n‖∞ = 64 by default, contracted radius 1.98); what lies beyond is the
background model. Samples along a ray are spaced uniformly in *contracted* arc length (:func:`contracted_edges`),
so every stratum spans about the same number of grid cells: linear inside the box, disparity-like beyond it.

The box (``Scene.aabb``) is either the file's ``aabb`` (honoured, never needed) or fitted to the data
(:mod:`toolkit.bounds`). ``contraction=False`` keeps the older bounded model: nothing exists outside the box and rays
are clipped to it (objects on a known background, e.g. RGBA renders with transparency).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ._checks import ConfigError, check_shape

__all__ = ["SceneSpace", "contract", "uncontract", "box_radius", "contracted_edges", "DEFAULT_FAR_RADIUS"]

DEFAULT_FAR_RADIUS = 64.0
"""Rays end where ‖n‖∞ reaches this (64 box half-sizes; contracted radius 2 − 1/64)."""


def box_radius(points: torch.Tensor, aabb: torch.Tensor) -> torch.Tensor:
    """float [N] ‖n‖∞ of world points [N, 3] normalised to the box ``aabb`` [2, 3] (≤ 1 inside the box)."""
    centre = 0.5 * (aabb[0] + aabb[1])
    half = 0.5 * (aabb[1] - aabb[0])
    return ((points - centre) / half).abs().amax(-1)


def contract(points: torch.Tensor, aabb: torch.Tensor) -> torch.Tensor:
    """Scene contraction: world points [..., 3] -> contracted coordinates in [-2, 2]^3 (module docstring).

    Plain differentiable tensor operations (exports to ONNX). Points inside ``aabb`` map affinely to [-1, 1]^3.
    """
    centre = 0.5 * (aabb[0] + aabb[1])
    half = 0.5 * (aabb[1] - aabb[0])
    n = (points - centre) / half
    r = n.abs().amax(-1, keepdim=True)
    rs = r.clamp_min(1.0)
    return torch.where(r > 1.0, (2.0 - 1.0 / rs) * n / rs, n)


def uncontract(coords: torch.Tensor, aabb: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`contract`: contracted coordinates [..., 3] (‖c‖∞ < 2) -> world points."""
    centre = 0.5 * (aabb[0] + aabb[1])
    half = 0.5 * (aabb[1] - aabb[0])
    rho = coords.abs().amax(-1, keepdim=True)
    rs = rho.clamp(1.0, 2.0 - 1e-6)
    n = torch.where(rho > 1.0, coords / rs / (2.0 - rs), coords)
    return centre + n * half


@dataclass(frozen=True)
class SceneSpace:
    """The space a field lives in.

    Attributes:
        aabb: float [2, 3] the scene box (metres).
        contraction: True: unbounded (contracted beyond the box); False: only the box exists.
        far_radius: ‖n‖∞ at which rays end (contraction only).
    """

    aabb: torch.Tensor
    contraction: bool = True
    far_radius: float = DEFAULT_FAR_RADIUS

    def __post_init__(self):
        check_shape(self.aabb, "2 3", "aabb")
        if self.far_radius <= 1.0:
            raise ConfigError(f"far_radius={self.far_radius} must be > 1 (box half-sizes)")

    @property
    def grid_aabb(self) -> torch.Tensor:
        """float [2, 3] the box the hash and occupancy grids cover, in the coordinates :meth:`to_grid` returns."""
        if self.contraction:
            return torch.tensor([[-2.0] * 3, [2.0] * 3], dtype=self.aabb.dtype, device=self.aabb.device)
        return self.aabb

    def to_grid(self, points: torch.Tensor) -> torch.Tensor:
        """World points [N, 3] -> grid coordinates (contracted, or world when bounded)."""
        return contract(points, self.aabb.to(points)) if self.contraction else points

    def inside(self, points: torch.Tensor) -> torch.Tensor:
        """bool [N]: the point is modelled (within the far radius, or inside the box when bounded)."""
        r = box_radius(points, self.aabb.to(points))
        return r <= (self.far_radius if self.contraction else 1.0)

    def step_scale(self, points: torch.Tensor) -> torch.Tensor:
        """float [N] world length of a unit grid step at each point relative to one inside the box
        (max(1, ‖n‖∞)², the contraction's radial stretch; 1 everywhere when bounded)."""
        if not self.contraction:
            return torch.ones(points.shape[:-1], dtype=points.dtype, device=points.device)
        return box_radius(points, self.aabb.to(points)).clamp_min(1.0).square()

    def ray_bounds(self, origins: torch.Tensor, directions: torch.Tensor,
                   near_min: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
        """(near, far) float [N]: the box (bounded) or the far-radius box (contracted) along each ray."""
        from .cameras import intersect_aabb

        aabb = self.aabb.to(origins)
        if self.contraction:
            c, h = 0.5 * (aabb[0] + aabb[1]), 0.5 * (aabb[1] - aabb[0])
            aabb = torch.stack([c - self.far_radius * h, c + self.far_radius * h])
        return intersect_aabb(origins, directions, aabb, near_min)

    def to(self, device) -> "SceneSpace":
        return SceneSpace(self.aabb.to(device), self.contraction, self.far_radius)


def contracted_edges(origins: torch.Tensor, directions: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                     space: SceneSpace, n: int, perturb: bool, generator: torch.Generator | None = None,
                     n_candidates: int = 96) -> torch.Tensor:
    """Stratum edges [R, n + 1] uniform in contracted arc length between ``near`` and ``far``.

    The contracted path length L(t) of each ray is tabulated at ``n_candidates`` + 1 depths spaced geometrically
    from ``near`` to ``far`` (L is piecewise linear in t inside the box, so this is exact there), and the ``n``
    strata are its equal parts (shifted by one random offset per ray with ``perturb``; the first and last strata
    are clipped to [near, far]). Rays with ``far <= near`` get zero-length strata.

    Args:
        origins, directions: float [R, 3] rays (unit directions).
        near, far: float [R] bounds (metres).
        space: the scene space (contracted).
        n: strata per ray.
        perturb: jitter the edges.
        generator: RNG for the jitter (CPU).
        n_candidates: resolution of the arc-length table.
    """
    R = origins.shape[0]
    dev, dt = origins.device, origins.dtype
    far = torch.maximum(far, near)
    lo = near.clamp_min(1e-4)
    ratio = (far.clamp_min(1e-4) / lo).clamp_min(1.0)
    u = torch.linspace(0.0, 1.0, n_candidates + 1, device=dev, dtype=dt)
    t = lo[:, None] * ratio[:, None] ** u[None]  # [R, K+1] geometric
    t = torch.where(far[:, None] > near[:, None], t, near[:, None].expand_as(t))
    pts = origins[:, None, :] + t[..., None] * directions[:, None, :]
    c = contract(pts.reshape(-1, 3), space.aabb.to(pts)).reshape(R, n_candidates + 1, 3)
    seg = (c[:, 1:] - c[:, :-1]).norm(dim=-1)
    L = torch.cat([torch.zeros(R, 1, device=dev, dtype=dt), torch.cumsum(seg, -1)], -1)  # [R, K+1]
    total = L[:, -1:].clamp_min(1e-12)
    s = torch.linspace(0.0, 1.0, n + 1, device=dev, dtype=dt)[None].expand(R, n + 1)
    if perturb:
        shift = (torch.rand(R, 1, generator=generator, device="cpu").to(dev, dt) - 0.5) / n
        s = (s + shift).clamp(0.0, 1.0)
    target = s * total  # [R, n+1] arc length of each edge
    k = torch.searchsorted(L.contiguous(), target.contiguous(), right=True).clamp(1, n_candidates) - 1
    L0, L1 = L.gather(1, k), L.gather(1, k + 1)
    t0, t1 = t.gather(1, k), t.gather(1, k + 1)
    frac = ((target - L0) / (L1 - L0).clamp_min(1e-12)).clamp(0.0, 1.0)
    edges = t0 + frac * (t1 - t0)
    edges = torch.minimum(torch.maximum(edges, near[:, None]), far[:, None])
    edges, _ = torch.cummax(edges, dim=-1)
    return edges
