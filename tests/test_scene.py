import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
import torch

from conftest import shared
from toolkit._checks import SceneError
from toolkit.io import write_png
from toolkit.scene import generate_rays, intersect_aabb, list_splits, load_scene, project_points


# ------------------------------------------------------------------ real data sets
def test_lego_400px():
    root = shared("nerf_synthetic", "lego")
    train = load_scene(root, "train")
    val = load_scene(root, "val")
    assert len(train) == 100 and len(val) == 100
    assert train.image_size == (400, 400)
    assert float(train.cameras.fx[0]) == pytest.approx(555.5555, abs=1e-3)
    assert float(train.cameras.cx[0]) == 200.0
    img = train.load_image(0, with_alpha=True)
    assert img.shape == (4, 400, 400)
    alpha = img[3]
    assert 0.05 < float((alpha > 0.5).float().mean()) < 0.6  # the lego covers part of the view
    # RGBA composited onto white: fully transparent pixels are white
    assert torch.allclose(img[:3][:, alpha == 0], torch.ones(1))
    assert bool((alpha == 0).any())
    black = load_scene(root, "train", background=(0, 0, 0)).load_image(0)
    assert float(black[:, alpha == 0].abs().max()) == 0.0
    # the scene box estimate contains the object and the cameras look at it
    assert torch.all(train.aabb[0] < -1.0) and torch.all(train.aabb[1] > 1.0)
    rays = generate_rays(train.cameras, [0], aabb=train.aabb)
    assert bool((rays.far > rays.near).all())


def test_lego_downscale():
    root = shared("nerf_synthetic", "lego")
    sc = load_scene(root, "val", downscale=4)
    assert sc.image_size == (100, 100)
    assert float(sc.cameras.fx[0]) == pytest.approx(555.5555 / 4, abs=1e-3)
    assert sc.load_image(3).shape == (3, 100, 100)


def test_fox_real_capture():
    root = shared("real", "fox")
    assert list_splits(root) == ["train", "test", "all"]
    train, test, every = load_scene(root, "train"), load_scene(root, "test"), load_scene(root, "all")
    assert (len(train), len(test), len(every)) == (43, 7, 50)  # every 8th frame is test
    assert train.image_size == (960, 540)
    assert float(train.cameras.fx[0]) == pytest.approx(687.76)
    assert float(train.cameras.cy[0]) == pytest.approx(482.634)
    assert train.frames[0].distortion is not None
    assert torch.equal(train.aabb, test.aabb)  # bounds do not depend on the split
    und = train.load_image(0)
    raw = load_scene(root, "train", distortion="undistort").load_image(0)
    assert torch.equal(und, raw)
    from toolkit.io import read_image

    original = torch.from_numpy(read_image(train.frames[0].image_path)).permute(2, 0, 1)
    assert und.shape == original.shape and float((und - original).abs().mean()) > 1e-3  # undistortion moved pixels
    with pytest.raises(SceneError, match="distortion='reject'"):
        load_scene(root, "train", distortion="reject")


def test_tiny_lego_npz():
    f = shared("tiny_lego", "tiny_lego_100.npz")
    train, test = load_scene(f, "train"), load_scene(f, "test")
    assert (len(train), len(test)) == (100, 6)
    assert train.image_size == (100, 100)
    assert float(train.cameras.fx[0]) == pytest.approx(138.8888, abs=1e-3)
    assert (train.near, train.far) == (2.0, 6.0)
    img = test.load_image(1)
    assert img.shape == (3, 100, 100) and 0.0 <= float(img.min()) and float(img.max()) <= 1.0
    assert test.frames[1].name.endswith("r_33")


def test_sample_loads_with_every_extra(sample_scene_path):
    for split in ("train", "test"):
        sc = load_scene(sample_scene_path, split)
        assert len(sc) == {"train": 80, "test": 20}[split]
        assert set(sc.extras_available()) >= {"depth", "semantic", "normal", "albedo", "roughness", "metallic",
                                               "metal", "radiance"}
        assert sc.sh is not None and sc.sh.shape == (9, 3)
        h, w = sc.image_size
        lab = sc.load_extra(0, "semantic")
        assert lab.shape == (h, w) and lab.dtype == torch.int64
        n = sc.load_extra(0, "normal")
        valid = n.abs().sum(0) > 0
        assert torch.allclose(n[:, valid].norm(dim=0), torch.ones(1), atol=1e-3)
        d = sc.load_extra(0, "depth")
        assert d.shape == (h, w) and float(d.max()) > 0.5


