"""A trained run: :func:`load_run` reads a run directory written by :func:`~toolkit.train.train` into a :class:`Run`
(field, background, light, occupancy, the training scene and its W maps) for rendering, evaluation and export;
:func:`field_callables` / :func:`load_field_callables` give the meshing and baking stages the field as callables.

Example:
    >>> run = load_run("out/run")                                   # doctest: +SKIP
    >>> img = run.render(run.train_scene.cameras, 0)               # a RenderedImage  # doctest: +SKIP
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, NamedTuple

import torch

from .._checks import DarsError
from ..cameras import Cameras
from ..field import DarsField
from ..pipeline import Background, RenderConfig, RenderedImage, RenderInputs, render_dars_context, render_image
from ..pixels import PackedViews
from ..priors import priors_path
from ..sampling import OccupancyGrid
from ..scene import Scene, load_scene
from .config import TrainConfig
from .data import prepare_data
from .folder import find_run, read_checkpoint, read_run_config, run_scene_options

__all__ = ["Run", "load_run", "render_views", "FieldCallables", "field_callables", "load_field_callables",
           "run_field_callables", "render_view_maps", "light_gain_map", "light_tint_map", "light_residual_off"]


@dataclass
class Run:
    """A trained run loaded for rendering, evaluation and export (:func:`load_run`).

    Attributes:
        path: the run directory.
        cfg: its :class:`~toolkit.train.TrainConfig` (``config.json``).
        scene_path, split: the scene and split it trained on.
        field, background, l_env, occupancy: the trained state (l_env: float [9, 3] SH light).
        train_scene: the training split (its box, near/far and cameras are the run's).
        weight_maps: W maps of the training views, packed (:class:`toolkit.pixels.PackedViews`, uint8
            ``quantised``; ``[i]`` gives view i as float [H, W] in [0, 1]) for DARS at render time, or None.
        step, elapsed: training steps and seconds done.
        meta: ``config.json`` as a dict (priors used, initial light, ...).
    """

    path: Path
    cfg: TrainConfig
    scene_path: str
    split: str
    field: DarsField
    background: Background
    l_env: torch.Tensor
    occupancy: OccupancyGrid
    train_scene: Scene
    weight_maps: PackedViews | None
    step: int
    elapsed: float
    meta: dict

    def dars_for(self, c2w: torch.Tensor):
        """DARS render context for a camera pose (None when the run has DARS off)."""
        if not self.cfg.render_sampler.dars or self.weight_maps is None:
            return None
        return render_dars_context(self.train_scene.cameras, self.weight_maps, c2w, self.cfg.render_sampler.n_neighbours)

    @property
    def downscale(self) -> int:
        """The factor the run's photos were shrunk by (``dars train --downscale``; 1 for runs written before it)."""
        return run_scene_options(self.meta)["downscale"]

    def load_split(self, split: str) -> Scene:
        """Split ``split`` of the run's scene at the run's image size and in its frame (``downscale``, ``upright``)."""
        return load_scene(self.scene_path, split, **run_scene_options(self.meta))

    def priors_dir(self, stage: str) -> Path:
        """Where this run read (or would have read) the ``stage`` prior: ``--priors DIR`` if training had one."""
        return priors_path(self.train_scene, stage, self.meta.get("priors_root"))

    def render_config(self, **overrides) -> RenderConfig:
        """This run's :class:`~toolkit.pipeline.RenderConfig`: its ``render_sampler``, shading, ``deferred`` setting and
        the training scene's near/far; ``overrides`` replace fields (e.g. ``sampler=...``, ``deferred=False``)."""
        cfg = RenderConfig(sampler=self.cfg.render_sampler, shading=self.cfg.shading, deferred=self.cfg.deferred,
                           near=self.train_scene.near, far=self.train_scene.far)
        return replace(cfg, **overrides)

    def render(self, cameras: Cameras, index: int, *, l_env: torch.Tensor | None = None,
               outputs_hook: Callable | None = None, **overrides) -> RenderedImage:
        """Render every output of camera ``index`` with this run's settings (:func:`toolkit.pipeline.render_image`).

        Args:
            cameras: the cameras (any split, or a path such as :func:`toolkit.cameras.orbit_cameras`).
            index: which camera.
            l_env: float [9, 3] global light instead of the run's (None: the run's).
            outputs_hook: see :func:`toolkit.pipeline.render_rays` (relighting, material edits).
            **overrides: :class:`~toolkit.pipeline.RenderConfig` fields (``sampler``, ``deferred``, ``chunk`` ...).
                The DARS context of the camera is used when the sampler has DARS on (and the run has W maps).
        """
        cfg = self.render_config(**overrides)
        dars = self.dars_for(cameras.c2w[index]) if cfg.sampler.dars else None
        inputs = RenderInputs(self.occupancy, self.l_env if l_env is None else l_env, self.background,
                              self.train_scene.aabb.to(cameras.device), dars)
        return render_image(self.field, cameras, index, cfg, inputs, outputs_hook)


def load_run(run_dir: str | Path, checkpoint: str | Path | None = None, device: str = "cpu",
             with_weights: bool = True) -> Run:
    """Load a run directory written by :func:`train` (``checkpoint`` picks a snapshot).

    Raises:
        DarsError: not a run, a corrupt ``config.json`` or checkpoint, or the run's scene is gone (naming the file).
    """
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.json"
    meta, ck_path = find_run(run_dir, checkpoint)
    cfg = read_run_config(meta, cfg_path)
    ck = read_checkpoint(ck_path, map_location=device, run_dir=run_dir)
    scene = load_scene(meta["scene"], meta.get("split", "train"), **run_scene_options(meta))
    if cfg.scene_box is not None:  # the box the run was trained with (fitted to the data when the file has none)
        scene = replace(scene, aabb=torch.tensor(cfg.scene_box, dtype=torch.float32))
    fld = DarsField(cfg.field, scene.aabb).to(device)
    bg = Background(ck.get("background_mode", "env"))
    try:
        fld.load_state_dict(ck["field"])
        bg.load_state_dict(ck["background"])
        occupancy = OccupancyGrid.from_state_dict(ck["occupancy"]).to(device)
    except (RuntimeError, KeyError, TypeError, ValueError) as e:
        raise DarsError(f"checkpoint {ck_path} does not fit the run's config.json ({str(e).splitlines()[0][:200]}); "
                        "was it copied from another run? Use the checkpoint.pt written with this config.json") from e
    fld.eval()
    wm = _weight_maps(scene, cfg, meta) if with_weights and cfg.render_sampler.dars else None
    return Run(path=run_dir, cfg=cfg, scene_path=meta["scene"], split=meta.get("split", "train"), field=fld,
               background=bg.to(device), l_env=ck["l_env"].to(device),
               occupancy=occupancy, train_scene=scene,
               weight_maps=wm, step=int(ck["step"]), elapsed=float(ck["elapsed"]), meta=meta)


def _weight_maps(scene: Scene, cfg: TrainConfig, meta: dict) -> PackedViews | None:
    """The W maps of a run's training views (DARS at render time), from the priors it trained with."""
    data_cfg = replace(cfg, albedo_supervision=False)
    return prepare_data(scene, data_cfg, log=lambda m: None, priors_root=meta.get("priors_root"),
                        with_images=False).weights


def render_views(run: Run, cameras: Cameras, keys: list[str], out_dir: str | Path, *, limit: int = 0,
                 l_env: torch.Tensor | None = None, outputs_hook: Callable | None = None,
                 progress: bool = True) -> list[str]:
    """Render cameras with the run's settings and write every decomposed output as ``<key>_<output>.png``.

    Args:
        run: the run.
        cameras: the views; ``keys`` [len(cameras)] names their files.
        out_dir: output folder.
        limit: render at most this many views (0: all).
        l_env, outputs_hook: see :meth:`Run.render` (relighting, material edits).
        progress: a progress bar on stderr.

    Returns:
        the paths written, view by view (outputs in :func:`toolkit.visualise.render_output_images` order).
    """
    from tqdm import tqdm

    from ..io import write_png
    from ..visualise import render_output_images

    out = Path(out_dir)
    n = len(cameras) if not limit else min(limit, len(cameras))
    written = []
    for i in tqdm(range(n), desc="render", file=sys.stderr, disable=not progress):
        image = run.render(cameras, i, l_env=l_env, outputs_hook=outputs_hook)
        for name, img in render_output_images(image, srgb=run.train_scene.srgb).items():
            p = out / f"{keys[i]}_{name}.png"
            write_png(p, img)
            written.append(str(p))
    return written


class FieldCallables(NamedTuple):
    """A trained field as callables for meshing and baking (:func:`load_field_callables`).

    Attributes:
        density_fn: ``density_fn(points [N, 3]) -> [N]`` σ in 1/metre.
        material_fn: ``material_fn(points [N, 3], normals=None) -> dict`` (see :func:`field_callables`).
        aabb: float [2, 3] scene box, metres.
        sh: float [9, 3] the run's global SH light, or None.
        cameras: the training cameras (TSDF fusion, unseen-face removal), or None.
        space: the field's :class:`toolkit.space.SceneSpace` (None: bounded by ``aabb``). With contraction the
            region to mesh comes from the training rays (:func:`toolkit.mesh.surface_region`).
        views: ``views(cameras) -> ViewMaps``: the field's own composited renders (albedo, roughness, metallic,
            colour, depth, opacity; ``views(cameras, light_gain=True)`` also the light gain where the callable takes
            that keyword) at ``cameras`` (:func:`render_view_maps`), for the view-projected bake
            (:mod:`toolkit.viewbake`); None when the field has no renderer (the bake queries points).
        background: float [h, w, 3] the run's learned background as a lat-long linear radiance map
            (:meth:`toolkit.pipeline.Background.radiance_map`; the GLB's backdrop, :mod:`toolkit.backdrop`), or None.
        room_layout: the room's box the run trained with (:class:`toolkit.layout.RoomLayout`, the ``room_layout`` of
            its ``config.json``; the mesh's walls and floor are flattened onto its faces, :mod:`toolkit.mesh.planes`),
            or None.
    """

    density_fn: Callable
    material_fn: Callable
    aabb: torch.Tensor
    sh: torch.Tensor | None
    cameras: Cameras | None
    space: Any = None
    views: Callable | None = None
    background: torch.Tensor | None = None
    room_layout: Any = None


def field_callables(run: Run, chunk: int = 65536):
    """(density_fn, material_fn) of a loaded run, for meshing and baking (no gradients, chunked).

    ``density_fn(points [N, 3]) -> [N]``; ``material_fn(points [N, 3], normals=None) -> dict`` with ``albedo``
    [N, 3] (linear), ``roughness`` [N], ``metallic`` [N], ``normal`` [N, 3] (the normal head, unit) and
    ``semantic`` [N] (argmax class id). A ``radiance`` run (standard NeRF) has no materials: its albedo is
    its view-averaged radiance seen from above and roughness/metallic take defaults (1, 0).
    """
    fld = run.field
    dev = next(fld.parameters()).device

    @torch.no_grad()
    def density_fn(points: torch.Tensor) -> torch.Tensor:
        pts = torch.as_tensor(points, dtype=torch.float32)
        return torch.cat([fld.density(pts[i:i + chunk].to(dev)).cpu() for i in range(0, pts.shape[0], chunk)]) \
            if pts.shape[0] else pts.new_zeros(0)

    @torch.no_grad()
    def material_fn(points: torch.Tensor, normals: torch.Tensor | None = None) -> dict:
        pts = torch.as_tensor(points, dtype=torch.float32)
        keys = ("albedo", "roughness", "metallic", "normal", "semantic")
        parts: dict[str, list] = {k: [] for k in keys}
        for i in range(0, pts.shape[0], chunk):
            p = pts[i:i + chunk].to(dev)
            if run.cfg.shading == "pbr":
                o = fld(p, None, None, "pbr")
                parts["albedo"].append(o.albedo.cpu())
                parts["roughness"].append(o.roughness.cpu())
                parts["metallic"].append(o.metallic.cpu())
            else:
                d = torch.tensor([[0.0, 0.0, -1.0]], device=dev).expand(p.shape[0], 3)
                o = fld(p, d, None, "radiance")
                parts["albedo"].append(o.radiance.cpu())
                parts["roughness"].append(torch.ones(p.shape[0]))
                parts["metallic"].append(torch.zeros(p.shape[0]))
            parts["normal"].append(o.normal.cpu())
            parts["semantic"].append(o.semantic_logits.argmax(-1).cpu())
        return {k: torch.cat(v) for k, v in parts.items()}

    return density_fn, material_fn


def load_field_callables(run_dir: str | Path, checkpoint: str | Path | None = None) -> FieldCallables:
    """:class:`FieldCallables` ``(density_fn, material_fn, aabb [2, 3], sh [9, 3], cameras)`` of a run directory (see
    :func:`field_callables`); ``cameras`` are the training cameras (for TSDF fusion and unseen-face removal).

    Raises:
        DarsError: ``run_dir`` is not a training run.
    """
    return run_field_callables(load_run(run_dir, checkpoint, with_weights=False))


def run_field_callables(run: Run) -> FieldCallables:
    """:class:`FieldCallables` of a loaded run, with its renderer for the view-projected bake."""
    from ..layout import RoomLayout

    d, m = field_callables(run)
    layout = run.meta.get("room_layout")
    return FieldCallables(d, m, run.train_scene.aabb.clone(), run.l_env.detach().cpu().clone(),
                          run.train_scene.cameras, run.field.space.to("cpu") if run.cfg.field.contraction else None,
                          lambda cameras, light_gain=False: render_view_maps(run, cameras, light_gain=light_gain),
                          run.background.radiance_map().detach().float().cpu().clone(),
                          RoomLayout.from_json(layout) if layout else None)


VIEW_MAP_KEYS = ("albedo", "roughness", "metallic", "normal", "rgb")
"""The composited outputs :func:`render_view_maps` keeps: the material channels and the rendered (unit, world) normal
a GLB bakes, and the colour (linear RGB, the background composited) its backdrop takes where the mesh is not
(:func:`toolkit.backdrop.backdrop_from_views`).
Asked for, a field with a light residual also gets ``light_gain`` (:func:`light_gain_map`)."""

LIGHT_GAIN_MAX = 8.0
"""``light_gain`` is clamped to [0, this]."""


def light_gain_map(shaded: torch.Tensor, shaded_global: torch.Tensor, opacity: torch.Tensor,
                   min_opacity: float = 0.5) -> torch.Tensor:
    """How much the field's per-point light Δl(x) brightens (> 1) or darkens (< 1) each pixel: the luminance of its
    shaded colour (diffuse + specular, linear) over that of the same render lit by the global SH alone. 1 where the
    pixel is less opaque than ``min_opacity`` or shades to (nearly) black under the global light.

    Args:
        shaded, shaded_global: float [..., 3] composited diffuse + specular with and without the residual.
        opacity: float [...] the pixels' opacity.
    """
    num, den = _luminance(shaded), _luminance(shaded_global)
    ok = (opacity >= min_opacity) & (den > 1e-4)
    gain = torch.where(ok, num / den.clamp_min(1e-4), torch.ones_like(num))
    return gain.clamp(0.0, LIGHT_GAIN_MAX)


def _luminance(rgb: torch.Tensor) -> torch.Tensor:
    """Rec. 709 luminance [...] of linear ``rgb`` [..., 3]."""
    from ..metrics import REC709_LUMA

    return rgb @ torch.tensor(REC709_LUMA, dtype=rgb.dtype, device=rgb.device)


def light_tint_map(shaded: torch.Tensor, shaded_global: torch.Tensor, opacity: torch.Tensor,
                   min_opacity: float = 0.5) -> torch.Tensor:
    """The colour of the field's per-point light Δl(x) that :func:`light_gain_map`'s one luminance factor drops:
    per channel, the shaded colour over that of the same render under the global SH alone, divided by the luminance
    gain. Float [..., 3] in [0, :data:`toolkit.bake.LIGHT_TINT_SCALE`] (what the GLB's texture holds), of
    luminance 1 where nothing clamps; 1 where the pixel is less opaque than ``min_opacity`` or a channel shades to
    (nearly) black under the global light.

    A viewer that multiplies its shaded colour by gain × tint shades each pixel with the field's own light colour
    (an RGB residual, ``FieldConfig.light_residual_colour="rgb"``, tints a wall warmer under a lamp or bluer under a
    window); the GLB's occlusion channel can only hold the gain."""
    from ..bake import LIGHT_TINT_SCALE

    num, den = _luminance(shaded), _luminance(shaded_global)
    ok = (opacity >= min_opacity) & (den > 1e-4) & (num > 1e-4)
    per = shaded / shaded_global.clamp_min(1e-4)
    tint = per / (num / den.clamp_min(1e-4)).clamp_min(1e-4)[..., None]
    tint = torch.where(ok[..., None] & (shaded_global > 1e-4), tint, torch.ones_like(tint))
    return tint.clamp(0.0, LIGHT_TINT_SCALE)


@contextmanager
def light_residual_off(run: Run):
    """For the ``with`` block, the run's field without its light residual head (shaded by the global SH alone);
    the head is put back after, whatever happens."""
    head = run.field.light_head
    run.field.light_head = None
    try:
        yield run
    finally:
        run.field.light_head = head


def render_view_maps(run: Run, cameras: Cameras, progress: bool = True, light_gain: bool = False):
    """The run's own renders at ``cameras`` (one pixel grid), as :class:`toolkit.viewbake.ViewMaps`: composited
    albedo (clamped to [0, 1]), roughness, metallic, normal, colour, depth and opacity, rendered with the run's
    settings (the DARS sampler's W maps included when the run has them). With ``light_gain``, a field with a
    per-point light residual Δl(x) is rendered a second time with the global SH alone (:func:`light_residual_off`),
    for the ``light_gain`` map (:func:`light_gain_map`: what the GLB's occlusion channel carries,
    :func:`toolkit.asset.bake_mesh`) and the ``light_tint`` map (:func:`light_tint_map`: its colour, the GLB's
    light-tint texture)."""
    from tqdm import tqdm

    from ..viewbake import ViewMaps

    if run.cfg.render_sampler.dars and run.weight_maps is None:  # loaded without them (load_field_callables)
        run.weight_maps = _weight_maps(run.train_scene, run.cfg, run.meta)
    with_gain = light_gain and getattr(run.field, "light_head", None) is not None and run.cfg.shading == "pbr"
    keys = (*VIEW_MAP_KEYS, "depth", "opacity")
    maps: dict[str, list] = {k: [] for k in (*keys, *(("light_gain", "light_tint") if with_gain else ()))}
    with torch.no_grad():
        for i in tqdm(range(len(cameras)), desc="rendering views for the bake", file=sys.stderr, unit="view",
                      disable=not progress):
            o = run.render(cameras, i)
            for k in keys:
                maps[k].append(getattr(o, k).detach().float().cpu())
            if with_gain:
                with light_residual_off(run):
                    g = run.render(cameras, i)
                shaded, shaded_global = o.diffuse + o.specular, g.diffuse + g.specular
                maps["light_gain"].append(light_gain_map(shaded, shaded_global, o.opacity).float().cpu())
                maps["light_tint"].append(light_tint_map(shaded, shaded_global, o.opacity).float().cpu())
    stacked = {k: torch.stack(v) for k, v in maps.items()}
    stacked["albedo"] = stacked["albedo"].clamp(0, 1)
    return ViewMaps(cameras.to("cpu"), stacked.pop("depth"), stacked.pop("opacity"), stacked)
