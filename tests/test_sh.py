"""Tests of toolkit.sh: basis, fitting, irradiance, rotation, map parametrisations, exporters, I/O and the CLI."""

from __future__ import annotations

import json
import math
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import SHARED
from toolkit._checks import DarsError, SceneError, ShapeError
from toolkit.sh import (
    SH_IRRADIANCE_BANDS,
    ShFitConfig,
    _latlong_basis_integrals,
    angular_directions,
    angular_solid_angles,
    eval_sh,
    fit_sh_probe,
    irradiance_sh,
    latlong_directions,
    latlong_solid_angles,
    lookup_latlong,
    probe_to_world_rotation,
    read_envmap,
    render_irradiance_envmap,
    render_sh_envmap,
    rotate_sh,
    rotation_x,
    rotation_z,
    sh_basis,
    sh_to_gltf_ibl,
    sh_to_threejs_lightprobe,
)

ENVMAPS = SHARED / "envmaps"  # ../shared/data beside the clone, or $DARS_SHARED_DATA
PROBES = sorted(ENVMAPS.glob("*.hdr")) if ENVMAPS.is_dir() else []


def _random_coeffs(seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.randn(9, 3, generator=g, dtype=torch.float64) * 0.5
    c[0] += 2.0
    return c


def _random_dirs(n: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)


def _random_rotation(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# ----------------------------------------------------------------------------------------------------------- basis
def test_basis_matches_spec_constants():
    d = _random_dirs(50)
    x, y, z = d.unbind(-1)
    expected = torch.stack(
        [torch.full_like(x, 0.282095), 0.488603 * y, 0.488603 * z, 0.488603 * x, 1.092548 * x * y, 1.092548 * y * z,
         0.315392 * (3 * z * z - 1), 1.092548 * x * z, 0.546274 * (x * x - y * y)], -1)
    torch.testing.assert_close(sh_basis(d), expected, atol=2e-6, rtol=0)


def test_basis_shapes_dtype_device_and_errors():
    assert sh_basis(torch.zeros(2, 5, 3)).shape == (2, 5, 9)
    assert sh_basis(torch.zeros(3, dtype=torch.float64)).dtype == torch.float64
    assert eval_sh(torch.zeros(9, 3), torch.zeros(4, 7, 3)).shape == (4, 7, 3)
    assert eval_sh(torch.zeros(4, 1, 9, 3), torch.zeros(4, 7, 3)).shape == (4, 7, 3)
    with pytest.raises(ShapeError, match="directions"):
        sh_basis(torch.zeros(4, 2))
    with pytest.raises(ShapeError, match="coeffs"):
        eval_sh(torch.zeros(8, 3), torch.zeros(4, 3))


def test_eval_and_irradiance_gradcheck():
    c = _random_coeffs().requires_grad_(True)
    d = _random_dirs(6).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: eval_sh(a, b), (c, d))
    assert torch.autograd.gradcheck(lambda a, b: irradiance_sh(a, b), (c, d))


def test_eval_sh_onnx_export_matches_torch(tmp_path):
    ort = pytest.importorskip("onnxruntime")

    class Probe(torch.nn.Module):
        def forward(self, coeffs, directions):
            return irradiance_sh(coeffs, directions)

    c = _random_coeffs().float()
    path = tmp_path / "sh.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(Probe(), (c, _random_dirs(5).float()), str(path), dynamo=False, input_names=["coeffs", "directions"],
                          dynamic_axes={"directions": {0: "n"}})
    d = _random_dirs(33, seed=4).float()
    out = ort.InferenceSession(str(path)).run(None, {"coeffs": c.numpy(), "directions": d.numpy()})[0]
    np.testing.assert_allclose(out, irradiance_sh(c, d).numpy(), atol=1e-5)


