"""export.gltf: Khronos validator, axis conversion, SH storage (EXT_lights_image_based + extras), semantics as
primitives, third-party readers, RGBD, geometry exports; and the `dars mesh / bake / export-asset` commands."""

import json
import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from export.gltf import (GltfConfig, decode_rgbd, encode_rgbd, export_gltf, export_obj, export_ply, gltf_to_world,
                         load_glb, sh_specular_cubemap, world_to_gltf)
from toolkit._checks import ConfigError, DarsError, SceneError, ShapeError
from toolkit.bake import BakeConfig, UnwrapConfig, bake_pbr_textures, unwrap_uv
from toolkit.mesh import Mesh, MeshConfig, extract_mesh, load_mesh

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
RNG = np.random.default_rng(7)
SH = RNG.normal(size=(9, 3)) * 0.3
SH[0] += 1.5


def validator_report(path: Path) -> dict:
    """Run the Khronos glTF validator (tools/validate_gltf.mjs) and return its JSON report."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed, so the Khronos glTF validator (npm gltf-validator) cannot run")
    if not (ROOT / "tools" / "node_modules" / "gltf-validator").is_dir():
        r = subprocess.run(["bash", str(ROOT / "scripts" / "setup_node.sh")], capture_output=True, text=True, timeout=300)
        if r.returncode != 0:
            pytest.fail(f"scripts/setup_node.sh could not install the pinned validator:\n{r.stdout}\n{r.stderr}")
    r = subprocess.run([node, str(ROOT / "tools" / "validate_gltf.mjs"), str(path)], capture_output=True, text=True,
                       timeout=120)
    if r.returncode == 2 or not r.stdout.strip():
        pytest.fail(f"validator crashed on {path}: {r.stderr}")
    return json.loads(r.stdout)


def sphere_mesh(res=32) -> Mesh:
    fn = lambda p: 1e3 * torch.sigmoid((0.5 - p.norm(dim=-1)) * 60)  # noqa: E731
    return extract_mesh(fn, np.array([[-1.0] * 3, [1.0] * 3]), MeshConfig(resolution=res, progress=False))


def material_fn(p, n):
    return {"albedo": (p * 0.5 + 0.5).clamp(0, 1), "roughness": torch.full((p.shape[0],), 0.4),
            "metallic": (p[:, 0] > 0).float(), "normal": n, "semantic": (p[:, 2] > 0.2).long() * 4}


@pytest.fixture(scope="module")
def baked():
    mesh = sphere_mesh()
    labels = np.where(mesh.vertices[:, 2] > 0.2, 4, 0).astype(np.uint8)  # wall on top, painting below
    labels[mesh.vertices[:, 2] < -0.3] = 255  # and an unlabelled cap
    mesh = Mesh(mesh.vertices, mesh.faces, mesh.normals, labels=labels)
    uvm = unwrap_uv(mesh, UnwrapConfig(texture_size=128))
    tex = bake_pbr_textures(uvm, material_fn, BakeConfig(size=128, progress=False))
    return uvm, tex


@pytest.fixture(scope="module")
def glb(baked, tmp_path_factory):
    uvm, tex = baked
    path = tmp_path_factory.mktemp("glb") / "scene.glb"
    export_gltf(uvm, tex, path, sh=SH, extras={"note": "test"})
    return path


# ------------------------------------------------------------------------------------------------ validity
def test_glb_passes_khronos_validator(glb):
    report = validator_report(glb)
    issues = report["issues"]
    assert issues["numErrors"] == 0, issues["messages"]
    assert issues["numWarnings"] == 0, issues["messages"]
    # infos only: the validator does not implement EXT_lights_image_based, so it cannot see the IBL images used
    codes = {m["code"] for m in issues["messages"]}
    assert codes <= {"UNSUPPORTED_EXTENSION", "UNUSED_OBJECT"}, codes
    info = report["info"]
    assert info["hasTextures"] and info["materialCount"] == 1 and info["totalTriangleCount"] == load_glb(glb).faces.shape[0]


@pytest.mark.parametrize("embed", [True, False])
def test_gltf_json_variants_pass_validator(baked, tmp_path, embed):
    uvm, tex = baked
    path = export_gltf(uvm, tex, tmp_path / "scene.gltf", sh=SH, embed=embed)
    assert (tmp_path / "scene.bin").exists() != embed
    assert validator_report(path)["issues"]["numErrors"] == 0
    back = load_glb(path)
    assert np.allclose(back.vertices, uvm.vertices, atol=1e-6) and back.images["base_color"].shape == (128, 128, 3)


def test_validator_catches_a_broken_file(glb, tmp_path):
    """The check can fail: corrupt one accessor's count and the validator reports errors."""
    raw = glb.read_bytes()
    n = int.from_bytes(raw[12:16], "little")
    js = json.loads(raw[20:20 + n])
    js["accessors"][0]["count"] += 1000
    blob = json.dumps(js, separators=(",", ":")).encode()
    blob += b" " * ((-len(blob)) % 4)
    rest = raw[20 + n:]
    bad = b"glTF" + (2).to_bytes(4, "little") + (12 + 8 + len(blob) + len(rest)).to_bytes(4, "little") \
        + len(blob).to_bytes(4, "little") + b"JSON" + blob + rest
    (tmp_path / "bad.glb").write_bytes(bad)
    assert validator_report(tmp_path / "bad.glb")["issues"]["numErrors"] > 0


