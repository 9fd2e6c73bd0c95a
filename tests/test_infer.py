"""The torch-free ONNX Runtime renderer (export/infer.py): no torch import, numpy mirrors of the torch sampler and
compositing, clear errors for incomplete exports, and ``dars infer``."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from _onnx_bundle import ROOT, SAMPLE, build_bundle  # noqa: E402
from export import infer  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def bundle(tmp_path_factory):
    if not (SAMPLE / "transforms_train.json").is_file():
        pytest.skip("bundled sample not rendered yet (samples/gallery)")
    return build_bundle(tmp_path_factory.getbasetemp() / "onnx_gallery")


def _env():
    return {**os.environ, "OMP_NUM_THREADS": "1"}


# ------------------------------------------------------------------------------------------------ no torch
def test_import_does_not_load_torch():
    code = "import sys, export.infer; print('torch' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=_env(), timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False", "export/infer.py must not import torch"


def test_render_without_torch_in_the_process(bundle):
    """Load, render a (downscaled) sample camera and segment a photo in a process that never imports torch."""
    code = f"""
import sys, json, numpy as np
from export import infer
m = infer.load_model({str(bundle['out'])!r}, threads=1)
c = infer.camera_from_transforms({str(SAMPLE / 'transforms_test.json')!r}, 0)
c = infer.PinholeCamera(c.c2w, c.fx / 4, c.fy / 4, c.cx / 4, c.cy / 4, 32, 32)
o = infer.render_view(m, c)
lab = infer.infer_segment({str(bundle['out'])!r}, [{str(SAMPLE / 'test' / 'r_000.png')!r}], threads=1)[0]
print(json.dumps({{"torch": 'torch' in sys.modules, "keys": sorted(o), "rgb": list(o["rgb"].shape),
                  "finite": bool(np.isfinite(o["rgb"]).all()), "labels": list(lab.shape)}}))
"""
    if not (SAMPLE / "test" / "r_000.png").is_file():
        pytest.skip("sample test image r_000.png not found")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=_env(), timeout=300)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout.strip().splitlines()[-1])
    assert d["torch"] is False
    assert d["rgb"] == [32, 32, 3] and d["finite"] and d["labels"] == [128, 128]
    for k in ("rgb", "depth", "opacity", "normal", "albedo", "roughness", "metallic", "semantic_logits", "diffuse",
              "specular", "samples"):
        assert k in d["keys"], k


# ------------------------------------------------------------------------------------------------ numpy mirrors
def test_rays_and_camera_reader_match_torch():
    from toolkit.scene import generate_rays, load_scene

    sc = load_scene(SAMPLE, "test")
    cam = infer.camera_from_transforms(SAMPLE / "transforms_test.json", 3)
    c = sc.cameras
    assert np.allclose(cam.c2w, c.c2w[3].numpy()) and cam.width == int(c.width[3]) and cam.height == int(c.height[3])
    assert np.allclose([cam.fx, cam.fy, cam.cx, cam.cy], [float(c.fx[3]), float(c.fy[3]), float(c.cx[3]),
                                                          float(c.cy[3])], rtol=1e-6)
    ref = generate_rays(c, [3], aabb=sc.aabb, near=sc.near, far=sc.far)
    got = infer.generate_camera_rays(cam, sc.aabb.numpy(), sc.near, sc.far)
    for k in ("origins", "directions", "near", "far", "z_scale"):
        assert np.allclose(got[k], getattr(ref, k).numpy(), atol=2e-6, rtol=1e-6), k


@pytest.mark.parametrize("near_far", [(None, None), (0.5, 40.0)])
def test_contracted_rays_run_to_the_far_radius(near_far):
    """A contracted space: rays end on the far-radius box (and within the scene's near/far when it has them)."""
    from toolkit.scene import generate_rays, load_scene
    from toolkit.space import SceneSpace

    sc = load_scene(SAMPLE, "test")
    cam = infer.camera_from_transforms(SAMPLE / "transforms_test.json", 2)
    near, far = near_far
    ref = generate_rays(sc.cameras, [2], aabb=SceneSpace(sc.aabb, True, 16.0), near=near, far=far)
    got = infer.generate_camera_rays(cam, infer.SceneSpace(sc.aabb.numpy(), True, 16.0), near, far)
    for k in ("origins", "directions", "near", "far", "z_scale"):
        assert np.allclose(got[k], getattr(ref, k).numpy(), atol=2e-6, rtol=1e-6), k
    if far is None:  # every ray leaves through the far-radius box: radius 16 at its far end
        ends = got["origins"] + got["far"][:, None] * got["directions"]
        assert np.allclose(infer.box_radius(ends, sc.aabb.numpy()), 16.0, rtol=1e-5)


def _rays_inside_and_outside(g, aabb, R):
    """Rays from inside the box, just outside it, far outside (beyond the far radius: some miss), pointing
    anywhere; bounds from the far-radius box as the toolkit sets them."""
    lo, hi = aabb
    o = lo + torch.rand(R, 3, generator=g) * (hi - lo)
    o[R // 3: 2 * R // 3] = (o[R // 3: 2 * R // 3] - aabb.mean(0)) * 3 + aabb.mean(0)
    o[2 * R // 3:] = (o[2 * R // 3:] - aabb.mean(0)) * 120 + aabb.mean(0)
    d = torch.nn.functional.normalize(torch.randn(R, 3, generator=g), dim=-1)
    d[:4] = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, -1.0]])  # axis-aligned
    return o, d


