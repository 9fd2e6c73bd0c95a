"""Stage 14 — ONNX export of a trained run for devices, with parity checks on every export.

:func:`export_onnx_models` turns a run directory (``dars train --out RUN``) into a device bundle::

    DIR/field.onnx        the decoupled field: points (+ view_dirs, + sh) -> density, normal, materials,
                          semantics, local light and the PBR-shaded colour (or the radiance of a NeRF run)
    DIR/segment.onnx      the scene's built-in segmenter (when ``priors/segment/segmenter.pt`` exists)
    DIR/light.onnx        the light-estimation network (when ``toolkit.lightnet`` and trained weights exist)
    DIR/heads.onnx        only for a run trained with per-ray (``deferred``) shading: the heads and the shading on a
                          ray's composited field feature (the field graph's ``feature`` output, Σ w h / Σ w)
    DIR/occupancy.npz     the occupancy grid: ``mask_bits`` (np.packbits of the R^3 occupied cells, x-major),
                          ``density`` float16 [R^3], ``resolution``, ``aabb`` [2, 3] (the scene box), ``step``,
                          ``threshold``, ``contraction`` (the cells cover contracted space [-2, 2]^3, else the box)
                          and ``far_radius`` (contracted: beyond it nothing is occupied)
    DIR/background.npz    ``mode`` (constant | learned | env), ``colour`` [3] or ``env_map`` [h, w, 3] linear
    DIR/metadata.json     conventions, l_env, box, sampler, files, graph signatures and the parity report
    DIR/field_fp16.onnx, DIR/field_int8.onnx   reduced-precision variants (optional; :mod:`export.onnx_precision`),
                          each measured: error per output and PSNR of the parity view vs fp32 and vs ground truth

**Field graph.** :class:`FieldOnnxModule` calls :meth:`toolkit.field.DarsField.forward` and
:func:`toolkit.shading.shade_pbr` — no re-implementation. For an unbounded run (``field.contraction``) the graph
therefore contains the scene contraction before the hash grid and the σ rescaling (density per contracted length,
σ / max(1, ‖n‖∞)², zero beyond ``far_radius``): it takes world points either way; ``metadata.json["space"]`` tells
a renderer how to bound and stratify the rays (:mod:`toolkit.space`, mirrored in :mod:`export.infer`). The hash
grid is forced onto :func:`toolkit.encoding.hash_grid_encode_torch` (``HashGrid.backend = "torch"``): gather-based
trilinear interpolation with int64 Mul/Add/Mod (sum hash, no XOR) and ``Gather`` on the table — no ``GridSample``,
no bitwise ops, so opset 17 suffices (the compiled C++ kernel is not traceable). The DFG table [32, 32, 2], the SH
band tables and the SH constants become graph constants. The batch axis ``N`` is dynamic; ``sh`` [9, 3] is the
global SH light ``l_env`` (SPEC convention) that conditions the lighting head, so a device can relight.

**Parity** (fails loudly with :class:`export.onnx.OnnxParityError`): ONNX Runtime vs torch per output on random
points in the box (contracted runs: and beyond it, out past the far radius) and on *real* inputs (the exact
samples the run's render sampler takes along the rays of a test view), max abs error ≤ ``tol`` (1e-4; for
``density``, which is in 1/m and reaches 1e3–1e4 on opaque surfaces, the bound is ``tol · max(1, |σ|)``, i.e. 1e-4
relative above 1, since float32 resolves only ~1e-7 relative; both figures are reported, and on the sample runs
even the raw density error is ~2e-5); then one test view is rendered by :func:`export.infer.render_view` (numpy +
ONNX Runtime, no torch) and by :meth:`toolkit.train.run.Run.render` and their PSNRs against the ground truth must
agree within ``psnr_tol`` (0.05 dB). DARS along-ray density is a render-time prior from the training W maps, not
part of the device path: the torch reference for the check has it disabled; with it on, its PSNR is reported as
well.

Example:
    >>> rep = export_onnx_models("runs/gallery", "out/onnx", precision=("fp32", "fp16", "int8"))  # doctest: +SKIP
    >>> rep.render["delta_db"] <= 0.05  # doctest: +SKIP
    True
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch
from torch import nn

from toolkit._checks import ConfigError, DarsError
from toolkit.field import DarsField
from toolkit.pinhole import PinholeCamera
from toolkit.shading import ShadingConfig, shade_pbr
from toolkit.sh import SH_C0, SH_C1, SH_C2, SH_C3, SH_C4

from .onnx import OnnxExportReport, OnnxParityError, export_onnx, export_segmenter_onnx
from .onnx_precision import make_fp16_variant, make_int8_variant
from . import infer as _infer

__all__ = ["FieldExportConfig", "OnnxModelsReport", "FieldOnnxModule", "export_field_onnx", "export_onnx_models",
           "field_io_signature", "heads_io_signature", "HeadsOnnxModule", "space_metadata", "PBR_OUTPUTS",
           "RADIANCE_OUTPUTS", "HEADS_FILE", "PRECISIONS"]

PBR_OUTPUTS = ("density", "normal", "albedo", "roughness", "metallic", "semantic_logits", "light", "colour",
               "diffuse", "specular", "feature")
RADIANCE_OUTPUTS = ("density", "normal", "semantic_logits", "radiance", "feature")
HEADS_FILE = "heads.onnx"
"""The heads graph of a run trained with ``deferred`` (per-ray) shading: :class:`HeadsOnnxModule`."""
PRECISIONS = ("fp32", "fp16", "int8")

CONVENTIONS = (
    "cameras: camera-to-world 4x4, OpenGL (x right, y up, looking down -z), metres; pixel (u, v) centre at "
    "(u+0.5, v+0.5); world +z up. SH: real, order 2, 9 coefficients x RGB, order (0,0) (1,-1) (1,0) (1,1) (2,-2) "
    "(2,-1) (2,0) (2,1) (2,2), basis constants 0.282095, 0.488603*(y, z, x), 1.092548*xy, 1.092548*yz, "
    "0.315392*(3z^2-1), 1.092548*xz, 0.546274*(x^2-y^2); coefficients are incident radiance L(w), w from the "
    "surface toward the light, world frame; irradiance bands (pi, 2pi/3, pi/4). Radiance/colour outputs are "
    "LINEAR (apply the sRGB transfer for display). view_dirs are unit ray directions camera -> point. "
    "Semantic classes: 0 painting, 1 frame, 2 display, 3 base, 4 wall, 5 floor, 6 other.")


# ============================================================================ config and report
@dataclass(frozen=True)
class FieldExportConfig:
    """Options of :func:`export_onnx_models` beyond the opset and precisions."""

    tol: float = 1e-4
    """Largest accepted |onnxruntime − torch| per output (fp32); density relative above 1 (module docstring)."""
    psnr_tol: float = 0.05
    """Largest accepted |PSNR(onnx render) − PSNR(torch render)| in dB on the parity view."""
    n_random: int = 4096
    """Random points (uniform in the box grown by 5 %, random unit view directions) for the random check; for a
    contracted field half of them lie beyond the box, out past the far radius."""
    n_real_rays: int = 256
    """Test-view rays whose render samples are the real inputs."""
    parity_split: str = "test"
    """Split of the run's scene holding the parity view (falls back to ``train`` when absent)."""
    parity_index: int = 0
    """Frame of the parity view."""
    check_render: bool = True
    """Render the parity view through ONNX Runtime and torch and compare (the 0.05 dB bar)."""
    threads: int = 0
    """ONNX Runtime intra-op threads in the checks (0: torch's current setting)."""
    segmenter: str | None = None
    """A ``segmenter.pt`` to export instead of the scene's ``priors/segment/segmenter.pt``."""
    light_model: str | None = None
    """Weights for ``toolkit.lightnet.load_lightnet`` instead of the scene's ``priors/light/*.pt``."""
    int8_gather: bool = True
    """Quantise the hash table (``Gather``, per-tensor int8) in the int8 variant as well as the MLP weights: the
    table is > 95 % of the file (16 MB -> 4 MB); False quantises the MLP ``MatMul`` weights only (tiny)."""

    def __post_init__(self):
        if not self.tol > 0 or not self.psnr_tol > 0:
            raise ConfigError(f"tol={self.tol} and psnr_tol={self.psnr_tol} must be positive")
        if self.n_random < 1 or self.n_real_rays < 1:
            raise ConfigError(f"n_random={self.n_random} and n_real_rays={self.n_real_rays} must be >= 1")


