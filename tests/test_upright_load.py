"""Upright on load (:func:`toolkit.scene.load_scene` ``upright=``): COLMAP models and transforms JSON files without a
box are rotated so that world up is +z; upright, boxed and ``dars poses`` scenes are left as they are."""

import json
import math

import numpy as np
import pytest
import torch

from toolkit.io import write_png
from toolkit.pinhole import look_at
from toolkit.scene import load_scene, scene_info
from toolkit.sh import eval_sh, rotate_sh, rotation_x, sh_rotation_matrix
from toolkit.upright import LOAD_TILT_TOLERANCE_DEG, estimate_world_up, plan_upright_rotation

TILT = rotation_x(30.0).numpy()  # the file's world is the upright one turned 30 deg about x
SH_UP = torch.tensor([[0.8, 0.7, 0.6], [0.1, 0.0, -0.1], [0.5, 0.4, 0.3], [0.0, 0.1, 0.2], [0.05, 0.0, 0.0],
                      [0.0, -0.05, 0.0], [0.1, 0.1, 0.1], [0.0, 0.0, 0.05], [-0.05, 0.0, 0.0]], dtype=torch.float64)
FLOOR, WALL = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])  # world-space normals in the upright frame


def _ring(n=16, radius=3.0):
    """Upright OpenGL c2w [n, 4, 4]: two rings at different heights looking at the origin (pitch varies)."""
    return np.stack([look_at([radius * math.cos(a), radius * math.sin(a), 1.5 if k % 2 else 0.6], [0.0, 0.0, 0.0])
                     for k, a in enumerate(np.linspace(0.0, 2 * math.pi, n, endpoint=False))])


def _rot4(rot):
    t = np.eye(4)
    t[:3, :3] = rot
    return t


def _frames(root, c2w, names, rot):
    """Frames with an 8x6 photo and a world-space normal map (PNG for even frames, .npy for odd) in frame ``rot``:
    left half floor, right half wall, top row no surface."""
    normal = np.zeros((6, 8, 3), np.float32)
    normal[1:, :4], normal[1:, 4:] = rot @ FLOOR, rot @ WALL
    frames = []
    for k, (m, name) in enumerate(zip(c2w, names)):
        write_png(root / f"{name}.png", np.full((6, 8, 3), 0.5, np.float32))
        if k % 2:
            np.save(root / f"{name}_n.npy", normal)
        else:
            write_png(root / f"{name}_n.png", np.where(normal.any(-1, keepdims=True), (normal + 1) / 2, 0.0), bits=16)
        frames.append({"file_path": f"{name}.png", "transform_matrix": m.tolist(),
                       "normal_path": f"{name}_n.{'npy' if k % 2 else 'png'}"})
    return frames


def _write_transforms(root, rot=np.eye(3), layout="splits", header=None):
    """A scene whose world is the upright ring turned by ``rot``; ground-truth light ``sh``/``sh_env`` in that frame."""
    root.mkdir(parents=True, exist_ok=True)
    c2w = _rot4(rot)[None] @ _ring()
    sh = rotate_sh(SH_UP, rot).tolist()
    meta = {"camera_angle_x": 0.8, "sh": sh, "sh_env": sh, **(header or {})}
    if layout == "single":
        frames = _frames(root, c2w, [f"r_{k:02d}" for k in range(len(c2w))], rot)
        (root / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))
    else:
        for split, idx in (("train", range(0, 12)), ("test", range(12, 16))):
            frames = _frames(root, c2w[list(idx)], [f"{split}_{k:02d}" for k in idx], rot)
            (root / f"transforms_{split}.json").write_text(json.dumps({**meta, "frames": frames}))
    return root


def _file_c2w(root, split):
    if (root / "transforms.json").is_file():
        frames = json.loads((root / "transforms.json").read_text())["frames"]
        idx = [i for i in range(len(frames)) if (i % 8 == 0) == (split == "test")]
        return torch.tensor([frames[i]["transform_matrix"] for i in idx], dtype=torch.float32)
    frames = json.loads((root / f"transforms_{split}.json").read_text())["frames"]
    return torch.tensor([f["transform_matrix"] for f in frames], dtype=torch.float32)


