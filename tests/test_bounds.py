import numpy as np
import pytest
import torch

from toolkit._checks import ConfigError
from toolkit.bounds import (SceneBoxConfig, SparsePoints, SparsePointsConfig, box_from_cameras, scene_box_from_points,
                            sparse_depth_targets, triangulate_sparse_points)


def _ring(n=12, radius=3.0, inward=True):
    """Cameras on a horizontal ring at height 1.5, looking at the origin (inward) or away from it."""
    c2w = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        o = np.array([radius * np.cos(a), radius * np.sin(a), 1.5])
        f = -o / np.linalg.norm(o) if inward else o / np.linalg.norm(o)
        f[2] = 0.0
        f /= np.linalg.norm(f)
        right = np.cross(f, [0, 0, 1.0])
        up = np.cross(right, f)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -f, o
        c2w.append(m)
    return np.stack(c2w)


def test_box_from_points_is_robust_and_padded():
    rng = np.random.default_rng(0)
    pts = rng.uniform([-1, -2, 0], [1, 2, 3], (2000, 3))
    pts = np.concatenate([pts, rng.normal(0, 1000, (10, 3))])  # stray far points
    c2w = _ring(inward=True, radius=8.0)
    box = scene_box_from_points(pts, c2w, np.full(12, 100.0), np.full(12, 100.0),
                                SceneBoxConfig(quantile=0.01, pad=0.1))
    assert box.source.startswith("sparse points")
    ext = np.array([2.0, 4.0, 3.0])
    assert np.all(box.aabb[0] < [-1, -2, 0]) and np.all(box.aabb[1] > [1, 2, 3])
    assert np.all(box.aabb[1] - box.aabb[0] < ext * 1.3), box.aabb  # stray points do not blow it up


def test_box_holds_cameras_inside_a_room():
    rng = np.random.default_rng(1)
    walls = np.concatenate([rng.uniform([-5, 4.9, 0], [5, 5.1, 3], (500, 3)), rng.uniform([-5, -5.1, 0], [5, -4.9, 3], (500, 3))])
    c2w = _ring(radius=4.5, inward=False)  # cameras near the side walls the points do not cover
    box = scene_box_from_points(walls, c2w, np.full(12, 100.0), np.full(12, 100.0))
    o = c2w[:, :3, 3]
    assert np.all(box.aabb[0] <= o.min(0)) and np.all(box.aabb[1] >= o.max(0))


def test_too_few_points_fall_back_to_cameras():
    c2w = _ring(inward=True)
    box = scene_box_from_points(np.zeros((3, 3)), c2w, np.full(12, 100.0), np.full(12, 100.0))
    assert box.source == "cameras"
    np.testing.assert_allclose(box.aabb, box_from_cameras(c2w, np.full(12, 100.0), np.full(12, 100.0)))
    centre = box.aabb.mean(0)
    assert np.allclose(centre[:2], 0.0, atol=1e-6)


def test_configs_refuse_bad_values():
    with pytest.raises(ConfigError):
        SparsePointsConfig(ratio=1.5)
    with pytest.raises(ConfigError):
        SceneBoxConfig(quantile=0.6)
    with pytest.raises(ConfigError, match="min_side"):
        SparsePointsConfig(min_side=0)


def _median_rel_depth_error(scene, sp) -> float:
    sd = sparse_depth_targets(scene, sp)
    rel = []
    for v in sd["views"].unique().tolist():
        m = sd["views"] == v
        g = scene.load_extra(v, "depth").reshape(scene.cameras.height[v], scene.cameras.width[v])[sd["rows"][m],
                                                                                                   sd["cols"][m]]
        rel.append((sd["depth"][m] - g).abs() / g.clamp_min(1e-3))
    return float(torch.cat(rel).median())


