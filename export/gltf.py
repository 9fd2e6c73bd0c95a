"""glTF 2.0 / GLB export of a baked asset (and a small reader for tests and viewers).

Conventions (fixed; ``tests/test_gltf.py`` checks each):

* **Axes.** Our world is +z up (SPEC); glTF is +y up, right-handed. Vertex data is rotated on export by
  ``(x, y, z) → (x, z, −y)`` (positions, normals and tangent xyz; a proper rotation, so winding and the tangent
  handedness w are unchanged). The rotation is baked into the data, not put on a node, so every consumer (and
  :func:`load_glb`) sees a +y-up asset; :func:`load_glb` rotates back to world coordinates. Units stay metres.
* **Material.** One metallic-roughness material: ``baseColorTexture`` (sRGB), ``metallicRoughnessTexture`` and
  ``occlusionTexture`` both point at the ORM image (R occlusion, G roughness, B metallic), ``normalTexture``
  (tangent space, +y green up); attributes POSITION, NORMAL, TANGENT (VEC4), TEXCOORD_0. Textures sample with
  trilinear mip-mapping and clamp-to-edge (an atlas must not wrap).
* **Texture blur.** A UV mesh with a ``texture_blur`` (:class:`toolkit.bake.UVMesh`: how many texels one training
  pixel spans where the textures were baked from views, :func:`toolkit.viewbake.face_texture_blur`) stores it as
  the application-specific vertex attribute ``_TEXTURE_BLUR`` (float SCALAR); ``dars view`` and the WebXR page
  narrow their mip filter by it, other glTF viewers ignore it; :func:`load_glb` reads it into
  :attr:`GltfAsset.texture_blur`.
* **Semantics.** One primitive per semantic class (SPEC ids 0-6; 255 unlabelled), all sharing the same vertex
  accessors and material, each with ``extras = {"semantic_class": id, "semantic_name": name}`` — viewers can hide
  or re-material a class without a custom attribute (the stage-16 editor assigns per-class materials this way).
  ``semantics="none"`` (or no labels) writes a single primitive.
* **Lighting.** With ``sh`` given, the SH probe is stored twice:
  1. ``EXT_lights_image_based`` (declared in ``extensionsUsed``, not required; the scene's
     ``extensions.EXT_lights_image_based.light = 0``): ``irradianceCoefficients`` from
     :func:`toolkit.sh.sh_to_gltf_ibl` (rotated into glTF's frame, Â_l-scaled irradiance, Babylon's basis signs),
     ``rotation`` identity, and the extension's required prefiltered specular cube map: ``specularImageSize``
     texels per face at mip 0, ``GltfConfig.ibl_mips`` mips, faces in the order +X −X +Y −Y +Z −Z (glTF frame,
     OpenGL cube-map face orientation, image row 0 = t 0), each a 4-channel PNG in Babylon's RGBD packing
     (``rgb = (L·D)^(1/2.2)``, ``a = D``; decode ``L = rgb^2.2 / a``). Mip m holds the SH radiance prefiltered
     for roughness m/(mips−1) with the same band attenuation our shading uses for ``L_spec``
     (:func:`toolkit.shading.specular_band_attenuation`: normalised-Phong lobe ratios, GGX↔Phong remap), so a
     viewer sampling these mips reproduces the trained model's specular term;
  2. the raw SPEC-convention coefficients (incident radiance, real SH order 2, [9, 3], *our +z-up world frame*,
     before the axis conversion) in the root ``extras.dars.sh`` — the lossless copy our own tools read back.
* **Backdrop.** ``dars export-asset`` adds a backdrop (what the viewers draw where the mesh is not — a gallery's
  sky, the white behind an object, holes in the mesh — from the field's renders) in the root ``extras.dars.backdrop``: a lat-long map in our
  +z-up world frame, linear radiance and a per-texel visibility (:class:`toolkit.backdrop.Backdrop`, passed in
  ``extras``), and for a run with a room box a second map under its ``box`` key, projected on the box's confident
  faces (:class:`toolkit.backdrop.BoxProjection`: a ray from the eye reads it where it leaves the box);
  :func:`load_glb` reads it into :attr:`GltfAsset.backdrop`. Other glTF viewers ignore it.
* **Light tint.** Textures with a ``light_tint`` (:class:`toolkit.bake.PBRTextures`: the colour of the field's
  per-point light, which the grey occlusion channel cannot hold) add a fourth texture, named in the root
  ``extras.dars.light_tint`` (``index``, ``scale``); ``dars view`` and the WebXR page multiply the shaded colour by
  texel × scale, other glTF viewers ignore it; :func:`load_glb` reads it into ``images["light_tint"]``.
"""

