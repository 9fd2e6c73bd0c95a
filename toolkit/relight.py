"""Stage 16 — relighting and material editing of a trained field.

Relighting replaces the global SH light ``l_env`` by another one (from an HDR probe through
:func:`toolkit.sh.fit_sh_probe`, or 27 coefficients). The field's per-point residual Δl(x) (shadows,
spotlights: learnt under the original light) is handled by ``residual``:

* ``scale`` (default): Δl is scaled per channel by the ratio of the new to the old DC term — a shadow that removes
  30 % of the light keeps removing 30 %;
* ``keep``: Δl as learnt; ``drop``: pure SH light, no local effects.

Material edits override albedo / roughness / metallic per semantic class, blended by the field's own class
probability p_c at each point (``m' = m + p_c (target − m)``), so edges between classes stay soft. Edits are
strings ``CLASS:KEY=VALUE[,KEY=VALUE]`` with KEY in ``albedo`` (r,g,b linear or one grey value), ``roughness``,
``metallic``; e.g. ``frame:metallic=0,roughness=0.8`` or ``painting:albedo=0.8,0.1,0.1`` (``albedo`` takes the
three following numbers).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from ._checks import ConfigError
from .field import FieldOutputs
from .scene import SEMANTIC_CLASSES

__all__ = ["MaterialEdit", "parse_material_edit", "apply_material_edits", "relight_hook", "edited_material_fn"]


@dataclass(frozen=True)
class MaterialEdit:
    """Override of one semantic class's material (None = unchanged)."""

    class_id: int
    albedo: tuple[float, float, float] | None = None
    roughness: float | None = None
    metallic: float | None = None


def parse_material_edit(text: str) -> MaterialEdit:
    """Parse ``CLASS:key=value,...`` (class by name or id). Raises :class:`ConfigError` naming the bad part."""
    if ":" not in text:
        raise ConfigError(f"material edit {text!r}: expected CLASS:KEY=VALUE (e.g. frame:metallic=0)")
    cls, rest = text.split(":", 1)
    cls = cls.strip()
    if cls.isdigit():
        cid = int(cls)
    elif cls in SEMANTIC_CLASSES:
        cid = SEMANTIC_CLASSES.index(cls)
    else:
        raise ConfigError(f"material edit {text!r}: unknown class {cls!r}; choose one of {list(SEMANTIC_CLASSES)}")
    if not 0 <= cid < len(SEMANTIC_CLASSES):
        raise ConfigError(f"material edit {text!r}: class id {cid} out of range 0-{len(SEMANTIC_CLASSES) - 1}")
    tokens = [t.strip() for t in rest.split(",") if t.strip()]
    vals: dict = {}
    i = 0
    while i < len(tokens):
        if "=" not in tokens[i]:
            raise ConfigError(f"material edit {text!r}: {tokens[i]!r} is not KEY=VALUE")
        key, v = tokens[i].split("=", 1)
        key = key.strip()
        try:
            if key == "albedo":
                nums = [float(v)]
                while len(nums) < 3 and i + 1 < len(tokens) and "=" not in tokens[i + 1]:
                    i += 1
                    nums.append(float(tokens[i]))
                if len(nums) == 1:
                    nums = nums * 3
                if len(nums) != 3:
                    raise ValueError("albedo needs 1 or 3 numbers")
                vals["albedo"] = tuple(nums)
            elif key in ("roughness", "metallic"):
                vals[key] = float(v)
            else:
                raise ConfigError(f"material edit {text!r}: unknown key {key!r} (albedo, roughness, metallic)")
        except ConfigError:
            raise
        except ValueError as e:
            raise ConfigError(f"material edit {text!r}: bad value for {key}: {e}") from e
        i += 1
    for k, v in vals.items():
        for x in (v if isinstance(v, tuple) else (v,)):
            if not 0.0 <= x <= 1.0:
                raise ConfigError(f"material edit {text!r}: {k}={x} must be in [0, 1]")
    if not vals:
        raise ConfigError(f"material edit {text!r}: nothing to change")
    return MaterialEdit(cid, **vals)


def apply_material_edits(albedo: torch.Tensor, roughness: torch.Tensor, metallic: torch.Tensor,
                         probs: torch.Tensor, edits: list[MaterialEdit]):
    """Blend edited materials by class probability.

    Args:
        albedo: float [N, 3]; roughness, metallic: float [N]; probs: float [N, C] class probabilities.
        edits: the edits.

    Returns:
        (albedo, roughness, metallic) edited.
    """
    for e in edits:
        p = probs[:, e.class_id]
        if e.albedo is not None:
            albedo = albedo + p[:, None] * (torch.tensor(e.albedo, dtype=albedo.dtype, device=albedo.device) - albedo)
        if e.roughness is not None:
            roughness = roughness + p * (e.roughness - roughness)
        if e.metallic is not None:
            metallic = metallic + p * (e.metallic - metallic)
    return albedo, roughness, metallic


def relight_hook(l_env_old: torch.Tensor, l_env_new: torch.Tensor | None = None, edits: list[MaterialEdit] = (),
                 residual: Literal["scale", "keep", "drop"] = "scale"):
    """An ``outputs_hook`` for :func:`toolkit.pipeline.render_rays` that swaps the light and edits materials.

    Render with the run's original ``l_env`` (the lighting head is conditioned on it) and this hook.
    """
    if residual not in ("scale", "keep", "drop"):
        raise ConfigError(f"residual={residual!r}: choose scale, keep or drop")
    factor = None
    if l_env_new is not None:
        new = l_env_new.reshape(9, 3)
        old_dc = l_env_old.reshape(9, 3)[0]
        factor = torch.where(old_dc.abs() > 1e-6, new[0] / old_dc, torch.zeros_like(new[0]))

    def hook(out: FieldOutputs) -> FieldOutputs:
        if edits and out.albedo is not None and out.semantic_logits is not None:
            probs = torch.softmax(out.semantic_logits, -1)
            out.albedo, out.roughness, out.metallic = apply_material_edits(out.albedo, out.roughness, out.metallic,
                                                                           probs, list(edits))
        if l_env_new is not None and out.light is not None:
            res = out.light_residual if out.light_residual is not None else torch.zeros_like(out.light)
            if residual == "drop":
                res = torch.zeros_like(res)
            elif residual == "scale":
                res = res * factor.to(res)
            out.light = new.to(out.light).reshape(1, 9, 3) + res
        return out

    return hook


def edited_material_fn(material_fn, semantic_probs_fn, edits: list[MaterialEdit]):
    """Wrap a baking ``material_fn(points, normals) -> dict`` so the baked textures carry the edits.

    ``semantic_probs_fn(points) -> [N, C]`` gives the field's class probabilities at the points.
    """

    def fn(points, normals=None):
        d = dict(material_fn(points, normals))
        if edits and "albedo" in d:
            probs = semantic_probs_fn(points)
            d["albedo"], d["roughness"], d["metallic"] = apply_material_edits(
                torch.as_tensor(d["albedo"]), torch.as_tensor(d["roughness"]), torch.as_tensor(d["metallic"]),
                torch.as_tensor(probs), list(edits))
        return d

    return fn
