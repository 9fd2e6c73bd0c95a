"""Real spherical harmonics of order 2: basis, evaluation, irradiance, rotation, probe fitting, conversions.

Conventions (``SPEC.md``, "SH"):

* 9 real SH per colour channel in the order (0,0) (1,-1) (1,0) (1,1) (2,-2) (2,-1) (2,0) (2,1) (2,2) with basis
  ``0.282095, 0.488603·(y, z, x), 1.092548·xy, 1.092548·yz, 0.315392·(3z²−1), 1.092548·xz, 0.546274·(x²−y²)``
  (the constants are computed in full precision, ``sqrt(1/4π)`` etc., and round to SPEC's 6 digits). There is no
  Condon–Shortley sign: every constant is positive.
* Coefficients ``[..., 9, 3]`` describe incident radiance ``L(ω)``, ``ω`` pointing from the surface toward the light, in
  world coordinates (+z up); flattened to 27 they are coefficient-major (L00 rgb, L1-1 rgb, ...).
* Irradiance ``E(n) = Σ Â_l L_lm Y_lm(n)``, ``Â = (π, 2π/3, π/4)`` (Ramamoorthi & Hanrahan 2001).
* Lat-long maps: row 0 looks at +z, ``ω = (sinθ sinφ, sinθ cosφ, cosθ)``, ``θ = π(row+½)/H``, ``φ = 2π(col+½)/W``
  (column 0 faces +y, φ grows toward +x).
* Angular light-probe maps (Debevec's angular map): a square image whose inscribed disc covers the sphere; the centre
  looks along the probe's −z (away from the camera), image right is the probe's +x, image up its +y, and the radius
  ``r ∈ [0, 1]`` maps linearly to the angle ``πr`` from −z. A probe is captured with +y up: rotate it into the
  +z-up world with ``rotation=probe_to_world_rotation()`` (the caller decides; nothing is rotated implicitly).

Quadrature: ``coeffs = Σ_p L_p ∫_pixel Y(ω) dΩ`` — each pixel is taken as constant radiance over its footprint and the
basis is integrated over that footprint (analytically for lat-long maps, by sub-pixel quadrature with the analytic
Jacobian for angular maps). A constant map is therefore projected exactly, and the per-pixel solid angles sum to 4π.
``ShFitConfig(quadrature="midpoint")`` gives the textbook ``Σ L(ω_p) Y(ω_p) dΩ_p`` instead.

Exporter conventions (converted at the boundary, tested in ``tests/test_sh.py``):

* three.js ``LightProbe`` / ``SphericalHarmonics3`` (``src/math/SphericalHarmonics3.js``): the same basis, constants
  and order as ours; coefficients are *radiance* (``getAt`` evaluates ``Σ c_k Y_k``; the shader's
  ``shGetIrradianceAt`` applies the Â_l factors itself, e.g. ``0.886227 = π·0.282095``; ``LightProbeGenerator``
  projects radiance with these basis functions). three.js is +y up, so directions map as
  ``(x, y, z)_ours → (x, z, −y)_three`` (three's y is our z) and the coefficients are rotated accordingly.
* glTF ``EXT_lights_image_based`` (``irradianceCoefficients``): the extension README only says "spherical harmonic
  coefficients for irradiance up to l=2"; its reference loader (Babylon.js ``EXT_lights_image_based.ts``) feeds them
  to ``SphericalHarmonics`` exactly where Babylon's own cube-map path has applied ``convertIncidentRadianceToIrradiance``
  (E_lm = Â_l L_lm) and before ``convertIrradianceToLambertianRadiance`` (÷π). Babylon's basis
  (``sphericalPolynomial.ts``) carries the Condon–Shortley sign: the (1,−1), (1,1), (2,−1), (2,1) constants are
  negative. So ``irradianceCoefficients = s_k · Â_l · L'_k`` with ``s = (+,−,+,−,+,−,+,−,+)`` and ``L'`` our
  coefficients rotated into glTF's +y-up right-handed frame with the same map as three.js (``(x, z, −y)``, the
  Blender/glTF exporter convention). Evaluating ``Σ irradianceCoefficients_k · Y^Babylon_k(n_gltf)`` gives ``E(n)``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from ._checks import ConfigError, DarsError, SceneError, check_finite, check_shape

__all__ = [
    "check_sh_coeffs",
    "read_sh_json",
    "SH_C0",
    "SH_C1",
    "SH_C2",
    "SH_C3",
    "SH_C4",
    "SH_IRRADIANCE_BANDS",
    "SH_BAND_OF_K",
    "ShFitConfig",
    "ShProbe",
    "sh_basis",
    "eval_sh",
    "irradiance_sh",
    "rotate_sh",
    "sh_rotation_matrix",
    "rotation_x",
    "rotation_z",
    "probe_to_world_rotation",
    "latlong_directions",
    "latlong_solid_angles",
    "lookup_latlong",
    "latlong_angles",
    "angular_directions",
    "angular_solid_angles",
    "fit_sh_probe",
    "render_sh_envmap",
    "render_irradiance_envmap",
    "read_envmap",
    "sh_to_threejs_lightprobe",
    "sh_to_gltf_ibl",
    "WORLD_TO_Y_UP",
    "GLTF_SH_SIGNS",
]

SH_C0 = 0.5 * math.sqrt(1.0 / math.pi)  # 0.282095
SH_C1 = math.sqrt(3.0 / (4.0 * math.pi))  # 0.488603
SH_C2 = math.sqrt(15.0 / (4.0 * math.pi))  # 1.092548
SH_C3 = math.sqrt(5.0 / (16.0 * math.pi))  # 0.315392
SH_C4 = math.sqrt(15.0 / (16.0 * math.pi))  # 0.546274

SH_IRRADIANCE_BANDS = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)
"""Â_l for l = 0, 1, 2: the clamped-cosine kernel in SH (Ramamoorthi & Hanrahan 2001, eq. 8)."""

SH_BAND_OF_K = (0, 1, 1, 1, 2, 2, 2, 2, 2)
"""The band l of each of the 9 coefficients, in SPEC order (for per-band factors such as ``SH_IRRADIANCE_BANDS``)."""

WORLD_TO_Y_UP = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))
"""Rotation taking our +z-up world directions to three.js / glTF +y-up ones: ``(x, y, z) → (x, z, −y)``."""

GLTF_SH_SIGNS = (1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0)
"""Sign of Babylon's (glTF ``EXT_lights_image_based``) basis relative to ours, per coefficient (Condon–Shortley)."""


