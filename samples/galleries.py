"""Procedural galleries on demand: seed lists and a render cache the benchmarks and training scripts call.

Seeds:

* :data:`VALIDATION_SEEDS` — the held-out validation galleries every quality claim is reported on (mean and worst).
  They are held out: no code path is tuned on them one by one and no network is trained on them. Do not add them to
  any training set, and do not pick or drop seeds after looking at scores.
* :data:`PRIOR_TRAIN_SEEDS` — a disjoint range for training the shipped segmentation and light networks (render
  them with the ``prior`` profile, and with the ``light`` profile — 8 views of 64 px, ~20 s a room on one core —
  for many more rooms and lightings for the light network).

Cache layout (never inside the repository)::

    $DARS_CACHE/galleries/            (default ~/.cache/dars/galleries)
      <profile>/seed_<seed>/          transforms_{train,test}.json, train/, test/, env.hdr, light.hdr,
                                      render_summary.json, stamp.json
      <profile>/.lock-seed_<seed>     a lock file while one process renders that seed

``stamp.json`` holds :func:`config_hash` (the generator version, the gallery's config and the profile's options). A
gallery is rendered when it is missing or its stamp differs (the generator changed), into a temporary directory
beside it that is renamed into place when complete, so a reader never sees a half-written gallery.

Usage::

    python samples/galleries.py --profile validation --seeds all      # render the missing validation galleries
    python samples/galleries.py --profile prior --seeds 0-299         # training galleries for the priors
    python samples/galleries.py --profile light --seeds 500-699       # many small rooms for the light network
    python samples/galleries.py --profile walls --seeds 400-479       # half of them papered/bricked/boarded (segmenter)
    python samples/galleries.py --profile validation --seeds all --status

    from galleries import VALIDATION_SEEDS, ensure_gallery
    scene_dir = ensure_gallery(VALIDATION_SEEDS[0])                     # renders on first use (~30-60 min), then cached
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Iterator, Sequence

sys.path.insert(0, str(Path(__file__).resolve().parent))

VALIDATION_SEEDS: tuple[int, ...] = tuple(range(1_000_000, 1_000_008))
"""Held-out validation galleries (8). Never trained or tuned on one by one."""
PRIOR_TRAIN_SEEDS = range(0, 1_000_000)
"""Training galleries for the networks; disjoint from :data:`VALIDATION_SEEDS`."""


def dars_cache() -> Path:
    """The render cache's base: ``$DARS_CACHE``, else ``~/.cache/dars``."""
    base = os.environ.get("DARS_CACHE")
    return Path(base).expanduser() if base else Path.home() / ".cache" / "dars"


def cache_root(root: str | Path | None = None) -> Path:
    """``root``, else ``$DARS_CACHE/galleries``, else ``~/.cache/dars/galleries``."""
    if root is not None:
        return Path(root).expanduser()
    return dars_cache() / "galleries"


def cached_scenes(profile: str = "validation", root: str | Path | None = None) -> list[str]:
    """The galleries of ``profile`` already rendered in the cache (sorted paths; none rendered here)."""
    return sorted(str(p) for p in (cache_root(root) / profile).glob("seed_*") if p.is_dir())


def _options(profile: str):
    import render_gallery as rg

    if profile not in rg.PROFILES:
        raise ValueError(f"unknown profile {profile!r}: choose one of {sorted(rg.PROFILES)}")
    return rg.PROFILES[profile]