@dataclass(frozen=True)
class OnnxModelsReport:
    """What :func:`export_onnx_models` wrote and measured (``to_dict()`` is JSON-able).

    Attributes:
        out_dir: the export directory.
        opset: ONNX default-domain opset of every graph.
        files: name -> bytes on disk.
        field: parity of ``field.onnx``: ``{"random": {output: max abs err}, "real": {...}, "max_abs_err",
            "max_scaled_err", "n_random", "n_real", "op_types": {op: count}}``.
        render: parity of a rendered view (``psnr_onnx``, ``psnr_torch``, ``delta_db``, ``psnr_onnx_vs_torch``,
            ``max_abs_diff``, ``frac_pixels_over_1e-4``, ``seconds_onnx``, ``seconds_torch``, ``view``; ``psnr_torch_dars`` when DARS is on).
        variants: per reduced precision: file, size, max abs error per output, PSNR vs fp32 and vs ground truth.
        segment: ``{"status": "exported" | "unavailable", "reason" | "path", ...}``.
        light: same for the light network.
    """

    out_dir: Path
    opset: int
    files: dict
    field: dict
    render: dict | None
    variants: dict
    segment: dict
    light: dict

    def to_dict(self) -> dict:
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        return d


# ============================================================================ the field graph
class FieldOnnxModule(nn.Module):
    """The exported field: :meth:`DarsField.forward` + :func:`shade_pbr` per point, as one graph.

    ``pbr``: ``forward(points [N, 3], view_dirs [N, 3], sh [9, 3])`` returns :data:`PBR_OUTPUTS` —
    density [N] (1/m), normal [N, 3], albedo [N, 3] (linear), roughness [N], metallic [N], semantic_logits
    [N, C], light [N, 9, 3] (l_env + Δl(x)), colour / diffuse / specular [N, 3] (linear, shaded toward −view_dirs
    under ``light``), feature [N, D] (the shared field feature h the heads read). ``radiance``: ``forward(points,
    view_dirs)`` returns :data:`RADIANCE_OUTPUTS`. A deferred run's renderer reads ``density`` and ``feature`` at
    the samples and shades each ray with :class:`HeadsOnnxModule` (ONNX Runtime 1.31 still runs the whole graph
    for that subset of outputs: measured the same time either way).
    """

    def __init__(self, fld: DarsField, shading: Literal["pbr", "radiance"] = "pbr",
                 shading_cfg: ShadingConfig = ShadingConfig()):
        super().__init__()
        if shading not in ("pbr", "radiance"):
            raise ConfigError(f"shading={shading!r}: choose 'pbr' or 'radiance'")
        self.field = fld
        self.shading = shading
        self.shading_cfg = shading_cfg

    def forward(self, points: torch.Tensor, view_dirs: torch.Tensor, sh: torch.Tensor | None = None):
        density, h = self.field.geometry_features(points)
        return (density, *_head_outputs(self.field, h, view_dirs, sh, self.shading, self.shading_cfg), h)


def _head_outputs(fld: DarsField, h: torch.Tensor, view_dirs: torch.Tensor, sh: torch.Tensor | None, shading: str,
                  shading_cfg: ShadingConfig) -> tuple:
    """The heads (and for ``pbr`` the shading) on features ``h`` [N, D]: the outputs of :data:`PBR_OUTPUTS` /
    :data:`RADIANCE_OUTPUTS` between ``density`` and ``feature``."""
    if shading == "radiance":
        o = fld.heads(h, view_dirs, None, "radiance")
        return o.normal, o.semantic_logits, o.radiance
    o = fld.heads(h, view_dirs, sh, "pbr")
    s = shade_pbr(o.albedo, o.roughness, o.metallic, o.normal, -view_dirs, o.light, shading_cfg)
    return o.normal, o.albedo, o.roughness, o.metallic, o.semantic_logits, o.light, s.colour, s.diffuse, s.specular


