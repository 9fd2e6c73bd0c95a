"""Assets built in code for tests/test_viewer.py and tests/test_web.py: a textured cube GLB, and (slow, cached for
the session) a short training run on samples/gallery exported with `dars export-asset`."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from export.gltf import export_gltf
from toolkit.bake import PBRTextures, UVMesh, compute_tangents
from toolkit.io import linear_to_srgb

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "gallery"

CUBE_FACES = ((0, 0, 1), (0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))
"""Outward normal of cube face k (world +z up); face k has semantic class k and atlas cell (k % 3, k // 3)."""
CUBE_ALBEDO = np.array([[0.8, 0.2, 0.2], [0.2, 0.7, 0.3], [0.2, 0.3, 0.85], [0.9, 0.8, 0.2], [0.7, 0.3, 0.8],
                        [0.9, 0.9, 0.9]])
CUBE_ROUGHNESS = np.array([0.15, 0.35, 0.55, 0.75, 0.95, 0.4])
CUBE_METALLIC = np.array([0.0, 1.0, 0.0, 0.0, 1.0, 0.0])
CUBE_SH = np.random.default_rng(3).normal(size=(9, 3)) * 0.3
CUBE_SH[0] += 2.5
CUBE_SH[2] += 0.8  # brighter from above


def textured_cube(path: Path, sh=CUBE_SH, cell: int = 32, pattern: bool = True, extras: dict | None = None,
                  occlusion: float = 1.0, light_tint=None, texture_blur: float | None = None,
                  occlusion_checker: bool = False) -> Path:
    """A unit cube centred at the origin as a GLB: 6 faces in a 3 x 2 atlas (``cell`` px per face, 2 px margins),
    per-face albedo / roughness / metallic (:data:`CUBE_ALBEDO` …), one semantic primitive per face.

    ``pattern``: a checker in the base colour and a ripple in the normal map of faces 0, 2, 4 (tilting the normal
    along the face's tangent); without it every face is flat and uniform (an analytic reference is exact).
    ``extras``: merged into the GLB's ``extras.dars`` (e.g. a backdrop). ``occlusion``: ORM red on every face
    (``occlusion_checker``: times the base colour's checker, 0.4 / 1).
    ``light_tint``: an RGB light tint (linear, at most :data:`toolkit.bake.LIGHT_TINT_SCALE`) on every face, stored
    as the GLB's light-tint texture; None: no such texture. ``texture_blur``: this many texels at every vertex, as
    the GLB's ``_TEXTURE_BLUR`` attribute (the blur a view-projected bake puts in its textures); None: none.
    """
    verts, uvs, nrms, faces, labels = [], [], [], [], []
    width, height = 3 * cell, 2 * cell
    for k, d in enumerate(CUBE_FACES):
        n = np.array(d, float)
        a = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u_ax = np.cross(a, n)
        v_ax = np.cross(n, u_ax)
        cx, cy = (k % 3) * cell, (k // 3) * cell
        base = len(verts)
        for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            verts.append(0.5 * (n + su * u_ax + sv * v_ax))
            nrms.append(n)
            # glTF UVs (v down): +v_ax is up in the image
            uvs.append(((cx + 2 + (su + 1) / 2 * (cell - 4)) / width, (cy + 2 + (1 - sv) / 2 * (cell - 4)) / height))
        faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
        labels += [k, k]
    verts, nrms, uvs = (np.array(x, np.float32) for x in (verts, nrms, uvs))
    faces = np.array(faces, np.int64)
    uvm = UVMesh(verts, faces, uvs, nrms, compute_tangents(verts, faces, uvs, nrms), np.arange(len(verts)),
                 np.array(labels, np.uint8),
                 None if texture_blur is None else np.full(len(verts), texture_blur, np.float32))
    yy, xx = np.mgrid[0:height, 0:width]
    face = (yy // cell) * 3 + xx // cell
    check = (((xx // 8) + (yy // 8)) % 2)[..., None] if pattern else np.ones((height, width, 1))
    linear = CUBE_ALBEDO[face] * (0.55 + 0.45 * check)
    base_color = np.round(linear_to_srgb(linear) * 255).astype(np.uint8)
    occ = np.full((height, width), occlusion)
    if occlusion_checker:
        occ = occ * (0.4 + 0.6 * (((xx // 8) + (yy // 8)) % 2))
    orm = np.stack([occ, CUBE_ROUGHNESS[face], CUBE_METALLIC[face]], -1)
    orm = np.round(orm * 255).astype(np.uint8)
    nt = np.zeros((height, width, 3))
    nt[..., 2] = 1.0
    if pattern:
        ripple = 0.35 * np.sin((xx % cell) / cell * 4 * np.pi)
        nt[..., 0] = np.where(face % 2 == 0, ripple, 0.0)
    nt /= np.linalg.norm(nt, axis=-1, keepdims=True)
    normal = np.round((nt + 1) / 2 * 255).astype(np.uint8)
    tint = None
    if light_tint is not None:
        from toolkit.bake import LIGHT_TINT_SCALE

        tint = np.round(np.broadcast_to(np.asarray(light_tint, float) / LIGHT_TINT_SCALE, (height, width, 3)) * 255)
        tint = tint.astype(np.uint8)
    return export_gltf(uvm, PBRTextures(base_color, orm, normal, np.ones((height, width), bool), light_tint=tint),
                       path, sh=sh, extras=extras)


# ------------------------------------------------------------------------------------------- trained sample (slow)
SAMPLE_STEPS = 160
"""Training steps of the sample run (~3 min on one busy CPU thread; a fixed step count keeps it reproducible)."""
SAMPLE_ASSET_ARGS = ("--resolution", "160", "--texture", "1024", "--view-rays", "200000")
"""export-asset options (the iso-level is chosen by :func:`surface_level`; the view-projected bake renders the 80
training views at 50x50, not the default ~79x79, to keep the session short)."""
_CACHE: dict[str, Path] = {}


def surface_level(run: Path, samples: int = 200_000) -> float:
    """An iso-level for a short run: half the 99.9th percentile of the field's density in its box, capped at the
    default half-opacity level ln 2 / voxel. (After ~3 CPU minutes the field is still a translucent fog whose peak
    density, ~1.5 /m, is far below the default ≈ 18 /m at 160 cells, which would extract no surface.)"""
    import math

    import torch

    from toolkit.train import load_field_callables

    density_fn, _, aabb, _, _ = load_field_callables(run)[:5]
    gen = torch.Generator().manual_seed(0)
    pts = aabb[0] + torch.rand(samples, 3, generator=gen) * (aabb[1] - aabb[0])
    q = float(torch.quantile(density_fn(pts), 0.999))
    default = math.log(2.0) / (float((aabb[1] - aabb[0]).max()) / int(SAMPLE_ASSET_ARGS[1]))
    return min(default, 0.5 * q)


def trained_sample(root: Path) -> tuple[Path, Path]:
    """(RUN, export-asset DIR) of a short run on samples/gallery, made once per test session under ``root``."""
    if "run" in _CACHE:
        return _CACHE["run"], _CACHE["asset"]
    import pytest

    if not (SAMPLE / "transforms_train.json").is_file():
        pytest.skip("bundled sample not rendered yet (samples/gallery)")
    run, asset = root / "run", root / "asset"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    dars = [sys.executable, "-m", "toolkit.cli"]
    steps = [dars + ["train", str(SAMPLE), "--out", str(run), "--steps", str(SAMPLE_STEPS), "--threads", "1",
                     "--quiet"],
             lambda: dars + ["export-asset", str(run), "--out", str(asset), *SAMPLE_ASSET_ARGS,
                             "--level", f"{surface_level(run):.4f}"]]
    for cmd in steps:
        cmd = cmd() if callable(cmd) else cmd
        r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=1200)
        if r.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stdout}\n{r.stderr}")
    _CACHE.update(run=run, asset=asset)
    return run, asset
