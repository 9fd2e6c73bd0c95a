"""Shared by tests/test_onnx_field.py and tests/test_infer.py: one small run on the bundled sample, exported once
per pytest session (cached under the session's base temp dir, so the second module reuses it).

The run: ``fast`` preset, 120 steps of 1024 rays on samples/gallery (about a minute on one core), DARS on (so the
report also carries the torch-with-DARS PSNR). The export: fp32 + fp16 + int8, an (untrained, seeded) built-in
segmenter and, when ``toolkit.lightnet`` is importable, an untrained ``small`` light network.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "gallery"


def small_config(**kw):
    from toolkit.train import make_config

    base = dict(steps=120, batch_rays=1024, ssim_patches=1, occupancy_warmup=32, log_every=50,
                checkpoint_every=10_000)
    base.update(kw)
    return make_config("fast", **base)


def light_available() -> bool:
    try:
        import export.onnx_light  # noqa: F401
        from toolkit.lightnet import LightNet, lightnet_config, save_lightnet  # noqa: F401
    except ImportError:
        return False
    return True


def build_bundle(base: Path) -> dict:
    """Train (if needed) and export (if needed); returns ``{"run", "out", "meta", "segmenter", "light"}``."""
    from export.field_onnx import FieldExportConfig, export_onnx_models
    from toolkit.segment import Segmenter, save_segmenter
    from toolkit.train import train

    base.mkdir(parents=True, exist_ok=True)
    run, out = base / "run", base / "onnx"
    seg, light = base / "segmenter.pt", base / "lightnet.pt"
    if not (out / "metadata.json").is_file() or "parity" not in json.loads((out / "metadata.json").read_text()):
        n = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            if not (run / "checkpoint.pt").is_file():
                # DARS on, whatever the default sampler: the parity report then covers it too
                train(SAMPLE, run, small_config(dars=True), progress_bar=False, log=lambda m: None)
            torch.manual_seed(0)
            save_segmenter(seg, Segmenter())
            light_model = None
            if light_available():
                from toolkit.lightnet import LightNet, lightnet_config, save_lightnet

                torch.manual_seed(0)
                save_lightnet(light, LightNet(lightnet_config("small")))
                light_model = str(light)
            cfg = FieldExportConfig(threads=1, segmenter=str(seg), light_model=light_model)
            export_onnx_models(run, out, precision=("fp32", "fp16", "int8"), cfg=cfg)
        finally:
            torch.set_num_threads(n)
    return {"run": run, "out": out, "meta": json.loads((out / "metadata.json").read_text()), "segmenter": seg,
            "light": light}
