"""Render the light-estimation training set: the gallery sample under many known environments (SPEC stage 4).

The scene is the gallery corner of :mod:`render_gallery` (same geometry, materials and camera distribution,
:func:`render_gallery.sample_cameras`); only the environment changes. Lightings (all seeded):

* the four Probulator HDR maps in ``/work/shared/data/envmaps`` rotated about world +z by a random angle and
  re-tinted (per-channel log-normal gains, σ = ``--tint-sigma``, normalised to unit mean);
* random smooth SH skies (:func:`gallery_assets.sky_environment`), also rotated about +z and re-tinted;
* mixtures of the two (training only): a rotated training probe and a random sky, each normalised to unit mean
  radiance, blended with a random sky weight in [0.2, 0.8] (the sky rotated independently by a column roll), tinted.
  They fill the gap between the strongly directional probes and the soft skies;
* sun + sky (training only): a random sky plus a small bright lobe ``exp(κ(ω·s − 1))`` (κ ∈ [300, 3000], i.e. a
  1-3.3° disc) at elevation 5-75°, carrying 30-85 % of the energy, with its own tint: hard, visible directional
  light of the kind a held-out probe with a sun shows, which the three training probes alone under-represent.

Held out (never trained on): **lightings, not views** — every rotation of one whole probe map (``--holdout-probe``,
default ``pisa``, the map the bundled sample ``samples/gallery`` was rendered with, so ``dars priors light
samples/gallery`` is a held-out figure too) and ``--test-skies`` skies whose seeds are disjoint from the training
skies'.

Ground truth is the environment's SH exactly as ``render_gallery.py`` computes it for the sample: the loaded
Mitsuba emitter is queried at SPEC lat-long pixel centres on a 2x denser grid than the input map
(:func:`render_gallery.environment_as_used`) and projected with :func:`toolkit.sh.fit_sh_probe`.

Exposure: every lighting gets a target mean sRGB drawn from ``--exposure-range`` (the sample used 0.42) and the
factor ``k`` that reaches it on that lighting's views (bisection, as the sample's automatic exposure). Rendering
is linear in the environment, so the file stores radiance and SH at the environment's own scale plus ``k``;
:func:`toolkit.lightnet.load_light_dataset` applies ``k`` to both (images and GT stay consistent, and a trainer
may jitter ``k`` further).

Speed: the scene is built once; each lighting only swaps the emitter's texel data and ``to_world`` (Mitsuba's
``envmap`` stores its bitmap with one wrap-around column on each side) — the renders and emitter queries match a
freshly built scene (checked by ``--self-check`` and in ``tests/test_lightnet.py``). With ``llvm_ad_rgb`` on one
thread, 64 x 64 px at 16 spp take ≈ 0.12 s a view: the default set (576 lightings x 4 views) takes ≈ 3 minutes of CPU (longer on a busy machine).

Output: one ``.npz`` (default ``~/.cache/dars/lightnet/gallery_lightings_s<seed>.npz``; never put it in git) with
``radiance`` float16 [N, H, W, 3] linear, ``sh`` float32 [N, 9, 3] (SPEC convention, world frame), ``exposure``
float32 [N], ``lighting`` int32 [N], ``test`` bool [N], ``c2w`` float32 [N, 4, 4], per-lighting ``sources``,
``rotate_deg``, ``tints``, and ``meta`` (JSON: command, seed, times).

Usage::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 OMP_NUM_THREADS=1 \\
    .venv/bin/python samples/render_lightings.py --seed 0          # -> ~/.cache/dars/lightnet/gallery_lightings_s0.npz
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

_HERE = Path(__file__).resolve().parent
for _p in (_HERE.parent, _HERE):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import render_gallery as rg  # noqa: E402

from toolkit._checks import ConfigError  # noqa: E402

ENVMAP_DIR = Path("/work/shared/data/envmaps")
PROBES = ("ennis", "grace_new", "pisa", "wells")
DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "dars" / "lightnet"

__all__ = ["LightingSpec", "LightingPlan", "plan_lightings", "EnvironmentSwapper", "render_lighting_dataset", "main"]


@dataclass(frozen=True)
class LightingSpec:
    """One environment of the data set."""

    source: str
    """Probe name (``pisa``...) or ``sky``."""
    seed: int
    """Sky seed (skies) or the seed of this lighting's tint/rotation/cameras."""
    rotate_deg: float
    """Rotation about world +z, degrees."""
    tint: tuple[float, float, float]
    """Per-channel gain (mean 1)."""
    exposure_target: float
    """Mean sRGB of this lighting's views after exposure."""
    test: bool
    """Held out from training."""
    sky_weight: float = 0.0
    """Mixtures: weight of a random sky blended with the probe (0: no mixture)."""
    sky_seed: int = 0
    """Mixtures: seed of the sky."""
    sky_roll: int = 0
    """Mixtures: the sky map's columns are rolled by this much (a rotation about +z of its own)."""
    sun_fraction: float = 0.0
    """Suns (``source == "sky"``): fraction of the energy in the sun lobe (0: no sun)."""
    sun_direction: tuple[float, float] = (45.0, 0.0)
    """Suns: (elevation, azimuth) in degrees; azimuth 0 faces +y, 90 faces +x (SPEC lat-long φ)."""
    sun_kappa: float = 1000.0
    """Suns: lobe sharpness κ."""
    sun_tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Suns: colour of the sun relative to the sky."""

    @property
    def label(self) -> str:
        """``pisa``, ``sky``, ``wells+sky`` for a mixture, ``sky+sun``."""
        if self.sun_fraction > 0:
            return "sky+sun"
        return f"{self.source}+sky" if self.sky_weight > 0 else self.source


@dataclass(frozen=True)
class LightingPlan:
    """How many lightings of each kind (see the module docstring)."""

    seed: int = 0
    rotations_per_probe: int = 40
    """Training lightings per training probe map."""
    holdout_probe: str = "pisa"
    """This probe is only used for held-out lightings."""
    holdout_rotations: int = 32
    train_skies: int = 120
    test_skies: int = 24
    mixtures: int = 160
    """Training lightings that blend a training probe with a random sky."""
    suns: int = 120
    """Training sun + sky lightings."""
    tint_sigma: float = 0.15
    """σ of the log-normal per-channel tint."""
    exposure_range: tuple[float, float] = (0.28, 0.56)
    """Target mean sRGB per lighting, uniform in this range."""


def plan_lightings(plan: LightingPlan = LightingPlan()) -> list[LightingSpec]:
    """The seeded list of lightings (training ones first, then held-out ones).

    The held-out lightings come from their own random stream, so they do not change when the training counts do.
    """
    if plan.holdout_probe not in PROBES and plan.holdout_probe != "none":
        raise ConfigError(f"--holdout-probe {plan.holdout_probe!r}: choose one of {PROBES} or 'none'")
    rng = np.random.default_rng(plan.seed)
    specs: list[LightingSpec] = []

    def tint() -> tuple[float, float, float]:
        g = np.exp(rng.normal(0.0, plan.tint_sigma, 3))
        return tuple(float(v) for v in g / g.mean())

    def add(source: str, seed: int, test: bool) -> None:
        specs.append(LightingSpec(source=source, seed=seed, rotate_deg=float(rng.uniform(0.0, 360.0)),
                                  tint=tint(),
                                  exposure_target=float(rng.uniform(*plan.exposure_range)), test=test))

    for p in PROBES:
        if p == plan.holdout_probe:
            continue
        for _ in range(plan.rotations_per_probe):
            add(p, int(rng.integers(1 << 30)), False)
    for k in range(plan.train_skies):
        add("sky", 1000 + plan.seed * 100_000 + k, False)
    train_probes = [p for p in PROBES if p != plan.holdout_probe]
    for k in range(plan.mixtures):
        probe = train_probes[int(rng.integers(len(train_probes)))]
        add(probe, int(rng.integers(1 << 30)), False)
        specs[-1] = replace(specs[-1], sky_weight=float(rng.uniform(0.2, 0.8)), sky_seed=50_000 + plan.seed * 100_000 + k,
                            sky_roll=int(rng.integers(0, 256)))
    for k in range(plan.suns):
        add("sky", 70_000 + plan.seed * 100_000 + k, False)
        specs[-1] = replace(specs[-1], sun_fraction=float(rng.uniform(0.3, 0.85)),
                            sun_direction=(float(rng.uniform(5.0, 75.0)), float(rng.uniform(0.0, 360.0))),
                            sun_kappa=float(np.exp(rng.uniform(np.log(300.0), np.log(3000.0)))), sun_tint=tint())
    rng = np.random.default_rng([plan.seed, 1])  # held-out stream
    if plan.holdout_probe != "none":
        for _ in range(plan.holdout_rotations):
            add(plan.holdout_probe, int(rng.integers(1 << 30)), True)
    for k in range(plan.test_skies):
        add("sky", 90_000 + plan.seed * 100_000 + k, True)
    return specs


def _sun_environment(spec: LightingSpec) -> "rg.Environment":
    """A random sky (unit mean radiance) plus a sun lobe holding ``spec.sun_fraction`` of the energy, tinted."""
    import torch

    from toolkit.sh import latlong_directions, latlong_solid_angles

    sky = rg.load_environment("sky", seed=spec.seed).latlong.astype(np.float64)
    sky = sky / sky.mean()
    H, W = sky.shape[:2]
    el, az = (math.radians(v) for v in spec.sun_direction)
    s = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    d = latlong_directions(H, W, dtype=torch.float64).numpy()
    dw = latlong_solid_angles(H, W, dtype=torch.float64).numpy()
    lobe = np.exp(spec.sun_kappa * (d @ s - 1.0))
    e_sky = float((sky.mean(-1) * dw).sum())
    scale = spec.sun_fraction / (1.0 - spec.sun_fraction) * e_sky / float((lobe * dw).sum())
    env = (sky + scale * lobe[..., None] * np.asarray(spec.sun_tint)) * np.asarray(spec.tint)
    return rg.Environment(latlong=np.ascontiguousarray(env, np.float32), rotate_z_deg=spec.rotate_deg,
                          source=f"sky:{spec.seed}+sun")


def probe_path(name: str) -> Path:
    """The Probulator map of a probe name."""
    return ENVMAP_DIR / f"probulator_{name}_256x128.hdr"


def environment_of(spec: LightingSpec) -> "rg.Environment":
    """The :class:`render_gallery.Environment` of a spec (tint applied; scale 1)."""
    src = "sky" if spec.source == "sky" else str(probe_path(spec.source))
    if spec.sun_fraction > 0:
        return _sun_environment(spec)
    if spec.sky_weight <= 0:
        return rg.load_environment(src, spec.rotate_deg, spec.tint, 1.0, spec.seed)
    env = rg.load_environment(src, spec.rotate_deg, (1.0, 1.0, 1.0), 1.0, spec.seed)
    probe = env.latlong / env.latlong.mean()
    sky = np.roll(rg.load_environment("sky", seed=spec.sky_seed).latlong, spec.sky_roll, axis=1)
    sky = sky / sky.mean()
    mixed = ((1.0 - spec.sky_weight) * probe + spec.sky_weight * sky) * np.asarray(spec.tint, np.float32)
    return rg.Environment(latlong=np.ascontiguousarray(mixed, np.float32), rotate_z_deg=env.rotate_z_deg,
                          source=f"{env.source}+sky:{spec.sky_seed}")


class EnvironmentSwapper:
    """The gallery built once; :meth:`set` swaps the environment emitter's texels and placement in place.

    Mitsuba's ``envmap`` keeps its bitmap as ``env.data`` [Hm, Wm + 2, 3] with a wrap-around column on each side
    (``[last, bitmap, first]``); we write the same layout, so the emitter equals one built from scratch.
    """

    def __init__(self, variant: str | None = None, cfg: rg.GalleryConfig | None = None, workdir: Path | None = None):
        import tempfile

        self.mi, self.dr, self.variant = rg.import_mitsuba(variant)
        self.cfg = cfg or rg.GalleryConfig()
        first = rg.load_environment("sky", seed=0)
        with tempfile.TemporaryDirectory() as tmp:
            self.built = rg.build_scene(self.mi, self.cfg, first, Path(workdir) if workdir else Path(tmp))
        self.params = self.mi.traverse(self.built.scene)
        self.env_shape = first.latlong.shape[:2]

    def set(self, env: "rg.Environment") -> None:
        """Install ``env`` (a SPEC lat-long map of the same size as the first one) as the scene's emitter."""
        mi = self.mi
        if env.latlong.shape[:2] != self.env_shape:
            raise ConfigError(f"environment {env.source} is {env.latlong.shape[:2]}, the swapper was built for {self.env_shape}")
        bm = rg._mitsuba_env_bitmap(env.latlong)
        self.params["env.data"] = mi.TensorXf(np.ascontiguousarray(np.concatenate([bm[:, -1:], bm, bm[:, :1]], 1)))
        T = mi.ScalarTransform4f if self.variant.startswith("scalar") else mi.Transform4f
        self.params["env.to_world"] = T().rotate([0, 0, 1], env.rotate_z_deg).rotate([1, 0, 0], 90)
        self.params.update()

    def ground_truth_sh(self) -> np.ndarray:
        """float64 [9, 3]: the SH of the installed emitter, computed as ``render_gallery.py`` does for the sample."""
        import torch

        from toolkit.sh import fit_sh_probe

        H, W = self.env_shape
        dense = rg.environment_as_used(self.mi, self.dr, self.built, 2 * H, 2 * W)
        return fit_sh_probe(torch.as_tensor(dense, dtype=torch.float64)).coeffs.numpy()

    def render(self, cameras: np.ndarray, size: int, spp: int, seed: int, fov_x: float = math.radians(45.0),
               max_depth: int = 8, sampler: str = "independent") -> np.ndarray:
        """Path-trace views under the installed environment: float32 [N, size, size, 3] linear radiance."""
        mi = self.mi
        scalar = self.variant.startswith("scalar")
        T = mi.ScalarTransform4f if scalar else mi.Transform4f
        key = (size, spp, fov_x, max_depth, sampler)
        if getattr(self, "_key", None) != key:
            self._sensor = mi.load_dict({
                "type": "perspective", "fov": math.degrees(fov_x), "fov_axis": "x",
                "to_world": mi.ScalarTransform4f(rg.c2w_to_mitsuba(cameras[0]).tolist()),
                "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                "sampler": {"type": sampler, "sample_count": spp},
            })
            self._integrator = mi.load_dict({"type": "path", "max_depth": max_depth, "hide_emitters": False})
            self._sensor_params = mi.traverse(self._sensor)
            self._key = key
        out = np.zeros((len(cameras), size, size, 3), np.float32)
        for i, c2w in enumerate(cameras):
            self._sensor_params["to_world"] = T(rg.c2w_to_mitsuba(c2w).tolist())
            self._sensor_params.update()
            img = mi.render(self.built.scene, sensor=self._sensor, integrator=self._integrator, spp=spp, seed=seed + i)
            out[i] = np.array(img)[..., :3]
        return out