# ------------------------------------------------------------------ rays and projection
def _one_camera(w=8, h=6, fx=10.0, fy=12.0, cx=4.0, cy=3.0, c2w=None):
    from toolkit.scene import Cameras

    c2w = torch.eye(4) if c2w is None else c2w
    return Cameras(c2w=c2w[None].float(), fx=torch.tensor([fx]), fy=torch.tensor([fy]), cx=torch.tensor([cx]),
                   cy=torch.tensor([cy]), width=torch.tensor([w]), height=torch.tensor([h]))


def test_ray_directions_for_known_pixels():
    cams = _one_camera()
    rays = generate_rays(cams, [0])
    assert len(rays) == 48
    # pixel (u=0, v=0): centre (0.5, 0.5) -> camera ray ((0.5-4)/10, -(0.5-3)/12, -1): up-left, looking down -z
    d = torch.tensor([(0.5 - 4) / 10, -(0.5 - 3) / 12, -1.0])
    assert torch.allclose(rays.directions[0], d / d.norm(), atol=1e-6)
    # pixel (3, 2) has its centre exactly 0.5 px from the principal point in each axis
    k = 2 * 8 + 3
    assert tuple(rays.pixels[k].tolist()) == (3, 2)
    d = torch.tensor([-0.5 / 10, 0.5 / 12, -1.0])
    assert torch.allclose(rays.directions[k], d / d.norm(), atol=1e-6)
    assert torch.allclose(rays.z_scale[k], 1 / d.norm(), atol=1e-6)
    # a rotated, translated camera: world direction = R d_cam, origin = t
    ang = math.radians(30)
    R = torch.tensor([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]])
    c2w = torch.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R, torch.tensor([1.0, 2.0, 3.0])
    rays2 = generate_rays(_one_camera(c2w=c2w), [0])
    assert torch.allclose(rays2.directions, rays.directions @ R.T, atol=1e-6)
    assert torch.allclose(rays2.origins, torch.tensor([1.0, 2.0, 3.0]).expand(48, 3))


def test_project_points_round_trip():
    ang = math.radians(-20)
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.tensor([[1, 0, 0], [0, math.cos(ang), -math.sin(ang)], [0, math.sin(ang), math.cos(ang)]])
    c2w[:3, 3] = torch.tensor([0.3, -2.0, 1.0])
    cams = _one_camera(w=32, h=24, fx=30, fy=30, cx=16.2, cy=11.7, c2w=c2w)
    rays = generate_rays(cams, [0])
    t = torch.rand(len(rays)) * 3 + 0.5
    pts = rays.origins + t[:, None] * rays.directions
    uv, depth = project_points(cams, 0, pts)
    assert torch.allclose(uv, rays.pixels.float() + 0.5, atol=1e-4)
    assert torch.allclose(depth, t * rays.z_scale, atol=1e-5)


def test_sampled_subset_and_aabb():
    cams = _one_camera()
    pix = torch.tensor([[0, 0], [7, 5]])
    rays = generate_rays(cams, torch.tensor([0, 0]), pixels=pix, aabb=torch.tensor([[-1.0, -1, -5], [1.0, 1, -1]]))
    assert len(rays) == 2
    assert torch.allclose(rays.near, 1.0 / rays.z_scale, atol=1e-5)  # enters the box at z = -1
    o = torch.zeros(1, 3)
    near, far = intersect_aabb(o, torch.tensor([[1.0, 0, 0]]), torch.tensor([[2.0, -1, -1], [3.0, 1, 1]]))
    assert (float(near), float(far)) == (2.0, 3.0)
    near, far = intersect_aabb(o, torch.tensor([[0.0, 1, 0]]), torch.tensor([[2.0, -1, -1], [3.0, 1, 1]]))
    assert float(far) <= float(near)  # miss


