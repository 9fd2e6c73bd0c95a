"""Data-parallel training (toolkit.distributed): a 2-process gloo run on CPU launched by torchrun, as a user runs it."""

import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

from synthetic import make_scene
from toolkit._checks import ConfigError
from toolkit.distributed import Distributed, split_count
from toolkit.layout import FACE_NAMES
from toolkit.train import load_run, make_config, train

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("tiny"), n_train=16, n_test=4)


def _env():
    # PYTHONFAULTHANDLER: a rank that dies on a signal prints every thread's Python stack (where it was)
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONFAULTHANDLER="1",
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("WORLD_SIZE", None)
    return env


def _torchrun(n: int, *args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    """``torchrun -m toolkit.cli ARGS`` with ``n`` processes.

    Once, in CI on 2026-12-05 (not reproduced in 22 local runs, idle or loaded), a gloo rank aborted
    in C++ ("terminate called without an active exception", SIGABRT) with no Python error. A run whose rank died on
    SIGABRT is therefore run once more, from an empty ``--out``, with a warning that carries the first run's stack
    (faulthandler); any other failure, or a second abort, fails the test."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(n),
           "-m", "toolkit.cli", *args]
    p = subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=timeout)
    if p.returncode != 0 and "(SIGABRT)" in p.stderr:
        warnings.warn(f"a rank aborted (SIGABRT); running once more. Its stderr:\n{p.stderr[-6000:]}")
        if "--out" in args:
            shutil.rmtree(args[args.index("--out") + 1], ignore_errors=True)
        p = subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=timeout)
    return p


def test_split_count_and_local_config():
    assert [split_count(10, r, 3) for r in range(3)] == [4, 3, 3]
    cfg = make_config("fast", batch_rays=4096, steps=10)
    parts = [Distributed(r, 2, r, "gloo").local_config(cfg) for r in range(2)]
    assert sum(p.batch_rays for p in parts) == 4096 and sum(p.ssim_patches for p in parts) == cfg.ssim_patches
    assert all(p.device == "cpu" for p in parts)
    small = Distributed(1, 2, 1, "gloo").local_config(make_config("fast", batch_rays=512, steps=1))
    assert small.batch_rays == 256 and small.ssim_patches == 0  # a patch would fill the rank's whole batch
    with pytest.raises(ConfigError, match="each rank needs at least 16 rays"):
        Distributed(0, 4, 0, "gloo").local_config(make_config("fast", batch_rays=32, steps=1))
    with pytest.raises(ConfigError, match="colour correction .* not supported with 2 processes"):
        Distributed(0, 2, 0, "gloo").check_supported(make_config("fast", colour_correction="on"), None)


def test_shutdown_meets_at_a_barrier_only_after_a_finished_command(monkeypatch):
    import toolkit.distributed as td

    calls = []

    def barrier():
        calls.append("barrier")
        if fail:
            raise RuntimeError("peer gone")

    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.distributed, "barrier", barrier)
    monkeypatch.setattr(torch.distributed, "destroy_process_group", lambda: calls.append("destroy"))
    for finished, fail, want in ((True, False, ["barrier", "destroy"]), (False, False, ["destroy"]),
                                 (True, True, ["barrier", "destroy"])):
        calls.clear()
        monkeypatch.setattr(td, "_CURRENT", Distributed(0, 2, 0, "gloo"))
        if fail:  # a failed barrier still leaves the group, and says why
            with pytest.raises(RuntimeError, match="peer gone"):
                td.shutdown(finished=finished)
        else:
            td.shutdown(finished=finished)
        assert calls == want and td.current() is None


def test_two_process_gloo_training_stays_in_sync_and_evaluates(tiny, tmp_path):
    run = tmp_path / "run"
    p = _torchrun(2, "train", str(tiny), "--out", str(run), "--steps", "8", "--threads", "1", "--batch-rays", "512",
                  "--quiet")
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-8000:]
    assert p.stdout.count("run: ") == 1  # rank 0 alone reports (and writes)
    rows = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]
    train_rows = [r for r in rows if r["kind"] == "train"]
    assert train_rows and all(r["world_size"] == 2 for r in train_rows)
    dist = [r for r in rows if r["kind"] == "distributed"]
    assert len(dist) == 1 and dist[0]["world_size"] == 2 and dist[0]["backend"] == "gloo"
    digests = dist[0]["parameter_digests"]
    assert len(digests) == 2 and digests[0] == digests[1] and dist[0]["in_sync"], digests  # identical copies
    assert len(dist[0]["peak_rss_mb"]) == 2 and min(dist[0]["peak_rss_mb"]) > 0
    meta = json.loads((run / "config.json").read_text())
    assert meta["world_size"] == 2 and meta["config"]["batch_rays"] == 512  # the global batch
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ck["step"] == 8 and ck["world_size"] == 2 and len(ck["generators"]) == 2
    assert not list(run.glob(".*.tmp"))  # written atomically, once

    # --resume at another world size (1 process) continues the run
    train(None, run, make_config("fast", steps=10), resume=True, progress_bar=False, log=lambda m: None)
    assert load_run(run, with_weights=False).step == 10
    assert json.loads((run / "config.json").read_text())["world_size"] == 1

    e = subprocess.run([sys.executable, "-m", "toolkit.cli", "eval", str(run), "--json", "--limit", "2", "--quiet"],
                       cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=240)
    assert e.returncode == 0, e.stderr[-3000:]
    out = json.loads(e.stdout)
    assert out["eval"]["checkpoint_step"] == 10 and out["eval"]["views"] == 2


def test_two_processes_share_rank_0s_room_box(tiny, tmp_path):
    """--layout-depth under torchrun: rank 0 fits the room's box on every photo and the ranks take it (one fit, one
    box), instead of each fitting its own on its shard. So with --light-fit on: rank 0 fits the light at the switch to
    stage (b) and every rank takes it (the parameter digests include l_env)."""
    run = tmp_path / "lay"
    p = _torchrun(2, "train", str(tiny), "--out", str(run), "--steps", "4", "--threads", "1", "--batch-rays", "512",
                  "--layout-depth", "0.1", "--no-auto-priors", "--light-fit", "on")
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-8000:]
    assert p.stderr.count("room layout: box") == 1, p.stderr[-3000:]  # rank 0 alone fits and reports
    assert p.stderr.count("light from the shading at step 2") == 1, p.stderr[-3000:]
    meta = json.loads((run / "config.json").read_text())
    assert meta["world_size"] == 2 and set(meta["room_layout"]["faces"]) == set(FACE_NAMES)
    assert meta["room_layout"]["photos"] == 16  # fitted on every photo, not on rank 0's shard of 8
    dist = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines() if '"distributed"' in x]
    assert dist and dist[0]["in_sync"]


def _test_psnr(run_dir) -> float:
    from toolkit.io import linear_to_srgb
    from toolkit.metrics import psnr
    from toolkit.scene import load_scene

    run = load_run(run_dir)
    sc = load_scene(run.scene_path, "test")
    vals = [float(psnr(linear_to_srgb(run.render(sc.cameras, i).rgb.clamp(0, 1)).permute(2, 0, 1), sc.load_image(i)))
            for i in range(len(sc))]
    return sum(vals) / len(vals)


@pytest.mark.slow
def test_two_processes_match_one_within_seed_noise(tiny, tmp_path):
    """Equal global batch and steps: the 2-process run's test PSNR is within the seed noise of 1-process runs."""
    args = ["--steps", "80", "--threads", "1", "--batch-rays", "512", "--quiet"]
    p = _torchrun(2, "train", str(tiny), "--out", str(tmp_path / "two"), *args)
    assert p.returncode == 0, p.stderr[-4000:]
    one = []
    for seed in (0, 1):
        q = subprocess.run([sys.executable, "-m", "toolkit.cli", "train", str(tiny), "--out", str(tmp_path / f"one{seed}"),
                            "--seed", str(seed), *args], cwd=ROOT, env=_env(), capture_output=True, text=True,
                           timeout=240)
        assert q.returncode == 0, q.stderr[-3000:]
        one.append(_test_psnr(tmp_path / f"one{seed}"))
    two = _test_psnr(tmp_path / "two")
    noise = abs(one[0] - one[1])
    assert abs(two - one[0]) <= max(3 * noise, 1.5), (two, one)


def test_one_rank_group_runs_the_data_parallel_path(tiny, tmp_path):
    """bench/one_rank_group.py (how the GPU machine checks NCCL with one card): ``dars train`` inside a one-rank
    process group takes the data-parallel path (gloo here) and writes a run; NCCL without CUDA is refused."""
    cmd = [sys.executable, str(ROOT / "bench" / "one_rank_group.py"), "--backend", "gloo", "--port", "29533", "train",
           str(tiny), "--out", str(tmp_path / "r"), "--steps", "3", "--batch-rays", "64", "--threads", "1"]
    r = subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "data-parallel: 1 processes (gloo)" in r.stdout + r.stderr and "one-rank group: gloo rc 0" in r.stdout
    assert load_run(tmp_path / "r", with_weights=False).step == 3
    if not torch.cuda.is_available():
        r = subprocess.run(cmd[:2] + ["train", str(tiny)], cwd=ROOT, env=_env(), capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 2 and "NCCL needs CUDA" in r.stderr
