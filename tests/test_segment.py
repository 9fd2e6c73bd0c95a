import json
import math

import numpy as np
import pytest
import torch
import torch.nn as nn

from _synthetic_gallery import make_views, make_world, write_scene
from toolkit._checks import ConfigError, ShapeError
from toolkit.io import linear_to_srgb
from toolkit.segment import (
    IGNORE_INDEX,
    NUM_CLASSES,
    SegmentConfig,
    Segmentation,
    SegmentationError,
    Segmenter,
    SegmenterConfig,
    TrainSegmenterConfig,
    load_segmenter,
    mean_iou,
    save_segmenter,
    segment_images,
    train_segmenter,
    validate_labels,
)

TINY = SegmenterConfig(widths=(8, 16, 32), groups=4)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Small tensors gain nothing from threads, and on a shared 2-core machine two OpenMP threads spin-wait
    (10x slower measured under load): run this module single-threaded, restore afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _as_images(views) -> torch.Tensor:
    return torch.from_numpy(linear_to_srgb(views["images"])).permute(0, 3, 1, 2).float().contiguous()


@pytest.fixture(scope="module")
def synth():
    world = make_world(0)
    tr, te = make_views(world, 8, 1, 48), make_views(world, 6, 2, 48)
    return (_as_images(tr), torch.from_numpy(tr["labels"]).long(), _as_images(te), torch.from_numpy(te["labels"]).long())


@pytest.fixture(scope="module")
def trained(synth):
    x, y, _, _ = synth
    cfg = TrainSegmenterConfig(arch=TINY, steps=200, batch_size=4, crop=32, seed=0)
    return train_segmenter(x, y, cfg)


# ------------------------------------------------------------------ network
def test_segmenter_shapes_and_size():
    net = Segmenter()
    assert 100_000 < net.num_parameters() < 1_000_000  # "a few hundred k"
    for h, w in ((37, 50), (128, 128), (9, 16)):
        assert net(torch.rand(2, 3, h, w)).shape == (2, NUM_CLASSES, h, w)
    assert not any(isinstance(m, nn.BatchNorm2d) for m in net.modules())
    with pytest.raises(ConfigError, match="groups"):
        SegmenterConfig(widths=(8, 12), groups=8)


# ------------------------------------------------------------------ mIoU
def test_mean_iou_known_values():
    miou, per = mean_iou(torch.tensor([0, 0, 1, 1]), torch.tensor([0, 1, 1, 255]), num_classes=2)
    # class 0: tp 1, fp 1, fn 0 -> 1/2; class 1: tp 1, fp 0 (the 255 pixel is ignored), fn 1 -> 1/2
    assert miou == pytest.approx(0.5) and per == pytest.approx([0.5, 0.5])
    miou, per = mean_iou(np.array([[0, 2]]), np.array([[0, 2]]), num_classes=7)
    assert miou == 1.0 and math.isnan(per[1])  # absent classes are nan and left out
    # a predicted 255 on a labelled pixel is a miss (not ignored)
    miou, per = mean_iou(torch.tensor([255, 1]), torch.tensor([0, 1]), num_classes=2)
    assert per[0] == 0.0 and per[1] == 1.0
    perfect = torch.randint(0, 7, (2, 5, 5))
    assert mean_iou(perfect, perfect)[0] == 1.0
    with pytest.raises(ShapeError, match="pixels"):
        mean_iou(torch.zeros(3), torch.zeros(4))


def test_validate_labels():
    with pytest.raises(SegmentationError, match=r"unknown class ids \[7, 9\]"):
        validate_labels(torch.tensor([[[0, 7, 9, 255]]]))
    with pytest.raises(SegmentationError, match="integer"):
        validate_labels(torch.zeros(1, 2, 2))
    with pytest.raises(SegmentationError, match=r"expected shape \[1, 2, 3\]"):
        validate_labels(torch.zeros(1, 2, 2, dtype=torch.long), (1, 2, 3))


