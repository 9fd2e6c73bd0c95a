import json
import os

import numpy as np
import pytest
import torch

from _synthetic_gallery import make_views, make_world, write_scene
from toolkit._checks import ConfigError, SceneError, ShapeError
from toolkit.colour import (
    ColourConfig,
    ColourCorrection,
    ColourTransforms,
    apply_colour_transforms,
    estimate_colour_transforms,
    linear_to_srgb_odd,
    perturb_scene_copy,
    select_pairs,
    srgb_to_linear_odd,
)
from toolkit.io import linear_to_srgb, srgb_to_linear

cv2 = pytest.importorskip("cv2")


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Small tensors gain nothing from threads; two OpenMP threads spin-wait on a shared 2-core machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _perturbed_views(n=16, size=80, seed=0, n_pert=6):
    """Synthetic overlapping views (linear), some re-exposed by +-1 stop and white balance (1.15, 1, 0.85)."""
    rng = np.random.default_rng(seed)
    v = make_views(make_world(seed), n, seed + 1, size)
    true = np.ones((n, 3))
    for k in rng.choice(n, n_pert, replace=False):
        true[k] = 2.0 ** rng.choice([-1.0, 1.0]) * np.array([1.15, 1.0, 0.85])
    srgb = linear_to_srgb(np.clip(v["images"] * true[:, None, None, :], 0, 1))
    srgb = np.round(srgb * 255) / 255  # 8-bit photos
    return torch.from_numpy(srgb).permute(0, 3, 1, 2).float().contiguous(), true, torch.from_numpy(v["c2w"])


def _relative_error(gains: np.ndarray, true: np.ndarray) -> np.ndarray:
    """|gain / true - 1| per image and channel, with gains normalised by the unperturbed views' geometric mean."""
    base = (true == 1).all(1)
    rel = gains / np.exp(np.log(gains[base]).mean(0))
    return np.abs(rel / true - 1)


# ------------------------------------------------------------------ transfer and apply
def test_odd_srgb_transfer_is_a_bijection():
    x = torch.linspace(-2, 3, 1001, dtype=torch.float64)
    torch.testing.assert_close(linear_to_srgb_odd(srgb_to_linear_odd(x)), x)
    y = torch.linspace(0, 1, 101)
    torch.testing.assert_close(srgb_to_linear_odd(y), srgb_to_linear(y))


def test_apply_and_inverse_are_exact():
    torch.manual_seed(0)
    imgs = torch.rand(3, 3, 8, 9, dtype=torch.float64)
    tr = ColourTransforms(torch.tensor([[2.0, 1.0, 0.5], [1.0, 1.0, 1.0], [0.7, 1.3, 1.1]]),
                          torch.tensor([[0.0, 0.0, 0.0], [0.01, -0.02, 0.03], [0.05, 0.0, 0.0]]))
    fwd = apply_colour_transforms(imgs, tr)
    torch.testing.assert_close(apply_colour_transforms(fwd, tr, inverse=True), imgs, atol=1e-10, rtol=0)
    assert float(fwd.max()) > 1.0 or float(fwd.min()) < 0.0  # no clamping: values may leave [0, 1]
    lin = apply_colour_transforms(srgb_to_linear(imgs), tr, srgb=False)
    torch.testing.assert_close(lin[0, 0], srgb_to_linear(imgs[0, 0]) / 2.0)
    # photo = gain * consensus: correcting the first image divides its red channel by 2 in linear space
    torch.testing.assert_close(srgb_to_linear_odd(fwd[0, 0]), srgb_to_linear(imgs[0, 0]) / 2.0)
    sub = apply_colour_transforms(imgs[:1], tr, indices=[2])
    torch.testing.assert_close(sub, apply_colour_transforms(imgs, tr)[2:3] * 0 + apply_colour_transforms(
        imgs[:1], ColourTransforms(tr.gains[2:], tr.offsets[2:])))
    with pytest.raises(ShapeError, match="indices reach 5"):
        apply_colour_transforms(imgs[:1], tr, indices=[5])
    with pytest.raises(ShapeError, match="2 indices for 3 images"):
        apply_colour_transforms(imgs, tr, indices=[0, 1])