def test_space_from_metadata_old_bundles_are_bounded():
    box = [[-1.0, -2.0, 0.0], [1.0, 2.0, 3.0]]
    old = infer.SceneSpace.from_metadata({"aabb": box})  # exported before unbounded scenes
    assert not old.contraction and np.array_equal(old.ray_box, np.asarray(box, np.float32))
    new = infer.SceneSpace.from_metadata({"aabb": box, "space": {"aabb": box, "contraction": True, "far_radius": 8.0,
                                                                 "edge_candidates": 32}})
    assert new.contraction and new.far_radius == 8.0 and new.edge_candidates == 32
    assert np.allclose(new.ray_box, [[-8.0, -16.0, -10.5], [8.0, 16.0, 13.5]])


def test_contraction_mirror_matches_torch_exactly():
    from toolkit.space import box_radius, contract

    g = torch.Generator().manual_seed(3)
    aabb = torch.tensor([[-3.1, -3.6, -0.1], [3.1, 1.25, 2.8]])
    pts = aabb.mean(0) + torch.randn(5000, 3, generator=g) * torch.exp(torch.randn(5000, 1, generator=g) * 2)
    assert np.array_equal(infer.contract(pts.numpy(), aabb.numpy()), contract(pts, aabb).numpy())
    assert np.array_equal(infer.box_radius(pts.numpy(), aabb.numpy()), box_radius(pts, aabb).numpy())
    assert np.abs(infer.contract(pts.numpy(), aabb.numpy())).max() < 2.0


