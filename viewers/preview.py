"""Stage 15a — moderngl preview of a baked GLB with the training shading (SPEC stage 15).

The fragment shader calls ``dars_shade_pbr``, generated from :mod:`toolkit.shading` by :mod:`viewers.shading_glsl`
(a test holds the two together). Per fragment:

* base colour: ``baseColorTexture`` uploaded as ``SRGB8_ALPHA8`` (hardware sRGB → linear before filtering) times
  ``baseColorFactor``; ORM: R occlusion (scales the lit colour), G roughness, B metallic (times the factors);
  tangent-space normal map decoded with the
  GLB's TANGENT (xyz re-orthogonalised against the interpolated normal, bitangent ``w · cross(n, t)``) — the frame
  :mod:`toolkit.bake` encodes with. Textures sample trilinearly with clamp-to-edge, as the GLB's sampler says,
  but with the filter narrowed to a pixel's own footprint less the blur the bake already put in the texture (the
  GLB's ``_TEXTURE_BLUR`` vertex attribute, b texels, :func:`toolkit.viewbake.face_texture_blur`): a footprint of
  ρ texels looks up a mip footprint of √((ρ² − 2b²) / 3), matching variances (see the shader), and the finest level
  while ρ² ≤ 2b². Plain trilinear mip-mapping (what other glTF viewers do) blurs the baked detail a second time.
* Geometry is drawn as stored (glTF +y up); the camera is rotated into that frame (:mod:`viewers.camera`) and the
  shading normal and view direction are rotated back to the dars world (+z up) where the SH lives.
* Output: ``lit`` = linear radiance × 2^exposure → clamp → sRGB; ``albedo`` = base colour in sRGB; ``roughness`` /
  ``metallic`` = the value as grey; ``normals`` = world normal ``(n + 1)/2`` (as :func:`toolkit.visualise.colourise_normals`);
  ``semantics`` = :data:`toolkit.visualise.LABEL_COLOURS` per semantic primitive (unlabelled black). Background in
  ``lit`` mode: the GLB's backdrop where it has one and the light is its own (:mod:`toolkit.backdrop`: the field's
  colour where the mesh left training pixels uncovered, else its learned background, blended per direction with the
  SH radiance by its visibility — ``visibility · backdrop + (1 − visibility) · SH``; where it has a box map, a ray
  that leaves the room's box through one of its faces reads that map at its exit point, mixed over by its weight:
  :class:`toolkit.backdrop.BoxProjection`), else the SH environment's
  radiance along each view ray (divided by the GLB's ``extras.dars.light_scale``: its SH lights the mesh at that
  multiple of the run's light, whose occlusion channel divides it back, :func:`viewers.lighting.light_scale`); a flat
  grey in the other modes. Alpha is 1 on the mesh, 0 elsewhere (the coverage mask of :class:`PreviewImage`).
* No MSAA offscreen (one sample per pixel centre, like the field's renderer); the window asks for 4x MSAA.

Headless rendering uses ``moderngl.create_standalone_context(backend="egl", require=330)`` (Mesa llvmpipe on CPU).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from export.gltf import WORLD_TO_GLTF, GltfAsset, load_glb
from toolkit._checks import ConfigError, SceneError
from toolkit.pinhole import PinholeCamera
from toolkit.shading import ShadingConfig

from .camera import default_camera, gltf_c2w, view_projection_gltf
from .gl import create_headless_context
from .shading_glsl import DFG_UNIFORM, GLSL_VERSION, dfg_texture_bytes, glsl_shading_source

__all__ = ["BACKGROUNDS", "MODES", "Mode", "PreviewConfig", "PreviewImage", "PreviewRenderer", "OffscreenPreview",
           "create_headless_context", "render_preview", "resolve_asset_path"]

Mode = Literal["lit", "albedo", "roughness", "metallic", "normals", "semantics"]
MODES: tuple[str, ...] = ("lit", "albedo", "roughness", "metallic", "normals", "semantics")
BACKGROUNDS: tuple[str, ...] = ("auto", "backdrop", "sh", "colour")


@dataclass(frozen=True)
class PreviewConfig:
    """Options of a preview render."""

    mode: Mode = "lit"
    """What to show (module docstring)."""
    exposure: float = 0.0
    """Exposure in stops for ``lit``: colour × 2^exposure before the sRGB transfer."""
    background: Literal["auto", "backdrop", "sh", "colour"] = "auto"
    """Behind the mesh in ``lit`` mode: ``backdrop``: the GLB's backdrop (:mod:`toolkit.backdrop`; an error when it
    has none); ``sh``: the SH light's radiance; ``auto``: the backdrop when the GLB has one and the light is the
    GLB's own (a relit view shows the new light's radiance), else ``sh``; ``colour``: ``background_colour``."""
    background_colour: tuple[float, float, float] = (0.08, 0.08, 0.08)
    """Display (sRGB) colour of the background when not drawing the SH environment."""
    shading: ShadingConfig = field(default_factory=ShadingConfig)
    """Shading options (the same dataclass the trainer uses)."""
    texture_filter: Literal["footprint", "trilinear"] = "footprint"
    """``footprint``: the mip filter narrowed to the pixel's footprint less the GLB's ``_TEXTURE_BLUR`` (module
    docstring; what the WebXR page does); ``trilinear``: plain trilinear mip-mapping, as other glTF viewers draw."""

    def __post_init__(self) -> None:
        if self.texture_filter not in ("footprint", "trilinear"):
            raise ConfigError(f"texture_filter={self.texture_filter!r} is not valid: choose 'footprint' or 'trilinear'")
        if self.mode not in MODES:
            raise ConfigError(f"mode={self.mode!r} is not valid: choose one of {', '.join(MODES)}")
        if self.background not in BACKGROUNDS:
            raise ConfigError(f"background={self.background!r} is not valid: choose one of {', '.join(BACKGROUNDS)}")
        if not np.isfinite(self.exposure):
            raise ConfigError(f"exposure={self.exposure} must be finite")


@dataclass(frozen=True)
class PreviewImage:
    """Result of :func:`render_preview`.

    Attributes:
        image: uint8 [H, W, 3] sRGB display image, row 0 at the top.
        mask: bool [H, W] pixels covered by the mesh.
        camera: the camera rendered.
        mode: the mode rendered.
    """

    image: np.ndarray
    mask: np.ndarray
    camera: PinholeCamera
    mode: str

    def to_float(self) -> np.ndarray:
        """float32 [H, W, 3] in [0, 1]."""
        return self.image.astype(np.float32) / 255.0


def resolve_asset_path(path: str | Path) -> Path:
    """A ``.glb`` / ``.gltf`` file, or a directory holding ``scene.glb`` (the output of ``dars export-asset``).

    Raises:
        SceneError: nothing loadable at ``path``.
    """
    path = Path(path)
    if path.is_dir():
        if (path / "scene.glb").is_file():
            return path / "scene.glb"
        raise SceneError(f"{path} is a directory without scene.glb; give a .glb file or the --out directory of "
                         "`dars export-asset RUN --out DIR`")
    if not path.is_file():
        raise SceneError(f"asset not found: {path} (give a .glb/.gltf file or an export-asset directory)")
    if path.suffix.lower() not in (".glb", ".gltf"):
        raise SceneError(f"{path}: expected a .glb or .gltf file")
    return path


# ============================================================================================================ shaders
_MESH_VS = """
uniform mat4 u_view_proj;   // clip from glTF frame
in vec3 in_position;        // glTF frame (+y up), metres
in vec3 in_normal;
in vec4 in_tangent;
in vec2 in_uv;
in float in_blur;           // texels (_TEXTURE_BLUR; 0 without)
out vec3 v_position;
out vec3 v_normal;
out vec4 v_tangent;
out vec2 v_uv;
out float v_blur;
void main() {
    v_position = in_position;
    v_blur = in_blur;
    v_normal = in_normal;
    v_tangent = in_tangent;
    v_uv = in_uv;
    gl_Position = u_view_proj * vec4(in_position, 1.0);
}
"""

_MESH_FS = """
uniform sampler2D u_base_color;   // sRGB texture: reads linear
uniform sampler2D u_orm;          // R occlusion, G roughness, B metallic (linear)
uniform sampler2D u_normal_map;   // tangent space, (n + 1) / 2
uniform sampler2D u_light_tint;   // linear tint / u_tint_scale (extras.dars.light_tint; white, scale 1 without)
uniform float u_tint_scale;
uniform float u_texture_size;     // the base-colour texture's side, texels (v_blur's unit)
uniform bool u_trilinear;         // PreviewConfig.texture_filter == "trilinear": the GPU's own mip selection
uniform vec4 u_base_factor;
uniform vec2 u_metal_rough_factor;
uniform float u_normal_scale;
uniform bool u_has_tangents;
uniform bool u_double_sided;
uniform vec3 u_camera_pos;        // glTF frame
uniform mat3 u_gltf_to_world;
uniform vec3 u_sh[9];             // SPEC radiance SH, world frame
uniform int u_mode;               // 0 lit, 1 albedo, 2 roughness, 3 metallic, 4 normals, 5 semantics
uniform float u_exposure_scale;
uniform vec3 u_label_colour;
in vec3 v_position;
in vec3 v_normal;
in vec4 v_tangent;
in vec2 v_uv;
in float v_blur;
out vec4 out_colour;