# ----------------------------------------------------------------------------------------------------------- basis
def sh_basis(directions: torch.Tensor) -> torch.Tensor:
    """Evaluate the 9 real SH basis functions (SPEC order) at unit directions.

    Plain arithmetic only (ONNX-traceable, differentiable); device and dtype follow ``directions``.

    Args:
        directions: float [..., 3] unit vectors (x, y, z), world frame.

    Returns:
        float [..., 9] basis values ``Y_k(ω)``.

    Raises:
        ShapeError: if the last dimension is not 3.

    Example:
        >>> sh_basis(torch.tensor([0.0, 0.0, 1.0]))[2]  # 0.488603 * z
        tensor(0.4886)
    """
    if not torch.jit.is_tracing():
        check_shape(directions, "... 3", name="directions")
    x = directions[..., 0]
    y = directions[..., 1]
    z = directions[..., 2]
    return torch.stack(
        [
            torch.ones_like(x) * SH_C0,
            SH_C1 * y,
            SH_C1 * z,
            SH_C1 * x,
            SH_C2 * x * y,
            SH_C2 * y * z,
            SH_C3 * (3.0 * z * z - 1.0),
            SH_C2 * x * z,
            SH_C4 * (x * x - y * y),
        ],
        dim=-1,
    )


def _as_coeffs(coeffs: torch.Tensor | np.ndarray, name: str = "coeffs") -> torch.Tensor:
    if not isinstance(coeffs, torch.Tensor):
        coeffs = torch.as_tensor(np.asarray(coeffs, dtype=np.float64))
    if torch.jit.is_tracing():
        return coeffs
    if coeffs.dim() == 1 and coeffs.shape[0] == 27:
        coeffs = coeffs.reshape(9, 3)
    check_shape(coeffs, "... 9 3", name=name)
    return coeffs