@pytest.mark.parametrize("layout", ["splits", "single"])
def test_tilted_transforms_load_upright(tmp_path, layout):
    tilted = _write_transforms(tmp_path / "tilted", TILT, layout)
    upright = _write_transforms(tmp_path / "upright", np.eye(3), layout)
    train, test = load_scene(tilted, "train"), load_scene(tilted, "test")
    rec = train.meta["upright"]
    assert rec["applied"] and rec["source"] == "cameras" and rec["tilt_deg"] == pytest.approx(30.0, abs=1.0)
    assert test.meta["upright"]["rotation"] == rec["rotation"]  # one rotation for every split
    every = torch.cat([train.cameras.c2w, test.cameras.c2w]).double().numpy()
    up = estimate_world_up(every).up
    assert math.degrees(math.acos(min(1.0, up[2]))) < 1.0
    # the rotation undoes the tilt: the same cameras, box and light as the upright copy of the scene
    for split, sc in (("train", train), ("test", test)):
        ref = load_scene(upright, split)
        torch.testing.assert_close(sc.cameras.c2w, ref.cameras.c2w, atol=1e-4, rtol=0)
        torch.testing.assert_close(sc.aabb, ref.aabb, atol=1e-4, rtol=0)
        torch.testing.assert_close(sc.sh, ref.sh, atol=1e-5, rtol=0)
        for k in ("sh", "sh_env"):
            np.testing.assert_allclose(sc.meta[k], SH_UP.numpy(), atol=1e-6)
    # world-space normal maps are rotated on load (PNG and .npy): floor +z, wall +x, no surface stays 0
    floor, wall = (torch.tensor(v, dtype=torch.float32)[:, None, None].expand(3, 5, 4) for v in (FLOOR, WALL))
    for i in (0, 1):
        n = train.load_extra(i, "normal")
        torch.testing.assert_close(n[:, 1:, :4], floor, atol=1e-3, rtol=0)
        torch.testing.assert_close(n[:, 1:, 4:], wall, atol=1e-3, rtol=0)
        assert float(n[:, 0].abs().max()) == 0.0
    info = scene_info(tilted)
    assert info["upright"]["applied"] and info["upright"]["rotation"] == rec["rotation"]


def test_upright_scene_is_left_exactly_as_it_is(tmp_path):
    root = _write_transforms(tmp_path, np.eye(3))
    for split in ("train", "test"):
        sc = load_scene(root, split)
        rec = sc.meta["upright"]
        assert not rec["applied"] and rec["tilt_deg"] < LOAD_TILT_TOLERANCE_DEG
        assert rec["rotation"] == np.eye(3).tolist()
        assert torch.equal(sc.cameras.c2w, _file_c2w(root, split))
        written = json.loads((root / f"transforms_{split}.json").read_text())
        assert torch.equal(sc.sh, torch.tensor(written["sh"], dtype=torch.float32)) and sc.meta["sh"] == written["sh"]
        n = sc.load_extra(1, "normal")  # .npy: read as stored
        assert torch.equal(n, torch.from_numpy(np.load(root / f"{sc.frames[1].name[:-4]}_n.npy").transpose(2, 0, 1)))


def test_small_tilt_within_tolerance_is_kept(tmp_path):
    root = _write_transforms(tmp_path, rotation_x(0.5 * LOAD_TILT_TOLERANCE_DEG).numpy())
    sc = load_scene(root, "train")
    assert not sc.meta["upright"]["applied"]
    assert sc.meta["upright"]["tilt_deg"] == pytest.approx(0.5 * LOAD_TILT_TOLERANCE_DEG, abs=0.1)
    assert torch.equal(sc.cameras.c2w, _file_c2w(root, "train"))


@pytest.mark.parametrize("how", ["off", "aabb", "dars_transform"])
def test_tilted_scene_kept_when_asked_or_boxed_or_from_dars_poses(tmp_path, how):
    header = {"aabb": {"aabb": [[-1, -1, -1], [1, 1, 1]]}, "dars_transform": {"dars_transform": {"scale": 1.0}}}
    root = _write_transforms(tmp_path, TILT, header=header.get(how))
    sc = load_scene(root, "train", upright="off" if how == "off" else "auto")
    rec = sc.meta["upright"]
    assert not rec["applied"] and rec["tilt_deg"] is None and rec["source"] is None
    assert {"off": "upright='off'", "aabb": "aabb", "dars_transform": "dars poses"}[how] in rec["kept"]
    assert torch.equal(sc.cameras.c2w, _file_c2w(root, "train"))
    assert torch.equal(sc.sh, torch.tensor(json.loads((root / "transforms_train.json").read_text())["sh"]))
    n = sc.load_extra(1, "normal")
    torch.testing.assert_close(n[:, 1, 0], torch.tensor(TILT @ FLOOR, dtype=torch.float32))


def test_bad_upright_value(tmp_path):
    from toolkit._checks import SceneError

    with pytest.raises(SceneError, match="upright must be 'auto' or 'off', got 'yes'"):
        load_scene(_write_transforms(tmp_path), "train", upright="yes")


