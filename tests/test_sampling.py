from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy import stats

from toolkit._checks import ConfigError
from toolkit.sampling import (OccupancyGrid, SamplerConfig, average_other_view_weights, build_ray_sampler,
                              merge_samples, neighbour_views, ray_budgets, sample_fine, select_rays,
                              stratified_edges)
from toolkit.pinhole import look_at
from toolkit.pixels import PackedViews
from toolkit.scene import Cameras, generate_rays


def test_ray_selection_follows_w_chi_square():
    g = torch.Generator().manual_seed(0)
    W = torch.rand(2, 4, 5, generator=g)
    rs = build_ray_sampler(W, (2, 4, 5), rho=0.6)
    expected = ((1 - 0.6) + 0.6 * W.reshape(-1).double())
    expected = expected / expected.sum()
    idx, iw = select_rays(rs, 200000, g)
    counts = torch.bincount(idx, minlength=40).numpy()
    chi2, p = stats.chisquare(counts, expected.numpy() * counts.sum())
    assert p > 1e-3, f"pixel counts do not follow (1-rho) + rho W (chi2={chi2:.1f}, p={p:.2g})"
    # importance weights make the estimate of a uniform-pixel mean unbiased
    f = torch.arange(40, dtype=torch.float64) ** 1.5
    est = float((iw.double() * f[idx]).mean())
    assert abs(est - float(f.mean())) / float(f.mean()) < 0.01


def test_ray_selection_over_views_of_different_sizes_chi_square():
    """Views of three sizes, W packed at uint8 precision: a view by its total weight, then a pixel by rejection
    sampling gives exactly p ∝ (1 - rho) + rho W over all pixels, and the importance weights stay unbiased."""
    g = torch.Generator().manual_seed(3)
    maps = [torch.rand(3, 4, generator=g), torch.rand(5, 2, generator=g) ** 3, torch.zeros(2, 3)]
    W = PackedViews.from_maps(maps, quantise=True)
    rs = build_ray_sampler(W, W, rho=0.8)
    w = torch.cat([W[i].reshape(-1) for i in range(3)]).double()  # the quantised values the sampler reads
    expected = (1 - 0.8) + 0.8 * w
    expected = expected / expected.sum()
    idx, iw = select_rays(rs, 300000, g)
    counts = torch.bincount(idx, minlength=W.n_pixels).numpy()
    chi2, p = stats.chisquare(counts, expected.numpy() * counts.sum())
    assert p > 1e-3, f"pixel counts do not follow (1-rho) + rho W (chi2={chi2:.1f}, p={p:.2g})"
    f = torch.arange(W.n_pixels, dtype=torch.float64) ** 1.5
    est = float((iw.double() * f[idx]).mean())
    assert abs(est - float(f.mean())) / float(f.mean()) < 0.01
    views, rows, cols = W.locate(idx[:50])
    assert torch.equal(W.flat_index(views, rows, cols), idx[:50])
    assert bool((rows < W.heights[views]).all() and (cols < W.widths[views]).all())


def test_ray_selection_falls_back_to_the_exact_cdf_for_peaky_views():
    """rho = 1 and one hot pixel per view: rejection almost never accepts; the leftovers are drawn exactly."""
    W = torch.zeros(2, 30, 30)
    W[0, 3, 4] = 1.0
    W[1, 20, 7] = 0.5
    rs = build_ray_sampler(W, (2, 30, 30), rho=1.0)
    idx, iw = select_rays(rs, 3000, torch.Generator().manual_seed(0), max_rounds=2)
    assert set(idx.tolist()) == {3 * 30 + 4, 900 + 20 * 30 + 7}
    frac = float((idx == 3 * 30 + 4).double().mean())
    assert abs(frac - 2 / 3) < 0.03
    with pytest.raises(ConfigError, match="no valid training pixels"):
        build_ray_sampler(torch.zeros(1, 2, 2), (1, 2, 2), rho=1.0)


