"""Stage 0 (poses): upright math on synthetic rigs, the transforms writer, bad input, and small real pycolmap runs."""

import hashlib
import io
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from toolkit.poses import MANIFEST_NAME, PosesConfig, PosesError, estimate_poses, list_photos, transforms_from_cameras
from toolkit.upright import (UprightConfig, align_similarity, compare_poses, estimate_world_up, rotation_between,
                             upright_rotation)
from toolkit._checks import ConfigError

from conftest import shared


# ------------------------------------------------------------------------------------------------ helpers
def _rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def _look_at(eye, target):
    f = (target - eye) / np.linalg.norm(target - eye)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, np.cross(r, f), -f, eye
    return m


def _rig(rng, n=24, arc_deg=360.0, tilt_deg=4.0):
    """Upright rig: cameras on a ring (or an arc) at ~1.5 m looking inward and down, slight random tilts."""
    out = []
    for i in range(n):
        phi = np.radians(arc_deg * i / n)
        eye = np.array([3 * np.cos(phi), 3 * np.sin(phi), 1.5 + 0.2 * rng.standard_normal()])
        m = _look_at(eye, np.array([0.0, 0.0, 0.3]))
        m[:3, :3] = m[:3, :3] @ _rot(rng.standard_normal(3), tilt_deg * rng.random())
        out.append(m)
    return np.stack(out)


def _points(rng):
    """A noisy ground plane (z = 0), an object above it and a wall (x-z plane at y = 3.5, perpendicular to up)."""
    ground = np.c_[rng.uniform(-3, 3, (600, 2)), 0.005 * rng.standard_normal(600)]
    obj = rng.uniform(-0.5, 0.5, (300, 3)) + [0, 0, 0.6]
    wall = np.c_[rng.uniform(-3, 3, 700), 3.5 + 0.005 * rng.standard_normal(700), rng.uniform(0, 3, 700)]
    return np.concatenate([ground, obj, wall])


def _up_error_deg(R, Q):
    """Angle between +z and where the recovered rotation sends the true up (R @ Q @ z)."""
    return float(np.degrees(np.arccos(np.clip((R @ Q)[2, 2], -1, 1))))


def _jpeg(path: Path, seed: int = 0, size=(96, 64)):
    from PIL import Image

    arr = (np.random.default_rng(seed).random((size[1], size[0], 3)) * 255).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path, "JPEG")


def _snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(folder.rglob("*"))}


# -------------------------------------------------------------------------------------------- upright math
@pytest.mark.parametrize("arc", [360.0, 100.0])
def test_upright_recovers_random_rotations(arc):
    rng = np.random.default_rng(0)
    c2w, pts = _rig(rng, arc_deg=arc), _points(rng)
    for _ in range(12):
        Q = _rot(rng.standard_normal(3), rng.uniform(0, 180))
        T = np.eye(4)
        T[:3, :3] = Q
        with_points = estimate_world_up(T @ c2w, pts @ Q.T)
        assert with_points.source == "cameras+plane"  # the ground, not the (larger) wall
        assert _up_error_deg(upright_rotation(T @ c2w, pts @ Q.T), Q) < 2.0
        assert _up_error_deg(upright_rotation(T @ c2w), Q) < 2.0  # cameras only


def test_upright_ignores_sideways_minority_and_pitch_bias():
    rng = np.random.default_rng(1)
    c2w = _rig(rng, n=30, arc_deg=60.0, tilt_deg=2.0)  # one side of the room, all looking down ~20 deg
    c2w[:5, :3, :3] = c2w[:5, :3, :3] @ _rot([0, 0, 1], 90)  # five portrait photos stored sideways
    up = estimate_world_up(c2w)
    assert up.camera_inliers == 25
    assert np.degrees(np.arccos(up.up[2])) < 2.0
    mean_up = c2w[5:, :3, 1].mean(0)
    assert np.degrees(np.arccos(mean_up[2] / np.linalg.norm(mean_up))) > 5.0  # what a plain mean would get


def test_upright_no_horizontal_plane_falls_back_to_cameras():
    rng = np.random.default_rng(2)
    c2w = _rig(rng)
    wall_only = _points(rng)[900:]
    up = estimate_world_up(c2w, wall_only)
    assert up.source == "cameras" and up.plane_normal is None
    assert np.degrees(np.arccos(up.up[2])) < 2.0
    assert estimate_world_up(c2w, wall_only, UprightConfig(use_plane=False)).source == "cameras"