# ------------------------------------------------------------------ bad input
def _write_scene(tmp_path, n=3, w=8, h=6, frames_edit=None, meta_edit=None):
    frames = []
    for i in range(n):
        write_png(tmp_path / f"r_{i}.png", np.full((h, w, 3), 0.5, np.float32))
        m = np.eye(4)
        m[:3, 3] = [0, -3 - i, 0.5]
        frames.append({"file_path": f"r_{i}.png", "transform_matrix": m.tolist()})
    meta = {"camera_angle_x": 0.7, "frames": frames}
    if frames_edit:
        frames_edit(frames)
    if meta_edit:
        meta_edit(meta)
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    return tmp_path


def test_error_missing_image(tmp_path):
    root = _write_scene(tmp_path)
    (root / "r_1.png").unlink()
    with pytest.raises(SceneError, match=r"frame 1 \('r_1.png'\).*image not found"):
        load_scene(root)


def test_error_corrupt_image(tmp_path):
    root = _write_scene(tmp_path)
    (root / "r_2.png").write_bytes(b"not a png at all")
    with pytest.raises(SceneError, match=r"frame 2 .*r_2.png is corrupt"):
        load_scene(root)


def test_error_corrupt_image_body(tmp_path):
    root = _write_scene(tmp_path)
    good = (root / "r_0.png").read_bytes()
    (root / "r_0.png").write_bytes(good[:40])  # header readable, pixels truncated
    with pytest.raises(SceneError, match="r_0.png"):
        load_scene(root).load_image(0)


def test_error_missing_pose(tmp_path):
    root = _write_scene(tmp_path, frames_edit=lambda f: f[1].pop("transform_matrix"))
    with pytest.raises(SceneError, match=r"frame 1 .*missing 'transform_matrix'"):
        load_scene(root)


def test_error_non_finite_pose(tmp_path):
    def edit(frames):
        frames[2]["transform_matrix"][0][3] = float("nan")

    root = _write_scene(tmp_path, frames_edit=edit)
    with pytest.raises(SceneError, match=r"frame 2 .*NaN or inf"):
        load_scene(root)


def test_error_non_orthonormal_rotation(tmp_path):
    def edit(frames):
        frames[0]["transform_matrix"][0][0] = 2.0

    root = _write_scene(tmp_path, frames_edit=edit)
    with pytest.raises(SceneError, match=r"frame 0 .*not orthonormal"):
        load_scene(root)


def test_error_size_disagrees_with_intrinsics(tmp_path):
    root = _write_scene(tmp_path, meta_edit=lambda m: m.update(w=10, h=6, fl_x=9.0))
    with pytest.raises(SceneError, match=r"frame 0 .*8x6 but the intrinsics say w=10, h=6"):
        load_scene(root)


def test_error_empty_split(tmp_path):
    root = _write_scene(tmp_path, n=0)
    with pytest.raises(SceneError, match="split 'train' is empty"):
        load_scene(root)
    with pytest.raises(SceneError, match="split 'test' not found"):
        load_scene(root, "test")


def _labelled_scene(tmp_path, label):
    def edit(frames):
        frames[0]["semantic_path"] = "lab_0.png"

    root = _write_scene(tmp_path, frames_edit=edit)
    write_png(root / "lab_0.png", label)
    return load_scene(root)


def test_error_labels_wrong_size(tmp_path):
    sc = _labelled_scene(tmp_path, np.zeros((5, 8), np.uint8))
    with pytest.raises(SceneError, match=r"frame 0 .*semantic labels is 8x5 but the camera intrinsics say 8x6"):
        sc.load_extra(0, "semantic")


def test_error_labels_unknown_class(tmp_path):
    lab = np.zeros((6, 8), np.uint8)
    lab[0, 0], lab[1, 1] = 9, 255
    sc = _labelled_scene(tmp_path, lab)
    with pytest.raises(SceneError, match=r"unknown class ids \[9\]"):
        sc.load_extra(0, "semantic")


def test_labels_ok(tmp_path):
    lab = np.zeros((6, 8), np.uint8)
    lab[2:4, 2:5], lab[0, :] = 6, 255
    sc = _labelled_scene(tmp_path, lab)
    out = sc.load_extra(0, "semantic")
    assert out.tolist() == lab.astype(np.int64).tolist()
    with pytest.raises(SceneError, match="has no 'semantic_path'"):
        sc.load_extra(1, "semantic")


