"""How much of a room's light do its photos show? A trained run renders a light probe of itself — a cube map of the
field's own radiance, seen from the point where a procedural gallery measured its ground-truth light
(``render.sh_point`` in the transforms JSON) — and this benchmark compares it with the truth:

* Env-light L2 (eq. 36) of the probe's SH projection against the gallery's ``"sh"``, beside the light network's
  estimate the run started from (``l_env_init``) and the run's final ``l_env`` (``hdr``: ``light.hdr``'s own SH
  against ``"sh"``, a check of frames and units, small but not 0: the map's lamps are splats);
* band 0 of the probe over the truth's (per channel: the light's level);
* the mean radiance of three belts of directions — up (z > 0.5), horizon (|z| <= 0.5), down (z < -0.5) — in the
  probe and in the gallery's ``light.hdr`` (the true probe, lamps splatted), as ratios probe / truth.

A field that reproduces its photos draws the belts the photos saw (the horizon: walls, paintings) as they are; the
ones they did not (lamps, skylights, the sky through an open top) it draws as whatever it learned there. So a
horizon ratio near 1 with an "up" ratio far below it says the light comes from where no photo looked, and no
reconstruction of the room can measure it: the light must come from a prior (the light network, issue 17).

Usage (a run trained on a procedural gallery; its ground truth is read for scoring only)::

    OMP_NUM_THREADS=2 .venv/bin/python bench/bench_light_probe.py RUN [RUN ...] [--face 32] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from toolkit.cameras import Cameras, generate_rays  # noqa: E402
from toolkit.io import write_json  # noqa: E402
from toolkit.metrics import env_light_l2  # noqa: E402
from toolkit.pinhole import look_at  # noqa: E402
from toolkit.sh import latlong_directions, latlong_solid_angles, read_envmap, sh_basis  # noqa: E402
from toolkit.train import load_run  # noqa: E402

FACES = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))
BELTS = {"up": lambda z: z > 0.5, "horizon": lambda z: z.abs() <= 0.5, "down": lambda z: z < -0.5}


def cube_cameras(point: np.ndarray, face: int) -> tuple[Cameras, torch.Tensor]:
    """Six 90° cameras at ``point`` looking along ±x, ±y, ±z (:data:`FACES`), ``face`` px square, and the solid
    angle of each of a face's pixels (row-major, float64 [face²]; the six faces' sum to 4π)."""
    c2w = [torch.from_numpy(look_at(point, point + np.array(d, float), (0, 0, 1) if abs(d[2]) < 0.5 else (0, 1, 0)))
           for d in FACES]
    f = torch.full((6,), face / 2.0)
    cams = Cameras(torch.stack(c2w).float(), f, f, f.clone(), f.clone(), torch.full((6,), face), torch.full((6,), face))
    v, u = torch.meshgrid(torch.arange(face), torch.arange(face), indexing="ij")
    x, y = ((u.reshape(-1) + 0.5) / face * 2 - 1).double(), ((v.reshape(-1) + 0.5) / face * 2 - 1).double()
    return cams, (2.0 / face) ** 2 / (1 + x * x + y * y) ** 1.5


def cube_directions(cams: Cameras) -> torch.Tensor:
    """Unit directions of every pixel of the six cameras, float64 [6 · face², 3]."""
    d = generate_rays(cams).directions.reshape(-1, 3).double().cpu()
    return d / d.norm(dim=-1, keepdim=True)


def field_probe(run, point: np.ndarray, face: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The run's radiance over a cube map at ``point``: (directions [M, 3], radiance [M, 3], solid angles [M])."""
    cams, d_omega = cube_cameras(point, face)
    with torch.no_grad():
        rad = torch.cat([run.render(cams, i).rgb.detach().reshape(-1, 3).double().cpu() for i in range(6)])
    return cube_directions(cams), rad, d_omega.repeat(6)