class HeadsOnnxModule(FieldOnnxModule):
    """The heads graph of a run trained with per-ray (``deferred``) shading: the heads and the PBR shading on a
    ray's composited feature h̄ = Σ w h / Σ w, as :func:`toolkit.pipeline.render_rays` shades such a run.

    ``forward(feature [R, D], view_dirs [R, 3], sh [9, 3])`` (``radiance``: without ``sh``) returns the outputs of
    :data:`PBR_OUTPUTS` (:data:`RADIANCE_OUTPUTS`) without ``density`` and ``feature``."""

    def forward(self, feature: torch.Tensor, view_dirs: torch.Tensor, sh: torch.Tensor | None = None):
        return _head_outputs(self.field, feature, view_dirs, sh, self.shading, self.shading_cfg)


def field_io_signature(shading: str, n_classes: int, feature_dim: int | None = None) -> tuple[dict, dict]:
    """(inputs, outputs) ``{name: shape}`` of the field graph (``"N"`` = dynamic batch; ``feature_dim`` D of the
    ``feature`` output, ``"D"`` when not given)."""
    inputs = {"points": ["N", 3], "view_dirs": ["N", 3]}
    d = "D" if feature_dim is None else int(feature_dim)
    if shading == "pbr":
        inputs["sh"] = [9, 3]
        outputs = {"density": ["N"], "normal": ["N", 3], "albedo": ["N", 3], "roughness": ["N"],
                   "metallic": ["N"], "semantic_logits": ["N", n_classes], "light": ["N", 9, 3], "colour": ["N", 3],
                   "diffuse": ["N", 3], "specular": ["N", 3], "feature": ["N", d]}
    else:
        outputs = {"density": ["N"], "normal": ["N", 3], "semantic_logits": ["N", n_classes], "radiance": ["N", 3],
                   "feature": ["N", d]}
    return inputs, outputs


def heads_io_signature(shading: str, n_classes: int, feature_dim: int) -> tuple[dict, dict]:
    """(inputs, outputs) ``{name: shape}`` of the heads graph (:class:`HeadsOnnxModule`; ``"R"`` = rays)."""
    ins, outs = field_io_signature(shading, n_classes, feature_dim)
    inputs = {"feature": ["R", int(feature_dim)], "view_dirs": ["R", 3]}
    if "sh" in ins:
        inputs["sh"] = [9, 3]
    outputs = {k: ["R", *v[1:]] for k, v in outs.items() if k not in ("density", "feature")}
    return inputs, outputs


class _TorchHashGrid:
    """Context: force the plain-torch (traceable) hash-grid path, restore the backend afterwards."""

    def __init__(self, fld: DarsField):
        self.grid = getattr(fld, "grid", None)
        self.old = None

    def __enter__(self):
        if self.grid is not None:
            self.old, self.grid.backend = self.grid.backend, "torch"
        return self

    def __exit__(self, *exc):
        if self.grid is not None:
            self.grid.backend = self.old


def _dars_version() -> str:
    try:
        from importlib.metadata import version

        return version("dars-toolkit")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        return "unknown"