def test_lazy_loading_holds_no_pixels(tmp_path):
    root = _write_scene(tmp_path, n=5)
    sc = load_scene(root)
    assert sc._array_images is None and all(f.image_path is not None for f in sc.frames)
    # deleting an image after loading only fails when that image is asked for
    (root / "r_4.png").unlink()
    assert sc.load_image(0).shape == (3, 6, 8)
    with pytest.raises(SceneError, match="r_4.png"):
        sc.load_image(4)


# ------------------------------------------------------------------ COLMAP
def _write_colmap(tmp_path, model="PINHOLE", params="20 20 8 6"):
    (tmp_path / "images").mkdir()
    write_png(tmp_path / "images" / "a.png", np.full((12, 16, 3), 0.4, np.float32))
    write_png(tmp_path / "images" / "b.png", np.full((12, 16, 3), 0.6, np.float32))
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"# comment\n1 {model} 16 12 {params}\n")
    # image a: identity rotation, camera at origin; image b: 90 deg about y
    q = [math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0]
    (sparse / "images.txt").write_text(
        "# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n"
        "1 1 0 0 0 0 0 0 1 a.png\n\n"
        f"2 {q[0]} {q[1]} {q[2]} {q[3]} 0 0 2 1 b.png\n1.0 2.0 -1\n")
    return tmp_path


def test_colmap_pinhole_and_conventions(tmp_path):
    root = _write_colmap(tmp_path)
    sc = load_scene(root, "all", upright="off")  # the file's own frame (upright on load: test_upright_load.py)
    assert len(sc) == 2 and sc.image_size == (12, 16)
    assert float(sc.cameras.fx[0]) == 20 and float(sc.cameras.cx[0]) == 8
    # COLMAP camera looks down +z with y down; in OpenGL c2w it looks down -z: optical axis = -c2w[:, 2]
    axis = -sc.cameras.c2w[0, :3, 2]
    assert torch.allclose(axis, torch.tensor([0.0, 0.0, 1.0]))
    up = sc.cameras.c2w[0, :3, 1]
    assert torch.allclose(up, torch.tensor([0.0, -1.0, 0.0]))
    # image b: world-to-camera t = (0, 0, 2) -> the camera centre is -R^T t
    R = torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    centre = -(R.T @ torch.tensor([0.0, 0, 2]))
    assert torch.allclose(sc.cameras.c2w[1, :3, 3], centre, atol=1e-6)


def test_colmap_simple_pinhole(tmp_path):
    sc = load_scene(_write_colmap(tmp_path, "SIMPLE_PINHOLE", "18 8 6"), "all")
    assert float(sc.cameras.fy[1]) == 18


def test_colmap_radial_undistorted_or_rejected(tmp_path):
    root = _write_colmap(tmp_path, "OPENCV", "20 20 8 6 0.1 -0.05 0.001 0.0")
    sc = load_scene(root, "all")
    assert sc.frames[0].distortion == (0.1, -0.05, 0.001, 0.0)
    assert sc.load_image(0).shape == (3, 12, 16)
    with pytest.raises(SceneError, match="OPENCV.*distortion='reject'"):
        load_scene(root, "all", distortion="reject")


def test_colmap_fisheye_rejected(tmp_path):
    root = _write_colmap(tmp_path, "OPENCV_FISHEYE", "20 20 8 6 0.1 0.0 0.0 0.0")
    with pytest.raises(SceneError, match="fisheye model OPENCV_FISHEYE.*image_undistorter"):
        load_scene(root, "all")


def test_colmap_size_mismatch(tmp_path):
    root = _write_colmap(tmp_path)
    shutil.copy(root / "images" / "a.png", root / "images" / "keep.png")
    write_png(root / "images" / "a.png", np.zeros((10, 16, 3), np.float32))
    with pytest.raises(SceneError, match="a.png.*16x10 but camera 1.*16x12"):
        load_scene(root, "all")