def test_upright_level_cameras_overrule_a_tilted_plane():
    """Level cameras fix up to a fraction of a degree: a slab of points 4 deg off (on the validation galleries, a
    band of wall and frame points at similar heights) is reported, not used; with rolled hand-held cameras the same
    plane is within their spread and wins."""
    rng = np.random.default_rng(3)
    c2w = _rig(rng, tilt_deg=0.0)  # level: no roll, pitch only
    tilt = _rot([1.0, 0.0, 0.0], 4.0)
    slab = np.c_[rng.uniform(-3, 3, (800, 2)), 0.005 * rng.standard_normal(800)] @ tilt.T + [0, 0, 1.2]
    pts = np.concatenate([_points(rng)[600:], slab])  # the wall and the object, and the tilted slab (no floor)
    up = estimate_world_up(c2w, pts)
    assert up.source == "cameras" and up.camera_roll_deg < 0.01 and up.plane_tolerance_deg == 1.5
    assert abs(up.plane_angle_deg - 4.0) < 0.5 and np.degrees(np.arccos(up.up[2])) < 0.01
    rolled = c2w.copy()
    for m in rolled:
        m[:3, :3] = m[:3, :3] @ _rot([0.0, 0.0, 1.0], rng.normal(0.0, 4.0))  # roll about the viewing axis
    up = estimate_world_up(rolled, pts)
    assert up.camera_roll_deg > 2.0 and up.plane_tolerance_deg > 4.5
    assert up.source == "cameras+plane" and np.degrees(np.arccos(up.up @ tilt[:, 2])) < 0.5
    assert np.isnan(estimate_world_up(c2w[:1].repeat(6, 0), pts).camera_roll_deg)  # one heading: cannot tell


def test_rotation_between_and_similarity():
    for a, b in [([1, 2, 3], [0, 0, 1]), ([0, 0, -1], [0, 0, 1]), ([0, 0, 1], [0, 0, 1])]:
        R = rotation_between(a, b)
        assert np.allclose(R @ (np.asarray(a) / np.linalg.norm(a)), b, atol=1e-9)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
    rng = np.random.default_rng(3)
    src = rng.standard_normal((20, 3))
    Q, s, t = _rot([1, 2, 3], 40), 2.5, np.array([1.0, -2.0, 0.5])
    s_est, R_est, t_est = align_similarity(src, s * src @ Q.T + t)
    assert np.isclose(s_est, s) and np.allclose(R_est, Q) and np.allclose(t_est, t)
    c2w = _rig(rng)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = s * Q, t
    ref = T @ c2w
    ref[:, :3, :3] /= s
    errs = compare_poses(c2w, ref)
    assert errs["rotation_error_deg"]["max"] < 1e-5 and errs["centre_error_rel"]["max"] < 1e-9
    assert np.isclose(errs["scale"], s)
    ref[:, :3, :3] = ref[:, :3, :3] @ _rot([0, 1, 0], 1.5)  # every camera turned by the same 1.5 deg
    errs = compare_poses(c2w, ref)
    assert np.allclose(errs["rotation_error_deg"]["per_camera"], 1.5, atol=1e-6)
    assert np.isclose(errs["rotation_offset_deg"], 1.5) and errs["relative_rotation_error_deg"]["max"] < 1e-5


