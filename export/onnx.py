"""Generic ONNX export with a parity check against torch.

:func:`export_onnx` exports any ``nn.Module`` (several inputs and outputs, named dynamic axes), checks the
graph with ``onnx.checker``, stores metadata in ``model.metadata_props``, writes one self-contained file
atomically, then runs ONNX Runtime on the example inputs *and* on fresh random inputs with another batch size
and compares every output with torch. Above ``tol`` it raises :class:`OnnxParityError` with the measured
error; the file is still written, so it can be inspected.

Exporter choice (torch 2.13): the ``torch.export``-based exporter (``dynamo=True``) emits opset 18+ and its
down-conversion to 17 fails on common graphs (``Resize``/``Reduce*`` axes), so ``exporter="auto"`` uses it
for ``opset >= 18`` and the TorchScript exporter (``dynamo=False``, deprecated but fully working) for
``opset <= 17``. Either way the written file's opset is checked to be the one asked for.

Example:
    >>> net = torch.nn.Sequential(torch.nn.Linear(4, 3))
    >>> rep = export_onnx(net, (torch.rand(2, 4),), "/tmp/net.onnx", ["x"], ["y"])  # doctest: +SKIP
    >>> rep.max_abs_err < 1e-5  # doctest: +SKIP
    True
"""

from __future__ import annotations

import contextlib
import io
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Mapping, Sequence

import numpy as np
import torch

from toolkit._checks import ConfigError, DarsError
from toolkit.io import atomic_write

__all__ = ["OnnxExportReport", "OnnxParityError", "export_onnx", "export_segmenter_onnx", "run_onnx", "read_onnx_metadata"]


class OnnxParityError(DarsError):
    """ONNX Runtime and torch disagree by more than the tolerance (the message gives the measured error)."""

    def __init__(self, message: str, max_abs_err: float, path: Path):
        super().__init__(message)
        self.max_abs_err = max_abs_err
        self.path = path


@dataclass(frozen=True)
class OnnxExportReport:
    """What :func:`export_onnx` wrote and measured.

    Attributes:
        path: the ``.onnx`` file (self-contained: weights inside).
        opset: default-domain opset of the written graph.
        exporter: ``"dynamo"`` or ``"legacy"`` (TorchScript).
        max_abs_err: largest |onnxruntime - torch| over every output and every checked input set.
        errors: per check name (``"example"``, ``"random_b<N>"``) and output name, the max abs error.
        inputs_checked: the input shapes of each check, by check name.
        file_size: bytes on disk.
        metadata: what was stored in ``metadata_props``.
    """

    path: Path
    opset: int
    exporter: str
    max_abs_err: float
    errors: dict[str, dict[str, float]]
    inputs_checked: dict[str, list[list[int]]]
    file_size: int
    metadata: dict[str, str] = field(default_factory=dict)