def eval_sh(coeffs: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Radiance ``L(ω) = Σ_k c_k Y_k(ω)`` of an SH environment.

    Args:
        coeffs: float [..., 9, 3] radiance coefficients (broadcast against ``directions``; ``[9, 3]`` is common).
        directions: float [..., 3] unit directions toward the light, world frame.

    Returns:
        float [..., 3] linear RGB radiance (not clamped: an order-2 fit can ring below zero).
    """
    coeffs = _as_coeffs(coeffs)
    basis = sh_basis(directions).to(coeffs.dtype)
    return (basis.unsqueeze(-1) * coeffs).sum(dim=-2)


def _band_scale(ref: torch.Tensor, bands: tuple[float, float, float]) -> torch.Tensor:
    return torch.tensor([bands[b] for b in SH_BAND_OF_K], dtype=ref.dtype, device=ref.device).unsqueeze(-1)


def irradiance_sh(coeffs: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Irradiance ``E(n) = Σ Â_l L_lm Y_lm(n)`` from radiance coefficients (Ramamoorthi & Hanrahan 2001).

    A Lambertian surface of albedo ``a`` reflects ``a·E(n)/π``.

    Args:
        coeffs: float [..., 9, 3] radiance coefficients.
        normals: float [..., 3] unit surface normals, world frame.

    Returns:
        float [..., 3] irradiance (W/m² per unit radiance scale); a constant radiance ``c`` gives ``π·c``.
    """
    coeffs = _as_coeffs(coeffs)
    return eval_sh(coeffs * _band_scale(coeffs, SH_IRRADIANCE_BANDS), normals)


# -------------------------------------------------------------------------------------------------------- rotation
_PERM_YZX = ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))  # (x, y, z) -> (y, z, x), the band-1 order


def _fibonacci_directions(n: int) -> np.ndarray:
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    s = np.sqrt(1.0 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)


def _check_rotation(rotation: torch.Tensor | np.ndarray, name: str = "rotation") -> torch.Tensor:
    rot = rotation if isinstance(rotation, torch.Tensor) else torch.as_tensor(np.asarray(rotation, dtype=np.float64))
    check_shape(rot, "3 3", name=name)
    r64 = rot.detach().to("cpu", torch.float64)
    err = float((r64.T @ r64 - torch.eye(3, dtype=torch.float64)).abs().max())
    det = float(torch.linalg.det(r64))
    if not math.isfinite(err) or err > 1e-4 or det < 0:
        raise DarsError(f"{name} must be a proper rotation (orthonormal, det +1); got max |RᵀR − I| = {err:.2e}, det = {det:.4f}")
    return rot


def sh_rotation_matrix(rotation: torch.Tensor | np.ndarray) -> torch.Tensor:
    """The 9x9 block-diagonal matrix ``M`` with ``rotate_sh(c, R) = M @ c``.

    Band 1 is the permuted rotation ``P R Pᵀ`` (``P`` reorders (x, y, z) to (y, z, x)); band 2 is solved exactly by
    least squares on 12 fixed, well-spread directions ``d_i``: ``M₂ = pinv(Y₂(R d_i)) Y₂(d_i)``, i.e. the unique
    5x5 matrix with ``Σ (M₂ c)_k Y_k(R d) = Σ c_k Y_k(d)`` (band 2 is rotation-invariant, 12 ≥ 5 directions).

    Args:
        rotation: float [3, 3] proper rotation (differentiable if a tensor).

    Returns:
        float [9, 9] on ``rotation``'s device (float64 if ``rotation`` is a numpy array).
    """
    rot = _check_rotation(rotation)
    dtype = rot.dtype if rot.dtype in (torch.float32, torch.float64) else torch.float64
    r = rot.to(torch.float64)
    perm = torch.tensor(_PERM_YZX, dtype=torch.float64, device=r.device)
    m1 = perm @ r @ perm.T
    dirs = torch.as_tensor(_fibonacci_directions(12), device=r.device)
    y_src = sh_basis(dirs)[:, 4:9]  # [12, 5]
    y_dst = sh_basis(dirs @ r.T)[:, 4:9]  # Y(R d_i)
    # c' must satisfy y_dst @ c' = y_src @ c for every c: c' = pinv(y_dst) @ y_src @ c = m2 @ c.
    m2 = torch.linalg.lstsq(y_dst, y_src).solution
    m = torch.zeros(9, 9, dtype=torch.float64, device=r.device)
    m[0, 0] = 1.0
    m[1:4, 1:4] = m1
    m[4:9, 4:9] = m2
    return m.to(dtype)


