"""Per-frame masks (``mask_path``, nerfstudio's key): left out of training and scoring, or read as the photo's alpha."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from synthetic import make_scene
from toolkit._checks import ConfigError
from toolkit.io import read_image, write_png
from toolkit.scene import SceneError, load_scene, photos_have_transparency

SIZE = 32
BLOCK = 10  # the masked-out corner of every training photo: a "visitor" painted magenta there


def _with_masks(root: Path, splits=("train",), paint: bool = True) -> Path:
    """Give every frame of ``splits`` a mask that is 0 on its top-left BLOCK x BLOCK corner, and paint that corner
    magenta in the photo (something in the way that the other photos do not show)."""
    for split in splits:
        meta = json.loads((root / f"transforms_{split}.json").read_text())
        for f in meta["frames"]:
            mask = np.full((SIZE, SIZE), 255, np.uint8)
            mask[:BLOCK, :BLOCK] = 0
            name = f["file_path"].replace(".png", "_mask.png")
            write_png(root / name, mask)
            f["mask_path"] = name
            if paint:
                img = read_image(root / f["file_path"], "photo")
                img[:BLOCK, :BLOCK, :3] = [1.0, 0.0, 1.0]
                write_png(root / f["file_path"], img)
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


@pytest.fixture(scope="module")
def masked(tmp_path_factory):
    return _with_masks(make_scene(tmp_path_factory.mktemp("masked"), n_train=16, n_test=4, size=SIZE), ("train", "test"))


def test_scene_reads_masks_as_pixels_to_ignore_or_as_alpha(masked):
    sc = load_scene(masked, "train")
    assert sc.masks == "ignore"
    keep = sc.valid_mask(0)
    assert keep.dtype == torch.bool and keep.shape == (SIZE, SIZE)
    assert not bool(keep[:BLOCK, :BLOCK].any()) and bool(keep[BLOCK:, :].all())
    assert torch.allclose(sc.load_image(0)[:, 0, 0], torch.tensor([1.0, 0.0, 1.0]))  # the photo is untouched
    assert not photos_have_transparency(sc)
    assert load_scene(masked, "train", masks="off").valid_mask(0) is None

    sa = load_scene(masked, "train", masks="alpha")
    rgba = sa.load_image(0, with_alpha=True)
    assert float(rgba[3, :BLOCK, :BLOCK].max()) == 0.0 and float(rgba[3, BLOCK:].min()) == 1.0
    assert torch.allclose(rgba[:3, 0, 0], torch.tensor(sa.background))  # composited onto the background
    assert sa.valid_mask(0) is None and photos_have_transparency(sa)
    half = load_scene(masked, "train", masks="alpha", downscale=4)  # area-filtered: a soft edge, not a hard one
    a = half.load_image(0, with_alpha=True)[3]
    assert a.shape == (SIZE // 4, SIZE // 4) and 0.0 < float(a[2, 1]) < 1.0


def test_scene_mask_errors(tmp_path):
    root = make_scene(tmp_path / "plain", n_train=4, n_test=2, size=16)
    with pytest.raises(SceneError, match="no frame of split 'train' has a mask_path"):
        load_scene(root, "train", masks="alpha")
    with pytest.raises(SceneError, match="masks must be 'ignore', 'alpha' or 'off'"):
        load_scene(root, "train", masks="holes")


def _small(sweep: bool = False, **kw):
    """A small room config; without ``sweep`` the terms that read whole photos for geometry (triangulated points,
    the room box's plane sweep) are off: they are slow here and not what these tests are about."""
    from dataclasses import replace

    from toolkit.train import make_config

    base = dict(batch_rays=512, ssim_patches=1, log_every=5, checkpoint_every=50, occupancy_resolution=24,
                occupancy_warmup=16, seed=0)
    base.update(kw)
    cfg = make_config("fast", **base)
    if not sweep:
        cfg = replace(cfg, losses=replace(cfg.losses, sparse_depth=0.0, layout_depth=0.0, layout_normal=0.0))
    return cfg


def test_masked_pixels_are_never_drawn_and_weigh_nothing(masked):
    from toolkit.train.config import resolve_config
    from toolkit.train.data import prepare_data
    from toolkit.train.step import init_state, sample_batch

    cfg, sc = resolve_config(_small(steps=10, labels="none"), load_scene(masked, "train"))
    assert cfg.masks == "ignore"
    data = prepare_data(sc, cfg, log=lambda m: None, priors_root=masked / "no_priors")
    assert data.valid is not None and data.priors_used["masks"].startswith("mask_path: ")
    assert int(data.valid.raw(0).sum()) == SIZE * SIZE - BLOCK * BLOCK
    state = init_state(cfg, data)
    s = cfg.ssim_patch_size
    seen_masked_patch = 0
    for _ in range(20):
        b = sample_batch(state, data)
        ok = data.valid.gather(b.pixels)
        assert bool(ok[:b.n_random].all())  # the sampler never draws a masked pixel
        assert bool((b.iw[b.n_random:][~ok[b.n_random:]] == 0).all())  # a patch's masked pixels weigh nothing
        bad = ~ok[b.n_random:].reshape(-1, s * s).all(1)
        assert bool((b.patch_iw[bad] == 0).all()) and bool((b.patch_iw[~bad] > 0).all())
        seen_masked_patch += int(bad.sum())
    assert seen_masked_patch > 0  # patches near the corner do reach into it: the test exercised that path
    # without masks every pixel may be drawn
    cfg_off, _ = resolve_config(_small(steps=10, labels="none", masks="off"), load_scene(masked, "train"))
    assert prepare_data(sc, cfg_off, log=lambda m: None, priors_root=masked / "no_priors").valid is None


def _repaint(src: Path, dst: Path, colour) -> Path:
    """A copy of the scene whose training photos have ``colour`` under their masks instead of magenta."""
    import shutil

    shutil.copytree(src, dst)
    meta = json.loads((dst / "transforms_train.json").read_text())
    for f in meta["frames"]:
        img = read_image(dst / f["file_path"], "photo")
        img[:BLOCK, :BLOCK, :3] = colour
        write_png(dst / f["file_path"], img)
    return dst


def test_what_the_masks_cover_never_reaches_training_and_eval_leaves_it_out(masked, tmp_path):
    """Two captures that differ only under their masks train to the same field, to the last bit, when the masks are
    honoured (the geometry terms that read the photos' features and the plane sweep off: they look at the photos as
    a whole); with --masks off they do not. dars eval scores the kept pixels only."""
    from toolkit.evaluate import EvalConfig, evaluate_run
    from toolkit.train import load_run, train

    other = _repaint(masked, tmp_path / "green", [0.0, 1.0, 0.0])
    no_sweep = dict(steps=4, labels="none", pretrain_fraction=0.5)

    def run(scene, mode):
        out = tmp_path / f"{scene.name}_{mode}"
        cfg = _small(masks=mode, **no_sweep)
        train(scene, out, cfg, progress_bar=False, log=lambda m: None)
        return out, torch.load(out / "checkpoint.pt", weights_only=False)

    def same(a, b):
        fa, fb = a["field"], b["field"]
        return all(torch.equal(fa[k], fb[k]) for k in fa) and torch.equal(a["l_env"], b["l_env"])

    (out_m, ck_m), (_, ck_g) = run(masked, "auto"), run(other, "auto")
    assert same(ck_m, ck_g)
    assert not same(run(masked, "off")[1], run(other, "off")[1])
    meta = json.loads((out_m / "config.json").read_text())
    assert meta["masks"] == "ignore" and meta["config"]["masks"] == "ignore" and "masks" in meta["priors"]
    res = evaluate_run(load_run(out_m), "test", EvalConfig(figure_views=0, weight_views=0))
    assert res.details["definitions"]["masks"] is not None
    assert all(abs(r["masked_out"] - BLOCK * BLOCK / SIZE ** 2) < 1e-6 for r in res.per_view)


def test_masks_alpha_makes_a_masked_capture_an_object(masked):
    from toolkit.train.config import resolve_config

    cfg, _ = resolve_config(_small(steps=10, masks="alpha"), load_scene(masked, "train", masks="alpha"))
    assert cfg.masks == "alpha" and cfg.scene_type == "object"
    cfg, _ = resolve_config(_small(steps=10), load_scene(masked, "train"))
    assert cfg.masks == "ignore" and cfg.scene_type == "unbounded"


def test_all_masked_out_is_a_clear_error(tmp_path):
    from toolkit.train.config import resolve_config
    from toolkit.train.data import prepare_data

    root = make_scene(tmp_path / "s", n_train=4, n_test=2, size=16)
    meta = json.loads((root / "transforms_train.json").read_text())
    for f in meta["frames"]:
        write_png(root / "zero.png", np.zeros((16, 16), np.uint8))
        f["mask_path"] = "zero.png"
    (root / "transforms_train.json").write_text(json.dumps(meta))
    cfg, sc = resolve_config(_small(steps=10, labels="none"), load_scene(root, "train"))
    with pytest.raises(ConfigError, match="every pixel of the training photos is masked out"):
        prepare_data(sc, cfg, log=lambda m: None, priors_root=root / "none")


def test_no_feature_point_on_a_masked_pixel(masked):
    from toolkit.bounds import sparse_depth_targets, triangulate_sparse_points

    sc = load_scene(masked, "train")
    t = sparse_depth_targets(sc, triangulate_sparse_points(sc))
    assert len(t["depth"]) > 0
    inside = (t["rows"] < BLOCK) & (t["cols"] < BLOCK)
    assert not bool(inside.any())
    t_off = sparse_depth_targets(sc, triangulate_sparse_points(load_scene(masked, "train", masks="off")))
    assert bool(((t_off["rows"] < BLOCK) & (t_off["cols"] < BLOCK)).any())  # without the masks, some land there


def _object_masks(root: Path, centre, radius) -> Path:
    """A synthetic scene whose every frame has the same disk as its mask (an object cut out, as NeRD's masks)."""
    root = make_scene(root, n_train=6, n_test=2, size=SIZE)
    yy, xx = np.mgrid[:SIZE, :SIZE]
    disk = ((yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 < radius ** 2).astype(np.uint8) * 255
    write_png(root / "disk.png", disk)
    for split in ("train", "test"):
        meta = json.loads((root / f"transforms_{split}.json").read_text())
        for f in meta["frames"]:
            f["mask_path"] = "disk.png"
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


def test_priors_see_an_object_as_training_does(tmp_path):
    """With masks that outline an object, the priors of `dars train` (and of `dars priors ...`) are computed on the
    photos composited on the background, as training sees them, not on the raw photos with their surroundings."""
    from toolkit.cli import main

    root = _object_masks(tmp_path / "s", (SIZE / 2, SIZE / 2), SIZE / 3)
    run = tmp_path / "run"
    assert main(["train", str(root), "--out", str(run), "--steps", "2", "--batch-rays", "256", "--quiet"]) == 0
    rec = json.loads((run / "priors" / "priors.json").read_text())
    assert rec["photos"].startswith("composited on the background")
    assert "out_of_domain" in json.loads((run / "priors" / "light" / "light.json").read_text())
    labels = read_image(run / "priors" / "segment" / f"{load_scene(root, 'train').frames[0].key}.png")
    assert labels.shape[:2] == (SIZE, SIZE)
    for masks, composited in (("auto", True), ("ignore", False)):
        out = tmp_path / f"light_{masks}"
        assert main(["priors", "light", str(root), "--out", str(out), "--masks", masks, "--json"]) == 0
        assert ("out_of_domain" in json.loads((out / "light.json").read_text())) == composited


def test_masks_that_outline_an_object_become_its_alpha(tmp_path, masked):
    """Object masks (NeRD, IDR, DTU: the thing photographed cut out of its surroundings) keep little of the photos'
    borders: ``--masks auto`` reads them as alpha, and the scene trains as an object. Masks that leave out a visitor
    keep most of the border and stay ``ignore``."""
    from toolkit.train.config import OBJECT_MASK_BORDER, masks_border_share, resolve_config

    root = _object_masks(tmp_path / "s", (SIZE / 2, SIZE / 2), SIZE / 3)
    sc = load_scene(root, "train")
    assert masks_border_share(sc) == 0.0
    cfg, sc2 = resolve_config(_small(steps=10, labels="none"), sc)
    assert cfg.masks == "alpha" and sc2.masks == "alpha" and cfg.scene_type == "object"
    alpha = sc2.load_image(0, with_alpha=True)[3]
    assert float(alpha[0, 0]) == 0.0 and float(alpha[SIZE // 2, SIZE // 2]) == 1.0
    visitor = load_scene(masked, "train")
    assert masks_border_share(visitor) > OBJECT_MASK_BORDER
    cfg, sc3 = resolve_config(_small(steps=10, labels="none"), visitor)
    assert cfg.masks == "ignore" and sc3.masks == "ignore" and cfg.scene_type == "unbounded"


def test_eval_scores_a_masked_object_alone_too(tmp_path):
    """On an object with alpha, dars eval adds the PSNR of the object's pixels alone (the plain background is easy
    to match): per view over alpha >= 0.5, checked against a direct render."""
    from toolkit.evaluate import EvalConfig, evaluate_run
    from toolkit.io import linear_to_srgb
    from toolkit.metrics import psnr
    from toolkit.train import load_run, train

    root = _object_masks(tmp_path / "s", (16, 16), 10)
    out = tmp_path / "run"
    train(root, out, _small(steps=4, labels="none", pretrain_fraction=0.5), progress_bar=False, log=lambda m: None)
    run = load_run(out)
    res = evaluate_run(run, "test", EvalConfig(figure_views=0, weight_views=0), log=lambda m: None)
    vals = [r["psnr_object"] for r in res.per_view]
    assert res.details["object_psnr"] == pytest.approx(sum(vals) / len(vals))
    sc = load_scene(root, "test", masks="alpha")
    with torch.no_grad():
        pred = linear_to_srgb(run.render(sc.cameras, 0).rgb.clamp(0, 1)).permute(2, 0, 1)
    rgba = sc.load_image(0, with_alpha=True)
    assert vals[0] == pytest.approx(float(psnr(pred, rgba[:3], rgba[3] >= 0.5)), abs=1e-3)
    assert vals[0] != pytest.approx(res.per_view[0]["psnr"], abs=1e-3)  # the background changes the full figure
