"""Input encodings of the field: positional encoding (paper eq. 9) and a multiresolution hash grid.

The hash grid is defined once, in plain torch (:func:`hash_grid_encode_torch`): gather-based trilinear
interpolation with integer arithmetic that ONNX opset 17 supports (Mul, Add, Mod, Gather — no 3-D
``grid_sample``, no bitwise ops). On CPU, training uses a compiled OpenMP kernel with the same arithmetic
(``toolkit/csrc/hashgrid.cpp``), built once by ``torch.utils.cpp_extension`` into ``.venv/`` at set-up
(:func:`hashgrid_kernel`); if it cannot be built, the torch path is used and a warning says so.
``tests/test_encoding.py`` holds the two to the same values and gradients.

Hash: level ``l`` has resolution ``R_l = floor(base * b**l)``; a corner ``(cx, cy, cz)`` maps to row
``cx + cy (R+1) + cz (R+1)^2`` when ``(R+1)^3 <= T`` (dense level) else ``(cx + cy·2654435761 + cz·805459861) mod T``.
The sum hash replaces Instant-NGP's XOR so the graph needs no bitwise operators (XOR arrives in opset 18).
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from ._checks import ConfigError, check_shape

__all__ = [
    "positional_encoding",
    "HashGridConfig",
    "HashGrid",
    "hash_grid_resolutions",
    "hash_grid_encode_torch",
    "hash_grid_encode",
    "hashgrid_kernel",
]

_PRIME_Y = 2654435761
_PRIME_Z = 805459861


def positional_encoding(x: torch.Tensor, n_freqs: int, include_input: bool = True) -> torch.Tensor:
    """γ(v) = [v, sin(2^0 π v), cos(2^0 π v), ..., sin(2^{L-1} π v), cos(2^{L-1} π v)] (paper eq. 9).

    Args:
        x: float [..., D].
        n_freqs: L (the paper: 10 for positions, 4 for directions).
        include_input: prepend ``x`` itself (NeRF convention).

    Returns:
        float [..., D * (2 L + include_input)].
    """
    freqs = (2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)) * math.pi
    xb = x[..., None, :] * freqs[:, None]  # [..., L, D]
    enc = torch.cat([torch.sin(xb), torch.cos(xb)], -1).flatten(-2)
    return torch.cat([x, enc], -1) if include_input else enc


@dataclass(frozen=True)
class HashGridConfig:
    """Multiresolution hash grid (Müller et al. 2022) sizes."""

    n_levels: int = 8
    """Number of resolution levels L."""
    features_per_level: int = 4
    """Features per level F (the encoding has L * F channels)."""
    log2_table_size: int = 17
    """Rows per level T = 2**log2_table_size (coarse levels that fit are stored densely)."""
    base_resolution: int = 16
    """Resolution of the coarsest level (cells across the scene box)."""
    max_resolution: int = 1024
    """Resolution of the finest level."""

    def __post_init__(self):
        if not 1 <= self.n_levels <= 32:
            raise ConfigError(f"n_levels={self.n_levels} must be in [1, 32]")
        if not 10 <= self.log2_table_size <= 24:
            raise ConfigError(f"log2_table_size={self.log2_table_size} must be in [10, 24]")
        if not 2 <= self.base_resolution <= self.max_resolution:
            raise ConfigError(f"need 2 <= base_resolution ({self.base_resolution}) <= max_resolution ({self.max_resolution})")

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.features_per_level


def hash_grid_resolutions(cfg: HashGridConfig) -> list[int]:
    """Per-level resolutions R_l = floor(base * b^l) with b chosen so the last level is ``max_resolution``."""
    if cfg.n_levels == 1:
        return [cfg.base_resolution]
    b = math.exp((math.log(cfg.max_resolution) - math.log(cfg.base_resolution)) / (cfg.n_levels - 1))
    return [int(math.floor(cfg.base_resolution * b ** lvl + 1e-6)) for lvl in range(cfg.n_levels)]


def hash_grid_encode_torch(x: torch.Tensor, table: torch.Tensor, resolutions: torch.Tensor, table_size: int) -> torch.Tensor:
    """Reference hash-grid encoding in plain torch (ONNX-exportable; any device).

    Args:
        x: float [N, 3] positions normalised to the unit cube [0, 1]^3 (values outside are clamped).
        table: float [L * T, F] feature rows, level ``l`` at rows ``l*T .. (l+1)*T - 1``.
        resolutions: int64 [L] per-level resolutions.
        table_size: T.

    Returns:
        float [N, L * F] interpolated features (level-major).
    """
    n_levels = resolutions.shape[0]
    feats = table.shape[1]
    x = x.clamp(0.0, 1.0)
    res = resolutions.to(x.device)
    res_f = res.to(x.dtype)
    pos = x[:, None, :] * res_f[None, :, None]  # [N, L, 3]
    c0 = torch.minimum(pos.floor(), (res_f - 1)[None, :, None])
    f = pos - c0
    c0 = c0.long()
    # A corner's row is linear in its coordinates, so it is the lower corner's row plus a per-level offset of the
    # corner (ONNX Runtime spends its time on [N, L, 8, ...] tensors: build as few of them as possible).
    # Multipliers of (cx, cy, cz): (1, R+1, (R+1)^2) on a dense level, (1, PRIME_Y, PRIME_Z) on a hashed one.
    r1 = res + 1
    dense = r1 * r1 * r1 <= table_size  # [L]
    mult = torch.stack([torch.ones_like(r1), torch.where(dense, r1, torch.full_like(r1, _PRIME_Y)),
                        torch.where(dense, r1 * r1, torch.full_like(r1, _PRIME_Z))], -1)  # [L, 3]
    offs = torch.tensor([[k & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], device=x.device)  # [8, 3]
    corner = (offs[None] * mult[:, None]).sum(-1)  # [L, 8]
    lin = (c0 * mult[None]).sum(-1)[:, :, None] + corner[None]  # [N, L, 8]
    # mod T hashes a hashed level and leaves a dense one as it is (its rows end at (R+1)^3 - 1 < T): no Where
    level_off = (torch.arange(n_levels, device=x.device) * table_size)[None, :, None]
    rows = torch.remainder(lin, table_size) + level_off  # [N, L, 8]
    # trilinear interpolation as three lerps, z (the outermost corner bit: corner k = x + 2 y + 4 z) first: 7 F
    # products a point and level against 8 + 8 F for the weights' outer product and the weighted sum, and fewer
    # [N, L, 8, ...] tensors in ONNX Runtime (field.onnx 1.1-1.25x the points a second; bench/bench_infer_ab.py)
    g = table[rows.reshape(-1)].reshape(x.shape[0], n_levels, 2, 4, feats)  # [N, L, z, (y, x), F]
    g0, g1 = g.unbind(2)
    g = (g0 + (g1 - g0) * f[:, :, 2, None, None]).reshape(x.shape[0], n_levels, 2, 2, feats)  # [N, L, y, x, F]
    g0, g1 = g.unbind(2)
    g = g0 + (g1 - g0) * f[:, :, 1, None, None]  # [N, L, x, F]
    g0, g1 = g.unbind(2)
    return (g0 + (g1 - g0) * f[:, :, 0, None]).reshape(x.shape[0], n_levels * feats)


# ------------------------------------------------------------------ compiled CPU kernel
_KERNEL = None
_KERNEL_TRIED = False


def _build_dir() -> Path:
    env = os.environ.get("DARS_EXT_DIR")
    if env:
        return Path(env)
    import sys

    return Path(sys.prefix) / "dars_ext"


def hashgrid_kernel():
    """The compiled CPU hash-grid kernel, built on first use (about a minute; cached), or ``None``.

    Set ``DARS_NO_EXT=1`` to force the plain-torch path.
    """
    global _KERNEL, _KERNEL_TRIED
    if _KERNEL_TRIED:
        return _KERNEL
    _KERNEL_TRIED = True
    if os.environ.get("DARS_NO_EXT"):
        return None
    try:
        from torch.utils.cpp_extension import load

        src = Path(__file__).with_name("csrc") / "hashgrid.cpp"
        build = _build_dir() / "hashgrid"
        build.mkdir(parents=True, exist_ok=True)
        _KERNEL = load(name="dars_hashgrid", sources=[str(src)], build_directory=str(build),
                       extra_cflags=["-O3", "-fopenmp", "-march=x86-64-v2"], extra_ldflags=["-fopenmp"],
                       verbose=False)
    except Exception as e:  # noqa: BLE001 - any build failure falls back to the reference path
        warnings.warn(f"dars: could not build the CPU hash-grid kernel ({type(e).__name__}: {e}); "
                      "training uses the slower plain-torch encoding", RuntimeWarning, stacklevel=2)
        _KERNEL = None
    return _KERNEL


class _HashGridFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, table, resolutions, table_size):
        kernel = hashgrid_kernel()
        ctx.save_for_backward(x, resolutions)
        ctx.table_size = table_size
        ctx.rows = table.shape[0]
        return kernel.forward(x, table, resolutions, table_size)

    @staticmethod
    def backward(ctx, grad_out):
        x, resolutions = ctx.saved_tensors
        grad_table = None
        if ctx.needs_input_grad[1]:
            grad_table = hashgrid_kernel().backward(x, grad_out.contiguous(), resolutions, ctx.table_size, ctx.rows)
        return None, grad_table, None, None


def hash_grid_encode(x: torch.Tensor, table: torch.Tensor, resolutions: torch.Tensor, table_size: int,
                     backend: str = "auto") -> torch.Tensor:
    """Hash-grid encoding; ``backend`` ``auto`` uses the compiled kernel on CPU when it is available and
    the inputs do not need a gradient w.r.t. positions, else :func:`hash_grid_encode_torch`."""
    use_kernel = (
        backend in ("auto", "kernel")
        and x.device.type == "cpu" and x.dtype == torch.float32 and table.dtype == torch.float32
        and not x.requires_grad
        and not torch.jit.is_tracing() and not torch.onnx.is_in_onnx_export()
        and hashgrid_kernel() is not None
    )
    if backend == "kernel" and not use_kernel:
        raise ConfigError("hash-grid kernel requested but unavailable for these inputs (CPU float32, no position grad)")
    if use_kernel:
        return _HashGridFn.apply(x.clamp(0.0, 1.0).contiguous(), table, resolutions, table_size)
    return hash_grid_encode_torch(x, table, resolutions, table_size)


class HashGrid(nn.Module):
    """Learnable multiresolution hash grid over a scene box.

    Args:
        cfg: sizes.
        aabb: float [2, 3] scene box (positions are normalised to it).
        init_scale: table initialised uniformly in ±init_scale (Instant-NGP: 1e-4).
    """

    def __init__(self, cfg: HashGridConfig, aabb: torch.Tensor, init_scale: float = 1e-4):
        super().__init__()
        self.cfg = cfg
        res = hash_grid_resolutions(cfg)
        self.table_size = 2 ** cfg.log2_table_size
        self.register_buffer("resolutions", torch.tensor(res, dtype=torch.long), persistent=False)
        self.register_buffer("aabb", aabb.detach().clone().float().reshape(2, 3))
        rows = self.table_size * cfg.n_levels
        self.table = nn.Parameter(torch.empty(rows, cfg.features_per_level).uniform_(-init_scale, init_scale))
        self.backend = "auto"

    @property
    def out_dim(self) -> int:
        return self.cfg.out_dim

    def normalise(self, points: torch.Tensor) -> torch.Tensor:
        """World points [N, 3] -> unit-cube coordinates [N, 3]."""
        lo, hi = self.aabb[0], self.aabb[1]
        return (points - lo) / (hi - lo)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        check_shape(points, "N 3", "points")
        return hash_grid_encode(self.normalise(points), self.table, self.resolutions, self.table_size, self.backend)