def test_transforms_json_roundtrip(tmp_path):
    tr = ColourTransforms(torch.tensor([[1.1, 1.0, 0.9], [0.5, 0.5, 0.5]]), torch.zeros(2, 3), ("a", "b"),
                          torch.tensor([True, False]), "mean", {"pairs_used": 3})
    d = tr.to_json(tmp_path / "c.json")
    assert d["images"][1]["stops"] == pytest.approx(-1.0)
    back = ColourTransforms.from_json(tmp_path / "c.json")
    torch.testing.assert_close(back.gains, tr.gains)
    assert back.keys == ("a", "b") and back.connected.tolist() == [True, False] and back.stats == {"pairs_used": 3}
    assert ColourTransforms.from_json(d).keys == ("a", "b")
    with pytest.raises(SceneError, match="not found"):
        ColourTransforms.from_json(tmp_path / "missing.json")
    with pytest.raises(SceneError, match="malformed"):
        ColourTransforms.from_json({"images": [{"gain": [1, 1, 1]}]})
    with pytest.raises(Exception, match="finite and positive"):
        ColourTransforms(torch.tensor([[0.0, 1.0, 1.0]]), torch.zeros(1, 3))


# ------------------------------------------------------------------ estimation
def test_select_pairs():
    assert select_pairs(4) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    seq = select_pairs(50, ColourConfig(neighbours=2))
    assert (0, 1) in seq and (0, 2) in seq and (0, 3) not in seq
    c2w = torch.eye(4).repeat(10, 1, 1)
    c2w[:, 0, 3] = torch.arange(10.0)  # cameras on a line: neighbours are adjacent
    near = select_pairs(10, ColourConfig(neighbours=2), c2w)
    assert (3, 4) in near and (4, 5) in near and (0, 9) not in near
    assert all(max(j - i for i, j in near if k in (i, j)) <= 2 for k in range(10))


@pytest.mark.parametrize("with_poses", [True, False])
def test_recovers_exposure_and_white_balance_within_5_percent(with_poses):
    imgs, true, c2w = _perturbed_views()
    tr = estimate_colour_transforms(imgs, ColourConfig(), c2w=c2w if with_poses else None)
    err = _relative_error(tr.gains.numpy(), true)
    assert err.max() < 0.05, f"max gain error {err.max():.4f}"  # measured ~0.5 %
    assert bool(tr.connected.all()) and tr.stats["pairs_used"] > 20
    assert np.abs(np.median(tr.log_gains.double().numpy(), axis=0)).max() < 1e-5  # default gauge: median gain 1
    # 6 of 16 views re-exposed: the median gauge leaves the 10 untouched ones at gain 1 without re-normalising
    # (the mean gauge would tint them by the perturbed views' average white balance)
    assert np.abs(tr.gains.numpy()[(true == 1).all(1)] - 1).max() < 0.03
    mean = estimate_colour_transforms(imgs, ColourConfig(gauge="mean"), c2w=c2w if with_poses else None)
    assert mean.gauge == "mean" and abs(float(mean.log_gains.mean(0).abs().max())) < 1e-6
    assert _relative_error(mean.gains.numpy(), true).max() < 0.05  # the same gains up to a common factor


def test_reference_gauge_and_isolated_image():
    imgs, true, _ = _perturbed_views(n=8, n_pert=3)
    noise = torch.rand(1, 3, imgs.shape[2], imgs.shape[3], generator=torch.Generator().manual_seed(5))
    imgs = torch.cat([imgs, noise])
    ref = int(np.flatnonzero((true == 1).all(1))[0])
    tr = estimate_colour_transforms(imgs, ColourConfig(gauge="reference", reference=ref))
    torch.testing.assert_close(tr.gains[ref], torch.ones(3), atol=1e-6, rtol=0)
    assert tr.gauge == f"reference:{ref}"
    assert not bool(tr.connected[-1]) and tr.stats["isolated"] == [8]
    torch.testing.assert_close(tr.gains[-1], torch.ones(3))  # nothing matched: left alone
    with pytest.raises(ConfigError, match="reference=20"):
        estimate_colour_transforms(imgs, ColourConfig(gauge="reference", reference=20))


def test_estimate_errors_and_empty():
    with pytest.raises(ShapeError, match="images"):
        estimate_colour_transforms(torch.rand(3, 8, 8))
    with pytest.raises(ConfigError, match="detector"):
        ColourConfig(detector="akaze")
    assert ColourConfig().detector == "orb"
    assert len(estimate_colour_transforms(torch.zeros(0, 3, 8, 8))) == 0


@pytest.mark.parametrize("kw", [dict(detector="sift"), dict(plane_pixels=0)])
def test_sift_and_keypoint_only_variants_also_work(kw):
    imgs, true, c2w = _perturbed_views(size=96)
    tr = estimate_colour_transforms(imgs, ColourConfig(**kw), c2w=c2w)
    assert _relative_error(tr.gains.numpy(), true).max() < 0.05


