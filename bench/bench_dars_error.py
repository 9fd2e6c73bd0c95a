"""Where does the test error sit, and does DARS move it? PSNR by distortion rank, paired across `dars ablate` runs.

DARS (paper §II.B) spends pixels and fine samples where the distortion weight W is high — edges, highlights,
metal — on the premise that those pixels carry the error. This benchmark checks both halves on *test* views,
which no sampler saw: it renders every ``--every``-th test view of each run, computes W for the **test photo**
(eqs. 2-4 + 8, :func:`toolkit.edges.weight_map`; with the split's ground-truth labels and metal mask where it has
them — ground truth used for scoring only, never for training), ranks each photo's pixels by W and pools the
squared error over three strata: ``hard`` (top 10 % of W), ``mid`` (50-90 %) and ``flat`` (bottom 50 %).

It prints each run's PSNR per stratum, then the paired difference of every variant against ``full`` (same scene,
same seed: ``variant − full``, mean ± sample std over the pairs). If DARS works as intended, ``no_dars − full`` is
negative on ``hard`` and small on ``flat``.

It also prints how far DARS's pixel selection moves from uniform, from each run's training W maps: the total
variation distance between the selection probabilities ``(1 − ρ) + ρ W`` (normalised) and uniform ones, i.e.
the fraction of drawn rays that DARS puts on other pixels than uniform sampling would.

Usage (read the runs of finished ablations; several folders of one scene are paired by seed)::

    dars ablate GALLERY --out OUT --steps 600 --seeds 0,1,2 --variants full,no_dars --threads 2
    python bench/bench_dars_error.py OUT [OUT2 ...] [--every 2] [--threads 2] [--out bench/out/dars_error]

Writes ``bench_dars_error.json`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

STRATA = (("hard", 0.9, 1.01), ("mid", 0.5, 0.9), ("flat", -0.01, 0.5))
"""(name, low, high): pixels whose per-photo rank of W lies in [low, high)."""
NAMES = tuple(name for name, _, _ in STRATA) + ("all",)


def collect_runs(folders: list[Path]) -> list[dict]:
    """Every (scene, variant, seed, run) of the given ``dars ablate`` folders (from their ``ablation.json``)."""
    runs = []
    for folder in folders:
        doc_path = folder / "ablation.json"
        if not doc_path.is_file():
            raise SystemExit(f"{folder}: no ablation.json — pass folders written by `dars ablate`")
        doc = json.loads(doc_path.read_text())
        for v in doc["variants"]:
            for r in v["runs"]:
                runs.append({"scene": str(Path(doc["scene"]).expanduser().resolve()), "variant": v["name"],
                             "seed": int(r["seed"]), "run": r["run"]})
    seen = set()
    for r in runs:
        key = (r["scene"], r["variant"], r["seed"])
        if key in seen:
            raise SystemExit(f"{r['variant']} seed {r['seed']} of {r['scene']} appears in two folders; pass one")
        seen.add(key)
    return runs


def selection_tv(run, rho: float) -> float | None:
    """Total variation distance between DARS's pixel-selection probabilities and uniform ones.

    Rays are drawn over all training pixels with probability ∝ ``(1 − ρ) + ρ W`` (W as the sampler reads it: the
    run's stored, normalised maps; :func:`toolkit.sampling.build_ray_sampler`). None when the run has no W maps.
    """
    import torch

    wm = run.weight_maps
    if wm is None:
        return None
    w = wm.gather(torch.arange(wm.n_pixels)).double().clamp(0.0, 1.0)
    p = (1.0 - rho) + rho * w
    p = p / p.sum()
    return 0.5 * float((p - 1.0 / p.numel()).abs().sum())


def stratified_psnr(run, every: int) -> dict:
    """Pooled PSNR per W stratum over every ``every``-th test view of ``run``."""
    import torch

    from toolkit.edges import quantile_normalise, weight_map
    from toolkit.io import linear_to_srgb

    scene = run.load_split("test")
    extras = scene.extras_available()
    acc = {name: [0.0, 0] for name in NAMES}
    views = list(range(0, len(scene), every))
    for i in views:
        with torch.no_grad():
            rgb = run.render(scene.cameras, i, chunk=8192).as_dict()["rgb"].float().clamp(0, 1).permute(2, 0, 1)
        pred = linear_to_srgb(rgb) if scene.srgb else rgb
        gt = scene.load_image(i)
        labels = scene.load_extra(i, "semantic")[None] if "semantic" in extras else None
        metal = scene.load_extra(i, "metal")[None] if "metal" in extras else None
        rank = quantile_normalise(weight_map(gt[None], labels, metal).weights)[0]
        se = ((pred - gt) ** 2).mean(0)
        for name, lo, hi in STRATA:
            m = (rank >= lo) & (rank < hi)
            acc[name][0] += float(se[m].sum())
            acc[name][1] += int(m.sum())
        acc["all"][0] += float(se.sum())
        acc["all"][1] += se.numel()
    out = {k: (-10.0 * math.log10(s / n) if n and s > 0 else None) for k, (s, n) in acc.items()}
    out["views"] = len(views)
    out["w_inputs"] = "test photo (G)" + (" + GT labels (E)" if "semantic" in extras else "") + \
        (" + GT metal (M)" if "metal" in extras else "")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="*", type=Path, help="`dars ablate` output folders")
    ap.add_argument("--every", type=int, default=2, help="render every N-th test view (default 2)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "out" / "dars_error")
    args = ap.parse_args(argv)
    if args.every < 1:
        raise SystemExit("--every must be >= 1")
    if not args.folders:  # `make bench` runs every benchmark without arguments: nothing of the user's to compare
        print("[dars-error] skipped: pass the folders of finished `dars ablate` runs "
              "(e.g. dars ablate GALLERY --out OUT --steps 600 --seeds 0,1,2 --variants full,no_dars)")
        return 0

    from toolkit.ablation import paired_differences
    from toolkit.cli._common import set_threads
    from toolkit.io import write_json
    from toolkit.train import load_run

    set_threads(args.threads)
    runs = collect_runs(args.folders)
    t0 = time.monotonic()
    for k, r in enumerate(runs, 1):
        run = load_run(r["run"])
        r.update(stratified_psnr(run, args.every))
        r["selection_tv"] = selection_tv(run, run.cfg.sampler.rho) if run.cfg.sampler.dars else 0.0
        tv = "" if r["selection_tv"] is None else f"  (selection TV {r['selection_tv']:.3f})"
        print(f"[{k}/{len(runs)}] {Path(r['scene']).name} {r['variant']} seed {r['seed']}: "
              + "  ".join(f"{n} {r[n]:.2f}" for n in NAMES) + tv, flush=True)

    print(f"\nPSNR (dB) by W stratum of the test photo, pooled over 1 in {args.every} test views; "
          f"W from {runs[0]['w_inputs']} (ground truth for scoring only)")
    print(f"{'scene':<16} {'variant':<14} {'seed':>4} " + " ".join(f"{n:>7}" for n in NAMES) + "  sel.TV")
    for r in runs:
        tv = "" if r["selection_tv"] is None else f"{r['selection_tv']:.3f}"
        print(f"{Path(r['scene']).name:<16} {r['variant']:<14} {r['seed']:>4} "
              + " ".join(f"{r[n]:7.2f}" for n in NAMES) + f"  {tv}")

    full = {(r["scene"], r["seed"]): r for r in runs if r["variant"] == "full"}
    paired: dict[str, dict] = {}
    for variant in sorted({r["variant"] for r in runs} - {"full"}):
        pairs = [(r, full[(r["scene"], r["seed"])]) for r in runs
                 if r["variant"] == variant and (r["scene"], r["seed"]) in full]
        if not pairs:
            continue
        paired[variant] = {n: paired_differences([a[n] for a, _ in pairs], [b[n] for _, b in pairs]) for n in NAMES}
        print(f"\n{variant} − full, same scene and seed ({len(pairs)} pairs): mean ± std (dB)")
        for n in NAMES:
            s = paired[variant][n]
            sd = f" ± {s['std']:.2f}" if s["std"] is not None else ""
            print(f"  {n:<5} {s['mean']:+.2f}{sd}   per pair: " + ", ".join(f"{x:+.2f}" for x in s["values"]))
    gap = [r["flat"] - r["hard"] for r in runs]
    print(f"\nflat − hard over all {len(runs)} runs: {statistics.fmean(gap):.2f} dB "
          f"(min {min(gap):.2f}, max {max(gap):.2f})")
    tvs = [r["selection_tv"] for r in runs if r["variant"] == "full" and r["selection_tv"] is not None]
    if tvs:
        print(f"DARS pixel selection vs uniform (full runs): total variation {statistics.fmean(tvs):.3f} "
              f"(min {min(tvs):.3f}, max {max(tvs):.3f}) — the fraction of drawn rays moved to other pixels")
    args.out.mkdir(parents=True, exist_ok=True)
    doc = {"command": "python bench/bench_dars_error.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "strata": {n: [lo, hi] for n, lo, hi in STRATA}, "every": args.every, "runs": runs, "paired": paired,
           "seconds": round(time.monotonic() - t0, 1)}
    write_json(args.out / "bench_dars_error.json", doc)
    print(f"\nwrote {args.out / 'bench_dars_error.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
