"""viewers.refit: the per-vertex light factor that brings what our viewer shows of a GLB to the field's colour."""

import numpy as np
import pytest
import torch

from _viewer_assets import textured_cube
from export.gltf import load_glb
from toolkit.cameras import cameras_from_pinholes
from toolkit.io import srgb_to_linear
from toolkit.mesh import Mesh
from toolkit.pinhole import PinholeCamera, look_at
from toolkit.viewbake import ViewMaps

SIZE = 48


def _views():
    eyes = [(2.2, -1.6, 1.4), (-1.8, -2.0, 1.2), (0.4, -2.6, 0.9)]
    return cameras_from_pinholes([PinholeCamera(look_at(e, (0.0, 0.0, 0.0)), 60.0, 60.0, SIZE / 2, SIZE / 2, SIZE,
                                                SIZE) for e in eyes])


def _shown(glb, cams, gl):
    """What the viewer shows at each camera: linear colour [V, H, W, 3] and the mesh's coverage [V, H, W]."""
    from viewers.preview import OffscreenPreview

    colour, mask = [], []
    with OffscreenPreview(glb, ctx=gl) as view:
        for i in range(len(cams)):
            img = view.render(PinholeCamera.from_cameras(cams, i, near=0.01, far=20.0))
            colour.append(srgb_to_linear(np.asarray(img.to_float(), np.float64)[..., :3]))
            mask.append(np.asarray(img.mask))
    return torch.as_tensor(np.stack(colour), dtype=torch.float32), torch.as_tensor(np.stack(mask))


def test_viewer_light_correction_recovers_the_light_the_viewer_lacks(tmp_path, gl):
    """The field shows the viewer's own render times (1.6, 1, 0.5): every vertex the views see gets that factor;
    vertices no view sees (the cube's far side) keep 1. A field that shows what the viewer shows gives 1."""
    from viewers.refit import CORRECTION_RANGE, viewer_light_correction

    glb = textured_cube(tmp_path / "flat.glb", pattern=False, sh=np.eye(9, 3)[:, [0, 0, 0]] * 1.2)
    asset = load_glb(glb)
    mesh = Mesh(np.asarray(asset.vertices, np.float32), np.asarray(asset.faces, np.int64))
    cams = _views()
    colour, mask = _shown(glb, cams, gl)
    assert mask.float().mean() > 0.1 and colour[mask].max() < 0.55  # unsaturated at 1.6x too
    depth = torch.ones(len(cams), SIZE, SIZE)
    factor = torch.tensor([1.6, 1.0, 0.5])
    maps = ViewMaps(cams, depth, mask.float(), {"rgb": colour * factor})
    c = viewer_light_correction(glb, mesh, maps)
    assert c.shape == (mesh.num_vertices, 3)
    seen = np.abs(c - 1.0).max(1) > 1e-6
    assert 0 < seen.sum() < mesh.num_vertices  # the far faces are not seen
    assert np.allclose(c[seen], factor.numpy(), rtol=0.03), c[seen]
    assert (c >= CORRECTION_RANGE[0]).all() and (c <= CORRECTION_RANGE[1]).all()
    same = viewer_light_correction(glb, mesh, ViewMaps(cams, depth, mask.float(), {"rgb": colour}))
    assert np.allclose(same, 1.0, atol=0.02)
    with pytest.raises(ValueError, match="field's colour"):
        viewer_light_correction(glb, mesh, ViewMaps(cams, depth, mask.float(), {"albedo": colour}))


def test_vertex_values_interpolate_on_the_closest_face():
    from toolkit.viewbake import VertexValues

    quad = Mesh(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2], [0, 2, 3]]))
    values = np.array([[0.0], [1.0], [1.0], [0.0]])  # = x
    pts = torch.tensor([[0.25, 0.5, 0.0], [0.8, 0.1, 0.02], [0.5, 0.9, -0.01]])
    assert torch.allclose(VertexValues(quad, values)(pts)[:, 0], pts[:, 0], atol=1e-5)
    with pytest.raises(ValueError, match="3 values for 4 vertices"):
        VertexValues(quad, values[:3])