# ------------------------------------------------------------------ COLMAP
def _quaternion(r):
    """(w, x, y, z) of a rotation matrix (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        return [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
    q = [0.0] * 4
    q[0], q[1 + i] = (r[k, j] - r[j, k]) / s, 0.25 * s
    q[1 + j], q[1 + k] = (r[j, i] + r[i, j]) / s, (r[k, i] + r[i, k]) / s
    return q


def _write_colmap_y_down(root, frame):
    """A COLMAP text model of the upright ring and a floor (z = -0.5) with clutter above it, in world frame ``frame``
    (``frame @ z = -y``: the y-down frame SfM often picks). Returns the upright c2w and points."""
    (root / "images").mkdir(parents=True)
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("1 PINHOLE 8 6 10 10 4 3\n")
    c2w_up = _ring()
    lines = []
    for k, m in enumerate(_rot4(frame)[None] @ c2w_up):
        w2c = np.linalg.inv(m @ np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenGL c2w -> COLMAP (OpenCV) world-to-camera
        q, t = [float(v) for v in _quaternion(w2c[:3, :3])], w2c[:3, 3]
        lines.append(f"{k + 1} {' '.join(map(repr, q))} {' '.join(map(repr, t.tolist()))} 1 im_{k:02d}.png\n\n")
        write_png(root / "images" / f"im_{k:02d}.png", np.full((6, 8, 3), 0.5, np.float32))
    (sparse / "images.txt").write_text("# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n" + "".join(lines))
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-2, 2, (300, 2)), np.full(300, -0.5)]
    clutter = rng.uniform([-1, -1, -0.5], [1, 1, 1.5], (100, 3))
    pts_up = np.r_[floor, clutter]
    pts = pts_up @ frame.T
    (sparse / "points3D.txt").write_text("".join(f"{i + 1} {float(x)!r} {float(y)!r} {float(z)!r} 128 128 128 0.5\n"
                                                 for i, (x, y, z) in enumerate(pts)))
    return c2w_up, pts_up


def test_colmap_y_down_model_loads_z_up(tmp_path):
    frame = rotation_x(90.0).numpy()  # upright +z becomes -y
    c2w_up, pts_up = _write_colmap_y_down(tmp_path, frame)
    sc = load_scene(tmp_path, "all")
    rec = sc.meta["upright"]
    assert rec["applied"] and rec["source"] == "cameras+plane" and rec["tilt_deg"] == pytest.approx(90.0, abs=1.0)
    up = estimate_world_up(sc.cameras.c2w.double().numpy()).up
    assert math.degrees(math.acos(min(1.0, up[2]))) < 1.0
    # (the floor fit takes in the clutter within its RANSAC threshold: up is off by ~0.002 deg)
    torch.testing.assert_close(sc.cameras.c2w, torch.tensor(c2w_up, dtype=torch.float32), atol=1e-3, rtol=0)
    # the points-derived box is recomputed in the upright frame: the floor bounds it from below
    loaded = pts_up @ frame.T @ np.asarray(rec["rotation"]).T
    lo, hi = np.percentile(loaded, 1, axis=0), np.percentile(loaded, 99, axis=0)
    np.testing.assert_allclose(sc.meta["aabb"], [lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo)], atol=1e-9)
    lo, hi = np.percentile(pts_up, 1, axis=0), np.percentile(pts_up, 99, axis=0)
    np.testing.assert_allclose(sc.meta["aabb"], [lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo)], atol=1e-3)
    train, test = load_scene(tmp_path, "train"), load_scene(tmp_path, "test")
    assert train.meta["upright"]["rotation"] == test.meta["upright"]["rotation"] == rec["rotation"]
    off = load_scene(tmp_path, "all", upright="off")
    torch.testing.assert_close(off.cameras.c2w, torch.tensor(_rot4(frame)[None] @ c2w_up, dtype=torch.float32),
                               atol=1e-5, rtol=0)


# ------------------------------------------------------------------ pieces
def test_rotated_sh_evaluated_at_rotated_directions_gives_the_original():
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    rot = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0]
    rot = rot * torch.sign(torch.linalg.det(rot))  # a proper rotation
    rotated = rotate_sh(SH_UP, rot)
    torch.testing.assert_close(eval_sh(rotated, dirs @ rot.T), eval_sh(SH_UP, dirs), atol=1e-10, rtol=0)
    torch.testing.assert_close(rotated, torch.einsum("ij,jc->ic", sh_rotation_matrix(rot), SH_UP), atol=1e-12, rtol=0)


def test_plan_upright_rotation_record():
    rec = plan_upright_rotation(_rot4(TILT)[None] @ _ring())
    assert rec["applied"] and rec["tilt_deg"] == pytest.approx(30.0, abs=1e-6)
    np.testing.assert_allclose(rec["rotation"], TILT.T, atol=1e-9)  # the smallest rotation back: -30 deg about x
    json.dumps(rec)  # recorded in scene.meta and reported by `dars info --json`
    kept = plan_upright_rotation(_ring())
    assert not kept["applied"] and kept["rotation"] == np.eye(3).tolist() and kept["tilt_deg"] < 1e-6