def _as_numpy(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().contiguous().numpy()


def _random_like(x: torch.Tensor, batch: int, generator: torch.Generator) -> torch.Tensor:
    shape = (batch,) + tuple(x.shape[1:])
    if x.dtype == torch.bool:
        return torch.rand(shape, generator=generator) > 0.5
    if not x.is_floating_point():
        lo, hi = int(x.min()) if x.numel() else 0, int(x.max()) + 1 if x.numel() else 2
        return torch.randint(lo, max(hi, lo + 1), shape, generator=generator, dtype=x.dtype)
    lo, hi = (float(x.min()), float(x.max())) if x.numel() else (0.0, 1.0)
    if hi <= lo:
        lo, hi = lo - 0.5, lo + 0.5
    return (torch.rand(shape, generator=generator, dtype=torch.float64) * (hi - lo) + lo).to(x.dtype)


def run_onnx(path: str | os.PathLike, inputs: Mapping[str, np.ndarray | torch.Tensor]) -> dict[str, np.ndarray]:
    """Run an ONNX file with ONNX Runtime on CPU; returns ``{output name: array}``.

    Raises:
        DarsError: the file cannot be loaded or an input name is not in the graph.
    """
    import onnxruntime as ort

    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        raise DarsError(f"ONNX Runtime could not load {path}: {e}") from e
    names = [i.name for i in sess.get_inputs()]
    missing = [n for n in names if n not in inputs]
    if missing:
        raise DarsError(f"{path}: inputs {missing} not given (the graph takes {names})")
    feed = {n: _as_numpy(v) if isinstance(v, torch.Tensor) else np.asarray(v) for n, v in inputs.items() if n in names}
    outs = sess.run(None, feed)
    return {o.name: v for o, v in zip(sess.get_outputs(), outs)}


def read_onnx_metadata(path: str | os.PathLike) -> dict[str, str]:
    """The ``metadata_props`` of an ONNX file as a dict (graph weights are not loaded)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in model.metadata_props}


def _torch_export(module, example_inputs, buf_path: str, input_names, output_names, opset, dynamic_axes, exporter):
    kw = dict(input_names=list(input_names), output_names=list(output_names), opset_version=opset,
              external_data=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if exporter == "dynamo":
            # dynamo=True accepts the TorchScript-style dynamic_axes mapping and converts it.
            with contextlib.redirect_stdout(io.StringIO()):
                torch.onnx.export(module, example_inputs, buf_path, dynamo=True, dynamic_axes=dynamic_axes or None,
                                  **kw)
        else:
            torch.onnx.export(module, example_inputs, buf_path, dynamo=False, dynamic_axes=dynamic_axes or None,
                              do_constant_folding=True, **kw)


def export_onnx(
    module: torch.nn.Module,
    example_inputs: tuple[torch.Tensor, ...],
    path: str | os.PathLike,
    input_names: Sequence[str],
    output_names: Sequence[str],
    dynamic_batch: bool = True,
    opset: int = 17,
    metadata: Mapping[str, str] | None = None,
    *,
    dynamic_axes: Mapping[str, Mapping[int, str]] | None = None,
    tol: float = 1e-4,
    random_batch: int | None = None,
    exporter: Literal["auto", "dynamo", "legacy"] = "auto",
    seed: int = 0,
) -> OnnxExportReport:
    """Export ``module`` to one ONNX file and check ONNX Runtime against torch.

    The module is exported in eval mode on CPU (its mode and device are restored afterwards). With
    ``dynamic_batch`` axis 0 of every input and output is a symbolic ``batch`` dimension, so the parity
    check also runs on random inputs with batch size ``random_batch`` (default: example batch + 3). Random
    inputs are uniform over each example input's value range (integers: over its range, bools: fair coins).

    Args:
        module: the network; ``module(*example_inputs)`` returns a tensor or a tuple of tensors.
        example_inputs: tensors, one per graph input, in ``forward`` order.
        path: where to write the ``.onnx`` file (parent folders are created; written atomically).
        input_names: one name per input.
        output_names: one name per output.
        dynamic_batch: make axis 0 of every input and output symbolic.
        opset: ONNX default-domain opset (17 is widely deployable; >= 18 uses the dynamo exporter).
        metadata: string key/values stored in ``model.metadata_props`` (e.g. ``{"dars.kind": "segmenter"}``).
        dynamic_axes: more symbolic axes, ``{name: {axis: symbol}}``, merged over the batch axes.
        tol: largest accepted max abs difference between ONNX Runtime and torch.
        random_batch: batch size of the random-input check (``None``: example batch + 3; 0 skips the check).
        exporter: ``"auto"`` (legacy for opset <= 17, dynamo above), ``"dynamo"`` or ``"legacy"``.
        seed: seed of the random inputs.

    Returns:
        :class:`OnnxExportReport` with the measured errors.

    Raises:
        ConfigError: names/inputs disagree, or the exporter cannot write the requested opset.
        OnnxParityError: ONNX Runtime differs from torch by more than ``tol`` (the file is kept).
    """
    import onnx

    path = Path(path)
    if not isinstance(example_inputs, tuple) or not all(isinstance(x, torch.Tensor) for x in example_inputs):
        raise ConfigError("example_inputs must be a tuple of tensors (wrap a single tensor as (x,))")
    if len(input_names) != len(example_inputs):
        raise ConfigError(f"{len(input_names)} input_names {list(input_names)} for {len(example_inputs)} example inputs")
    if exporter not in ("auto", "dynamo", "legacy"):
        raise ConfigError(f"exporter={exporter!r} is not valid: choose 'auto', 'dynamo' or 'legacy'")
    if exporter == "auto":
        exporter = "legacy" if opset <= 17 else "dynamo"
    meta = {str(k): str(v) for k, v in (metadata or {}).items()}

    axes: dict[str, dict[int, str]] = {}
    if dynamic_batch:
        for n in list(input_names) + list(output_names):
            axes[n] = {0: "batch"}
    for n, d in (dynamic_axes or {}).items():
        if n not in input_names and n not in output_names:
            raise ConfigError(f"dynamic_axes names '{n}', which is neither an input {list(input_names)} "
                              f"nor an output {list(output_names)}")
        axes.setdefault(n, {}).update({int(a): str(s) for a, s in d.items()})

    was_training = module.training
    try:
        first_param = next(iter(module.parameters()), None)
    except Exception:
        first_param = None
    device = first_param.device if first_param is not None else torch.device("cpu")
    module = module.eval().cpu()
    cpu_inputs = tuple(x.detach().cpu() for x in example_inputs)
    try:
        with torch.no_grad():
            ref = module(*cpu_inputs)
        ref_t = (ref,) if isinstance(ref, torch.Tensor) else tuple(ref)
        if len(ref_t) != len(output_names):
            raise ConfigError(f"the module returns {len(ref_t)} outputs but output_names has {len(output_names)}: "
                              f"{list(output_names)}")

        path.parent.mkdir(parents=True, exist_ok=True)
        tmp_dir = path.parent
        import tempfile

        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".export.onnx", dir=tmp_dir)
        os.close(fd)
        try:
            _torch_export(module, cpu_inputs, tmp, input_names, output_names, opset, axes, exporter)
            model = onnx.load(tmp)
        finally:
            for p in (tmp, tmp + ".data"):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(p)
        got_opset = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), None)
        if got_opset != opset:
            raise ConfigError(f"the {exporter} exporter wrote opset {got_opset}, not the requested {opset}; "
                              "use exporter='legacy' for opset <= 17 or ask for opset >= 18")
        for k, v in meta.items():
            entry = next((p for p in model.metadata_props if p.key == k), None)
            if entry is None:
                entry = model.metadata_props.add()
                entry.key = k
            entry.value = v
        onnx.checker.check_model(model, full_check=True)
        data = model.SerializeToString()
        with atomic_write(path) as f:
            f.write(data)

        # ---- parity: example inputs, then random inputs with another batch size
        checks: dict[str, tuple[torch.Tensor, ...]] = {"example": cpu_inputs}
        if dynamic_batch and random_batch != 0:
            b = random_batch if random_batch is not None else int(cpu_inputs[0].shape[0]) + 3
            g = torch.Generator().manual_seed(seed)
            checks[f"random_b{b}"] = tuple(_random_like(x, b, g) for x in cpu_inputs)
        errors: dict[str, dict[str, float]] = {}
        shapes: dict[str, list[list[int]]] = {}
        for name, xs in checks.items():
            with torch.no_grad():
                r = module(*xs)
            r = (r,) if isinstance(r, torch.Tensor) else tuple(r)
            got = run_onnx(path, dict(zip(input_names, xs)))
            errors[name] = {}
            for oname, t in zip(output_names, r):
                o = got[oname]
                tn = _as_numpy(t)
                if o.shape != tn.shape:
                    raise OnnxParityError(f"{path}: output '{oname}' has shape {list(o.shape)} in ONNX Runtime but "
                                          f"{list(tn.shape)} in torch (check '{name}')", float("inf"), path)
                err = float(np.abs(o.astype(np.float64) - tn.astype(np.float64)).max()) if o.size else 0.0
                errors[name][oname] = err
            shapes[name] = [list(x.shape) for x in xs]
        max_err = max((e for d in errors.values() for e in d.values()), default=0.0)
        if not np.isfinite(max_err) or max_err > tol:
            raise OnnxParityError(f"{path}: ONNX Runtime differs from torch by {max_err:.3g} > tol {tol:g} "
                                  f"(per check and output: {errors})", max_err, path)
    finally:
        module.train(was_training)
        module.to(device)
    return OnnxExportReport(path=path, opset=int(got_opset), exporter=exporter, max_abs_err=max_err, errors=errors,
                            inputs_checked=shapes, file_size=path.stat().st_size, metadata=meta)


def export_segmenter_onnx(model: torch.nn.Module, path: str | os.PathLike, image_size: tuple[int, int] = (128, 128),
                          opset: int = 17, tol: float = 1e-4) -> OnnxExportReport:
    """Export :class:`toolkit.segment.Segmenter` with dynamic batch, height and width.

    The file follows the ``onnx`` backend contract of :mod:`toolkit.segment`: input ``images`` float32
    N x 3 x H x W RGB (sRGB) in [0, 1], output ``logits`` N x 7 x H x W (then ``metal`` N x 1 x H x W, the metal
    probability, for a network with a metal channel); metadata ``dars.kind=segmenter``, ``dars.work_size``,
    ``dars.classes``, ``dars.normalize=none``.

    Args:
        model: the segmenter.
        path: output ``.onnx``.
        image_size: (H, W) of the example inputs used for tracing and the parity check.
        opset: ONNX opset.
        tol: parity tolerance (max abs logit difference).

    Returns:
        :class:`OnnxExportReport`.
    """
    from toolkit.scene import SEMANTIC_CLASSES

    from toolkit.segment import METAL_THRESHOLD, SegmenterExport

    g = torch.Generator().manual_seed(0)
    example = torch.rand(2, 3, int(image_size[0]), int(image_size[1]), generator=g)
    cfg = getattr(model, "cfg", None)
    metal = bool(getattr(cfg, "metal", False))
    meta = {
        "dars.kind": "segmenter",
        "dars.classes": ",".join(SEMANTIC_CLASSES),
        "dars.normalize": "none",
        "dars.work_size": str(int(getattr(cfg, "work_size", 0) or 0)),
        "dars.input": "images: float32 N x 3 x H x W, RGB, sRGB-encoded, [0, 1]; resize so the short side is "
                      "dars.work_size (0: any size) and resize the outputs back",
        "dars.output": "logits: float32 N x 7 x H x W (argmax = class id)"
                       + (f"; metal: float32 N x 1 x H x W, probability of metal (mask: > {METAL_THRESHOLD})" if metal else ""),
    }
    outs = ["logits", "metal"] if metal else ["logits"]
    axes = {"images": {2: "height", 3: "width"}, **{o: {2: "height", 3: "width"} for o in outs}}
    module = SegmenterExport(model) if hasattr(model, "split") else model
    return export_onnx(module, (example,), path, ["images"], outs, dynamic_batch=True, opset=opset,
                       metadata=meta, dynamic_axes=axes, tol=tol)