# --------------------------------------------------------------------------------------- transforms writer
def test_transforms_from_cameras_shared_and_per_frame(tmp_path):
    from toolkit.scene import load_scene

    rng = np.random.default_rng(4)
    c2w = _rig(rng, n=4)
    for i in range(4):
        _jpeg(tmp_path / "images" / f"v{i}.jpg", i, size=(64, 48) if i < 3 else (48, 64))
    names = [f"v{i}.jpg" for i in range(4)]
    shared_intr = np.tile([50.0, 51.0, 32.0, 24.0, 64, 48], (3, 1))
    doc = transforms_from_cameras(names[:3], c2w[:3], shared_intr, extra={"ply_file_path": "sparse_pc.ply"})
    assert doc["fl_x"] == 50.0 and doc["w"] == 64 and "fl_x" not in doc["frames"][0]
    assert doc["frames"][1]["file_path"] == "images/v1.jpg" and doc["ply_file_path"] == "sparse_pc.ply"
    intr = np.vstack([shared_intr, [40.0, 40.0, 24.0, 32.0, 48, 64]])
    doc = transforms_from_cameras(names, c2w, intr)
    assert "fl_x" not in doc and doc["frames"][3]["w"] == 48 and doc["frames"][3]["fl_x"] == 40.0
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    scene = load_scene(tmp_path, "all")
    assert len(scene) == 4
    assert np.allclose(scene.cameras.c2w.numpy(), c2w, atol=1e-5)
    assert float(scene.cameras.fx[3]) == 40.0 and int(scene.cameras.width[3]) == 48


# ----------------------------------------------------------------------------------------------- bad input
def test_config_checks():
    with pytest.raises(ConfigError, match="camera_model"):
        PosesConfig(camera_model="KANNALA").check()
    with pytest.raises(ConfigError, match="max_size"):
        PosesConfig(max_size=50).check()
    with pytest.raises(ConfigError, match="vocab_tree"):
        PosesConfig(vocab_tree="/nonexistent/vocab.bin").check()


