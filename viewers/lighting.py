"""Where a viewer's SH light comes from: the GLB, a JSON file or an HDR probe (relighting).

All functions return float64 [9, 3] SPEC-convention radiance SH in the dars world frame (+z up), the form
:func:`toolkit.shading.shade_pbr` and the viewers' shaders take.

* :func:`asset_sh`: the GLB's lossless copy in the root ``extras.dars.sh`` (written by :func:`export.gltf.export_gltf`);
  failing that, the ``EXT_lights_image_based`` ``irradianceCoefficients`` converted back (:func:`sh_from_gltf_ibl`,
  the inverse of :func:`toolkit.sh.sh_to_gltf_ibl`, so third-party GLBs with that extension light correctly).
* :func:`toolkit.sh.read_sh_json`: ``{"coeffs": 9 x [r, g, b]}`` (the output of ``dars priors sh-probe FILE --json``),
  ``{"sh": ...}`` (a transforms JSON), or a bare 9 x 3 / 27 list.
* :func:`sh_from_probe`: an HDR environment map (``.hdr`` / ``.exr``) projected with :func:`toolkit.sh.fit_sh_probe`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import torch

from toolkit._checks import ConfigError, DarsError
from toolkit.sh import (GLTF_SH_SIGNS, SH_BAND_OF_K, SH_C0, SH_IRRADIANCE_BANDS, WORLD_TO_Y_UP, check_sh_coeffs,
                        read_sh_json, rotate_sh)

__all__ = ["DEFAULT_SH", "asset_sh", "sh_from_gltf_ibl", "sh_from_probe", "resolve_sh", "draws_backdrop",
           "light_scale"]


DEFAULT_SH = np.zeros((9, 3))
DEFAULT_SH[0] = 1.0 / SH_C0
"""Uniform white radiance 1 (irradiance π): the light used when an asset carries none."""


def sh_from_gltf_ibl(light: dict) -> np.ndarray:
    """Radiance SH (world frame) from an ``EXT_lights_image_based`` light's ``irradianceCoefficients``.

    Inverts :func:`toolkit.sh.sh_to_gltf_ibl`: divide by Babylon's basis signs and the Â_l bands, divide out the
    light's ``intensity``, rotate from glTF's +y-up frame back to the +z-up world. (The light's ``rotation``
    quaternion is applied when it is not the identity.)

    Raises:
        DarsError: no or malformed coefficients.
    """
    if "irradianceCoefficients" not in light:
        raise DarsError("EXT_lights_image_based light has no irradianceCoefficients")
    irr = check_sh_coeffs(light["irradianceCoefficients"], "EXT_lights_image_based irradianceCoefficients")
    scale = np.array([GLTF_SH_SIGNS[k] * SH_IRRADIANCE_BANDS[SH_BAND_OF_K[k]] for k in range(9)])
    radiance_gltf = irr / scale[:, None] * float(light.get("intensity", 1.0))
    q = np.asarray(light.get("rotation", [0.0, 0.0, 0.0, 1.0]), dtype=np.float64)
    c = torch.as_tensor(radiance_gltf)
    if np.abs(q - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        x, y, z, w = q / np.linalg.norm(q)
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        c = rotate_sh(c, rot)
    to_world = np.asarray(WORLD_TO_Y_UP, dtype=np.float64).T
    return rotate_sh(c, to_world).numpy()


def asset_sh(asset) -> np.ndarray | None:
    """The SH light stored in a loaded GLB (:class:`export.gltf.GltfAsset`), or None when it has none."""
    if asset.sh is not None:
        return check_sh_coeffs(asset.sh, "GLB extras.dars.sh")
    if asset.ibl is not None and "irradianceCoefficients" in asset.ibl:
        return sh_from_gltf_ibl(asset.ibl)
    return None


def sh_from_probe(path: str | Path, layout: Literal["latlong", "angular"] = "latlong") -> np.ndarray:
    """Project an HDR probe onto SH (:func:`toolkit.sh.fit_sh_probe`).

    Args:
        path: ``.hdr`` or ``.exr`` environment map.
        layout: ``latlong`` (SPEC lat-long, world frame) or ``angular`` (a +y-up light probe, rotated into the world
            with :func:`toolkit.sh.probe_to_world_rotation`).
    """
    from toolkit.sh import fit_sh_probe, probe_to_world_rotation, read_envmap

    img = read_envmap(path)
    rot = probe_to_world_rotation() if layout == "angular" else None
    return fit_sh_probe(img, layout=layout, rotation=rot).coeffs.double().numpy()


def light_scale(asset) -> float:
    """The GLB's ``extras.dars.light_scale`` (1 when absent): its SH is the run's times this, and its occlusion
    channel holds the field's per-point light gain divided by it (:attr:`toolkit.asset.AssetConfig.light_occlusion`)."""
    dars = ((getattr(asset, "json", None) or {}).get("extras") or {}).get("dars") or {}
    value = dars.get("light_scale", 1.0)
    if not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
        raise DarsError(f"GLB extras.dars.light_scale={value!r} must be a positive number; re-export the GLB")
    return float(value)


def resolve_sh(asset, sh_json: str | Path | None = None, probe: str | Path | None = None,
               probe_layout: Literal["latlong", "angular"] = "latlong") -> tuple[np.ndarray, str]:
    """The light to preview with: ``sh_json`` or ``probe`` if given (relighting), else the asset's, else
    :data:`DEFAULT_SH`. Returns ``(sh [9, 3], source description)``.

    A relight of a GLB with a ``light_scale`` (:func:`light_scale`) is multiplied by it, so the occlusion channel
    (the field's light gain over that scale) modulates the new light as it did the run's, at the same level."""
    if sh_json is not None and probe is not None:
        raise DarsError("give either an SH JSON or an HDR probe, not both")
    if sh_json is not None or probe is not None:
        if sh_json is not None:
            sh, source = read_sh_json(sh_json), f"SH JSON {sh_json}"
        else:
            sh, source = sh_from_probe(probe, probe_layout), f"probe {probe} ({probe_layout})"
        scale = light_scale(asset)
        if scale != 1.0:
            sh, source = sh * scale, f"{source} x {scale:g} (the GLB's light_scale)"
        return sh, source
    sh = asset_sh(asset)
    if sh is not None:
        return sh, "asset"
    return DEFAULT_SH.copy(), "default (uniform white, the asset has no SH)"


def draws_backdrop(background: str, asset, sh: np.ndarray) -> bool:
    """Whether a viewer lit by ``sh`` draws the GLB's backdrop (:mod:`toolkit.backdrop`) for the ``background``
    choice (``dars view``'s and the WebXR page's rule): ``"backdrop"`` always (an error on a GLB without one),
    ``"auto"`` when the GLB has one and ``sh`` is the GLB's own light (a relit view shows the new light's radiance
    instead), any other choice never.

    Raises:
        ConfigError: ``"backdrop"`` on a GLB without one.
    """
    if background == "backdrop":
        if asset.backdrop is None:
            raise ConfigError("background='backdrop': this GLB carries no backdrop (exported before 2026-11-29 or "
                              "with --no-backdrop); use 'sh' or re-export it with `dars export-asset RUN`")
        return True
    if background != "auto" or asset.backdrop is None or asset.sh is None:
        return False
    return bool(np.allclose(np.asarray(sh, np.float64), asset.sh, rtol=1e-5, atol=1e-6))
