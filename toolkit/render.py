"""Volume rendering on packed (variable-length) samples.

Samples of all rays live in flat arrays with a ``ray_indices`` [S] vector (sorted by ray, then depth), as in
nerfacc: no padding to the longest ray. For sample ``i`` of a ray with density σ_i over the interval
δ_i = t_end − t_start:

    α_i = 1 − exp(−σ_i δ_i),   T_i = exp(−Σ_{j<i} σ_j δ_j),   w_i = T_i α_i

(paper eq. 14 discretised; Max 1995). Any per-sample quantity is rendered as Σ_i w_i v_i. Transmittance uses an
exclusive cumulative sum over the packed array in float64 minus each ray's offset, so long batches stay exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ._checks import check_shape

__all__ = ["PackedSamples", "render_weights", "accumulate_along_rays", "ray_starts", "composite_background"]


@dataclass(frozen=True)
class PackedSamples:
    """Samples of many rays, packed.

    Attributes:
        t_starts, t_ends: float [S] interval bounds along the ray (metres along the unit direction).
        ray_indices: int64 [S] which ray each sample belongs to (non-decreasing).
        n_rays: number of rays R (rays may have no samples).
    """

    t_starts: torch.Tensor
    t_ends: torch.Tensor
    ray_indices: torch.Tensor
    n_rays: int

    def __len__(self) -> int:
        return int(self.t_starts.shape[0])

    @property
    def t_mids(self) -> torch.Tensor:
        return 0.5 * (self.t_starts + self.t_ends)

    @property
    def deltas(self) -> torch.Tensor:
        return self.t_ends - self.t_starts

    def points(self, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """float [S, 3] world positions of the interval midpoints."""
        return origins[self.ray_indices] + self.t_mids[:, None] * directions[self.ray_indices]

    def counts(self) -> torch.Tensor:
        """int64 [R] samples per ray."""
        return torch.bincount(self.ray_indices, minlength=self.n_rays)


def ray_starts(ray_indices: torch.Tensor, n_rays: int) -> torch.Tensor:
    """int64 [R] index of each ray's first sample in the packed arrays (its count's exclusive prefix sum)."""
    counts = torch.bincount(ray_indices, minlength=n_rays)
    return torch.cumsum(counts, 0) - counts


def render_weights(
    densities: torch.Tensor, deltas: torch.Tensor, ray_indices: torch.Tensor, n_rays: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Compositing weights of packed samples.

    Args:
        densities: float [S] σ ≥ 0 (1/metre).
        deltas: float [S] interval lengths (metres).
        ray_indices: int64 [S] sorted ray index of each sample.
        n_rays: R.

    Returns:
        (weights [S], transmittance [S] before each sample, alphas [S]); differentiable w.r.t. densities.
    """
    check_shape(densities, "S", "densities")
    sd = densities * deltas
    alphas = 1.0 - torch.exp(-sd)
    if sd.numel() == 0:
        return sd, sd, sd
    cs = torch.cumsum(sd.double(), 0)
    excl = cs - sd.double()
    starts = ray_starts(ray_indices, n_rays)
    offset = excl[starts.clamp(max=excl.shape[0] - 1)][ray_indices]
    trans = torch.exp(-(excl - offset)).to(densities.dtype)
    return trans * alphas, trans, alphas


def accumulate_along_rays(weights: torch.Tensor, values: torch.Tensor | None, ray_indices: torch.Tensor,
                          n_rays: int) -> torch.Tensor:
    """Σ_i w_i v_i per ray.

    Args:
        weights: float [S].
        values: float [S, C] (or ``None`` to accumulate the weights themselves: opacity).
        ray_indices: int64 [S].
        n_rays: R.

    Returns:
        float [R, C] (or [R, 1] for ``values=None``).
    """
    src = weights[:, None] if values is None else weights[:, None] * values
    out = torch.zeros(n_rays, src.shape[1], dtype=src.dtype, device=src.device)
    return out.index_add(0, ray_indices, src)


def composite_background(colour: torch.Tensor, opacity: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """colour [R, 3] + (1 − opacity [R, 1]) · background ([3] or [R, 3])."""
    return colour + (1.0 - opacity) * background