def test_empty_folder_and_one_photo(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "notes.txt").write_text("x")
    (photos / "IMG_1.HEIC").write_bytes(b"x")
    with pytest.raises(PosesError, match=r"no photos in .*found 1 \.heic, 1 \.txt.*convert HEIC to JPEG"):
        estimate_poses(photos, tmp_path / "out")
    _jpeg(photos / "a.jpg")
    with pytest.raises(PosesError, match=r"only one photo .*a\.jpg"):
        estimate_poses(photos, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_corrupt_photos_are_named(tmp_path):
    photos = tmp_path / "photos"
    for i in range(3):
        _jpeg(photos / f"ok{i}.jpg", i)
    good = (photos / "ok0.jpg").read_bytes()
    (photos / "broken.jpg").write_bytes(good[: len(good) // 2])
    (photos / "sub" / "fake.png").parent.mkdir()
    (photos / "sub" / "fake.png").write_bytes(b"not a png")
    before = _snapshot(photos)
    with pytest.raises(PosesError) as e:
        estimate_poses(photos, tmp_path / "out")
    msg = str(e.value)
    assert "2 of 5 photos" in msg and "broken.jpg: corrupt or truncated" in msg and "sub/fake.png: not an image" in msg
    assert "ok0.jpg" not in msg and _snapshot(photos) == before
    assert list_photos(photos)[0] == ["broken.jpg", "ok0.jpg", "ok1.jpg", "ok2.jpg", "sub/fake.png"]


def test_foreign_out_refused_and_untouched(tmp_path):
    photos = tmp_path / "photos"
    for i in range(3):
        _jpeg(photos / f"p{i}.jpg", i)
    out = tmp_path / "mine"
    (out / "images").mkdir(parents=True)
    (out / "notes.txt").write_text("my notes")
    _jpeg(out / "images" / "keep.jpg", 9)
    before = _snapshot(out)
    with pytest.raises(PosesError, match="not empty .* not made by dars"):
        estimate_poses(photos, out)
    with pytest.raises(PosesError, match="already has images.* never overwrites"):
        estimate_poses(photos, out, PosesConfig(force=True))
    with pytest.raises(PosesError, match="nothing to resume"):
        estimate_poses(photos, out, PosesConfig(resume=True))
    assert _snapshot(out) == before
    with pytest.raises(PosesError, match="inside the photos folder"):
        estimate_poses(photos, photos / "scene")
    scene = tmp_path / "scene"
    shutil.copytree(photos, scene / "images")
    with pytest.raises(PosesError, match="which dars poses writes"):
        estimate_poses(scene / "images", scene)
    assert not (photos / "scene").exists() and not (scene / MANIFEST_NAME).exists()


def test_cli_error_is_one_message(tmp_path, capsys):
    from toolkit.cli import main

    (tmp_path / "photos").mkdir()
    assert main(["poses", str(tmp_path / "photos"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "dars poses: error: no photos" in err and "Traceback" not in err


# ------------------------------------------------------------------------------------------- real pycolmap
def _fox_subset(dest: Path, count: int = 10) -> Path:
    """Every 5th fox photo (the first ``count`` of those), downscaled to 320 px, in ``dest`` (a temporary copy; the
    shared data stay untouched)."""
    from PIL import Image

    src = shared("real", "fox", "images")
    dest.mkdir(parents=True)
    for n in sorted(p.name for p in src.glob("*.jpg"))[::5][:count]:
        with Image.open(src / n) as im:
            im.resize((180, 320), Image.Resampling.LANCZOS).save(dest / n, quality=95)
    return dest


@pytest.fixture(scope="module")
def fox_run(tmp_path_factory):
    pytest.importorskip("pycolmap")
    root = tmp_path_factory.mktemp("fox")
    photos = _fox_subset(root / "photos")
    lines: list[str] = []
    result = estimate_poses(photos, root / "scene", PosesConfig(num_threads=2), log=lines.append)
    return photos, root / "scene", result, lines


def test_fox_small_run(fox_run):
    from toolkit.scene import load_scene

    photos, scene_dir, result, lines = fox_run
    assert result.num_registered >= 8 and result.num_photos == 10
    assert result.mean_reprojection_error < 2.0 and result.num_points > 100
    assert any(line.startswith(f"registered {result.num_registered}/10 photos, mean reprojection error") for line in lines)
    doc = json.loads((scene_dir / "transforms.json").read_text())
    assert doc["ply_file_path"] == "sparse_pc.ply" and doc["camera_model"] == "PINHOLE"
    assert 170 <= doc["w"] <= 180 and 310 <= doc["h"] <= 320  # one camera: shared intrinsics (undistortion crops)
    tr = doc["dars_transform"]
    assert tr["source"] == "colmap" and tr["scale"] == 1.0 and tr["up_from"] in ("cameras", "cameras+plane")
    assert np.allclose(np.asarray(doc["applied_transform"])[:, :3], tr["rotation"])
    for sub in ("images", "sparse/0", "colmap/database.db"):
        assert (scene_dir / sub).exists(), sub
    assert json.loads((scene_dir / MANIFEST_NAME).read_text())["status"] == "done"
    ply = (scene_dir / "sparse_pc.ply").read_bytes()
    assert f"element vertex {result.num_points}".encode() in ply[:200]
    scene = load_scene(scene_dir, "train")
    assert len(scene) + len(load_scene(scene_dir, "test")) == result.num_registered
    assert tuple(scene.load_image(0).shape) == (3, doc["h"], doc["w"])
    # against the given poses: the cameras agree after a similarity alignment
    given = json.loads(shared("real", "fox", "transforms.json").read_text())
    ref = {Path(f["file_path"]).name: np.asarray(f["transform_matrix"]) for f in given["frames"]}
    errs = compare_poses(result.c2w, np.stack([ref[n] for n in result.names]))
    assert errs["rotation_error_deg"]["median"] < 2.0
    # upright: +z agrees with the given frame's up (colmap2nerf's mean camera up) to within a few degrees
    z_in_given = np.asarray(errs["rotation"]) @ [0.0, 0.0, 1.0]
    assert z_in_given[2] > np.cos(np.radians(10))


def test_fox_rerun_refused_then_resumed(fox_run):
    photos, scene_dir, result, _ = fox_run
    with pytest.raises(PosesError, match="already holds a dars poses scene.*--resume"):
        estimate_poses(photos, scene_dir)
    with pytest.raises(PosesError, match="other feature options .*max_size"):
        estimate_poses(photos, scene_dir, PosesConfig(resume=True, max_size=800))
    lines: list[str] = []
    again = estimate_poses(photos, scene_dir, PosesConfig(resume=True, num_threads=2), log=lines.append)
    assert again.names == result.names and np.allclose(again.c2w, result.c2w)
    assert any("already in the database" in ln or "already matched" in ln for ln in lines) or not any(
        ln.startswith("features:") and "extracting" in ln for ln in lines)
    assert any(ln.startswith("mapping: reusing") for ln in lines)


def test_unrelated_photos_are_named(tmp_path):
    pytest.importorskip("pycolmap")
    from PIL import Image

    photos = _fox_subset(tmp_path / "photos", 7)
    lego = shared("nerf_synthetic", "lego", "train")
    for n in ("r_0.png", "r_1.png", "r_2.png"):
        with Image.open(lego / n) as im:
            im.convert("RGB").resize((320, 320)).save(photos / f"lego_{n}")
    Image.new("RGB", (180, 320), (128, 128, 128)).save(photos / "grey.jpg")  # a lens cap shot: no features
    with pytest.raises(PosesError) as e:
        estimate_poses(photos, tmp_path / "scene", PosesConfig(num_threads=2))
    msg = str(e.value)
    assert "registered only 7 of 11 photos" in msg
    for n in ("lego_r_0.png", "lego_r_1.png", "lego_r_2.png"):
        assert f"  {n}: " in msg and ("no verified matches" in msg or "matches only other unregistered" in msg)
    assert "  grey.jpg: too few features (0 SIFT keypoints" in msg
    assert "what to try" in msg and "--resume --min-registered 0.63" in msg
    assert not any(f"  {p.name}: " in msg for p in photos.glob("0*.jpg"))
    unregistered = {f"lego_r_{i}.png" for i in range(3)} | {"grey.jpg"}
    manifest = json.loads((tmp_path / "scene" / MANIFEST_NAME).read_text())
    assert manifest["status"] == "failed" and set(manifest["unregistered"]) == unregistered
    ok = estimate_poses(photos, tmp_path / "scene", PosesConfig(resume=True, min_registered=0.6, num_threads=2))
    assert ok.num_registered == 7 and set(ok.unregistered) == unregistered


def test_sequential_pairs_follow_colmap():
    from toolkit.poses import _pairs

    names = [f"{i}.jpg" for i in range(40)]
    pairs = set(_pairs(names, "sequential", 3))
    assert ("0.jpg", "3.jpg") in pairs and ("0.jpg", "4.jpg") in pairs and ("0.jpg", "5.jpg") not in pairs
    assert len(_pairs(names, "exhaustive", 3)) == 40 * 39 // 2
    assert list_photos(Path(shared("real", "fox", "images")))[0][:2] == ["0001.jpg", "0002.jpg"]


def test_fox_sequential_per_photo_cameras(fox_run, tmp_path):
    from toolkit.scene import load_scene

    photos = fox_run[0]
    result = estimate_poses(photos, tmp_path / "seq", PosesConfig(matcher="sequential", overlap=3, single_camera=False,
                                                                  min_registered=0.5, num_threads=2))
    assert result.matcher == "sequential" and result.num_cameras == result.num_registered >= 5
    doc = json.loads((tmp_path / "seq" / "transforms.json").read_text())
    assert "fl_x" not in doc and all("fl_x" in f and "w" in f for f in doc["frames"])
    assert len(load_scene(tmp_path / "seq", "all")) == result.num_registered


def test_photo_names_with_spaces(fox_run, tmp_path):
    photos = tmp_path / "my photos"
    photos.mkdir()
    for p in sorted(fox_run[0].glob("*.jpg"))[:6]:
        shutil.copy(p, photos / f"IMG {p.name}")  # COLMAP's pair lists are space-separated: dars must not use them
    result = estimate_poses(photos, tmp_path / "scene", PosesConfig(num_threads=2, min_registered=0.5))
    assert result.num_registered >= 4 and all(n.startswith("IMG ") for n in result.names)
    assert (tmp_path / "scene" / "images" / result.names[0]).is_file()


def test_cli_defaults_match_config():
    """The CLI repeats PosesConfig's defaults (so --help imports nothing heavy): they must agree."""
    import argparse

    from toolkit.cli import poses as cli_poses
    from toolkit.poses import CAMERA_MODELS, PosesConfig

    assert cli_poses.CAMERA_MODELS == CAMERA_MODELS
    sub = argparse.ArgumentParser().add_subparsers()
    cli_poses.add_parser(sub)
    args = sub.choices["poses"].parse_args(["photos", "--out", "x"])
    d = PosesConfig()
    assert (args.matcher, args.max_size, args.camera_model, args.overlap, args.min_registered, args.threads,
            args.seed) == (d.matcher, d.max_size, d.camera_model, d.overlap, d.min_registered, d.num_threads, d.seed)