def _random_inputs(aabb: torch.Tensor, n: int, seed: int, far_radius: float | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Random points [n, 3] uniform in the box grown by 5 % and random unit directions [n, 3]. With ``far_radius``
    (a contracted field) the second half of the points lies beyond the box instead: box radius ‖n‖∞ log-uniform
    in [1, 1.25 · far_radius] (the contracted shell, and some beyond the far radius, where σ must be 0)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = aabb[0].float(), aabb[1].float()
    pad = 0.05 * (hi - lo)
    pts = (lo - pad) + torch.rand(n, 3, generator=g) * (hi - lo + 2 * pad)
    dirs = nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    if far_radius is not None and n > 1:
        m = n // 2
        cube = torch.rand(m, 3, generator=g) * 2 - 1
        cube = cube / cube.abs().amax(-1, keepdim=True).clamp_min(1e-6)  # on the unit cube's surface (‖·‖∞ = 1)
        radius = torch.exp(torch.rand(m, 1, generator=g) * math.log(1.25 * far_radius))
        pts[n - m:] = 0.5 * (lo + hi) + cube * radius * 0.5 * (hi - lo)
    return pts, dirs


def _compare(module: FieldOnnxModule, sess, inputs: dict[str, torch.Tensor], names: Sequence[str],
             chunk: int = 65536) -> tuple[dict[str, float], dict[str, float]]:
    """(max abs error, max scaled error) per output of ONNX Runtime vs torch; scaled = |d| / max(1, |ref|)."""
    abs_err = {k: 0.0 for k in names}
    scaled = {k: 0.0 for k in names}
    n = next(iter(inputs.values())).shape[0]
    for i in range(0, n, chunk):
        xs = {k: (v[i:i + chunk] if k != "sh" else v) for k, v in inputs.items()}
        with torch.no_grad():
            ref = module(*xs.values())
        got = sess.run(None, {k: v.detach().cpu().numpy().astype(np.float32) for k, v in xs.items()})
        for k, r, o in zip(names, ref, got):
            r64 = r.detach().double().numpy()
            if o.shape != r64.shape:
                raise OnnxParityError(f"field output '{k}' has shape {list(o.shape)} in ONNX Runtime but "
                                      f"{list(r64.shape)} in torch", float("inf"), Path("field.onnx"))
            if o.size:
                d = np.abs(o.astype(np.float64) - r64)
                abs_err[k] = max(abs_err[k], float(d.max()))
                scaled[k] = max(scaled[k], float((d / np.maximum(1.0, np.abs(r64))).max()))
    return abs_err, scaled


def export_field_onnx(fld: DarsField, path: str | os.PathLike, l_env: torch.Tensor | None = None,
                      shading: Literal["pbr", "radiance"] = "pbr", opset: int = 17, metadata: dict | None = None,
                      tol: float = 1e-4) -> OnnxExportReport:
    """Export a :class:`DarsField` as ``field.onnx`` (checked with ``onnx.checker``; example-input parity).

    Args:
        fld: the field (any device; exported on CPU, restored afterwards).
        path: output ``.onnx``.
        l_env: float [9, 3] global SH light used as the example ``sh`` input (``pbr``).
        shading: ``pbr`` (decomposed + shaded colour) or ``radiance`` (standard NeRF run).
        opset: ONNX opset (≤ 17 uses the TorchScript exporter; the graph needs nothing newer).
        metadata: extra ``metadata_props``.
        tol: parity tolerance on the example inputs (scaled error, see the module docstring).

    Returns:
        :class:`export.onnx.OnnxExportReport`.
    """
    module = FieldOnnxModule(fld, shading).eval()
    ins, outs = field_io_signature(shading, fld.cfg.n_classes, fld.feature_dim)
    pts, dirs = _random_inputs(fld.aabb.detach().cpu(), 64, seed=1, far_radius=_far_radius(fld))
    example = (pts, dirs)
    if shading == "pbr":
        sh = torch.zeros(9, 3) if l_env is None else torch.as_tensor(l_env, dtype=torch.float32).reshape(9, 3).cpu()
        example = (pts, dirs, sh)
    axes = {k: {0: "N"} for k in list(ins)[:2] + list(outs)}
    with _TorchHashGrid(fld):
        # example-input parity on a scaled tolerance (density reaches 1e4/m); random and real checks follow
        return export_onnx(module, example, path, list(ins), list(outs), dynamic_batch=False, opset=opset,
                           metadata=metadata, dynamic_axes=axes, tol=max(tol, tol * _max_density(module, example)),
                           random_batch=0)


def _far_radius(fld: DarsField) -> float | None:
    """The field's far radius when it is contracted (unbounded), else None."""
    return float(fld.cfg.far_radius) if fld.cfg.contraction else None


def space_metadata(fld: DarsField) -> dict:
    """``metadata.json["space"]``: what a renderer needs to bound and stratify rays like :mod:`toolkit.space`.

    ``aabb`` [2, 3] the scene box (metres); ``contraction`` (unbounded: rays run to the far-radius box and are
    stratified uniformly in contracted arc length); ``far_radius`` (box half-sizes, L∞); ``edge_candidates`` (the
    arc-length table of :func:`toolkit.space.contracted_edges`); ``grid_aabb`` the box the hash and occupancy grids
    cover in grid coordinates ([-2, 2]^3 contracted, else the scene box).
    """
    import inspect

    from toolkit.space import contracted_edges

    sp = fld.space
    k = inspect.signature(contracted_edges).parameters["n_candidates"].default
    return {"aabb": sp.aabb.detach().cpu().float().tolist(), "contraction": bool(sp.contraction),
            "far_radius": float(sp.far_radius), "edge_candidates": int(k),
            "grid_aabb": sp.grid_aabb.detach().cpu().float().tolist(),
            "contract": "n = (x - centre) / half; c = n if max|n| <= 1 else (2 - 1/max|n|) n / max|n|",
            "density": "per metre; beyond the box already divided by max(1, max|n|)^2 in the graph, 0 beyond "
                       "far_radius"}


def _max_density(module: FieldOnnxModule, example) -> float:
    with torch.no_grad():
        return float(module(*example)[0].abs().max().clamp_min(1.0))


# ============================================================================ helpers for the bundle
def _write_occupancy(path: Path, occ) -> None:
    mask = occ.mask.detach().cpu().numpy().astype(bool)
    contraction = bool(getattr(occ, "contraction", False))
    layout = ("index = i*R*R + j*R + k, ijk = floor((contract(x, aabb) + 2) / 4 * R); occupied only where "
              "max|(x - centre) / half| <= far_radius" if contraction else
              "index = i*R*R + j*R + k, ijk = floor((x - aabb[0]) / (aabb[1] - aabb[0]) * R)")
    np.savez_compressed(path, mask_bits=np.packbits(mask), resolution=np.int64(occ.resolution),
                        aabb=occ.aabb.detach().cpu().numpy().astype(np.float32),
                        density=np.minimum(occ.density.detach().cpu().numpy(), 6e4).astype(np.float16),
                        step=np.float32(occ.step), threshold=np.float32(occ.threshold),
                        contraction=np.bool_(contraction),
                        far_radius=np.float32(getattr(occ, "far_radius", 64.0)), layout=np.array(layout))


def _write_background(path: Path, bg) -> dict:
    with torch.no_grad():
        if bg.mode == "env":
            env = bg.env_map().detach().cpu().numpy().astype(np.float32)
            np.savez(path, mode=np.array("env"), env_map=env)
            return {"mode": "env", "shape": list(env.shape)}
        colour = (bg.colour if bg.mode == "constant" else torch.sigmoid(bg.raw)).detach().cpu().numpy()
        np.savez(path, mode=np.array(bg.mode), colour=colour.astype(np.float32))
        return {"mode": bg.mode, "colour": [float(c) for c in colour]}


def _op_types(path: Path) -> dict[str, int]:
    import onnx

    hist: dict[str, int] = {}
    for n in onnx.load(str(path), load_external_data=False).graph.node:
        hist[n.op_type] = hist.get(n.op_type, 0) + 1
    return dict(sorted(hist.items()))


def _export_segmenter(run, out_dir: Path, opset: int, cfg: FieldExportConfig) -> dict:
    from toolkit.segment import DEFAULT_SEGMENTER, load_segmenter

    pt = Path(cfg.segmenter) if cfg.segmenter else run.priors_dir("segment") / "segmenter.pt"
    if not pt.is_file() and cfg.segmenter:
        return {"status": "unavailable", "reason": f"--segmenter {pt}: file not found"}
    if not pt.is_file():  # no network fine-tuned on this scene: the shipped one, which labelled its photos
        pt = DEFAULT_SEGMENTER
    if not pt.is_file():
        return {"status": "unavailable", "reason": f"the shipped segmenter {pt} is missing from this installation"}
    net = load_segmenter(pt)
    h, w = run.train_scene.image_size
    rep = export_segmenter_onnx(net, out_dir / "segment.onnx", image_size=(min(h, 128), min(w, 128)), opset=opset)
    return {"status": "exported", "path": "segment.onnx", "source": str(pt), "max_abs_err": rep.max_abs_err,
            "opset": rep.opset}


def _light_weights(run, cfg: FieldExportConfig) -> tuple[Path | None, str]:
    """The light network to export: ``cfg.light_model``, else the weights named in the scene's
    ``priors/light/light.json``, else the shipped default of :mod:`toolkit.lightnet`."""
    if cfg.light_model:
        return Path(cfg.light_model), "--light-weights"
    info = run.priors_dir("light") / "light.json"
    if info.is_file():
        try:
            p = json.loads(info.read_text()).get("model", {}).get("path")
        except (OSError, ValueError):
            p = None
        if p and Path(p).is_file():
            return Path(p), str(info)
    from toolkit import lightnet

    default = getattr(lightnet, "DEFAULT_WEIGHTS", None)
    return (Path(default), "shipped default") if default is not None else (None, "")


def _export_light(run, out_dir: Path, opset: int, cfg: FieldExportConfig) -> dict:
    """``light.onnx`` through ``toolkit.lightnet.load_lightnet`` + ``export.onnx_light.export_lightnet_onnx``;
    reports why it is unavailable otherwise (module missing, no weights)."""
    try:
        from toolkit import lightnet  # type: ignore[attr-defined]
    except ImportError as e:
        return {"status": "unavailable", "reason": f"toolkit.lightnet is not available in this installation ({e})"}
    try:
        from export.onnx_light import export_lightnet_onnx  # type: ignore[attr-defined]
    except ImportError:
        export_lightnet_onnx = getattr(lightnet, "export_lightnet_onnx", None)
    if export_lightnet_onnx is None or not hasattr(lightnet, "load_lightnet"):
        return {"status": "unavailable", "reason": "no export_lightnet_onnx (export.onnx_light) / load_lightnet"}
    weights, source = _light_weights(run, cfg)
    if weights is None or not weights.is_file():
        return {"status": "unavailable", "reason": f"no light-network weights ({weights or 'none'} not found); "
                "train them (bench/bench_lightnet.py) or pass --light-weights FILE"}
    try:
        model = lightnet.load_lightnet(weights)
        rep = export_lightnet_onnx(model, out_dir / "light.onnx", opset=opset)
    except OnnxParityError:
        raise
    except Exception as e:  # noqa: BLE001 - another stage's module: report, do not lose the bundle
        return {"status": "unavailable", "reason": f"light network export failed: {type(e).__name__}: {e}"}
    return {"status": "exported", "path": "light.onnx", "source": str(weights), "chosen_by": source,
            "max_abs_err": getattr(rep, "max_abs_err", None), "opset": getattr(rep, "opset", None)}


def _srgb_psnr(rgb_linear: np.ndarray, target_chw: np.ndarray) -> float:
    from toolkit.io import linear_to_srgb

    pred = np.clip(linear_to_srgb(np.clip(rgb_linear, 0.0, 1.0)), 0.0, 1.0).transpose(2, 0, 1)
    mse = float(np.mean((pred.astype(np.float64) - target_chw.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def _psnr_pair(a: np.ndarray, b: np.ndarray) -> float:
    from toolkit.io import linear_to_srgb

    pa = np.clip(linear_to_srgb(np.clip(a, 0.0, 1.0)), 0, 1).astype(np.float64)
    pb = np.clip(linear_to_srgb(np.clip(b, 0.0, 1.0)), 0, 1).astype(np.float64)
    mse = float(np.mean((pa - pb) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def _parity_scene(run, cfg: FieldExportConfig):
    from toolkit.scene import list_splits

    split = cfg.parity_split if cfg.parity_split in list_splits(run.scene_path) else run.split
    sc = run.load_split(split)
    if not 0 <= cfg.parity_index < len(sc):
        raise ConfigError(f"parity view {split}:{cfg.parity_index} is out of range ({len(sc)} frames)")
    return sc, split


def _real_inputs(run, sc, index: int, n_rays: int, composited: bool = False) -> dict[str, torch.Tensor]:
    """The samples the run's render sampler takes along ``n_rays`` rays of a view (DARS off), as field inputs; with
    ``composited``, those rays' composited features h̄ = Σ w h / Σ w and directions instead, as heads inputs."""
    from toolkit.pipeline import RenderInputs, render_rays
    from toolkit.scene import generate_rays

    bounds = run.field.space if run.field.cfg.contraction else run.train_scene.aabb  # as render_image
    rays = generate_rays(sc.cameras, [index], aabb=bounds, near=run.train_scene.near, far=run.train_scene.far)
    hit = torch.nonzero(rays.far > rays.near).squeeze(-1)
    if hit.numel() == 0:
        hit = torch.arange(len(rays))
    pick = hit[torch.linspace(0, hit.numel() - 1, min(n_rays, hit.numel())).long()]
    sub = rays[pick]
    sampler = replace(run.cfg.render_sampler, dars=False, perturb=False)
    with torch.no_grad(), _TorchHashGrid(run.field):
        r = render_rays(run.field, sub, run.render_config(sampler=sampler, deferred=composited),
                        RenderInputs(run.occupancy, run.l_env, run.background))
        if composited:
            from toolkit.render import accumulate_along_rays

            n = len(sub)
            hbar = accumulate_along_rays(r.weights, r.sample_features, r.sample_ray_indices, n)
            return {"feature": (hbar / r.opacity[:, None].clamp_min(1e-6)).detach(), "view_dirs": sub.directions}
    return {"points": r.sample_points.detach(), "view_dirs": sub.directions[r.sample_ray_indices].detach()}


def _torch_render(run, sc, index: int, dars: bool) -> tuple[np.ndarray, dict, float]:
    """The torch reference of the device renderer: the run's render sampler (DARS along-ray density only with
    ``dars``), shaded where the run shades (per sample, or per ray for a ``deferred`` run)."""
    sampler = run.cfg.render_sampler if dars else replace(run.cfg.render_sampler, dars=False)
    t0 = time.perf_counter()
    outs = run.render(sc.cameras, index, sampler=sampler, deferred=bool(run.cfg.deferred)).as_dict()
    return outs["rgb"].cpu().numpy(), outs, time.perf_counter() - t0


def _render_parity(run, sc, split: str, out: Path, cfg: FieldExportConfig, threads: int, log):
    """Render the parity view through ONNX Runtime (numpy renderer) and torch; raise beyond ``cfg.psnr_tol``.

    Returns:
        (report dict, ground-truth image [3, H, W], ONNX fp32 rgb [H, W, 3] linear).
    """
    rs_cfg, i = run.cfg.render_sampler, cfg.parity_index
    gt = sc.load_image(i).cpu().numpy()
    log(f"[export-onnx] rendering {split}:{i} through ONNX Runtime and torch ...")
    model = _infer.load_model(out, "fp32", threads)
    t0 = time.perf_counter()
    onnx_out = _infer.render_view(model, PinholeCamera.from_cameras(sc.cameras, i))
    t_onnx = time.perf_counter() - t0
    onnx_rgb = onnx_out["rgb"]
    torch_rgb, torch_out, t_torch = _torch_render(run, sc, i, dars=False)
    p_onnx, p_torch = _srgb_psnr(onnx_rgb, gt), _srgb_psnr(torch_rgb, gt)
    diffs = {k: np.abs(onnx_out[k] - torch_out[k].cpu().numpy()) for k in onnx_out if k in torch_out}
    rep = {"view": f"{split}:{i}", "psnr_onnx": p_onnx, "psnr_torch": p_torch, "delta_db": abs(p_onnx - p_torch),
           "psnr_onnx_vs_torch": _psnr_pair(onnx_rgb, torch_rgb),
           "max_abs_diff": {k: float(d.max()) for k, d in diffs.items()},
           # pixels whose |onnx − torch| > 1e-4 (any channel): a ray whose inverse-CDF draw falls within float32
           # rounding of a CDF plateau (a run of empty strata) puts that fine sample on the far side of the gap in
           # one renderer and the near side in the other — rare, and the only source of larger per-pixel differences
           "frac_pixels_over_1e-4": {k: float((d.reshape(d.shape[0], d.shape[1], -1) > 1e-4).any(-1).mean())
                                     for k, d in diffs.items()},
           "seconds_onnx": round(t_onnx, 3), "seconds_torch": round(t_torch, 3), "threads": threads,
           "torch_reference": f"render_image(deferred={bool(run.cfg.deferred)}, dars=None)"}
    if rs_cfg.dars and run.weight_maps is not None:
        rep["psnr_torch_dars"] = _srgb_psnr(_torch_render(run, sc, i, dars=True)[0], gt)
    log(f"[export-onnx] PSNR onnx {p_onnx:.3f} dB, torch {p_torch:.3f} dB (delta {abs(p_onnx - p_torch):.4f})")
    if not abs(p_onnx - p_torch) <= cfg.psnr_tol:
        raise OnnxParityError(f"{out}: the ONNX render of {split}:{i} has PSNR {p_onnx:.3f} dB, torch "
                              f"{p_torch:.3f} dB: |delta| {abs(p_onnx - p_torch):.4f} > {cfg.psnr_tol} dB",
                              abs(p_onnx - p_torch), out / "field.onnx")
    return rep, gt, onnx_rgb


def _clear_previous_bundle(out: Path) -> None:
    """Remove the files of an earlier export in ``out`` (only when its metadata.json says it is one), so a stale
    variant or network is never mistaken for part of the new bundle. Other files are left alone."""
    meta = out / "metadata.json"
    try:
        is_bundle = meta.is_file() and json.loads(meta.read_text()).get("format") == "dars-onnx"
    except (OSError, ValueError):
        is_bundle = False
    if is_bundle:
        for name in ("metadata.json", "field.onnx", "field_fp16.onnx", "field_int8.onnx", HEADS_FILE, "segment.onnx",
                     "light.onnx", "occupancy.npz", "background.npz"):
            (out / name).unlink(missing_ok=True)


# ============================================================================ the stage
def export_onnx_models(run_dir: str | os.PathLike, out_dir: str | os.PathLike, opset: int = 17,
                       precision: Sequence[str] = ("fp32",), cfg: FieldExportConfig = FieldExportConfig(),
                       log=None) -> OnnxModelsReport:
    """Export a trained run for devices and check every export against torch (module docstring).

    Args:
        run_dir: a run directory of ``dars train``.
        out_dir: output directory (created; files are overwritten).
        opset: ONNX opset, 13–17 (the graphs need nothing newer; ≥ 18 would need torch's dynamo exporter, which
            fails on the shading code in torch 2.13).
        precision: any of ``fp32`` (always written: it is the reference), ``fp16``, ``int8``.
        cfg: tolerances, parity view and optional model paths.
        log: callable for progress messages (default: silent).

    Returns:
        :class:`OnnxModelsReport` (also stored in ``metadata.json`` under ``"parity"``).

    Raises:
        DarsError: not a run directory, bad precision names.
        OnnxParityError: ONNX Runtime disagrees with torch beyond ``cfg.tol`` / ``cfg.psnr_tol`` (files are kept
            for inspection; ``metadata.json`` is not written).
    """
    from toolkit.train import load_run

    log = log or (lambda m: None)
    bad = [p for p in precision if p not in PRECISIONS]
    if bad:
        raise ConfigError(f"precision {bad} not supported: choose from {list(PRECISIONS)}")
    if not 13 <= int(opset) <= 17:
        raise ConfigError(f"opset={opset}: choose 13..17. The field needs nothing newer than 17 (Gather/Mod/Where, "
                          "no GridSample or bitwise ops); opset >= 18 would go through torch's dynamo exporter, which "
                          "cannot trace the shading's clamps in torch 2.13. If a runtime demands a newer opset, "
                          "convert field.onnx with onnx.version_converter.")
    run_dir, out = Path(run_dir), Path(out_dir)
    if not run_dir.is_dir():
        raise DarsError(f"RUN directory not found: {run_dir} (give the --out directory of `dars train`)")
    run = load_run(run_dir, with_weights=cfg.check_render)  # W maps: only for the torch-with-DARS figure
    run.field.eval()
    sc, split = _parity_scene(run, cfg)
    out.mkdir(parents=True, exist_ok=True)
    _clear_previous_bundle(out)
    threads = cfg.threads or torch.get_num_threads()
    fld, shading = run.field, run.cfg.shading
    aabb = run.train_scene.aabb.detach().cpu().float()
    ins, outs_sig = field_io_signature(shading, fld.cfg.n_classes, fld.feature_dim)
    out_names = list(outs_sig)
    l_env = run.l_env.detach().cpu().float().reshape(9, 3)
    meta_props = {
        "dars.kind": "field",
        "dars.version": _dars_version(),
        "dars.opset": str(opset),
        "dars.shading": shading,
        "dars.conventions": CONVENTIONS,
        "dars.sh_order": "(0,0) (1,-1) (1,0) (1,1) (2,-2) (2,-1) (2,0) (2,1) (2,2)",
        "dars.sh_constants": json.dumps([SH_C0, SH_C1, SH_C2, SH_C3, SH_C4]),
        "dars.l_env": json.dumps(l_env.tolist()),
        "dars.aabb": json.dumps(aabb.tolist()),
        "dars.contraction": json.dumps(bool(fld.cfg.contraction)),
        "dars.far_radius": repr(float(fld.cfg.far_radius)),
        "dars.density_scale": repr(fld.density_scale),
        "dars.density_units": "1/metre (alpha = 1 - exp(-density * delta_t))",
        "dars.inputs": json.dumps(ins),
        "dars.outputs": json.dumps(outs_sig),
        "dars.hash_grid": ("hash_grid_encode_torch: trilinear gather, int64 Mul/Add/Mod sum hash, no GridSample"
                           if fld.cfg.encoding == "grid" else "none (mlp encoding: positional encoding + LayerNorm)"),
    }
    # ---------------------------------------------------------------- field.onnx (+ example parity, checker)
    log("[export-onnx] field.onnx ...")
    t0 = time.perf_counter()
    rep = export_field_onnx(fld, out / "field.onnx", l_env, shading, opset, meta_props, cfg.tol)
    export_s = time.perf_counter() - t0
    sess = _infer.make_session(out / "field.onnx", threads)
    module = FieldOnnxModule(fld, shading).eval()
    # ---------------------------------------------------------------- random + real inputs
    pts, dirs = _random_inputs(aabb, cfg.n_random, seed=0, far_radius=_far_radius(fld))
    rnd = {"points": pts, "view_dirs": dirs}
    real = _real_inputs(run, sc, cfg.parity_index, cfg.n_real_rays)
    if shading == "pbr":
        rnd["sh"] = l_env
        real["sh"] = l_env
    with _TorchHashGrid(fld):
        ra, rs = _compare(module, sess, rnd, out_names)
        ea, es = _compare(module, sess, real, out_names)
    field_rep = {"random": ra, "real": ea, "random_scaled": rs, "real_scaled": es,
                 "max_abs_err": max(list(ra.values()) + list(ea.values())),
                 "max_scaled_err": max(list(rs.values()) + list(es.values())),
                 "n_random": int(pts.shape[0]), "n_real": int(real["points"].shape[0]),
                 "real_view": f"{split}:{cfg.parity_index}", "export_seconds": round(export_s, 2),
                 "op_types": _op_types(out / "field.onnx"), "exporter": rep.exporter}
    if "GridSample" in field_rep["op_types"]:
        raise OnnxParityError("field.onnx contains GridSample, which the device path must not use",
                              float("inf"), out / "field.onnx")

    def _over(errs_abs, errs_scaled):
        return {k: v for k, v in errs_abs.items()
                if not np.isfinite(v) or (errs_scaled[k] if k == "density" else v) > cfg.tol}

    over = {**{f"random/{k}": v for k, v in _over(ra, rs).items()}, **{f"real/{k}": v for k, v in _over(ea, es).items()}}
    if over:
        raise OnnxParityError(f"{out / 'field.onnx'}: ONNX Runtime differs from torch beyond tol {cfg.tol:g}: {over} "
                              f"(random: {ra}; real: {ea})", max(over.values()), out / "field.onnx")
    log(f"[export-onnx] field parity: random max {max(ra.values()):.3g}, real max {max(ea.values()):.3g}")
    heads_meta = None
    if run.cfg.deferred:  # the run shades once per ray: the device renderer composites features, then the heads
        heads_meta, field_rep["heads"] = _export_heads(run, sc, out, opset, meta_props, cfg, threads)
        log(f"[export-onnx] {HEADS_FILE} parity: real max {field_rep['heads']['max_abs_err']:.3g}")
    # ---------------------------------------------------------------- bundle files
    _write_occupancy(out / "occupancy.npz", run.occupancy)
    bg_info = _write_background(out / "background.npz", run.background)
    rs_cfg = run.cfg.render_sampler
    metadata = {
        "format": "dars-onnx", "version": 1, "dars_version": _dars_version(), "opset": int(rep.opset),
        "run": str(run_dir.resolve()), "scene": run.scene_path, "step": run.step, "shading": shading,
        "srgb": bool(run.train_scene.srgb), "conventions": CONVENTIONS,
        "l_env": l_env.tolist(), "aabb": aabb.tolist(), "near": run.train_scene.near, "far": run.train_scene.far,
        "near_min": 0.05, "density_scale": fld.density_scale, "space": space_metadata(fld),
        "render_sampler": {"n_coarse": rs_cfg.n_coarse, "n_fine": rs_cfg.n_fine, "perturb": False,
                           "dars_in_run": bool(rs_cfg.dars), "dars_on_device": False,
                           "note": "the device renderer uses the hierarchical proposal only; DARS along-ray "
                                   "density needs the training W maps (render-time prior)"},
        "deferred_in_run": bool(run.cfg.deferred),
        "heads": heads_meta,
        "field": {"file": "field.onnx", "inputs": ins, "outputs": outs_sig,
                  "encoding": fld.cfg.encoding, "hash_grid": meta_props["dars.hash_grid"]},
        "occupancy": {"file": "occupancy.npz", "resolution": run.occupancy.resolution,
                      "occupied_fraction": run.occupancy.occupancy_fraction(),
                      "contraction": bool(run.occupancy.contraction), "far_radius": float(run.occupancy.far_radius)},
        "background": {"file": "background.npz", **bg_info},
        "semantic_classes": list(_infer.SEMANTIC_CLASSES),
    }
    # ---------------------------------------------------------------- segmenter and light network
    seg = _export_segmenter(run, out, opset, cfg)
    light = _export_light(run, out, opset, cfg)
    log(f"[export-onnx] segment.onnx: {seg['status']}; light.onnx: {light['status']}")
    # ---------------------------------------------------------------- rendered view (0.05 dB bar), variants
    meta_path = out / "metadata.json"
    meta_path.write_text(json.dumps(metadata, indent=2))  # the renderer reads it; rewritten with the report below
    try:
        render_rep, gt, onnx_rgb = (_render_parity(run, sc, split, out, cfg, threads, log) if cfg.check_render
                                    else (None, None, None))
        variants = {}
        for p in precision:
            if p == "fp32":
                continue
            variants[p] = _make_variant(p, out, module, rnd, real, out_names, sc, cfg, threads, gt, onnx_rgb)
            log(f"[export-onnx] {p}: {variants[p].get('psnr_vs_fp32', 'n/a')} dB vs fp32")
    except BaseException:
        meta_path.unlink(missing_ok=True)  # a failed export must not look complete
        raise
    files = {f.name: f.stat().st_size for f in sorted(out.iterdir()) if f.is_file() and not f.name.startswith(".")}
    report = OnnxModelsReport(out_dir=out, opset=int(rep.opset), files=files, field=field_rep, render=render_rep,
                              variants=variants, segment=seg, light=light)
    metadata["segment"] = seg
    metadata["light"] = light
    metadata["variants"] = {k: v.get("file") for k, v in variants.items()}
    metadata["parity"] = report.to_dict()
    meta_path.write_text(json.dumps(metadata, indent=2, default=_json_default))
    report.files["metadata.json"] = meta_path.stat().st_size
    return report


def _export_heads(run, sc, out: Path, opset: int, meta_props: dict, cfg: FieldExportConfig, threads: int
                  ) -> tuple[dict, dict]:
    """``heads.onnx`` of a ``deferred`` run, checked against torch on the composited features of a test view's
    rays (ONNX Runtime vs torch per output, ``cfg.tol``). Returns (metadata entry, parity report)."""
    fld, shading = run.field, run.cfg.shading
    ins, outs = heads_io_signature(shading, fld.cfg.n_classes, fld.feature_dim)
    module = HeadsOnnxModule(fld, shading).eval()
    real = _real_inputs(run, sc, cfg.parity_index, cfg.n_real_rays, composited=True)
    l_env = run.l_env.detach().cpu().float().reshape(9, 3)
    if shading == "pbr":
        real["sh"] = l_env
    example = tuple(v[:64] if k != "sh" else v for k, v in real.items())
    axes = {k: {0: "R"} for k in ["feature", "view_dirs", *outs]}
    props = {**meta_props, "dars.kind": "heads", "dars.inputs": json.dumps(ins), "dars.outputs": json.dumps(outs)}
    export_onnx(module, example, out / HEADS_FILE, list(ins), list(outs), dynamic_batch=False, opset=opset,
                metadata=props, dynamic_axes=axes, tol=cfg.tol, random_batch=0)
    sess = _infer.make_session(out / HEADS_FILE, threads)
    err, _ = _compare(module, sess, real, list(outs))
    bad = {k: v for k, v in err.items() if not v <= cfg.tol}
    if bad:
        raise OnnxParityError(f"{out / HEADS_FILE}: ONNX Runtime differs from torch beyond tol {cfg.tol:g}: {bad}",
                              max(bad.values()), out / HEADS_FILE)
    meta = {"file": HEADS_FILE, "inputs": ins, "outputs": outs,
            "use": "deferred shading: composite the field graph's 'feature' along each ray (Σ w h / Σ w), then run "
                   "this graph once per ray"}
    return meta, {"real": err, "max_abs_err": max(err.values()), "n_real": int(real["feature"].shape[0])}


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def _make_variant(p: str, out: Path, module, rnd, real, out_names, sc, cfg: FieldExportConfig, threads: int,
                  gt, fp32_rgb) -> dict:
    """Write ``field_<p>.onnx``; measure its error per output and the PSNR of the parity view vs fp32."""
    dst = out / _infer.FIELD_FILES[p]
    t0 = time.perf_counter()
    try:
        notes = make_fp16_variant(out / "field.onnx", dst) if p == "fp16" else \
            make_int8_variant(out / "field.onnx", dst, cfg.int8_gather)
        sess = _infer.make_session(dst, threads)
    except Exception as e:  # noqa: BLE001 - a failed optional variant is reported, not fatal
        return {"status": "failed", "reason": f"{type(e).__name__}: {e}"}
    res = {"status": "exported", "file": dst.name, "bytes": dst.stat().st_size, "notes": notes,
           "convert_seconds": round(time.perf_counter() - t0, 2)}
    with _TorchHashGrid(module.field):
        res["random"], _ = _compare(module, sess, rnd, out_names)
        res["real"], res["real_scaled"] = _compare(module, sess, real, out_names)
    if cfg.check_render and fp32_rgb is not None:
        model = _infer.load_model(out, p, threads)
        t1 = time.perf_counter()
        rgb = _infer.render_view(model, PinholeCamera.from_cameras(sc.cameras, cfg.parity_index))["rgb"]
        res["seconds_render"] = round(time.perf_counter() - t1, 3)
        res["psnr_vs_fp32"] = _psnr_pair(rgb, fp32_rgb)
        res["psnr_gt"] = _srgb_psnr(rgb, gt)
        res["psnr_gt_fp32"] = _srgb_psnr(fp32_rgb, gt)
        res["delta_db"] = res["psnr_gt_fp32"] - res["psnr_gt"]
    return res
