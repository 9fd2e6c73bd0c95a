"""Shading against numeric integration of the same BRDF under the same SH light.

BRDF: Lambert a(1-m)/π + GGX D, height-correlated Smith visibility, Schlick Fresnel with F0 = mix(0.04, a, m).
Reference: a Fibonacci-sphere quadrature of ∫ f_r(l, v) L(l) (n·l) dl with 400k directions.
Stated tolerances (measured worst cases in brackets): diffuse exact to 1e-6 relative (4.6e-9: SH irradiance is
exact for an order-2 light); total colour within 3 % relative for roughness in [0.25, 1], metallic 0 or 1,
view angles 0-70° (2.6 %: the split-sum and SH-lobe approximations).
"""
import math

import pytest
import torch

from toolkit.sh import eval_sh
from toolkit.shading import (SPEC_BAND_G1, SPEC_BAND_G2, ShadingConfig, dfg_table, env_brdf, shade_pbr,
                             specular_band_attenuation)


def _fib(n):
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    r = (1 - z * z).sqrt()
    phi = math.pi * (1 + 5 ** 0.5) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


DIRS = _fib(400000)
DW = 4 * math.pi / DIRS.shape[0]


def _reference(a, rough, m, n, v, sh):
    L = eval_sh(sh, DIRS).clamp_min(0)
    ndl = (DIRS @ n).clamp_min(0)
    h = torch.nn.functional.normalize(DIRS + v, dim=-1)
    alpha = rough ** 2
    a2 = alpha ** 2
    ndh = (h @ n).clamp_min(0)
    ndv = float(n @ v)
    vdh = (h @ v).clamp_min(0)
    D = a2 / (math.pi * ((ndh ** 2) * (a2 - 1) + 1) ** 2)
    lv = ndl * math.sqrt(ndv * ndv * (1 - a2) + a2)
    ll = ndv * torch.sqrt(ndl * ndl * (1 - a2) + a2)
    vis = 0.5 / (lv + ll).clamp_min(1e-12)
    f0 = 0.04 * (1 - m) + a * m
    F = f0[None] + (1 - f0[None]) * ((1 - vdh) ** 5)[:, None]
    spec = (D * vis)[:, None] * F
    diff = (a * (1 - m) / math.pi)[None].expand(DIRS.shape[0], 3)
    total = ((diff + spec) * L * ndl[:, None]).sum(0) * DW
    diffuse = (diff * L * ndl[:, None]).sum(0) * DW
    return total, diffuse


@pytest.fixture(scope="module")
def sh_light():
    g = torch.Generator().manual_seed(0)
    sh = torch.zeros(9, 3, dtype=torch.float64)
    sh[0] = 1.5 / 0.282095
    sh[1:4] = torch.randn(3, 3, generator=g, dtype=torch.float64) * 0.5
    sh[4:] = torch.randn(5, 3, generator=g, dtype=torch.float64) * 0.25
    return sh


@pytest.mark.parametrize("rough", [0.25, 0.5, 0.75, 1.0])
@pytest.mark.parametrize("metal", [0.0, 1.0])
@pytest.mark.parametrize("angle", [0, 45, 70])
def test_shading_matches_numeric_integration(sh_light, rough, metal, angle):
    t = math.radians(angle)
    n = torch.tensor([0.0, 0, 1], dtype=torch.float64)
    v = torch.tensor([math.sin(t), 0, math.cos(t)], dtype=torch.float64)
    a = torch.tensor([0.8, 0.5, 0.3], dtype=torch.float64)
    ref, ref_d = _reference(a, rough, metal, n, v, sh_light)
    ours = shade_pbr(a, torch.tensor(rough, dtype=torch.float64), torch.tensor(metal, dtype=torch.float64), n, v,
                     sh_light)
    assert float(((ours.colour - ref).abs() / ref.abs()).max()) < 0.03
    if metal == 0.0:
        assert torch.allclose(ours.diffuse, ref_d, rtol=1e-6)
    else:
        assert float(ours.diffuse.abs().max()) == 0.0