from __future__ import annotations

import base64
import io
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from toolkit._checks import ConfigError, DarsError, SceneError, check_shape
from toolkit.backdrop import Backdrop

__all__ = [
    "GltfConfig",
    "GltfAsset",
    "WORLD_TO_GLTF",
    "world_to_gltf",
    "gltf_to_world",
    "export_gltf",
    "export_ply",
    "export_obj",
    "load_glb",
    "sh_specular_cubemap",
    "encode_rgbd",
    "decode_rgbd",
]

WORLD_TO_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Rotation taking our +z-up world vectors to glTF's +y-up frame: ``(x, y, z) → (x, z, −y)``."""

SEMANTIC_NAMES = ("painting", "frame", "display", "base", "wall", "floor", "other")

_FLOAT, _UINT16, _UINT32 = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
TEXTURE_BLUR_ATTRIBUTE = "_TEXTURE_BLUR"
"""The vertex attribute holding :attr:`toolkit.bake.UVMesh.texture_blur` (application-specific: glTF's leading
underscore)."""
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP = 9729, 9987, 33071


def world_to_gltf(v: np.ndarray) -> np.ndarray:
    """Rotate float [..., 3] world (+z up) vectors or points into glTF's +y-up frame: (x, y, z) → (x, z, −y).

    Example:
        >>> world_to_gltf(np.array([0.0, 0.0, 1.0]))  # up stays up
        array([0., 1., 0.])
    """
    v = np.asarray(v)
    out = v.astype(np.float64) @ WORLD_TO_GLTF.T
    return out.astype(v.dtype) if v.dtype.kind == "f" else out


def gltf_to_world(v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`world_to_gltf`: (x, y, z)_glTF → (x, −z, y)_world."""
    v = np.asarray(v)
    out = v.astype(np.float64) @ WORLD_TO_GLTF
    return out.astype(v.dtype) if v.dtype.kind == "f" else out


@dataclass(frozen=True)
class GltfConfig:
    """Options of :func:`export_gltf`.

    Attributes:
        name: name of the mesh, node and scene.
        ibl_size: texels per cube face at mip 0 of the specular map (power of two).
        ibl_mips: number of mips written (the last one is roughness 1); ``ibl_size / 2**(ibl_mips-1)`` ≥ 1.
        ibl_intensity: the IBL's ``intensity``.
        double_sided: the material's ``doubleSided`` (useful for open room scans seen from both sides).
    """

    name: str = "dars_scene"
    ibl_size: int = 64
    ibl_mips: int = 3
    ibl_intensity: float = 1.0
    double_sided: bool = False


# ========================================================================================================= writer
class _Bin:
    """The binary buffer: 4-byte aligned buffer views."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []

    def add(self, blob: bytes, target: int | None = None, stride: int | None = None) -> int:
        pad = (-len(self.data)) % 4
        self.data += b"\0" * pad
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(blob)}
        if target is not None:
            view["target"] = target
        if stride is not None:
            view["byteStride"] = stride
        self.data += blob
        self.views.append(view)
        return len(self.views) - 1


def _png_bytes(image: np.ndarray) -> bytes:
    from toolkit.io import encode_png

    try:
        return encode_png(image)
    except OSError as e:
        raise DarsError(f"could not encode a PNG texture: {e}") from e


def _png_decode(blob: bytes) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SceneError("an embedded image could not be decoded")
    if img.ndim == 3 and img.shape[2] == 3:
        return img[..., ::-1].copy()
    if img.ndim == 3 and img.shape[2] == 4:
        return img[..., [2, 1, 0, 3]].copy()
    return img