def test_build_asset_viewer_fit_keeps_the_bake_without_opengl_and_refits_with_it(gl):
    """asset._viewer_fit: one pass re-bakes with the viewer's factor and says so in the statistics; with no viewer
    given, or where no headless OpenGL context can be made, the first bake is kept and the statistics say why."""
    from types import SimpleNamespace

    from test_viewbake import _blue, _floor_quad, _lit_maps, _sh
    from toolkit._checks import DarsError
    from toolkit.asset import AssetConfig, _viewer_fit, bake_mesh
    from viewers.refit import viewer_correction

    maps = _lit_maps((0.12, 0.06, 0.02))
    cfg = AssetConfig(texture=64)
    mesh = _floor_quad()
    uvmesh, tex, stats = bake_mesh(mesh, _blue, cfg, views=maps, sh=_sh())
    field = SimpleNamespace(material_fn=_blue, sh=_sh())
    mesh_stats = {"vertices": mesh.num_vertices, "faces": mesh.num_faces, "area_m2": 1.0, "method": "mc"}
    _, tex1, stats1 = _viewer_fit(mesh, field, maps, cfg, uvmesh, tex, stats, None, viewer_correction, mesh_stats)
    assert stats1["viewer_fit"]["passes"] == 1 and stats1["light_fit"] is True
    assert 0 < stats1["viewer_fit"]["vertices_corrected"] <= 1
    assert np.array_equal(tex1.base_color, tex.base_color)

    def no_gl(*a, **k):
        raise DarsError("could not create a headless OpenGL 3.3 context on EGL (test)")

    _, tex2, stats2 = _viewer_fit(mesh, field, maps, cfg, uvmesh, tex, stats, None, no_gl, mesh_stats)
    assert "headless OpenGL" in stats2["viewer_fit"]["skipped"]
    assert tex2 is tex
    _, tex3, stats3 = _viewer_fit(mesh, field, maps, cfg, uvmesh, tex, stats, None, None, mesh_stats)
    assert "viewers.refit.viewer_correction" in stats3["viewer_fit"]["skipped"] and tex3 is tex


def test_rebake_reuses_the_unwrap_and_gives_the_same_textures(monkeypatch):
    """bake_mesh(uvmesh=...) skips the UV unwrap and the face labelling (a re-bake of the viewer fit) and bakes
    what a fresh unwrap would; an uvmesh of another mesh is refused."""
    import toolkit.bake as bake
    from test_viewbake import _blue, _floor_quad, _lit_maps, _sh
    from toolkit._checks import ShapeError
    from toolkit.asset import AssetConfig, bake_mesh

    maps = _lit_maps((0.12, 0.06, 0.02))
    cfg = AssetConfig(texture=64)
    mesh = _floor_quad()
    uvmesh, tex, _ = bake_mesh(mesh, _blue, cfg, views=maps, sh=_sh())

    def refused(*a, **k):
        raise AssertionError("re-bake ran the unwrap or the labelling again")

    monkeypatch.setattr(bake, "unwrap_uv", refused)
    monkeypatch.setattr(bake, "label_faces", refused)
    uv2, tex2, stats2 = bake_mesh(mesh, _blue, cfg, views=maps, sh=_sh(), uvmesh=uvmesh)
    assert np.array_equal(uv2.uvs, uvmesh.uvs) and np.array_equal(uv2.face_labels, uvmesh.face_labels)
    for k in ("base_color", "orm", "normal"):
        assert np.array_equal(getattr(tex2, k), getattr(tex, k)), k
    assert stats2["unwrap_seconds"] == 0.0
    small = Mesh(mesh.vertices[:3], mesh.faces[:1])
    with pytest.raises(ShapeError, match="not an unwrap of this mesh"):
        bake_mesh(small, _blue, cfg, views=maps, sh=_sh(), uvmesh=uvmesh)
