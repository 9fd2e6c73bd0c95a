"""The training loop (:func:`train`): schedules, logging, checkpoints and resume, snapshots, loss curves."""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

from .._checks import ConfigError, DarsError
from ..distributed import current as current_distributed
from ..distributed import peak_rss_mb
from ..io import save_torch, write_json
from ..sampling import OccupancyGrid
from ..scene import load_scene
from .config import TrainConfig, resolve_config
from .data import prepare_data
from .folder import first_checkpoint_due, open_run_dir, read_checkpoint, read_run_config, run_scene_options
from .step import (RETIME_AT, TrainingDiverged, TrainState, calibrate_steps, init_state, is_light_step, light_step,
                   lr_progress, progress, retime_steps, stage_b_starts, train_step, wants_light_fit)

__all__ = ["train", "save_checkpoint", "load_checkpoint"]


def _set_lr(state: TrainState) -> None:
    f = state.cfg.lr_final_factor ** lr_progress(state)
    for opt in (state.optimizer, state.light_optimizer):
        for g in opt.param_groups:
            g["lr"] = g["initial_lr"] * f


# ============================================================================ checkpoints
def _checkpoint_dict(state: TrainState) -> dict:
    return {
        "version": 1,
        "config": state.cfg.to_dict(),
        "step": state.step,
        "elapsed": state.elapsed,
        "field": state.field.state_dict(),
        "background": state.background.state_dict(),
        "background_mode": state.background.mode,
        "l_env": state.l_env.detach().cpu(),
        "colour": None if state.colour is None else state.colour.state_dict(),
        "optimizer": state.optimizer.state_dict(),
        "light_optimizer": state.light_optimizer.state_dict(),
        "occupancy": state.occupancy.state_dict(),
        "generator": state.generator.get_state(),
        "snapshots_done": list(state.snapshots_done),
    }


def save_checkpoint(state: TrainState, path: Path) -> None:
    """Write the state atomically (temp file + rename)."""
    save_torch(path, _checkpoint_dict(state))


def load_checkpoint(path: Path, state: TrainState) -> TrainState:
    """Restore ``state`` (built by :func:`init_state` with the same config) from ``path``."""
    ck = read_checkpoint(path, map_location=state.device)
    state.field.load_state_dict(ck["field"])
    state.background.load_state_dict(ck["background"])
    with torch.no_grad():
        state.l_env.copy_(ck["l_env"].to(state.device))
    if state.colour is not None and ck.get("colour") is not None:
        state.colour.load_state_dict(ck["colour"])
    state.optimizer.load_state_dict(ck["optimizer"])
    state.light_optimizer.load_state_dict(ck["light_optimizer"])
    state.occupancy = OccupancyGrid.from_state_dict(ck["occupancy"]).to(state.device)
    state.generator.set_state(ck["generator"])
    ddp = current_distributed()
    if ddp is not None:  # every rank its own saved stream (or a fresh one at another world size)
        ddp.restore_generator(state, ck)
    state.step = int(ck["step"])
    state.elapsed = float(ck["elapsed"])
    state.snapshots_done = list(ck.get("snapshots_done", []))
    return state


# ============================================================================ the loop
def _plot_curves(log_path: Path, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(ln) for ln in log_path.read_text().splitlines() if ln.strip()]
    rows = [r for r in rows if r.get("kind") == "train"]
    if not rows:
        return
    keys = [k for k in ("loss", "rgb", "ssim", "psnr_loss", "mat", "eikonal", "orientation", "semantic", "light_reg",
                        "distortion", "layout_depth", "layout_normal", "albedo_smooth") if any(k in r for r in rows)]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for k in keys:
        xs = [r["step"] for r in rows if k in r]
        ys = [r[k] for r in rows if k in r]
        if k == "psnr":
            continue
        axes[0].plot(xs, ys, label=f"L_{k}" if k != "loss" else "L_total")
    axes[0].set_yscale("symlog", linthresh=1e-3)
    axes[0].set_xlabel("step")
    axes[0].set_title("training losses (Fig. 6)")
    axes[0].legend(fontsize=7)
    axes[1].plot([r["step"] for r in rows], [r["psnr"] for r in rows], color="tab:green")
    axes[1].set_xlabel("step")
    axes[1].set_ylabel("batch PSNR (dB)")
    axes[1].set_title("training PSNR")
    fig.tight_layout()
    tmp = out.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, out)