# ------------------------------------------------------------------------------------------------ lat-long geometry
def test_latlong_directions_follow_spec():
    d = latlong_directions(64, 128, dtype=torch.float64)
    assert d.shape == (64, 128, 3)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(64, 128, dtype=torch.float64))
    assert d[0, :, 2].min() > 0.99 and d[-1, :, 2].max() < -0.99  # row 0 looks up
    mid = 32
    assert d[mid, 0, 1] > 0.99  # column 0 faces +y
    assert d[mid, 32, 0] > 0.99  # a quarter turn later: +x (φ grows toward +x)
    theta = math.pi * (10 + 0.5) / 64
    phi = 2 * math.pi * (7 + 0.5) / 128
    torch.testing.assert_close(d[10, 7], torch.tensor([math.sin(theta) * math.sin(phi), math.sin(theta) * math.cos(phi), math.cos(theta)], dtype=torch.float64))


def test_latlong_solid_angles_exact():
    w = latlong_solid_angles(256, 512, dtype=torch.float64)
    assert abs(float(w.sum()) - 4 * math.pi) < 1e-12
    theta0 = math.pi / 256
    assert abs(float(w[0, 0]) - 2 * math.pi / 512 * (1 - math.cos(theta0))) < 1e-15


def test_basis_orthonormal_under_quadrature():
    H, W = 256, 512
    Y = sh_basis(latlong_directions(H, W, dtype=torch.float64)).reshape(-1, 9)
    gram_pixel = _latlong_basis_integrals(H, W).reshape(-1, 9).T @ Y
    wmid = latlong_solid_angles(H, W, dtype=torch.float64).reshape(-1, 1)
    gram_mid = (Y * wmid).T @ Y
    for gram in (gram_pixel, gram_mid):
        torch.testing.assert_close(gram, torch.eye(9, dtype=torch.float64), atol=1e-3, rtol=0)
    # the pixel-integrated basis is exactly normalised on band 0 and exactly orthogonal to it
    integ = _latlong_basis_integrals(H, W).reshape(-1, 9).sum(0)
    assert abs(float(integ[0]) - math.sqrt(4 * math.pi)) < 1e-12
    assert float(integ[1:].abs().max()) < 1e-10


def test_lookup_latlong_at_pixel_centres_is_identity():
    m = torch.rand(16, 32, 3, dtype=torch.float64)
    torch.testing.assert_close(lookup_latlong(m, latlong_directions(16, 32, dtype=torch.float64)), m)


# ----------------------------------------------------------------------------------------------------------- fitting
def test_fit_recovers_known_coefficients_latlong():
    c = _random_coeffs()
    env = render_sh_envmap(c, 256, 512)
    for quad in ("pixel", "midpoint"):
        fitted = fit_sh_probe(env, cfg=ShFitConfig(quadrature=quad)).coeffs
        torch.testing.assert_close(fitted, c, atol=1e-3, rtol=0)


def test_fit_of_constant_map_is_exact():
    value = torch.tensor([0.5, 1.25, 3.0], dtype=torch.float64)
    probe = fit_sh_probe(value.expand(128, 256, 3).clone())
    torch.testing.assert_close(probe.coeffs[0], value * math.sqrt(4 * math.pi), atol=1e-12, rtol=1e-12)
    assert float(probe.coeffs[1:].abs().max()) < 1e-10
    torch.testing.assert_close(probe.dc_irradiance, math.pi * value)
    # irradiance of a constant environment c is π c in every direction
    e = irradiance_sh(probe.coeffs, _random_dirs(20))
    torch.testing.assert_close(e, (math.pi * value).expand(20, 3), atol=1e-9, rtol=0)


def test_fit_numpy_input_and_dtype():
    probe = fit_sh_probe(np.ones((32, 64, 3), np.float32))
    assert probe.coeffs.dtype == torch.float32 and probe.coeffs.shape == (9, 3)
    assert probe.source_shape == (32, 64) and probe.layout == "latlong"
    assert len(probe.to_list()) == 9 and len(probe.to_list()[0]) == 3
    assert fit_sh_probe(torch.ones(32, 64, 4, dtype=torch.float64)).coeffs.dtype == torch.float64  # alpha ignored