def test_small_photos_are_enlarged_for_detection(sample_scene_path):
    """min_side: the sample's 128-px photos enlarged to 256 px for SIFT: several times the points, none less accurate (ground-
    truth depth for scoring only)."""
    from toolkit.scene import load_scene

    scene = load_scene(sample_scene_path, "train")
    small = triangulate_sparse_points(scene, SparsePointsConfig(max_views=24, neighbours=3))
    big = triangulate_sparse_points(scene, SparsePointsConfig(max_views=24, neighbours=3, min_side=256))
    assert len(big) > 3 * len(small) > 0
    assert _median_rel_depth_error(scene, big) <= _median_rel_depth_error(scene, small) + 1e-3


def test_triangulated_points_of_the_sample_lie_on_its_surfaces(sample_scene_path):
    """Without using its box: the sample's points fall on its wall, floor, painting and pedestal."""
    from toolkit.scene import load_scene

    scene = load_scene(sample_scene_path, "train")
    sp = triangulate_sparse_points(scene, SparsePointsConfig(max_views=24, neighbours=3, max_side=128))
    assert len(sp) > 300
    file_box = scene.aabb.numpy()
    inside = np.all((sp.points >= file_box[0] - 0.2) & (sp.points <= file_box[1] + 0.2), axis=1)
    assert inside.mean() > 0.9
    # most points lie on the back wall plane (y = 1) or in front of it, above the floor (z = 0)
    assert np.quantile(sp.points[:, 1], 0.95) < 1.1 and np.quantile(sp.points[:, 2], 0.05) > -0.1
    c2w = scene.cameras.c2w.double().numpy()
    box = scene_box_from_points(sp.points, c2w, scene.cameras.fx.double().numpy(), scene.cameras.width.double().numpy())
    painting_centre = np.array([-0.6, 0.985, 1.45])
    assert np.all(box.aabb[0] < painting_centre) and np.all(box.aabb[1] > painting_centre)
    assert torch.is_tensor(scene.aabb)


def test_sparse_depth_targets_match_the_samples_depth_maps(sample_scene_path):
    """Each triangulated point projected into its two views: the pixel's ground-truth depth (scoring only) agrees."""
    from toolkit.scene import load_scene

    scene = load_scene(sample_scene_path, "train")
    sp = triangulate_sparse_points(scene, SparsePointsConfig(max_views=24, neighbours=3, max_side=128))
    sd = sparse_depth_targets(scene, sp)
    assert len(sd["depth"]) == len(sd["views"]) == len(sd["rows"]) == len(sd["cols"])
    assert len(sd["depth"]) > 1.8 * len(sp)  # both views of almost every point
    assert set(sd["views"].unique().tolist()) <= set(sp.views.reshape(-1).tolist())
    assert _median_rel_depth_error(scene, sp) < 0.03


def test_sparse_depth_targets_drop_points_outside_or_behind_the_view(tmp_path):
    """A point behind the camera and one far outside its frustum give no target; an empty set gives empty tensors."""
    from synthetic import make_scene
    from toolkit.scene import load_scene

    scene = load_scene(make_scene(tmp_path / "s", n_train=3, n_test=1, size=16), "train")
    c2w = scene.cameras.c2w[0].double().numpy()
    fwd = -c2w[:3, 2]
    pts = np.stack([c2w[:3, 3] + 2.0 * fwd, c2w[:3, 3] - 2.0 * fwd, c2w[:3, 3] + 2.0 * fwd + 50.0 * c2w[:3, 0]])
    sd = sparse_depth_targets(scene, SparsePoints(points=pts, views=np.array([[0, 0]] * 3), n_pairs=1))
    assert len(sd["depth"]) == 2 and torch.allclose(sd["depth"], torch.tensor([2.0, 2.0]), atol=1e-4)
    none = SparsePoints(points=np.zeros((0, 3)), views=np.zeros((0, 2), np.int64), n_pairs=0)
    empty = sparse_depth_targets(scene, none)
    assert all(len(t) == 0 for t in empty.values())
