"""ONNX Runtime inference for devices — no torch (SPEC stage 14).

Reads a directory written by :func:`export.field_onnx.export_onnx_models` (``field.onnx``, ``occupancy.npz``,
``background.npz``, ``metadata.json``, optionally ``segment.onnx`` / ``light.onnx`` and reduced-precision
variants ``field_fp16.onnx`` / ``field_int8.onnx``) and renders novel views with numpy + ONNX Runtime. Only
numpy, onnxruntime and (for photos) Pillow are imported: ``import export.infer`` never loads torch. Cameras are
:class:`toolkit.pinhole.PinholeCamera` (numpy; the viewers' camera type too).

The renderer is the algorithm of :func:`toolkit.pipeline.render_image` with the run's ``render_sampler`` and the
run's shading (per sample, or once per ray for a run trained with ``deferred`` shading, whose bundle has
``heads.onnx``), re-implemented in numpy with the same float32 arithmetic:

1. rays through pixel centres ``(u + 0.5, v + 0.5)`` (OpenGL camera: x right, y up, looking down −z), clipped
   by a slab test (entry clamped to 0.05 m) to the scene box — or, for a *contracted* (unbounded) field, to the
   box grown ``far_radius`` times about its centre, where the field ends (:mod:`toolkit.space`) — and to the
   scene's near/far when it has them;
2. ``n_coarse`` strata in [near, far] (``perturb=False``): evenly spaced in metres (bounded), or equal in
   *contracted* arc length (:func:`contracted_edges`, the mirror of :func:`toolkit.space.contracted_edges`);
   their midpoints kept where the occupancy grid (``occupancy.npz``) is occupied — a grid over the scene box, or
   over contracted space [−2, 2]³ (points are contracted first; beyond the far radius is empty);
3. the field at the kept coarse samples; their compositing weights form the hierarchical proposal, from which
   ``n_fine`` samples per ray are drawn by deterministic inverse-CDF sampling (CDF slice centres);
4. the union, sorted along each ray with Voronoi intervals (at most one coarse step; contracted: at most the
   sample's own stratum, whose lengths differ), composited as packed samples: ``α = 1 − exp(−σ δ)``,
   ``w = T α``; per-sample PBR-shaded colour (the graph's ``colour``) summed with ``w``, plus ``(1 − opacity)``
   × the background (``background.npz``: constant colour or lat-long map). A ``deferred`` run asks the field
   graph for ``density`` and ``feature`` only, composites the feature
   h̄ = Σ w h / Σ w per ray and runs ``heads.onnx`` once per ray: rgb = opacity · colour + (1 − opacity) × the
   background.

The field graph itself contracts its input points and rescales σ (density per contracted length beyond the
box, zero beyond the far radius), so ``field.onnx`` is queried with world points in both cases. The space a
bundle lives in is ``metadata.json["space"]`` (``aabb``, ``contraction``, ``far_radius``, ``edge_candidates``);
a bundle without it (exported before unbounded scenes) is bounded.

DARS along-ray density (SPEC stage 7 part 3) needs the training views' W maps and is a training/render-time
prior: it is *not* part of the device path, which uses the hierarchical proposal only (the export report gives
both the torch render with and without it).

Example:
    >>> model = load_model("out/onnx")                                           # doctest: +SKIP
    >>> cam = camera_from_transforms("samples/gallery/transforms_test.json", 0)  # doctest: +SKIP
    >>> img = render_view(model, cam)["rgb"]       # float32 [H, W, 3] linear    # doctest: +SKIP
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from toolkit.pinhole import PinholeCamera

__all__ = ["InferError", "PinholeCamera", "FieldModel", "RenderSettings", "SceneSpace", "load_model", "render_view",
           "render_rays", "generate_camera_rays", "contract", "box_radius", "contracted_edges",
           "camera_from_transforms", "poses_for_photos", "read_photo", "infer_segment", "infer_light",
           "camera_heading_np", "geometry_session", "FIELD_FILES", "GEOMETRY_OUTPUTS", "REQUIRED_FILES"]

FIELD_FILES = {"fp32": "field.onnx", "fp16": "field_fp16.onnx", "int8": "field_int8.onnx"}
"""Field graph file per precision."""
GEOMETRY_OUTPUTS = ("density", "feature")
"""What a render shaded once per ray asks the field at each sample (:func:`geometry_session`)."""
REQUIRED_FILES = ("metadata.json", "field.onnx", "occupancy.npz", "background.npz")
"""What a directory needs to render (``export_onnx_models`` writes all of them)."""
SEMANTIC_CLASSES = ("painting", "frame", "display", "base", "wall", "floor", "other")


class InferError(ValueError):
    """Bad input to the device inference path (missing files, wrong shapes); the message says what to do."""


# ====================================================================== space (numpy mirror of toolkit.space)
@dataclass(frozen=True)
class SceneSpace:
    """The space an exported field lives in (numpy mirror of :class:`toolkit.space.SceneSpace`).

    Attributes:
        aabb: float32 [2, 3] the scene box, metres.
        contraction: True: unbounded (contracted beyond the box, the field ends at ``far_radius``); False: only
            the box exists.
        far_radius: ‖n‖∞ (box half-sizes, n = (x − centre) / half-size) at which rays and the field end.
        edge_candidates: resolution of the contracted arc-length table of :func:`contracted_edges`.
    """

    aabb: np.ndarray
    contraction: bool = False
    far_radius: float = 64.0
    edge_candidates: int = 96

    @classmethod
    def from_metadata(cls, metadata: dict) -> "SceneSpace":
        """From ``metadata.json`` (its ``space``; a bundle without one is bounded by its ``aabb``)."""
        sp = metadata.get("space")
        if sp is None:
            return cls(np.asarray(metadata["aabb"], np.float32).reshape(2, 3))
        return cls(np.asarray(sp["aabb"], np.float32).reshape(2, 3), bool(sp["contraction"]),
                   float(sp["far_radius"]), int(sp.get("edge_candidates", 96)))

    @property
    def ray_box(self) -> np.ndarray:
        """float32 [2, 3] the box rays are clipped to: the scene box, or (contracted) the far-radius box."""
        aabb = np.asarray(self.aabb, np.float32)
        if not self.contraction:
            return aabb
        c, h = np.float32(0.5) * (aabb[0] + aabb[1]), np.float32(0.5) * (aabb[1] - aabb[0])
        fr = np.float32(self.far_radius)
        return np.stack([c - fr * h, c + fr * h]).astype(np.float32)


def box_radius(points: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    """float32 [N] ‖n‖∞ of world points [N, 3] normalised to the box ``aabb`` [2, 3] (≤ 1 inside the box;
    :func:`toolkit.space.box_radius`)."""
    f32 = np.float32
    centre = f32(0.5) * (aabb[0] + aabb[1])
    half = f32(0.5) * (aabb[1] - aabb[0])
    return np.abs((points - centre) / half).max(-1)


def contract(points: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    """Scene contraction of world points [..., 3] into [-2, 2]³ (float32; :func:`toolkit.space.contract`)."""
    f32 = np.float32
    centre = f32(0.5) * (aabb[0] + aabb[1])
    half = f32(0.5) * (aabb[1] - aabb[0])
    n = (points - centre) / half
    r = np.abs(n).max(-1, keepdims=True)
    rs = np.maximum(r, f32(1.0))
    return np.where(r > 1.0, (f32(2.0) - f32(1.0) / rs) * n / rs, n).astype(f32)


def _pow_f32(base: np.ndarray, exponent: np.ndarray) -> np.ndarray:
    """float32 ``base ** exponent`` rounded from float64 (torch's vectorised float32 pow is within 1 ulp of it)."""
    return (base.astype(np.float64) ** exponent.astype(np.float64)).astype(np.float32)


def _norm3(v: np.ndarray) -> np.ndarray:
    """float32 ‖v‖ over a last axis of 3 in the order torch's CPU norm kernel takes (fused multiply-adds, emulated
    in float64: the products are exact there)."""
    f64 = np.float64
    acc = np.zeros(v.shape[:-1], np.float32)
    for i in range(v.shape[-1]):
        x = v[..., i].astype(f64)
        acc = (x * x + acc.astype(f64)).astype(np.float32)
    return np.sqrt(acc)


def contracted_edges(origins: np.ndarray, directions: np.ndarray, near: np.ndarray, far: np.ndarray,
                     aabb: np.ndarray, n: int, n_candidates: int = 96) -> np.ndarray:
    """float32 [R, n + 1] stratum edges uniform in contracted arc length (mirror of
    :func:`toolkit.space.contracted_edges` with ``perturb=False``).

    The contracted path length of each ray is tabulated at ``n_candidates`` + 1 depths spaced geometrically from
    ``near`` to ``far``; the ``n`` strata are its equal parts (linear interpolation in the table). Rays with
    ``far <= near`` get zero-length strata. Same float32 operations as torch, but not bit-exact: torch's
    vectorised float32 ``pow`` (SLEEF, within 1 ulp) and ``linspace`` round a few table depths differently, so
    edges agree to ~1e-6 relative (most of them exactly).

    Args:
        origins, directions: float32 [R, 3] rays (unit directions).
        near, far: float32 [R] bounds (metres).
        aabb: float32 [2, 3] scene box.
        n: strata per ray.
        n_candidates: resolution of the arc-length table (the exporting toolkit's, ``metadata["space"]``).
    """
    f32 = np.float32
    R, K = origins.shape[0], int(n_candidates)
    aabb = np.asarray(aabb, f32)
    far = np.maximum(far, near)
    lo = np.maximum(near, f32(1e-4))
    ratio = np.maximum(np.maximum(far, f32(1e-4)) / lo, f32(1.0))
    t = lo[:, None] * _pow_f32(ratio[:, None], _torch_linspace01(K)[None])  # [R, K+1] geometric
    t = np.where(far[:, None] > near[:, None], t, near[:, None]).astype(f32)
    pts = origins[:, None, :] + t[..., None] * directions[:, None, :]
    c = contract(pts, aabb)
    seg = _norm3(c[:, 1:] - c[:, :-1])
    L = np.concatenate([np.zeros((R, 1), f32), np.cumsum(seg.astype(np.float64), -1).astype(f32)], -1)
    total = np.maximum(L[:, -1:], f32(1e-12))
    target = _torch_linspace01(n)[None] * total  # [R, n+1]
    rows = np.repeat(np.arange(R), n + 1)
    k = _row_searchsorted(L, rows, target.ravel()).reshape(R, n + 1)  # searchsorted(L, target, right=True)
    k = np.clip(k, 1, K) - 1
    L0, L1 = np.take_along_axis(L, k, 1), np.take_along_axis(L, k + 1, 1)
    t0, t1 = np.take_along_axis(t, k, 1), np.take_along_axis(t, k + 1, 1)
    frac = np.clip((target - L0) / np.maximum(L1 - L0, f32(1e-12)), f32(0.0), f32(1.0))
    edges = t0 + frac * (t1 - t0)
    edges = np.minimum(np.maximum(edges, near[:, None]), far[:, None])
    return np.maximum.accumulate(edges, axis=-1).astype(f32)


def stratified_edges(origins: np.ndarray, directions: np.ndarray, near: np.ndarray, far: np.ndarray,
                     space: SceneSpace, n: int) -> np.ndarray:
    """float32 [R, n + 1] deterministic stratum edges (mirror of :func:`toolkit.sampling.stratified_edges` with
    ``perturb=False``): equal in contracted arc length for a contracted space, else equal in metres."""
    if space.contraction:
        return contracted_edges(origins, directions, near, far, space.aabb, n, space.edge_candidates)
    far_m = np.maximum(far, near)
    return (near[:, None] + (far_m - near)[:, None] * _torch_linspace01(n)[None]).astype(np.float32)


# ====================================================================== loading
@dataclass(frozen=True)
class RenderSettings:
    """Sampler of the device renderer (defaults: the exported run's ``render_sampler``, read from metadata)."""

    n_coarse: int
    """Stratified samples per ray."""
    n_fine: int
    """Hierarchical samples per ray (0: coarse only)."""
    near_min: float = 0.05
    """Rays starting inside the box start here (metres), as :func:`toolkit.scene.generate_rays`."""
    chunk: int = 8192
    """Rays per batch (memory bound; results do not depend on it)."""


class FieldModel:
    """An exported run loaded for inference: the field session, occupancy grid, background and metadata.

    Use :func:`load_model` to build one.

    Attributes:
        path: the export directory.
        metadata: ``metadata.json`` as a dict.
        precision: which field graph is loaded (``fp32``, ``fp16``, ``int8``).
        shading: ``pbr`` (decomposed) or ``radiance`` (standard NeRF run).
        sh: float32 [9, 3] the run's SH light ``l_env`` (SPEC convention), the default ``sh`` input.
        aabb: float32 [2, 3] scene box.
        space: the :class:`SceneSpace` (box, contraction, far radius) the field and its rays live in.
        occupancy_mask: bool [R^3] occupied cells (x-major: index = i R² + j R + k).
        occupancy_resolution: R.
        occupancy_contraction: the grid covers contracted space [-2, 2]³ (else the box ``occupancy_aabb``).
        background: ``{"mode": ..., "colour": [3] or "env_map": [h, w, 3]}`` linear radiance.
    """

    def __init__(self, path: Path, metadata: dict, session, precision: str, occupancy: dict, background: dict,
                 heads_session=None, geometry_session=None):
        self.path = path
        self.heads_session = heads_session
        """``heads.onnx`` of a run shaded once per ray (``deferred``), else None."""
        self.geometry_session = geometry_session
        """The field graph cut to ``points -> density, feature`` (:func:`geometry_session`), or None: what a
        ``deferred`` render asks per sample, without the heads ONNX Runtime would otherwise run there too."""
        self.metadata = metadata
        self.session = session
        self.precision = precision
        self.shading = metadata["shading"]
        self.sh = np.asarray(metadata["l_env"], np.float32).reshape(9, 3)
        self.aabb = np.asarray(metadata["aabb"], np.float32).reshape(2, 3)
        self.space = SceneSpace.from_metadata(metadata)
        self.occupancy_resolution = int(occupancy["resolution"])
        self.occupancy_aabb = np.asarray(occupancy["aabb"], np.float32).reshape(2, 3)
        self.occupancy_mask = occupancy["mask"]
        self.occupancy_contraction = bool(occupancy.get("contraction", False))
        self.occupancy_far_radius = float(occupancy.get("far_radius", self.space.far_radius))
        self.background = background
        self.input_names = [i.name for i in session.get_inputs()]
        self.output_names = [o.name for o in session.get_outputs()]
        s = metadata["render_sampler"]
        self.settings = RenderSettings(n_coarse=int(s["n_coarse"]), n_fine=int(s["n_fine"]),
                                       near_min=float(metadata.get("near_min", 0.05)))

    # ------------------------------------------------------------------ field
    @property
    def deferred(self) -> bool:
        """The run shades once per ray: the renderer composites the field's ``feature`` and runs ``heads.onnx``."""
        return self.heads_session is not None

    def query(self, points: np.ndarray, view_dirs: np.ndarray, sh: np.ndarray | None = None,
              chunk: int = 65536, outputs: Sequence[str] | None = None,
              out: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """Run the field graph on points (chunked).

        Args:
            points: float [N, 3] world positions, metres.
            view_dirs: float [N, 3] unit ray directions (camera -> point).
            sh: float [9, 3] global SH light (default: the run's ``l_env``); ignored by a ``radiance`` field.
            chunk: points per ONNX Runtime call.
            outputs: the outputs to return (default: all).
            out: float32 arrays [N, ...] per output to write into (returned), e.g. views of one larger buffer.

        Returns:
            ``{output name: float32 array [N, ...]}`` (see ``metadata["field"]["outputs"]``).
        """
        points = np.ascontiguousarray(points, np.float32)
        view_dirs = np.ascontiguousarray(view_dirs, np.float32)
        if points.ndim != 2 or points.shape[1] != 3 or view_dirs.shape != points.shape:
            raise InferError(f"points {list(points.shape)} and view_dirs {list(view_dirs.shape)} must both be [N, 3]")
        if self.geometry_session is not None and outputs is not None and set(outputs) <= set(GEOMETRY_OUTPUTS):
            return _run_chunked(self.geometry_session, self.metadata["field"]["outputs"], {"points": points},
                                self.sh if sh is None else sh, chunk, outputs, out)
        return _run_chunked(self.session, self.metadata["field"]["outputs"], {"points": points, "view_dirs": view_dirs},
                            self.sh if sh is None else sh, chunk, outputs, out)

    def output_buffers(self, n: int, outputs: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """Uninitialised float32 arrays [n, ...] for the field's ``outputs`` (default: all), for :meth:`query`'s
        ``out``."""
        names = [o.name for o in self.session.get_outputs()] if outputs is None else list(outputs)
        return _output_arrays(self.metadata["field"]["outputs"], names, n)

    def query_heads(self, features: np.ndarray, view_dirs: np.ndarray, sh: np.ndarray | None = None,
                    chunk: int = 65536) -> dict[str, np.ndarray]:
        """Run ``heads.onnx`` (a ``deferred`` run) on composited ray features [R, D] and ray directions [R, 3]."""
        if self.heads_session is None:
            raise InferError(f"{self.path}: this bundle has no heads.onnx (the run shades per sample)")
        return _run_chunked(self.heads_session, self.metadata["heads"]["outputs"],
                            {"feature": features, "view_dirs": view_dirs}, self.sh if sh is None else sh, chunk)

    # ------------------------------------------------------------------ occupancy and background
    def occupied(self, points: np.ndarray) -> np.ndarray:
        """bool [N]: inside the modelled space and in an occupied cell (as
        :meth:`toolkit.sampling.OccupancyGrid.occupied`): bounded, the grid spans the box; contracted, points are
        contracted first, the grid spans [-2, 2]³ and beyond the far radius is empty."""
        points = np.asarray(points, np.float32)
        if self.occupancy_contraction:
            lo, hi = np.full(3, -2.0, np.float32), np.full(3, 2.0, np.float32)
            u = (contract(points, self.occupancy_aabb) - lo) / (hi - lo)
            inside = box_radius(points, self.occupancy_aabb) <= self.occupancy_far_radius
        else:
            lo, hi = self.occupancy_aabb[0], self.occupancy_aabb[1]
            u = (points - lo) / (hi - lo)
            inside = ((u >= 0) & (u <= 1)).all(-1)
        r = self.occupancy_resolution
        ijk = np.clip((u * np.float32(r)).astype(np.int64), 0, r - 1)
        return self.occupancy_mask[ijk[:, 0] * r * r + ijk[:, 1] * r + ijk[:, 2]] & inside

    def background_radiance(self, directions: np.ndarray) -> np.ndarray:
        """float32 [R, 3] background radiance for unit directions (as :class:`toolkit.pipeline.Background`)."""
        bg = self.background
        if bg["mode"] != "env":
            return np.broadcast_to(np.asarray(bg["colour"], np.float32), (directions.shape[0], 3)).copy()
        env = bg["env_map"]
        h, w, _ = env.shape
        z = np.clip(directions[:, 2], -1.0, 1.0)
        theta = np.arccos(z)
        phi = np.arctan2(directions[:, 0], directions[:, 1]) % np.float32(2 * math.pi)
        r = np.clip(theta / np.float32(math.pi) * h - 0.5, 0, h - 1)
        c = phi / np.float32(2 * math.pi) * w - 0.5
        r0 = np.minimum(np.floor(r), h - 2).astype(np.int64) if h > 1 else r.astype(np.int64)
        fr = (r - r0)[:, None]
        c0f = np.floor(c)
        fc = (c - c0f)[:, None]
        c0 = c0f.astype(np.int64) % w
        c1 = (c0 + 1) % w
        r1 = np.minimum(r0 + 1, h - 1)
        flat = env.reshape(-1, 3)
        return (flat[r0 * w + c0] * ((1 - fr) * (1 - fc)) + flat[r0 * w + c1] * ((1 - fr) * fc)
                + flat[r1 * w + c0] * (fr * (1 - fc)) + flat[r1 * w + c1] * (fr * fc)).astype(np.float32)


def _output_arrays(shapes: dict, names: Sequence[str], n: int) -> dict[str, np.ndarray]:
    """Uninitialised float32 arrays [n, ...] for the outputs ``names`` of a graph whose output shapes (``N`` first,
    from ``metadata.json``) are ``shapes``."""
    return {k: np.empty([n] + [int(d) for d in shapes[k][1:]], np.float32) for k in names}


def _run_chunked(session, shapes: dict, inputs: dict[str, np.ndarray], sh: np.ndarray, chunk: int,
                 outputs: Sequence[str] | None = None, out: dict[str, np.ndarray] | None = None
                 ) -> dict[str, np.ndarray]:
    """Run an ONNX session on row-chunked ``inputs`` (float [N, ...] each, the same N), feeding ``sh`` [9, 3] when
    the graph takes it. ``shapes``: the graph's output shapes (``metadata.json``), for an empty batch. ``out``:
    float32 arrays [N, ...] per output to fill (returned) instead of new ones."""
    names = [o.name for o in session.get_outputs()] if outputs is None else list(outputs)
    inputs = {k: np.ascontiguousarray(v, np.float32) for k, v in inputs.items()}
    n = next(iter(inputs.values())).shape[0]
    bad = {k: list(v.shape) for k, v in inputs.items() if v.ndim != 2 or v.shape[0] != n}
    if bad:
        raise InferError(f"inputs {bad} must be 2-D with one row each")
    if out is not None:
        bad = {k: list(out[k].shape) if k in out else None for k in names
               if k not in out or out[k].shape[0] != n or out[k].dtype != np.float32}
        if bad:
            raise InferError(f"out {bad} must hold float32 arrays of {n} rows for every output")
    if n == 0:
        return {k: out[k] for k in names} if out is not None else _output_arrays(shapes, names, 0)
    feed_sh = np.ascontiguousarray(sh, np.float32)
    if feed_sh.shape != (9, 3):
        raise InferError(f"sh must be [9, 3] (SPEC order, linear radiance), got {list(feed_sh.shape)}")
    takes_sh = any(i.name == "sh" for i in session.get_inputs())
    parts: dict[str, list[np.ndarray]] = {k: [] for k in names}
    for i in range(0, n, chunk):
        feed = {k: v[i:i + chunk] for k, v in inputs.items()}
        if takes_sh:
            feed["sh"] = feed_sh
        for k, v in zip(names, session.run(names, feed)):
            if out is None:
                parts[k].append(v)
            else:
                out[k][i:i + v.shape[0]] = v
    if out is not None:
        return {k: out[k] for k in names}
    return {k: np.concatenate(v).astype(np.float32, copy=False) for k, v in parts.items()}


def _check_dir(path: Path, needed: Sequence[str]) -> None:
    if not path.is_dir():
        raise InferError(f"export directory not found: {path} (create it with `dars export-onnx RUN --out DIR`)")
    missing = [f for f in needed if not (path / f).is_file()]
    if missing:
        raise InferError(f"{path} is missing {', '.join(missing)}: it is not a complete `dars export-onnx` output; "
                         "re-run `dars export-onnx RUN --out DIR`")


def make_session(path: str | os.PathLike | bytes, threads: int | None = None):
    """An ONNX Runtime CPU session with ``threads`` intra-op threads (None: ORT's default); ``path`` may also be a
    serialised model (bytes)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    try:
        return ort.InferenceSession(path if isinstance(path, bytes) else str(path), sess_options=opts,
                                    providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        what = "a serialised model" if isinstance(path, bytes) else path
        raise InferError(f"ONNX Runtime could not load {what}: {e}") from e


def geometry_session(path: str | os.PathLike, threads: int | None = None):
    """A session of the field graph at ``path`` cut to ``points -> density, feature`` (:data:`GEOMETRY_OUTPUTS`),
    or None where the ``onnx`` package is not installed or the graph does not cut there.

    ONNX Runtime runs a whole graph whatever outputs are asked for, so a render shaded once per ray, which needs
    only density and feature at its samples, would also run every head there. The cut graph is the same nodes, so it
    gives the same values; it is built in memory from the shipped file, so the bundle carries one copy of the hash
    table. Without ``onnx`` (a device with ONNX Runtime alone) the renderer uses the whole graph, slower only.
    """
    try:
        import onnx
        from onnx.utils import Extractor
    except ImportError:
        return None
    try:
        cut = Extractor(onnx.load(str(path))).extract_model(["points"], list(GEOMETRY_OUTPUTS))
        return make_session(cut.SerializeToString(), threads)
    except Exception:  # noqa: BLE001 - a graph that does not cut there (an older export): use the whole graph
        return None


def load_model(path: str | os.PathLike, precision: str = "fp32", threads: int | None = None) -> FieldModel:
    """Load an export directory for rendering.

    Args:
        path: directory written by ``dars export-onnx``.
        precision: ``fp32`` (``field.onnx``), ``fp16`` (``field_fp16.onnx``) or ``int8`` (``field_int8.onnx``).
        threads: ONNX Runtime intra-op threads (None: its default, all cores).

    Raises:
        InferError: the directory or one of its files is missing or unreadable.
    """
    path = Path(path)
    if precision not in FIELD_FILES:
        raise InferError(f"precision={precision!r}: choose one of {sorted(FIELD_FILES)}")
    _check_dir(path, REQUIRED_FILES)
    if not (path / FIELD_FILES[precision]).is_file():
        raise InferError(f"{path / FIELD_FILES[precision]} not found: export it with "
                         f"`dars export-onnx RUN --out {path} --precision fp32,{precision}`")
    current = "metadata.json"  # the file being read, named when it is damaged
    try:
        metadata = json.loads((path / "metadata.json").read_text())
        if not isinstance(metadata, dict):
            raise ValueError(f"it holds a {type(metadata).__name__}, not an object")
        current = "occupancy.npz"
        occ = _load_npz(path / "occupancy.npz")
        r = int(occ["resolution"])
        occupancy = {"resolution": r, "aabb": occ["aabb"],
                     "mask": np.unpackbits(occ["mask_bits"], count=r ** 3).astype(bool),
                     "contraction": bool(occ["contraction"]) if "contraction" in occ.files else False}
        if "far_radius" in occ.files:
            occupancy["far_radius"] = float(occ["far_radius"])
        current = "background.npz"
        b = _load_npz(path / "background.npz")
        mode = str(b["mode"])
        background = {"mode": mode}
        if mode == "env":
            background["env_map"] = np.asarray(b["env_map"], np.float32)
        else:
            background["colour"] = np.asarray(b["colour"], np.float32).reshape(3)
    except Exception as e:  # noqa: BLE001 - json, zipfile, zlib and numpy raise many types for a damaged file
        raise InferError(f"{path / current} is truncated or corrupt ({type(e).__name__}: {str(e)[:160]}); "
                         f"re-run `dars export-onnx RUN --out {path}`") from e
    session = make_session(path / FIELD_FILES[precision], threads)
    heads = None
    if metadata.get("heads"):  # a run shaded once per ray; the heads graph stays fp32 in every variant
        name = metadata["heads"].get("file", "heads.onnx")
        _check_dir(path, [name])
        heads = make_session(path / name, threads)
    geometry = geometry_session(path / FIELD_FILES[precision], threads) if heads is not None else None
    return FieldModel(path, metadata, session, precision, occupancy, background, heads, geometry)


def _load_npz(path: Path):
    """``np.load`` of an ``.npz`` that says "not an .npz archive" for a truncated or foreign file (numpy would try
    to read it as pickled data)."""
    import zipfile

    if not zipfile.is_zipfile(path):
        raise ValueError("not an .npz archive: truncated, or another kind of file")
    return np.load(path, allow_pickle=False)


# ====================================================================== cameras and rays
def _read_transforms(path: Path) -> dict:
    """The JSON object of a ``transforms*.json`` with a ``frames`` list (InferError naming the file otherwise)."""
    if not path.is_file():
        raise InferError(f"transforms file not found: {path}")
    try:
        meta = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise InferError(f"{path} is not a valid transforms JSON ({e})") from e
    if not isinstance(meta, dict) or not isinstance(meta.get("frames", []), list):
        raise InferError(f"{path}: expected a JSON object with a 'frames' list")
    return meta


def camera_from_transforms(path: str | os.PathLike, index: int) -> PinholeCamera:
    """Camera ``index`` of a Blender/nerfstudio ``transforms*.json`` (no torch; no undistortion or downscaling).

    Intrinsics from per-frame or top-level ``fl_x, fl_y, cx, cy, w, h``, or ``camera_angle_x`` (+ the image size
    from ``w, h`` or the frame's image file).

    Raises:
        InferError: missing file or frame, or intrinsics that cannot be determined.
    """
    path = Path(path)
    meta = _read_transforms(path)
    frames = meta.get("frames", [])
    if not 0 <= index < len(frames):
        raise InferError(f"{path}: frame index {index} out of range (the file has {len(frames)} frames)")
    fr = frames[index]
    get = lambda k: fr.get(k, meta.get(k))  # noqa: E731
    w, h = get("w"), get("h")
    if w is None or h is None:
        fp = fr.get("file_path")
        if fp is None:
            raise InferError(f"{path}: frame {index} has no image size (w, h) and no file_path")
        img = path.parent / fp
        cands = [img] + [img.with_suffix(s) for s in (".png", ".jpg", ".jpeg")] + [Path(str(img) + ".png")]
        found = next((c for c in cands if c.is_file()), None)
        if found is None:
            raise InferError(f"{path}: frame {index} has no w/h and its image {img} was not found")
        from PIL import Image

        with Image.open(found) as im:
            w, h = im.size
    w, h = int(w), int(h)
    if get("fl_x") is not None:
        fx = float(get("fl_x"))
        fy = float(get("fl_y") if get("fl_y") is not None else fx)
    elif get("camera_angle_x") is not None:
        fx = 0.5 * w / math.tan(0.5 * float(get("camera_angle_x")))
        fy = 0.5 * h / math.tan(0.5 * float(get("camera_angle_y"))) if get("camera_angle_y") is not None else fx
    else:
        raise InferError(f"{path}: no intrinsics (fl_x or camera_angle_x)")
    cx = float(get("cx")) if get("cx") is not None else 0.5 * w
    cy = float(get("cy")) if get("cy") is not None else 0.5 * h
    c2w = np.asarray(fr["transform_matrix"], np.float32).reshape(4, 4)
    return PinholeCamera(c2w, fx, fy, cx, cy, w, h)


def _intersect_aabb(o: np.ndarray, d: np.ndarray, aabb: np.ndarray, near_min: float):
    inv = np.float32(1.0) / np.where(np.abs(d) < 1e-12, np.float32(1e-12), d)
    t0 = (aabb[0] - o) * inv
    t1 = (aabb[1] - o) * inv
    near = np.maximum(np.minimum(t0, t1).max(-1), np.float32(near_min))
    far = np.maximum(t0, t1).min(-1)
    return near, far


def generate_camera_rays(camera: PinholeCamera, aabb, near: float | None = None,
                         far: float | None = None, near_min: float = 0.05) -> dict[str, np.ndarray]:
    """Every pixel's ray, row-major (numpy mirror of :func:`toolkit.scene.generate_rays`).

    Args:
        camera: the view.
        aabb: float [2, 3] scene box the rays are clipped to, or a :class:`SceneSpace` (contracted: the rays run
            to its far radius).
        near, far: the scene's bounds (metres), applied on top of the box when both are given.
        near_min: entry clamp for rays starting inside the box.

    Returns:
        dict of float32 ``origins`` [R, 3], ``directions`` [R, 3] (unit), ``near``, ``far``, ``z_scale`` [R].
    """
    h, w = int(camera.height), int(camera.width)
    f32 = np.float32
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    pu = u.reshape(-1).astype(f32) + f32(0.5)
    pv = v.reshape(-1).astype(f32) + f32(0.5)
    d_cam = np.stack([(pu - f32(camera.cx)) / f32(camera.fx), -(pv - f32(camera.cy)) / f32(camera.fy),
                      -np.ones_like(pu)], -1)
    c2w = np.asarray(camera.c2w, f32)
    d_world = (c2w[:3, :3][None] * d_cam[:, None, :]).sum(-1)
    norm = np.sqrt((d_world * d_world).sum(-1, keepdims=True))
    directions = d_world / norm
    origins = np.broadcast_to(c2w[:3, 3], directions.shape).copy()
    if isinstance(aabb, SceneSpace):
        n, fa = _intersect_aabb(origins, directions, aabb.ray_box, near_min)
        if near is not None and far is not None:
            n, fa = np.maximum(n, np.full_like(n, near)), np.minimum(fa, np.full_like(fa, far))
        return {"origins": origins, "directions": directions.astype(f32), "near": n.astype(f32),
                "far": fa.astype(f32), "z_scale": (f32(1.0) / norm[:, 0]).astype(f32)}
    aabb = np.asarray(aabb, f32)
    if near is not None and far is not None:
        bn, bf = _intersect_aabb(origins, directions, aabb, near_min)
        n = np.maximum(np.full_like(pu, near), bn)
        fa = np.minimum(np.full_like(pu, far), bf)
    else:
        n, fa = _intersect_aabb(origins, directions, aabb, near_min)
    return {"origins": origins, "directions": directions.astype(f32), "near": n.astype(f32),
            "far": fa.astype(f32), "z_scale": (f32(1.0) / norm[:, 0]).astype(f32)}


# ====================================================================== packed volume rendering (numpy)
def _torch_linspace01(n: int) -> np.ndarray:
    """float32 [n + 1] like ``torch.linspace(0, 1, n + 1)`` (it fills the two halves from either end)."""
    steps = n + 1
    step = np.float32(1.0) / np.float32(n)
    i = np.arange(steps)
    half = steps // 2
    return np.where(i < half, i.astype(np.float32) * step,
                    np.float32(1.0) - (steps - 1 - i).astype(np.float32) * step).astype(np.float32)


def _ray_starts(ray_indices: np.ndarray, n_rays: int) -> np.ndarray:
    counts = np.bincount(ray_indices, minlength=n_rays)
    return np.cumsum(counts) - counts


def render_weights(density: np.ndarray, deltas: np.ndarray, ray_indices: np.ndarray, n_rays: int) -> np.ndarray:
    """float32 [S] compositing weights ``T α`` of packed samples (mirror of :func:`toolkit.render.render_weights`)."""
    sd = (density * deltas).astype(np.float32)
    alphas = np.float32(1.0) - np.exp(-sd)
    if sd.size == 0:
        return sd
    sd64 = sd.astype(np.float64)
    excl = np.cumsum(sd64) - sd64
    starts = _ray_starts(ray_indices, n_rays)
    offset = excl[np.minimum(starts, excl.shape[0] - 1)][ray_indices]
    trans = np.exp(-(excl - offset)).astype(np.float32)
    return trans * alphas


class _RaySums:
    """Σ w v per ray over one chunk's packed samples, for as many per-sample values v as the render needs: they
    share the weights and the rays, so the rays × samples matrix of the weights is built once.

    ``rows`` (a permutation of the S samples): ``values[rows[i]]`` is sample i's value, the order the field queries
    wrote the values in, which then need not be gathered into sample order. With scipy, one sparse product (CSR)
    per value: float32 sums in sample order, as torch's ``index_add`` takes them in
    :func:`toolkit.render.accumulate_along_rays` (bit for bit), and no [S, C] temporary (a feature has tens of
    channels; 30-40× faster than the fallback on 31-64). Without scipy (``export.infer`` needs only numpy and
    onnxruntime), ``np.bincount`` channel by channel, in float64.

    Attributes:
        counts: int64 [R] samples per ray.
    """

    def __init__(self, weights: np.ndarray, ray_indices: np.ndarray, n_rays: int, rows: np.ndarray | None = None):
        self.weights = np.asarray(weights, np.float32)
        self.ray_indices = np.asarray(ray_indices, np.int64)
        self.n_rays, self.rows = n_rays, rows
        self.counts = np.bincount(self.ray_indices, minlength=n_rays)
        self.matrix = None
        try:
            from scipy.sparse import csr_matrix
        except ImportError:
            return
        S = self.weights.shape[0]
        if S > 0:
            ri = self.ray_indices
            order = np.arange(S) if bool((ri[1:] >= ri[:-1]).all()) else np.argsort(ri, kind="stable")
            cols = order if rows is None else np.asarray(rows, np.int64)[order]
            self.matrix = csr_matrix((self.weights[order], cols, np.concatenate([[0], np.cumsum(self.counts)])),
                                     shape=(n_rays, S))

    def __call__(self, values: np.ndarray | None = None) -> np.ndarray:
        """float32 [R, C] Σ w v per ray of ``values`` [S, ...] (C: the product of its trailing sizes), or Σ w
        ([R, 1]) for None."""
        S = self.weights.shape[0]
        vals = (np.ones((S, 1), np.float32) if values is None
                else np.asarray(values, np.float32).reshape(S, int(np.prod(values.shape[1:], dtype=np.int64))))
        if self.matrix is not None:
            return np.asarray(self.matrix @ vals, np.float32).reshape(self.n_rays, vals.shape[1])
        src = self.weights[:, None] * (vals if self.rows is None else vals[self.rows])
        out = np.empty((self.n_rays, vals.shape[1]), np.float32)
        for c in range(vals.shape[1]):
            out[:, c] = np.bincount(self.ray_indices, weights=src[:, c], minlength=self.n_rays)
        return out


def _sort_keys(x: np.ndarray) -> np.ndarray:
    """int64 keys of float32 values in the same order as the values (IEEE bits, negatives flipped; −0 as +0)."""
    u = (np.asarray(x, np.float32) + np.float32(0.0)).view(np.uint32).astype(np.int64)
    return np.where(u >= 0x80000000, 0xFFFFFFFF - u, u + 0x80000000)


def _row_searchsorted(table: np.ndarray, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
    """int64 count of ``table[rows[i]] <= values[i]`` for each i: ``np.searchsorted(..., side="right")`` on each
    row of ``table`` [R, K] (float32, every row non-decreasing), in one call: the flattened table's keys are
    (row, value) pairs packed into one int64, so the comparisons are exact."""
    R, K = table.shape
    rows = np.asarray(rows, np.int64)
    flat = (np.arange(R, dtype=np.int64)[:, None] << 32 | _sort_keys(table)).ravel()
    return np.searchsorted(flat, rows << 32 | _sort_keys(values), side="right") - rows * K


def _sample_fine(edges: np.ndarray, pdf: np.ndarray, counts: np.ndarray, return_strata: bool = False):
    """Deterministic inverse-CDF samples (mirror of :func:`toolkit.sampling.sample_fine` with ``perturb=False``).

    Returns:
        (t [S_f], ray_indices [S_f]), and the stratum index [S_f] of each sample with ``return_strata``.
    """
    R, n = pdf.shape
    total = int(counts.sum())
    if total == 0:
        z, e = np.zeros(0, np.float32), np.zeros(0, np.int64)
        return (z, e, e) if return_strata else (z, e)
    f32 = np.float32
    valid = (edges[:, 1:] > edges[:, :-1]).astype(f32)
    p = pdf * valid
    s = p.sum(-1, keepdims=True)
    p = np.where(s > 1e-12, p / np.maximum(s, f32(1e-12)), valid / np.maximum(valid.sum(-1, keepdims=True), f32(1.0)))
    cdf = np.concatenate([np.zeros((R, 1), f32), np.cumsum(p.astype(np.float64), -1).astype(f32)], -1)  # as torch
    cdf[:, -1] = 1.0
    ray_idx = np.repeat(np.arange(R), counts)
    j = np.arange(total) - _ray_starts(ray_idx, R)[ray_idx]
    u = np.clip((j.astype(f32) + f32(0.5)) / counts[ray_idx].astype(f32), f32(0.0), f32(1.0 - 1e-6))
    k = np.clip(_row_searchsorted(cdf, ray_idx, u), 1, n) - 1  # searchsorted(right=True)
    c0, c1 = cdf[ray_idx, k], cdf[ray_idx, k + 1]
    e0, e1 = edges[ray_idx, k], edges[ray_idx, k + 1]
    frac = np.clip((u - c0) / np.maximum(c1 - c0, f32(1e-12)), f32(0.0), f32(1.0))
    t = (e0 + frac * (e1 - e0)).astype(f32)
    return (t, ray_idx, k) if return_strata else (t, ray_idx)


def _merge(t_a, ray_a, t_b, ray_b, max_delta, near, far, sample_max_delta=None):
    """Union sorted by (ray, t) with Voronoi intervals (mirror of :func:`toolkit.sampling.merge_samples`);
    ``sample_max_delta`` [S_a + S_b] (each sample's longest interval) replaces the per-ray ``max_delta``."""
    t = np.concatenate([t_a, t_b])
    r = np.concatenate([ray_a, ray_b])
    if t.size == 0:
        return t, t, r, np.zeros(0, np.int64)
    span = np.maximum(far - near, np.float32(1e-9)).astype(np.float64)
    key = r.astype(np.float64) + np.clip((t.astype(np.float64) - near.astype(np.float64)[r]) / span[r], 0.0, 1.0 - 1e-9)
    order = np.argsort(key, kind="stable")
    t, r = t[order], r[order]
    half = np.float32(0.5) * (max_delta[r] if sample_max_delta is None else sample_max_delta[order])
    same_prev = np.concatenate([[False], r[1:] == r[:-1]])
    same_next = np.concatenate([r[:-1] == r[1:], [False]])
    gap = t[1:] - t[:-1]
    gap_prev = np.concatenate([np.zeros(1, np.float32), gap])
    gap_next = np.concatenate([gap, np.zeros(1, np.float32)])
    left = np.where(same_prev, np.minimum(np.float32(0.5) * gap_prev, half), half)
    right = np.where(same_next, np.minimum(np.float32(0.5) * gap_next, half), half)
    starts = np.maximum(t - left, near[r])
    ends = np.maximum(np.minimum(t + right, far[r]), starts)
    return starts.astype(np.float32), ends.astype(np.float32), r, order


_PER_SAMPLE = ("albedo", "roughness", "metallic")


def render_rays(model: FieldModel, origins: np.ndarray, directions: np.ndarray, near: np.ndarray, far: np.ndarray,
                z_scale: np.ndarray, settings: RenderSettings | None = None,
                sh: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Render R rays through the exported field (see the module docstring for the algorithm).

    Args:
        model: from :func:`load_model`.
        origins, directions: float [R, 3] (unit directions).
        near, far: float [R] ray bounds (``far <= near``: the ray misses the box).
        z_scale: float [R] cosine to the optical axis (depth = t · z_scale).
        settings: sample counts (default: the run's render sampler).
        sh: float [9, 3] global SH light (default: the run's ``l_env``): relights a ``pbr`` field.

    Returns:
        float32 arrays per ray: ``rgb`` [R, 3] (linear radiance, background composited), ``depth`` [R] (metres
        along the optical axis), ``opacity`` [R], ``normal`` [R, 3], ``semantic_logits`` [R, C] (opacity-normalised),
        ``samples`` [R];
        for ``pbr``: ``albedo`` [R, 3], ``roughness``/``metallic`` [R] (opacity-normalised), ``diffuse``/
        ``specular`` [R, 3] (premultiplied by opacity).
    """
    st = settings or model.settings
    f32 = np.float32
    R, n = origins.shape[0], int(st.n_coarse)
    space = model.space
    edges = stratified_edges(origins, directions, near, far, space, n)
    starts, ends = edges[:, :-1], edges[:, 1:]
    mids = f32(0.5) * (starts + ends)
    pts = origins[:, None, :] + mids[..., None] * directions[:, None, :]
    keep = (ends > starts) & model.occupied(pts.reshape(-1, 3)).reshape(R, n)
    ray_c, k_c = np.nonzero(keep)
    t0c, t1c = starts[ray_c, k_c], ends[ray_c, k_c]
    tmid_c = f32(0.5) * (t0c + t1c)
    per_ray = model.deferred  # a run shaded once per ray: density and feature at the samples, heads per ray
    want = GEOMETRY_OUTPUTS if per_ray else None
    counts = np.zeros(R, np.int64)
    if st.n_fine > 0:
        counts[np.unique(ray_c)] = st.n_fine
    # one buffer per output for every sample, coarse then fine (query order); ``order`` below merges them
    S_c = ray_c.shape[0]
    outs = model.output_buffers(S_c + int(counts.sum()), want)
    out_c = model.query(origins[ray_c] + tmid_c[:, None] * directions[ray_c], directions[ray_c], sh, outputs=want,
                        out={k: v[:S_c] for k, v in outs.items()})
    if st.n_fine > 0:
        w_c = render_weights(out_c["density"], t1c - t0c, ray_c, R)
        pdf = np.zeros((R, n), f32)
        pdf[ray_c, k_c] = w_c
        t_f, ray_f, k_f = _sample_fine(edges, pdf, counts, return_strata=True)
    else:
        t_f, ray_f, k_f = np.zeros(0, f32), np.zeros(0, np.int64), np.zeros(0, np.int64)
    model.query(origins[ray_f] + t_f[:, None] * directions[ray_f], directions[ray_f], sh, outputs=want,
                out={k: v[S_c:] for k, v in outs.items()})
    max_delta = (np.maximum(far, near) - near) / f32(n)
    sample_delta = None
    if space.contraction:  # strata of unequal length: each sample spans at most its own stratum
        sample_delta = np.concatenate([t1c - t0c, edges[ray_f, k_f + 1] - edges[ray_f, k_f]]).astype(f32)
    s0, s1, ri, order = _merge(tmid_c, ray_c, t_f, ray_f, max_delta, near, far, sample_delta)
    weights = render_weights(outs["density"][order], s1 - s0, ri, R)
    sums = _RaySums(weights, ri, R, rows=order)  # of values in query order, as ``outs`` holds them
    opacity = sums()
    safe = np.maximum(opacity, f32(1e-6))
    tm = np.empty_like(s0)
    tm[order] = f32(0.5) * (s0 + s1)  # the samples' mid-points, in query order
    depth = (sums(tm)[:, 0] / safe[:, 0]) * z_scale
    bg = model.background_radiance(directions)
    if per_ray:
        return _shade_rays(model, sums, outs["feature"], opacity, depth, directions, bg, sh)
    res = {"rgb": sums(outs["colour" if model.shading == "pbr" else "radiance"]) + (f32(1.0) - opacity) * bg,
           "depth": depth, "opacity": opacity[:, 0]}
    nrm = sums(outs["normal"])
    res["normal"] = nrm / np.maximum(np.sqrt((nrm * nrm).sum(-1, keepdims=True)), f32(1e-6))
    res["semantic_logits"] = sums(outs["semantic_logits"]) / safe  # as torch: Σ w l / Σ w
    if model.shading == "pbr":
        res["albedo"] = sums(outs["albedo"]) / safe
        res["roughness"] = (sums(outs["roughness"]) / safe)[:, 0]
        res["metallic"] = (sums(outs["metallic"]) / safe)[:, 0]
        res["diffuse"] = sums(outs["diffuse"])
        res["specular"] = sums(outs["specular"])
    res["samples"] = sums.counts.astype(np.float32)
    return {k: v.astype(np.float32, copy=False) for k, v in res.items()}


def _shade_rays(model: FieldModel, sums: _RaySums, features: np.ndarray, opacity: np.ndarray, depth: np.ndarray,
                directions: np.ndarray, bg: np.ndarray, sh: np.ndarray | None) -> dict[str, np.ndarray]:
    """The outputs of :func:`render_rays` for a run shaded once per ray (``deferred``), as
    :func:`toolkit.pipeline.render_rays` computes them: the heads on h̄ = Σ w h / Σ w (``sums`` of the samples'
    ``features``), rgb = opacity · colour + (1 − opacity) · background, diffuse and specular premultiplied by
    opacity."""
    f32 = np.float32
    hbar = sums(features) / np.maximum(opacity, f32(1e-6))
    heads = model.query_heads(hbar, directions, sh)
    colour = heads["colour"] if model.shading == "pbr" else heads["radiance"]
    res = {"rgb": opacity * colour + (f32(1.0) - opacity) * bg, "depth": depth, "opacity": opacity[:, 0],
           "normal": heads["normal"], "semantic_logits": heads["semantic_logits"]}
    if model.shading == "pbr":
        res.update(albedo=heads["albedo"], roughness=heads["roughness"], metallic=heads["metallic"],
                   diffuse=opacity * heads["diffuse"], specular=opacity * heads["specular"])
    res["samples"] = sums.counts.astype(np.float32)
    return {k: v.astype(np.float32, copy=False) for k, v in res.items()}


def render_view(model: FieldModel, camera: PinholeCamera, settings: RenderSettings | None = None,
                sh: np.ndarray | None = None, progress: Callable[[int, int], None] | None = None
                ) -> dict[str, np.ndarray]:
    """Render every decomposed output of one camera (numpy + ONNX Runtime; the same algorithm as
    :func:`toolkit.pipeline.render_image` with the run's shading and no DARS along-ray density).

    Args:
        model: from :func:`load_model`.
        camera: the view.
        settings: sampler (default: the run's ``render_sampler``; ``chunk`` rays per batch).
        sh: float [9, 3] SH light to relight with (default: the run's ``l_env``).
        progress: called as ``progress(rays_done, rays_total)`` after each chunk.

    Returns:
        dict of float32 images: ``rgb``, ``albedo``, ``diffuse``, ``specular``, ``normal`` [H, W, 3],
        ``semantic_logits`` [H, W, C], ``depth``, ``opacity``, ``roughness``, ``metallic``, ``samples`` [H, W]
        (``rgb`` is linear radiance: apply the sRGB transfer for display).
    """
    st = settings or model.settings
    md = model.metadata
    rays = generate_camera_rays(camera, model.space if model.space.contraction else model.aabb, md.get("near"),
                                md.get("far"), st.near_min)
    total = rays["origins"].shape[0]
    parts: dict[str, list[np.ndarray]] = {}
    for i in range(0, total, st.chunk):
        sl = slice(i, i + st.chunk)
        r = render_rays(model, rays["origins"][sl], rays["directions"][sl], rays["near"][sl], rays["far"][sl],
                        rays["z_scale"][sl], st, sh)
        for k, v in r.items():
            parts.setdefault(k, []).append(v)
        if progress is not None:
            progress(min(i + st.chunk, total), total)
    h, w = int(camera.height), int(camera.width)
    return {k: np.concatenate(v).reshape((h, w) + np.concatenate(v).shape[1:]) for k, v in parts.items()}


# ====================================================================== photos: segmentation and light
def poses_for_photos(path: str | os.PathLike, photos: Sequence[str | os.PathLike]) -> np.ndarray:
    """float64 [N, 4, 4] camera-to-world poses of ``photos`` from a ``transforms*.json``, matched by file name
    without extension against the frames' ``file_path`` (no torch).

    Raises:
        InferError: missing or invalid file, or a photo no frame names.
    """
    path = Path(path)
    try:
        frames = {Path(str(fr["file_path"])).stem: fr["transform_matrix"] for fr in _read_transforms(path)["frames"]}
    except (KeyError, TypeError) as e:
        raise InferError(f"{path}: every frame needs file_path and transform_matrix (missing {e})") from e
    out = []
    for ph in photos:
        stem = Path(str(ph)).stem
        if stem not in frames:
            raise InferError(f"{path}: no frame's file_path names photo {ph} (looked for '{stem}' among "
                             f"{len(frames)} frames)")
        m = np.asarray(frames[stem], np.float64)
        out.append(np.vstack([m[:3], [0.0, 0.0, 0.0, 1.0]]) if m.shape == (3, 4) else m)
    return np.stack(out) if out else np.zeros((0, 4, 4))


def read_photo(photo) -> np.ndarray:
    """float32 [H, W, 3] sRGB in [0, 1] from a path (PNG/JPEG, via Pillow) or an array (uint8 or float [0, 1])."""
    if isinstance(photo, (str, os.PathLike)):
        p = Path(photo)
        if not p.is_file():
            raise InferError(f"photo not found: {p}")
        from PIL import Image

        try:
            with Image.open(p) as im:
                arr = np.asarray(im.convert("RGB"), np.float32) / 255.0
        except OSError as e:
            raise InferError(f"{p} is not a readable image ({e})") from e
        return arr
    arr = np.asarray(photo)
    if arr.ndim != 3 or arr.shape[-1] not in (3, 4):
        raise InferError(f"a photo array must be [H, W, 3] (or RGBA), got {list(arr.shape)}")
    arr = arr[..., :3]
    return arr.astype(np.float32) / 255.0 if arr.dtype == np.uint8 else arr.astype(np.float32)


def _resize(img: np.ndarray, h: int, w: int) -> np.ndarray:
    from PIL import Image

    chans = [np.asarray(Image.fromarray(img[..., c]).resize((w, h), Image.BILINEAR)) for c in range(img.shape[-1])]
    return np.stack(chans, -1).astype(np.float32)


def _image_input(session) -> tuple[str, int | None, int | None]:
    inp = session.get_inputs()[0]
    shape = inp.shape
    if len(shape) != 4:
        raise InferError(f"the network's input '{inp.name}' has shape {shape}; expected N x 3 x H x W")
    h = shape[2] if isinstance(shape[2], int) else None
    w = shape[3] if isinstance(shape[3], int) else None
    return inp.name, h, w


def infer_segment(path: str | os.PathLike, photos: Sequence, threads: int | None = None) -> list[np.ndarray]:
    """7-class labels of photos with ``segment.onnx`` (SPEC classes 0 painting .. 6 other).

    Args:
        path: export directory (or the ``segment.onnx`` file itself).
        photos: paths or [H, W, 3] arrays (sRGB; uint8 or float in [0, 1]).
        threads: ONNX Runtime intra-op threads.

    Returns:
        one uint8 [H, W] label image per photo, at the photo's size.

    Raises:
        InferError: no ``segment.onnx`` (an old export) or unreadable photos.
    """
    f = Path(path)
    f = f / "segment.onnx" if f.is_dir() else f
    if not f.is_file():
        raise InferError(f"{f} not found: the export has no segmentation network (an export made before dars "
                         "shipped one); re-run `dars export-onnx RUN --out DIR`")
    sess = make_session(f, threads)
    name, sh_, sw_ = _image_input(sess)
    try:
        work = int((sess.get_modelmeta().custom_metadata_map or {}).get("dars.work_size", "0"))
    except ValueError:
        work = 0
    labels = []
    for ph in photos:
        img = read_photo(ph)
        H, W = img.shape[:2]
        if sh_ is not None and sw_ is not None:
            x = _resize(img, sh_, sw_)
        elif work > 0 and min(H, W) != work:  # the scale the network was trained at
            k = work / min(H, W)
            x = _resize(img, max(1, round(H * k)), max(1, round(W * k)))
        else:
            x = img
        logits = sess.run(None, {name: np.ascontiguousarray(x.transpose(2, 0, 1)[None], np.float32)})[0][0]
        lab = logits.argmax(0).astype(np.uint8)
        if lab.shape != (H, W):
            from PIL import Image

            lab = np.asarray(Image.fromarray(lab).resize((W, H), Image.NEAREST))
        labels.append(lab)
    return labels


def _srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 (as :func:`toolkit.io.srgb_to_linear`, which this module cannot import: it loads torch)."""
    x = np.clip(x, 0.0, None)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, None)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 1e-8), 1 / 2.4) - 0.055).astype(np.float32)


def _adaptive_avg_pool(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """[H, W, C] -> [h, w, C] with torch's ``adaptive_avg_pool2d`` bins (floor(i H / h) .. ceil((i + 1) H / h))."""
    H, W = img.shape[:2]
    c = np.zeros((H + 1, W + 1, img.shape[2]), np.float64)
    c[1:, 1:] = img.astype(np.float64).cumsum(0).cumsum(1)
    r0 = (np.arange(h) * H) // h
    r1 = -((-(np.arange(h) + 1) * H) // h)
    c0 = (np.arange(w) * W) // w
    c1 = -((-(np.arange(w) + 1) * W) // w)
    s = c[r1][:, c1] - c[r0][:, c1] - c[r1][:, c0] + c[r0][:, c0]
    area = ((r1 - r0)[:, None] * (c1 - c0)[None])[..., None]
    return (s / area).astype(np.float32)


def _bilinear(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """[H, W, C] -> [h, w, C] bilinear with half-pixel centres (torch ``align_corners=False``)."""
    H, W = img.shape[:2]

    def coords(n_out, n_in):
        x = np.maximum((np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5, 0.0)
        i0 = np.minimum(np.floor(x).astype(np.int64), n_in - 1)
        i1 = np.minimum(i0 + 1, n_in - 1)
        return i0, i1, (x - i0)

    y0, y1, fy = coords(h, H)
    x0, x1, fx = coords(w, W)
    fy, fx = fy[:, None, None], fx[None, :, None]
    top = img[y0][:, x0] * (1 - fx) + img[y0][:, x1] * fx
    bot = img[y1][:, x0] * (1 - fx) + img[y1][:, x1] * fx
    return (top * (1 - fy) + bot * fy).astype(np.float32)


def camera_heading_np(c2w: np.ndarray) -> np.ndarray:
    """float32 [N, 2] (cos ψ, sin ψ) of each camera's forward direction turned horizontal (world +z up); the numpy
    twin of :func:`toolkit.lightnet.camera_heading` (no torch here)."""
    c2w = np.asarray(c2w, np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise InferError(f"camera poses must be N x 4 x 4 (or N x 3 x 4), got {list(c2w.shape)}")
    fwd, up = -c2w[:, :3, 2], c2w[:, :3, 1]
    h = fwd[:, :2] - np.sign(fwd[:, 2:3]) * up[:, :2]
    n = np.linalg.norm(h, axis=1, keepdims=True)
    if (n < 1e-6).any():
        raise InferError(f"camera {int(np.nonzero(n[:, 0] < 1e-6)[0][0])} has no horizontal direction (a degenerate pose)")
    return (h / n).astype(np.float32)


def infer_light(path: str | os.PathLike, photos: Sequence, threads: int | None = None,
                c2w: np.ndarray | None = None) -> np.ndarray:
    """SH light [N, 9, 3] (SPEC order, incident radiance, world frame) of photos with ``light.onnx``.

    Contract of ``light.onnx`` (:func:`export.onnx_light.export_lightnet_onnx`): input N x 3 x H x W float32,
    sRGB in [0, 1], and for a network that answers relative to each photo's heading (``dars.frame = heading``,
    the shipped one) a second input ``heading`` N x 2 computed here from ``c2w`` (each photo's camera-to-world
    pose, world +z up: the SH comes back in that world); output N x 9 x 3 (or N x 27, coefficient-major). Photos
    are resized to the trained
    ``dars.input_size`` as :func:`toolkit.lightnet.predict_sh` does (area averaging in linear light when
    shrinking — ``dars.resize = area-srgb`` in the metadata averages the sRGB values instead — bilinear when
    enlarging, clamped to [0, 1]); a graph with a static H x W is fed at that size; ``dars.normalize =
    imagenet`` asks for ImageNet mean/std normalisation outside the graph.

    Raises:
        InferError: no ``light.onnx`` in the export (see ``metadata.json`` ``light`` for why) or bad photos.
    """
    f = Path(path)
    f = f / "light.onnx" if f.is_dir() else f
    if not f.is_file():
        raise InferError(f"{f} not found: the export has no light-estimation network (see metadata.json "
                         "'light' for why; re-export with --light-weights FILE)")
    sess = make_session(f, threads)
    name, sh_, sw_ = _image_input(sess)
    meta = sess.get_modelmeta().custom_metadata_map
    size = int(meta["dars.input_size"]) if meta.get("dars.input_size", "").isdigit() else None
    heading_in = next((i.name for i in sess.get_inputs()[1:] if i.name == "heading"), None)
    headings = None
    if heading_in is not None:
        if c2w is None:
            raise InferError(f"{f} estimates the light relative to each photo's heading: give the photos' camera "
                             "poses (dars infer DIR --light PHOTO... --poses transforms.json)")
        headings = camera_heading_np(c2w)
        if len(headings) != len(photos):
            raise InferError(f"{len(photos)} photos but {len(headings)} camera poses")
    th, tw = (sh_, sw_) if sh_ is not None and sw_ is not None else ((size, size) if size else (None, None))
    out = []
    linear_area = meta.get("dars.resize", "area-linear") != "area-srgb"
    for ph in photos:
        img = read_photo(ph)
        if th is not None and img.shape[:2] != (th, tw):
            if img.shape[0] >= th and img.shape[1] >= tw:
                img = (_linear_to_srgb(_adaptive_avg_pool(_srgb_to_linear(img), th, tw)) if linear_area
                       else _adaptive_avg_pool(img, th, tw))
            else:
                img = _bilinear(img, th, tw)
            img = np.clip(img, 0.0, 1.0).astype(np.float32)
        if meta.get("dars.normalize") == "imagenet":
            img = (img - np.array([0.485, 0.456, 0.406], np.float32)) / np.array([0.229, 0.224, 0.225], np.float32)
        feed = {name: np.ascontiguousarray(img.transpose(2, 0, 1)[None], np.float32)}
        if headings is not None:
            feed[heading_in] = headings[len(out)][None]
        y = sess.run(None, feed)[0]
        if y.size != 27:
            raise InferError(f"{f}: output has {y.size} values per image; expected 27 SH coefficients")
        out.append(y.reshape(9, 3))
    return np.stack(out).astype(np.float32) if out else np.zeros((0, 9, 3), np.float32)
