"""Stage 8 — the structure–material–lighting decoupled field (paper section II.C, eqs. 9–18).

Two interchangeable encodings behind one interface (:class:`DarsField`):

* ``mlp`` — the paper's: positional encoding γ(x) with L=10 (eq. 9), an 8 × 256 ReLU + LayerNorm backbone
  (eq. 10), heads on its 256-d feature ``h``. GPU-scale.
* ``grid`` — a multiresolution hash grid (:mod:`toolkit.encoding`) + a one-hidden-layer geometry MLP, for
  CPU-speed training. The heads are the same; only their width differs.

Heads (all on the shared feature ``h``):

* structure: density σ = softplus(W_σ h + b_σ) (eq. 13) and normal n = N(h)/‖N(h)‖ (eq. 18). σ is expressed in
  units of 1/δ_ref with δ_ref = box diagonal / 1024 (Instant-NGP's render step) and the pre-activation starts
  at −8 (σ ≈ 3e-4/δ_ref: the box starts transparent, so density grows only where the images need it — an
  opaque start lets the optimiser paint the views on a shell of density); an opaque surface (σ δ ≫ 1 over a
  few millimetres) is then a few units of W_σ h away instead of hundreds;
* semantics: 7 class logits (3D-consistent labels rendered at novel views);
* material: albedo, roughness, metallic through sigmoids (eqs. 15–17), from [h; s] where s is the field's
  own *detached* class distribution (SPEC: no 2D label is needed at test time);
* lighting: a residual Δl(x) [9, 3] added to the global SH ``l_env`` (from [h; l_env]) — spatially varying
  light for spotlights and shadows, bounded by ½|L00| per channel (tanh) and kept small by a regulariser;
* radiance: a plain view-dependent colour from [h; γ(d)] with L=4 — used only by the ``standard NeRF``
  baseline (``shading="radiance"``).

Where eq. 10 feeds [γ(x); γ(d); s; l_env] into the backbone, we feed γ(x) only and condition the heads on
s, l_env and γ(d): density and geometry must not change with the viewing direction or the global light
estimate, and s comes from the field itself (documented deviation; see README "Method notes").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import nn

from ._checks import ConfigError, check_shape
from .encoding import HashGrid, HashGridConfig, positional_encoding
from .io import srgb_to_linear
from .space import SceneSpace, box_radius, contract

__all__ = ["FieldConfig", "FieldOutputs", "DarsField", "N_CLASSES"]

N_CLASSES = 7


@dataclass(frozen=True)
class FieldConfig:
    """Architecture of :class:`DarsField`."""

    encoding: Literal["grid", "mlp"] = "grid"
    """``mlp``: the paper's PE + 8x256 backbone; ``grid``: hash grid + tiny MLP (CPU speed)."""
    grid: HashGridConfig = field(default_factory=HashGridConfig)
    """Hash-grid sizes (``grid`` encoding)."""
    pe_freqs_position: int = 10
    """L for γ(x) (eq. 9; ``mlp`` encoding)."""
    pe_freqs_direction: int = 4
    """L for γ(d) (radiance head)."""
    backbone_width: int = 256
    """Width of the ``mlp`` backbone (paper: 256)."""
    backbone_depth: int = 8
    """Layers of the ``mlp`` backbone (paper: 8)."""
    geo_hidden: int = 64
    """Hidden width of the ``grid`` geometry MLP."""
    feature_dim: int = 31
    """Size of the shared feature h for the ``grid`` encoding (``mlp``: backbone_width)."""
    head_hidden: int = 64
    """Hidden width of the heads."""
    n_classes: int = N_CLASSES
    light_residual: bool = True
    """Predict the per-point lighting residual Δl(x)."""
    light_residual_colour: str = "rgb"
    """The residual's colour. ``rgb``: one Δl per SH coefficient and colour channel. ``grey``: one per coefficient,
    shared by the channels as a fraction of each channel's ambient (Δl_c = tanh(g)·½|L00_c|), so the residual can
    shade and shadow but not tint: colour the photos show goes to the albedo, which a GLB carries, not to the local
    light, which it does not."""
    shell: float = 0.0
    """Room prior: thickness, as a fraction of the box diagonal, of an opaque layer the density starts with on the
    box faces in ``shell_faces`` (0: off, a transparent start everywhere). For captures taken inside an enclosed
    room: a textureless wall then starts as a surface near its true place instead of being explained by the
    environment behind it; the learned density moves or removes the layer where the photos disagree."""
    shell_faces: tuple[bool, bool, bool, bool, bool, bool] = (True, True, True, True, True, True)
    """Which faces carry the layer: (x min, y min, z min, x max, y max, z max)."""
    contraction: bool = True
    """Unbounded space (:mod:`toolkit.space`): positions beyond the scene box are contracted into a shell, so walls,
    floor and sky beyond the box are modelled too. False: the bounded model (nothing exists outside the box)."""
    far_radius: float = 64.0
    """With contraction: the field ends (and rays stop) where the box-normalised L∞ radius reaches this."""

    def __post_init__(self):
        if self.encoding not in ("grid", "mlp"):
            raise ConfigError(f"field encoding={self.encoding!r}: choose 'grid' or 'mlp'")
        for name in ("backbone_width", "backbone_depth", "geo_hidden", "feature_dim", "head_hidden"):
            if getattr(self, name) < 1:
                raise ConfigError(f"field {name}={getattr(self, name)} must be >= 1")
        if not 0.0 <= self.shell < 0.5:
            raise ConfigError(f"field shell={self.shell} must be in [0, 0.5) (a fraction of the box diagonal)")
        if self.light_residual_colour not in ("rgb", "grey"):
            raise ConfigError(f"field light_residual_colour={self.light_residual_colour!r}: choose 'rgb' or 'grey'")
        if len(self.shell_faces) != 6:
            raise ConfigError(f"field shell_faces needs 6 flags (x min, y min, z min, x max, y max, z max), "
                              f"got {len(self.shell_faces)}")


