"""The light a baked GLB still lacks where the viewer shows it: a per-vertex correction from the viewer's own renders.

The bake fits each texel's occlusion and light tint at the views whose *field depth* agrees with the texel
(:func:`toolkit.viewbake.fit_light`). A viewer shows something else at a pixel wherever the mesh and the field's
depth part (a wall meshed a few centimetres off, an edge, a hole the backdrop fills) and wherever its texture filter
averages texels the fit treated one by one. So :func:`viewer_light_correction` renders the GLB with the preview
(:class:`viewers.preview.OffscreenPreview`) at the views the bake was fitted to, casts every pixel's ray against the
mesh (the first front face it meets: what a viewer that culls back faces draws there,
:func:`toolkit.backdrop.front_hits`), and fits one RGB factor per mesh vertex that brings the viewer's linear colour
C to the field's F there: c = Σ w C F / Σ w C² over the pixels around the vertex (barycentric weights; w as in
:func:`~toolkit.viewbake.fit_light`). :func:`toolkit.asset.build_asset`, given :func:`viewer_correction` (``dars
export-asset`` gives it), re-bakes with the light multiplied by c (``AssetConfig.viewer_fit``; README, "The GLB
refitted at its own views").
"""

from __future__ import annotations

import numpy as np

__all__ = ["viewer_correction", "viewer_light_correction", "CORRECTION_RANGE"]

CORRECTION_RANGE = (0.25, 4.0)
"""A vertex's correction is clamped to this range (a factor of 4 either way: an edge pixel that sees a different
surface in the viewer than in the field must not blacken or blow out a vertex)."""


def viewer_light_correction(glb, mesh, maps, saturated: float = 0.995, min_opacity: float = 0.5) -> np.ndarray:
    """One RGB light factor per vertex of ``mesh`` that makes the viewer's render of ``glb`` at ``maps``' cameras
    show the field's colour there.

    Args:
        glb: the baked GLB (path or loaded :class:`export.gltf.GltfAsset`) of ``mesh``.
        mesh: the :class:`toolkit.mesh.Mesh` the GLB was unwrapped from (world coordinates).
        maps: :class:`toolkit.viewbake.ViewMaps` holding the field's linear colour ``rgb`` and opacity.
        saturated: pixels the viewer shows at or above this sRGB value in any channel are left out (the clamp hides
            how far off they are).
        min_opacity: pixels where the field's opacity is below this are left out (the field shows no surface).

    Returns:
        float32 [V, 3] factors in :data:`CORRECTION_RANGE`; 1 where no pixel sees a vertex.

    Raises:
        DarsError: no headless OpenGL context (:func:`viewers.gl.create_headless_context`).
    """
    from toolkit.backdrop import front_hits
    from toolkit.bake import ray_scene
    from toolkit.cameras import generate_rays
    from toolkit.io import srgb_to_linear
    from toolkit.pinhole import PinholeCamera
    from toolkit.viewbake import FIT_WEIGHT_EXPONENT

    from .preview import OffscreenPreview

    if "rgb" not in maps.values:
        raise ValueError(f"viewer_light_correction needs the field's colour in the view maps; they hold "
                         f"{sorted(maps.values)}")
    vertices = np.asarray(mesh.vertices, np.float32)
    faces = np.asarray(mesh.faces, np.int64)
    scene = ray_scene(vertices, faces)
    extent = float(np.linalg.norm(vertices.max(0) - vertices.min(0))) if len(vertices) else 1.0
    num = np.zeros((len(vertices), 3))
    den = np.zeros((len(vertices), 3))
    cams = maps.cameras
    with OffscreenPreview(glb) as view:
        for i in range(len(cams)):
            shown = view.render(PinholeCamera.from_cameras(cams, i, near=extent * 1e-3, far=extent * 10))
            srgb = np.asarray(shown.to_float(), np.float64)[..., :3]
            h, w = srgb.shape[:2]
            rays = generate_rays(cams, [i])
            prim, bary_uv = front_hits(scene, rays.origins.numpy(), rays.directions.numpy(), extent)
            prim = prim.reshape(h, w)
            bary_uv = bary_uv.reshape(h, w, 2)
            ok = (np.asarray(shown.mask) & (prim >= 0) & (srgb.max(-1) < saturated)
                  & (maps.opacity[i].numpy() >= min_opacity))
            if not ok.any():
                continue
            c = srgb_to_linear(srgb[ok])
            f = maps.values["rgb"][i].numpy().astype(np.float64)[ok]
            wt = np.clip(f, 1e-3, 1.0) ** FIT_WEIGHT_EXPONENT
            b = bary_uv[ok]
            bary = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], 1)
            corner = faces[prim[ok]]
            for k in range(3):
                for ch in range(3):
                    num[:, ch] += np.bincount(corner[:, k], wt[:, ch] * c[:, ch] * f[:, ch] * bary[:, k],
                                              minlength=len(vertices))
                    den[:, ch] += np.bincount(corner[:, k], wt[:, ch] * c[:, ch] ** 2 * bary[:, k],
                                              minlength=len(vertices))
    out = np.where(den > 1e-8, num / np.maximum(den, 1e-8), 1.0)
    return np.clip(out, *CORRECTION_RANGE).astype(np.float32)


def viewer_correction(mesh, uvmesh, textures, sh, extras: dict, maps) -> np.ndarray:
    """:func:`viewer_light_correction` of a bake not yet written: the GLB of ``uvmesh`` and ``textures`` (with
    ``sh`` and the GLB ``extras``) goes to a temporary file first. What :func:`toolkit.asset.build_asset` takes as
    ``viewer_correction``.

    Returns:
        float32 [V, 3] per vertex of ``mesh``.
    """
    import tempfile
    from pathlib import Path

    from export.gltf import export_gltf

    with tempfile.TemporaryDirectory(prefix="dars-viewer-fit-") as tmp:
        glb = export_gltf(uvmesh, textures, Path(tmp) / "draft.glb", sh=sh, extras=extras)
        return viewer_light_correction(glb, mesh, maps)