// The texture filter, narrowed by the blur the bake already put in the texture (v_blur: texels one training pixel
// spans there, toolkit.viewbake.face_texture_blur). In variances: a pixel's own footprint, a box of rho texels (its
// longer axis), holds rho²/12; the baked detail already holds 2·b²/12 (a training pixel's box, b wide, at a random
// offset to the texel, averaged over views); a trilinear mip lookup of footprint r adds r²/4 (level box r²/12 and
// bilinear tent r²/6). So r² = (rho² − 2 b²) / 3, and the finest level where rho² ≤ 2 b². Without the attribute
// (b = 0) that is rho / sqrt(3). Derivatives are taken once here, in uniform control flow: every map shares
// TEXCOORD_0.
vec2 g_dx, g_dy;
vec4 dars_texture(sampler2D s, vec2 uv) { return textureGrad(s, uv, g_dx, g_dy); }

void main() {
    g_dx = dFdx(v_uv);
    g_dy = dFdy(v_uv);
    float rho2 = max(dot(g_dx, g_dx), dot(g_dy, g_dy));
    float b = v_blur / u_texture_size;
    float rest = rho2 - 2.0 * b * b;
    float narrow = u_trilinear ? 1.0 : (rest > 0.0 ? sqrt(rest / (3.0 * rho2)) : 0.0);
    g_dx *= narrow;
    g_dy *= narrow;
    vec3 N = normalize(v_normal);
    if (u_double_sided && !gl_FrontFacing) N = -N;
    vec3 n = N;
    if (u_has_tangents) {
        vec3 T = v_tangent.xyz - N * dot(N, v_tangent.xyz);
        float tl = length(T);
        if (tl > 1e-6) {
            T /= tl;
            vec3 B = cross(N, T) * (v_tangent.w < 0.0 ? -1.0 : 1.0);
            vec3 nt = dars_texture(u_normal_map, v_uv).xyz * 2.0 - 1.0;
            nt.xy *= u_normal_scale;
            vec3 p = T * nt.x + B * nt.y + N * nt.z;
            float pl = length(p);
            n = pl > 1e-6 ? p / pl : N;
        }
    }
    vec3 n_world = normalize(u_gltf_to_world * n);
    vec3 v_world = normalize(u_gltf_to_world * (u_camera_pos - v_position));
    vec4 base = dars_texture(u_base_color, v_uv) * u_base_factor;
    vec3 orm = dars_texture(u_orm, v_uv).rgb;
    float roughness = clamp(orm.g * u_metal_rough_factor.y, 0.0, 1.0);
    float metallic = clamp(orm.b * u_metal_rough_factor.x, 0.0, 1.0);
    vec3 albedo = clamp(base.rgb, 0.0, 1.0);
    vec3 display;
    if (u_mode == 0) {
        DarsShading s = dars_shade_pbr(albedo, roughness, metallic, n_world, v_world, u_sh);
        // glTF occlusion (ORM red) scales the SH lighting, diffuse and specular: three.js (the WebXR page) does
        // the same; dars bakes the field's per-point light gain into it (toolkit.asset.AssetConfig.light_occlusion)
        // and that light's colour into the light-tint texture (AssetConfig.light_tint)
        vec3 tint = dars_texture(u_light_tint, v_uv).rgb * u_tint_scale;
        display = dars_linear_to_srgb(clamp(s.colour * orm.r * tint * u_exposure_scale, 0.0, 1.0));
    } else if (u_mode == 1) {
        display = dars_linear_to_srgb(albedo);
    } else if (u_mode == 2) {
        display = vec3(roughness);
    } else if (u_mode == 3) {
        display = vec3(metallic);
    } else if (u_mode == 4) {
        display = n_world * 0.5 + 0.5;
    } else {
        display = u_label_colour;
    }
    out_colour = vec4(display, 1.0);
}
"""

_BACKGROUND_VS = """
in vec2 in_pos;
out vec2 v_ndc;
void main() { v_ndc = in_pos; gl_Position = vec4(in_pos, 1.0, 1.0); }
"""

_BACKGROUND_FS = """
uniform mat4 u_inv_view_proj;     // glTF frame from clip
uniform mat3 u_gltf_to_world;
uniform vec3 u_sh[9];
uniform float u_exposure_scale;
uniform bool u_use_sh;
uniform bool u_use_backdrop;
uniform sampler2D u_backdrop;     // lat-long (toolkit.backdrop): rgb linear radiance, a visibility
uniform bool u_use_box;           // the backdrop's box map (toolkit.backdrop.BoxProjection)
uniform sampler2D u_box_map;      // lat-long from the box's centre: rgb linear radiance, a weight
uniform vec3 u_eye;               // the camera's position, world
uniform mat3 u_box_axes;          // world -> box frame
uniform vec3 u_box_origin;
uniform vec3 u_box_lo;
uniform vec3 u_box_hi;
uniform vec3 u_box_centre;
uniform vec3 u_box_face_lo;       // 1 where the low face along that axis keys the box map
uniform vec3 u_box_face_hi;
uniform vec3 u_colour;
in vec2 v_ndc;
out vec4 out_colour;
void main() {
    if (!u_use_sh) { out_colour = vec4(u_colour, 0.0); return; }
    vec4 a = u_inv_view_proj * vec4(v_ndc, -1.0, 1.0);
    vec4 b = u_inv_view_proj * vec4(v_ndc, 1.0, 1.0);
    vec3 d = normalize(u_gltf_to_world * (b.xyz / b.w - a.xyz / a.w));  // the light arriving from d
    vec3 radiance = max(dars_sh_eval(u_sh, dars_sh_basis(d)), vec3(0.0));
    if (u_use_backdrop) {
        vec4 bd = texture(u_backdrop, dars_latlong_uv(d));
        radiance = mix(radiance, max(bd.rgb, vec3(0.0)), clamp(bd.a, 0.0, 1.0));
        if (u_use_box) {  // where the ray leaves the box (toolkit.backdrop.BOX_CONVENTION)
            vec4 key = dars_box_key(u_eye, d, u_box_axes, u_box_origin, u_box_lo, u_box_hi, u_box_face_lo,
                                    u_box_face_hi, u_box_centre);
            if (key.w > 0.5) {
                vec4 bx = texture(u_box_map, dars_latlong_uv(key.xyz));
                radiance = mix(radiance, max(bx.rgb, vec3(0.0)), clamp(bx.a, 0.0, 1.0));
            }
        }
    }
    out_colour = vec4(dars_linear_to_srgb(clamp(radiance * u_exposure_scale, 0.0, 1.0)), 0.0);
}
"""

_MODE_INDEX = {m: i for i, m in enumerate(MODES)}
_SRGB8_ALPHA8 = 0x8C43


def _set(prog, name: str, value) -> None:
    """Set a uniform if the linker kept it (unused uniforms are optimised away)."""
    if name in prog:
        prog[name].value = value


def _write_mat(prog, name: str, m: np.ndarray) -> None:
    if name in prog:
        prog[name].write(np.ascontiguousarray(np.asarray(m, dtype=np.float64).T, dtype=np.float32).tobytes())


def _label_runs(labels: np.ndarray | None, n_faces: int) -> list[tuple[int, int, int]]:
    """(first face, face count, label) runs of equal labels in face order (primitives are contiguous)."""
    if labels is None or n_faces == 0:
        return [(0, n_faces, 255)]
    change = np.flatnonzero(np.diff(labels.astype(np.int64))) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [n_faces]])
    return [(int(s), int(e - s), int(labels[s])) for s, e in zip(starts, ends)]


class PreviewRenderer:
    """GPU resources of one asset in a moderngl context, and the draw calls (module docstring).

    Args:
        ctx: a moderngl context (window or standalone).
        asset: a loaded GLB (:func:`export.gltf.load_glb`).
        sh: float [9, 3] SPEC radiance SH, world frame (default: :func:`viewers.lighting.resolve_sh`'s choice).
        shading: the shading compiled up front (others are compiled on first use: ``PreviewConfig.shading``).
    """

    def __init__(self, ctx, asset: GltfAsset, sh: np.ndarray | None = None,
                 shading: ShadingConfig = ShadingConfig()) -> None:
        import moderngl

        from toolkit.visualise import LABEL_COLOURS

        from .lighting import light_scale, resolve_sh

        self.ctx = ctx
        self.asset = asset
        self.sky_scale = 1.0 / light_scale(asset)  # the SH lights the mesh at light_scale x what its sky shows
        self._label_colours = LABEL_COLOURS
        self._objects: list = []
        # ---- geometry (glTF frame, as stored)
        pos = np.asarray(asset.positions_gltf, dtype=np.float32)
        n_vert = pos.shape[0]
        if asset.normals is not None:
            nrm = (asset.normals.astype(np.float64) @ WORLD_TO_GLTF.T).astype(np.float32)
        else:
            from toolkit.mesh import compute_vertex_normals

            nrm = compute_vertex_normals(pos.astype(np.float64), asset.faces).astype(np.float32)
        self.has_tangents = asset.tangents is not None and asset.uvs is not None
        if self.has_tangents:
            tan = np.concatenate([asset.tangents[:, :3].astype(np.float64) @ WORLD_TO_GLTF.T,
                                  asset.tangents[:, 3:4]], 1).astype(np.float32)
        else:
            tan = np.zeros((n_vert, 4), np.float32)
        uv = asset.uvs.astype(np.float32) if asset.uvs is not None else np.zeros((n_vert, 2), np.float32)
        blur = getattr(asset, "texture_blur", None)
        blur = np.zeros((n_vert, 1), np.float32) if blur is None else np.asarray(blur, np.float32).reshape(n_vert, 1)
        interleaved = np.concatenate([pos, nrm, tan, uv, blur], 1).astype(np.float32)
        self.vbo = self._keep(ctx.buffer(interleaved.tobytes()))
        faces = np.asarray(asset.faces, dtype=np.uint32)
        self.num_faces = int(faces.shape[0])
        self.ibo = self._keep(ctx.buffer(faces.tobytes()))
        self.runs = _label_runs(asset.face_labels, self.num_faces)
        self.quad = self._keep(ctx.buffer(np.array([-1, -1, 3, -1, -1, 3], np.float32).tobytes()))
        self._pipelines: dict[ShadingConfig, tuple] = {}
        self._pipeline(shading)  # compile the default now: shader errors surface at construction
        # ---- material
        mat = (asset.json.get("materials") or [{}])[0]
        pbr = mat.get("pbrMetallicRoughness", {})
        self.base_factor = tuple(float(x) for x in pbr.get("baseColorFactor", (1.0, 1.0, 1.0, 1.0)))
        self.metal_rough_factor = (float(pbr.get("metallicFactor", 1.0)), float(pbr.get("roughnessFactor", 1.0)))
        self.normal_scale = float((mat.get("normalTexture") or {}).get("scale", 1.0))
        self.double_sided = bool(mat.get("doubleSided", False))
        images = asset.images
        self.base_color = self._texture(images.get("base_color"), np.array([188, 188, 188], np.uint8), srgb=True)
        # the unit of the _TEXTURE_BLUR attribute: the bake's atlas side (every map of a dars GLB has it); the
        # largest map present when a GLB has no base-colour texture
        self.texture_size = float(max((max(images[k].shape[:2]) for k in ("base_color", "orm", "normal")
                                       if images.get(k) is not None), default=1))
        self.orm = self._texture(images.get("orm"), np.array([255, 255, 0], np.uint8))
        self.normal_map = self._texture(images.get("normal"), np.array([128, 128, 255], np.uint8))
        self.light_tint = self._texture(images.get("light_tint"), np.array([255, 255, 255], np.uint8))
        tint_ref = ((asset.json.get("extras") or {}).get("dars") or {}).get("light_tint") or {}
        self.tint_scale = float(tint_ref.get("scale", 1.0)) if "light_tint" in images else 1.0
        size, blob = dfg_texture_bytes()
        self.dfg = self._keep(ctx.texture(size, 2, blob, dtype="f4"))
        self.dfg.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.dfg.repeat_x = self.dfg.repeat_y = False
        self.backdrop = self._backdrop_texture(asset.backdrop)
        self.box_map = self._backdrop_texture(asset.backdrop, box=True)
        if sh is None:
            sh, _ = resolve_sh(asset)
        self.set_sh(sh)

    # ------------------------------------------------------------------------------------------------ resources
    def _keep(self, obj):
        self._objects.append(obj)
        return obj

    def _texture(self, image: np.ndarray | None, default_rgb: np.ndarray, srgb: bool = False):
        import moderngl

        if image is None:
            image = default_rgb.reshape(1, 1, 3)
        img = np.asarray(image)
        if img.dtype != np.uint8:
            raise SceneError(f"GLB texture has dtype {img.dtype}; the viewer reads 8-bit PNG/JPEG textures")
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        rgb = img[..., :3]
        rgba = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], 2)
        h, w = rgba.shape[:2]
        tex = self._keep(self.ctx.texture((w, h), 4, np.ascontiguousarray(rgba).tobytes(),
                                          internal_format=_SRGB8_ALPHA8 if srgb else None))
        tex.build_mipmaps()
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        tex.repeat_x = tex.repeat_y = False
        return tex

    def _backdrop_texture(self, backdrop, box: bool = False):
        """RGBA float texture of the GLB's backdrop (rgb radiance, a visibility), or of its box map (``box``: rgb
        radiance, a weight), or None."""
        import moderngl

        if backdrop is None or (box and backdrop.box is None):
            return None
        rgba = backdrop.rgba(box)
        h, w = rgba.shape[:2]
        tex = self._keep(self.ctx.texture((w, h), 4, rgba.tobytes(), dtype="f4"))
        tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        tex.repeat_x, tex.repeat_y = True, False
        return tex

    def uses_backdrop(self, cfg: "PreviewConfig") -> bool:
        """Whether ``cfg`` draws the GLB's backdrop behind the mesh (``PreviewConfig.background``).

        Raises:
            ConfigError: ``background="backdrop"`` on a GLB without one.
        """
        from .lighting import draws_backdrop

        return cfg.mode == "lit" and draws_backdrop(cfg.background, self.asset, self.sh)

    def _pipeline(self, shading: ShadingConfig) -> tuple:
        """(mesh program, mesh VAO, background program, background VAO) for a shading config (compiled once)."""
        if shading not in self._pipelines:
            ctx = self.ctx
            src = glsl_shading_source(shading)
            mesh = self._keep(ctx.program(vertex_shader=GLSL_VERSION + _MESH_VS,
                                          fragment_shader=GLSL_VERSION + src + _MESH_FS))
            bg = self._keep(ctx.program(vertex_shader=GLSL_VERSION + _BACKGROUND_VS,
                                        fragment_shader=GLSL_VERSION + src + _BACKGROUND_FS))
            vao = self._keep(ctx.vertex_array(
                mesh, [(self.vbo, "3f 3f 4f 2f 1f", "in_position", "in_normal", "in_tangent", "in_uv", "in_blur")],
                index_buffer=self.ibo, index_element_size=4))
            bg_vao = self._keep(ctx.vertex_array(bg, [(self.quad, "2f", "in_pos")]))
            self._pipelines[shading] = (mesh, vao, bg, bg_vao)
        return self._pipelines[shading]

    def set_sh(self, sh: np.ndarray) -> None:
        """Swap the SH light (relighting): float [9, 3] SPEC radiance SH, world frame (used from the next frame)."""
        from toolkit.sh import check_sh_coeffs

        self.sh = check_sh_coeffs(sh, "set_sh")

    def release(self) -> None:
        """Free every GPU object (the context stays)."""
        for obj in reversed(self._objects):
            obj.release()
        self._objects.clear()

    # ------------------------------------------------------------------------------------------------ drawing
    def render(self, camera: PinholeCamera, cfg: PreviewConfig = PreviewConfig(), framebuffer=None) -> None:
        """Draw one frame into ``framebuffer`` (default: the context's current one) with viewport = camera size."""
        import moderngl

        ctx = self.ctx
        fbo = framebuffer if framebuffer is not None else ctx.fbo
        fbo.use()
        fbo.viewport = (0, 0, camera.width, camera.height)
        view_proj = view_projection_gltf(camera)
        gltf_to_world = WORLD_TO_GLTF.T
        exposure_scale = float(2.0 ** cfg.exposure)
        p, vao, bg, bg_vao = self._pipeline(cfg.shading)
        sh_value = [tuple(float(v) for v in row) for row in self.sh]
        use_sh = cfg.mode == "lit" and cfg.background != "colour"
        use_backdrop = self.uses_backdrop(cfg)
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        _write_mat(bg, "u_inv_view_proj", np.linalg.inv(view_proj))
        _write_mat(bg, "u_gltf_to_world", gltf_to_world)
        _set(bg, "u_exposure_scale", exposure_scale)
        _set(bg, "u_use_sh", use_sh)
        _set(bg, "u_colour", tuple(float(c) for c in cfg.background_colour))
        _set(bg, "u_sh", [tuple(float(v) * self.sky_scale for v in row) for row in self.sh])
        _set(bg, "u_use_backdrop", use_backdrop)
        if use_backdrop:
            self.backdrop.use(0)
            _set(bg, "u_backdrop", 0)
        use_box = use_backdrop and self.box_map is not None
        _set(bg, "u_use_box", use_box)
        if use_box:
            box = self.asset.backdrop.box
            self.box_map.use(1)
            _set(bg, "u_box_map", 1)
            _set(bg, "u_eye", tuple(float(x) for x in np.asarray(camera.c2w, np.float64)[:3, 3]))
            _write_mat(bg, "u_box_axes", box.axes)
            for name, value in (("u_box_origin", box.origin), ("u_box_lo", box.lo), ("u_box_hi", box.hi),
                                ("u_box_centre", box.centre), ("u_box_face_lo", box.faces[0::2].astype(float)),
                                ("u_box_face_hi", box.faces[1::2].astype(float))):
                _set(bg, name, tuple(float(x) for x in value))
        bg_vao.render(moderngl.TRIANGLES)

        ctx.enable(moderngl.DEPTH_TEST)
        if self.double_sided:
            ctx.disable(moderngl.CULL_FACE)
        else:
            ctx.enable(moderngl.CULL_FACE)
            ctx.front_face = "ccw"
            ctx.cull_face = "back"
        _write_mat(p, "u_view_proj", view_proj)
        _write_mat(p, "u_gltf_to_world", gltf_to_world)
        _set(p, "u_camera_pos", tuple(float(x) for x in gltf_c2w(camera.c2w)[:3, 3]))
        _set(p, "u_base_factor", self.base_factor)
        _set(p, "u_metal_rough_factor", self.metal_rough_factor)
        _set(p, "u_normal_scale", self.normal_scale)
        _set(p, "u_has_tangents", bool(self.has_tangents))
        _set(p, "u_double_sided", self.double_sided)
        _set(p, "u_mode", _MODE_INDEX[cfg.mode])
        _set(p, "u_exposure_scale", exposure_scale)
        _set(p, "u_sh", sh_value)
        _set(p, "u_tint_scale", self.tint_scale)
        _set(p, "u_texture_size", self.texture_size)
        _set(p, "u_trilinear", cfg.texture_filter == "trilinear")
        for unit, (name, tex) in enumerate((("u_base_color", self.base_color), ("u_orm", self.orm),
                                            ("u_normal_map", self.normal_map), (DFG_UNIFORM, self.dfg),
                                            ("u_light_tint", self.light_tint))):
            tex.use(unit)
            _set(p, name, unit)
        if cfg.mode == "semantics":
            for first, count, label in self.runs:
                colour = self._label_colours[label] if label < len(self._label_colours) else np.zeros(3)
                _set(p, "u_label_colour", tuple(float(c) for c in colour))
                vao.render(moderngl.TRIANGLES, vertices=count * 3, first=first * 3)
        else:
            vao.render(moderngl.TRIANGLES, vertices=self.num_faces * 3)
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)