def test_ray_selection_respects_a_valid_mask():
    g = torch.Generator().manual_seed(4)
    W = torch.rand(2, 6, 6, generator=g)
    valid = torch.rand(2, 6, 6, generator=g) > 0.7
    rs = build_ray_sampler(W, (2, 6, 6), rho=0.5, valid=valid)
    idx, iw = select_rays(rs, 20000, g)
    assert bool(valid.reshape(-1)[idx].all())
    expected = ((1 - 0.5) + 0.5 * W.reshape(-1).double()) * valid.reshape(-1)
    counts = torch.bincount(idx, minlength=72).numpy()[valid.reshape(-1).numpy()]
    e = (expected / expected.sum()).numpy()[valid.reshape(-1).numpy()]
    assert stats.chisquare(counts, e * counts.sum())[1] > 1e-3


def test_uniform_selection_when_rho_zero():
    rs = build_ray_sampler(torch.rand(1, 3, 3), (1, 3, 3), rho=0.0)
    _, iw = select_rays(rs, 1000, torch.Generator().manual_seed(1))
    assert torch.allclose(iw, torch.ones(1000))


def test_ray_budgets_total_range_and_threshold():
    g = torch.Generator().manual_seed(2)
    w = torch.rand(5000, generator=g) ** 2
    b = ray_budgets(w, 6, tau=0.7, lo=1, hi=12)
    assert int(b.sum()) == 6 * 5000  # fixed total
    assert int(b.min()) >= 1 and int(b.max()) <= 12
    assert int(b[w <= 0.7].max()) <= 6  # extra samples only where W > tau
    assert int(b[w > 0.7].max()) > 6
    rho, _ = stats.spearmanr(w.numpy(), b.numpy())
    assert rho > 0.8  # counts follow W (ties at the caps keep the rank correlation below 1)
    means = [float(b[(w >= lo) & (w < lo + 0.1)].float().mean()) for lo in np.arange(0, 1, 0.1)]
    assert all(m1 >= m0 - 1e-6 for m0, m1 in zip(means, means[1:]))  # non-decreasing in W
    assert means[0] < 6 < means[-1]
    # the flattest rays go down to the minimum
    assert int(b[w < 0.01].max()) <= 2


def test_budget_config_rejected():
    with pytest.raises(ConfigError, match="n_fine=20"):
        SamplerConfig(n_fine=20, budget_max=12)
    with pytest.raises(ConfigError, match="rho"):
        SamplerConfig(rho=1.5)


def test_inverse_cdf_sampling_ks():
    # piecewise-constant density over 4 strata of [0, 4]: KS test of 20k draws against its CDF
    edges = torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0]])
    pdf = torch.tensor([[0.1, 0.5, 0.0, 0.4]])
    t, ray = sample_fine(edges, pdf, torch.tensor([20000]), perturb=True, generator=torch.Generator().manual_seed(3))
    assert (ray == 0).all() and t.shape == (20000,)
    assert not ((t > 2.0) & (t < 3.0)).any()  # zero-density stratum never sampled

    def cdf(x):
        x = np.asarray(x)
        c = np.array([0.0, 0.1, 0.6, 0.6, 1.0])
        k = np.clip(np.floor(x).astype(int), 0, 3)
        return c[k] + (c[k + 1] - c[k]) * (x - k)

    _, p = stats.kstest(t.numpy(), cdf)
    assert p > 1e-3


def test_sample_fine_variable_counts_are_packed():
    edges = torch.linspace(0, 1, 9).expand(3, 9).contiguous()
    pdf = torch.ones(3, 8)
    t, ray = sample_fine(edges, pdf, torch.tensor([2, 0, 5]), perturb=False)
    assert ray.tolist() == [0, 0, 2, 2, 2, 2, 2]
    assert torch.allclose(t[:2], torch.tensor([0.25, 0.75]))


def test_merge_samples_sorted_disjoint_intervals():
    g = torch.Generator().manual_seed(4)
    ta = torch.rand(50, generator=g) * 2 + 1
    ra = torch.randint(0, 5, (50,), generator=g)
    tb = torch.rand(30, generator=g) * 2 + 1
    rb = torch.randint(0, 5, (30,), generator=g)
    near, far = torch.ones(5), torch.full((5,), 3.0)
    s, order = merge_samples(ta, ra, tb, rb, 5, torch.full((5,), 0.1), near, far)
    assert torch.equal(s.ray_indices, torch.sort(s.ray_indices).values)
    same = s.ray_indices[1:] == s.ray_indices[:-1]
    assert bool((s.t_starts[1:][same] >= s.t_ends[:-1][same] - 1e-6).all())  # no overlap within a ray
    assert bool((s.t_ends - s.t_starts <= 0.1 + 1e-6).all())
    assert torch.allclose(torch.cat([ta, tb])[order].sort().values, torch.cat([ta, tb]).sort().values)


