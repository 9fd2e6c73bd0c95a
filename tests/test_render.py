import math

import torch

from toolkit.render import PackedSamples, accumulate_along_rays, render_weights


def test_constant_density_slab_closed_form():
    # rays through a slab of density sigma and thickness L: opacity 1 - exp(-sigma L) for any sampling
    sigma, L = 2.5, 0.8
    counts = torch.tensor([1, 3, 17, 64])
    ray_idx = torch.repeat_interleave(torch.arange(4), counts)
    deltas = torch.cat([torch.full((int(c),), L / int(c)) for c in counts])
    w, trans, alpha = render_weights(torch.full_like(deltas, sigma), deltas, ray_idx, 4)
    opacity = accumulate_along_rays(w, None, ray_idx, 4)[:, 0]
    assert torch.allclose(opacity, torch.full((4,), 1 - math.exp(-sigma * L)), atol=1e-6)
    # expected depth of a slab from 1 to 1 + L: ∫ t σ e^{-σ(t-1)} dt / opacity
    t_mid = torch.cat([1 + (torch.arange(int(c)) + 0.5) * L / int(c) for c in counts])
    depth = accumulate_along_rays(w, t_mid[:, None], ray_idx, 4)[:, 0] / opacity
    exact = 1 + (1 - math.exp(-sigma * L) * (1 + sigma * L)) / (sigma * (1 - math.exp(-sigma * L)))
    assert abs(float(depth[-1]) - exact) < 1e-3
    # transmittance restarts at 1 on every ray
    starts = torch.cumsum(counts, 0) - counts
    assert torch.allclose(trans[starts], torch.ones(4))


def test_two_slabs_and_empty_rays():
    ray_idx = torch.tensor([0, 0, 2, 2, 2])
    dens = torch.tensor([1.0, 3.0, 0.0, 10.0, 5.0])
    d = torch.tensor([0.5, 0.5, 1.0, 0.1, 0.2])
    w, _, _ = render_weights(dens, d, ray_idx, 3)
    op = accumulate_along_rays(w, None, ray_idx, 3)[:, 0]
    assert torch.allclose(op, torch.tensor([1 - math.exp(-2.0), 0.0, 1 - math.exp(-2.0)]), atol=1e-6)
    assert abs(float(w[0]) - (1 - math.exp(-0.5))) < 1e-6
    assert abs(float(w[1]) - math.exp(-0.5) * (1 - math.exp(-1.5))) < 1e-6


def test_long_batches_keep_precision():
    # 200k samples of opaque rays: the float64 cumulative sum keeps each ray's transmittance exact
    n_rays, per = 4000, 50
    ray_idx = torch.arange(n_rays).repeat_interleave(per)
    dens = torch.full((n_rays * per,), 40.0)
    d = torch.full_like(dens, 0.05)
    w, trans, _ = render_weights(dens, d, ray_idx, n_rays)
    last = accumulate_along_rays(w, None, ray_idx, n_rays)[-1, 0]
    assert abs(float(last) - (1 - math.exp(-40 * 0.05 * per))) < 1e-6
    assert float(trans[-per]) == 1.0


def test_gradients_flow_to_density():
    dens = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64, requires_grad=True)
    ri = torch.zeros(3, dtype=torch.long)
    d = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    col = torch.tensor([[1.0], [0.5], [0.25]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda s: accumulate_along_rays(render_weights(s, d, ri, 1)[0], col, ri, 1), (dens,))


def test_packed_samples_helpers():
    s = PackedSamples(torch.tensor([0.0, 1.0, 0.5]), torch.tensor([1.0, 2.0, 1.5]), torch.tensor([0, 0, 2]), 3)
    assert s.counts().tolist() == [2, 0, 1]
    pts = s.points(torch.zeros(3, 3), torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]))
    assert torch.allclose(pts[2], torch.tensor([0.0, 0, 1.0]))


def test_permute_matches_indexing_values_and_gradients():
    # render_rays reorders cat([coarse, fine]) by merge_samples' permutation; its backward gathers by the inverse
    # permutation instead of autograd's accumulating scatter, and must give the same values and gradients
    from toolkit.pipeline import _permute

    g = torch.Generator().manual_seed(0)
    a = torch.randn(50, 9, 3, generator=g, requires_grad=True)
    b = torch.randn(30, 9, 3, generator=g, requires_grad=True)
    order = torch.randperm(80, generator=g)
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(80)
    w = torch.randn(80, 9, 3, generator=g)
    out = _permute(a, b, order, inverse)
    ref = torch.cat([a, b])[order]
    assert torch.equal(out, ref)
    ga, gb = torch.autograd.grad((out * w).sum(), (a, b))
    ra, rb = torch.autograd.grad((ref * w).sum(), (a, b))
    assert torch.equal(ga, ra) and torch.equal(gb, rb)
    with torch.no_grad():  # no graph: plain indexing
        assert torch.equal(_permute(a, b, order, inverse), ref)