def _room_layout(cfg: TrainConfig, scene, saved: dict | None, ddp, log, priors_root):
    """The room's box for ``--layout-depth`` when it need not be fitted from this process's photos: the box a resumed
    run recorded (the same targets, without the minutes of a second fit), the box of ``dars priors layout`` in the
    run's priors folder or the scene's own, or, under torch.distributed, the box rank 0 fits on every photo (each
    rank would otherwise fit its own on its shard, and the ranks' targets would disagree). None: off, or one
    process fits it in ``prepare_data``."""
    if not cfg.losses.uses_room_layout:
        return None
    from ..layout import RoomLayout, fit_room_layout
    from ..priors import priors_path, read_layout

    if saved and saved.get("room_layout"):
        log("[dars] room layout: the box recorded in the run's config.json")
        return RoomLayout.from_json(saved["room_layout"])
    for root in dict.fromkeys([priors_root, None]):  # the run's priors, then the scene's own priors/ folder
        room = read_layout(scene, root)
        if room is not None:
            log(f"[dars] room layout: the box of `dars priors layout` ({priors_path(scene, 'layout', root)})")
            return room
    if ddp is None:
        return None
    return ddp.broadcast_object(fit_room_layout(scene, log=log) if ddp.is_main else None)


def _finite_or_none(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _fit_light(state: TrainState, data, ddp, main: bool, log, log_path: Path) -> None:
    """Fit l_env's directional bands to the photos' shading (:mod:`toolkit.lightfit`): rank 0 fits on its views
    and every rank takes its light."""
    from ..lightfit import fit_light_to_shading

    res = None
    if main:
        cfg = state.cfg
        res = fit_light_to_shading(state.field, state.occupancy, state.background, state.l_env, data.scene,
                                   cfg.sampler, cfg.shading, cfg.deferred)
    sh = res.sh.detach().cpu() if main else None
    if ddp is not None:
        sh = ddp.broadcast_object(sh)
    with torch.no_grad():
        state.l_env.copy_(sh.to(state.l_env))
    if main:
        log(f"[dars] light from the shading at step {state.step}: {res.describe()}")
        with open(log_path, "a") as f:
            f.write(json.dumps({"kind": "light_fit", "step": state.step, "used": res.used, "pixels": res.pixels,
                                "tv_before": _finite_or_none(res.tv_before),
                                "tv_after": _finite_or_none(res.tv_after), "reason": res.reason,
                                "l_env": sh.tolist()}) + "\n")


def train(scene_path: str | Path, out_dir: str | Path, cfg: TrainConfig, resume: bool = False, split: str = "train",
          progress_bar: bool = True, log=None, stop_at: int | None = None,
          priors_root: str | Path | None = None, force: bool = False, downscale: int = 1,
          upright: str = "auto") -> Path:
    """Train on ``scene_path`` into the run directory ``out_dir``; returns the checkpoint path.

    With ``resume`` the run continues from ``out_dir/checkpoint.pt`` with the saved config (``cfg`` may only
    raise ``steps``/``minutes``). Without it, an existing run directory with a checkpoint is refused (nothing
    is overwritten). ``stop_at`` ends this call after that step (checkpointed) without changing the run's
    schedule, so a later ``resume`` continues exactly (time-sliced jobs). ``priors_root``: where the prior
    stages wrote their outputs (default: next to the scene); recorded in the run. ``force``: start again in a folder
    holding a run (its run files are replaced), or write beside other files (never over them; :mod:`toolkit.outputs`).
    ``downscale``: shrink the photos (and intrinsics) by this integer factor on load; recorded in the run
    (``config.json`` key ``downscale``) so rendering, evaluation and ``resume`` use the same image size.
    ``upright``: ``load_scene``'s ``upright`` (``"off"``: keep the input's orientation, ``dars train --no-upright``);
    recorded in the run (key ``upright``) so they load the scene in the same frame.
    """
    from tqdm import tqdm

    log = log or (lambda m: print(m, file=sys.stderr))
    ddp = current_distributed()  # a data-parallel run (torchrun): toolkit.distributed
    main = ddp is None or ddp.is_main
    world_size = 1 if ddp is None else ddp.world_size
    if not main:  # rank 0 alone logs and writes the run
        log, progress_bar = (lambda m: None), False
    out = Path(out_dir)
    ck_path = out / "checkpoint.pt"
    cfg_path = out / "config.json"
    folder, saved = open_run_dir(out, resume, force, scene_path if resume else None, priors_root)
    if resume:
        base = read_run_config(saved, cfg_path)
        steps = base.steps
        if cfg.steps:
            steps = max(cfg.steps, base.steps)
        elif cfg.minutes and base.minutes and cfg.minutes > base.minutes and base.steps:  # a longer budget, same rate
            steps = int(round(base.steps * cfg.minutes / base.minutes))
        cfg = replace(base, steps=steps, minutes=max(cfg.minutes, base.minutes))
        saved_calibration = saved.get("calibration")
        scene_path = saved["scene"]
        split = saved.get("split", split)
        priors_root = saved.get("priors_root")
        loaded = run_scene_options(saved)  # the scene is loaded as it was: same image size, same frame
        if downscale not in (1, loaded["downscale"]):
            raise DarsError(f"--resume: {out} was trained with --downscale {loaded['downscale']}, not {downscale}; "
                            "drop --downscale or start a new run")
        if upright not in ("auto", loaded["upright"]):
            raise DarsError(f"--resume: {out} was trained with the scene made upright on load, not with --no-upright; "
                            "drop --no-upright or start a new run")
        downscale, upright = loaded["downscale"], loaded["upright"]
    else:
        saved_calibration = None
    if not cfg.steps and not cfg.minutes:
        raise ConfigError("give a training length: --steps N or --minutes M")
    if cfg.device != "auto" and cfg.device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={cfg.device} requested but CUDA is not available")
    scene = load_scene(scene_path, split, downscale=downscale, upright=upright,
                       masks=cfg.masks if cfg.masks in ("alpha", "off") else "ignore")
    if ddp is not None:  # rank 0 resolves the box and grid; the others take its config
        if main:
            cfg, _ = resolve_config(cfg, scene, log)
        cfg = ddp.broadcast_object(cfg)
    cfg, scene = resolve_config(cfg, scene, log)
    log("[dars] sampler: " + ("DARS (W-weighted rays, per-ray fine budgets, W-guided samples along the ray)"
                              if cfg.sampler.dars else "uniform pixels + hierarchical fine samples (DARS: --dars)"))
    local = (lambda c: c) if ddp is None else ddp.local_config  # this rank's share of the global batch
    room = _room_layout(cfg, scene, saved if resume else None, ddp, log, priors_root)
    data = prepare_data(scene if ddp is None else ddp.shard(scene), local(cfg), log, priors_root, room_layout=room)
    state = init_state(local(cfg), data)
    if ddp is not None:
        ddp.check_supported(cfg, data)
        state.grad_sync = ddp.average_gradients
        ddp.seed_generator(state)
        ddp.broadcast_state(state)
        log(f"[dars] data-parallel: {world_size} processes ({ddp.backend}), {len(data.scene)} photos and "
            f"{state.cfg.batch_rays} of {cfg.batch_rays} rays per step on each")
    if resume:
        load_checkpoint(ck_path, state)
        log(f"[dars] resumed {out} at step {state.step} ({state.elapsed / 60:.1f} min)")
    if ddp is not None:
        ddp.barrier()  # every rank has checked the folder before rank 0 writes to it
    if main:
        folder.begin()  # creates the folder only now, when the run is about to be written

    def save(path: Path, collective: bool = True) -> None:
        """Rank 0 writes the checkpoint (the run's global config, every rank's RNG state)."""
        gens = ddp.gather_objects(state.generator.get_state()) if ddp is not None and collective else None
        if main:
            ck = _checkpoint_dict(state)
            ck.update(config=cfg.to_dict(), world_size=world_size)
            if gens is not None:
                ck["generators"] = gens
            save_torch(path, ck)

    def write_run_config(calibration):
        if not main:
            return
        write_json(cfg_path, {"config": cfg.to_dict(), "scene": str(Path(scene_path).resolve()), "split": split,
                              "downscale": downscale, "upright": upright, "masks": cfg.masks,
                              "priors_root": str(Path(priors_root).resolve()) if priors_root else None,
                              "priors": data.priors_used, "l_env_init": data.l_env_init.tolist(),
                              "l_env_source": data.l_env_source, "torch": torch.__version__,
                              "calibration": calibration, "world_size": world_size,
                              "room_layout": data.room_layout})

    write_run_config(saved_calibration)
    log_path = out / "log.jsonl"
    if main and not resume and log_path.exists():
        log_path.unlink()
    total = cfg.steps if cfg.steps else None
    bar = tqdm(total=total, initial=state.step, disable=not progress_bar, file=sys.stderr, dynamic_ncols=True,
               unit="step", desc="train")
    t_last_ck = time.monotonic()
    t_window = None
    mark, checks, calibration = None, [], saved_calibration  # re-timing of a budget calibrated in this call
    last = {}
    fit_light = wants_light_fit(cfg, data.l_env_source)
    try:
        while True:
            if cfg.steps and state.step >= cfg.steps:
                break
            if stop_at is not None and state.step >= stop_at:
                break
            t0 = time.monotonic()
            _set_lr(state)
            if state.step % cfg.occupancy_every == 0:
                state.occupancy.update(state.field.density, state.generator,
                                       all_cells=state.step < cfg.occupancy_warmup,
                                       warmup=state.step < cfg.occupancy_warmup)
                if ddp is not None:  # each rank probed its own random cells: rank 0's grid for all
                    ddp.sync_occupancy(state.occupancy)
            if fit_light and stage_b_starts(state.cfg, state.step):
                _fit_light(state, data, ddp, main, log, log_path)
            if is_light_step(state.cfg, state.step):
                res = light_step(state, data)
                res["stage"] = "b-light"
            else:
                res = train_step(state, data)
            state.step += 1
            state.elapsed += time.monotonic() - t0
            last.update(res)
            # what depends on the clock; in a data-parallel run rank 0's clock decides for every rank
            n_win = max(1, min(24, cfg.calibration_steps // 4))
            calibrate = not cfg.steps and (state.step >= cfg.calibration_steps
                                           or state.elapsed >= 60.0 * cfg.minutes)
            snaps = [m not in state.snapshots_done and state.elapsed >= 60.0 * m for m in cfg.snapshot_minutes]
            checkpoint = (state.step % cfg.checkpoint_every == 0 or time.monotonic() - t_last_ck > 300
                          or first_checkpoint_due(state, ck_path))
            if ddp is not None:
                calibrate, *snaps, checkpoint = ddp.decide(calibrate, *snaps, checkpoint)
            if not cfg.steps:  # a minutes budget: fix the step count once the first steps are timed
                if state.step == cfg.calibration_steps - n_win:
                    t_window = state.elapsed
                if calibrate:
                    full = state.step >= cfg.calibration_steps and t_window is not None
                    rec = calibrate_steps(state, cfg.minutes, state.elapsed - (t_window if full else 0.0),
                                          n_win if full else state.step, log)
                    if ddp is not None:
                        rec = ddp.broadcast_object(rec)
                    cfg = replace(cfg, steps=rec["steps"],
                                  schedule_knots=rec.get("schedule_knots", cfg.schedule_knots))
                    state.cfg = local(cfg)
                    bar.total = cfg.steps
                    write_run_config(rec)
                    calibration, mark = rec, (state.step, state.elapsed)
                    checks = [p for p in RETIME_AT if p > progress(state)]
            elif mark is not None and checks and progress(state) >= checks[0] and state.step - mark[0] >= n_win:
                # a calibrated budget checks its clock again: a step may cost more as the occupancy grid fills
                while checks and progress(state) >= checks[0]:
                    checks.pop(0)
                new = retime_steps(cfg, state.step, state.elapsed, mark, log) if main else None
                if ddp is not None:
                    new = ddp.broadcast_object(new)
                mark = (state.step, state.elapsed)
                if new is not None:
                    cfg = replace(cfg, steps=new[0], schedule_knots=new[1])
                    state.cfg = local(cfg)
                    bar.total = cfg.steps
                    calibration = {**calibration, "steps": cfg.steps,
                                   "retimed": [*calibration.get("retimed", []),
                                               {"at_step": state.step, "elapsed": round(state.elapsed, 2),
                                                "steps": cfg.steps}]}
                    write_run_config(calibration)
            if state.step % cfg.log_every == 0 or state.step == 1:
                if ddp is not None:  # the batch's loss and PSNR over every rank's rays
                    last = ddp.average_scalars(last, ("loss", "psnr"))
                rec = {"kind": "train", "step": state.step, "elapsed": round(state.elapsed, 2),
                       "lr": state.optimizer.param_groups[0]["lr"], "occupancy": state.occupancy.occupancy_fraction(),
                       **{k: v for k, v in last.items()}, "world_size": world_size}
                if main:
                    with open(log_path, "a") as f:
                        f.write(json.dumps(rec) + "\n")
            for m, due in zip(cfg.snapshot_minutes, snaps):
                if due:
                    save(out / "snapshots" / f"checkpoint_{m:g}min.pt")
                    state.snapshots_done.append(m)
            if checkpoint:
                save(ck_path)
                t_last_ck = time.monotonic()
            bar.update(1)
            if "psnr" in last:
                bar.set_postfix_str(f"loss {last.get('loss', float('nan')):.4f} psnr {last['psnr']:.2f} "
                                    f"{last.get('stage', '')}".strip())
    except TrainingDiverged as e:
        bar.close()
        if main:
            folder.finish()
        log(f"[dars] {e}")
        raise
    except KeyboardInterrupt:
        bar.close()
        save(ck_path, collective=False)  # the other ranks may be gone: rank 0's RNG state only
        if main:
            folder.finish()
        log(f"[dars] interrupted at step {state.step}; checkpoint saved, continue with --resume")
        raise
    bar.close()
    save(ck_path)
    snaps = [m not in state.snapshots_done and state.elapsed >= 60.0 * m - 1.0 for m in cfg.snapshot_minutes]
    if ddp is not None:
        snaps = ddp.decide(*snaps) if snaps else []
    for m, due in zip(cfg.snapshot_minutes, snaps):  # a budget that ends exactly at a milestone
        if due:
            save(out / "snapshots" / f"checkpoint_{m:g}min.pt")
    if ddp is not None:  # the copies must be identical: record each rank's parameter digest
        digests = ddp.parameter_digests(state)
        in_sync = len(set(digests)) == 1
        rss = ddp.gather_objects(peak_rss_mb())
        if main:
            with open(log_path, "a") as f:
                f.write(json.dumps({"kind": "distributed", "step": state.step, "world_size": world_size,
                                    "backend": ddp.backend, "parameter_digests": digests, "in_sync": in_sync,
                                    "peak_rss_mb": rss}) + "\n")
        if not in_sync:
            log(f"[dars] warning: the ranks' parameters differ at the end ({digests}); rank 0's are saved")
    if main:
        try:
            _plot_curves(log_path, out / "loss_curves.png")
        except Exception as e:  # noqa: BLE001 - a plot must never lose a finished run
            log(f"[dars] could not plot loss curves: {e}")
        folder.finish()
    log(f"[dars] trained {state.step} steps in {state.elapsed / 60:.1f} min -> {ck_path}")
    return ck_path