def rotate_sh(coeffs: torch.Tensor, rotation: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Rotate an SH environment: the result satisfies ``eval_sh(out, R d) == eval_sh(coeffs, d)``.

    Use it to move coefficients between frames: with ``R`` mapping frame-A directions to frame-B directions, coefficients
    expressed in A become coefficients expressed in B. Band energies ``Σ_m c_lm²`` are preserved.

    Args:
        coeffs: float [..., 9, 3] radiance coefficients.
        rotation: float [3, 3] proper rotation matrix ``R``.

    Returns:
        float [..., 9, 3], same dtype and device as ``coeffs``.

    Raises:
        DarsError: if ``rotation`` is not a proper rotation.
    """
    coeffs = _as_coeffs(coeffs)
    rot = rotation if isinstance(rotation, torch.Tensor) else torch.as_tensor(np.asarray(rotation, dtype=np.float64))
    m = sh_rotation_matrix(rot.to(coeffs.device)).to(coeffs.dtype)
    return torch.einsum("ij,...jc->...ic", m, coeffs)


def rotation_x(degrees: float, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Right-handed rotation by ``degrees`` about +x, float [3, 3] (``rotation_x(90)`` takes +y to +z)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=dtype)


def rotation_z(degrees: float, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Right-handed rotation by ``degrees`` about +z, float [3, 3] (``rotation_z(90)`` takes +x to +y)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)


def probe_to_world_rotation(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Rotation from a +y-up probe frame (angular maps, most captures) to the +z-up world: ``rotation_x(90)``.

    Probe +y (up) → world +z; probe −z (the angular map's centre, "forward") → world +y, which is lat-long column 0.
    """
    return rotation_x(90.0, dtype)


# ---------------------------------------------------------------------------------------------- map parametrisations
def latlong_directions(H: int, W: int, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Directions at the pixel centres of an H x W lat-long map (SPEC convention).

    Args:
        H: rows (row 0 looks at +z).
        W: columns (column 0 faces +y, φ grows toward +x).

    Returns:
        float [H, W, 3] unit vectors ``(sinθ sinφ, sinθ cosφ, cosθ)``, ``θ = π(row+½)/H``, ``φ = 2π(col+½)/W``.
    """
    theta = (torch.arange(H, dtype=torch.float64) + 0.5) * (math.pi / H)
    phi = (torch.arange(W, dtype=torch.float64) + 0.5) * (2.0 * math.pi / W)
    st, ct = torch.sin(theta)[:, None], torch.cos(theta)[:, None]
    d = torch.stack([st * torch.sin(phi)[None], st * torch.cos(phi)[None], ct.expand(H, W)], -1)
    return d.to(device=device, dtype=dtype)


def latlong_solid_angles(H: int, W: int, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Exact solid angle of every lat-long pixel, ``(2π/W)(cos θ_top − cos θ_bottom)``; they sum to 4π.

    Returns:
        float [H, W] steradians.
    """
    edges = torch.cos(torch.arange(H + 1, dtype=torch.float64) * (math.pi / H))
    band = (edges[:-1] - edges[1:]) * (2.0 * math.pi / W)
    return band[:, None].expand(H, W).to(device=device, dtype=dtype).contiguous()


def latlong_angles(directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(θ, φ) of unit directions [..., 3] in the SPEC lat-long convention: θ = acos(z) from +z in [0, π], φ =
    atan2(x, y) in [0, 2π) — row ``θ/π·H`` and column ``φ/(2π)·W`` of a map (:func:`lookup_latlong`)."""
    theta = torch.acos(torch.clamp(directions[..., 2], -1.0, 1.0))
    phi = torch.remainder(torch.atan2(directions[..., 0], directions[..., 1]), 2.0 * math.pi)
    return theta, phi


def lookup_latlong(envmap: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of a SPEC lat-long map in given directions (texel centres at ``θ = π(row+½)/H``,
    ``φ = 2π(col+½)/W``; rows clamp at the poles, columns wrap).

    Args:
        envmap: float [H, W, C] lat-long map.
        directions: float [..., 3] unit directions, world frame.

    Returns:
        float [..., C] on ``envmap``'s device and dtype.
    """
    dims = check_shape(envmap, "H W C", name="envmap")
    check_shape(directions, "... 3", name="directions")
    H, W = dims["H"], dims["W"]
    theta, phi = latlong_angles(directions.to(device=envmap.device, dtype=torch.float64))
    rf = torch.clamp(theta * (H / math.pi) - 0.5, 0.0, H - 1.0)
    cf = phi * (W / (2.0 * math.pi)) - 0.5
    r0 = torch.clamp(torch.floor(rf), 0, H - 1).long()
    r1 = torch.clamp(r0 + 1, max=H - 1)
    c0f = torch.floor(cf)
    wr = (rf - r0.to(rf.dtype))[..., None]
    wc = (cf - c0f)[..., None]
    c0 = torch.remainder(c0f.long(), W)
    c1 = torch.remainder(c0 + 1, W)
    img = envmap.to(torch.float64)
    top = img[r0, c0] * (1 - wc) + img[r0, c1] * wc
    bottom = img[r1, c0] * (1 - wc) + img[r1, c1] * wc
    return (top * (1 - wr) + bottom * wr).to(envmap.dtype)


def _latlong_basis_integrals(H: int, W: int) -> torch.Tensor:
    """``∫_pixel Y_k(ω) dΩ`` for every lat-long pixel, analytically, float64 [H, W, 9]."""
    u = torch.cos(torch.arange(H + 1, dtype=torch.float64) * (math.pi / H))  # cos θ at row edges (decreasing)
    u0, u1 = u[:-1], u[1:]
    s = lambda v: torch.sqrt(torch.clamp(1.0 - v * v, min=0.0))  # noqa: E731
    prim_s = lambda v: 0.5 * (v * s(v) + torch.asin(torch.clamp(v, -1.0, 1.0)))  # noqa: E731  ∫ sqrt(1-u²) du
    g0 = u0 - u1  # ∫ du
    gs = prim_s(u0) - prim_s(u1)  # ∫ sinθ du
    gu = 0.5 * (u0 * u0 - u1 * u1)  # ∫ cosθ du
    gss = (u0 - u0**3 / 3.0) - (u1 - u1**3 / 3.0)  # ∫ sin²θ du
    gsu = -(s(u0) ** 3) / 3.0 + (s(u1) ** 3) / 3.0  # ∫ sinθ cosθ du
    guu = (u0**3 - u1**3) / 3.0  # ∫ cos²θ du
    p = torch.arange(W + 1, dtype=torch.float64) * (2.0 * math.pi / W)
    p0, p1 = p[:-1], p[1:]
    q0 = p1 - p0
    qsin = torch.cos(p0) - torch.cos(p1)  # ∫ sinφ dφ
    qcos = torch.sin(p1) - torch.sin(p0)  # ∫ cosφ dφ
    qsc = 0.25 * (torch.cos(2 * p0) - torch.cos(2 * p1))  # ∫ sinφ cosφ dφ
    qc2 = 0.5 * (torch.sin(2 * p1) - torch.sin(2 * p0))  # ∫ cos 2φ dφ
    t = lambda a, b: a[:, None] * b[None, :]  # noqa: E731
    return torch.stack(
        [
            SH_C0 * t(g0, q0),
            SH_C1 * t(gs, qcos),  # y = sinθ cosφ
            SH_C1 * t(gu, q0),  # z
            SH_C1 * t(gs, qsin),  # x = sinθ sinφ
            SH_C2 * t(gss, qsc),  # xy
            SH_C2 * t(gsu, qcos),  # yz
            SH_C3 * t(3.0 * guu - g0, q0),  # 3z² − 1
            SH_C2 * t(gsu, qsin),  # xz
            -SH_C4 * t(gss, qc2),  # x² − y² = −sin²θ cos 2φ
        ],
        -1,
    )


def _angular_uv(N: int, offsets: tuple[float, float] = (0.5, 0.5)) -> tuple[torch.Tensor, torch.Tensor]:
    idx = torch.arange(N, dtype=torch.float64)
    u = (idx + offsets[0]) * (2.0 / N) - 1.0  # image right = +x
    v = 1.0 - (idx + offsets[1]) * (2.0 / N)  # image up = +y (row 0 at the top)
    return u[None, :].expand(N, N), v[:, None].expand(N, N)


def _angular_dirs_from_uv(u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    r = torch.sqrt(u * u + v * v)
    a = math.pi * r
    safe_r = torch.where(r > 0, r, torch.ones_like(r))
    sin_over_r = torch.where(r > 0, torch.sin(a) / safe_r, torch.full_like(r, math.pi))
    d = torch.stack([sin_over_r * u, sin_over_r * v, -torch.cos(a)], -1)
    inside = r <= 1.0
    jac = torch.where(inside, math.pi * sin_over_r, torch.zeros_like(r))  # dΩ/dA = π sin(πr)/r
    d = torch.where(inside[..., None], d, torch.zeros_like(d))
    return d, jac


def angular_directions(N: int, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Directions (probe frame: +y up, centre looks along −z) at the pixel centres of an N x N angular map.

    Returns:
        float [N, N, 3] unit vectors inside the disc ``r ≤ 1``; zero vectors for pixel centres outside it.
    """
    u, v = _angular_uv(N)
    d, _ = _angular_dirs_from_uv(u, v)
    return d.to(device=device, dtype=dtype)


def _angular_quadrature(N: int, subsamples: int, with_basis: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Per-pixel solid angles [N, N] and basis integrals [N, N, 9] by S x S sub-pixel quadrature (float64)."""
    area = (2.0 / N) ** 2 / subsamples**2
    omega = torch.zeros(N, N, dtype=torch.float64)
    basis = torch.zeros(N, N, 9, dtype=torch.float64) if with_basis else None
    for i in range(subsamples):
        for j in range(subsamples):
            u, v = _angular_uv(N, ((j + 0.5) / subsamples, (i + 0.5) / subsamples))
            d, jac = _angular_dirs_from_uv(u, v)
            w = jac * area
            omega += w
            if basis is not None:
                basis += sh_basis(d) * w[..., None]
    return omega, basis


def angular_solid_angles(
    N: int, subsamples: int = 8, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """Per-pixel solid angles of an N x N angular map.

    Each pixel is split into ``subsamples²`` sub-pixels weighted by the analytic Jacobian ``dΩ/dA = π sin(πr)/r``
    (``A`` the image area in units where the disc has radius 1); sub-pixels outside the disc weigh 0. The total is
    4π to ~1e-5 for N ≥ 64 with the default 8x8 sub-pixels (tested to 1e-3).

    Returns:
        float [N, N] steradians.
    """
    if subsamples < 1:
        raise ConfigError(f"subsamples={subsamples} must be >= 1")
    omega, _ = _angular_quadrature(N, subsamples, with_basis=False)
    return omega.to(device=device, dtype=dtype)


# ------------------------------------------------------------------------------------------------------ probe fitting
@dataclass(frozen=True)
class ShFitConfig:
    """Options of :func:`fit_sh_probe`."""

    quadrature: Literal["pixel", "midpoint"] = "pixel"
    """``pixel``: integrate the basis over each pixel's footprint (exact for piecewise-constant maps);
    ``midpoint``: ``Σ L(ω_p) Y(ω_p) dΩ_p`` at pixel centres with exact solid angles."""
    angular_subsamples: int = 4
    """Sub-pixels per axis for the angular-map quadrature (Jacobian and basis sampled at sub-pixel centres)."""


@dataclass(frozen=True)
class ShProbe:
    """Result of :func:`fit_sh_probe`."""

    coeffs: torch.Tensor
    """float [9, 3] radiance SH (SPEC convention), world frame after ``rotation``."""
    layout: str
    """``latlong`` or ``angular``."""
    source_shape: tuple[int, int]
    """(H, W) of the fitted map."""
    dc_irradiance: torch.Tensor
    """float [3] ``π · mean radiance``: irradiance on a surface that sees the whole sphere's average (band 0 only)."""

    def to_list(self) -> list[list[float]]:
        """Coefficients as 9 x [r, g, b] Python floats (the transforms-JSON ``"sh"`` form)."""
        return [[float(v) for v in row] for row in self.coeffs.detach().cpu().tolist()]


def fit_sh_probe(
    envmap: torch.Tensor | np.ndarray,
    layout: Literal["latlong", "angular"] = "latlong",
    rotation: torch.Tensor | np.ndarray | None = None,
    cfg: ShFitConfig = ShFitConfig(),
) -> ShProbe:
    """Project an HDR environment map onto order-2 real SH by solid-angle quadrature.

    Args:
        envmap: float [H, W, 3] linear radiance (a 4th channel is ignored). ``latlong``: SPEC lat-long map;
            ``angular``: N x N Debevec angular map (probe frame).
        layout: parametrisation of ``envmap``.
        rotation: optional float [3, 3] rotation taking map directions to world directions (for an angular probe
            captured +y up: :func:`probe_to_world_rotation`). ``None``: the map is already in the world frame.
        cfg: quadrature options.

    Returns:
        :class:`ShProbe` with float [9, 3] coefficients on ``envmap``'s device (float32 for numpy input, else
        ``envmap``'s floating dtype). Computed in float64.

    Raises:
        ShapeError: wrong shape (angular maps must be square).
        DarsError: non-finite values or a bad rotation.
        ConfigError: unknown layout or quadrature.

    Example:
        >>> probe = fit_sh_probe(torch.ones(64, 128, 3))
        >>> round(float(probe.coeffs[0, 0]), 4)  # sqrt(4π)
        3.5449
    """
    if layout not in ("latlong", "angular"):
        raise ConfigError(f"layout={layout!r} is not valid: choose 'latlong' or 'angular'")
    if cfg.quadrature not in ("pixel", "midpoint"):
        raise ConfigError(f"quadrature={cfg.quadrature!r} is not valid: choose 'pixel' or 'midpoint'")
    if isinstance(envmap, torch.Tensor):
        device = envmap.device
        out_dtype = envmap.dtype if envmap.is_floating_point() else torch.float32
        img = envmap.detach().to("cpu", torch.float64)
    else:
        device, out_dtype = torch.device("cpu"), torch.float32
        img = torch.as_tensor(np.asarray(envmap, dtype=np.float64))
    if img.dim() == 3 and img.shape[-1] == 4:
        img = img[..., :3]
    dims = check_shape(img, "H W 3", name="envmap")
    check_finite(img, "envmap")
    H, W = dims["H"], dims["W"]
    if layout == "latlong":
        if cfg.quadrature == "pixel":
            weights = _latlong_basis_integrals(H, W)
        else:
            weights = sh_basis(latlong_directions(H, W, dtype=torch.float64)) * latlong_solid_angles(H, W, dtype=torch.float64)[..., None]
    else:
        if H != W:
            raise DarsError(f"envmap: an angular map must be square, got {H} x {W}")
        if cfg.quadrature == "pixel":
            _, weights = _angular_quadrature(H, max(1, int(cfg.angular_subsamples)))
        else:
            u, v = _angular_uv(H)
            d, jac = _angular_dirs_from_uv(u, v)
            weights = sh_basis(d) * (jac * (2.0 / H) ** 2)[..., None]
    coeffs = torch.einsum("hwk,hwc->kc", weights, img)
    if rotation is not None:
        coeffs = rotate_sh(coeffs, _check_rotation(rotation).detach().to("cpu", torch.float64))
    coeffs = coeffs.to(device=device, dtype=out_dtype)
    return ShProbe(coeffs=coeffs, layout=layout, source_shape=(H, W), dc_irradiance=math.pi * SH_C0 * coeffs[0])


def render_sh_envmap(coeffs: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """Reconstruct the radiance of an SH environment as a SPEC lat-long map.

    Args:
        coeffs: float [9, 3] radiance coefficients.
        H, W: map size.

    Returns:
        float [H, W, 3] on ``coeffs``' device and dtype (not clamped).
    """
    coeffs = _as_coeffs(coeffs)
    return eval_sh(coeffs, latlong_directions(H, W, device=coeffs.device, dtype=coeffs.dtype))


def render_irradiance_envmap(coeffs: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """Irradiance ``E(n)`` for every lat-long direction ``n`` (a diffuse convolution of the environment).

    Returns:
        float [H, W, 3] on ``coeffs``' device and dtype.
    """
    coeffs = _as_coeffs(coeffs)
    return irradiance_sh(coeffs, latlong_directions(H, W, device=coeffs.device, dtype=coeffs.dtype))


def read_envmap(path: str | Path) -> np.ndarray:
    """Read an HDR environment map (``.hdr`` Radiance RGBE or ``.exr`` OpenEXR) as linear RGB.

    Returns:
        float32 [H, W, 3] (alpha dropped, grey replicated to RGB).

    Raises:
        SceneError: missing, unreadable or unsupported file, or non-finite values, naming the file.
    """
    from . import io as _io

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"environment map not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".hdr":
        img = _io.read_hdr(path)
    elif suffix == ".exr":
        img = _io.read_exr(path)
    else:
        raise SceneError(f"environment map {path}: unsupported format {suffix!r}; use a Radiance .hdr or OpenEXR .exr file")
    img = np.asarray(img, dtype=np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        raise SceneError(f"environment map {path}: expected H x W x 3 pixels, got shape {list(img.shape)}")
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    img = np.ascontiguousarray(img[..., :3])
    if not np.isfinite(img).all():
        raise SceneError(f"environment map {path} contains NaN or inf pixels")
    return img


# -------------------------------------------------------------------------------------------------------- conversions
def sh_to_threejs_lightprobe(coeffs: torch.Tensor | np.ndarray) -> list[float]:
    """Coefficients for three.js ``LightProbe`` / ``SphericalHarmonics3.fromArray`` (27 floats).

    three.js uses our basis, order and radiance meaning; only the frame differs (+y up): the coefficients are rotated
    by :data:`WORLD_TO_Y_UP`, so ``SphericalHarmonics3.getAt((x, z, −y))`` equals ``eval_sh(coeffs, (x, y, z))`` and
    its shader's ``shGetIrradianceAt`` equals :func:`irradiance_sh`.

    Args:
        coeffs: float [9, 3] (or 27) radiance coefficients, world frame.

    Returns:
        27 floats, coefficient-major (``new LightProbe(new SphericalHarmonics3().fromArray(list))``).
    """
    c = _as_coeffs(coeffs).detach().to("cpu", torch.float64)
    check_shape(c, "9 3", name="coeffs")
    out = rotate_sh(c, torch.tensor(WORLD_TO_Y_UP, dtype=torch.float64))
    return [float(v) for v in out.reshape(-1).tolist()]


def sh_to_gltf_ibl(coeffs: torch.Tensor | np.ndarray, intensity: float = 1.0) -> dict:
    """An ``EXT_lights_image_based`` light with ``irradianceCoefficients`` from our radiance SH.

    ``irradianceCoefficients[k] = s_k · Â_l · L'_k`` (see the module docstring: Babylon.js basis signs ``s``, Â band
    factors, ``L'`` rotated into glTF's +y-up frame by :data:`WORLD_TO_Y_UP`). The extension also requires
    ``specularImages`` and ``specularImageSize`` (a prefiltered cube map), which the asset exporter must add.

    Args:
        coeffs: float [9, 3] (or 27) radiance coefficients, world frame.
        intensity: the light's ``intensity`` field (brightness multiplier, applied by the loader).

    Returns:
        ``{"intensity": float, "rotation": [0, 0, 0, 1], "irradianceCoefficients": 9 x [r, g, b]}``.
    """
    c = _as_coeffs(coeffs).detach().to("cpu", torch.float64)
    check_shape(c, "9 3", name="coeffs")
    rotated = rotate_sh(c, torch.tensor(WORLD_TO_Y_UP, dtype=torch.float64))
    scale = torch.tensor([GLTF_SH_SIGNS[k] * SH_IRRADIANCE_BANDS[SH_BAND_OF_K[k]] for k in range(9)], dtype=torch.float64)
    irr = rotated * scale[:, None]
    return {
        "intensity": float(intensity),
        "rotation": [0.0, 0.0, 0.0, 1.0],
        "irradianceCoefficients": [[float(v) for v in row] for row in irr.tolist()],
    }


# ============================================================================ SH files
def check_sh_coeffs(c, where: str) -> np.ndarray:
    """SH coefficients as float64 [9, 3] (9 x [r, g, b], or 27 numbers coefficient-major).

    Raises:
        DarsError: another shape, or NaN / inf, naming ``where``.
    """
    c = np.asarray(c, dtype=np.float64)
    if c.shape == (27,):
        c = c.reshape(9, 3)
    if c.shape != (9, 3):
        raise DarsError(f"{where}: SH must be 9 x [r, g, b] (or 27 numbers), got shape {list(c.shape)}")
    if not np.isfinite(c).all():
        raise DarsError(f"{where}: SH contains NaN or inf")
    return c


def read_sh_json(path: str | Path) -> np.ndarray:
    """Read float64 [9, 3] SH coefficients from a JSON file: ``{"coeffs": 9 x [r, g, b]}`` (the output of
    ``dars priors sh-probe FILE --json``), ``{"sh": ...}`` (a transforms JSON), ``{"l_env": ...}``, or a bare
    9 x 3 / 27 list.

    Raises:
        SceneError: missing or unreadable file, or no coefficients in it, naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"SH JSON not found: {path}")
    try:
        obj = json.loads(path.read_text())
    except ValueError as e:
        raise SceneError(f"{path} is not valid JSON: {e}") from e
    if isinstance(obj, dict):
        for key in ("coeffs", "sh", "l_env"):
            if key in obj:
                obj = obj[key]
                break
        else:
            raise SceneError(f"{path}: no SH found; expected a 'coeffs' or 'sh' key (9 x [r, g, b]) "
                             "as written by `dars priors sh-probe FILE --json`")
    try:
        return check_sh_coeffs(obj, str(path))
    except (TypeError, ValueError) as e:
        raise SceneError(str(e) if str(path) in str(e) else f"{path}: {e}") from e