@pytest.mark.parametrize("n", [64, 48])
def test_contracted_edges_match_torch(n):
    """The numpy mirror of toolkit.space.contracted_edges (perturb=False) on rays inside and outside the box. Not
    bit-exact: torch's float32 pow (SLEEF, within 1 ulp) and its vectorised linspace round a few table depths
    differently; the edges then agree to a few 1e-7 relative (measured: max 5e-6 at the far end of rays that
    start near the box)."""
    from toolkit.space import SceneSpace, contracted_edges

    g = torch.Generator().manual_seed(4)
    aabb = torch.tensor([[-3.1, -3.6, -0.1], [3.1, 1.25, 2.8]])
    sp = SceneSpace(aabb, True, 64.0)
    o, d = _rays_inside_and_outside(g, aabb, 3000)
    near, far = sp.ray_bounds(o, d)
    near[5], far[5] = 2.0, 2.0  # a zero-length ray
    assert bool((far <= near).any()) and bool((far > near).any()), "need rays that miss the far box and some that hit"
    ref = contracted_edges(o, d, near, far, sp, n, perturb=False).numpy()
    got = infer.contracted_edges(o.numpy(), d.numpy(), near.numpy(), far.numpy(), aabb.numpy(), n)
    assert got.shape == ref.shape == (3000, n + 1) and got.dtype == np.float32
    assert np.all(np.abs(got - ref) <= 1e-5 * np.maximum(1.0, np.abs(ref))), np.abs(got - ref).max()
    assert (got == ref).mean() > 0.7, "most edges are bit-identical"
    hit = (far > near).numpy()
    assert np.array_equal(got[:, 0], np.where(hit, near.numpy(), np.maximum(far.numpy(), near.numpy())))
    assert np.allclose(got[hit, -1], far.numpy()[hit], rtol=1e-5) and np.all(np.diff(got, axis=1) >= 0)
    # uniform in contracted arc length (up to the arc-length table's chords): strata span ~equal contracted lengths
    cpts = infer.contract(o.numpy()[:, None] + got[..., None] * d.numpy()[:, None], aabb.numpy())
    seg = np.linalg.norm(np.diff(cpts, axis=1), axis=-1)[hit]
    assert np.quantile(np.abs(seg / seg.sum(1, keepdims=True) * n - 1.0), 0.99) < 0.1
    # bounded: the plain stratification, unchanged (bit-exact where torch's linspace is: n a power of two)
    bnd = infer.stratified_edges(o.numpy(), d.numpy(), near.numpy(), far.numpy(), infer.SceneSpace(aabb.numpy()), n)
    ref = (near[:, None] + (torch.maximum(far, near) - near)[:, None] * torch.linspace(0.0, 1.0, n + 1)).numpy()
    assert np.array_equal(bnd, ref) if n & (n - 1) == 0 else np.allclose(bnd, ref, rtol=1e-6)


def test_sampler_and_compositing_match_torch():
    from toolkit.render import render_weights
    from toolkit.sampling import merge_samples, sample_fine

    g = torch.Generator().manual_seed(0)
    R, n = 40, 16
    near = torch.rand(R, generator=g)
    far = near + 0.1 + 2 * torch.rand(R, generator=g)
    far[3] = near[3] - 0.1  # a ray that misses
    u = torch.linspace(0, 1, n + 1)
    edges = near[:, None] + (torch.maximum(far, near) - near)[:, None] * u
    pdf = torch.rand(R, n, generator=g) * (torch.rand(R, n, generator=g) > 0.5)
    pdf[5] = 0.0  # all-zero row: uniform
    counts = torch.randint(0, 9, (R,), generator=g)
    t_ref, r_ref, k_ref = sample_fine(edges, pdf, counts, perturb=False, return_strata=True)
    t_got, r_got, k_got = infer._sample_fine(edges.numpy(), pdf.numpy(), counts.numpy(), return_strata=True)
    assert np.array_equal(r_got, r_ref.numpy()) and np.allclose(t_got, t_ref.numpy(), atol=1e-6)
    assert np.array_equal(k_got, k_ref.numpy())
    t_c = 0.5 * (edges[:, :-1] + edges[:, 1:])
    keep = torch.rand(R, n, generator=g) > 0.6
    ray_c, k_c = torch.nonzero(keep, as_tuple=True)
    max_delta = (torch.maximum(far, near) - near) / n
    ps, order = merge_samples(t_c[ray_c, k_c], ray_c, t_ref, r_ref, R, max_delta, near, far)
    s0, s1, ri, order_np = infer._merge(t_c[ray_c, k_c].numpy(), ray_c.numpy(), t_got, r_got, max_delta.numpy(),
                                        near.numpy(), far.numpy())
    assert np.array_equal(ri, ps.ray_indices.numpy())
    assert np.allclose(s0, ps.t_starts.numpy(), atol=1e-6) and np.allclose(s1, ps.t_ends.numpy(), atol=1e-6)
    dens = torch.rand(len(ps), generator=g) * 5
    w_ref, _, _ = render_weights(dens, ps.deltas, ps.ray_indices, R)
    w_got = infer.render_weights(dens.numpy(), (s1 - s0), ri, R)
    assert np.allclose(w_got, w_ref.numpy(), atol=1e-6)
    # contracted runs: per-sample longest intervals (each sample's own stratum)
    sd = torch.rand(len(ray_c) + len(r_ref), generator=g) * 0.3
    ps, order = merge_samples(t_c[ray_c, k_c], ray_c, t_ref, r_ref, R, max_delta, near, far, sample_max_delta=sd)
    s0, s1, ri, order_np = infer._merge(t_c[ray_c, k_c].numpy(), ray_c.numpy(), t_got, r_got, max_delta.numpy(),
                                        near.numpy(), far.numpy(), sd.numpy())
    assert np.array_equal(order_np, order.numpy()) and np.array_equal(ri, ps.ray_indices.numpy())
    assert np.allclose(s0, ps.t_starts.numpy(), atol=1e-6) and np.allclose(s1, ps.t_ends.numpy(), atol=1e-6)