def render_lighting_dataset(specs: Sequence[LightingSpec], views: int = 4, size: int = 64, spp: int = 16,
                            seed: int = 0, variant: str | None = None, progress: bool = True) -> dict[str, Any]:
    """Render ``views`` views of the gallery under every lighting; returns the arrays written to the ``.npz``.

    Cameras of lighting ``l`` are :func:`render_gallery.sample_cameras` ``(views, seed * 1_000_003 + 7919 * l + 1)``
    (the sample's distribution, a different set per lighting).
    """
    from tqdm import tqdm

    if views < 1 or size < 8 or spp < 1:
        raise ConfigError(f"views={views}, size={size}, spp={spp}: need views >= 1, size >= 8, spp >= 1")
    t0 = time.time()
    sw = EnvironmentSwapper(variant)
    L, N = len(specs), len(specs) * views
    rad = np.zeros((N, size, size, 3), np.float16)
    sh = np.zeros((N, 9, 3), np.float32)
    exposure = np.zeros(N, np.float32)
    c2w_all = np.zeros((N, 4, 4), np.float32)
    for li, spec in enumerate(tqdm(specs, desc=f"lightings ({sw.variant}, {size}px, {spp} spp)", disable=not progress,
                                   file=sys.stderr)):
        sw.set(environment_of(spec))
        cams = rg.sample_cameras(views, seed * 1_000_003 + 7919 * li + 1)
        r = sw.render(cams, size, spp, seed=(seed * 1_000_003 + li) * 64)
        k = rg._auto_exposure(r, spec.exposure_target)
        s = slice(li * views, (li + 1) * views)
        rad[s] = np.minimum(r, 60000.0).astype(np.float16)
        sh[s] = sw.ground_truth_sh().astype(np.float32)[None]
        exposure[s] = k
        c2w_all[s] = cams
    return {
        "radiance": rad, "sh": sh, "exposure": exposure, "c2w": c2w_all,
        "lighting": np.repeat(np.arange(L, dtype=np.int32), views),
        "test": np.repeat(np.array([s.test for s in specs], bool), views),
        "sources": np.array([s.label for s in specs]),
        "rotate_deg": np.array([s.rotate_deg for s in specs], np.float32),
        "tints": np.array([s.tint for s in specs], np.float32),
        "exposure_target": np.array([s.exposure_target for s in specs], np.float32),
        "variant": sw.variant, "seconds": time.time() - t0,
    }