def _ring_cameras(n=6, size=20):
    c2ws = []
    for k in range(n):
        a = 2 * np.pi * k / n
        c2ws.append(look_at([3 * np.cos(a), 3 * np.sin(a), 0.0], [0.0, 0.0, 0.0]))
    t = lambda v: torch.full((n,), float(v))  # noqa: E731
    return Cameras(torch.tensor(np.stack(c2ws), dtype=torch.float32), t(20), t(20), t(size / 2), t(size / 2),
                   torch.full((n,), size), torch.full((n,), size))


def test_other_view_weights_peak_where_the_point_projects_on_high_w():
    cams = _ring_cameras()
    W = torch.zeros(6, 20, 20)
    W[:, 10, 10] = 1.0  # every view has a hot pixel at its centre: the origin projects there
    nb = neighbour_views(cams, 2)
    assert nb.shape == (6, 2) and not (nb == torch.arange(6)[:, None]).any()  # other views only
    pts = torch.tensor([[0.0, 0, 0], [0.0, 0, 0.9]])
    w = average_other_view_weights(pts, torch.tensor([0, 0]), nb, cams, W)
    assert float(w[0]) == pytest.approx(1.0) and float(w[1]) == 0.0


def test_other_view_weights_with_views_of_different_sizes():
    """W̄ reads each neighbour's map at that view's own size (a flat buffer with per-view offsets)."""
    cams = _ring_cameras()
    sizes = [(20, 20), (12, 30), (20, 20), (30, 12), (20, 20), (16, 16)]
    cams = replace(cams, width=torch.tensor([w for _, w in sizes]), height=torch.tensor([h for h, _ in sizes]),
                   cx=torch.tensor([w / 2 for _, w in sizes], dtype=torch.float32),
                   cy=torch.tensor([h / 2 for h, _ in sizes], dtype=torch.float32))
    maps = []
    for h, w in sizes:
        m = torch.zeros(h, w)
        m[h // 2, w // 2] = 1.0  # the origin projects onto each view's centre pixel
        maps.append(m)
    W = PackedViews.from_maps(maps, quantise=True)
    nb = neighbour_views(cams, 3)
    pts = torch.tensor([[0.0, 0, 0], [0.0, 0, 0.9]])
    for v in range(6):
        w = average_other_view_weights(pts, torch.tensor([v, v]), nb, cams, W)
        assert float(w[0]) == pytest.approx(1.0) and float(w[1]) == 0.0


def test_occupancy_grid_marks_empty_space():
    grid = OccupancyGrid(torch.tensor([[-1.0, -1, -1], [1, 1, 1]]), resolution=16, step=0.05)
    assert grid.occupancy_fraction() == 1.0  # unknown = occupied

    def ball(p):
        return torch.where(p.norm(dim=-1) < 0.5, torch.full_like(p[:, 0], 100.0), torch.zeros_like(p[:, 0]))

    grid.update(ball, torch.Generator().manual_seed(0), all_cells=True)
    assert 0.02 < grid.occupancy_fraction() < 0.2
    assert bool(grid.occupied(torch.tensor([[0.0, 0, 0]]))) and not bool(grid.occupied(torch.tensor([[0.9, 0.9, 0.9]])))
    assert not bool(grid.occupied(torch.tensor([[3.0, 0, 0]])))  # outside the box


def test_stratified_edges_within_bounds():
    cams = _ring_cameras(1)
    rays = generate_rays(cams, [0], aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    e = stratified_edges(rays, 8, True, torch.Generator().manual_seed(0))
    hit = rays.far > rays.near
    assert bool((e[hit] >= rays.near[hit, None] - 1e-6).all()) and bool((e[hit] <= rays.far[hit, None] + 1e-6).all())
    assert bool((e[:, 1:] >= e[:, :-1]).all())