def test_fit_errors_name_the_problem():
    with pytest.raises(ShapeError, match="envmap"):
        fit_sh_probe(torch.ones(32, 64))
    bad = torch.ones(32, 64, 3)
    bad[3, 4, 1] = float("nan")
    with pytest.raises(DarsError, match="NaN"):
        fit_sh_probe(bad)
    with pytest.raises(DarsError, match="square"):
        fit_sh_probe(torch.ones(32, 64, 3), layout="angular")
    with pytest.raises(DarsError, match="layout"):
        fit_sh_probe(torch.ones(32, 64, 3), layout="cubemap")  # type: ignore[arg-type]
    with pytest.raises(DarsError, match="rotation"):
        fit_sh_probe(torch.ones(32, 64, 3), rotation=torch.eye(3) * 2)


def test_irradiance_matches_brute_force_cosine_integral():
    c = _random_coeffs(3)
    H, W = 256, 512
    dirs = latlong_directions(H, W, dtype=torch.float64).reshape(-1, 3)
    L = eval_sh(c, dirs)
    w = latlong_solid_angles(H, W, dtype=torch.float64).reshape(-1, 1)
    for n in _random_dirs(5, seed=9):
        brute = (L * w * torch.clamp(dirs @ n, min=0)[:, None]).sum(0)
        torch.testing.assert_close(irradiance_sh(c, n), brute, atol=2e-3 * float(brute.abs().max()), rtol=0)
    assert SH_IRRADIANCE_BANDS == pytest.approx((math.pi, 2 * math.pi / 3, math.pi / 4))


def test_render_envmaps():
    c = _random_coeffs()
    m = render_sh_envmap(c, 8, 16)
    e = render_irradiance_envmap(c, 8, 16)
    assert m.shape == e.shape == (8, 16, 3) and m.dtype == torch.float64
    torch.testing.assert_close(e, irradiance_sh(c, latlong_directions(8, 16, dtype=torch.float64)))


# ---------------------------------------------------------------------------------------------------------- rotation
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_rotation_matches_evaluation_and_preserves_band_energy(seed):
    c = _random_coeffs(seed)
    R = _random_rotation(seed + 10)
    rc = rotate_sh(c, R)
    d = _random_dirs(200, seed=seed)
    torch.testing.assert_close(eval_sh(rc, d @ R.T), eval_sh(c, d), atol=1e-5, rtol=0)
    for sl in (slice(0, 1), slice(1, 4), slice(4, 9)):
        torch.testing.assert_close((rc[sl] ** 2).sum(0), (c[sl] ** 2).sum(0), atol=1e-9, rtol=1e-9)


def test_rotation_composes_and_identity():
    c = _random_coeffs()
    R1, R2 = _random_rotation(1), _random_rotation(2)
    torch.testing.assert_close(rotate_sh(rotate_sh(c, R1), R2), rotate_sh(c, R2 @ R1), atol=1e-10, rtol=0)
    torch.testing.assert_close(rotate_sh(c, torch.eye(3, dtype=torch.float64)), c, atol=1e-12, rtol=0)
    torch.testing.assert_close(rotation_z(90) @ torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0, 1.0, 0], dtype=torch.float64))
    torch.testing.assert_close(rotation_x(90) @ torch.tensor([0, 1.0, 0], dtype=torch.float64), torch.tensor([0, 0, 1.0], dtype=torch.float64))
    with pytest.raises(DarsError, match="rotation"):
        rotate_sh(c, torch.diag(torch.tensor([1.0, 1.0, -1.0])))  # reflection


def test_fit_with_rotation_equals_rotated_fit():
    c = _random_coeffs(5)
    env = render_sh_envmap(c, 128, 256)
    R = rotation_z(30.0)
    torch.testing.assert_close(fit_sh_probe(env, rotation=R).coeffs, rotate_sh(fit_sh_probe(env).coeffs, R), atol=1e-10, rtol=0)