# ------------------------------------------------------------------ the trainable module
def test_colour_correction_module():
    init = ColourTransforms(torch.tensor([[2.0, 2.0, 2.0], [1.0, 1.0, 1.0]]), torch.zeros(2, 3))
    cc = ColourCorrection(2, init)
    # re-gauged to zero mean log gain: gains sqrt(2) and 1/sqrt(2)
    torch.testing.assert_close(cc.log_gain.exp(), torch.tensor([[2 ** 0.5] * 3, [2 ** -0.5] * 3]))
    assert float(cc.regulariser().detach()) == pytest.approx(0.0, abs=1e-10)
    rgb = torch.rand(5, 3)
    idx = torch.tensor([0, 1, 1, 0, 1])
    torch.testing.assert_close(cc(rgb, idx), rgb * cc.log_gain.exp()[idx])
    with pytest.raises(ShapeError, match="leading shape"):
        cc(rgb, idx[:3])
    with pytest.raises(ShapeError, match="n_images=3"):
        ColourCorrection(3, init)
    # the gauge term pins the common gain: shifting all log gains together costs, relative shifts only the init term
    with torch.no_grad():
        cc.log_gain += 0.1
    assert float(cc.regulariser().detach()) > 10 * 0.1 ** 2 * 3 * 0.99
    # median gauge: two of five images odd, the three typical ones keep gain 1 (a mean gauge would tint them)
    init5 = ColourTransforms(torch.tensor([[2.0, 2.0, 2.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0],
                                           [2.3, 2.0, 1.7]]), torch.zeros(5, 3))
    cc5 = ColourCorrection(5, init5)
    torch.testing.assert_close(cc5.log_gain.exp(), init5.gains)


def test_colour_correction_learns_gains_and_stays_gauged():
    torch.manual_seed(0)
    true = torch.tensor([[1.5, 1.0, 0.8], [1.0, 1.0, 1.0], [0.6, 0.7, 1.2], [1.0, 1.1, 1.0]])
    true = true / true.log().mean(0).exp()  # a zero-mean-log truth (the gauge)
    consensus = torch.rand(256, 3)
    idx = torch.randint(0, 4, (256,))
    photo = consensus * true[idx]
    cc = ColourCorrection(4, learn_offsets=True, weight_init=0.0, weight_offset=1e-3)
    opt = torch.optim.Adam(cc.parameters(), lr=0.05)
    for _ in range(400):
        loss = (cc(consensus, idx) - photo).abs().mean() + cc.regulariser()
        opt.zero_grad()
        loss.backward()
        opt.step()
    learnt = cc.to_transforms()
    assert float((learnt.gains / true - 1).abs().max()) < 0.03
    assert float(cc.log_gain.detach().mean(0).abs().max()) < 0.01


# ------------------------------------------------------------------ done-when: perturbed scene copy
def _done_when_check(src, tmp_path):
    from toolkit.scene import load_scene

    gains = perturb_scene_copy(src, tmp_path / "perturbed", n=10, seed=0)
    assert len(gains) == 10
    rec = json.loads((tmp_path / "perturbed" / "perturbation.json").read_text())
    assert rec["gains"] == gains
    scene = load_scene(tmp_path / "perturbed", "train")
    imgs = scene.load_images()
    tr = estimate_colour_transforms(imgs, ColourConfig(), c2w=scene.cameras.c2w, keys=[f.key for f in scene.frames])
    true = np.array([gains.get(f.name, [1.0, 1.0, 1.0]) for f in scene.frames])
    err = _relative_error(tr.gains.numpy(), true)
    return err, tr, scene


def test_perturbed_copy_gains_recovered_synthetic(tmp_path):
    src = write_scene(tmp_path / "src", n_train=24, n_test=2, size=96)
    before = {p: p.read_bytes() for p in (src / "train").glob("*.png")}
    err, tr, scene = _done_when_check(src, tmp_path)
    assert err.max() < 0.05, f"max gain error {err.max():.4f}"  # measured 0.5 %
    assert all(p.read_bytes() == b for p, b in before.items())  # the source is untouched
    with pytest.raises(SceneError, match="not empty"):
        perturb_scene_copy(src, tmp_path / "perturbed")
    with pytest.raises(SceneError, match="fewer than n=99"):
        perturb_scene_copy(src, tmp_path / "p2", n=99)


@pytest.mark.slow
def test_perturbed_copy_gains_recovered_on_sample(sample_scene_path, tmp_path):
    """SPEC stage 2 done-when: 10 sample views at +-1 stop and WB (1.15, 1, 0.85) -> gains within 5 %."""
    err, tr, _ = _done_when_check(sample_scene_path, tmp_path)
    assert err.max() < 0.05, f"max gain error {err.max():.4f}; stats {tr.stats}"


