"""Stage 9 — PBR shading under SH lighting (paper eq. 19; SPEC stage 9). One definition, used by training,
rendering, the ONNX field and (mirrored in GLSL, held together by a test) the moderngl viewer.

    c = a (1 - m) E(n) / π  +  (F0 · A + B) · L_spec(r)

* ``E(n)``: irradiance of the SH radiance (Ramamoorthi–Hanrahan bands π, 2π/3, π/4), exact for an order-2
  SH environment.
* ``F0 = mix(0.04, a, m)`` (metallic workflow).
* ``L_spec(r)``: the SH radiance at the specular dominant direction ``r = normalise(lerp(n, r_mirror, s))``,
  ``r_mirror = 2 (n·v) n − v``, ``s = (1 − α)(√(1 − α) + α)`` (Lagarde & de Rousiers 2014, Frostbite: rough lobes
  lean toward the normal), band-attenuated by the
  roughness: band ``l`` is scaled by ``g_l``, the zonal (Legendre) moment of the split-sum prefiltering lobe
  ``p(l) ∝ D_GGX(h) (n·l)`` with ``n = v = r`` and ``α = roughness²`` (Karis 2013 prefiltering; glTF/Disney
  roughness remap). ``g_1, g_2`` are tabulated at 33 roughness values (:data:`SPEC_BAND_G1`, ``_G2``;
  ``tests/test_shading.py`` recomputes them by quadrature) and interpolated linearly; ``g_0 = 1``.
  Roughness 1 gives the Lambertian bands (2/3, 1/4), roughness 0 the unfiltered radiance.
* ``A, B``: split-sum DFG terms of our specular BRDF (GGX D, height-correlated Smith visibility, Schlick
  Fresnel), so ``F0·A + B = ∫ f_spec (n·l) dl`` for a constant environment; a 32 x 32 table over roughness and
  n·v (:func:`dfg_table`), interpolated bilinearly.

Directions: ``normals`` unit world normals; ``view_dirs`` unit vectors from the surface *toward the camera*
(= −ray direction). Radiance values are linear. Everything is plain arithmetic (ONNX-exportable).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from .sh import SH_BAND_OF_K, SH_IRRADIANCE_BANDS, sh_basis

__all__ = ["ShadingConfig", "Shading", "shade_pbr", "specular_band_attenuation", "env_brdf", "dfg_table",
           "DIELECTRIC_F0", "SPEC_BAND_G1", "SPEC_BAND_G2"]

DIELECTRIC_F0 = 0.04

SPEC_BAND_G1 = (1.00000, 0.99998, 0.99974, 0.99895, 0.99724, 0.99429, 0.98987, 0.98382, 0.97609, 0.96671, 0.95576,
                0.94339, 0.92979, 0.91516, 0.89973, 0.88374, 0.86740, 0.85091, 0.83449, 0.81829, 0.80247, 0.78716,
                0.77245, 0.75842, 0.74513, 0.73262, 0.72090, 0.70998, 0.69985, 0.69048, 0.68186, 0.67393, 0.66667)
"""g_1 at roughness i/32, i = 0..32 (band-1 attenuation of the specular prefiltering lobe)."""
SPEC_BAND_G2 = (1.00000, 0.99994, 0.99925, 0.99697, 0.99208, 0.98375, 0.97140, 0.95473, 0.93374, 0.90863, 0.87980,
                0.84780, 0.81325, 0.77679, 0.73909, 0.70077, 0.66241, 0.62450, 0.58748, 0.55171, 0.51746, 0.48493,
                0.45427, 0.42556, 0.39882, 0.37406, 0.35123, 0.33027, 0.31108, 0.29356, 0.27762, 0.26314, 0.25000)
"""g_2 at roughness i/32, i = 0..32."""


@dataclass(frozen=True)
class ShadingConfig:
    """Options of :func:`shade_pbr`."""

    dielectric_f0: float = DIELECTRIC_F0
    """Normal-incidence reflectance of non-metals."""
    clamp_negative_light: bool = True
    """Clamp SH radiance and irradiance at 0 (an order-2 fit can ring below zero)."""
    specular: bool = True
    """Include the specular lobe (False: Lambertian only)."""


@dataclass(frozen=True)
class Shading:
    """Result of :func:`shade_pbr`; every field float [..., 3] linear radiance."""

    colour: torch.Tensor
    diffuse: torch.Tensor
    specular: torch.Tensor


def specular_band_attenuation(roughness: torch.Tensor) -> torch.Tensor:
    """Per-coefficient SH attenuation of the specular lobe.

    Args:
        roughness: float [...] perceptual roughness in [0, 1].

    Returns:
        float [..., 9] factors ``g_l`` for the 9 coefficients (SPEC order).
    """
    n = len(SPEC_BAND_G1) - 1
    x = roughness.clamp(0.0, 1.0) * n
    i0 = x.floor().clamp(max=n - 1)
    f = x - i0
    i0 = i0.long()
    t1 = torch.tensor(SPEC_BAND_G1, dtype=roughness.dtype, device=roughness.device)
    t2 = torch.tensor(SPEC_BAND_G2, dtype=roughness.dtype, device=roughness.device)
    g1 = t1[i0] * (1 - f) + t1[i0 + 1] * f
    g2 = t2[i0] * (1 - f) + t2[i0 + 1] * f
    g0 = torch.ones_like(g1)
    return torch.stack([g0, g1, g1, g1, g2, g2, g2, g2, g2], -1)


DFG_SIZE = 32
"""Resolution of the DFG table (roughness x n·v)."""


@functools.lru_cache(maxsize=4)
def _dfg_table(size: int = DFG_SIZE, samples: int = 4096) -> torch.Tensor:
    """float64 [size, size, 2] (A, B) over roughness (rows, i/(size-1)) and n·v (cols, (j+0.5)/size)."""
    i = torch.arange(samples, dtype=torch.float64)
    # Hammersley points: (i/N, radical inverse of i)
    bits = i.long()
    rev = torch.zeros_like(i)
    scale = 0.5
    for _ in range(16):
        rev = rev + (bits & 1).double() * scale
        bits = bits >> 1
        scale *= 0.5
    u1, u2 = (i + 0.5) / samples, rev
    rough = torch.linspace(0.0, 1.0, size, dtype=torch.float64).clamp_min(1.0 / 64)
    ndv = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    a = (rough ** 2)[:, None, None]  # alpha
    a2 = a * a
    cos_h = torch.sqrt((1 - u1) / (1 + (a2 - 1) * u1))  # GGX importance sample of h around n
    sin_h = torch.sqrt((1 - cos_h * cos_h).clamp_min(0))
    phi = 2 * math.pi * u2
    hx, hy, hz = sin_h * torch.cos(phi), sin_h * torch.sin(phi), cos_h
    vx, vz = torch.sqrt(1 - ndv * ndv)[None, :, None], ndv[None, :, None]
    vdh = (vx * hx + vz * hz).clamp_min(0)
    lz = 2 * vdh * hz - vz
    ndl = lz.clamp_min(0)
    nv = vz
    lam_v = ndl * torch.sqrt(nv * nv * (1 - a2) + a2)
    lam_l = nv * torch.sqrt(ndl * ndl * (1 - a2) + a2)
    vis = 0.5 / (lam_v + lam_l).clamp_min(1e-12)
    g_vis = torch.where(lz > 0, vis * 4 * ndl * vdh / hz.clamp_min(1e-12), torch.zeros_like(lz))
    fc = (1 - vdh) ** 5
    A = ((1 - fc) * g_vis).mean(-1)
    B = (fc * g_vis).mean(-1)
    return torch.stack([A, B], -1)


def dfg_table() -> torch.Tensor:
    """float32 [32, 32, 2]: split-sum DFG terms (A, B) of our specular BRDF — GGX D, height-correlated Smith
    visibility, Schlick Fresnel — for roughness i/31 (rows) and n·v = (j+0.5)/32 (columns). Computed once by
    GGX importance sampling (4096 Hammersley samples per entry); the viewers upload the same table."""
    return _dfg_table().float()


def env_brdf(roughness: torch.Tensor, n_dot_v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split-sum DFG terms (A, B) so that ∫ f_spec (n·l) dl = F0·A + B (bilinear lookup in :func:`dfg_table`).

    Args:
        roughness: float [...] perceptual roughness in [0, 1].
        n_dot_v: float [...] cosine between normal and view direction, in (0, 1].

    Returns:
        (A, B) float [...] each.
    """
    table = _dfg_table().to(dtype=roughness.dtype, device=roughness.device)
    n = table.shape[0]
    x = roughness.clamp(0.0, 1.0) * (n - 1)
    y = (n_dot_v.clamp(0.0, 1.0) * n - 0.5).clamp(0.0, n - 1)
    x0 = x.floor().clamp(max=n - 2)
    y0 = y.floor().clamp(max=n - 2)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0, y0 = x0.long(), y0.long()
    v = (table[x0, y0] * (1 - fx) * (1 - fy) + table[x0 + 1, y0] * fx * (1 - fy)
         + table[x0, y0 + 1] * (1 - fx) * fy + table[x0 + 1, y0 + 1] * fx * fy)
    return v[..., 0], v[..., 1]


