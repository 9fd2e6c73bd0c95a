"""ONNX export of the light estimation network (:class:`toolkit.lightnet.LightNet`).

Contract of the written file (``light.onnx``):

* input ``images``: float32 N x 3 x H x W, RGB, **sRGB-encoded** values in [0, 1] (photos as loaded); N, H and W are
  dynamic. The network was trained at ``dars.input_size`` (64) px: resize to it (area averaging) for the trained
  behaviour, as :func:`toolkit.lightnet.predict_sh` does — the resize stays outside the graph.
* input ``heading`` (networks with ``frame="heading"``, the shipped one): float32 N x 2, each photo's camera heading
  (cos ψ, sin ψ) of its forward direction turned horizontal (:func:`toolkit.lightnet.camera_heading` of its
  camera-to-world pose, world +z up). The graph turns its heading-frame answer into the world frame with it.
* output ``sh``: float32 N x 9 x 3 radiance SH, SPEC convention (real SH order 2, incident radiance, world frame
  +z up; rows (0,0) (1,-1) (1,0) (1,1) (2,-2) (2,-1) (2,0) (2,1) (2,2), columns r g b).
* metadata: ``dars.kind=lightnet``, ``dars.arch``, ``dars.input_size``, ``dars.output_range``, ``dars.frame``,
  ``dars.input``, ``dars.output``, ``dars.sh_convention``.

Parity with torch is checked on export (:func:`export.onnx.export_onnx`: example batch and a random batch of
another size); the measured error is in the returned report.
"""

from __future__ import annotations

import os

import torch

from export.onnx import OnnxExportReport, export_onnx
from toolkit._checks import ConfigError

__all__ = ["export_lightnet_onnx"]


def export_lightnet_onnx(model: torch.nn.Module, path: str | os.PathLike, image_size: int | None = None,
                         opset: int = 17, tol: float = 1e-4, batch: int = 2) -> OnnxExportReport:
    """Export a :class:`toolkit.lightnet.LightNet` with dynamic batch, height and width, and check parity.

    Args:
        model: the network (exported in eval mode; its mode is restored).
        path: output ``.onnx`` (one self-contained file, written atomically).
        image_size: square size of the example inputs (default ``model.cfg.input_size``).
        opset: ONNX opset (17: widely deployable).
        tol: largest accepted max |onnxruntime − torch| over the SH outputs.
        batch: example batch size (the random check uses ``batch + 3``).

    Returns:
        :class:`export.onnx.OnnxExportReport` (``max_abs_err`` is the parity figure).

    Raises:
        ConfigError: not a LightNet.
        OnnxParityError: ONNX Runtime differs from torch by more than ``tol``.
    """
    from toolkit.lightnet import LightNet

    if not isinstance(model, LightNet):
        raise ConfigError(f"export_lightnet_onnx expects a toolkit.lightnet.LightNet, got {type(model).__name__}")
    size = int(image_size or model.cfg.input_size)
    g = torch.Generator().manual_seed(0)
    example = torch.rand(batch, 3, size, size, generator=g)
    heading = model.cfg.frame == "heading"
    angles = torch.rand(batch, generator=g) * 6.283185307179586
    inputs = (example, torch.stack([angles.cos(), angles.sin()], 1)) if heading else (example,)
    meta = {
        "dars.kind": "lightnet",
        "dars.arch": model.cfg.name,
        "dars.input_size": str(model.cfg.input_size),
        "dars.output_range": model.cfg.output_range,
        "dars.frame": model.cfg.frame,
        "dars.input": "images: float32 N x 3 x H x W, RGB, sRGB-encoded, [0, 1]; trained at dars.input_size px"
                      + ("; heading: float32 N x 2, (cos, sin) of each camera's forward direction turned horizontal "
                         "(world +z up)" if heading else ""),
        "dars.output": "sh: float32 N x 9 x 3 radiance SH coefficients (rows k = 0..8, columns r, g, b)",
        "dars.sh_convention": "real SH order 2, SPEC order (0,0) (1,-1) (1,0) (1,1) (2,-2) (2,-1) (2,0) (2,1) (2,2), "
                              "incident radiance, world frame +z up",
    }
    return export_onnx(model, inputs, path, ["images", "heading"][:len(inputs)], ["sh"], dynamic_batch=True,
                       opset=opset, metadata=meta, dynamic_axes={"images": {2: "height", 3: "width"}}, tol=tol)
