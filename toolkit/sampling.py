"""Stage 7 — ray and sample selection: occupancy grid, stratified + hierarchical sampling, and DARS.

**Baseline** (``dars=False``): every ray gets ``n_coarse`` stratified samples in [near, far]; those in empty
cells of the :class:`OccupancyGrid` are skipped; the field's densities at the kept coarse samples give the
hierarchical proposal from which ``n_fine`` samples per ray are drawn by inverse-CDF sampling; the field is
rendered on the union (NeRF's coarse + fine scheme with one field).

**DARS** (``dars=True``; SPEC stage 7, paper eqs. 4–7), four parts:

1. *ray selection* — training pixels are drawn with probability ∝ (1 − ρ) + ρ·W(pixel), and each ray carries
   the importance weight ``(1 / N_pix) / p`` so the loss stays an unbiased estimate of the uniform-pixel loss; a
   view is picked by its total weight, then a pixel of it by rejection sampling, so nothing is held per pixel
   beyond W itself and views may differ in size (:func:`build_ray_sampler`, :func:`select_rays`);
2. *per-ray budget* — the fine samples of a batch total ``n_fine · R`` (fixed), split ∝ W, clamped to
   [``budget_min``, ``budget_max``] = [1, 12]; rays with W ≤ τ = 0.7 get at most the uniform share, so the
   extra samples go only where W > τ (:func:`ray_budgets`);
3. *along the ray* — p(t) ∝ W̄(r(t)) · p₀(t) where W̄(x) averages W_j(Π_j(x)) over the ``n_neighbours``
   nearest *other* training views j (depth-dependent: it peaks where the point lands on edges and highlights in
   other views), p₀ the stratified (occupied) prior; mixed with the hierarchical proposal weights
   (1 − μ)·w + μ·p and inverted (:func:`average_other_view_weights`, :func:`sample_fine`);
4. *packing* — samples are packed with ray indices (:class:`toolkit.render.PackedSamples`), never padded.

At render time there is no photo to compute W from: every ray gets the mean budget and part 3 still applies.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ._checks import ConfigError, check_range, check_shape
from .render import PackedSamples, ray_starts
from .scene import Cameras, RayBundle
from .pixels import PackedViews
from .space import SceneSpace, contracted_edges, uncontract

__all__ = [
    "SamplerConfig",
    "OccupancyGrid",
    "stratified_edges",
    "coarse_samples",
    "proposal_weights",
    "sample_fine",
    "merge_samples",
    "RaySampler",
    "build_ray_sampler",
    "select_rays",
    "ray_budgets",
    "neighbour_views",
    "average_other_view_weights",
    "projection_matrices",
]


@dataclass(frozen=True)
class SamplerConfig:
    """Sample counts and DARS parameters."""

    n_coarse: int = 64
    """Stratified samples per ray (paper: 64 for training, 128 for testing)."""
    n_fine: int = 8
    """Mean hierarchical/DARS samples per ray (the fixed total is ``n_fine`` x rays)."""
    dars: bool = True
    """Use DARS ray selection, budgets and along-ray density; False: uniform pixels + hierarchical sampling."""
    rho: float = 0.5
    """Ray selection mixes uniform (1 - rho) and W-proportional (rho) pixel probabilities."""
    tau: float = 0.7
    """W threshold above which a ray may receive more than the uniform share of samples."""
    budget_min: int = 1
    """Fewest fine samples per ray (paper: 1 in flat shadow)."""
    budget_max: int = 12
    """Most fine samples per ray (paper: 12 in highlights)."""
    mix: float = 0.5
    """Weight μ of the W̄-based density against the hierarchical proposal weights."""
    n_neighbours: int = 4
    """Other training views averaged into W̄(x)."""
    perturb: bool = True
    """Jitter stratified samples (training); False for deterministic rendering."""
    normalise: str = "quantile"
    """How the sampler reads W: ``quantile`` — per image by rank (:func:`toolkit.edges.quantile_normalise`: τ
    selects the top 1 − τ of each photo), ``none`` — as computed (min-max, eq. 4)."""

    def __post_init__(self):
        if self.n_coarse < 2:
            raise ConfigError(f"n_coarse={self.n_coarse} must be >= 2")
        if self.n_fine < 0:
            raise ConfigError(f"n_fine={self.n_fine} must be >= 0")
        check_range(self.rho, 0.0, 1.0, "rho")
        check_range(self.tau, 0.0, 1.0, "tau")
        check_range(self.mix, 0.0, 1.0, "mix")
        if self.normalise not in ("quantile", "none"):
            raise ConfigError(f"sampler normalise={self.normalise!r}: choose 'quantile' or 'none'")
        if not 0 <= self.budget_min <= self.budget_max:
            raise ConfigError(f"need 0 <= budget_min ({self.budget_min}) <= budget_max ({self.budget_max})")
        if self.dars and not self.budget_min <= self.n_fine <= self.budget_max:
            raise ConfigError(f"n_fine={self.n_fine} (the mean DARS budget) must lie in "
                              f"[budget_min, budget_max] = [{self.budget_min}, {self.budget_max}]")


# ====================================================================== occupancy grid
class OccupancyGrid:
    """A coarse density grid used to skip empty space (over the scene box, or over all of contracted space).

    Each cell keeps an exponential moving maximum of the field's density at random points in it
    (Instant-NGP): ``d ← max(decay · d, σ(x))``. A cell is occupied when ``d · step · s(x) > threshold`` — the
    opacity one sample in it adds, ``step`` the spacing of the samples (the trainer passes box diagonal / coarse
    samples per ray; Instant-NGP's own fine render step, diagonal / 1024, would count density that a coarse sample
    still sees as empty), ``s(x)`` the contraction's stretch at the cell
    (:meth:`toolkit.space.SceneSpace.step_scale`: far cells are crossed by longer steps) — or, early on, when it is
    above the mean. All cells start occupied and stay so during warm-up.

    Args:
        aabb: float [2, 3] scene box.
        resolution: cells per axis.
        step: sample spacing (metres) that turns density into opacity.
        threshold: opacity below which a cell counts as empty.
        decay: EMA decay per update.
        contraction: cover all of space through the scene contraction (:mod:`toolkit.space`); False: the box only.
        far_radius: the contraction's far radius.
    """

    def __init__(self, aabb: torch.Tensor, resolution: int = 64, step: float = 0.01, threshold: float = 0.01,
                 decay: float = 0.95, contraction: bool = False, far_radius: float = 64.0):
        if resolution < 2:
            raise ConfigError(f"occupancy resolution={resolution} must be >= 2")
        self.aabb = torch.as_tensor(aabb, dtype=torch.float32).reshape(2, 3)
        self.contraction = bool(contraction)
        self.far_radius = float(far_radius)
        self.explore = 0.0
        """Fraction of all cells marked occupied at random at each update (0: off)."""
        self.resolution = int(resolution)
        self.step = float(step)
        self.threshold = float(threshold)
        self.decay = float(decay)
        n = self.resolution ** 3
        self.density = torch.full((n,), 1e6, device=self.aabb.device)  # "unknown = occupied" until measured
        self.mask = torch.ones(n, dtype=torch.bool, device=self.aabb.device)
        self.updates = 0

    @property
    def space(self) -> SceneSpace:
        return SceneSpace(self.aabb, self.contraction, self.far_radius)

    def to(self, device) -> "OccupancyGrid":
        self.aabb, self.density, self.mask = self.aabb.to(device), self.density.to(device), self.mask.to(device)
        return self

    def state_dict(self) -> dict:
        return {"aabb": self.aabb.cpu(), "resolution": self.resolution, "step": self.step, "threshold": self.threshold,
                "decay": self.decay, "density": self.density.cpu(), "mask": self.mask.cpu(), "updates": self.updates,
                "contraction": self.contraction, "far_radius": self.far_radius}

    @classmethod
    def from_state_dict(cls, d: dict) -> "OccupancyGrid":
        g = cls(d["aabb"], d["resolution"], d["step"], d["threshold"], d["decay"],
                contraction=bool(d.get("contraction", False)), far_radius=float(d.get("far_radius", 64.0)))
        g.density, g.mask, g.updates = d["density"].clone(), d["mask"].clone(), int(d["updates"])
        return g

    def cell_index(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(flat cell index [N], modelled-space mask [N]) of world points [N, 3]."""
        sp = self.space
        g = sp.to_grid(points)
        box = sp.grid_aabb.to(points)
        u = (g - box[0]) / (box[1] - box[0])
        inside = sp.inside(points) if self.contraction else ((u >= 0) & (u <= 1)).all(-1)
        ijk = (u * self.resolution).long().clamp(0, self.resolution - 1)
        r = self.resolution
        return ijk[:, 0] * r * r + ijk[:, 1] * r + ijk[:, 2], inside

    def occupied(self, points: torch.Tensor) -> torch.Tensor:
        """bool [N]: the point is inside the modelled space and its cell is occupied."""
        idx, inside = self.cell_index(points)
        return self.mask[idx] & inside

    def cell_centres(self, idx: torch.Tensor, jitter: torch.Tensor | None = None) -> torch.Tensor:
        """World positions [N, 3] of cells ``idx`` (their centres, or offset by ``jitter`` [N, 3] in cell units,
        in grid coordinates, so a jittered point stays in its cell also in contracted space)."""
        r = self.resolution
        ijk = torch.stack([idx // (r * r), (idx // r) % r, idx % r], -1).float()
        if jitter is not None:
            ijk = ijk + jitter.to(ijk)
        box = self.space.grid_aabb.to(ijk.device)
        g = box[0] + (ijk + 0.5) / r * (box[1] - box[0])
        if not self.contraction:
            return g
        return uncontract(g, self.aabb.to(g))

    @torch.no_grad()
    def update(self, density_fn, generator: torch.Generator | None = None, all_cells: bool = False,
               chunk: int = 262144, warmup: bool = False) -> None:
        """Refresh cells: all of them (``all_cells``) or a random quarter plus the currently occupied ones.
        ``density_fn(points [N, 3]) -> [N]``. During ``warmup`` densities are recorded but every cell stays
        occupied (the field has not learnt where empty space is yet)."""
        n = self.resolution ** 3
        dev = self.density.device
        if all_cells:
            idx = torch.arange(n, device=dev)
        else:
            rand = torch.randint(0, n, (n // 4,), generator=generator, device="cpu").to(dev)
            occ = torch.nonzero(self.mask).squeeze(-1)
            if occ.numel() > n // 4:
                occ = occ[torch.randint(0, occ.numel(), (n // 4,), generator=generator, device="cpu").to(dev)]
            idx = torch.unique(torch.cat([rand, occ]))
        jitter = torch.rand(idx.numel(), 3, generator=generator, device="cpu").to(dev) - 0.5
        pts = self.cell_centres(idx, jitter)
        sig = torch.cat([density_fn(pts[i:i + chunk]).float() for i in range(0, pts.shape[0], chunk)])
        if self.contraction:  # a far cell is crossed by proportionally longer steps: compare opacities, not σ
            sig = sig * self.space.step_scale(pts).to(sig)
        cur = self.density[idx]
        cur = torch.where(cur >= 1e6, torch.zeros_like(cur), cur)  # first measurement replaces "unknown"
        self.density[idx] = torch.maximum(cur * self.decay, sig)
        measured = self.density < 1e6
        occ_val = self.density * self.step
        mean = occ_val[measured].mean() if measured.any() else occ_val.new_tensor(0.0)
        thr = min(float(mean), self.threshold)
        self.mask = (occ_val > thr) | ~measured
        if self.explore > 0 and not all_cells:  # a few random empty cells stay sampled, so density can grow back
            k = int(self.explore * n)
            pick = torch.randint(0, n, (k,), generator=generator, device="cpu").to(dev)
            self.mask[pick] = True
        if warmup:
            self.mask = torch.ones_like(self.mask)
        self.updates += 1

    def occupancy_fraction(self) -> float:
        return float(self.mask.float().mean())


# ====================================================================== stratified + hierarchical
def stratified_edges(rays: RayBundle, n: int, perturb: bool, generator: torch.Generator | None = None,
                     space: SceneSpace | None = None) -> torch.Tensor:
    """float [R, n + 1] stratum edges in [near, far] per ray (shifted by one random offset per ray when
    ``perturb``; the first/last strata are clipped to [near, far]). Rays that miss (far <= near) get
    zero-length strata. With a contracted ``space`` the strata are equal in contracted arc length
    (:func:`toolkit.space.contracted_edges`), else equal in metres."""
    if space is not None and space.contraction:
        return contracted_edges(rays.origins, rays.directions, rays.near, rays.far, space, n, perturb, generator)
    R = len(rays)
    near = rays.near
    far = torch.maximum(rays.far, rays.near)
    u = torch.linspace(0.0, 1.0, n + 1, device=near.device)
    edges = near[:, None] + (far - near)[:, None] * u[None]
    if perturb:
        shift = (torch.rand(R, 1, generator=generator, device="cpu").to(near.device) - 0.5) * (far - near)[:, None] / n
        edges = torch.minimum(torch.maximum(edges + shift, near[:, None]), far[:, None])
    return edges


def coarse_samples(rays: RayBundle, edges: torch.Tensor, occupancy: OccupancyGrid | None) -> tuple[PackedSamples, torch.Tensor]:
    """Packed coarse samples in occupied cells.

    Returns:
        (samples, stratum index [S] of each kept sample within its ray).
    """
    R, S1 = edges.shape
    starts, ends = edges[:, :-1], edges[:, 1:]
    keep = ends > starts
    if occupancy is not None:
        mids = 0.5 * (starts + ends)
        pts = rays.origins[:, None, :] + mids[..., None] * rays.directions[:, None, :]
        keep = keep & occupancy.occupied(pts.reshape(-1, 3)).reshape(R, S1 - 1)
    ray_idx, k = torch.nonzero(keep, as_tuple=True)
    return PackedSamples(starts[ray_idx, k], ends[ray_idx, k], ray_idx, R), k


def proposal_weights(coarse: PackedSamples, stratum: torch.Tensor, densities: torch.Tensor, n_strata: int) -> torch.Tensor:
    """Dense [R, n_strata] rendering weights of the coarse samples (zero in skipped strata); no gradient."""
    from .render import render_weights

    with torch.no_grad():
        w, _, _ = render_weights(densities.detach(), coarse.deltas, coarse.ray_indices, coarse.n_rays)
        dense = torch.zeros(coarse.n_rays, n_strata, dtype=w.dtype, device=w.device)
        dense[coarse.ray_indices, stratum] = w
    return dense


def sample_fine(edges: torch.Tensor, pdf: torch.Tensor, counts: torch.Tensor, perturb: bool,
                generator: torch.Generator | None = None, return_strata: bool = False):
    """Inverse-CDF sampling of a per-ray piecewise-constant density over the strata.

    Args:
        edges: float [R, n + 1] stratum edges.
        pdf: float [R, n] non-negative weights per stratum (rows summing to 0 are treated as uniform).
        counts: int64 [R] samples to draw per ray (the packed budget).
        perturb: stratified random ``u`` within each of the ``counts`` equal CDF slices (else slice centres).

        return_strata: also return the stratum index [S_f] of each sample.

    Returns:
        (t [S_f], ray_indices [S_f]) sorted by ray, then t (and the strata with ``return_strata``).
    """
    R, n = pdf.shape
    total = int(counts.sum())
    if total == 0:
        z = edges.new_zeros(0)
        e = torch.zeros(0, dtype=torch.long, device=edges.device)
        return (z, e, e) if return_strata else (z, e)
    valid = (edges[:, 1:] > edges[:, :-1]).to(pdf.dtype)
    p = pdf * valid
    s = p.sum(-1, keepdim=True)
    p = torch.where(s > 1e-12, p / s.clamp_min(1e-12), valid / valid.sum(-1, keepdim=True).clamp_min(1.0))
    cdf = torch.cat([torch.zeros(R, 1, dtype=p.dtype, device=p.device), torch.cumsum(p, -1)], -1)
    cdf[:, -1] = 1.0
    ray_idx = torch.repeat_interleave(torch.arange(R, device=edges.device), counts)
    j = torch.arange(total, device=edges.device) - ray_starts(ray_idx, R)[ray_idx]
    jitter = torch.rand(total, generator=generator, device="cpu").to(edges.device) if perturb else torch.full((total,), 0.5, device=edges.device)
    u = ((j.to(p.dtype) + jitter) / counts[ray_idx].to(p.dtype)).clamp(0.0, 1.0 - 1e-6)
    rows = cdf[ray_idx]
    k = torch.searchsorted(rows, u[:, None], right=True).squeeze(-1).clamp(1, n) - 1
    c0 = rows.gather(1, k[:, None]).squeeze(-1)
    c1 = rows.gather(1, (k + 1)[:, None]).squeeze(-1)
    e = edges[ray_idx]
    e0 = e.gather(1, k[:, None]).squeeze(-1)
    e1 = e.gather(1, (k + 1)[:, None]).squeeze(-1)
    frac = ((u - c0) / (c1 - c0).clamp_min(1e-12)).clamp(0.0, 1.0)
    if return_strata:
        return e0 + frac * (e1 - e0), ray_idx, k
    return e0 + frac * (e1 - e0), ray_idx


def merge_samples(t_a: torch.Tensor, ray_a: torch.Tensor, t_b: torch.Tensor, ray_b: torch.Tensor, n_rays: int,
                  max_delta: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                  sample_max_delta: torch.Tensor | None = None) -> tuple[PackedSamples, torch.Tensor]:
    """Union of two sets of sample positions, sorted by (ray, t), with Voronoi intervals.

    Each sample's interval reaches half-way to its neighbours on the same ray, at most ``max_delta[ray] / 2``
    on either side and never beyond [near, far] — so isolated samples represent one coarse step and packed
    samples split the ray between them.

    Args:
        t_a, ray_a / t_b, ray_b: float [S_a] / [S_b] positions and int64 ray indices.
        n_rays: R.
        max_delta: float [R] longest interval (the coarse step) per ray.
        near, far: float [R] ray bounds.
        sample_max_delta: float [S_a + S_b] longest interval per sample (its stratum's width, for strata of
            unequal length as in contracted space), used instead of ``max_delta`` when given.

    Returns:
        (samples, order) where ``order`` [S_a + S_b] maps packed positions to indices into cat([a, b]).
    """
    t = torch.cat([t_a, t_b])
    r = torch.cat([ray_a, ray_b])
    if t.numel() == 0:
        return PackedSamples(t, t, r, n_rays), torch.zeros(0, dtype=torch.long, device=t.device)
    # one sort on a float64 key: ray index + normalised depth in [0, 1)
    span = (far - near).clamp_min(1e-9).double()
    key = r.double() + ((t.double() - near.double()[r]) / span[r]).clamp(0.0, 1.0 - 1e-9)
    order = torch.argsort(key, stable=True)  # ties keep cat([a, b]) order (export/infer.py's numpy mirror does too)
    t, r = t[order], r[order]
    half = 0.5 * (max_delta[r] if sample_max_delta is None else sample_max_delta[order])
    same_prev = torch.cat([torch.zeros(1, dtype=torch.bool, device=t.device), r[1:] == r[:-1]])
    same_next = torch.cat([r[:-1] == r[1:], torch.zeros(1, dtype=torch.bool, device=t.device)])
    gap_prev = torch.cat([t.new_zeros(1), t[1:] - t[:-1]])
    gap_next = torch.cat([t[1:] - t[:-1], t.new_zeros(1)])
    left = torch.where(same_prev, torch.minimum(0.5 * gap_prev, half), half)
    right = torch.where(same_next, torch.minimum(0.5 * gap_next, half), half)
    starts = torch.maximum(t - left, near[r])
    ends = torch.minimum(t + right, far[r])
    ends = torch.maximum(ends, starts)
    return PackedSamples(starts, ends, r, n_rays), order


# ====================================================================== DARS: ray selection and budgets
@dataclass(frozen=True)
class RaySampler:
    """Pixel selection ∝ (1 − ρ) + ρ·W over every training pixel, without a table over all of them.

    A draw picks a view with probability ∝ its total weight ``Σ_pixels (1 − ρ) + ρ·W``, then a pixel of that view by
    rejection sampling: a uniform pixel is kept with probability ``(1 − ρ) + ρ·W ≤ 1`` (so at least 1 − ρ of the
    proposals are kept). Memory: the W buffer the trainer holds anyway plus [V] numbers (the old float64 CDF over all
    pixels cost 12 bytes a pixel).

    Attributes:
        layout: a :class:`toolkit.pixels.PackedViews` giving the view sizes (its data is W, or unused when ``weights``
            is None).
        weights: W [P] in [0, 1] (packed), or None for uniform selection.
        valid: bool [P] pixels that may be drawn (packed), or None for all.
        rho: mixing weight ρ.
        view_cdf: float64 [V] cumulative view probabilities.
        total: Σ over all pixels of the unnormalised probability (the normaliser of p).
        n_pixels: P.
    """

    layout: PackedViews
    weights: PackedViews | None
    valid: PackedViews | None
    rho: float
    view_cdf: torch.Tensor
    total: float
    n_pixels: int

    def pixel_weight(self, flat: torch.Tensor) -> torch.Tensor:
        """float64 [N] unnormalised probability (1 − ρ) + ρ·W (0 where not valid) of buffer indices ``flat`` [N]."""
        if self.weights is None:
            p = torch.ones(flat.shape[0], dtype=torch.float64)
        else:
            p = (1.0 - self.rho) + self.rho * self.weights.gather(flat).double().clamp(0.0, 1.0).cpu()
        if self.valid is not None:
            p = p * self.valid.gather(flat).double().cpu()
        return p


def _as_packed(maps, name: str) -> PackedViews | None:
    if maps is None or isinstance(maps, PackedViews):
        return maps
    if isinstance(maps, torch.Tensor):
        return PackedViews.from_maps(maps)
    raise ConfigError(f"{name}: expected a PackedViews or a tensor [V, H, W], got {type(maps).__name__}")


def build_ray_sampler(weights: PackedViews | torch.Tensor | None, shape: PackedViews | tuple[int, int, int], rho: float,
                      valid: PackedViews | torch.Tensor | None = None) -> RaySampler:
    """Pixel probabilities ∝ (1 − ρ) + ρ·W (uniform when ``weights`` is None or ρ = 0), views of any sizes.

    Args:
        weights: W in [0, 1]: a :class:`toolkit.pixels.PackedViews` (uint8-quantised or float) or a float tensor
            [V, H, W], or None.
        shape: the view sizes: a ``PackedViews`` (e.g. the images), or (V, H, W) when all views share one size.
        rho: mixing weight.
        valid: bool pixels that may be drawn (e.g. inside the image mask), packed or [V, H, W], or None for all.

    Raises:
        ConfigError: the sizes of ``weights``/``valid`` disagree with ``shape``, or no pixel may be drawn.
    """
    if isinstance(shape, PackedViews):
        layout = shape
    else:
        V, H, W = (int(x) for x in shape)
        layout = PackedViews(torch.zeros(0), torch.full((V,), H), torch.full((V,), W),
                             torch.arange(V + 1, dtype=torch.long) * (H * W))
    weights = None if rho == 0.0 else _as_packed(weights, "weights")
    valid = _as_packed(valid, "valid")
    for name, m in (("weights", weights), ("valid", valid)):
        if m is not None and (len(m) != len(layout) or not torch.equal(m.heights.cpu(), layout.heights.cpu())
                              or not torch.equal(m.widths.cpu(), layout.widths.cpu())):
            raise ConfigError(f"{name}: view sizes {list(zip(m.heights.tolist(), m.widths.tolist()))[:4]} differ from "
                              f"the views' {list(zip(layout.heights.tolist(), layout.widths.tolist()))[:4]}")
    counts = (layout.heights * layout.widths).double().cpu()
    if weights is None:
        per_view = counts.clone() if valid is None else valid.sums()
    elif valid is None:
        per_view = (1.0 - rho) * counts + rho * weights.sums()
    else:  # masked views: sum (1 - rho + rho W) over the valid pixels, view by view
        per_view = torch.zeros(len(layout), dtype=torch.float64)
        for i in range(len(layout)):
            m = valid.raw(i).reshape(-1).cpu()
            per_view[i] = float(((1.0 - rho) + rho * weights[i].reshape(-1).double().cpu()[m]).sum())
    total = float(per_view.sum())
    if not total > 0:
        raise ConfigError("no valid training pixels to sample (all masked out)")
    return RaySampler(layout=layout, weights=weights, valid=valid, rho=float(rho),
                      view_cdf=torch.cumsum(per_view / total, 0), total=total, n_pixels=layout.n_pixels)


def select_rays(sampler: RaySampler, n: int, generator: torch.Generator | None = None,
                max_rounds: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    """Draw ``n`` pixels (with replacement) from the sampler: a view by its total weight, then a pixel of it by
    rejection sampling; draws still rejected after ``max_rounds`` rounds (a view whose W is almost all zero with
    ρ = 1, or mostly masked out) are drawn exactly from their view's own CDF.

    Returns:
        (buffer indices int64 [n] — ``view * H * W + row * W + col`` when all views share one size; see
        :meth:`toolkit.pixels.PackedViews.locate` —, importance weights float [n] = (1 / P) / p(pixel), mean ≈ 1).
    """
    lay = sampler.layout
    offsets = lay.offsets.cpu()
    sizes = (lay.heights * lay.widths).cpu()
    u = torch.rand(n, generator=generator, dtype=torch.float64)
    views = torch.searchsorted(sampler.view_cdf, u * float(sampler.view_cdf[-1]), right=True).clamp(max=len(lay) - 1)
    flat = torch.empty(n, dtype=torch.long)
    todo = torch.arange(n)
    uniform = sampler.weights is None and sampler.valid is None
    for _ in range(max_rounds):
        if todo.numel() == 0:
            break
        v = views[todo]
        cand = offsets[v] + (torch.rand(todo.numel(), generator=generator, dtype=torch.float64)
                             * sizes[v]).long().clamp(max=sizes[v] - 1)
        if uniform:
            flat[todo] = cand
            todo = todo[:0]
            break
        keep = torch.rand(todo.numel(), generator=generator, dtype=torch.float64) < sampler.pixel_weight(cand)
        flat[todo[keep]] = cand[keep]
        todo = todo[~keep]
    for vi in torch.unique(views[todo]).tolist():  # the rare leftovers: exact inverse CDF within their view
        sel = todo[views[todo] == vi]
        cand = torch.arange(int(offsets[vi]), int(offsets[vi + 1]))
        cdf = torch.cumsum(sampler.pixel_weight(cand), 0)
        r = torch.rand(sel.numel(), generator=generator, dtype=torch.float64) * float(cdf[-1])
        flat[sel] = cand[torch.searchsorted(cdf, r, right=True).clamp(max=cand.numel() - 1)]
    p = sampler.pixel_weight(flat) / sampler.total
    weight = (1.0 / sampler.n_pixels) / p.clamp_min(1e-300)
    return flat, weight.float()


def ray_budgets(w: torch.Tensor, mean_budget: int, tau: float, lo: int, hi: int) -> torch.Tensor:
    """Integer samples per ray ∝ W under a fixed total ``mean_budget · R``, clamped to [lo, hi], and more than
    the uniform share (``mean_budget``) only where W > τ.

    Args:
        w: float [R] per-ray weight (W at the ray's pixel), in [0, 1].
        mean_budget: the uniform share; the total is ``mean_budget * R`` (exactly, when attainable).
        tau: threshold for extra samples.
        lo, hi: clamp.

    Returns:
        int64 [R].
    """
    R = w.shape[0]
    if R == 0:
        return torch.zeros(0, dtype=torch.long, device=w.device)
    total = mean_budget * R
    w_raw = w.float().clamp(0.0, 1.0)
    cap = torch.where(w_raw > tau, torch.full_like(w_raw, float(hi)), torch.full_like(w_raw, float(min(hi, mean_budget))))
    w = w_raw + 1e-3  # every ray keeps a share
    floor_ = torch.full_like(w, float(lo))
    # Find the scale s with sum(clamp(s * w, lo, cap)) = total (monotone in s: bisection).
    s_lo, s_hi = 0.0, float(hi) / float(w.min()) + 1.0
    for _ in range(50):
        s = 0.5 * (s_lo + s_hi)
        if float(torch.minimum(torch.maximum(s * w, floor_), cap).sum()) < total:
            s_lo = s
        else:
            s_hi = s
    real = torch.minimum(torch.maximum(s_hi * w, floor_), cap)
    base = real.floor()
    short = int(round(total - float(base.sum())))
    if short > 0:  # largest remainders first, only where the cap allows
        frac = torch.where(base < cap, real - base, torch.full_like(real, -1.0))
        take = torch.topk(frac, min(short, R)).indices
        base[take] += 1
    elif short < 0:
        frac = torch.where(base > floor_, real - base, torch.full_like(real, 2.0))
        take = torch.topk(-frac, min(-short, R)).indices
        base[take] -= 1
    return base.long()


# ====================================================================== DARS: along-ray density from other views
def neighbour_views(cameras: Cameras, k: int) -> torch.Tensor:
    """int64 [V, k] the ``k`` nearest *other* training views of each view (camera-centre distance plus a
    viewing-direction term, so views looking elsewhere are not picked)."""
    V = len(cameras)
    k = min(k, max(V - 1, 0))
    if k == 0:
        return torch.zeros(V, 0, dtype=torch.long)
    o = cameras.origins
    f = -cameras.c2w[:, :3, 2]
    scale = (o - o.mean(0)).norm(dim=-1).mean().clamp_min(1e-6)
    d = torch.cdist(o, o) / scale + (1.0 - f @ f.T)
    d.fill_diagonal_(float("inf"))
    return torch.topk(d, k, largest=False).indices


def projection_matrices(cameras: Cameras) -> torch.Tensor:
    """float [V, 3, 4] matrices P with P [x; 1] = (u·d, v·d, d): pixel coordinates (u, v) in the convention of
    :mod:`toolkit.scene` (pixel index = floor) and depth d along the optical axis."""
    c2w = cameras.c2w
    A = c2w[:, :3, :3].transpose(1, 2)  # R^T
    b = -(A @ c2w[:, :3, 3:4])[..., 0]  # -R^T o
    fx, fy, cx, cy = (t[:, None] for t in (cameras.fx, cameras.fy, cameras.cx, cameras.cy))
    row0 = torch.cat([fx * A[:, 0] - cx * A[:, 2], fx * b[:, 0:1] - cx * b[:, 2:3]], -1)
    row1 = torch.cat([-fy * A[:, 1] - cy * A[:, 2], -fy * b[:, 1:2] - cy * b[:, 2:3]], -1)
    row2 = torch.cat([-A[:, 2], -b[:, 2:3]], -1)
    return torch.stack([row0, row1, row2], 1)


def average_other_view_weights(points: torch.Tensor, ray_views: torch.Tensor, neighbours: torch.Tensor,
                               cameras: Cameras, weight_maps: PackedViews | torch.Tensor,
                               projections: torch.Tensor | None = None) -> torch.Tensor:
    """W̄(x): mean of W_j(Π_j(x)) over the neighbour views j of each point's ray view (nearest-pixel lookups —
    the maps are smooth by construction; views where x falls outside the image or behind the camera are left
    out; 0 if no neighbour sees it).

    Args:
        points: float [S, 3] world points.
        ray_views: int64 [S] row of ``neighbours`` for each point (its ray's training view).
        neighbours: int64 [V', k] from :func:`neighbour_views`.
        cameras: the training cameras (each view its own size: ``cameras.width``/``height``).
        weight_maps: W in [0, 1] of the training views: packed (:class:`toolkit.pixels.PackedViews`, views of any
            sizes, uint8-quantised or float) or a float tensor [V, H, W].
        projections: float [V, 3, 4] from :func:`projection_matrices` (computed when None).

    Returns:
        float [S].
    """
    S = points.shape[0]
    if S == 0 or neighbours.shape[1] == 0:
        return points.new_zeros(S)
    wm = _as_packed(weight_maps, "weight_maps").to(points.device)
    P = projection_matrices(cameras).to(points) if projections is None else projections.to(points)
    nb = neighbours.to(points.device)[ray_views]  # [S, k]
    proj = torch.einsum("skij,sj->ski", P[nb][..., :3], points) + P[nb][..., 3]  # [S, k, 3]
    d = proj[..., 2]
    ds = d.clamp_min(1e-9)
    u = torch.floor(proj[..., 0] / ds)
    v = torch.floor(proj[..., 1] / ds)
    H = wm.heights[nb].to(u.dtype)
    W = wm.widths[nb].to(u.dtype)
    ok = (d > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    uu = torch.minimum(u.clamp_min(0), W - 1).long()
    vv = torch.minimum(v.clamp_min(0), H - 1).long()
    val = wm.gather(wm.flat_index(nb, vv, uu)).to(points)
    okf = ok.to(points.dtype)
    return (val * okf).sum(-1) / okf.sum(-1).clamp_min(1.0)