def test_texture_blur_attribute_round_trips_and_validates(baked, tmp_path):
    """A UV mesh's texture_blur is stored as the _TEXTURE_BLUR vertex attribute: the Khronos validator accepts it
    (an application-specific attribute), load_glb reads it back; a GLB without it reads None; a negative value is
    refused on load, naming the attribute."""
    from dataclasses import replace

    uvm, tex = baked
    blur = np.linspace(0.0, 9.0, uvm.num_vertices).astype(np.float32)
    path = export_gltf(replace(uvm, texture_blur=blur), tex, tmp_path / "blur.glb", sh=SH)
    report = validator_report(path)["issues"]
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"]
    back = load_glb(path)
    assert back.texture_blur is not None and np.allclose(back.texture_blur, blur)
    assert load_glb(export_gltf(uvm, tex, tmp_path / "plain.glb", sh=SH)).texture_blur is None
    blur[3] = -1.0
    bad = export_gltf(replace(uvm, texture_blur=blur), tex, tmp_path / "bad.glb", sh=SH)
    with pytest.raises(SceneError, match="_TEXTURE_BLUR"):
        load_glb(bad)


# ------------------------------------------------------------------------------------------------ conventions
def test_axis_conversion_z_up_becomes_y_up(baked, glb):
    assert np.allclose(world_to_gltf(np.array([0.0, 0.0, 1.0])), [0, 1, 0])  # up stays up
    assert np.allclose(world_to_gltf(np.array([0.0, 1.0, 0.0])), [0, 0, -1])
    assert np.allclose(world_to_gltf(np.array([1.0, 0.0, 0.0])), [1, 0, 0])
    uvm, _ = baked
    a = load_glb(glb)
    top = int(np.argmax(uvm.vertices[:, 2]))  # the highest world point ...
    assert int(np.argmax(a.positions_gltf[:, 1])) == top  # ... is the highest glTF point
    assert np.allclose(a.positions_gltf, np.stack([uvm.vertices[:, 0], uvm.vertices[:, 2], -uvm.vertices[:, 1]], 1))
    acc = a.json["accessors"][a.json["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    assert np.allclose(acc["max"], a.positions_gltf.max(0)) and np.allclose(acc["min"], a.positions_gltf.min(0))
    # normals and tangents rotate with the points; handedness and winding are unchanged (det = +1)
    assert np.allclose(a.normals, uvm.normals, atol=1e-5) and np.allclose(a.tangents, uvm.tangents, atol=1e-5)
    assert np.allclose(gltf_to_world(world_to_gltf(uvm.vertices)), uvm.vertices, atol=1e-6)
    v = a.positions_gltf[a.faces].astype(np.float64)
    assert np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() > 0  # still outward in glTF


def test_material_and_textures_round_trip(baked, glb):
    uvm, tex = baked
    a = load_glb(glb)
    assert np.array_equal(a.images["base_color"], tex.base_color)
    assert np.array_equal(a.images["orm"], tex.orm) and "occlusion" not in a.images  # ORM doubles as occlusion
    assert np.array_equal(a.images["normal"], tex.normal)
    m = a.json["materials"][0]
    assert m["occlusionTexture"]["index"] == m["pbrMetallicRoughness"]["metallicRoughnessTexture"]["index"]
    assert np.allclose(a.uvs, uvm.uvs)
    assert a.json["samplers"][0]["wrapS"] == 33071  # clamp: an atlas must not wrap


def babylon_irradiance(irr: np.ndarray, n_gltf: np.ndarray) -> np.ndarray:
    """E(n) from EXT_lights_image_based irradianceCoefficients in Babylon's basis (Condon–Shortley signs)."""
    from toolkit.sh import GLTF_SH_SIGNS, sh_basis

    y = sh_basis(torch.as_tensor(n_gltf)).numpy() * np.asarray(GLTF_SH_SIGNS)
    return y @ irr


def test_sh_stored_and_reread(glb):
    from toolkit.sh import eval_sh, irradiance_sh

    a = load_glb(glb)
    assert np.allclose(a.sh, SH)  # raw SPEC coefficients, world frame, in extras
    assert a.json["extras"]["dars"]["note"] == "test"
    assert a.json["extensionsUsed"] == ["EXT_lights_image_based"] and "extensionsRequired" not in a.json
    assert a.json["scenes"][0]["extensions"]["EXT_lights_image_based"]["light"] == 0
    irr = np.asarray(a.ibl["irradianceCoefficients"])
    assert irr.shape == (9, 3)
    # the stored irradiance, evaluated in glTF's frame, is our irradiance at the same physical direction
    n_world = RNG.normal(size=(64, 3))
    n_world /= np.linalg.norm(n_world, axis=1, keepdims=True)
    expected = irradiance_sh(torch.as_tensor(SH), torch.as_tensor(n_world)).numpy()
    assert np.allclose(babylon_irradiance(irr, world_to_gltf(n_world)), expected, rtol=1e-6, atol=1e-9)
    # world up (+z) is glTF +y: the probe's "sky" stays up
    assert np.allclose(babylon_irradiance(irr, np.array([[0.0, 1.0, 0.0]])),
                       irradiance_sh(torch.as_tensor(SH), torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)).numpy())
    # prefiltered specular cube: 3 mips x 6 faces, 64/32/16 px, RGBD; mip 0 is the unfiltered SH radiance
    assert a.ibl["specularImageSize"] == 64
    assert [len(m) for m in a.ibl_images] == [6, 6, 6]
    assert [m[0].shape for m in a.ibl_images] == [(64, 64, 4), (32, 32, 4), (16, 16, 4)]
    from export.gltf import _cube_face_directions

    d = gltf_to_world(_cube_face_directions(64))
    for k in range(6):
        L = np.maximum(eval_sh(torch.as_tensor(SH), torch.as_tensor(d[k])).numpy(), 0)
        got = decode_rgbd(a.ibl_images[0][k])
        assert np.abs(got - L).max() < 0.03 * L.max() + 0.01
    # +Y face (index 2) looks up in glTF = world +z
    assert np.allclose(_cube_face_directions(4)[2][1, 1] @ [0, 1, 0], _cube_face_directions(4)[2][1, 1].max())


def test_specular_mips_blur_toward_the_mean():
    sh = np.zeros((9, 3))
    sh[0] = 1.0
    sh[3] = 0.8  # strong x-gradient
    mips = sh_specular_cubemap(sh, 16, 3)
    spread = [np.ptp(np.concatenate([f.reshape(-1, 3) for f in m])) for m in mips]
    assert spread[0] > spread[1] > spread[2]
    with pytest.raises(ConfigError, match="power of two"):
        sh_specular_cubemap(sh, 48, 2)


def test_rgbd_round_trip():
    L = np.concatenate([RNG.random((8, 8, 3)) * 0.9, RNG.random((8, 8, 3)) * 50.0], 0)
    back = decode_rgbd(encode_rgbd(L))
    assert np.allclose(back, L, rtol=0.03, atol=0.01 * L.max(-1, keepdims=True).clip(0.05))
    assert encode_rgbd(L).dtype == np.uint8 and encode_rgbd(L).shape == (16, 8, 4)


def test_semantics_as_primitives(baked, glb, tmp_path):
    uvm, tex = baked
    a = load_glb(glb)
    prims = a.json["meshes"][0]["primitives"]
    classes = [p["extras"]["semantic_class"] for p in prims]
    assert classes == sorted(np.unique(uvm.face_labels).tolist()) == [0, 4, 255]
    assert [p["extras"]["semantic_name"] for p in prims] == ["painting", "wall", "unlabelled"]
    assert len({p["attributes"]["POSITION"] for p in prims}) == 1  # vertex data shared, only indices differ
    assert len({p["material"] for p in prims}) == 1
    for c in classes:
        assert (a.face_labels == c).sum() == (uvm.face_labels == c).sum()
    got = {tuple(sorted(f)) + (int(lab),) for f, lab in zip(a.faces.tolist(), a.face_labels)}
    want = {tuple(sorted(f)) + (int(lab),) for f, lab in zip(uvm.faces.tolist(), uvm.face_labels)}
    assert got == want
    one = load_glb(export_gltf(uvm, tex, tmp_path / "one.glb", semantics="none"))
    assert len(one.json["meshes"][0]["primitives"]) == 1 and one.face_labels is None and one.sh is None
    assert "extensionsUsed" not in one.json


def test_third_party_readers(glb, baked):
    import pygltflib
    import trimesh

    uvm, _ = baked
    g = pygltflib.GLTF2.load(str(glb))
    assert len(g.meshes[0].primitives) == 3 and g.extensionsUsed == ["EXT_lights_image_based"]
    scene = trimesh.load(str(glb))
    total = sum(len(m.faces) for m in scene.geometry.values())
    assert total == uvm.num_faces
    pts = np.concatenate([m.vertices for m in scene.geometry.values()])
    assert np.allclose(pts.max(0), world_to_gltf(uvm.vertices).max(0), atol=1e-6)  # trimesh reads glTF's +y up


def test_export_errors(baked, tmp_path):
    uvm, tex = baked
    with pytest.raises(ConfigError, match=r"\.glb or \.gltf"):
        export_gltf(uvm, tex, tmp_path / "x.fbx")
    with pytest.raises(ShapeError, match="sh"):
        export_gltf(uvm, tex, tmp_path / "x.glb", sh=np.zeros((4, 3)))
    with pytest.raises(ConfigError, match="semantics"):
        export_gltf(uvm, tex, tmp_path / "x.glb", semantics="attribute")
    with pytest.raises(ConfigError, match="power of two"):
        export_gltf(uvm, tex, tmp_path / "x.glb", sh=SH, cfg=GltfConfig(ibl_size=48))
    assert not (tmp_path / "x.glb").exists()  # nothing half-written
    with pytest.raises(DarsError, match="not found"):
        load_glb(tmp_path / "missing.glb")


def test_geometry_exports(tmp_path):
    mesh = sphere_mesh(16)
    export_ply(mesh, tmp_path / "m.ply")
    export_obj(mesh, tmp_path / "m.obj")
    assert load_mesh(tmp_path / "m.ply").num_faces == mesh.num_faces == load_mesh(tmp_path / "m.obj").num_faces
    with pytest.raises(ConfigError):
        export_ply(mesh, tmp_path / "m.obj")


# ------------------------------------------------------------------------------------------------ CLI
def _ring_cameras(n=8, dist=2.5, size=48, focal=50.0):
    from toolkit.pinhole import look_at
    from toolkit.scene import Cameras

    c2ws = []
    for k in range(n):
        a = 2 * math.pi * k / n
        el = 0.6 * math.sin(2 * a)
        eye = dist * np.array([math.cos(a) * math.cos(el), math.sin(a) * math.cos(el), math.sin(el)])
        c2ws.append(look_at(eye, [0.0, 0.0, 0.0]))
    full = lambda v: torch.full((n,), float(v))  # noqa: E731
    return Cameras(torch.tensor(np.stack(c2ws), dtype=torch.float32), full(focal), full(focal), full(size / 2),
                   full(size / 2), full(size), full(size))


@pytest.fixture
def fake_field(monkeypatch):
    """A stand-in for toolkit.train.run.load_field_callables: a sphere with a colourful material."""
    import toolkit.train.folder
    import toolkit.train.run

    def load_field_callables(run_dir):
        density = lambda p: 1e3 * torch.sigmoid((0.5 - p.norm(dim=-1)) * 400)  # noqa: E731  (opaque at r ≈ 0.51)
        aabb = torch.tensor([[-1.0] * 3, [1.0] * 3])
        return density, material_fn, aabb, torch.as_tensor(SH), _ring_cameras()

    monkeypatch.setattr(toolkit.train.run, "load_field_callables", load_field_callables)
    # the commands check RUN before any work; the stand-in's RUN is an empty folder
    monkeypatch.setattr(toolkit.train.folder, "find_run", lambda run_dir, checkpoint=None: ({}, Path(run_dir)))
    return load_field_callables


def test_cli_export_asset_end_to_end(fake_field, tmp_path, capsys):
    from toolkit.cli import main

    run = tmp_path / "run"
    run.mkdir()
    out = tmp_path / "asset"
    rc = main(["export-asset", str(run), "--out", str(out), "--resolution", "40", "--faces", "1500",
               "--texture", "128", "--json"])
    assert rc == 0
    stats = json.loads(capsys.readouterr().out)  # --json: only JSON on stdout
    assert stats["faces"] <= 1500 * 1.02 and stats["simplify"]["error"]["mean_fraction"] < 0.01
    glb = out / "scene.glb"
    assert glb.is_file() and (out / "textures" / "base_color.png").is_file() and (out / "mesh_stats.json").is_file()
    a = load_glb(glb)
    assert np.allclose(a.sh, SH) and a.faces.shape[0] == stats["faces"]
    assert set(np.unique(a.face_labels)) == {0, 4}
    assert validator_report(glb)["issues"]["numErrors"] == 0
    # the two-step path: dars mesh, then dars bake
    assert main(["mesh", str(run), "--resolution", "32", "--faces", "800", "--method", "tsdf", "--depth-samples", "64"]) == 0
    mesh = load_mesh(run / "mesh" / "mesh.ply")
    assert 0 < mesh.num_faces <= 820 and mesh.colors is not None and mesh.labels is not None
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert abs(np.median(r) - 0.5) < 2 / 32, np.median(r)  # within a TSDF voxel
    assert main(["bake", str(run), "--texture", "64"]) == 0
    assert (run / "bake" / "base_color.png").is_file() and (run / "bake" / "mesh_uv.obj").is_file()


def test_cli_errors_are_clear(monkeypatch, tmp_path, capsys):
    from toolkit.cli import main

    (tmp_path / "run").mkdir()  # a directory, but not a training run
    assert main(["export-asset", str(tmp_path / "run"), "--out", str(tmp_path / "o")]) == 2
    assert "is not a training run" in capsys.readouterr().err
    assert main(["export-asset", str(tmp_path / "run"), "--out", str(tmp_path / "o"), "--texture", "3"]) == 2
    assert "--texture: must be ≥ 16, got 3" in capsys.readouterr().err  # checked while parsing
    assert main(["mesh", str(tmp_path / "nope")]) == 2
    assert "RUN directory not found" in capsys.readouterr().err
