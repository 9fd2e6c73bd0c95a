import math

import pytest
import torch

from toolkit._checks import ConfigError, ShapeError
from toolkit.space import SceneSpace, box_radius, contract, contracted_edges, uncontract

BOX = torch.tensor([[-1.0, -2.0, 0.0], [3.0, 2.0, 1.0]])


def test_contract_inside_is_affine_and_outside_is_bounded():
    g = torch.Generator().manual_seed(0)
    inside = BOX[0] + torch.rand(500, 3, generator=g) * (BOX[1] - BOX[0])
    c = contract(inside, BOX)
    centre, half = BOX.mean(0), 0.5 * (BOX[1] - BOX[0])
    torch.testing.assert_close(c, (inside - centre) / half)
    far = torch.randn(2000, 3, generator=g) * 100
    cf = contract(far, BOX)
    assert cf.abs().amax() < 2.0
    out = box_radius(far, BOX) > 1
    assert (cf[out].abs().amax(-1) > 1.0).all()


def test_uncontract_inverts_contract():
    x = torch.randn(3000, 3, generator=torch.Generator().manual_seed(1)) * 20
    torch.testing.assert_close(uncontract(contract(x, BOX), BOX), x, rtol=1e-4, atol=1e-3)


def test_contract_is_continuous_at_the_box_faces():
    n = torch.tensor([[1.0, 0.3, -0.2]])
    centre, half = BOX.mean(0), 0.5 * (BOX[1] - BOX[0])
    a = contract(centre + n * half * (1 - 1e-5), BOX)
    b = contract(centre + n * half * (1 + 1e-5), BOX)
    assert float((a - b).abs().max()) < 1e-4


def test_scene_space_bounds_and_scale():
    sp = SceneSpace(BOX, True, 16.0)
    o = torch.tensor([[1.0, 0.0, 0.5]])
    d = torch.tensor([[1.0, 0.0, 0.0]])
    near, far = sp.ray_bounds(o, d, 0.05)
    assert float(near) == pytest.approx(0.05)
    assert float(far) == pytest.approx(2.0 * 16.0)  # half-size 2 along x, 16 half-sizes from the centre
    assert torch.equal(sp.step_scale(torch.tensor([[0.0, 0.0, 0.5], [5.0, 0.0, 0.5]])), torch.tensor([1.0, 4.0]))
    assert bool(sp.inside(torch.tensor([[30.0, 0.0, 0.5]]))) and not bool(sp.inside(torch.tensor([[40.0, 0, 0.5]])))
    bounded = SceneSpace(BOX, False)
    assert torch.equal(bounded.grid_aabb, BOX)
    with pytest.raises(ConfigError, match="far_radius"):
        SceneSpace(BOX, True, 1.0)
    with pytest.raises(ShapeError):
        SceneSpace(torch.zeros(3, 3))


def _contracted_length(o, d, t0, t1, k=4000):
    t = torch.linspace(float(t0), float(t1), k, dtype=torch.float64)
    c = contract(o.double() + t[:, None] * d.double(), BOX.double())
    return float((c[1:] - c[:-1]).norm(dim=-1).sum())


@pytest.mark.parametrize("origin", [[1.0, 0.0, 0.5], [-6.0, 3.0, 4.0]])
def test_contracted_edges_split_contracted_length_evenly(origin):
    sp = SceneSpace(BOX, True, 64.0)
    o = torch.tensor([origin])
    d = torch.nn.functional.normalize(torch.tensor([[0.7, -0.3, 0.2]]), dim=-1)
    if origin[0] < 0:
        d = torch.nn.functional.normalize(BOX.mean(0, keepdim=True) - o, dim=-1)
    near, far = sp.ray_bounds(o, d)
    e = contracted_edges(o, d, near, far, sp, 16, perturb=False, n_candidates=256)[0]
    assert float(e[0]) == pytest.approx(float(near), rel=1e-4) and float(e[-1]) == pytest.approx(float(far), rel=1e-3)
    assert bool((e[1:] >= e[:-1]).all())
    lengths = [_contracted_length(o[0], d[0], e[i], e[i + 1]) for i in range(16)]
    assert max(lengths) / min(lengths) < 1.15, lengths


def test_contracted_edges_perturbed_stay_in_bounds_and_miss_rays_are_empty():
    sp = SceneSpace(BOX, True)
    g = torch.Generator().manual_seed(3)
    o = torch.randn(64, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    near, far = sp.ray_bounds(o, d)
    far[:4] = near[:4]  # rays that miss
    e = contracted_edges(o, d, near, far, sp, 8, perturb=True, generator=g)
    assert bool((e >= near[:, None] - 1e-5).all() and (e <= far[:, None] + 1e-3).all())
    assert bool((e[:, 1:] >= e[:, :-1]).all())
    assert bool((e[:4, 1:] == e[:4, :-1]).all())
    assert math.isfinite(float(e.sum()))
