"""How long does one training step take, and what did the per-sample hot spots cost? (issue 16: every minute of a
``--minutes`` budget buys steps.)

One process trains the sample (``fast`` preset, as ``make demo``: photos and poses, with the priors the shipped
networks predict from them, computed first into a temporary folder unless ``--priors`` names one; no ground truth)
and, after a warm-up, times field steps with the current code and with the reference implementations below swapped in,
interleaved in blocks of three steps so that a slow minute of the machine hits every variant alike:

* ``reference``: ``cat([coarse, fine])[order]`` with autograd's accumulating ``index_put_`` backward, the two SH
  contractions of :func:`toolkit.shading.shade_pbr` (``shading._sh_light``) as broadcast multiply-and-sums over
  ``[S, 9, 3]``, and the light head on ``cat([h, l_env])`` (the code before 2026-11-29, but for the two SH weight
  rows being stacked first, a [S, 2, 9] copy);
* ``gather``: only the reordering changed (:func:`toolkit.pipeline._permute`: the backward gathers by the inverse
  permutation);
* ``current``: the code as it is.

Printed: mean and median seconds a step per variant and the ratio to ``reference`` measured in the same run. The
three give the same values (the reordering bit for bit, the rest to float rounding; ``tests/test_render.py``,
``tests/test_train.py``).

    python bench/bench_step.py [--scene samples/gallery] [--priors DIR] [--rounds 10] [--threads 2]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import toolkit.pipeline as pipeline  # noqa: E402
import toolkit.shading as shading  # noqa: E402
from toolkit.field import DarsField  # noqa: E402


def reference_permute(a, b, order, inverse):
    return torch.cat([a, b])[order]


def reference_sh_light(y, sh):
    """The SH contraction as before: a broadcast multiply-and-sum over [..., 9, 3] for each row of ``y``."""
    return torch.stack([(y[..., j, :, None] * sh).sum(-2) for j in range(y.shape[-2])], -2)


def reference_light_head(self, h, l_env):
    return self.light_head(torch.cat([h, l_env.reshape(1, 27).to(h).expand(h.shape[0], 27)], -1))


CURRENT = (pipeline._permute, shading._sh_light, DarsField._light_head)
VARIANTS = {"reference": (reference_permute, reference_sh_light, reference_light_head),
            "gather": (CURRENT[0], reference_sh_light, reference_light_head),
            "current": CURRENT}


def use(name: str) -> None:
    pipeline._permute, shading._sh_light, DarsField._light_head = VARIANTS[name]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default=str(ROOT / "samples" / "gallery"))
    ap.add_argument("--rounds", type=int, default=10, help="blocks of three steps per variant")
    ap.add_argument("--warmup", type=int, default=70, help="steps before timing (past the occupancy warm-up)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--priors", default=None, help="a priors folder (dars priors ... --out DIR/<stage>) to reuse")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_step_") as tmp:
        priors = args.priors
        if priors is None:
            priors = tmp
            t0 = time.time()
            for stage in ("segment", "weights", "light"):
                subprocess.run([sys.executable, "-m", "toolkit.cli", "priors", stage, args.scene, "--out",
                                str(Path(tmp) / stage)], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
            print(f"[step] priors predicted from the photos in {time.time() - t0:.0f} s")
        return _run(args, priors)


def _run(args, priors: str) -> int:
    torch.set_num_threads(args.threads)
    from toolkit.scene import load_scene
    from toolkit.train import init_state, make_config, prepare_data, resolve_config, train_step

    scene = load_scene(args.scene, "train")
    cfg = make_config("fast", steps=100000, pretrain_fraction=0.0, seed=0)
    cfg, scene = resolve_config(cfg, scene)
    data = prepare_data(scene, cfg, log=lambda m: None, priors_root=priors)
    st = init_state(cfg, data)

    def step():
        if st.step % cfg.occupancy_every == 0:
            st.occupancy.update(st.field.density, st.generator, all_cells=st.step < cfg.occupancy_warmup,
                                warmup=st.step < cfg.occupancy_warmup)
        return train_step(st, data)

    t0 = time.time()
    for _ in range(args.warmup):
        step()
        st.step += 1
    print(f"[step] {args.scene}: {cfg.batch_rays} rays a step, {args.warmup} warm-up steps in "
          f"{time.time() - t0:.0f} s, {args.threads} threads")
    times = {v: [] for v in VARIANTS}
    spr = 0.0
    for _ in range(args.rounds):
        for v in VARIANTS:
            use(v)
            for _ in range(3):
                t = time.time()
                r = step()
                times[v].append(time.time() - t)
                spr = r["samples_per_ray"]
            st.step += 1
    use("current")
    ref = sum(times["reference"]) / len(times["reference"])
    print(f"[step] {spr:.1f} samples a ray; seconds a step over {3 * args.rounds} steps each, interleaved:")
    print("| variant | mean s | median s | vs reference |\n|---|---|---|---|")
    for v, ts in times.items():
        mean, med = sum(ts) / len(ts), sorted(ts)[len(ts) // 2]
        print(f"| {v} | {mean:.3f} | {med:.3f} | {mean / ref:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
