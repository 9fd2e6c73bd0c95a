"""Poses from photos alone (issue 18, SPEC stage 0): ``dars poses`` on the real fox capture against its given poses.

1. ``dars poses ../shared/data/real/fox/images --out bench/out/poses/fox_scene`` (all 50 phone frames, 540x960,
   plain defaults: SIFT, exhaustive matching, SIMPLE_RADIAL, one camera) — run as the user runs it, through the CLI;
2. the recovered cameras are compared with the fox's ``transforms.json`` (instant-ngp's colmap2nerf output: its own
   COLMAP run, then re-centred, scaled and rotated; NeRF/OpenGL convention like ours) after a similarity alignment
   (Umeyama on the camera centres): rotation error = angle of ``R_aligned^T R_given`` per camera, centre error =
   distance / camera spread (RMS distance of the given centres to their mean).

Targets (issue 18): >= 95 % of the photos registered, median rotation error <= 2 deg.
Prints registered/total, reprojection error, time, rotation and centre errors; writes
``bench/out/poses/bench_poses.json``.

Usage: ``python bench/bench_poses.py [--photos DIR] [--reference transforms.json] [--max-size 1600]
[--threads 2] [--out bench/out/poses] [--reuse]`` (``--reuse``: compare the scene left by an earlier run).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("DARS_SHARED_DATA", ROOT / ".." / "shared" / "data")).resolve()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photos", default=str(SHARED / "real" / "fox" / "images"))
    ap.add_argument("--reference", default=str(SHARED / "real" / "fox" / "transforms.json"),
                    help="transforms JSON with the given poses (matched to ours by file name)")
    ap.add_argument("--max-size", type=int, default=1600)
    ap.add_argument("--matcher", default="auto")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(ROOT / "bench" / "out" / "poses"))
    ap.add_argument("--reuse", action="store_true", help="compare the scene an earlier run left in OUT (no SfM run)")
    args = ap.parse_args()

    import numpy as np

    from toolkit.scene import load_scene
    from toolkit.upright import compare_poses

    photos, ref_file = Path(args.photos), Path(args.reference)
    if not photos.is_dir() or not ref_file.is_file():
        print(f"bench_poses: skipped, data not present ({photos}, {ref_file})")
        return 0
    out = Path(args.out)
    scene = out / "fox_scene"
    cmd = [sys.executable, "-m", "toolkit.cli", "poses", str(photos), "--out", str(scene), "--max-size",
           str(args.max_size), "--matcher", args.matcher, "--threads", str(args.threads), "--json"]
    if args.reuse:
        manifest = json.loads((scene / "dars_manifest.json").read_text())
        res, wall = manifest["result"], None
    else:
        if scene.exists():
            shutil.rmtree(scene)
        out.mkdir(parents=True, exist_ok=True)
        print("$ dars " + " ".join(cmd[3:]), flush=True)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "OMP_NUM_THREADS": str(args.threads)})
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            print(f"bench_poses: dars poses failed (exit {proc.returncode})")
            return 1
        res = json.loads(proc.stdout)

    ours = json.loads((scene / "transforms.json").read_text())
    given = json.loads(ref_file.read_text())
    ref = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"], np.float64) for f in given["frames"]}
    est = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"], np.float64) for f in ours["frames"]}
    common = sorted(set(ref) & set(est))
    cmp = compare_poses(np.stack([est[n] for n in common]), np.stack([ref[n] for n in common]))
    loaded = len(load_scene(scene, "all"))
    # our +z (world up) seen in the given frame (colmap2nerf sets its up from the mean camera up)
    up_in_given = np.asarray(cmp["rotation"]) @ np.array([0.0, 0.0, 1.0])
    up_angle = float(np.degrees(np.arccos(np.clip(up_in_given[2], -1, 1))))

    rot, cen = cmp["rotation_error_deg"], cmp["centre_error_rel"]
    frac = res["registered"] / res["photos"]
    report = {
        "photos": res["photos"], "registered": res["registered"], "registered_fraction": frac,
        "mean_reprojection_error_px": res["mean_reprojection_error_px"], "points": res["points"],
        "seconds_dars": res["seconds"], "seconds_wall": wall, "timings": res["timings"],
        "compared": len(common), "rotation_error_deg": rot, "centre_error_rel": cen, "alignment_scale": cmp["scale"],
        "relative_rotation_error_deg": cmp["relative_rotation_error_deg"], "rotation_offset_deg": cmp["rotation_offset_deg"],
        "up_from": res["up_from"], "up_angle_to_given_deg": up_angle, "load_scene_frames": loaded,
        "targets": {"registered_fraction": 0.95, "median_rotation_error_deg": 2.0},
        "passed": bool(frac >= 0.95 and rot["median"] <= 2.0),
        "command": "dars " + " ".join(cmd[3:]), "max_size": args.max_size, "threads": args.threads,
    }
    (out / "bench_poses.json").write_text(json.dumps(report, indent=2))
    print(f"registered        {res['registered']}/{res['photos']} ({100 * frac:.0f} %, target >= 95 %)")
    print(f"reprojection      {res['mean_reprojection_error_px']:.3f} px mean, {res['points']} points")
    print(f"time              {res['seconds']:.1f} s in dars poses ("
          + (f"{wall:.1f} s wall with start-up; " if wall is not None else "")
          + ", ".join(f"{k} {v:.1f} s" for k, v in res["timings"].items()) + ")")
    print(f"rotation error    median {rot['median']:.3f} deg, max {rot['max']:.3f} deg (target median <= 2 deg; "
          f"{len(common)} cameras)")
    rel = cmp["relative_rotation_error_deg"]
    print(f"                  of which a common offset of {cmp['rotation_offset_deg']:.3f} deg (the centre alignment's); "
          f"without it median {rel['median']:.3f} deg, max {rel['max']:.3f} deg")
    print(f"centre error      median {100 * cen['median']:.2f} %, max {100 * cen['max']:.2f} % of the camera spread")
    print(f"upright           up from {res['up_from']}; {up_angle:.1f} deg from the given frame's +z (colmap2nerf: mean camera up)")
    print(f"load_scene        {loaded} frames; {'PASS' if report['passed'] else 'FAIL'}; wrote {out / 'bench_poses.json'}")
    return 0 if report["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
