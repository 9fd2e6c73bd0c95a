"""Masks that hide what should not be learned (``mask_path``, ``dars train --masks``) on a real capture.

Real photos of a gallery have people, a tripod or a guard in them, different in every photo. nerfstudio's
``mask_path`` marks those pixels (0 = leave out). This benchmark paints such occluders into the training photos of a
real capture (default: the fox, ``../shared/data/real/fox``): per photo a few solid "visitors" (ellipses and
rectangles of a random colour with a little texture, ``--cover`` of the frame in all), with a mask that is 0 on them;
the test photos are left as they were. It trains, with the same seed and steps:

1. ``clean``: the capture as it is (the reference);
2. ``masked``: the occluded photos with their masks (``--masks auto``, i.e. ``ignore``);
3. ``unmasked``: the occluded photos, masks not read (``--masks off``);

each through the CLI as a user runs it (``dars train SCENE --out RUN --steps N --downscale D --seed S``, then
``dars eval RUN --json``), and prints the test PSNR / SSIM / FLIP of each, and each occluded run against the clean
one. Ground truth: none (a real capture); the test photos are the reference. Writes ``OUT/bench_masks.json``.

Usage: ``python bench/bench_masks.py [--scene DIR_OR_JSON] [--steps 400] [--downscale 4] [--seed 0]
[--threads 2] [--cover 0.12] [--out bench/out/masks]``
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


def occluders(h: int, w: int, cover: float, rng) -> tuple:
    """(colour layer float [h, w, 3], mask bool [h, w]: True where an occluder is) with about ``cover`` of the frame."""
    import numpy as np

    yy, xx = np.mgrid[0:h, 0:w]
    occ = np.zeros((h, w), bool)
    layer = np.zeros((h, w, 3), np.float32)
    while occ.mean() < cover:
        ch, cw = rng.uniform(0.15, 0.45) * h, rng.uniform(0.08, 0.25) * w  # upright, person-like proportions
        cy, cx = rng.uniform(0.2, 1.0) * h, rng.uniform(0.0, 1.0) * w
        if rng.random() < 0.5:
            shape = ((yy - cy) / (0.5 * ch)) ** 2 + ((xx - cx) / (0.5 * cw)) ** 2 <= 1.0
        else:
            shape = (np.abs(yy - cy) <= 0.5 * ch) & (np.abs(xx - cx) <= 0.5 * cw)
        colour = rng.uniform(0.0, 1.0, 3).astype(np.float32)
        stripes = 0.85 + 0.15 * np.sin(yy / max(h, 1) * rng.uniform(20, 60))[..., None]
        layer = np.where(shape[..., None], np.clip(colour * stripes, 0, 1), layer)
        occ |= shape
    return layer, occ


def make_occluded(scene: Path, out: Path, cover: float, seed: int) -> tuple[Path, dict]:
    """A copy of ``scene`` (a transforms JSON) whose training photos carry occluders and a ``mask_path`` each."""
    import numpy as np

    from toolkit.io import read_image, write_png
    from toolkit.scene import load_scene

    src = scene if scene.is_file() else scene / "transforms.json"
    meta = json.loads(src.read_text())
    test_keys = {f.name for f in load_scene(src, "test", upright="off").frames}
    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    (out / "masks").mkdir()
    rng = np.random.default_rng(seed)
    covered = []
    for f in meta["frames"]:
        path = src.parent / f["file_path"]
        stem = Path(f["file_path"]).stem
        if f["file_path"] in test_keys:  # test photos: as they were
            dst = out / "images" / path.name
            shutil.copyfile(path, dst)
            f["file_path"] = f"images/{path.name}"
            continue
        img = read_image(path, "photo")[..., :3]
        layer, occ = occluders(img.shape[0], img.shape[1], cover, rng)
        write_png(out / "images" / f"{stem}.png", np.where(occ[..., None], layer, img))
        write_png(out / "masks" / f"{stem}.png", np.where(occ, 0, 255).astype(np.uint8))
        f["file_path"], f["mask_path"] = f"images/{stem}.png", f"masks/{stem}.png"
        covered.append(float(occ.mean()))
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return out / "transforms.json", {"train_photos": len(covered), "test_photos": len(test_keys),
                                     "covered_mean": float(np.mean(covered)), "cover_asked": cover}


def train_and_eval(scene: Path, run: Path, args, extra: list[str]) -> dict:
    dars = [sys.executable, "-m", "toolkit.cli"]
    if run.exists():
        shutil.rmtree(run)
    t0 = time.time()
    subprocess.run(dars + ["train", str(scene), "--out", str(run), "--steps", str(args.steps), "--downscale",
                           str(args.downscale), "--seed", str(args.seed), "--threads", str(args.threads), "--quiet",
                           *extra], check=True, cwd=ROOT)
    t_train = time.time() - t0
    res = subprocess.run(dars + ["eval", str(run), "--json", "--threads", str(args.threads)], check=True, cwd=ROOT,
                         capture_output=True, text=True)
    ev = json.loads(res.stdout)
    m = ev.get("metrics", ev)
    return {"psnr": m.get("psnr"), "ssim": m.get("ssim"), "flip": m.get("flip"), "train_s": round(t_train, 1),
            "masks": json.loads((run / "config.json").read_text()).get("masks")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(SHARED / "real" / "fox" / "transforms.json"))
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--downscale", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cover", type=float, default=0.12, help="share of each training photo the occluders cover")
    ap.add_argument("--out", default=str(ROOT / "bench" / "out" / "masks"))
    args = ap.parse_args()

    scene = Path(args.scene)
    if not scene.exists():
        print(f"bench_masks: skipped, data not present ({scene})")
        return 0
    out = Path(args.out)
    occluded, info = make_occluded(scene, out / "occluded_scene", args.cover, args.seed)
    print(f"occluded copy: {info['train_photos']} training photos, {100 * info['covered_mean']:.1f} % of each covered "
          f"on average; {info['test_photos']} test photos untouched -> {occluded}")
    rows = {}
    for name, sc, extra in (("clean", scene, []), ("masked", occluded, []), ("unmasked", occluded, ["--masks", "off"])):
        print(f"[{name}] training {args.steps} steps ...", flush=True)
        rows[name] = train_and_eval(sc, out / f"run_{name}", args, extra)
        r = rows[name]
        print(f"[{name}] test PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.3f}, FLIP {r['flip']:.3f} "
              f"(masks: {r['masks']}, {r['train_s']:.0f} s)", flush=True)
    c = rows["clean"]
    print(f"\n{'run':<10}{'PSNR':>8}{'SSIM':>8}{'FLIP':>8}{'dPSNR vs clean':>16}")
    for name, r in rows.items():
        print(f"{name:<10}{r['psnr']:8.2f}{r['ssim']:8.3f}{r['flip']:8.3f}{r['psnr'] - c['psnr']:+16.2f}")
    fig = {"command": "bench/bench_masks.py " + " ".join(sys.argv[1:]), "scene": str(scene), "occluded": info,
           "steps": args.steps, "downscale": args.downscale, "seed": args.seed, "runs": rows,
           "masked_minus_unmasked_psnr": rows["masked"]["psnr"] - rows["unmasked"]["psnr"],
           "ground_truth": "none (a real capture; the untouched test photos are the reference)"}
    from toolkit.io import write_json

    write_json(out / "bench_masks.json", fig)
    print(f"masked - unmasked: {fig['masked_minus_unmasked_psnr']:+.2f} dB; wrote {out / 'bench_masks.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
