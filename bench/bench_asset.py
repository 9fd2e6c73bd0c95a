"""Benchmark of the asset stages: mesh extraction (256³ vs 512³), simplification 1M → 100k faces (fast vs quality),
UV unwrap of 100k faces, PBR baking at 1024² and 2048².

Every case runs in a fresh subprocess (so peak memories don't mix) with one torch/OpenMP thread; it reports wall
time and the peak resident set size above the process's baseline after imports (``resource.getrusage`` max RSS),
plus tracemalloc's peak of Python/numpy allocations for the extraction cases. The fields are analytic stand-ins of
realistic cost: a gallery room as a union of 14 SDF primitives (walls, floor, plinths, frames, sculptures) with a
VolSDF density, and a small MLP material head (3 x 64, ReLU) for baking.

Usage: ``python bench/bench_asset.py`` (all cases, prints a table) or ``--case NAME --json`` (one case, JSON line).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASES = ["extract_256", "extract_512", "simplify_fast", "simplify_quality", "unwrap_100k", "unwrap_noisy_one",
         "unwrap_noisy_pieces", "bake_1024", "bake_2048"]


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def gallery_density():
    """A 10 x 8 x 4 m gallery: floor, walls, plinths, frames on the walls, spheres and a torus on plinths (VolSDF)."""
    import torch

    boxes = torch.tensor([  # centre xyz, half extents xyz
        [0.0, 0.0, -0.05, 5.0, 4.0, 0.05],  # floor
        [0.0, 4.05, 2.0, 5.0, 0.05, 2.0], [0.0, -4.05, 2.0, 5.0, 0.05, 2.0],  # walls
        [5.05, 0.0, 2.0, 0.05, 4.0, 2.0], [-5.05, 0.0, 2.0, 0.05, 4.0, 2.0],
        [-2.0, 0.0, 0.5, 0.4, 0.4, 0.5], [2.0, 1.0, 0.45, 0.35, 0.35, 0.45], [0.5, -2.0, 0.4, 0.3, 0.3, 0.4],  # plinths
        [-2.5, 3.97, 1.8, 0.8, 0.03, 0.6], [1.5, 3.97, 1.6, 0.6, 0.03, 0.8], [4.97, -1.0, 1.7, 0.03, 0.9, 0.6],  # frames
    ])
    spheres = torch.tensor([[-2.0, 0.0, 1.35, 0.35], [2.0, 1.0, 1.2, 0.3]])
    beta = 0.01  # metres: sharper than the 512³ voxel (1.95 cm)

    def fn(p):
        d = []
        for b in boxes:
            q = (p - b[:3]).abs() - b[3:]
            d.append(q.clamp_min(0).norm(dim=-1) + q.amax(-1).clamp_max(0))
        for s in spheres:
            d.append((p - s[:3]).norm(dim=-1) - s[3])
        q = p - torch.tensor([0.5, -2.0, 1.15])  # torus on the third plinth
        d.append(torch.stack([q[:, :2].norm(dim=-1) - 0.28, q[:, 2]], -1).norm(dim=-1) - 0.08)
        sdf = torch.stack(d, -1).amin(-1)
        return torch.where(sdf > 0, 0.5 * torch.exp(-sdf.clamp_min(0) / beta),
                           1 - 0.5 * torch.exp(sdf.clamp_max(0) / beta)) / beta

    return fn, torch.tensor([[-5.2, -4.2, -0.2], [5.2, 4.2, 4.2]])


def bumpy_sphere(n_faces: int):
    """A displaced UV sphere with about ``n_faces`` triangles (deterministic)."""
    import numpy as np

    from toolkit.mesh import Mesh, compute_vertex_normals

    rows = int(round((n_faces / 4) ** 0.5))
    cols = 2 * rows
    th = (np.arange(1, rows) / rows) * np.pi
    ph = np.arange(cols) / cols * 2 * np.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    r = 1.0 + 0.05 * np.sin(7 * T) * np.cos(5 * P) + 0.02 * np.sin(23 * T + 3 * P)
    v = np.stack([r * np.sin(T) * np.cos(P), r * np.sin(T) * np.sin(P), r * np.cos(T)], -1).reshape(-1, 3)
    v = np.concatenate([v, [[0, 0, 1.0], [0, 0, -1.0]]])
    idx = np.arange((rows - 1) * cols).reshape(rows - 1, cols)
    a, b = idx[:-1], np.roll(idx[:-1], -1, 1)
    c, d = idx[1:], np.roll(idx[1:], -1, 1)
    f = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    top, bot = len(v) - 2, len(v) - 1
    f = np.concatenate([f, np.stack([np.full(cols, top), idx[0], np.roll(idx[0], -1)], 1),
                        np.stack([np.full(cols, bot), np.roll(idx[-1], -1), idx[-1]], 1)])
    return Mesh(v.astype(np.float32), f.astype(np.int64), normals=compute_vertex_normals(v, f))


def mlp_material():
    import torch

    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 64), torch.nn.ReLU(), torch.nn.Linear(64, 64), torch.nn.ReLU(),
                              torch.nn.Linear(64, 64), torch.nn.ReLU(), torch.nn.Linear(64, 8))

    def fn(p, n):
        with torch.no_grad():
            o = net(p)
        nrm = torch.nn.functional.normalize(n + 0.2 * torch.tanh(o[:, 5:8]), dim=-1)
        return {"albedo": torch.sigmoid(o[:, :3]), "roughness": torch.sigmoid(o[:, 3]), "metallic": torch.sigmoid(o[:, 4]),
                "normal": nrm}

    return fn


def run_case(name: str, workdir: Path) -> dict:
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from toolkit.bake import BakeConfig, UnwrapConfig, bake_pbr_textures, unwrap_uv
    from toolkit.mesh import MeshConfig, SimplifyConfig, extract_mesh, simplify_mesh

    out: dict = {"case": name}
    if name.startswith("extract"):
        import tracemalloc

        res = int(name.split("_")[1])
        fn, aabb = gallery_density()
        base = _rss_mb()
        tracemalloc.start()
        t0 = time.perf_counter()
        mesh = extract_mesh(fn, aabb, MeshConfig(resolution=res, progress=False))
        out["seconds"] = time.perf_counter() - t0
        out["tracemalloc_peak_mb"] = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
        out["peak_rss_mb"] = _rss_mb() - base
        dims = [int(np.ceil(float(e) / (float((aabb[1] - aabb[0]).max()) / res))) + 1 for e in (aabb[1] - aabb[0])]
        out["grid_mb_if_dense"] = np.prod(dims) * 4 / 1e6
        out["faces"] = mesh.num_faces
        out["note"] = f"grid {dims[0]}x{dims[1]}x{dims[2]}, {np.prod(dims) / 1e6:.0f}M density queries"
    elif name.startswith("simplify"):
        method = name.split("_")[1]
        mesh = bumpy_sphere(1_000_000)
        base = _rss_mb()
        t0 = time.perf_counter()
        small, rep = simplify_mesh(mesh, 100_000, method=method, cfg=SimplifyConfig(error_samples=200_000))
        out["seconds"] = rep.seconds
        out["seconds_with_error_report"] = time.perf_counter() - t0
        out["peak_rss_mb"] = _rss_mb() - base
        out["faces"] = f"{rep.faces_in} -> {rep.faces_out}"
        out["chamfer_frac"] = rep.error.mean_fraction
        out["hausdorff_frac"] = rep.error.max_fraction
        out["note"] = f"chamfer {rep.error.mean_fraction:.2e}, hausdorff {rep.error.max_fraction:.2e} of diagonal"
    elif name.startswith("unwrap"):
        if name == "unwrap_100k":
            mesh, cfg = bumpy_sphere(100_000), UnwrapConfig(texture_size=2048)
        else:
            # a surface as noisy as a trained room's: xatlas makes a chart of every few faces and merges them in a
            # time superlinear in their count per piece; "one" is the baseline (one piece), "pieces" the default cut
            from toolkit.mesh import Mesh, compute_vertex_normals

            m = bumpy_sphere(20_000)
            v = m.vertices + 0.01 * np.random.default_rng(0).standard_normal(m.vertices.shape)
            mesh = Mesh(v.astype(np.float32), m.faces, compute_vertex_normals(v, m.faces))
            cfg = UnwrapConfig(texture_size=1024, max_piece_faces=None if name.endswith("one") else 5000)
        base = _rss_mb()
        t0 = time.perf_counter()
        uvm = unwrap_uv(mesh, cfg)
        out["seconds"] = time.perf_counter() - t0
        out["peak_rss_mb"] = _rss_mb() - base
        out["faces"] = uvm.num_faces
        if name == "unwrap_100k":
            np.savez(workdir / "uvmesh.npz", **{k: getattr(uvm, k) for k in ("vertices", "faces", "uvs", "normals",
                                                                              "tangents", "vmapping")})
            out["note"] = f"xatlas, {uvm.num_vertices} split vertices"
        else:
            out["note"] = f"20k noisy faces, {'one piece' if cfg.max_piece_faces is None else 'pieces of 5000'}"
    elif name.startswith("bake"):
        from toolkit.bake import UVMesh

        size = int(name.split("_")[1])
        path = workdir / "uvmesh.npz"
        if path.exists():
            d = np.load(path)
            uvm = UVMesh(**{k: d[k] for k in d.files})
        else:
            uvm = unwrap_uv(bumpy_sphere(100_000), UnwrapConfig(texture_size=2048))
        fn = mlp_material()
        base = _rss_mb()
        t0 = time.perf_counter()
        tex = bake_pbr_textures(uvm, fn, BakeConfig(size=size, progress=False))
        out["seconds"] = time.perf_counter() - t0
        out["peak_rss_mb"] = _rss_mb() - base
        out["faces"] = uvm.num_faces
        out["note"] = f"{int(tex.mask.sum()) / 1e6:.2f}M texels queried (coverage {tex.mask.mean():.0%})"
    else:
        raise SystemExit(f"unknown case {name!r}: choose from {CASES}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=CASES)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--only", nargs="*", default=None, help="subset of cases to run")
    args = ap.parse_args()
    if args.case:
        sys.path.insert(0, str(ROOT))
        res = run_case(args.case, Path(args.workdir or tempfile.mkdtemp()))
        print(json.dumps(res))
        return 0
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for case in args.only or CASES:
            r = subprocess.run([sys.executable, __file__, "--case", case, "--json", "--workdir", work],
                               capture_output=True, text=True, env=env)
            if r.returncode != 0:
                print(f"{case}: FAILED\n{r.stderr[-2000:]}", file=sys.stderr)
                return 1
            rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
            print(f"  done {case}: {rows[-1]['seconds']:.1f} s", file=sys.stderr)
    by = {r["case"]: r for r in rows}
    print(f"{'case':<18} {'seconds':>9} {'peak RSS MB':>12}  {'faces':<22} notes")
    for r in rows:
        extra = f" (tracemalloc {r['tracemalloc_peak_mb']:.0f} MB; dense grid would be {r['grid_mb_if_dense']:.0f} MB)" \
            if "tracemalloc_peak_mb" in r else ""
        print(f"{r['case']:<18} {r['seconds']:>9.2f} {r['peak_rss_mb']:>12.0f}  {str(r['faces']):<22} {r['note']}{extra}")
    print()

    def ratio(a, b, key="seconds"):
        if a in by and b in by and by[b][key]:
            return f"{by[a][key] / by[b][key]:.2f}"
        return "n/a"

    print(f"extract 512³ / 256³: time x{ratio('extract_512', 'extract_256')}, "
          f"peak RSS x{ratio('extract_512', 'extract_256', 'peak_rss_mb')} (dense grids would be x8)")
    print(f"simplify quality / fast: time x{ratio('simplify_quality', 'simplify_fast')}, "
          f"chamfer x{ratio('simplify_quality', 'simplify_fast', 'chamfer_frac')}, "
          f"hausdorff x{ratio('simplify_quality', 'simplify_fast', 'hausdorff_frac')}")
    print(f"bake 2048² / 1024²: time x{ratio('bake_2048', 'bake_1024')}, "
          f"peak RSS x{ratio('bake_2048', 'bake_1024', 'peak_rss_mb')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