def test_cli_info(tmp_path, capsys):
    from toolkit.cli import main

    root = _write_scene(tmp_path)
    assert main(["info", str(root), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["splits"]["train"]["frames"] == 3 and out["splits"]["train"]["image_size"] == [8, 6]
    assert main(["info", str(tmp_path / "nope")]) == 2
    assert "scene not found" in capsys.readouterr().err


def _write_llff(tmp_path, n=3, masks=True, size=(16, 12), hwf=(24.0, 32.0, 40.0)):
    """An LLFF capture (poses_bounds.npy + images/ + masks/) whose OpenGL camera-to-world matrices are returned."""
    (tmp_path / "images").mkdir(parents=True)
    rows, c2ws = [], []
    for k in range(n):
        a = 0.4 * k
        R = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        t = np.array([0.1 * k, -0.2, 1.5 + k])
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R, t
        c2ws.append(c2w)
        # LLFF stores the rotation's columns as (down, right, backwards) = (-y, x, z) of OpenGL
        P = np.concatenate([np.stack([-R[:, 1], R[:, 0], R[:, 2]], 1), t[:, None], np.array(hwf)[:, None]], 1)
        rows.append(np.concatenate([P.ravel(), [0.5, 4.0]]))
        write_png(tmp_path / "images" / f"IMG_{k:02d}.png", np.full((size[1], size[0], 3), 0.1 * k, np.float32))
    np.save(tmp_path / "poses_bounds.npy", np.stack(rows))
    if masks:
        (tmp_path / "masks").mkdir()
        for k in range(n):
            m = np.zeros((size[1], size[0]), np.uint8)
            m[2:8, 3:10] = 255
            write_png(tmp_path / "masks" / f"IMG_{k:02d}.png", m)
    return tmp_path, np.stack(c2ws)


def test_llff_capture_loads_with_poses_focal_and_masks(tmp_path):
    root, c2ws = _write_llff(tmp_path)
    assert list_splits(root) == ["train", "test", "all"]
    sc = load_scene(root, "all", upright="off")
    assert sc.meta["format"] == "llff" and sc.meta["llff_near_far"] == [0.5, 4.0]
    assert [f.image_path.name for f in sc.frames] == ["IMG_00.png", "IMG_01.png", "IMG_02.png"]
    assert np.allclose(sc.cameras.c2w.numpy(), c2ws, atol=1e-6)
    assert float(sc.cameras.fx[0]) == pytest.approx(20.0)  # 40 px at the poses' 32 px width, the photos are 16
    assert float(sc.cameras.cx[0]) == 8.0 and float(sc.cameras.cy[0]) == 6.0
    keep = sc.valid_mask(1)
    assert int(keep.sum()) == 6 * 7 and bool(keep[3, 4]) and not bool(keep[0, 0])
    assert [len(load_scene(root, s)) for s in ("train", "test")] == [2, 1]


def test_llff_capture_errors(tmp_path):
    root, _ = _write_llff(tmp_path / "a")
    (root / "masks" / "IMG_01.png").unlink()
    with pytest.raises(SceneError, match="no mask for IMG_01.png"):
        load_scene(root, "all")
    root, _ = _write_llff(tmp_path / "b", masks=False)
    write_png(root / "images" / "extra.png", np.zeros((12, 16, 3), np.float32))
    with pytest.raises(SceneError, match="3 poses but 4 photos"):
        load_scene(root, "all")
    root, _ = _write_llff(tmp_path / "c", masks=False, hwf=(32.0, 32.0, 40.0))
    with pytest.raises(SceneError, match="16x12 but the poses say 32x32"):
        load_scene(root, "all")
    root, _ = _write_llff(tmp_path / "d", masks=False)
    np.save(root / "poses_bounds.npy", np.zeros((3, 12)))
    with pytest.raises(SceneError, match=r"expected an \[N, 17\] array"):
        load_scene(root, "all")


def test_jpeg_mask_is_cut_at_half_its_range(tmp_path):
    """JPEG compression leaves faint values over a mask's background: they must not count as kept pixels."""
    import cv2

    root = _write_scene(tmp_path, n=2, w=32, h=32)
    meta = json.loads((root / "transforms_train.json").read_text())
    m = np.zeros((32, 32), np.uint8)
    m[8:24, 8:24] = 255
    m[0, :] = 6  # what compression leaves: faint, non-zero
    cv2.imwrite(str(root / "m.jpg"), m, [cv2.IMWRITE_JPEG_QUALITY, 70])
    write_png(root / "m.png", m)
    for f, name in zip(meta["frames"], ("m.jpg", "m.png")):
        f["mask_path"] = name
    (root / "transforms_train.json").write_text(json.dumps(meta))
    sc = load_scene(root, "train", upright="off")
    jpg, png = sc.load_extra(0, "mask"), sc.load_extra(1, "mask")
    assert not bool(jpg[0].any()) and not bool(jpg[:6].any()) and bool(jpg[12:20, 12:20].all())
    assert bool(png[0].all())  # a lossless mask keeps every non-zero pixel, as nerfstudio reads it
    alpha = load_scene(root, "train", upright="off", masks="alpha").load_image(0, with_alpha=True)[3]
    assert float(alpha[:6].max()) == 0.0 and float(alpha[12:20, 12:20].min()) == 1.0


def test_large_jpegs_decode_at_the_downscale_directly(tmp_path):
    """A JPEG loaded with --downscale 2/4/8 is decoded by libjpeg at that size (several times faster on 4000-px
    photos); the pixels agree with decoding it whole and area-filtering, its JPEG mask too, and a downscale no
    reduction divides still decodes whole."""
    import cv2

    yy, xx = np.mgrid[0:96, 0:128].astype(np.float32)
    rgb = np.stack([xx / 128, yy / 96, 0.5 + 0.4 * np.sin(xx / 9) * np.cos(yy / 7)], -1)
    cv2.imwrite(str(tmp_path / "p.jpg"), (rgb[..., ::-1] * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 95])
    mask = ((xx - 64) ** 2 + (yy - 48) ** 2 < 30 ** 2).astype(np.uint8) * 255
    cv2.imwrite(str(tmp_path / "m.jpg"), mask, [cv2.IMWRITE_JPEG_QUALITY, 80])
    meta = {"camera_angle_x": 0.7, "w": 128, "h": 96, "frames": [
        {"file_path": "p.jpg", "mask_path": "m.jpg", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    whole = cv2.imread(str(tmp_path / "p.jpg"))[..., ::-1].astype(np.float32) / 255
    for d in (2, 4, 8):
        sc = load_scene(tmp_path, "train", downscale=d, upright="off", masks="alpha")
        assert sc._jpeg_reduction(0) == d
        img = sc.load_image(0, with_alpha=True).numpy()
        assert img.shape == (4, 96 // d, 128 // d)
        ref = cv2.resize(whole, (128 // d, 96 // d), interpolation=cv2.INTER_AREA).transpose(2, 0, 1)
        alpha = img[3]
        ref_alpha = cv2.resize(mask.astype(np.float32) / 255, (128 // d, 96 // d), interpolation=cv2.INTER_AREA)
        assert np.abs(alpha - ref_alpha).mean() < 0.02 and alpha.max() == 1.0 and alpha.min() == 0.0
        inside = ref_alpha > 0.99  # composited onto the background elsewhere
        assert np.abs(img[:3][:, inside] - ref[:, inside]).mean() < 0.01
    meta_k1 = {**meta, "k1": 0.08, "k2": -0.05}  # a lens to undo: at half the reduction, then an area filter of 2
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta_k1))
    for d, k in ((2, 1), (4, 2), (8, 4)):
        sc = load_scene(tmp_path, "train", downscale=d, upright="off")
        assert sc._jpeg_reduction(0) == k
        whole = dataclasses.replace(sc)  # the same scene decoding its photo whole
        object.__setattr__(whole, "_jpeg_reduction", lambda i, path=None: 1)
        assert np.abs(sc.load_image(0).numpy() - whole.load_image(0).numpy()).mean() < 0.01
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    assert load_scene(tmp_path, "train", downscale=3, upright="off")._jpeg_reduction(0) == 1
    assert load_scene(tmp_path, "train", downscale=6, upright="off")._jpeg_reduction(0) == 2
    assert load_scene(tmp_path, "train", downscale=6, upright="off").load_image(0).shape == (3, 16, 21)
    from toolkit.io import read_image
    with pytest.raises(ValueError, match="reduce must be 1 or one of"):
        read_image(tmp_path / "p.jpg", reduce=3)
    sc = load_scene(tmp_path, "train", downscale=4, upright="off")
    small = cv2.resize(cv2.imread(str(tmp_path / "p.jpg")), (120, 96))  # replaced after loading by another size
    cv2.imwrite(str(tmp_path / "p.jpg"), small)
    with pytest.raises(SceneError, match=r"frame 0 \('p.jpg'\): image is about 120x96 \(decoded at 1/4 of its size\) "
                                         r"but the camera intrinsics say 128x96"):
        sc.load_image(0)
