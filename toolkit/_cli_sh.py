"""``dars priors sh-probe FILE``: fit order-2 SH to an HDR environment map (handler for ``toolkit.cli``).

The subcommand only parses, calls :func:`toolkit.sh.fit_sh_probe` and writes outputs. Wiring (by ``toolkit/cli.py``)::

    from . import _cli_sh
    _cli_sh.add_parser(priors_subparsers)   # adds "sh-probe", sets func=_cli_sh.main

Output: a table of the 9 x 3 coefficients on stdout (or, with ``--json``, only the JSON document on stdout), and the
same JSON written atomically to ``<stem>.sh.json`` beside the probe, or to ``--out``. An existing file is never
overwritten without ``--force``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

__all__ = ["add_parser", "main", "build_payload"]

_LM = ["(0,0)", "(1,-1)", "(1,0)", "(1,1)", "(2,-2)", "(2,-1)", "(2,0)", "(2,1)", "(2,2)"]


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``sh-probe`` on an ``argparse`` sub-parsers object and return the new parser."""
    p = subparsers.add_parser(
        "sh-probe",
        help="fit 27 SH coefficients (SPEC convention) to an HDR probe (.hdr/.exr)",
        description="Project an HDR environment map (lat-long or angular light probe) onto order-2 real spherical "
        "harmonics of incident radiance, SPEC convention (world +z up). Angular probes are captured +y up: pass "
        "--rotate-x 90 to bring them into the +z-up world.",
    )
    p.add_argument("file", help="environment map, Radiance .hdr or OpenEXR .exr")
    p.add_argument("--layout", choices=["latlong", "angular"], default="latlong", help="map parametrisation (default: latlong)")
    p.add_argument("--rotate-x", type=float, default=0.0, metavar="DEG", help="rotate map directions about +x by DEG degrees before fitting (90 for a +y-up probe)")
    p.add_argument("--out", default=None, help="output JSON path (default: <stem>.sh.json beside FILE)")
    p.add_argument("--no-save", action="store_true", help="do not write the JSON file, only print")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.add_argument("--json", action="store_true", help="print only machine-readable JSON on stdout")
    p.set_defaults(func=main)
    return p


def build_payload(path: Path, layout: str, rotate_x_deg: float) -> dict[str, Any]:
    """Read the map, fit it and return the JSON document (no output written)."""
    from .sh import fit_sh_probe, read_envmap, rotation_x, sh_to_gltf_ibl, sh_to_threejs_lightprobe

    image = read_envmap(path)
    rotation = rotation_x(rotate_x_deg) if rotate_x_deg else None
    probe = fit_sh_probe(image, layout=layout, rotation=rotation)
    return {
        "coeffs": probe.to_list(),
        "file": str(path),
        "layout": layout,
        "rotate_x_deg": float(rotate_x_deg),
        "shape": list(probe.source_shape),
        "dc_irradiance": [float(v) for v in probe.dc_irradiance.tolist()],
        "convention": "real SH order 2, SPEC order, incident radiance, world +z up, coeffs 9 x [r, g, b]",
        "threejs": sh_to_threejs_lightprobe(probe.coeffs),
        "gltf": sh_to_gltf_ibl(probe.coeffs),
    }


def _table(payload: dict[str, Any]) -> str:
    lines = [f"SH probe of {payload['file']} ({payload['layout']}, {payload['shape'][0]}x{payload['shape'][1]})", f"{'k':>2} {'(l,m)':>7} {'R':>12} {'G':>12} {'B':>12}"]
    for k, (lm, rgb) in enumerate(zip(_LM, payload["coeffs"])):
        lines.append(f"{k:>2} {lm:>7} " + " ".join(f"{v:12.6f}" for v in rgb))
    dc = payload["dc_irradiance"]
    lines.append(f"DC irradiance (π · mean radiance): {dc[0]:.5g} {dc[1]:.5g} {dc[2]:.5g}")
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    """Run the subcommand; returns the process exit code (0 ok, 2 bad input)."""
    from ._checks import DarsError
    from .io import write_json

    path = Path(args.file)
    try:
        payload = build_payload(path, args.layout, float(args.rotate_x))
    except DarsError as e:
        print(f"dars priors sh-probe: error: {e}", file=sys.stderr)
        return 2
    out = None
    if not getattr(args, "no_save", False):
        out = Path(args.out) if args.out else path.with_name(path.stem + ".sh.json")
        if out.exists() and not args.force:
            print(f"dars priors sh-probe: error: {out} exists; pass --force to overwrite it or --out to write elsewhere", file=sys.stderr)
            return 2
        try:
            write_json(out, payload)
        except OSError as e:
            print(f"dars priors sh-probe: error: could not write {out}: {e} (use --out or --no-save)", file=sys.stderr)
            return 2
    if args.json:
        sys.stdout.write(json.dumps(payload) + "\n")
    else:
        print(_table(payload))
        if out is not None:
            print(f"wrote {out}")
    return 0