def project_sh(dirs: torch.Tensor, rad: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    return ((sh_basis(dirs.float()).double() * w[:, None]).T @ rad).float()  # [9, 3]


def belt_means(dirs: torch.Tensor, rad: torch.Tensor, w: torch.Tensor) -> dict[str, np.ndarray]:
    out = {}
    for name, sel in BELTS.items():
        m = sel(dirs[:, 2])
        out[name] = ((rad[m] * w[m, None]).sum(0) / w[m].sum()).numpy()
    return out


def score(run_dir: str, face: int) -> dict:
    run = load_run(run_dir)
    sc = run.train_scene
    if sc.sh is None:
        raise SystemExit(f"{run_dir}: its scene has no ground-truth 'sh' to score against")
    point_raw = (sc.meta.get("render") or {}).get("sh_point")
    if point_raw is None:
        raise SystemExit(f"{run_dir}: its scene's JSON has no render.sh_point (a procedural gallery's probe point)")
    # the run's world is the JSON's turned upright where load_scene did so (a rotation, no shift or scale)
    upright = sc.meta.get("upright") or {}
    rot = np.asarray(upright["rotation"], float) if upright.get("applied") else np.eye(3)
    point = rot @ np.asarray(point_raw, float)
    gt = sc.sh.float()
    dirs, rad, w = field_probe(run, point, face)
    sh = project_sh(dirs, rad, w)
    env = torch.as_tensor(read_envmap(Path(run.scene_path) / "light.hdr"), dtype=torch.float64)[..., :3]
    gdirs = latlong_directions(*env.shape[:2], dtype=torch.float64).reshape(-1, 3)
    gdirs = gdirs @ torch.as_tensor(rot).T  # into the run's world, as the SH truth
    gw = latlong_solid_angles(*env.shape[:2], dtype=torch.float64).reshape(-1)
    true_belts = belt_means(gdirs, env.reshape(-1, 3), gw)
    # a check of frames and units: light.hdr's own SH against the JSON's (the lamps are splatted into the map)
    hdr_check = float(env_light_l2(project_sh(gdirs, env.reshape(-1, 3), gw), gt))
    field_belts = belt_means(dirs, rad, w)
    init = torch.tensor(json.loads((Path(run_dir) / "config.json").read_text())["l_env_init"]).float()
    return {
        "run": str(run_dir), "point": np.round(point, 3).tolist(),
        "env_light_l2": {"field_probe": float(env_light_l2(sh, gt)), "light_prior": float(env_light_l2(init, gt)),
                         "final_l_env": float(env_light_l2(run.l_env.detach().float().cpu(), gt)),
                         "light_hdr_check": hdr_check},
        "band0_probe_over_truth": np.round((sh[0] / gt[0]).numpy(), 3).tolist(),
        "belt_probe_over_truth": {k: float((field_belts[k] / np.maximum(true_belts[k], 1e-9)).mean()) for k in BELTS},
        "belt_truth_radiance": {k: float(true_belts[k].mean()) for k in BELTS},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run directories trained on procedural galleries")
    ap.add_argument("--face", type=int, default=32, help="cube-map face size, pixels (default 32)")
    ap.add_argument("--json", default=str(ROOT / "bench" / "out" / "light_probe.json"))
    args = ap.parse_args()
    rows = [score(r, args.face) for r in args.runs]
    print(f"{'run':44s} {'L2 probe':>8s} {'prior':>6s} {'final':>6s} {'hdr':>5s}  band0 probe/truth   belts probe/truth "
          "(up, horizon, down)   truth up/horizon")
    for r in rows:
        e, b = r["env_light_l2"], r["belt_probe_over_truth"]
        t = r["belt_truth_radiance"]
        print(f"{r['run'][-44:]:44s} {e['field_probe']:8.2f} {e['light_prior']:6.2f} {e['final_l_env']:6.2f} {e['light_hdr_check']:5.2f}  "
              f"{np.mean(r['band0_probe_over_truth']):.2f}                {b['up']:.2f} {b['horizon']:.2f} {b['down']:.2f}"
              f"                   {t['up'] / max(t['horizon'], 1e-9):.1f}")
    if len(rows) > 1:
        for k in ("up", "horizon", "down"):
            v = [r["belt_probe_over_truth"][k] for r in rows]
            print(f"belt {k:8s} probe / truth: mean {np.mean(v):.2f}, range {min(v):.2f}-{max(v):.2f}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, rows)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