def _sh_light(y: torch.Tensor, sh: torch.Tensor) -> torch.Tensor:
    """Σ_k y[..., j, k] · sh[..., k, c]: SH weights y [..., J, 9] against radiance coefficients sh [..., 9, 3]
    (or [9, 3]) -> [..., J, 3]. One batched product: per sample on the CPU ~1.3x faster forward and backward than
    J broadcast multiply-and-sums over [..., 9, 3] (``bench/bench_step.py`` swaps this for that reference)."""
    return y @ sh


def shade_pbr(
    albedo: torch.Tensor,
    roughness: torch.Tensor,
    metallic: torch.Tensor,
    normals: torch.Tensor,
    view_dirs: torch.Tensor,
    sh: torch.Tensor,
    cfg: ShadingConfig = ShadingConfig(),
) -> Shading:
    """Shade surface points with the metallic-roughness BRDF under SH lighting (module docstring).

    Args:
        albedo: float [..., 3] linear base colour in [0, 1].
        roughness: float [...] perceptual roughness in [0, 1].
        metallic: float [...] metalness in [0, 1].
        normals: float [..., 3] unit world normals.
        view_dirs: float [..., 3] unit directions from the surface toward the camera.
        sh: float [..., 9, 3] (or [9, 3]) SH radiance coefficients of the incident light (SPEC convention).
        cfg: options.

    Returns:
        :class:`Shading` with ``colour = diffuse + specular``.

    Example:
        >>> sh = torch.zeros(9, 3); sh[0] = 1 / 0.282095  # constant radiance 1
        >>> shade_pbr(torch.ones(3) * 0.5, torch.tensor(1.0), torch.tensor(0.0), torch.tensor([0., 0, 1]),
        ...           torch.tensor([0., 0, 1]), sh, ShadingConfig(specular=False)).colour  # a·E/π = 0.5
        tensor([0.5000, 0.5000, 0.5000])
    """
    band_w = torch.tensor([SH_IRRADIANCE_BANDS[b] for b in SH_BAND_OF_K], dtype=albedo.dtype, device=albedo.device)
    y = sh_basis(normals) * band_w  # [..., 9]: the irradiance weights of the normal
    if cfg.specular:
        n_dot_v_raw = (normals * view_dirs).sum(-1, keepdim=True)
        reflected = 2.0 * n_dot_v_raw * normals - view_dirs
        a = roughness[..., None].clamp(0.0, 1.0) ** 2
        # clamped under the root: roughness = sigmoid saturates at exactly 1.0 in float32, where d√(1−a)/da is
        # infinite and 0·∞ would make the gradient NaN (the value is the same)
        lerp = (1.0 - a) * (torch.sqrt((1.0 - a).clamp_min(1e-12)) + a)
        reflected = torch.nn.functional.normalize(normals + lerp * (reflected - normals), dim=-1, eps=1e-8)
        y = torch.stack([y, sh_basis(reflected) * specular_band_attenuation(roughness)], -2)  # [..., 2, 9]
    else:
        y = y[..., None, :]  # [..., 1, 9]
    light = _sh_light(y, sh)  # [..., J, 3]: irradiance (and the reflection's radiance)
    if cfg.clamp_negative_light:
        light = light.clamp_min(0.0)
    m = metallic[..., None]
    diffuse = albedo * (1.0 - m) * light[..., 0, :] / torch.pi
    if not cfg.specular:
        return Shading(diffuse, diffuse, torch.zeros_like(diffuse))
    radiance = light[..., 1, :]
    n_dot_v = n_dot_v_raw.squeeze(-1).clamp(1e-4, 1.0)
    A, B = env_brdf(roughness, n_dot_v)
    f0 = cfg.dielectric_f0 * (1.0 - m) + albedo * m
    specular = (f0 * A[..., None] + B[..., None]) * radiance
    return Shading(diffuse + specular, diffuse, specular)
