"""``dars priors light SCENE`` — the light estimation network (stage 4) on a scene's photos.

Runs :class:`toolkit.lightnet.LightNet` (default: the shipped ``toolkit/weights/lightnet_small.pt``) on every
image of the split (batched), combines the per-image SH into one estimate — the **mean** of the predictions
(``--reduce median``: the per-coefficient median, robust to a few odd views) — and writes
``<scene>/priors/light/light.json`` (or ``--out DIR``)::

    {"coeffs": [[r, g, b] x 9], "per_image": [{"key": ..., "coeffs": [[r, g, b] x 9]}, ...],
     "model": {...}, "source": "lightnet", "reduce": "mean", "evaluation": {...} | null, ...}

``dars train`` reads ``coeffs`` from there to initialise ``l_env``. When the scene has ground-truth ``"sh"``, the
Env-light L2 (eq. 36) of the estimate is reported next to the two baselines: (a) the training-set mean SH stored
with the weights, (b) the SH of the images' mean colour.

Registered on ``dars priors`` by :func:`register` (``toolkit/_cli_priors.py`` imports this module).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["register", "priors_light", "cmd_light"]

_LM = ["(0,0)", "(1,-1)", "(1,0)", "(1,1)", "(2,-2)", "(2,-1)", "(2,0)", "(2,1)", "(2,2)"]


def priors_light(scene, out_dir=None, weights: str | None = None, reduce: str = "mean", batch_size: int = 32,
                 force: bool = False) -> dict:
    """Estimate the scene's SH lighting with the light network and write ``light.json``; returns its content.

    Args:
        scene: a loaded :class:`toolkit.scene.Scene` (sRGB photos; linear HDR scenes are clipped to [0, 1] and
            sRGB-encoded first, as the network was trained on 8-bit-style photos).
        out_dir: output folder (path or :class:`toolkit._cli_priors.OutputDir`; ``None``: ``scene.priors_dir("light")``).
        weights: a file written by :func:`toolkit.lightnet.save_lightnet` (``None``: the shipped weights).
        reduce: ``mean`` or ``median`` of the per-image predictions.
        batch_size: images per forward pass (images are loaded batch by batch).
        force: overwrite files in the folder that dars did not write.

    Raises:
        LightNetError: missing or corrupt weights; DarsError: unwritable folder, user files in the way.
    """
    import torch

    from ._cli_priors import _progress, prepare_out_dir
    from .io import linear_to_srgb, write_json
    from .lightnet import DEFAULT_WEIGHTS, aggregate_sh, load_lightnet, mean_colour_sh, predict_sh
    from .metrics import env_light_l2

    if reduce not in ("mean", "median"):
        from ._checks import ConfigError

        raise ConfigError(f"--reduce {reduce!r}: choose 'mean' or 'median'")
    model = load_lightnet(weights)  # fail before touching the output folder
    out = prepare_out_dir(scene, "light", out_dir, ["light.json"], force)
    per, base_b = [], []
    for i in _progress(range(0, len(scene), batch_size), "light", (len(scene) + batch_size - 1) // batch_size):
        imgs = torch.stack([scene.load_image(j) for j in range(i, min(i + batch_size, len(scene)))]).float()
        if not scene.srgb:
            imgs = linear_to_srgb(imgs.clamp(0.0, 1.0))
        per.append(predict_sh(model, imgs, batch_size))
        base_b.append(mean_colour_sh(imgs))
    per_image = torch.cat(per)
    coeffs = aggregate_sh(per_image, reduce)
    meta = model.meta
    info: dict = {
        "coeffs": coeffs.tolist(),
        "source": "lightnet",
        "reduce": reduce,
        "per_image": [{"key": f.key, "coeffs": c.tolist()} for f, c in zip(scene.frames, per_image)],
        "model": {"path": str(Path(weights) if weights else DEFAULT_WEIGHTS), "arch": model.cfg.name,
                  "parameters": model.num_parameters(), "input_size": model.cfg.input_size,
                  "output_range": model.cfg.output_range, "training_command": meta.get("training_command"),
                  "heldout_env_light_l2": meta.get("heldout_env_light_l2")},
        "scene": str(scene.source), "split": scene.split, "views": len(scene),
        "convention": "real SH order 2, SPEC order, incident radiance, world frame +z up, coeffs 9 x [r, g, b]",
        "note": "world-frame bands 1-2 are only meaningful for rooms like the one the network was trained on",
        "evaluation": None,
    }
    if scene.sh is not None:
        gt = scene.sh.float()
        ev = {"env_light_l2": float(env_light_l2(coeffs, gt)),
              "env_light_l2_per_image_mean": float(env_light_l2(per_image, gt[None].expand_as(per_image)).mean()),
              "baseline_mean_colour": float(env_light_l2(aggregate_sh(torch.cat(base_b), reduce), gt))}
        if "train_mean_sh" in meta:
            ev["baseline_train_mean_sh"] = float(env_light_l2(torch.tensor(meta["train_mean_sh"]).float(), gt))
        ev["gt"] = gt.tolist()
        info["evaluation"] = ev
    info["out"] = str(out.path)
    write_json(out.file("light.json"), info)
    out.finish({"scene": str(scene.source), "split": scene.split})
    return info


def cmd_light(args: argparse.Namespace) -> int:
    from .scene import load_scene

    scene = load_scene(args.scene, args.split)
    info = priors_light(scene, args.out, args.weights, args.reduce, args.batch_size, args.force)
    if args.json:
        import json

        sys.stdout.write(json.dumps(info, indent=2) + "\n")
        return 0
    ev = info["evaluation"]
    head = f"{'k':>2} {'(l,m)':>7} {'R':>9} {'G':>9} {'B':>9}" + (f"   {'GT R':>8} {'GT G':>8} {'GT B':>8}" if ev else "")
    print(f"SH lighting of {info['scene']} [{info['split']}, {info['views']} views], {info['reduce']} of the "
          f"per-image predictions of {info['model']['arch']} ({info['model']['path']})")
    print(head)
    for k, (lm, rgb) in enumerate(zip(_LM, info["coeffs"])):
        line = f"{k:>2} {lm:>7} " + " ".join(f"{v:9.4f}" for v in rgb)
        if ev:
            line += "   " + " ".join(f"{v:8.4f}" for v in ev["gt"][k])
        print(line)
    if ev:
        parts = [f"network {ev['env_light_l2']:.4f} (per image {ev['env_light_l2_per_image_mean']:.4f})"]
        if "baseline_train_mean_sh" in ev:
            parts.append(f"baseline training-set mean SH {ev['baseline_train_mean_sh']:.4f}")
        parts.append(f"baseline image mean colour {ev['baseline_mean_colour']:.4f}")
        print("Env-light L2 vs GT (eq. 36): " + "; ".join(parts))
    print(f"-> {Path(info['out']) / 'light.json'}")
    return 0


def register(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``light`` to the ``dars priors`` sub-parsers."""
    q = sub.add_parser("light", help="SH lighting from the photos with the light estimation network (eq. 11)",
                       description="Run the light network on every image of a split and write priors/light/light.json "
                                   "(mean of the per-image SH; dars train initialises l_env from it).")
    q.add_argument("scene", help="scene directory, transforms JSON, COLMAP model or tiny-NeRF .npz")
    q.add_argument("--split", default="train", help="split to process (default: train)")
    q.add_argument("--out", default=None, help="output directory (default: <scene>/priors/light)")
    q.add_argument("--weights", default=None, help="light-network weights (default: toolkit/weights/lightnet_small.pt)")
    q.add_argument("--reduce", choices=["mean", "median"], default="mean", help="combine per-image SH (default: mean)")
    q.add_argument("--batch-size", type=int, default=32)
    q.add_argument("--force", action="store_true", help="overwrite files in the output directory that dars did not write")
    q.add_argument("--json", action="store_true", help="print only JSON on stdout")
    q.set_defaults(func=cmd_light)
    return q