def test_lambertian_constant_light():
    sh = torch.zeros(9, 3)
    sh[0] = 1.0 / 0.282095  # radiance 1 everywhere: E = π, a E / π = a
    out = shade_pbr(torch.full((5, 3), 0.4), torch.ones(5), torch.zeros(5), torch.nn.functional.normalize(torch.randn(5, 3), dim=-1),
                    torch.tensor([[0.0, 0, 1]]).expand(5, 3), sh, ShadingConfig(specular=False))
    assert torch.allclose(out.colour, torch.full((5, 3), 0.4), atol=1e-5)


def test_band_table_matches_quadrature():
    th = torch.linspace(0, math.pi / 2, 200001, dtype=torch.float64)
    mu = torch.cos(th)
    for i in (0, 5, 16, 27, 32):
        r = i / 32
        a = max(r * r, 1e-4)
        a2 = a * a
        D = a2 / (math.pi * ((torch.cos(th / 2) ** 2) * (a2 - 1) + 1) ** 2)
        p = D * mu * torch.sin(th)
        z = torch.trapz(p, th)
        assert abs(float(torch.trapz(p * mu, th) / z) - SPEC_BAND_G1[i]) < 2e-4
        assert abs(float(torch.trapz(p * (3 * mu * mu - 1) / 2, th) / z) - SPEC_BAND_G2[i]) < 2e-4
    g = specular_band_attenuation(torch.tensor([0.0, 1.0]))
    assert torch.allclose(g[1], torch.tensor([1, 2 / 3, 2 / 3, 2 / 3, 0.25, 0.25, 0.25, 0.25, 0.25]), atol=1e-4)
    assert torch.allclose(g[0], torch.ones(9))


def test_dfg_table_properties():
    t = dfg_table()
    assert t.shape == (32, 32, 2)
    assert bool(((t[..., 0] + t[..., 1]) <= 1.0 + 1e-3).all())  # energy: F0 = 1 reflects at most everything
    A, B = env_brdf(torch.tensor(0.0), torch.tensor(1.0))
    assert abs(float(A) - 1.0) < 0.02 and abs(float(B)) < 0.01  # a mirror at normal incidence reflects F0


def test_shading_gradcheck():
    torch.manual_seed(0)
    a = torch.rand(4, 3, dtype=torch.float64, requires_grad=True)
    r = (torch.rand(4, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    m = torch.rand(4, dtype=torch.float64, requires_grad=True)
    n = torch.nn.functional.normalize(torch.randn(4, 3, dtype=torch.float64) + torch.tensor([0, 0, 2.0], dtype=torch.float64), dim=-1)
    v = torch.tensor([[0.0, 0, 1]], dtype=torch.float64).expand(4, 3)
    sh = (torch.randn(9, 3, dtype=torch.float64) * 0.1).requires_grad_()
    with torch.no_grad():
        sh[0] += 3.0
    assert torch.autograd.gradcheck(lambda a, r, m, sh: shade_pbr(a, r, m, n, v, sh).colour, (a, r, m, sh))


def test_gradients_finite_at_saturated_roughness():
    """A sigmoid roughness saturates at exactly 0 or 1 in float32; the shading's gradient must stay finite there
    (√(1 − a) at a = 1 once made it NaN and stopped a Lego run at step 132)."""
    logits = torch.tensor([-200.0, 40.0, 0.0], requires_grad=True)
    r = torch.sigmoid(logits)
    assert float(r[1].detach()) == 1.0 and float(r[0].detach()) == 0.0
    n = torch.nn.functional.normalize(torch.tensor([[0.2, 0.1, 1.0]] * 3), dim=-1)
    v = torch.tensor([[0.0, 0.0, 1.0]] * 3)
    sh = torch.zeros(9, 3)
    sh[0] = 2.0
    sh[2] = 0.5
    shade_pbr(torch.full((3, 3), 0.5), r, torch.full((3,), 0.3), n, v, sh).colour.sum().backward()
    assert torch.isfinite(logits.grad).all(), logits.grad