@dataclass
class FieldOutputs:
    """Per-point outputs (N points). Missing heads are ``None``.

    Attributes:
        density: float [N] σ ≥ 0 (1/metre).
        normal: float [N, 3] unit world normals (normal head).
        albedo: float [N, 3] linear base colour in [0, 1].
        roughness, metallic: float [N] in [0, 1].
        semantic_logits: float [N, C].
        light: float [N, 9, 3] local SH light l_env + Δl(x) (or ``None`` without an l_env).
        light_residual: float [N, 9, 3] Δl(x).
        radiance: float [N, 3] plain view-dependent colour (radiance head), linear, in [0, 1].
    """

    density: torch.Tensor
    normal: torch.Tensor | None = None
    albedo: torch.Tensor | None = None
    roughness: torch.Tensor | None = None
    metallic: torch.Tensor | None = None
    semantic_logits: torch.Tensor | None = None
    light: torch.Tensor | None = None
    light_residual: torch.Tensor | None = None
    radiance: torch.Tensor | None = None


def _mlp(sizes: list[int], last_init_zero: bool = False) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU(inplace=True))
    if last_init_zero:
        nn.init.zeros_(layers[-1].weight)
        nn.init.zeros_(layers[-1].bias)
    return nn.Sequential(*layers)


class DarsField(nn.Module):
    """The decoupled field. ``aabb`` float [2, 3] is the scene box (positions are normalised to it)."""

    def __init__(self, cfg: FieldConfig, aabb: torch.Tensor):
        super().__init__()
        self.cfg = cfg
        aabb = torch.as_tensor(aabb, dtype=torch.float32).reshape(2, 3)
        self.register_buffer("aabb", aabb.clone())
        grid_box = SceneSpace(aabb, cfg.contraction, cfg.far_radius).grid_aabb
        self.density_scale = float(1024.0 / (aabb[1] - aabb[0]).norm())
        """1/δ_ref: softplus outputs are densities per reference step."""
        self.density_bias = -8.0
        self.shell_bias = 4.0
        """Pre-activation on the box faces of the room prior (σ = 4.0/δ_ref), fading linearly to density_bias."""
        self.register_buffer("shell_faces", torch.tensor([float(f) for f in cfg.shell_faces]), persistent=False)
        if cfg.shell > 0:
            # 0 … 1: how much of the layer is on; the trainer fades it in after stage (a), once the objects in the
            # room have formed in front of it (present from the start, it is painted with what they look like)
            self.register_buffer("shell_weight", torch.ones(()))
        if cfg.encoding == "grid":
            self.grid = HashGrid(cfg.grid, grid_box)
            self.geometry = _mlp([self.grid.out_dim, cfg.geo_hidden, 1 + cfg.feature_dim])
            fdim = cfg.feature_dim
        else:
            in_dim = 3 * (2 * cfg.pe_freqs_position + 1)
            layers: list[nn.Module] = []
            d = in_dim
            for _ in range(cfg.backbone_depth):
                layers += [nn.Linear(d, cfg.backbone_width), nn.LayerNorm(cfg.backbone_width), nn.ReLU(inplace=True)]
                d = cfg.backbone_width
            self.backbone = nn.Sequential(*layers)
            self.density_head = nn.Linear(cfg.backbone_width, 1)
            fdim = cfg.backbone_width
        hh = cfg.head_hidden
        self.feature_dim = fdim
        self.normal_head = _mlp([fdim, hh // 2, 3])
        self.semantic_head = _mlp([fdim, hh // 2, cfg.n_classes])
        self.material_head = _mlp([fdim + cfg.n_classes, hh, 5])
        self.light_head = _mlp([fdim + 27, hh // 2, 27], last_init_zero=True) if cfg.light_residual else None
        dir_dim = 3 * (2 * cfg.pe_freqs_direction + 1)
        self.radiance_head = _mlp([fdim + dir_dim, hh, hh, 3])

    # ------------------------------------------------------------------ geometry
    @property
    def space(self) -> SceneSpace:
        """The space the field lives in (box, contraction, far radius), on the field's device."""
        return SceneSpace(self.aabb, self.cfg.contraction, self.cfg.far_radius)

    def _normalised(self, points: torch.Tensor) -> torch.Tensor:
        """World points -> [-1, 1]^3 (the scene box; with contraction the whole of space, the box in [-½, ½]^3)."""
        if self.cfg.contraction:
            return contract(points, self.aabb) * 0.5
        lo, hi = self.aabb[0], self.aabb[1]
        return (points - lo) / (hi - lo) * 2.0 - 1.0

    def geometry_features(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(density [N], shared feature h [N, D]) at world points [N, 3]."""
        check_shape(points, "N 3", "points")
        if self.cfg.encoding == "grid":
            out = self.geometry(self.grid(contract(points, self.aabb) if self.cfg.contraction else points))
            raw, h = out[:, 0], out[:, 1:]
        else:
            h = self.backbone(positional_encoding(self._normalised(points), self.cfg.pe_freqs_position))
            raw = self.density_head(h)[:, 0]
        bias = self.density_bias
        if self.cfg.shell > 0:
            lo, hi = self.aabb[0], self.aabb[1]
            d = torch.cat([points - lo, hi - points], -1)            # [N, 6] distance to each face (inside ≥ 0)
            d = torch.where(self.shell_faces > 0, d, torch.full_like(d, 1e9)).amin(-1)
            ramp = (1.0 - d / (self.cfg.shell * float((hi - lo).norm()))).clamp(0.0, 1.0)
            bias = bias + (self.shell_bias - self.density_bias) * self.shell_weight * ramp
        sigma = nn.functional.softplus(raw + bias) * self.density_scale
        r = box_radius(points, self.aabb)
        if self.cfg.contraction:
            # density per *contracted* length: beyond the box a unit of grid spans r² times more metres, so the
            # same head output means the same opacity per grid step everywhere (and the far shell does not start
            # as an opaque fog: at r = 64 one stratum spans ~4000 reference steps)
            sigma = sigma / r.clamp_min(1.0).square()
        inside = r <= (self.cfg.far_radius if self.cfg.contraction else 1.0)
        return torch.where(inside, sigma, torch.zeros_like(sigma)), h

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """float [N] σ at world points [N, 3] (geometry branch only; for occupancy grids and meshing).
        Zero outside the scene box."""
        return self.geometry_features(points)[0]

    # ------------------------------------------------------------------ heads
    def _light_head(self, h: torch.Tensor, l_env: torch.Tensor) -> torch.Tensor:
        """``light_head(cat([h, l_env]))`` [N, 27] for one global ``l_env`` [9, 3]: its 27 inputs are the same for
        every point, so the first layer takes them as part of its bias instead of a [N, D + 27] concatenation."""
        first = self.light_head[0]
        d = h.shape[1]
        bias = first.bias + first.weight[:, d:] @ l_env.reshape(27).to(h)
        z = nn.functional.linear(h, first.weight[:, :d], bias)
        for layer in self.light_head[1:]:
            z = layer(z)
        return z

    def heads(
        self,
        h: torch.Tensor,
        view_dirs: torch.Tensor | None = None,
        l_env: torch.Tensor | None = None,
        shading: Literal["pbr", "radiance", "none"] = "pbr",
    ) -> FieldOutputs:
        """Run the heads on shared features ``h`` [N, D] (of points, or accumulated along rays).

        Returns :class:`FieldOutputs` with ``density`` left empty (size 0).
        """
        normal = nn.functional.normalize(self.normal_head(h), dim=-1, eps=1e-6)
        logits = self.semantic_head(h)
        out = FieldOutputs(density=h.new_zeros(0), normal=normal, semantic_logits=logits)
        if shading == "pbr":
            s = torch.softmax(logits.detach(), -1)
            mat = torch.sigmoid(self.material_head(torch.cat([h, s], -1)))
            out.albedo, out.roughness, out.metallic = mat[:, :3], mat[:, 3], mat[:, 4]
            if l_env is not None:
                if self.light_head is not None:
                    # bounded: |Δl_k| ≤ ½·|L00| per channel (a local correction of the room's light, not a second
                    # light source; unbounded, it can blow up to 10x the ambient level on white-background scenes)
                    bound = 0.5 * l_env.reshape(1, 9, 3)[:, :1, :].abs().to(h) + 1e-3
                    z = self._light_head(h, l_env).reshape(-1, 9, 3)
                    if self.cfg.light_residual_colour == "grey":
                        z = z.mean(-1, keepdim=True)  # one factor per coefficient, for every channel
                    res = torch.tanh(z) * bound
                    out.light_residual = res
                    out.light = l_env.reshape(1, 9, 3).to(h) + res
                else:
                    out.light = l_env.reshape(1, 9, 3).to(h).expand(h.shape[0], 9, 3)
        elif shading == "radiance":
            if view_dirs is None:
                raise ConfigError("the radiance head needs view_dirs")
            d = positional_encoding(view_dirs, self.cfg.pe_freqs_direction)
            # the head's sigmoid is sRGB-encoded (dark linear values sit at logits near -2, not -5, so the head
            # does not saturate on dark scenes); radiance is linear like everything the renderer composites
            out.radiance = srgb_to_linear(torch.sigmoid(self.radiance_head(torch.cat([h, d], -1))))
        return out

    # ------------------------------------------------------------------ full query
    def forward(
        self,
        points: torch.Tensor,
        view_dirs: torch.Tensor | None = None,
        l_env: torch.Tensor | None = None,
        shading: Literal["pbr", "radiance", "none"] = "pbr",
    ) -> FieldOutputs:
        """Query every head at world points.

        Args:
            points: float [N, 3] world positions, metres.
            view_dirs: float [N, 3] unit ray directions (camera -> point); needed for ``radiance``.
            l_env: float [9, 3] global SH light (SPEC convention); needed for the lighting head.
            shading: which heads to run — ``pbr`` (structure, semantics, material, lighting), ``radiance``
                (structure, semantics, radiance), ``none`` (structure and semantics only).

        Returns:
            :class:`FieldOutputs`.
        """
        density, h = self.geometry_features(points)
        out = self.heads(h, view_dirs, l_env, shading)
        out.density = density
        return out

