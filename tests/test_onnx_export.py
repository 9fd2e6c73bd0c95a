import numpy as np
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from export.onnx import (  # noqa: E402
    OnnxExportReport,
    OnnxParityError,
    export_onnx,
    export_segmenter_onnx,
    read_onnx_metadata,
    run_onnx,
)
from toolkit._checks import ConfigError, DarsError  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Small tensors gain nothing from threads, and on a shared 2-core machine two OpenMP threads spin-wait
    (10x slower measured under load): run this module single-threaded, restore afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


class TwoInTwoOut(nn.Module):
    """points [N, 3], dirs [N, 3] -> (sigma [N, 1], rgb [N, 3]): the shape of a field network."""

    def __init__(self):
        super().__init__()
        self.a = nn.Sequential(nn.Linear(3, 32), nn.ReLU(), nn.Linear(32, 17))
        self.b = nn.Linear(16 + 3, 3)

    def forward(self, points, dirs):
        h = self.a(points)
        return F.softplus(h[:, :1]), torch.sigmoid(self.b(torch.cat([h[:, 1:], dirs], -1)))


class Wrong(nn.Module):
    """Torch and ONNX disagree on purpose: a python-side branch on the batch size is frozen by tracing."""

    def forward(self, x):
        return x * 2.0 if x.shape[0] == 2 else x * 3.0


def test_export_multi_io_dynamic_batch(tmp_path):
    torch.manual_seed(0)
    net = TwoInTwoOut()
    ex = (torch.rand(5, 3), torch.rand(5, 3))
    rep = export_onnx(net, ex, tmp_path / "field.onnx", ["points", "dirs"], ["sigma", "rgb"],
                      metadata={"dars.kind": "test", "note": "hello"})
    assert isinstance(rep, OnnxExportReport)
    assert rep.opset == 17 and rep.exporter == "legacy"
    assert rep.max_abs_err <= 1e-5
    assert set(rep.errors) == {"example", "random_b8"}
    assert rep.inputs_checked["random_b8"] == [[8, 3], [8, 3]]
    assert rep.file_size == (tmp_path / "field.onnx").stat().st_size > 1000
    assert not (tmp_path / "field.onnx.data").exists()  # one self-contained file
    assert read_onnx_metadata(rep.path) == {"dars.kind": "test", "note": "hello"}
    out = run_onnx(rep.path, {"points": np.random.rand(11, 3).astype(np.float32),
                              "dirs": np.random.rand(11, 3).astype(np.float32)})
    assert out["sigma"].shape == (11, 1) and out["rgb"].shape == (11, 3)
    import onnx

    m = onnx.load(str(rep.path))
    dims = [d.dim_param for d in m.graph.input[0].type.tensor_type.shape.dim]
    assert dims[0] == "batch"
    assert net.training  # mode restored


def test_export_opset18_dynamo(tmp_path):
    net = TwoInTwoOut()
    rep = export_onnx(net, (torch.rand(4, 3), torch.rand(4, 3)), tmp_path / "f18.onnx", ["points", "dirs"],
                      ["sigma", "rgb"], opset=18)
    assert rep.opset == 18 and rep.exporter == "dynamo" and rep.max_abs_err <= 1e-5


def test_parity_error_is_raised_with_measured_error(tmp_path):
    with pytest.raises(OnnxParityError, match=r"differs from torch by [0-9.]+ > tol 0.0001") as e:
        export_onnx(Wrong(), (torch.ones(2, 3),), tmp_path / "w.onnx", ["x"], ["y"], random_batch=4)
    assert isinstance(e.value, DarsError)
    # the graph froze "x * 2"; torch computes x * 3 at batch 4, so the error is max(x) of the random input
    # (uniform on [0.5, 1.5] around the constant example value 1)
    assert 0.5 < e.value.max_abs_err <= 1.5
    assert (tmp_path / "w.onnx").is_file()  # kept for inspection


def test_export_errors(tmp_path):
    net = TwoInTwoOut()
    with pytest.raises(ConfigError, match="1 input_names"):
        export_onnx(net, (torch.rand(2, 3), torch.rand(2, 3)), tmp_path / "a.onnx", ["points"], ["s", "r"])
    with pytest.raises(ConfigError, match="returns 2 outputs"):
        export_onnx(net, (torch.rand(2, 3), torch.rand(2, 3)), tmp_path / "a.onnx", ["p", "d"], ["s"])
    with pytest.raises(ConfigError, match="tuple of tensors"):
        export_onnx(net, torch.rand(2, 3), tmp_path / "a.onnx", ["p"], ["s"])
    with pytest.raises(ConfigError, match="neither an input"):
        export_onnx(net, (torch.rand(2, 3), torch.rand(2, 3)), tmp_path / "a.onnx", ["p", "d"], ["s", "r"],
                    dynamic_axes={"nope": {1: "x"}})
    with pytest.raises(DarsError, match="not given"):
        rep = export_onnx(net, (torch.rand(2, 3), torch.rand(2, 3)), tmp_path / "b.onnx", ["p", "d"], ["s", "r"])
        run_onnx(rep.path, {"p": np.zeros((1, 3), np.float32)})


def test_segmenter_parity_dynamic_batch_and_size(tmp_path):
    """The builtin segmenter: max abs logit diff <= 1e-4 at the example size, another batch, and another size."""
    from toolkit.segment import Segmenter

    torch.manual_seed(0)
    net = Segmenter()
    rep = export_segmenter_onnx(net, tmp_path / "seg.onnx", image_size=(40, 56))
    assert rep.max_abs_err <= 1e-4, rep.errors
    meta = read_onnx_metadata(rep.path)
    assert meta["dars.kind"] == "segmenter" and meta["dars.normalize"] == "none"
    x = torch.rand(3, 3, 33, 71)
    got = run_onnx(rep.path, {"images": x.numpy()})["logits"]
    with torch.no_grad():
        ref = net.eval()(x).numpy()
    assert got.shape == (3, 7, 33, 71)
    assert np.abs(got - ref).max() <= 1e-4


def test_shipped_segmenter_onnx_has_metal_and_work_size(tmp_path):
    """The shipped segmenter exports its metal channel as a second output and its working scale as metadata; the
    ``onnx`` backend (resizing to that scale) gives the torch backend's labels and metal mask."""
    from toolkit.segment import SegmentConfig, load_segmenter, segment_images

    net = load_segmenter()  # the shipped network
    assert net.cfg.metal and net.cfg.work_size > 0
    rep = export_segmenter_onnx(net, tmp_path / "seg.onnx", image_size=(48, 64))
    assert rep.max_abs_err <= 1e-4, rep.errors
    meta = read_onnx_metadata(rep.path)
    assert meta["dars.work_size"] == str(net.cfg.work_size)
    x = torch.rand(2, 3, 90, 120)
    ref = segment_images(x, SegmentConfig(backend="builtin"), model=net)
    got = segment_images(x, SegmentConfig(backend="onnx"), model=str(rep.path))
    assert got.metal is not None and got.metal.shape == (2, 90, 120)
    assert (got.labels == ref.labels).float().mean() > 0.999
    assert (got.metal - ref.metal).abs().max() < 1e-3