def config_hash(seed: int, profile: str = "validation") -> str:
    """sha256 (16 hex digits) of what determines a cached gallery: generator version, config, profile options."""
    import procedural as pg

    opts = asdict(replace(_options(profile), progress=True, variant=None))
    if not opts["wall_patterns"]:  # added after galleries were cached: hashed only when set, so those stay valid
        del opts["wall_patterns"]
    cfg = pg.random_gallery(seed, wall_patterns=_options(profile).wall_patterns)
    blob = json.dumps({"generator": pg.GENERATOR_VERSION, "config": cfg.to_dict(), "options": opts}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def gallery_dir(seed: int, profile: str = "validation", root: str | Path | None = None) -> Path:
    """Where a gallery is (or will be) cached."""
    return cache_root(root) / profile / f"seed_{int(seed)}"


def is_cached(seed: int, profile: str = "validation", root: str | Path | None = None) -> bool:
    """True when the cached gallery exists and its stamp matches the current generator."""
    stamp = gallery_dir(seed, profile, root) / "stamp.json"
    try:
        return json.loads(stamp.read_text()).get("hash") == config_hash(seed, profile)
    except (OSError, ValueError):
        return False


@contextlib.contextmanager
def _lock(path: Path) -> Iterator[None]:
    import fcntl

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def ensure_gallery(seed: int, profile: str = "validation", root: str | Path | None = None, force: bool = False,
                   progress: bool = False) -> Path:
    """The directory of a rendered gallery, rendering it first if it is missing or stale.

    Args:
        seed: gallery seed (:func:`procedural.random_gallery`).
        profile: render profile (``validation``, ``prior``, ...; see ``render_gallery.PROFILES``).
        root: cache root (default: :func:`cache_root`).
        force: render even if cached.
        progress: show per-view progress bars.

    Returns:
        the gallery directory (``transforms_{train,test}.json`` inside), loadable by ``toolkit.scene.load_scene``.

    Raises:
        ValueError: unknown profile or a negative seed. ConfigError: Mitsuba or the HDR probes are missing.
    """
    import procedural as pg
    import render_gallery as rg

    if int(seed) < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    opts = replace(_options(profile), progress=progress)
    final = gallery_dir(seed, profile, root)
    want = config_hash(seed, profile)
    with _lock(final.parent / f".lock-seed_{int(seed)}"):
        if not force and is_cached(seed, profile, root):
            return final
        t0 = time.time()

        def render(tmp: Path) -> dict:
            summary = rg.render_gallery(pg.random_gallery(int(seed), wall_patterns=opts.wall_patterns), tmp, opts)
            return {"hash": want, "seed": int(seed), "profile": profile, "generator": pg.GENERATOR_VERSION,
                    "seconds": round(time.time() - t0, 1), "rendered_at": time.strftime("%Y-%m-%dT%H:%M:%S"),
                    "summary": summary}

        render_in_place_of(final, render)
    return final


def render_in_place_of(final: Path, render) -> None:
    """Render into a temporary sibling of ``final`` (``render(tmp)`` fills it and returns its stamp), write the stamp
    as ``stamp.json``, then swap it in for ``final``; the old folder is removed only after the swap. Call it holding
    :func:`_lock` on ``final``'s seed."""
    tmp = final.parent / f".tmp-{final.name}-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        stamp = render(tmp)
        (tmp / "stamp.json").write_text(json.dumps(stamp, indent=1) + "\n")
        old = final.parent / f".old-{final.name}-{os.getpid()}"
        if final.exists():
            final.rename(old)
        tmp.rename(final)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def parse_seeds(spec: str, profile: str) -> list[int]:
    """``all`` (the validation seeds; for other profiles too), ``A-B`` (inclusive), ``a,b,c`` or a mix."""
    if spec == "all":
        return list(VALIDATION_SEEDS)
    out: list[int] = []
    for part in spec.split(","):
        part = part.strip()
        if "-" in part:
            a, b = part.split("-", 1)
            out += list(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    if profile != "validation" and set(out) & set(VALIDATION_SEEDS):
        raise ValueError(f"seeds {sorted(set(out) & set(VALIDATION_SEEDS))} are validation seeds: they are held out of profile {profile!r}")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profile", default="validation", help="render profile: validation, prior, ... (default: validation)")
    ap.add_argument("--seeds", default="all", help="all (the validation seeds), A-B, or a,b,c")
    ap.add_argument("--root", default=None, help="cache root (default: $DARS_CACHE/galleries or ~/.cache/dars/galleries)")
    ap.add_argument("--force", action="store_true", help="re-render even when cached")
    ap.add_argument("--status", action="store_true", help="only print which galleries are cached, stale or missing")
    ap.add_argument("--progress", action="store_true", help="per-view progress bars")
    args = ap.parse_args(argv)
    try:
        _options(args.profile)
        seeds = parse_seeds(args.seeds, args.profile)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    rows = []
    for k, seed in enumerate(seeds):
        d = gallery_dir(seed, args.profile, args.root)
        cached = is_cached(seed, args.profile, args.root)
        if args.status:
            print(f"seed {seed}: {'cached' if cached else ('stale' if d.exists() else 'missing')}  {d}")
            continue
        t0 = time.time()
        if cached and not args.force:
            print(f"[{k + 1}/{len(seeds)}] seed {seed}: cached  {d}", flush=True)
            continue
        print(f"[{k + 1}/{len(seeds)}] seed {seed}: rendering ({args.profile}) ...", flush=True)
        try:
            ensure_gallery(seed, args.profile, args.root, force=args.force, progress=args.progress)
        except Exception as e:  # keep going with the next seed; report at the end
            print(f"[{k + 1}/{len(seeds)}] seed {seed}: FAILED: {type(e).__name__}: {e}", file=sys.stderr, flush=True)
            rows.append((seed, None, None))
            continue
        stamp = json.loads((d / "stamp.json").read_text())
        noise = stamp["summary"]["noise"]
        rows.append((seed, time.time() - t0, noise))
        print(f"[{k + 1}/{len(seeds)}] seed {seed}: {time.time() - t0:.0f} s  spp {noise['spp_mean']:.0f} (min {noise['spp_min']}, max "
              f"{noise['spp_max']})  noise {noise.get('psnr_db_mean', float('nan'))} dB (min {noise.get('psnr_db_min', float('nan'))})  {d}",
              flush=True)
    done = [r for r in rows if r[1] is not None]
    if done:
        secs = [r[1] for r in done]
        print(f"rendered {len(done)} galleries: {sum(secs) / len(secs):.0f} s each on average (min {min(secs):.0f}, max {max(secs):.0f})")
    return 1 if any(r[1] is None for r in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
