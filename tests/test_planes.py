"""Walls and floor flattened onto the room's box (toolkit.mesh.planes, AssetConfig.snap_layout)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from toolkit._checks import ConfigError, ShapeError
from toolkit.layout import FACE_NAMES, RoomLayout
from toolkit.mesh import Mesh, PlaneSnapConfig, compute_vertex_normals, snap_to_planes


def _grid(n: int, size: float, z, x0: float = 0.0, y0: float = 0.0):
    """An n × n vertex grid over [x0, x0 + size] × [y0, y0 + size] at heights z (scalar or [n, n])."""
    u = np.linspace(0, size, n)
    x, y = np.meshgrid(x0 + u, y0 + u, indexing="ij")
    v = np.stack([x, y, np.broadcast_to(z, x.shape)], -1).reshape(-1, 3)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel(), i[:-1, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _bumpy_floor_and_post(seed: int = 0):
    """A 2 m floor at z = 0 with ±5 cm bumps, and beside it a vertical 1 m post face (x = 2.5) rising from z = 0."""
    rng = np.random.default_rng(seed)
    v1, f1 = _grid(21, 2.0, rng.uniform(-0.05, 0.05, (21, 21)))
    v2, f2 = _grid(11, 1.0, 0.0)
    v2 = v2[:, [2, 0, 1]] + [2.5, 0, 0]  # the grid stood up: x = 2.5, y and z over [0, 1]
    v = np.concatenate([v1, v2]).astype(np.float32)
    f = np.concatenate([f1, f2 + len(v1)]).astype(np.int64)
    return Mesh(v, f, compute_vertex_normals(v, f)), len(v1)


def test_a_bumpy_floor_goes_flat_and_a_post_standing_on_it_keeps_its_shape():
    mesh, n_floor = _bumpy_floor_and_post()
    out, stats = snap_to_planes(mesh, [[0, 0, 1.0]], [0.0], PlaneSnapConfig(tolerance=0.2), ["floor"])
    floor, post, post0 = out.vertices[:n_floor], out.vertices[n_floor:], mesh.vertices[n_floor:]
    assert np.abs(floor[:, 2]).max() < 1e-6  # every bump flattened
    low = post0[:, 2] < 0.2  # the post's foot moves down its own face: x and y stay, the face stays where it was
    np.testing.assert_array_equal(post[:, :2], post0[:, :2])
    assert np.abs(post[low, 2]).max() < 1e-6 and np.array_equal(post[~low], post0[~low])
    assert stats["vertices_moved"] == n_floor + low.sum() and stats["planes"]["floor"]["skipped"] is None
    assert abs(stats["planes"]["floor"]["median_shift_m"]) < 0.02
    assert out.normals is not None and np.allclose(np.abs(out.normals[:n_floor, 2]), 1, atol=1e-5)
    np.testing.assert_array_equal(out.faces, mesh.faces)
    # only vertices whose normals face the plane: the post does not move at all
    out, _ = snap_to_planes(mesh, [[0, 0, 1.0]], [0.0], PlaneSnapConfig(tolerance=0.2, min_cos=0.5))
    np.testing.assert_array_equal(out.vertices[n_floor:], post0)
    # only the vertices allowed to move (the floor's): the post stays, the floor still goes flat
    out, stats = snap_to_planes(mesh, [[0, 0, 1.0]], [0.0], PlaneSnapConfig(tolerance=0.2),
                                movable=np.arange(mesh.num_vertices) < n_floor)
    np.testing.assert_array_equal(out.vertices[n_floor:], post0)
    assert np.abs(out.vertices[:n_floor, 2]).max() < 1e-6 and stats["vertices_moved"] == n_floor
    with pytest.raises(ShapeError):
        snap_to_planes(mesh, [[0, 0, 1.0]], [0.0], PlaneSnapConfig(tolerance=0.2), movable=np.ones(3, bool))


def test_vertices_beyond_the_tolerance_stay_and_a_plane_the_mesh_disagrees_with_is_left_alone():
    mesh, n_floor = _bumpy_floor_and_post()
    lifted = Mesh(mesh.vertices + np.float32([0, 0, 0.5]) * (np.arange(mesh.num_vertices) < n_floor)[:, None],
                  mesh.faces)
    out, stats = snap_to_planes(lifted, [[0, 0, 1.0]], [0.0], PlaneSnapConfig(tolerance=0.2))
    np.testing.assert_array_equal(out.vertices[:n_floor], lifted.vertices[:n_floor])  # 0.45-0.55 m away
    # the plane 9 cm below the floor: its candidates lie 9 cm off on the median, more than a third of 0.2 m
    out, stats = snap_to_planes(mesh, [[0, 0, 1.0]], [-0.09], PlaneSnapConfig(tolerance=0.2), ["low"])
    np.testing.assert_array_equal(out.vertices, mesh.vertices)
    assert "off it on the median" in stats["planes"]["low"]["skipped"] and stats["vertices_moved"] == 0
    _, stats = snap_to_planes(mesh, [[1.0, 0, 0]], [-5.0], PlaneSnapConfig(tolerance=0.2), ["far"])
    assert stats["planes"]["far"]["skipped"] == "no vertex of the mesh lies near it"


def test_each_vertex_goes_to_its_nearest_plane():
    v, f = _grid(11, 1.0, 0.0)  # a floor near two planes 4 cm apart: z = 0.01 and z = -0.03
    mesh = Mesh(v.astype(np.float32), f.astype(np.int64))
    out, stats = snap_to_planes(mesh, [[0, 0, 1.0], [0, 0, 1.0]], [0.01, -0.03],
                                PlaneSnapConfig(tolerance=0.2, max_disagreement=1.0), ["near", "far"])
    np.testing.assert_allclose(out.vertices[:, 2], 0.01, atol=1e-6)
    assert stats["planes"]["near"]["vertices"] == len(v) and stats["planes"]["far"]["vertices"] == 0


def test_bad_snap_config_and_planes_raise():
    for kw in ({"tolerance": 0}, {"tolerance": float("nan")}, {"tolerance": 0.1, "min_cos": 1.0},
               {"tolerance": 0.1, "min_cos": -0.1}, {"tolerance": 0.1, "max_disagreement": 0}):
        with pytest.raises(ConfigError):
            PlaneSnapConfig(**kw)
    mesh, _ = _bumpy_floor_and_post()
    with pytest.raises(ConfigError, match="names"):
        snap_to_planes(mesh, [[0, 0, 1.0]], [0.0], PlaneSnapConfig(tolerance=0.1), ["a", "b"])


def test_room_layout_planes_are_the_confident_faces_in_world_coordinates():
    rot = np.array([[np.cos(0.3), np.sin(0.3), 0], [-np.sin(0.3), np.cos(0.3), 0], [0, 0, 1.0]])
    layout = RoomLayout(origin=np.array([1.0, -2.0, 0.5]), axes=rot, lo=np.array([-3.0, -2.0, -1.5]),
                        hi=np.array([4.0, 2.5, 1.5]), confident=np.array([1, 1, 0, 1, 1, 0], bool),
                        contrast=np.zeros(6), coverage=np.zeros(6))
    normals, offsets, names = layout.planes()
    assert names == ["-a", "+a", "+b", "floor"]
    for n, c, name in zip(normals, offsets, names):
        j = FACE_NAMES.index(name)
        q = np.array([0.3, -0.4, 0.2])
        q[j // 2] = (layout.lo if j % 2 == 0 else layout.hi)[j // 2]
        x = layout.origin + layout.axes.T @ q  # a point on that face of the box
        assert abs(n @ x - c) < 1e-9 and abs(np.linalg.norm(n) - 1) < 1e-9
    assert len(layout.planes(confident_only=False)[2]) == 6


def test_build_mesh_flattens_onto_the_runs_room_box_and_says_why_when_it_cannot():
    """A contracted cube the field labels wall and a confident box face 2 cm beyond its +x side: the TSDF mesh's
    side moves onto that face; labelled 'base' (an exhibit), without a box, with ``snap_layout=0`` or with marching
    cubes the mesh is left as it is."""
    import torch
    from test_asset import _ring, _sphere

    from toolkit.asset import AssetConfig, build_mesh
    from toolkit.space import SceneSpace
    from toolkit.train.run import FieldCallables

    def cube(p):
        return 1e3 * torch.sigmoid((0.5 - p.abs().amax(-1)) * 400)

    wall = RoomLayout(origin=np.zeros(3), axes=np.eye(3), lo=np.array([-3.0, -3.0, -3.0]),
                      hi=np.array([0.52, 3.0, 3.0]), confident=np.array([0, 1, 0, 0, 0, 0], bool),
                      contrast=np.zeros(6), coverage=np.zeros(6))
    def walls(p, n=None):
        return {**_sphere().material_fn(p, n), "semantic": torch.full((len(p),), 4, dtype=torch.long)}

    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    field = FieldCallables(cube, walls, box, None, _ring(8, size=(32, 24)), SceneSpace(box, contraction=True),
                           room_layout=wall)
    cfg = AssetConfig(resolution=48, faces=0, depth_samples=96, depth_rays=8 * 16 * 12, min_component=0)
    plain, s0 = build_mesh(field, replace(cfg, snap_layout=0))
    assert "snap_layout" not in s0
    mesh, stats = build_mesh(field, cfg)
    snap = stats["snap_layout"]
    assert snap["fraction"] == cfg.snap_layout and snap["planes"]["+a"]["skipped"] is None
    assert snap["tolerance_m"] == pytest.approx(cfg.snap_layout * snap["median_depth_m"], abs=1e-3)
    assert snap["planes"]["+a"]["median_shift_m"] == pytest.approx(-0.02, abs=0.01)
    near = np.abs(plain.vertices[:, 0] - 0.52) < snap["tolerance_m"]  # the +x side and the edges of its neighbours
    assert (np.abs(plain.vertices[:, 0] - 0.5) < 0.03).sum() > 20 and snap["vertices_moved"] == near.sum()
    assert np.abs(mesh.vertices[near, 0] - 0.52).max() < 1e-5  # onto the face, along its normal
    np.testing.assert_array_equal(mesh.vertices[near, 1:], plain.vertices[near, 1:])
    np.testing.assert_array_equal(mesh.vertices[~near], plain.vertices[~near])  # the rest as it was
    assert mesh.num_faces == plain.num_faces and snap["movable"].startswith(f"{plain.num_vertices} of ")
    small, stats = build_mesh(field, replace(cfg, faces=plain.num_faces // 4))  # simplified first, then flattened
    assert stats["simplify"]["faces_out"] == small.num_faces < plain.num_faces
    assert stats["snap_layout"]["movable"].startswith(f"{small.num_vertices} of {small.num_vertices} vertices")
    near = np.abs(small.vertices[:, 0] - 0.52) < stats["snap_layout"]["tolerance_m"]
    assert near.sum() == stats["snap_layout"]["vertices_moved"] > 0
    assert np.abs(small.vertices[near, 0] - 0.52).max() < 1e-5
    exhibit, stats = build_mesh(field._replace(material_fn=_sphere().material_fn), cfg)  # every vertex 'base'
    np.testing.assert_array_equal(exhibit.vertices, plain.vertices)
    assert stats["snap_layout"]["movable"].startswith("0 of ") and stats["snap_layout"]["vertices_moved"] == 0
    _, stats = build_mesh(field._replace(room_layout=None), cfg)
    assert "no room box" in stats["snap_layout"]["skipped"]
    _, stats = build_mesh(field, replace(cfg, level=100.0))  # marching cubes: no depth maps
    assert "tsdf depth maps" in stats["snap_layout"]["skipped"]
    with pytest.raises(ConfigError, match="--snap-layout"):
        AssetConfig(snap_layout=0.6)