def _sums(weights, values, ray_indices, n_rays, rows=None):
    return infer._RaySums(weights, ray_indices, n_rays, rows=rows)(values)


def test_accumulation_is_torchs_bit_for_bit(monkeypatch):
    """Σ w v per ray: the same float32 sums in the same order as toolkit.render.accumulate_along_rays (index_add),
    with the values in query order (``rows``) and with samples out of ray order; without scipy, float64 bincounts
    that agree to float32 rounding."""
    from toolkit.render import accumulate_along_rays

    rng = np.random.default_rng(3)
    R, S = 300, 9000
    ri = np.sort(rng.integers(0, R, S))
    ri[ri == 7] = 8  # a ray with no sample
    w = rng.random(S).astype(np.float32)
    for C in (1, 3, 31):
        v = rng.standard_normal((S, C)).astype(np.float32)
        ref = accumulate_along_rays(torch.from_numpy(w), torch.from_numpy(v), torch.from_numpy(ri), R).numpy()
        got = _sums(w, v, ri, R)
        assert got.dtype == np.float32 and got.shape == (R, C) and np.array_equal(got, ref), C
        assert not got[7].any()
        perm = rng.permutation(S)  # values stored in another order, sample i's at rows[i]
        inv = np.argsort(perm)
        assert np.array_equal(_sums(w, v[perm], ri, R, rows=inv), ref)
        # samples not grouped by ray: each ray still sums in sample order
        shuf = rng.permutation(S)
        ref_u = accumulate_along_rays(torch.from_numpy(w[shuf]), torch.from_numpy(v[shuf]),
                                      torch.from_numpy(ri[shuf]), R).numpy()
        assert np.array_equal(_sums(w[shuf], v[shuf], ri[shuf], R), ref_u)
    ref = accumulate_along_rays(torch.from_numpy(w), None, torch.from_numpy(ri), R).numpy()
    assert np.array_equal(_sums(w, None, ri, R), ref.reshape(R, 1))
    assert _sums(w[:0], v[:0], ri[:0], R).shape == (R, 31)
    # the fallback of a device without scipy
    import builtins

    real_import = builtins.__import__

    def no_scipy(name, *a, **k):
        if name.startswith("scipy"):
            raise ImportError(name)
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_scipy)
    fb = _sums(w, v[perm], ri, R, rows=inv)
    ref = accumulate_along_rays(torch.from_numpy(w), torch.from_numpy(v), torch.from_numpy(ri), R).numpy()
    assert np.allclose(fb, ref, rtol=1e-5, atol=1e-5) and not np.array_equal(fb, ref)


def test_rays_with_no_occupied_sample_render_the_background(bundle):
    """A chunk of rays that meets no occupied cell (a view into empty space, the background rows of an object's
    photo) renders the background at zero opacity; it raised a reshape error before 2026-12-08."""
    m = infer.load_model(bundle["out"], threads=1)
    R = 12
    o = np.zeros((R, 3), np.float32)
    d = np.tile(np.float32([0.0, 0.6, 0.8]), (R, 1))
    near, far = np.full(R, 2.0, np.float32), np.full(R, 1.0, np.float32)  # every ray misses the box
    r = infer.render_rays(m, o, d, near, far, np.ones(R, np.float32))
    assert np.array_equal(r["opacity"], np.zeros(R, np.float32)) and not r["samples"].any()
    assert np.allclose(r["rgb"], m.background_radiance(d), atol=1e-7)
    assert all(v.shape[0] == R and np.isfinite(v).all() for v in r.values())


