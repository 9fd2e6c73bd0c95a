"""Per-pixel data of many views in one flat buffer: photos of different sizes, stored compactly.

Training draws a few thousand pixels per step from every photo of a capture. Holding each photo as float32
[3, H, W] (12 bytes a pixel) plus float maps and a float64 table over all pixels made memory grow with megapixels
(58 photos of 1 MP peaked at 8.4 GB). :class:`PackedViews` holds one per-pixel quantity of V views — colour, class
label, mask or DARS weight W — as a flat tensor ``data`` [P] or [P, C]: the views one after another, each row-major
(H-W-C), so views may differ in size (portrait and landscape photos, per-frame intrinsics).

Storage (bytes per pixel): colour uint8 (3), labels uint8 (1), masks bool (1), W uint8 (1) — values in [0, 1]
``quantised`` to ``round(255 x)``, read back as ``x = q / 255`` (an error of at most 1/510: exact for 8-bit photos);
anything else (float16 ground-truth albedo) as given. A buffer can live in a memory-mapped file (``path=``) so a
capture larger than RAM stays on disk and only the pages a batch touches are read.

Example:
    >>> w = PackedViews.allocate([2, 3], [4, 2], quantised=True)    # two views: 2x4 and 3x2 pixels
    >>> w.write(1, torch.full((3, 2), 0.5))
    >>> w.n_pixels, w[1].shape, round(float(w[1][0, 0]), 3)
    (14, torch.Size([3, 2]), 0.502)
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ._checks import ShapeError

__all__ = ["PackedViews"]

_QUANT = 255.0


@dataclass(frozen=True)
class PackedViews:
    """One per-pixel quantity of V views of possibly different sizes, in one flat buffer.

    Attributes:
        data: [P] or [P, C] the pixels of view 0 (row-major), then view 1, ... (uint8, bool, float16 or float32).
        heights, widths: int64 [V] view sizes in pixels.
        offsets: int64 [V + 1] index in ``data`` of each view's first pixel (``offsets[-1] = P``).
        quantised: ``data`` is uint8 holding ``round(255 x)`` of values x in [0, 1] (read back as ``q / 255``).
    """

    data: torch.Tensor
    heights: torch.Tensor
    widths: torch.Tensor
    offsets: torch.Tensor
    quantised: bool = False

    # ------------------------------------------------------------------ construction
    @classmethod
    def allocate(cls, heights: Sequence[int] | torch.Tensor, widths: Sequence[int] | torch.Tensor,
                 channels: int | None = None, dtype: torch.dtype = torch.uint8, quantised: bool = False,
                 path: str | Path | None = None) -> "PackedViews":
        """A zero-filled buffer for views of the given sizes.

        Args:
            heights, widths: [V] view sizes.
            channels: C for a [P, C] buffer, None for [P].
            dtype: storage dtype (uint8 when ``quantised``).
            quantised: store values in [0, 1] as ``round(255 x)`` (uint8).
            path: a file to memory-map the buffer to (created or overwritten; CPU only), or None for RAM.
        """
        h = torch.as_tensor(heights, dtype=torch.long).reshape(-1).cpu()
        w = torch.as_tensor(widths, dtype=torch.long).reshape(-1).cpu()
        if h.shape != w.shape or bool((h < 1).any() | (w < 1).any()):
            raise ShapeError(f"view sizes must be positive and as many heights as widths, got {h.tolist()} x {w.tolist()}")
        if quantised:
            dtype = torch.uint8
        offsets = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(h * w, 0)])
        shape = (int(offsets[-1]),) if channels is None else (int(offsets[-1]), int(channels))
        if path is None:
            data = torch.zeros(shape, dtype=dtype)
        else:
            np_dtype = torch.empty(0, dtype=dtype).numpy().dtype
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            data = torch.from_numpy(np.lib.format.open_memmap(str(path), mode="w+", dtype=np_dtype, shape=shape))
        return cls(data, h, w, offsets, quantised)

    @classmethod
    def from_maps(cls, maps: torch.Tensor | Sequence[torch.Tensor], quantise: bool = False) -> "PackedViews":
        """Pack per-view maps: a tensor [V, H, W] / [V, H, W, C] (no copy unless quantising) or a list of [H, W] /
        [H, W, C] tensors of any sizes. ``quantise``: store float values in [0, 1] as uint8."""
        if isinstance(maps, torch.Tensor):
            if maps.dim() not in (3, 4):
                raise ShapeError(f"maps: expected [V, H, W] or [V, H, W, C], got {list(maps.shape)}")
            V, H, W = maps.shape[:3]
            C = None if maps.dim() == 3 else maps.shape[3]
            if not quantise:
                flat = maps.reshape(V * H * W, *(() if C is None else (C,)))
                offsets = torch.arange(V + 1, dtype=torch.long) * (H * W)
                return cls(flat, torch.full((V,), H, dtype=torch.long), torch.full((V,), W, dtype=torch.long), offsets)
            maps = list(maps)
        maps = list(maps)
        if not maps:
            raise ShapeError("maps: need at least one view")
        C = None if maps[0].dim() == 2 else maps[0].shape[2]
        out = cls.allocate([m.shape[0] for m in maps], [m.shape[1] for m in maps], C,
                           maps[0].dtype if not quantise else torch.uint8, quantise)
        for i, m in enumerate(maps):
            out.write(i, m)
        return out

    def write(self, i: int, values: torch.Tensor) -> None:
        """Store view ``i``: ``values`` [H, W] or [H, W, C] (floats in [0, 1] when quantised, clamped)."""
        dst = self.raw(i)
        if tuple(values.shape) != tuple(dst.shape):
            raise ShapeError(f"view {i}: expected values of shape {list(dst.shape)}, got {list(values.shape)}")
        if self.quantised:
            values = values.float().clamp(0.0, 1.0).mul(_QUANT).round_()
        dst.copy_(values.to(dst.dtype))

    # ------------------------------------------------------------------ sizes and views
    def __len__(self) -> int:
        return int(self.heights.shape[0])

    @property
    def n_pixels(self) -> int:
        return int(self.offsets[-1])

    @property
    def channels(self) -> int | None:
        return None if self.data.dim() == 1 else int(self.data.shape[1])

    @property
    def nbytes(self) -> int:
        return self.data.numel() * self.data.element_size()

    @property
    def device(self) -> torch.device:
        return self.data.device

    def size(self, i: int) -> tuple[int, int]:
        """(height, width) of view ``i``."""
        return int(self.heights[i]), int(self.widths[i])

    def raw(self, i: int) -> torch.Tensor:
        """View ``i`` as stored, [H, W] or [H, W, C] (no copy)."""
        h, w = self.size(i)
        o = int(self.offsets[i])
        return self.data[o:o + h * w].view(h, w, *self.data.shape[1:])

    def __getitem__(self, i: int) -> torch.Tensor:
        """View ``i`` as float32 values [H, W] or [H, W, C] (dequantised)."""
        if not isinstance(i, int):
            raise TypeError(f"PackedViews index must be an int view index, got {type(i).__name__}")
        if not -len(self) <= i < len(self):
            raise IndexError(f"view {i} out of range for {len(self)} views")
        return self._values(self.raw(i % len(self)))

    def _values(self, x: torch.Tensor) -> torch.Tensor:
        if self.quantised:
            return x.float() / _QUANT
        return x.float() if x.is_floating_point() else x

    # ------------------------------------------------------------------ pixel addressing
    def flat_index(self, views: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
        """int64 [N] buffer index of pixels (view, row, col) [N]."""
        v = views.to(self.offsets.device)
        return self.offsets[v] + rows.to(v.device) * self.widths.to(v.device)[v] + cols.to(v.device)

    def locate(self, flat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(views, rows, cols) int64 [N] of buffer indices ``flat`` [N]."""
        flat = flat.to(self.offsets.device)
        views = torch.searchsorted(self.offsets, flat, right=True) - 1
        rem = flat - self.offsets[views]
        w = self.widths.to(flat.device)[views]
        return views, rem // w, rem % w

    def gather(self, flat: torch.Tensor) -> torch.Tensor:
        """Values at buffer indices ``flat`` [N]: float32 [N] / [N, C] (dequantised); integer and bool buffers keep
        their dtype."""
        return self._values(self.data[flat.to(self.data.device)])

    # ------------------------------------------------------------------ whole-buffer helpers
    def to(self, device: torch.device | str) -> "PackedViews":
        """The buffer on ``device`` (itself when already there)."""
        device = torch.device(device)
        if self.data.device == device:
            return self
        return replace(self, data=self.data.to(device), heights=self.heights.to(device), widths=self.widths.to(device),
                       offsets=self.offsets.to(device))

    def subset(self, indices: Sequence[int]) -> "PackedViews":
        """A new buffer (in RAM) holding views ``indices`` in that order."""
        idx = [int(i) for i in indices]
        out = PackedViews.allocate(self.heights[idx], self.widths[idx], self.channels, self.data.dtype, self.quantised)
        for k, i in enumerate(idx):
            out.raw(k).copy_(self.raw(i))
        return out.to(self.device)

    def sums(self) -> torch.Tensor:
        """float64 [V] sum of each view's values (dequantised; all channels)."""
        out = torch.zeros(len(self), dtype=torch.float64)
        for i in range(len(self)):
            o0, o1 = int(self.offsets[i]), int(self.offsets[i + 1])
            out[i] = float(self.data[o0:o1].sum(dtype=torch.float64))
        return out / _QUANT if self.quantised else out
