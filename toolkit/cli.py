"""The ``dars`` command line. Subcommands only parse arguments, call stages and write outputs.

Every command prints a clear error and exits non-zero on bad input; with ``--json`` it prints
machine-readable output on stdout and nothing else there (progress and logs go to stderr).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable

from ._checks import DarsError

Handler = Callable[[argparse.Namespace], int]


def _print_json(obj) -> None:
    sys.stdout.write(json.dumps(obj, indent=2) + "\n")


# ---------------------------------------------------------------------------- info
def scene_info(path: str | Path) -> dict:
    """Everything ``dars info`` reports about a scene, as a dict (no pixels are decoded)."""
    from .scene import list_splits, load_scene

    path = Path(path)
    splits = list_splits(path)
    info: dict = {"scene": str(path), "splits": {}}
    first = None
    for s in splits:
        if s == "all" and len(splits) > 1 and "train" in splits:
            continue
        sc = load_scene(path, s)
        first = first or sc
        h, w = sc.image_size
        info["splits"][s] = {
            "frames": len(sc),
            "image_size": [w, h],
            "ground_truth": sc.extras_available(),
        }
    cams = first.cameras
    info["format"] = first.meta.get("format", "transforms json")
    info["source"] = str(first.source)
    info["intrinsics"] = {
        "fx": float(cams.fx[0]), "fy": float(cams.fy[0]), "cx": float(cams.cx[0]), "cy": float(cams.cy[0]),
        "shared": bool((cams.fx == cams.fx[0]).all() and (cams.cx == cams.cx[0]).all()),
        "distortion": first.frames[0].distortion is not None,
    }
    info["aabb"] = first.aabb.tolist()
    info["near_far"] = [first.near, first.far] if first.near is not None else None
    info["sh"] = first.sh.tolist() if first.sh is not None else None
    info["envmap"] = str(first.envmap_path) if first.envmap_path else None
    return info


def cmd_info(args: argparse.Namespace) -> int:
    info = scene_info(args.scene)
    if args.json:
        _print_json(info)
        return 0
    print(f"scene     {info['scene']}  ({info['format']})")
    for s, d in info["splits"].items():
        gt = ", ".join(d["ground_truth"]) or "none"
        print(f"  {s:<6} {d['frames']:>4} frames  {d['image_size'][0]}x{d['image_size'][1]} px   ground truth: {gt}")
    k = info["intrinsics"]
    print(f"intrinsics fx={k['fx']:.2f} fy={k['fy']:.2f} cx={k['cx']:.2f} cy={k['cy']:.2f} "
          f"({'shared' if k['shared'] else 'per frame'}{', undistorted on load' if k['distortion'] else ''})")
    lo, hi = info["aabb"]
    print(f"bounds    [{lo[0]:.2f}, {lo[1]:.2f}, {lo[2]:.2f}] .. [{hi[0]:.2f}, {hi[1]:.2f}, {hi[2]:.2f}] m")
    if info["near_far"]:
        print(f"near/far  {info['near_far'][0]} / {info['near_far'][1]}")
    print(f"GT light  {'SH (27 coefficients)' if info['sh'] else 'none'}"
          f"{'; env map ' + info['envmap'] if info['envmap'] else ''}")
    return 0


def cmd_contact_sheet(args: argparse.Namespace) -> int:
    from .preview import contact_sheet
    from .scene import load_scene

    scene = load_scene(args.scene, args.split)
    out = contact_sheet(scene, Path(args.out), n=args.n)
    print(f"wrote {out}")
    return 0


# ---------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dars",
        description="DARS-NeRF toolkit: posed photos of galleries -> decomposed digital twins "
                    "(geometry, PBR materials, SH lighting, semantics), glTF, ONNX and previews.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    q = sub.add_parser("info", help="frames per split, image size, intrinsics, bounds, ground truth")
    q.add_argument("scene", help="scene directory, transforms JSON, COLMAP model or tiny-NeRF .npz")
    q.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    q.set_defaults(func=cmd_info)

    q = sub.add_parser("contact-sheet", help="a PNG grid of images and their ground-truth maps")
    q.add_argument("scene")
    q.add_argument("--split", default="train")
    q.add_argument("--out", required=True, help="output PNG")
    q.add_argument("-n", type=int, default=6, help="number of views")
    q.set_defaults(func=cmd_contact_sheet)

    from . import _cli_train

    _cli_train.add_parser(sub)
    for register in _REGISTRARS:
        register(sub)
    return p


_COMMAND_MODULES: tuple[tuple[str, str], ...] = (
    ("_cli_priors", "priors"),  # weights, segment, colour, light; sh-probe from _cli_sh
    ("_cli_asset", "mesh, bake, export-asset"),
    ("_cli_view", "view, export-web"),
    ("_cli_export", "export-onnx, infer"),
    ("_cli_eval", "eval, ablate"),
    ("_cli_poses", "poses"),
)
"""Modules that register subcommands with ``add_parser(subparsers)``, imported lazily so one broken optional
dependency cannot take the whole CLI down."""


def _register_modules(sub: argparse._SubParsersAction) -> None:
    import importlib

    for module, commands in _COMMAND_MODULES:
        try:
            mod = importlib.import_module(f".{module}", __package__)
        except ImportError as e:
            print(f"dars: {commands!r} unavailable ({e})", file=sys.stderr)
            continue
        mod.add_parser(sub)


_REGISTRARS: list[Callable[[argparse._SubParsersAction], None]] = [_register_modules]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except DarsError as e:
        print(f"dars {args.command}: error: {e}", file=sys.stderr)
        return 2
    except FileNotFoundError as e:
        print(f"dars {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dars {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