def test_row_searchsorted_is_numpys_row_by_row():
    rng = np.random.default_rng(5)
    table = np.sort(rng.choice(np.float32([-2.5, -1e-30, -0.0, 0.0, 1e-30, 0.25, 0.5, 1.0, 7.0]), (50, 12)), -1)
    table[3] = 0.0
    rows = rng.integers(0, 50, 4000)
    vals = rng.choice(np.float32([-3.0, -2.5, -1e-30, -0.0, 0.0, 1e-30, 1e-31, 0.3, 0.5, 1.0, 7.0, 9.0]), 4000)
    want = np.array([np.searchsorted(table[r], v, side="right") for r, v in zip(rows, vals)])
    assert np.array_equal(infer._row_searchsorted(table, rows, vals), want)


def test_background_and_occupancy_match_torch(bundle):
    from toolkit.pipeline import Background
    from toolkit.train import load_run

    run = load_run(bundle["run"], with_weights=False)
    m = infer.load_model(bundle["out"], threads=1)
    g = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=-1)
    d[:3] = torch.tensor([[0.0, 0, 1], [0, 0, -1], [0, 1, 0]])  # poles and the seam
    with torch.no_grad():
        assert np.allclose(m.background_radiance(d.numpy()), run.background(d).numpy(), atol=1e-6)
        env = Background("env", (0.3, 0.5, 0.7), resolution=(8, 16))
        env.raw.uniform_(-2, 2, generator=g)
        m2 = infer.FieldModel.__new__(infer.FieldModel)
        m2.background = {"mode": "env", "env_map": env.env_map().numpy()}
        assert np.allclose(infer.FieldModel.background_radiance(m2, d.numpy()), env(d).numpy(), atol=1e-6)
    lo, hi = run.occupancy.aabb
    pts = lo - 0.1 + torch.rand(20000, 3, generator=g) * (hi - lo + 0.2)
    assert np.array_equal(m.occupied(pts.numpy()), run.occupancy.occupied(pts).numpy())
    assert m.occupancy_contraction == run.occupancy.contraction and m.space.contraction == run.field.cfg.contraction
    if run.occupancy.contraction:  # the shell beyond the box, out past the far radius (empty there)
        r = torch.exp(torch.rand(20000, 1, generator=g) * np.log(1.5 * run.occupancy.far_radius))
        d = torch.nn.functional.normalize(torch.randn(20000, 3, generator=g), dim=-1)
        far_pts = ((lo + hi) / 2 + d * r * (hi - lo)).numpy()
        got = m.occupied(far_pts)
        assert np.array_equal(got, run.occupancy.occupied(torch.from_numpy(far_pts)).numpy())
        assert got.any() and not got[infer.box_radius(far_pts, m.aabb) > run.occupancy.far_radius].any()


def test_relighting_through_sh_input(bundle):
    m = infer.load_model(bundle["out"], threads=1)
    pts = np.tile(m.aabb.mean(0), (64, 1)).astype(np.float32) + np.linspace(-0.2, 0.2, 64, dtype=np.float32)[:, None]
    d = np.tile(np.array([[0.0, 0.6, -0.8]], np.float32), (64, 1))
    a = m.query(pts, d)
    b = m.query(pts, d, sh=m.sh * 2.0)
    assert np.allclose(a["albedo"], b["albedo"]) and not np.allclose(a["colour"], b["colour"])
    with pytest.raises(infer.InferError, match=r"sh must be \[9, 3\]"):
        m.query(pts, d, sh=np.zeros(27, np.float32))
    with pytest.raises(infer.InferError, match=r"must both be \[N, 3\]"):
        m.query(pts[:, :2], d)