# ------------------------------------------------------------------ provided
def test_provided_backend_passes_labels_through():
    lab = torch.randint(0, 7, (2, 6, 5))
    lab[0, 0, 0] = IGNORE_INDEX
    seg = segment_images(torch.rand(2, 3, 6, 5), SegmentConfig("provided"), labels=lab.to(torch.uint8))
    assert isinstance(seg, Segmentation) and seg.backend == "provided"
    assert torch.equal(seg.labels, lab) and seg.labels.dtype == torch.int64
    assert seg.probabilities.shape == (2, 7, 6, 5)
    assert float(seg.probabilities[0, :, 0, 0].sum()) == 0.0  # unlabelled: no class
    assert torch.equal(seg.probabilities[1].argmax(0), lab[1])
    with pytest.raises(SegmentationError, match="needs the scene's labels"):
        segment_images(torch.rand(1, 3, 4, 4), SegmentConfig("provided"))
    with pytest.raises(SegmentationError, match=r"unknown class ids \[12\]"):
        segment_images(torch.rand(1, 3, 4, 4), labels=torch.full((1, 4, 4), 12))
    with pytest.raises(ShapeError, match="images"):
        segment_images(torch.rand(3, 4, 4), labels=torch.zeros(1, 4, 4, dtype=torch.long))
    with pytest.raises(ConfigError, match="backend"):
        SegmentConfig(backend="mask2former")


# ------------------------------------------------------------------ builtin
def test_train_segmenter_learns_and_generalises(synth, trained):
    _, _, xt, yt = synth
    assert np.mean(trained.losses[-10:]) < 0.5 * np.mean(trained.losses[:10])
    seg = segment_images(xt, SegmentConfig("builtin", batch_size=4), model=trained.model)
    assert seg.labels.shape == yt.shape and seg.probabilities.shape == (6, 7, 48, 48)
    torch.testing.assert_close(seg.probabilities.sum(1), torch.ones(6, 48, 48))
    miou, per = mean_iou(seg.labels, yt)
    assert miou > 0.55, f"held-out mIoU on the synthetic wall {miou:.3f} ({per})"  # measured 0.72 at 200 steps
    assert not trained.model.training


def test_train_segmenter_is_seeded(synth):
    x, y, _, _ = synth
    cfg = TrainSegmenterConfig(arch=TINY, steps=5, batch_size=2, crop=24, seed=3)
    a, b = train_segmenter(x[:3], y[:3], cfg), train_segmenter(x[:3], y[:3], cfg)
    assert a.losses == b.losses


def test_train_segmenter_errors():
    with pytest.raises(SegmentationError, match="at least one labelled pixel"):
        train_segmenter(torch.rand(2, 3, 8, 8), torch.full((2, 8, 8), 255), TrainSegmenterConfig(steps=1))
    with pytest.raises(ShapeError, match="images"):
        train_segmenter(torch.rand(2, 8, 8), torch.zeros(2, 8, 8, dtype=torch.long))
    with pytest.raises(SegmentationError, match="needs a trained Segmenter"):
        segment_images(torch.rand(1, 3, 8, 8), SegmentConfig("builtin"))


def test_save_load_roundtrip(tmp_path, trained):
    p = save_segmenter(tmp_path / "seg.pt", trained.model, {"note": "x"})
    net = load_segmenter(p)
    x = torch.rand(2, 3, 30, 30)
    with torch.no_grad():
        torch.testing.assert_close(net(x), trained.model(x))
    assert net.cfg == TINY
    assert not any(f.name.startswith(".seg.pt") for f in tmp_path.iterdir())  # no temp file left
    with pytest.raises(SegmentationError, match="not found"):
        load_segmenter(tmp_path / "missing.pt")
    torch.save({"something": 1}, tmp_path / "other.pt")
    with pytest.raises(SegmentationError, match="not a dars segmenter file"):
        load_segmenter(tmp_path / "other.pt")