# ----------------------------------------------------------------------------------------------------- angular maps
def test_angular_geometry():
    N = 64
    d = angular_directions(N, dtype=torch.float64)
    assert d.shape == (N, N, 3)
    centre = d[N // 2 - 1 : N // 2 + 1, N // 2 - 1 : N // 2 + 1].mean((0, 1))
    assert centre[2] < -0.99  # the centre looks along −z
    assert d[N // 2, int(N * 0.75), 0] > 0.99  # half-way to the right rim: +x (90° from −z)
    assert d[N // 4, N // 2, 1] > 0.99  # half-way up: +y
    assert float(d[0, 0].norm()) == 0.0  # corner pixel is outside the disc
    inside = d.norm(dim=-1) > 0
    torch.testing.assert_close(d[inside].norm(dim=-1), torch.ones(int(inside.sum()), dtype=torch.float64))


@pytest.mark.parametrize("N", [64, 256])
def test_angular_solid_angles_sum_to_4pi(N):
    w = angular_solid_angles(N, dtype=torch.float64)
    assert abs(float(w.sum()) - 4 * math.pi) < 1e-3
    assert float(w[0, 0]) == 0.0 and float(w.min()) >= 0.0


def _smooth_env(d: torch.Tensor) -> torch.Tensor:
    """A smooth environment with content above order 2: a sky gradient plus a soft sun."""
    sun = torch.nn.functional.normalize(torch.tensor([0.4, -0.3, 0.8], dtype=torch.float64), dim=0)
    lobe = torch.exp(12.0 * (d @ sun - 1.0))[..., None]
    return 0.5 + 0.3 * d[..., 2:3] + torch.tensor([4.0, 3.5, 3.0], dtype=torch.float64) * lobe


def test_angular_fit_agrees_with_latlong_fit():
    ll = _smooth_env(latlong_directions(256, 512, dtype=torch.float64))
    ref = fit_sh_probe(ll).coeffs
    N = 512
    R = probe_to_world_rotation()
    world = angular_directions(N, dtype=torch.float64) @ R.T  # probe frame (+y up) → world (+z up)
    ang = _smooth_env(world)
    fitted = fit_sh_probe(ang, layout="angular", rotation=R).coeffs
    torch.testing.assert_close(fitted, ref, atol=2e-3 * float(ref[0].abs().max()), rtol=0)
    # without the rotation the probe is misread (up would point at −y in the world)
    assert float((fit_sh_probe(ang, layout="angular").coeffs - ref).abs().max()) > 0.05


# ------------------------------------------------------------------------------------------------------ conversions
def _threejs_get_at(sh27, n):
    """three.js SphericalHarmonics3.getAt, transcribed from src/math/SphericalHarmonics3.js."""
    c = np.asarray(sh27).reshape(9, 3)
    x, y, z = n
    return (c[0] * 0.282095 + c[1] * 0.488603 * y + c[2] * 0.488603 * z + c[3] * 0.488603 * x + c[4] * 1.092548 * (x * y)
            + c[5] * 1.092548 * (y * z) + c[6] * 0.315392 * (3.0 * z * z - 1.0) + c[7] * 1.092548 * (x * z) + c[8] * 0.546274 * (x * x - y * y))


def _threejs_irradiance_at(sh27, n):
    """three.js shGetIrradianceAt (lights_pars_begin.glsl) / SphericalHarmonics3.getIrradianceAt."""
    c = np.asarray(sh27).reshape(9, 3)
    x, y, z = n
    return (c[0] * 0.886227 + c[1] * 2.0 * 0.511664 * y + c[2] * 2.0 * 0.511664 * z + c[3] * 2.0 * 0.511664 * x
            + c[4] * 2.0 * 0.429043 * x * y + c[5] * 2.0 * 0.429043 * y * z + c[6] * (0.743125 * z * z - 0.247708)
            + c[7] * 2.0 * 0.429043 * x * z + c[8] * 0.429043 * (x * x - y * y))


def _ours_to_y_up(d):
    x, y, z = d
    return np.array([x, z, -y])


def test_threejs_lightprobe_evaluates_like_ours():
    c = _random_coeffs(7)
    sh27 = sh_to_threejs_lightprobe(c)
    assert len(sh27) == 27 and all(isinstance(v, float) for v in sh27)
    for d in _random_dirs(25, seed=3).numpy():
        np.testing.assert_allclose(_threejs_get_at(sh27, _ours_to_y_up(d)), eval_sh(c, torch.as_tensor(d)).numpy(), atol=1e-5)
        np.testing.assert_allclose(_threejs_irradiance_at(sh27, _ours_to_y_up(d)), irradiance_sh(c, torch.as_tensor(d)).numpy(), atol=2e-5)
    # light from our +z (up) is light from three's +y (up)
    up = torch.zeros(9, 3, dtype=torch.float64)
    up[0], up[2] = 1.0, 1.0
    probe = np.asarray(sh_to_threejs_lightprobe(up)).reshape(9, 3)
    assert probe[1, 0] > 0.99 and abs(probe[2, 0]) < 1e-9 and abs(probe[3, 0]) < 1e-9


def _babylon_basis(n):
    """Babylon.js SH3ylmBasisConstants x trigonometric terms (sphericalPolynomial.ts), Condon–Shortley signs."""
    x, y, z = n
    k = [math.sqrt(1 / (4 * math.pi)), -math.sqrt(3 / (4 * math.pi)), math.sqrt(3 / (4 * math.pi)), -math.sqrt(3 / (4 * math.pi)),
         math.sqrt(15 / (4 * math.pi)), -math.sqrt(15 / (4 * math.pi)), math.sqrt(5 / (16 * math.pi)), -math.sqrt(15 / (4 * math.pi)),
         math.sqrt(15 / (16 * math.pi))]
    t = [1.0, y, z, x, x * y, y * z, 3 * z * z - 1, x * z, x * x - y * y]
    return np.array([a * b for a, b in zip(k, t)])


def test_gltf_irradiance_coefficients_evaluate_to_irradiance():
    c = _random_coeffs(8)
    light = sh_to_gltf_ibl(c, intensity=2.0)
    assert light["intensity"] == 2.0 and light["rotation"] == [0.0, 0.0, 0.0, 1.0]
    irr = np.asarray(light["irradianceCoefficients"])
    assert irr.shape == (9, 3)
    for d in _random_dirs(25, seed=5).numpy():
        e = _babylon_basis(_ours_to_y_up(d)) @ irr
        np.testing.assert_allclose(e, irradiance_sh(c, torch.as_tensor(d)).numpy(), atol=1e-9)
    # DC: E00 = π L00 (irradiance, not radiance)
    const = torch.zeros(9, 3, dtype=torch.float64)
    const[0] = 1.0
    assert sh_to_gltf_ibl(const)["irradianceCoefficients"][0][0] == pytest.approx(math.pi)
    json.dumps(light)


# ---------------------------------------------------------------------------------------------------------------- I/O
@pytest.mark.skipif(not PROBES, reason=f"probulator probes not found under {ENVMAPS}")
@pytest.mark.parametrize("path", PROBES, ids=lambda p: p.name)
def test_probulator_probes_give_plausible_coefficients(path):
    img = read_envmap(path)
    assert img.dtype == np.float32 and img.ndim == 3 and img.shape[2] == 3 and img.shape[1] == 2 * img.shape[0]
    probe = fit_sh_probe(img)
    c = probe.coeffs.double()
    assert torch.isfinite(c).all()
    assert (c[0] > 0).all()
    # the DC term is the solid-angle-weighted mean radiance
    w = latlong_solid_angles(*img.shape[:2], dtype=torch.float64)
    mean = (torch.as_tensor(img, dtype=torch.float64) * w[..., None]).sum((0, 1)) / (4 * math.pi)
    torch.testing.assert_close(c[0] * 0.5 / math.sqrt(math.pi), mean, rtol=1e-5, atol=0)
    # for a non-negative function the band-1 vector is bounded by sqrt(3) L00
    assert (c[1:4].norm(dim=0) <= math.sqrt(3) * c[0] + 1e-9).all()
    assert (probe.dc_irradiance > 0).all() and float(probe.dc_irradiance.max()) < 1e5


def test_exr_round_trip(tmp_path):
    OpenEXR = pytest.importorskip("OpenEXR")
    img = render_sh_envmap(_random_coeffs(2), 32, 64).clamp_min(0).float().numpy()
    path = tmp_path / "probe.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"RGB": img}) as f:
        f.write(str(path))
    back = read_envmap(path)
    np.testing.assert_array_equal(back, img)
    torch.testing.assert_close(fit_sh_probe(back).coeffs, fit_sh_probe(img).coeffs)
    half = tmp_path / "half.exr"
    chans = {k: img[..., i].astype(np.float16) for i, k in enumerate("RGB")}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, chans) as f:
        f.write(str(half))
    np.testing.assert_allclose(read_envmap(half), img, rtol=1e-3, atol=1e-3)


def test_hdr_round_trip(tmp_path):
    from toolkit.io import write_hdr

    img = render_sh_envmap(_random_coeffs(2), 32, 64).clamp_min(0).float().numpy()
    write_hdr(tmp_path / "p.hdr", img)
    back = read_envmap(tmp_path / "p.hdr")
    # RGBE: an 8-bit mantissa per channel with the exponent of the brightest channel
    assert (np.abs(back - img) <= img.max(-1, keepdims=True) * 2.0 / 256.0 + 1e-6).all()


def test_read_envmap_errors_name_the_file(tmp_path):
    with pytest.raises(SceneError, match="missing.hdr"):
        read_envmap(tmp_path / "missing.hdr")
    png = tmp_path / "probe.png"
    png.write_bytes(b"not really")
    with pytest.raises(SceneError, match="probe.png.*unsupported"):
        read_envmap(png)
    bad = tmp_path / "broken.hdr"
    bad.write_bytes(b"#?RADIANCE\ngarbage")
    with pytest.raises(SceneError, match="broken.hdr"):
        read_envmap(bad)


# ---------------------------------------------------------------------------------------------------------------- CLI
def _cli(argv):
    from toolkit.cli import main

    return main(["priors", "sh-probe", *argv])


def _probe_file(tmp_path) -> Path:
    from toolkit.io import write_hdr

    path = tmp_path / "probe.hdr"
    write_hdr(path, render_sh_envmap(_random_coeffs(1), 32, 64).clamp_min(0).float().numpy())
    return path


def test_cli_json_output_and_file(tmp_path, capsys):
    path = _probe_file(tmp_path)
    assert _cli([str(path), "--json"]) == 0
    out = capsys.readouterr().out
    doc = json.loads(out)  # stdout holds only the JSON document
    assert np.asarray(doc["coeffs"]).shape == (9, 3)
    assert len(doc["threejs"]) == 27 and np.asarray(doc["gltf"]["irradianceCoefficients"]).shape == (9, 3)
    assert doc["layout"] == "latlong" and doc["file"] == str(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["probe.hdr"]  # nothing written beside the input
    np.testing.assert_allclose(doc["coeffs"], fit_sh_probe(read_envmap(path)).coeffs.numpy(), atol=1e-6)
    written = tmp_path / "probe.sh.json"
    assert _cli([str(path), "--json", "--out", str(written)]) == 0
    assert json.loads(written.read_text())["coeffs"] == doc["coeffs"]
    capsys.readouterr()
    # never overwrite without --force
    assert _cli([str(path), "--json", "--out", str(written)]) == 2
    assert "exists" in capsys.readouterr().err
    assert _cli([str(path), "--json", "--out", str(written), "--force"]) == 0


def test_cli_table_out_rotation_and_errors(tmp_path, capsys):
    path = _probe_file(tmp_path)
    out = tmp_path / "sub" / "coeffs.json"
    assert _cli([str(path), "--out", str(out), "--rotate-x", "90"]) == 0
    text = capsys.readouterr().out
    assert "(2,2)" in text and str(out) in text
    doc = json.loads(out.read_text())
    expected = rotate_sh(fit_sh_probe(read_envmap(path)).coeffs.double(), rotation_x(90))
    np.testing.assert_allclose(doc["coeffs"], expected.numpy(), atol=1e-5)
    assert not (tmp_path / "probe.sh.json").exists()
    assert _cli([str(tmp_path / "nope.hdr"), "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "nope.hdr" in captured.err


@pytest.mark.skipif(not PROBES, reason=f"probulator probes not found under {ENVMAPS}")
def test_cli_on_shared_probe_without_writing(tmp_path, capsys):
    probe = tmp_path / PROBES[0].name
    shutil.copy(PROBES[0], probe)
    assert _cli([str(probe), "--json", "--no-save"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["coeffs"][0][0] > 0 and not (tmp_path / (probe.stem + ".sh.json")).exists()
