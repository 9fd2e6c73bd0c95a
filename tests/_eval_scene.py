"""A tests/synthetic.py scene with full ground truth on its test split, for the evaluation tests.

The sphere-on-a-floor scene is analytic, so depth (metres along the camera axis), world normals, linear albedo and
roughness are exact; a GT SH is added to ``transforms_test.json`` and, with ``patch=True``, a ``scene`` block whose
``painting_plane`` is the top of the sphere (as the gallery sample's JSON names its painting).
"""
import json
import math

import numpy as np

GT_SH = [[0.8, 0.75, 0.7]] + [[0.1 * (k % 3) - 0.1, 0.05, -0.02 * k] for k in range(1, 9)]


def _gt_maps(c2w: np.ndarray, size: int, focal: float):
    """Analytic ground truth of tests/synthetic.py's sphere (r 0.5) on a floor (z = -0.5, |x|, |y| < 1.5)."""
    H = W = size
    v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    d_cam = np.stack([(u + 0.5 - W / 2) / focal, -(v + 0.5 - H / 2) / focal, -np.ones_like(u, float)], -1)
    d = d_cam @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = c2w[:3, 3]
    b = (d * o).sum(-1)
    disc = b * b - ((o * o).sum() - 0.25)
    t_s = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    t_s = np.where(t_s > 0, t_s, np.inf)
    t_f = np.where(np.abs(d[..., 2]) > 1e-6, (-0.5 - o[2]) / d[..., 2], np.inf)
    p_f = o + t_f[..., None] * d
    t_f = np.where((t_f > 0) & (np.abs(p_f[..., 0]) < 1.5) & (np.abs(p_f[..., 1]) < 1.5), t_f, np.inf)
    hit_s, hit_f = t_s < t_f, np.isfinite(t_f) & ~(t_s < t_f)
    t = np.where(hit_s, t_s, np.where(hit_f, t_f, 0.0))
    fwd = -c2w[:3, 2]
    depth = np.where(hit_s | hit_f, t * (d @ fwd), 0.0).astype(np.float32)
    p = o + t[..., None] * d
    normal = np.where(hit_s[..., None], p / 0.5, np.where(hit_f[..., None], [0.0, 0.0, 1.0], 0.0)).astype(np.float32)
    albedo = np.where(hit_s[..., None], [0.6, 0.4, 0.3], np.where(hit_f[..., None], [0.4, 0.35, 0.3], 0.0))
    rough = np.where(hit_s, 0.3, np.where(hit_f, 0.8, 0.0))
    return depth, normal, albedo.astype(np.float32), rough.astype(np.float32)


def add_ground_truth(root, patch: bool = False):
    """Give the test split of a synthetic scene depth, normal, albedo and roughness maps and a GT SH."""
    meta = json.loads((root / "transforms_test.json").read_text())
    size = 32
    focal = 0.5 * size / math.tan(0.5 * meta["camera_angle_x"])
    for k, fr in enumerate(meta["frames"]):
        depth, normal, albedo, rough = _gt_maps(np.asarray(fr["transform_matrix"]), size, focal)
        for name, arr in (("depth", depth), ("normal", normal), ("albedo", albedo), ("roughness", rough)):
            np.save(root / f"test/r_{k:03d}_{name}.npy", arr)
        fr.update(depth_file_path=f"test/r_{k:03d}_depth.npy", normal_path=f"test/r_{k:03d}_normal.npy",
                  albedo_path=f"test/r_{k:03d}_albedo.npy", roughness_path=f"test/r_{k:03d}_roughness.npy")
    meta["sh"] = GT_SH
    if patch:
        meta["scene"] = {"painting_plane": {"point": [0.0, 0.0, 0.5], "normal": [0.0, 0.0, 1.0]},
                         "painting_corners": [[-0.5, -0.5, 0.5], [0.5, -0.5, 0.5], [0.5, 0.5, 0.5], [-0.5, 0.5, 0.5]]}
    (root / "transforms_test.json").write_text(json.dumps(meta))
    return root


def small_config(**kw):
    """A ``fast`` config small enough for tests (512-ray batches, a coarse occupancy grid).

    These scenes carry ground-truth labels and no segmenter output, so the tests that score the semantic head ask for
    the labels explicitly (``labels="ground-truth"``; training's default is ``predicted``)."""
    from toolkit.train import make_config

    base = dict(batch_rays=512, ssim_patches=1, log_every=2, checkpoint_every=50, occupancy_resolution=24,
                occupancy_warmup=8, occupancy_every=4, labels="ground-truth")
    base.update(kw)
    return make_config("fast", **base)