# ============================================================================================================ offscreen
class OffscreenPreview:
    """A headless context + renderer + framebuffer for repeated renders (tests, CLI, benchmarks).

    Args:
        asset: a loaded GLB or a path (:func:`resolve_asset_path`).
        sh: float [9, 3] light (default: the asset's).
        ctx: an existing moderngl context (default: a new EGL one, released by :meth:`release`).
        shading: shading options baked into the shader.
        renderer: reuse this :class:`PreviewRenderer` (of ``ctx``) instead of uploading the asset again; it is
            not released by :meth:`release`.

    Example:
        >>> with OffscreenPreview("out/scene.glb") as view:
        ...     img = view.render(view.default_camera(320, 240))
    """

    def __init__(self, asset: GltfAsset | str | Path, sh: np.ndarray | None = None, ctx=None,
                 shading: ShadingConfig = ShadingConfig(), renderer: PreviewRenderer | None = None) -> None:
        self.asset = asset if isinstance(asset, GltfAsset) else load_glb(resolve_asset_path(asset))
        self._own_ctx = ctx is None
        self.ctx = create_headless_context() if ctx is None else ctx
        self._own_renderer = renderer is None
        self.renderer = PreviewRenderer(self.ctx, self.asset, sh, shading) if renderer is None else renderer
        if renderer is not None and sh is not None:
            renderer.set_sh(sh)
        self._fbo = None
        self._size: tuple[int, int] | None = None

    def __enter__(self) -> "OffscreenPreview":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def default_camera(self, width: int = 1280, height: int = 720) -> PinholeCamera:
        """A camera framing the asset (:func:`viewers.camera.default_camera`)."""
        return default_camera(self.asset.vertices, width, height)

    def _framebuffer(self, width: int, height: int):
        if self._size != (width, height):
            if self._fbo is not None:
                for a in (*self._fbo.color_attachments, self._fbo.depth_attachment, self._fbo):
                    a.release()
            colour = self.ctx.texture((width, height), 4)
            depth = self.ctx.depth_renderbuffer((width, height))
            self._fbo = self.ctx.framebuffer(color_attachments=[colour], depth_attachment=depth)
            self._size = (width, height)
        return self._fbo

    def draw(self, camera: PinholeCamera, cfg: PreviewConfig = PreviewConfig()) -> None:
        """Render without reading back (benchmarks: follow with ``ctx.finish()``)."""
        self.renderer.render(camera, cfg, self._framebuffer(camera.width, camera.height))

    def render(self, camera: PinholeCamera, cfg: PreviewConfig = PreviewConfig()) -> PreviewImage:
        """Render and read back one image."""
        self.draw(camera, cfg)
        raw = self._fbo.read(components=4, alignment=1)
        rgba = np.frombuffer(raw, np.uint8).reshape(camera.height, camera.width, 4)[::-1]
        return PreviewImage(np.ascontiguousarray(rgba[..., :3]), rgba[..., 3] > 127, camera, cfg.mode)

    def measure_fps(self, camera: PinholeCamera, cfg: PreviewConfig = PreviewConfig(), frames: int = 20,
                    warmup: int = 2) -> float:
        """Frames per second of :meth:`draw` + ``glFinish`` (no read-back)."""
        for _ in range(warmup):
            self.draw(camera, cfg)
        self.ctx.finish()
        t0 = time.perf_counter()
        for _ in range(frames):
            self.draw(camera, cfg)
            self.ctx.finish()
        return frames / (time.perf_counter() - t0)

    def release(self) -> None:
        if self._fbo is not None:
            for a in (*self._fbo.color_attachments, self._fbo.depth_attachment, self._fbo):
                a.release()
            self._fbo = None
            self._size = None
        if self._own_renderer:
            self.renderer.release()
        if self._own_ctx:
            self.ctx.release()


def render_preview(asset: GltfAsset | str | Path, camera: PinholeCamera | None = None,
                   cfg: PreviewConfig = PreviewConfig(), sh: np.ndarray | None = None) -> PreviewImage:
    """Render one headless preview image of a baked asset (creates and releases an EGL context).

    Args:
        asset: a loaded GLB, a ``.glb`` path or an ``export-asset`` directory.
        camera: the view (default: :func:`viewers.camera.default_camera` at 1280 x 720).
        cfg: mode, exposure, background.
        sh: float [9, 3] SPEC radiance SH to light with (relighting; default: the asset's).

    Returns:
        :class:`PreviewImage`.

    Raises:
        SceneError: the asset cannot be read.
        DarsError: no headless OpenGL context.
    """
    with OffscreenPreview(asset, sh, shading=cfg.shading) as view:
        return view.render(camera if camera is not None else view.default_camera(), cfg)