# ------------------------------------------------------------------ onnx backend
def test_onnx_backend_matches_builtin(tmp_path, synth, trained):
    pytest.importorskip("onnxruntime")
    from export.onnx import export_segmenter_onnx

    _, _, xt, _ = synth
    rep = export_segmenter_onnx(trained.model, tmp_path / "seg.onnx", image_size=(48, 48))
    assert rep.max_abs_err <= 1e-4
    a = segment_images(xt, SegmentConfig("builtin"), model=trained.model)
    b = segment_images(xt, SegmentConfig("onnx", batch_size=4), model=str(rep.path))
    c = segment_images(xt, SegmentConfig("onnx", onnx_path=str(rep.path)))
    assert float((a.labels == b.labels).float().mean()) > 0.999
    assert float((a.probabilities - b.probabilities).abs().max()) < 1e-4
    assert torch.equal(b.labels, c.labels)


class _Linear(nn.Module):
    """Per-pixel 1x1 conv; optionally at a fixed, lower output resolution, or emitting int labels."""

    def __init__(self, out: int = 7, labels: bool = False, down: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(3, out, 1)
        self.labels, self.down = labels, down

    def forward(self, x):
        if self.down > 1:
            x = nn.functional.avg_pool2d(x, self.down)
        y = self.conv(x)
        return y.argmax(1) if self.labels else y


def _export(tmp_path, net, name, example, dynamic=True, meta=None, hw_dynamic=True):
    axes = {"images": {2: "h", 3: "w"}} if hw_dynamic else {}
    torch.onnx.export(net.eval(), (example,), str(tmp_path / name), input_names=["images"], output_names=["out"],
                      opset_version=17, dynamo=False, external_data=False,
                      dynamic_axes={**({"images": {0: "n"}} if dynamic else {}),
                                    **{k: {**({0: "n"} if dynamic else {}), **v} for k, v in axes.items()}})
    if meta:
        import onnx

        m = onnx.load(str(tmp_path / name))
        for k, v in meta.items():
            e = m.metadata_props.add()
            e.key, e.value = k, v
        onnx.save(m, str(tmp_path / name))
    return tmp_path / name


def test_onnx_contract_variants(tmp_path):
    pytest.importorskip("onnxruntime")
    import warnings

    warnings.simplefilter("ignore")
    torch.manual_seed(0)
    x = torch.rand(3, 3, 16, 20)
    # ImageNet normalisation requested through metadata
    net = _Linear()
    f = _export(tmp_path, net, "imnet.onnx", x, meta={"dars.normalize": "imagenet"})
    seg = segment_images(x, SegmentConfig("onnx"), model=f)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    with torch.no_grad():
        ref = net((x - mean) / std).softmax(1)
    assert float((seg.probabilities - ref).abs().max()) < 1e-5
    # low-resolution logits are resized bilinearly to the image size
    f = _export(tmp_path, _Linear(down=4), "low.onnx", x)
    assert segment_images(x, SegmentConfig("onnx"), model=f).labels.shape == (3, 16, 20)
    # int label output
    lab_net = _Linear(labels=True)
    f = _export(tmp_path, lab_net, "labels.onnx", x)
    seg = segment_images(x, SegmentConfig("onnx"), model=f)
    with torch.no_grad():
        assert torch.equal(seg.labels, lab_net(x))
    # a fixed input size: images are resized to it
    f = _export(tmp_path, _Linear(), "fixed.onnx", torch.rand(1, 3, 8, 8), dynamic=False, hw_dynamic=False)
    assert segment_images(x, SegmentConfig("onnx"), model=f).labels.shape == (3, 16, 20)


def test_onnx_contract_errors(tmp_path):
    pytest.importorskip("onnxruntime")
    import warnings

    warnings.simplefilter("ignore")
    x = torch.rand(2, 3, 8, 8)
    f = _export(tmp_path, _Linear(out=5), "five.onnx", x)
    with pytest.raises(SegmentationError, match=r"shape \[2, 5, 8, 8\]; expected logits \[2, 7, h, w\]"):
        segment_images(x, SegmentConfig("onnx"), model=f)

    class TwoInputs(nn.Module):
        def forward(self, a, b):
            return a + b

    torch.onnx.export(TwoInputs(), (x, x), str(tmp_path / "two.onnx"), input_names=["a", "b"], dynamo=False,
                      opset_version=17, external_data=False)
    with pytest.raises(SegmentationError, match="has 2 inputs"):
        segment_images(x, SegmentConfig("onnx"), model=tmp_path / "two.onnx")

    class FourChannels(nn.Module):
        def forward(self, a):
            return a[:, :3].repeat(1, 3, 1, 1)[:, :7]

    torch.onnx.export(FourChannels(), (torch.rand(1, 4, 8, 8),), str(tmp_path / "four.onnx"), input_names=["a"],
                      dynamo=False, opset_version=17, external_data=False)
    with pytest.raises(SegmentationError, match=r"input 'a' has shape \[1, 4, 8, 8\]"):
        segment_images(x, SegmentConfig("onnx"), model=tmp_path / "four.onnx")
    f = _export(tmp_path, _Linear(), "batch2.onnx", x, dynamic=False, hw_dynamic=False)
    with pytest.raises(SegmentationError, match="batch is fixed to 2"):
        segment_images(x, SegmentConfig("onnx"), model=f)
    with pytest.raises(SegmentationError, match="not found"):
        segment_images(x, SegmentConfig("onnx"), model=tmp_path / "nope.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(SegmentationError, match="could not load"):
        segment_images(x, SegmentConfig("onnx"), model=tmp_path / "junk.onnx")
    with pytest.raises(SegmentationError, match="needs a model file"):
        segment_images(x, SegmentConfig("onnx"))


# ------------------------------------------------------------------ the bundled sample
@pytest.mark.slow
# ------------------------------------------------------------------ the scene's class prior
def test_train_class_prior_is_the_balanced_frequency():
    from toolkit.segment import train_class_prior

    p = train_class_prior([400, 100, 0, 0, 0, 0, 100])
    want = torch.tensor([20, 10, 0, 0, 0, 0, 10], dtype=torch.float64) / 40
    assert torch.allclose(p, want, atol=1e-3) and p.min() > 0  # a class never trained on: 1e-4, not 0
    assert torch.allclose(train_class_prior([3, 1, 0, 0, 0, 0, 0], class_balance=False)[:2],
                          torch.tensor([0.75, 0.25], dtype=torch.float64), atol=1e-3)
    with pytest.raises(SegmentationError, match="7 non-negative counts"):
        train_class_prior([1, 2, 3])


def _calibrated(labels: torch.Tensor, confidence: torch.Tensor, prior: torch.Tensor, g) -> torch.Tensor:
    """Probabilities of a network trained under ``prior``: the true class at ``confidence``, the rest spread by it."""
    n = labels.numel()
    rest = prior[None].expand(n, -1).clone()
    rest[torch.arange(n), labels] = 0
    rest = rest / rest.sum(1, keepdim=True) * (1 - confidence)[:, None]
    rest[torch.arange(n), labels] = confidence
    return rest


def test_scene_prior_drops_a_class_the_scene_lacks_and_keeps_a_small_real_one():
    """A network answers 'display' on 2 % of the pixels at low confidence in a room with no display case, and 'frame'
    on 0.3 % (true frames) with high confidence: EM removes the first, keeps the second."""
    from toolkit.segment import apply_scene_prior, estimate_scene_prior

    g = torch.Generator().manual_seed(0)
    pt = torch.tensor([0.16, 0.08, 0.05, 0.10, 0.36, 0.18, 0.07], dtype=torch.float64)  # as the shipped network's
    n = 20000
    truth = torch.full((n,), 4)  # wall
    truth[:6000] = 5  # floor
    truth[6000:8000] = 0  # painting
    truth[8000:8060] = 1  # a real frame, 0.3 %
    lab = truth.clone()
    fake = torch.arange(8100, 8500)  # 2 % of wall pixels the network calls display at 0.4
    lab[fake] = 2
    conf = torch.full((n,), 0.9, dtype=torch.float64)
    conf[8000:8060] = 0.995  # sure enough to outweigh a prior 200x smaller than the wall's
    conf[fake] = 0.4
    P = _calibrated(lab, conf, pt, g)
    P[fake, 4] = 0.35  # their second guess is the wall
    P[fake] = P[fake] / P[fake].sum(1, keepdim=True)
    assert (P.argmax(1) == 2).sum() == 400
    pi = estimate_scene_prior(P, pt)  # the defaults: floor 0.03, ceiling 2
    assert torch.isclose(pi.sum(), torch.tensor(1.0, dtype=torch.float64))
    assert pi[2] < 0.04 * pt[2] and pi[1] > 0.002, pi
    relab = apply_scene_prior(P.T.reshape(1, NUM_CLASSES, 1, n), pi, pt)[0].argmax(0).flatten()
    assert (relab == 2).sum() == 0 and (relab[fake] == 4).all()
    assert (relab[8000:8060] == 1).all() and (relab[:6000] == 5).all()
    assert torch.allclose(estimate_scene_prior(P[:0], pt), pt)  # no pixel: the training prior
    # a network that leans to 'painting' everywhere (a real capture it does not understand) cannot make the whole
    # scene painting: the ceiling holds its prior at 2x the training prior, and the others take the rest
    lean = _calibrated(torch.zeros(n, dtype=torch.long), torch.full((n,), 0.5, dtype=torch.float64), pt, g)
    pi = estimate_scene_prior(lean, pt, floor=0.03, ceiling=2.0)
    assert abs(float(pi[0]) - 2 * float(pt[0])) < 1e-6 and torch.isclose(pi.sum(), torch.tensor(1.0, dtype=pi.dtype))
    assert float(estimate_scene_prior(lean, pt, floor=0.03, ceiling=1e9)[0]) > 0.9  # plain EM: all painting
    with pytest.raises(ConfigError, match="floor"):
        estimate_scene_prior(P, pt, floor=2.0)


def test_shipped_segmenter_records_its_training_prior():
    from toolkit.segment import segmenter_train_prior

    pt = segmenter_train_prior(load_segmenter())
    assert pt is not None and pt.shape == (NUM_CLASSES,) and torch.isclose(pt.sum(), torch.tensor(1.0, dtype=pt.dtype))
    assert pt[4] == pt.max()  # walls: the most frequent class
    assert segmenter_train_prior(Segmenter(TINY)) is None


def test_builtin_on_sample(sample_scene_path):
    """Train on every 4th train view of the sample (reduced steps), evaluate on the test split."""
    from toolkit.scene import load_scene

    train, test = load_scene(sample_scene_path, "train"), load_scene(sample_scene_path, "test")
    if not (train.has_extra("semantic") and test.has_extra("semantic")):
        pytest.skip("sample has no semantic labels")
    idx = list(range(0, len(train), 4))
    x = train.load_images(idx)
    y = torch.stack([train.load_extra(i, "semantic") for i in idx])
    res = train_segmenter(x, y, TrainSegmenterConfig(steps=150))
    seg = segment_images(test.load_images(), SegmentConfig("builtin"), model=res.model)
    gt = torch.stack([test.load_extra(i, "semantic") for i in range(len(test))])
    miou, per = mean_iou(seg.labels, gt)
    assert miou > 0.5, f"sample test-split mIoU {miou:.3f} per class {per}"


# ------------------------------------------------------------------ CLI
def _run(argv, capsys):
    from toolkit.cli import main

    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def test_cli_segment_provided_and_builtin(tmp_path, capsys):
    scene = write_scene(tmp_path / "scene", n_train=6, n_test=3, size=40)
    # default: the shipped network on the photos (labels are only scored), with a metal mask per frame
    rc, out, err = _run(["priors", "segment", str(scene)], capsys)
    assert rc == 0, err
    seg_dir = scene / "priors" / "segment"
    for f in ("train__r_000.png", "train__r_005_preview.png", "train__r_003_metal.png"):
        assert (seg_dir / f).is_file(), f
    info = json.loads((seg_dir / "segment.json").read_text())
    assert info["backend"] == "shipped" and info["model"].startswith("shipped") and info["metal_mask"] == "predicted"
    sp = info["scene_prior"]  # relabelled by the scene's own class prior, estimated on its photos
    assert sp["applied"] and len(sp["scene_prior"]) == 7 and abs(sum(sp["scene_prior"]) - 1) < 1e-3 and sp["pixels"] > 0
    assert 0.0 <= info["miou_heldout"] <= 1.0 and info["heldout_views"] == 6  # nothing trained on: all 6 scored
    man = json.loads((seg_dir / "dars_manifest.json").read_text())
    assert man["dars"] == "priors segment" and "segment.json" in man["files"]
    # provided: the scene's own labels pass through
    rc, out, err = _run(["priors", "segment", str(scene), "--backend", "provided", "--out", str(tmp_path / "p")], capsys)
    assert rc == 0, err
    info = json.loads((tmp_path / "p" / "segment.json").read_text())
    assert info["backend"] == "provided" and info["miou_heldout"] == 1.0 and not info["scene_prior"]["applied"]
    rc, out, err = _run(["priors", "segment", str(scene), "--scene-prior", "off", "--out", str(tmp_path / "raw")], capsys)
    assert rc == 0, err
    info = json.loads((tmp_path / "raw" / "segment.json").read_text())
    assert info["scene_prior"] == {"applied": False, "reason": "turned off (--scene-prior off)"}

    out_dir = tmp_path / "seg_builtin"
    rc, out, err = _run(["priors", "segment", str(scene), "--backend", "builtin", "--train-every", "2", "--steps", "20",
                         "--out", str(out_dir), "--json"], capsys)
    assert rc == 0, err
    info = json.loads(out)  # stdout holds only JSON
    assert info["train_views"] == ["train__r_000", "train__r_002", "train__r_004"]
    assert 0.0 <= info["miou_heldout"] <= 1.0 and info["eval_split"] == "test" and "miou_eval" in info
    assert info["onnx"]["max_abs_err"] <= 1e-4
    for f in ("segmenter.pt", "segmenter.onnx", "segment.json", "train__r_001.png"):
        assert (out_dir / f).is_file(), f
    # the saved model segments again through --model, and the onnx one through the onnx backend
    rc, out, err = _run(["priors", "segment", str(scene), "--backend", "onnx", "--model", str(out_dir / "segmenter.onnx"),
                         "--out", str(tmp_path / "seg_onnx")], capsys)
    assert rc == 0, err and "mIoU" in out


def test_cli_segment_errors(tmp_path, capsys):
    scene = write_scene(tmp_path / "scene", n_train=3, n_test=1, size=32, with_labels=False)
    rc, out, err = _run(["priors", "segment", str(scene), "--backend", "builtin", "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and "no semantic_path labels" in err and "shipped" in err
    rc, out, err = _run(["priors", "segment", str(scene), "--backend", "onnx", "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and "needs --model" in err


@pytest.mark.parametrize("p, metal", [(0.6, False), (0.8, True)])
def test_priors_segment_metal_mask_is_the_probability_above_the_threshold(tmp_path, p, metal):
    """The metal mask a run trains with is the segmenter's metal probability above METAL_THRESHOLD (0.7, chosen on
    unseen galleries), not above 0.5: a network that says 0.6 everywhere marks nothing, one that says 0.8 all."""
    import math

    from toolkit.priors import priors_segment
    from toolkit.scene import load_scene
    from toolkit.segment import METAL_THRESHOLD, Segmenter, SegmenterConfig, save_segmenter

    assert METAL_THRESHOLD == 0.7
    scene = load_scene(write_scene(tmp_path / "scene", n_train=2, n_test=1, size=24), "train")
    torch.manual_seed(0)
    net = Segmenter(SegmenterConfig(metal=True))
    with torch.no_grad():  # the metal channel's logit is its bias alone
        net.head.weight[-1].zero_()
        net.head.bias[-1] = math.log(p / (1 - p))
    w = save_segmenter(tmp_path / "net.pt", net)
    info = priors_segment(scene, tmp_path / "seg", model=str(w))
    assert info["metal_threshold"] == METAL_THRESHOLD
    from toolkit.io import read_map

    for f in scene.frames:
        m = np.asarray(read_map(tmp_path / "seg" / f"{f.key}_metal.png"))
        assert (m > 0).all() if metal else (m == 0).all()