def export_gltf(uvmesh, textures, path: str | Path, sh=None, *, semantics: Literal["primitives", "none"] = "primitives",
                embed: bool = True, extras: dict | None = None, cfg: GltfConfig = GltfConfig()) -> Path:
    """Write a baked asset as glTF 2.0: ``.glb`` (one binary file, textures embedded) or ``.gltf``.

    Args:
        uvmesh: :class:`toolkit.bake.UVMesh` (world +z up, metres).
        textures: :class:`toolkit.bake.PBRTextures`.
        path: output ``.glb`` or ``.gltf`` file (written atomically; for ``.gltf`` with ``embed=False`` the buffer
            ``NAME.bin`` and the PNG textures ``NAME_*.png`` are written beside it).
        sh: optional float [9, 3] SPEC-convention radiance SH (world frame), stored as described in the module
            docstring.
        semantics: "primitives" (one primitive per class in ``uvmesh.face_labels``) or "none".
        embed: for ``.gltf``: embed buffer and images as data URIs (True) or write them beside the file.
            ``.glb`` always embeds.
        extras: JSON-serialisable dict merged into the root ``extras.dars`` (e.g. mesh statistics).
        cfg: :class:`GltfConfig`.

    Returns:
        the path written.

    Raises:
        ConfigError: bad suffix, semantics or IBL size.
        ShapeError: ``sh`` is not [9, 3].
    """
    from toolkit.io import atomic_write

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".glb", ".gltf"):
        raise ConfigError(f"export_gltf: {path} must end in .glb or .gltf")
    if semantics not in ("primitives", "none"):
        raise ConfigError(f"export_gltf: semantics={semantics!r} is not valid: choose 'primitives' or 'none'")
    if uvmesh.num_faces == 0:
        raise DarsError("export_gltf: the mesh has no faces")
    buf = _Bin()
    accessors: list[dict] = []

    def add_accessor(array: np.ndarray, kind: str, target: int | None, minmax: bool = False) -> int:
        comp = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint16): _UINT16, np.dtype(np.uint32): _UINT32}[array.dtype]
        view = buf.add(np.ascontiguousarray(array).tobytes(), target)
        acc = {"bufferView": view, "componentType": comp, "count": int(array.shape[0]), "type": kind}
        if minmax:
            acc["min"] = [float(x) for x in array.reshape(array.shape[0], -1).min(0)]
            acc["max"] = [float(x) for x in array.reshape(array.shape[0], -1).max(0)]
        accessors.append(acc)
        return len(accessors) - 1

    # ---- vertex data, rotated into glTF's +y-up frame
    pos = world_to_gltf(uvmesh.vertices.astype(np.float64)).astype(np.float32)
    nrm = _unit32(world_to_gltf(uvmesh.normals.astype(np.float64)))
    tan_xyz = _unit32(world_to_gltf(uvmesh.tangents[:, :3].astype(np.float64)))
    w = np.where(uvmesh.tangents[:, 3] < 0, -1.0, 1.0).astype(np.float32)
    tan = np.concatenate([tan_xyz, w[:, None]], 1)
    attributes = {
        "POSITION": add_accessor(pos, "VEC3", _ARRAY_BUFFER, minmax=True),
        "NORMAL": add_accessor(nrm, "VEC3", _ARRAY_BUFFER),
        "TANGENT": add_accessor(tan, "VEC4", _ARRAY_BUFFER),
        "TEXCOORD_0": add_accessor(np.ascontiguousarray(uvmesh.uvs, dtype=np.float32), "VEC2", _ARRAY_BUFFER),
    }
    blur = getattr(uvmesh, "texture_blur", None)
    if blur is not None:
        attributes[TEXTURE_BLUR_ATTRIBUTE] = add_accessor(np.ascontiguousarray(blur, dtype=np.float32), "SCALAR",
                                                          _ARRAY_BUFFER)
    index_dtype = np.uint16 if uvmesh.num_vertices < 65535 else np.uint32

    # ---- primitives (one per semantic class)
    labels = uvmesh.face_labels if semantics == "primitives" else None
    groups: list[tuple[int | None, np.ndarray]]
    if labels is None:
        groups = [(None, uvmesh.faces)]
    else:
        groups = [(int(c), uvmesh.faces[labels == c]) for c in np.unique(labels)]
    primitives = []
    for cls, faces in groups:
        idx = add_accessor(faces.reshape(-1).astype(index_dtype), "SCALAR", _ELEMENT_ARRAY_BUFFER)
        prim: dict[str, Any] = {"attributes": dict(attributes), "indices": idx, "material": 0, "mode": 4}
        if cls is not None:
            prim["extras"] = {"semantic_class": cls,
                              "semantic_name": SEMANTIC_NAMES[cls] if cls < len(SEMANTIC_NAMES) else "unlabelled"}
        primitives.append(prim)

    # ---- textures
    images: list[dict] = []
    external: dict[str, bytes] = {}

    def add_image(array: np.ndarray, name: str) -> int:
        blob = _png_bytes(array)
        if suffix == ".gltf" and not embed:
            uri = f"{path.stem}_{name}.png"
            external[uri] = blob
            images.append({"uri": uri, "name": name})
        elif suffix == ".gltf":
            images.append({"uri": "data:image/png;base64," + base64.b64encode(blob).decode(), "name": name})
        else:
            images.append({"bufferView": buf.add(blob), "mimeType": "image/png", "name": name})
        return len(images) - 1

    img_base = add_image(textures.base_color, "base_color")
    img_orm = add_image(textures.orm, "orm")
    img_nrm = add_image(textures.normal, "normal")
    gltf_textures = [{"sampler": 0, "source": img_base}, {"sampler": 0, "source": img_orm}, {"sampler": 0, "source": img_nrm}]
    material = {
        "name": "dars_pbr",
        "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicRoughnessTexture": {"index": 1},
                                 "baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 1.0, "roughnessFactor": 1.0},
        "normalTexture": {"index": 2, "scale": 1.0},
        "occlusionTexture": {"index": 1, "strength": 1.0},
        "doubleSided": bool(cfg.double_sided),
    }

    dars_extras: dict[str, Any] = {
        "up_axis": "glTF +y; converted from the dars world (+z up) by (x, y, z) -> (x, z, -y)",
        "units": "metres",
        "semantic_classes": list(SEMANTIC_NAMES),
        "semantics": "one primitive per class (primitive extras.semantic_class)" if labels is not None else "none",
        "texture_defaults": list(getattr(textures, "defaults", ())),
    }
    tint = getattr(textures, "light_tint", None)
    if tint is not None:
        from toolkit.bake import LIGHT_TINT_SCALE

        gltf_textures.append({"sampler": 0, "source": add_image(tint, "light_tint")})
        dars_extras["light_tint"] = {
            "index": len(gltf_textures) - 1, "texCoord": 0, "scale": LIGHT_TINT_SCALE,
            "meaning": "the colour of the field's per-point light (toolkit.train.run.light_tint_map), linear RGB / "
                       "scale; a viewer multiplies its shaded colour (diffuse and specular, with the occlusion) by "
                       "texel x scale. Viewers that do not read it show the grey occlusion."}
    root: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "dars toolkit (export/gltf.py)"},
        "scene": 0,
        "scenes": [{"name": cfg.name, "nodes": [0]}],
        "nodes": [{"name": cfg.name, "mesh": 0}],
        "meshes": [{"name": cfg.name, "primitives": primitives}],
        "materials": [material],
        "textures": gltf_textures,
        "samplers": [{"magFilter": _LINEAR, "minFilter": _LINEAR_MIPMAP_LINEAR, "wrapS": _CLAMP, "wrapT": _CLAMP}],
    }
    if sh is not None:
        from toolkit.sh import sh_to_gltf_ibl

        coeffs = _sh_array(sh)
        light = sh_to_gltf_ibl(coeffs, intensity=cfg.ibl_intensity)
        faces_per_mip = sh_specular_cubemap(coeffs, cfg.ibl_size, cfg.ibl_mips)
        light["name"] = "dars_sh_probe"
        light["specularImageSize"] = int(cfg.ibl_size)
        light["specularImages"] = [[add_image(encode_rgbd(face), f"ibl_mip{m}_face{k}") for k, face in enumerate(mip)]
                                   for m, mip in enumerate(faces_per_mip)]
        root["extensionsUsed"] = ["EXT_lights_image_based"]
        root["extensions"] = {"EXT_lights_image_based": {"lights": [light]}}
        root["scenes"][0]["extensions"] = {"EXT_lights_image_based": {"light": 0}}
        dars_extras["sh"] = {
            "coeffs": coeffs.tolist(),
            "convention": "SPEC: incident radiance L(w), real SH order 2 [9, 3], basis order (0,0) (1,-1) (1,0) (1,1) "
                          "(2,-2) (2,-1) (2,0) (2,1) (2,2), dars world frame (+z up, before the glTF axis conversion)",
        }
    if extras:
        dars_extras.update(extras)
    root["extras"] = {"dars": dars_extras}
    root["images"] = images
    root["accessors"] = accessors
    root["bufferViews"] = buf.views
    pad = (-len(buf.data)) % 4
    bin_blob = bytes(buf.data) + b"\0" * pad
    root["buffers"] = [{"byteLength": len(bin_blob)}]

    if suffix == ".glb":
        blob = _glb_bytes(root, bin_blob)
        with atomic_write(path) as f:
            f.write(blob)
        return path
    if embed:
        root["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bin_blob).decode()
    else:
        root["buffers"][0]["uri"] = f"{path.stem}.bin"
        with atomic_write(path.with_name(f"{path.stem}.bin")) as f:
            f.write(bin_blob)
        for uri, blob in external.items():
            with atomic_write(path.with_name(uri)) as f:
                f.write(blob)
    with atomic_write(path, "w") as f:
        json.dump(root, f, separators=(",", ":"))
    return path


def _unit32(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=1, keepdims=True)
    out = np.where(n > 1e-12, v / np.maximum(n, 1e-12), np.array([0.0, 1.0, 0.0]))
    return out.astype(np.float32)


def _sh_array(sh) -> np.ndarray:
    if hasattr(sh, "detach"):
        sh = sh.detach().cpu().double().numpy()
    c = np.asarray(sh, dtype=np.float64)
    if c.shape == (27,):
        c = c.reshape(9, 3)
    check_shape(c, "9 3", "sh")
    if not np.isfinite(c).all():
        raise DarsError("sh contains NaN or inf values")
    return c


def _glb_bytes(root: dict, bin_blob: bytes) -> bytes:
    js = json.dumps(root, separators=(",", ":")).encode("utf-8")
    js += b" " * ((-len(js)) % 4)
    total = 12 + 8 + len(js) + 8 + len(bin_blob)
    out = io.BytesIO()
    out.write(struct.pack("<4sII", b"glTF", 2, total))
    out.write(struct.pack("<I4s", len(js), b"JSON"))
    out.write(js)
    out.write(struct.pack("<I4s", len(bin_blob), b"BIN\0"))
    out.write(bin_blob)
    return out.getvalue()


# ========================================================================================================= IBL maps
def _cube_face_directions(size: int) -> np.ndarray:
    """float64 [6, size, size, 3] unit directions (glTF frame) of the texel centres of the six cube faces, in the
    order +X −X +Y −Y +Z −Z and OpenGL cube-map orientation (row i ↔ t = (i + ½)/size, column j ↔ s)."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    tc, sc = np.meshgrid(c, c, indexing="ij")
    one = np.ones_like(sc)
    faces = [
        np.stack([one, -tc, -sc], -1),
        np.stack([-one, -tc, sc], -1),
        np.stack([sc, one, tc], -1),
        np.stack([sc, -one, -tc], -1),
        np.stack([sc, -tc, one], -1),
        np.stack([-sc, -tc, -one], -1),
    ]
    d = np.stack(faces)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def sh_specular_cubemap(sh, size: int = 64, mips: int = 3) -> list[list[np.ndarray]]:
    """Prefiltered specular cube map of an SH environment (band attenuation of :mod:`toolkit.shading`).

    Args:
        sh: float [9, 3] SPEC radiance coefficients, world frame.
        size: texels per face at mip 0 (power of two).
        mips: number of mip levels (mip m has size/2^m texels, roughness m/(mips−1)).

    Returns:
        ``mips`` lists of 6 float32 [s, s, 3] linear radiance faces (+X −X +Y −Y +Z −Z, glTF frame), ≥ 0.
    """
    import torch

    from toolkit.sh import eval_sh

    if not (isinstance(size, int) and size >= 1 and size & (size - 1) == 0):
        raise ConfigError(f"ibl_size={size!r} must be a power of two")
    if not (isinstance(mips, int) and 1 <= mips and size >> (mips - 1) >= 1):
        raise ConfigError(f"ibl_mips={mips!r} must be ≥ 1 with ibl_size / 2**(mips-1) ≥ 1")
    from toolkit.shading import specular_band_attenuation

    c = torch.as_tensor(_sh_array(sh))
    out = []
    for m in range(mips):
        rough = m / (mips - 1) if mips > 1 else 0.0
        atten = specular_band_attenuation(torch.tensor(rough, dtype=torch.float64))
        s = size >> m
        d_gltf = _cube_face_directions(s)
        d_world = gltf_to_world(d_gltf)
        L = eval_sh(c * atten[:, None], torch.as_tensor(d_world)).numpy()
        out.append([np.maximum(L[k], 0.0).astype(np.float32) for k in range(6)])
    return out


def encode_rgbd(radiance_hwc: np.ndarray, max_range: float = 255.0) -> np.ndarray:
    """Pack linear HDR RGB into Babylon.js RGBD (uint8 RGBA): D = clamp(floor(max(range/max(rgb), 1))/255, 0, 1),
    rgb = (L·D)^(1/2.2), a = D.

    Args:
        radiance_hwc: float [H, W, 3] linear radiance ≥ 0.

    Returns:
        uint8 [H, W, 4].
    """
    L = np.maximum(np.asarray(radiance_hwc, dtype=np.float64), 0.0)
    mx = np.maximum(L.max(-1), 1e-6)
    D = np.clip(np.floor(np.maximum(max_range / mx, 1.0)) / 255.0, 1.0 / 255.0, 1.0)
    rgb = np.clip(L * D[..., None], 0.0, 1.0) ** (1 / 2.2)
    rgbd = np.concatenate([rgb, D[..., None]], -1)
    return np.clip(np.rint(rgbd * 255.0), 0, 255).astype(np.uint8)


def decode_rgbd(rgbd: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_rgbd`: uint8 [H, W, 4] → float32 [H, W, 3] linear radiance."""
    x = np.asarray(rgbd, dtype=np.float64) / 255.0
    return ((x[..., :3] ** 2.2) / np.maximum(x[..., 3:4], 1.0 / 255.0)).astype(np.float32)


# ====================================================================================================== geometry
def export_ply(mesh, path: str | Path) -> Path:
    """Geometry-only PLY (world +z up, metres; vertex colours/labels when present). See :func:`toolkit.mesh.save_mesh`."""
    from toolkit.mesh import save_mesh

    if Path(path).suffix.lower() != ".ply":
        raise ConfigError(f"export_ply: {path} must end in .ply")
    return save_mesh(mesh, path)


def export_obj(mesh, path: str | Path) -> Path:
    """Geometry-only OBJ (world +z up, metres; positions and normals). See :func:`toolkit.mesh.save_mesh`."""
    from toolkit.mesh import save_mesh

    if Path(path).suffix.lower() != ".obj":
        raise ConfigError(f"export_obj: {path} must end in .obj")
    return save_mesh(mesh, path)


# ========================================================================================================== reader
@dataclass(frozen=True)
class GltfAsset:
    """What :func:`load_glb` reads back (world frame unless named ``*_gltf``).

    Attributes:
        vertices: float32 [V, 3] world positions (+z up), metres.
        faces: int64 [F, 3] all primitives' triangles (primitive order).
        face_labels: uint8 [F] semantic class per face (from primitive extras), or None.
        uvs: float32 [V, 2] TEXCOORD_0 (glTF convention), or None.
        normals: float32 [V, 3] world normals, or None.
        tangents: float32 [V, 4] world tangent xyz + w, or None.
        positions_gltf: float32 [V, 3] positions as stored (+y up).
        images: decoded material images by role: ``base_color``, ``orm`` (also ``occlusion`` if different),
            ``light_tint`` (``extras.dars.light_tint``: tint / its ``scale``, linear; :mod:`toolkit.bake`),
            ``normal`` (uint8 H-W-C).
        sh: float64 [9, 3] the raw SPEC SH from ``extras.dars.sh`` (world frame), or None.
        ibl: the ``EXT_lights_image_based`` light dict as stored, or None.
        ibl_images: decoded specular cube faces per mip (uint8 RGBD [s, s, 4]), or [].
        json: the whole glTF JSON.
        backdrop: the backdrop from ``extras.dars.backdrop`` (:class:`toolkit.backdrop.Backdrop`:
            what the viewers draw where the mesh is not), or None.
        texture_blur: float32 [V] the ``_TEXTURE_BLUR`` vertex attribute (texels the baked detail is blurred
            over, :func:`toolkit.viewbake.face_texture_blur`), or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_labels: np.ndarray | None
    uvs: np.ndarray | None
    normals: np.ndarray | None
    tangents: np.ndarray | None
    positions_gltf: np.ndarray
    images: dict[str, np.ndarray]
    sh: np.ndarray | None
    ibl: dict | None
    ibl_images: list[list[np.ndarray]]
    json: dict
    backdrop: Any = None
    texture_blur: np.ndarray | None = None


_NUMPY_OF = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH_OF = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def load_glb(path: str | Path) -> GltfAsset:
    """Read a ``.glb`` (or ``.gltf`` with data URIs or files beside it) written by :func:`export_gltf` — or any
    triangle glTF without sparse accessors — into numpy arrays, rotating back to world coordinates.

    Raises:
        SceneError: missing file, not glTF 2.0, truncated or damaged, or unsupported content (naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"glTF file not found: {path}")
    try:
        return _load_glb(path)
    except SceneError as e:
        if str(path) in str(e):
            raise
        raise SceneError(f"{path}: {e}; re-export it (`dars export-asset RUN --out DIR`)") from e
    except (struct.error, KeyError, IndexError, ValueError, TypeError, AttributeError, OSError, EOFError) as e:
        size = path.stat().st_size
        raise SceneError(f"{path} is truncated or not a valid glTF file ({size} bytes; {type(e).__name__}: "
                         f"{str(e)[:160]}); re-export it (`dars export-asset RUN --out DIR`) or copy it again") from e


def _load_glb(path: Path) -> GltfAsset:
    raw = path.read_bytes()
    if not raw:
        raise SceneError(f"{path} is empty (0 bytes), not a glTF file; re-export it "
                         "(`dars export-asset RUN --out DIR`) or copy it again")
    bin_chunk = b""
    if raw[:4] == b"glTF":
        _, version, length = struct.unpack_from("<4sII", raw, 0)
        if version != 2:
            raise SceneError(f"{path}: GLB version {version}, expected 2")
        if length > len(raw):
            raise SceneError(f"{path} is truncated: its header says {length} bytes but the file has {len(raw)}; "
                             "re-export it (`dars export-asset RUN --out DIR`) or copy it again")
        off, root = 12, None
        while off < length:
            n, kind = struct.unpack_from("<I4s", raw, off)
            chunk = raw[off + 8:off + 8 + n]
            if kind == b"JSON":
                root = json.loads(chunk.decode("utf-8"))
            elif kind == b"BIN\0":
                bin_chunk = chunk
            off += 8 + n
        if root is None:
            raise SceneError(f"{path}: GLB without a JSON chunk")
    else:
        try:
            root = json.loads(raw.decode("utf-8"))
        except ValueError as e:
            raise SceneError(f"{path} is neither GLB nor glTF JSON: {e}") from e

    def buffer_bytes(i: int) -> bytes:
        b = root["buffers"][i]
        uri = b.get("uri")
        if uri is None:
            return bin_chunk
        if uri.startswith("data:"):
            return base64.b64decode(uri.split(",", 1)[1])
        return (path.parent / uri).read_bytes()

    buffers = [buffer_bytes(i) for i in range(len(root.get("buffers", [])))]

    def view_bytes(i: int) -> bytes:
        v = root["bufferViews"][i]
        o = v.get("byteOffset", 0)
        return buffers[v["buffer"]][o:o + v["byteLength"]]

    def accessor(i: int) -> np.ndarray:
        a = root["accessors"][i]
        if "sparse" in a:
            raise SceneError(f"{path}: sparse accessors are not supported")
        dt = np.dtype(_NUMPY_OF[a["componentType"]])
        width = _WIDTH_OF[a["type"]]
        v = root["bufferViews"][a["bufferView"]]
        stride = v.get("byteStride") or dt.itemsize * width
        data = view_bytes(a["bufferView"])
        start = a.get("byteOffset", 0)
        count = a["count"]
        if count == 0:
            arr = np.zeros((0, width), dt)
        else:
            need = start + (count - 1) * stride + dt.itemsize * width
            arr = np.ndarray((count, width), dt, buffer=bytes(data[:need]), offset=start,
                             strides=(stride, dt.itemsize)).copy()
        return arr[:, 0] if width == 1 else arr

    def image(i: int) -> np.ndarray:
        im = root["images"][i]
        if "bufferView" in im:
            return _png_decode(view_bytes(im["bufferView"]))
        uri = im["uri"]
        blob = base64.b64decode(uri.split(",", 1)[1]) if uri.startswith("data:") else (path.parent / uri).read_bytes()
        return _png_decode(blob)

    prims = [p for m in root.get("meshes", []) for p in m["primitives"]]
    if not prims:
        raise SceneError(f"{path}: no mesh primitives")
    pos_list, faces_list, labels_list, attr_lists = [], [], [], {"TEXCOORD_0": [], "NORMAL": [], "TANGENT": [],
                                                                TEXTURE_BLUR_ATTRIBUTE: []}
    offset, seen = 0, {}
    for p in prims:
        if p.get("mode", 4) != 4:
            raise SceneError(f"{path}: only triangle primitives (mode 4) are supported")
        key = p["attributes"]["POSITION"]
        if key not in seen:  # primitives sharing vertex accessors share vertices
            seen[key] = offset
            pos = accessor(key).astype(np.float32)
            pos_list.append(pos)
            for name in attr_lists:
                attr_lists[name].append(accessor(p["attributes"][name]).astype(np.float32) if name in p["attributes"] else None)
            offset += pos.shape[0]
        base = seen[key]
        idx = accessor(p["indices"]).astype(np.int64) if "indices" in p else np.arange(accessor(key).shape[0])
        faces_list.append(idx.reshape(-1, 3) + base)
        cls = (p.get("extras") or {}).get("semantic_class")
        labels_list.append(np.full(idx.size // 3, 255 if cls is None else cls, dtype=np.uint8))
    positions = np.concatenate(pos_list)

    def cat(name):
        parts = attr_lists[name]
        return None if any(x is None for x in parts) else np.concatenate(parts)

    uvs, normals, tangents = cat("TEXCOORD_0"), cat("NORMAL"), cat("TANGENT")
    blur = cat(TEXTURE_BLUR_ATTRIBUTE)
    if blur is not None and (blur.ndim != 1 or not np.all(np.isfinite(blur)) or np.any(blur < 0)):
        raise SceneError(f"{path}: the {TEXTURE_BLUR_ATTRIBUTE} attribute must be finite texels ≥ 0, one per vertex; "
                         "re-export the GLB")
    has_labels = any((p.get("extras") or {}).get("semantic_class") is not None for p in prims)
    images: dict[str, np.ndarray] = {}
    textures = root.get("textures", [])
    mats = root.get("materials", [])
    if mats:
        m = mats[0]
        pbr = m.get("pbrMetallicRoughness", {})
        for role, ref in (("base_color", pbr.get("baseColorTexture")), ("orm", pbr.get("metallicRoughnessTexture")),
                          ("normal", m.get("normalTexture")), ("occlusion", m.get("occlusionTexture"))):
            if ref is not None:
                images[role] = image(textures[ref["index"]]["source"])
    if "occlusion" in images and "orm" in images and images["occlusion"].shape == images["orm"].shape \
            and np.array_equal(images["occlusion"], images["orm"]):
        del images["occlusion"]
    dars = (root.get("extras") or {}).get("dars") or {}
    tint_ref = dars.get("light_tint")
    if isinstance(tint_ref, dict) and isinstance(tint_ref.get("index"), int) and 0 <= tint_ref["index"] < len(textures):
        images["light_tint"] = image(textures[tint_ref["index"]]["source"])
    sh = np.asarray(dars["sh"]["coeffs"], dtype=np.float64) if "sh" in dars else None
    ibl = None
    ibl_images: list[list[np.ndarray]] = []
    lights = ((root.get("extensions") or {}).get("EXT_lights_image_based") or {}).get("lights")
    if lights:
        ibl = lights[0]
        ibl_images = [[image(i) for i in mip] for mip in ibl.get("specularImages", [])]
    return GltfAsset(
        vertices=gltf_to_world(positions.astype(np.float64)).astype(np.float32),
        faces=np.concatenate(faces_list),
        face_labels=np.concatenate(labels_list) if has_labels else None,
        uvs=uvs,
        normals=None if normals is None else gltf_to_world(normals.astype(np.float64)).astype(np.float32),
        tangents=None if tangents is None else np.concatenate(
            [gltf_to_world(tangents[:, :3].astype(np.float64)), tangents[:, 3:4]], 1).astype(np.float32),
        positions_gltf=positions,
        images=images,
        sh=sh,
        ibl=ibl,
        ibl_images=ibl_images,
        json=root,
        backdrop=Backdrop.from_json(dars["backdrop"], f"{path}: extras.dars.backdrop") if "backdrop" in dars else None,
        texture_blur=blur,
    )