def self_check(variant: str | None = None) -> dict[str, float]:
    """Swapped environment vs a scene built from scratch (emitter query and one render), and the sample's GT SH.

    Returns max abs differences: ``emitter``, ``render`` and ``sample_sh`` (``pisa`` at 0°, scaled by the sample's
    exposure, vs ``samples/gallery/transforms_train.json``'s ``"sh"``; NaN when the sample is absent).
    """
    import tempfile

    sw = EnvironmentSwapper(variant)
    env = rg.load_environment(str(probe_path("wells")), 73.0, (1.1, 0.9, 0.8))
    sw.set(env)
    with tempfile.TemporaryDirectory() as tmp:
        fresh = rg.build_scene(sw.mi, sw.cfg, env, Path(tmp))
    a = rg.environment_as_used(sw.mi, sw.dr, sw.built, 32, 64)
    b = rg.environment_as_used(sw.mi, sw.dr, fresh, 32, 64)
    cams = rg.sample_cameras(1, 5)
    x = sw.render(cams, 32, 8, seed=3)
    sensor, integ = sw._sensor, sw._integrator
    y = np.array(sw.mi.render(fresh.scene, sensor=sensor, integrator=integ, spp=8, seed=3))[..., :3]
    out = {"emitter": float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12)), "render": float(np.abs(x[0] - y).max())}
    sample = _HERE / "gallery" / "transforms_train.json"
    if sample.is_file():
        meta = json.loads(sample.read_text())
        sw.set(rg.load_environment(str(probe_path("pisa")), 0.0))
        got = sw.ground_truth_sh() * float(meta["render"]["exposure"])
        out["sample_sh"] = float(np.abs(got - np.asarray(meta["sh"])).max())
    else:
        out["sample_sh"] = float("nan")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=None, help=f"output .npz (default {DEFAULT_CACHE}/gallery_lightings_s<seed>.npz)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--views", type=int, default=4, help="views per lighting (default 4)")
    ap.add_argument("--size", type=int, default=64, help="image size in pixels (default 64)")
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    ap.add_argument("--rotations-per-probe", type=int, default=40)
    ap.add_argument("--holdout-probe", default="pisa", help=f"probe used only for held-out lightings ({', '.join(PROBES)}, none)")
    ap.add_argument("--holdout-rotations", type=int, default=32)
    ap.add_argument("--train-skies", type=int, default=120)
    ap.add_argument("--test-skies", type=int, default=24)
    ap.add_argument("--mixtures", type=int, default=160, help="training probe+sky blends (default 160)")
    ap.add_argument("--suns", type=int, default=120, help="training sun+sky lightings (default 120)")
    ap.add_argument("--tint-sigma", type=float, default=0.15)
    ap.add_argument("--exposure-range", type=float, nargs=2, default=(0.28, 0.56), metavar=("LO", "HI"))
    ap.add_argument("--variant", default=None, help="mitsuba variant (default: llvm_ad_rgb if libLLVM 19 exists)")
    ap.add_argument("--threads", type=int, default=1, help="Dr.Jit worker threads (default 1)")
    ap.add_argument("--self-check", action="store_true", help="check the environment swap and the sample's GT SH, then exit")
    ap.add_argument("--force", action="store_true", help="overwrite an existing --out")
    args = ap.parse_args(argv)

    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import torch

    torch.set_num_threads(args.threads)
    try:
        _, dr, variant = rg.import_mitsuba(args.variant)
        dr.set_thread_count(args.threads)
        if args.self_check:
            print(json.dumps(self_check(variant)))
            return 0
        out = Path(args.out).expanduser() if args.out else DEFAULT_CACHE / f"gallery_lightings_s{args.seed}.npz"
        if out.exists() and not args.force:
            print(f"error: {out} exists; pass --force to overwrite it", file=sys.stderr)
            return 2
        plan = LightingPlan(seed=args.seed, rotations_per_probe=args.rotations_per_probe, holdout_probe=args.holdout_probe,
                            holdout_rotations=args.holdout_rotations, train_skies=args.train_skies, test_skies=args.test_skies, mixtures=args.mixtures, suns=args.suns,
                            tint_sigma=args.tint_sigma, exposure_range=tuple(args.exposure_range))
        specs = plan_lightings(plan)
        data = render_lighting_dataset(specs, args.views, args.size, args.spp, args.seed, variant)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    meta = {"command": "samples/render_lightings.py " + " ".join(sys.argv[1:] if argv is None else argv),
            "plan": asdict(plan), "views": args.views, "size": args.size, "spp": args.spp, "variant": data.pop("variant"),
            "seconds": round(data.pop("seconds"), 1), "fov_x_deg": 45.0, "format": "dars-light-dataset", "version": 1,
            "sh": "SPEC real SH order 2, incident radiance, world +z up, at the environment's scale (multiply by exposure)"}
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.npz")
    np.savez(tmp, meta=np.array(json.dumps(meta)), **data)
    os.replace(tmp, out)
    n, nt = len(data["test"]), int(data["test"].sum())
    print(f"wrote {n} views ({n - nt} train / {nt} held-out, {len(specs)} lightings) to {out} in {meta['seconds']} s "
          f"({meta['variant']}, {args.size}px, {args.spp} spp)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