# ------------------------------------------------------------------ CLI
def _run(argv, capsys):
    from toolkit.cli import main

    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def test_cli_colour(tmp_path, capsys):
    scene = write_scene(tmp_path / "scene", n_train=8, n_test=1, size=64)
    rc, out, err = _run(["priors", "colour", str(scene)], capsys)
    assert rc == 0, err
    assert "gain R" in out and "train__r_007" in out
    d = json.loads((scene / "priors" / "colour" / "colour.json").read_text())
    assert len(d["images"]) == 8 and d["gauge"] == "median"
    tr = ColourTransforms.from_json(scene / "priors" / "colour" / "colour.json")
    assert float((tr.gains - 1).abs().max()) < 0.05  # an unperturbed scene is consistent already
    rc, out, err = _run(["priors", "colour", str(scene), "--json", "--reference", "2"], capsys)
    assert rc == 0 and json.loads(out)["gauge"] == "reference:2"
    rc, out, err = _run(["priors", "colour", str(scene), "--json", "--gauge", "mean", "--force"], capsys)
    assert rc == 0 and json.loads(out)["gauge"] == "mean"


def test_cli_read_only_scene_and_foreign_files(tmp_path, capsys):
    scene = write_scene(tmp_path / "scene", n_train=3, n_test=1, size=32)
    os.chmod(scene, 0o555)
    try:
        rc, out, err = _run(["priors", "colour", str(scene)], capsys)
    finally:
        os.chmod(scene, 0o755)
    assert rc == 2 and "read-only" in err and "--out" in err
    out_dir = tmp_path / "mine"
    out_dir.mkdir()
    (out_dir / "colour.json").write_text("{\"user\": true}")
    rc, out, err = _run(["priors", "colour", str(scene), "--out", str(out_dir)], capsys)
    assert rc == 2 and "refusing to write" in err and "colour.json" in err and "--force" in err
    assert json.loads((out_dir / "colour.json").read_text()) == {"user": True}
    rc, out, err = _run(["priors", "colour", str(scene), "--out", str(out_dir), "--force"], capsys)
    assert rc == 2 and "never overwrites your files" in err  # --force writes beside a user's file, never over it
    assert json.loads((out_dir / "colour.json").read_text()) == {"user": True}
    (out_dir / "colour.json").rename(out_dir / "my_colour.json")
    rc, out, err = _run(["priors", "colour", str(scene), "--out", str(out_dir), "--force"], capsys)
    assert rc == 0 and "images" in json.loads((out_dir / "colour.json").read_text())
    assert json.loads((out_dir / "my_colour.json").read_text()) == {"user": True}
    # our own files are overwritten freely on the next run
    rc, out, err = _run(["priors", "colour", str(scene), "--out", str(out_dir)], capsys)
    assert rc == 0, err


def test_training_loads_the_colour_prior(tmp_path, capsys):
    """`dars priors colour` then `dars train`: the run starts from the estimated per-image gains, matched to its
    frames by key (the estimate covers every split; this path once crashed on a missing ``subset``)."""
    from toolkit.train import init_state, make_config, prepare_data
    from toolkit.scene import load_scene

    scene = write_scene(tmp_path / "scene", n_train=8, n_test=1, size=64)
    assert _run(["priors", "colour", str(scene)], capsys)[0] == 0
    est = ColourTransforms.from_json(scene / "priors" / "colour" / "colour.json")
    train_scene = load_scene(scene, "train")
    data = prepare_data(train_scene, make_config("fast", steps=2), lambda m: None, None)
    assert data.priors_used["colour"].startswith("loaded")
    assert data.colour_init.keys == tuple(f.key for f in train_scene.frames)
    order = {k: i for i, k in enumerate(est.keys)}
    want = est.gains[[order[f.key] for f in train_scene.frames]]
    assert torch.equal(data.colour_init.gains, want)
    part = est.subset([2, 0])
    assert part.keys == (est.keys[2], est.keys[0]) and torch.equal(part.gains[1], est.gains[0])
    with pytest.raises(Exception, match="out of range"):
        est.subset([len(est)])
    # the gains get their own, smaller learning rate (at lr_net they random-walk several per cent in 1000 steps)
    cfg = make_config("fast", steps=2, lr_colour=3e-5)
    state = init_state(cfg, prepare_data(train_scene, cfg, lambda m: None, None))
    group = next(g for g in state.optimizer.param_groups if g["name"] == "colour")
    assert group["lr"] == 3e-5 and group["params"][0] is state.colour.log_gain
    with pytest.raises(Exception, match="lr_colour"):
        make_config("fast", steps=2, lr_colour=0.0)