# ------------------------------------------------------------------------------------------------ errors
def test_missing_files_give_clear_messages(bundle, tmp_path):
    with pytest.raises(infer.InferError, match="export directory not found"):
        infer.load_model(tmp_path / "nope")
    partial = tmp_path / "partial"
    shutil.copytree(bundle["out"], partial)
    (partial / "occupancy.npz").unlink()
    with pytest.raises(infer.InferError, match=r"missing occupancy.npz.*dars export-onnx"):
        infer.load_model(partial)
    (partial / "field_int8.onnx").unlink()
    shutil.copy(bundle["out"] / "occupancy.npz", partial / "occupancy.npz")
    with pytest.raises(infer.InferError, match=r"field_int8.onnx not found.*--precision fp32,int8"):
        infer.load_model(partial, "int8")
    with pytest.raises(infer.InferError, match="precision='bf16'"):
        infer.load_model(partial, "bf16")
    (partial / "background.npz").write_bytes(b"not a zip")
    with pytest.raises(infer.InferError, match=r"background.npz is truncated or corrupt \(ValueError: not an .npz"):
        infer.load_model(partial)
    (partial / "segment.onnx").unlink()
    with pytest.raises(infer.InferError, match="segment.onnx not found.*dars export-onnx"):
        infer.infer_segment(partial, [np.zeros((8, 8, 3), np.uint8)])
    with pytest.raises(infer.InferError, match="light.onnx not found"):
        infer.infer_light(tmp_path, [np.zeros((8, 8, 3), np.uint8)])
    with pytest.raises(infer.InferError, match="photo not found"):
        infer.infer_segment(bundle["out"], [tmp_path / "nope.png"])
    with pytest.raises(infer.InferError, match="frame index 99 out of range"):
        infer.camera_from_transforms(SAMPLE / "transforms_test.json", 99)


# ------------------------------------------------------------------------------------------------ CLI
def test_cli_infer_camera_segment_light_and_errors(bundle, tmp_path):
    exe = [sys.executable, "-m", "toolkit.cli", "infer", str(bundle["out"])]
    r = subprocess.run(exe + ["--camera", f"{SAMPLE}:test:0", "--out", str(tmp_path / "v.png"), "--json",
                              "--threads", "1"], capture_output=True, text=True, cwd=ROOT, env=_env(), timeout=300)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert (tmp_path / "v.png").is_file() and (tmp_path / "v_albedo.png").is_file() and "semantic" in d["files"]
    assert abs(d["psnr"] - bundle["meta"]["parity"]["render"]["psnr_onnx"]) < 0.05
    assert "infer" in r.stderr and "ray" in r.stderr, "a progress bar over the rays on stderr"
    photo = str(SAMPLE / "test" / "r_001.png")
    r = subprocess.run(exe + ["--segment", photo, "--out", str(tmp_path / "seg"), "--json"], capture_output=True,
                       text=True, cwd=ROOT, env=_env(), timeout=300)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "seg" / "r_001_labels.png").is_file() and json.loads(r.stdout)["pixels_per_class"]
    if (bundle["out"] / "light.onnx").is_file():
        r = subprocess.run(exe + ["--light", photo, "--json"], capture_output=True, text=True, cwd=ROOT, env=_env(),
                           timeout=300)
        assert r.returncode == 0, r.stderr
        assert np.asarray(json.loads(r.stdout)["coeffs"]).shape == (1, 9, 3)
    r = subprocess.run([sys.executable, "-m", "toolkit.cli", "infer", str(tmp_path / "none"), "--camera",
                        f"{SAMPLE}:test:0", "--out", str(tmp_path / "x.png")], capture_output=True, text=True,
                       cwd=ROOT, env=_env(), timeout=300)
    assert r.returncode == 2 and "export directory not found" in r.stderr, r.stderr
    r = subprocess.run(exe + ["--camera", f"{SAMPLE}:test", "--out", str(tmp_path / "x.png")], capture_output=True,
                       text=True, cwd=ROOT, env=_env(), timeout=300)
    assert r.returncode == 2 and "SCENE:SPLIT:INDEX" in r.stderr, r.stderr
