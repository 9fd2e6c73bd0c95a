"""Room layout by photometric plane sweep (toolkit.layout): a box room rendered in code, its box recovered."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from toolkit._checks import ConfigError
from toolkit.cameras import Cameras, generate_rays
from toolkit.layout import (FACE_NAMES, LayoutConfig, RoomLayout, box_depth, face_normals, fit_room_layout,
                            layout_depth_targets, line_yaw)
from toolkit.pinhole import look_at

YAW = math.radians(20.0)  # the room is not aligned with the world axes
R = np.array([[math.cos(YAW), -math.sin(YAW), 0.0], [math.sin(YAW), math.cos(YAW), 0.0], [0.0, 0.0, 1.0]])
LO, HI = np.array([-2.0, -1.5, 0.0]), np.array([3.0, 2.0, 2.8])


def _texture(q: np.ndarray, face: np.ndarray, plain: bool) -> np.ndarray:
    """Colour [N, 3] of box points q (box frame) on faces: plain walls with a painting each, a tiled floor."""
    base = np.array([[0.55, 0.52, 0.48], [0.50, 0.50, 0.52], [0.60, 0.55, 0.50], [0.45, 0.47, 0.50],
                     [0.30, 0.20, 0.12], [0.80, 0.80, 0.80]])
    col = base[face].copy()
    if plain:
        return np.full_like(col, 0.5)
    k = face // 2
    u = np.where(k[:, None] == 0, q[:, [1, 2]], np.where(k[:, None] == 1, q[:, [0, 2]], q[:, [0, 1]]))
    wall = k < 2
    inside = wall & (np.abs(u[:, 0] - 0.3) < 0.6) & (np.abs(u[:, 1] - 1.5) < 0.45)  # a painting on every wall
    pat = 0.5 + 0.4 * np.sin(7 * u[:, 0] + 3 * np.sin(5 * u[:, 1])) * np.cos(9 * u[:, 1] + face)
    col[inside] = pat[inside, None] * np.array([0.9, 0.6, 0.3])
    floor = face == 4
    tiles = ((np.floor(u[:, 0] / 0.5) + np.floor(u[:, 1] / 0.5)) % 2)[:, None] * 0.08
    col[floor] += tiles[floor]
    return col.clip(0, 1)


class _BoxRoom:
    """What :func:`fit_room_layout` reads of a Scene: cameras, len and load_image."""

    def __init__(self, n: int = 16, size: int = 64, plain: bool = False, glossy: bool = False):
        rng = np.random.default_rng(0)
        c2w = []
        for i in range(n):
            a = 2 * math.pi * i / n
            eye = R @ np.array([0.5 + 1.2 * math.cos(a), 0.25 + 0.9 * math.sin(a), 1.4 + 0.1 * rng.standard_normal()])
            target = R @ np.array([0.5 + 3.0 * math.cos(a + 0.4), 0.25 + 3.0 * math.sin(a + 0.4), 1.2])
            c2w.append(look_at(eye, target, up=np.array([0.0, 0.0, 1.0])))
        c2w = torch.tensor(np.stack(c2w), dtype=torch.float64)
        f = torch.full((n,), size * 0.6, dtype=torch.float64)
        c = torch.full((n,), size / 2, dtype=torch.float64)
        s = torch.full((n,), size, dtype=torch.int64)
        self.cameras = Cameras(c2w, f, f, c, c, s, s)
        self.layout = RoomLayout(origin=np.zeros(3), axes=R.T.copy(), lo=LO, hi=HI, confident=np.ones(6, bool),
                                 contrast=np.zeros(6), coverage=np.zeros(6))
        self.size, self.plain, self.glossy = size, plain, glossy
        # sparse points as SIFT would find them: on the paintings (and a few on the floor tiles)
        pts = []
        for fidx in range(4):
            k, side = divmod(fidx, 2)
            q = np.zeros((40, 3))
            q[:, k] = HI[k] if side else LO[k]
            other = 1 - k
            q[:, other] = 0.3 + rng.uniform(-0.6, 0.6, 40)
            q[:, 2] = 1.5 + rng.uniform(-0.45, 0.45, 40)
            pts.append(q)
        self.points = np.concatenate(pts) @ R.T

    def __len__(self) -> int:
        return len(self.cameras)

    def load_image(self, v: int) -> torch.Tensor:
        rays = generate_rays(self.cameras, [v])  # every pixel, row-major
        o, d = rays.origins, rays.directions
        t, face = box_depth(self.layout, o, d)
        q = ((o + t[:, None] * d).numpy()) @ R  # world -> box frame (R's columns are the box axes)
        col = _texture(q, face.numpy(), self.plain)
        if self.glossy:  # the +a wall: dark and glossy, its painting matte
            ob, db = o.numpy() @ R, d.numpy() @ R
            wall = (face.numpy() == 1) & ~((np.abs(q[:, 1] - 0.3) < 0.6) & (np.abs(q[:, 2] - 1.5) < 0.45))
            # a mirror's image of the room lies behind it: the ray, continued through the wall, meets what it
            # reflects; here a smooth (blurred) pattern on a plane 1.5 m behind the wall
            tv = (HI[0] + 1.5 - ob[:, 0]) / np.where(np.abs(db[:, 0]) > 1e-9, db[:, 0], 1e-9)
            qv = ob + tv[:, None] * db
            refl = 0.35 * (0.5 + 0.5 * np.sin(1.3 * qv[:, 1] + 0.4) * np.cos(1.1 * qv[:, 2]))
            col[wall] = 0.05 + refl[wall, None] * np.array([1.0, 0.95, 0.9])
        return torch.from_numpy(col.T.reshape(3, self.size, self.size)).float()


CFG = LayoutConfig(max_side=64, max_views=16)


def _face_errors(lay: RoomLayout) -> np.ndarray:
    """|fitted - true| per face (order FACE_NAMES), compared along the fitted axes."""
    corners = np.array([[x, y, z] for x in (LO[0], HI[0]) for y in (LO[1], HI[1]) for z in (LO[2], HI[2])]) @ R.T
    proj = (corners - lay.origin) @ lay.axes.T
    return np.abs(np.stack([lay.lo - proj.min(0), lay.hi - proj.max(0)], 1).reshape(-1))


def test_a_box_room_with_paintings_is_recovered_and_its_walls_count():
    room = _BoxRoom()
    lay = fit_room_layout(room, room.points, CFG)
    assert lay.photos == len(room)
    assert abs(abs(lay.axes[2] @ np.array([0, 0, 1.0])) - 1) < 1e-3  # up
    # the horizontal axes are the room's (either order and sign), not the world's
    assert max(abs(lay.axes[0] @ R[:, 0]), abs(lay.axes[0] @ R[:, 1])) > math.cos(math.radians(1.0))
    err = _face_errors(lay)  # every face's position, compared in world coordinates
    walls_floor = [0, 1, 2, 3, 4]
    assert (err[walls_floor] < 0.12).all(), dict(zip(FACE_NAMES, err.round(3)))
    assert lay.confident[walls_floor].all(), lay.to_json()
    tg = layout_depth_targets(room, lay, regions=lambda v: np.ones((room.size, room.size), np.int32))
    assert len(tg["depth"]) > 0.5 * len(room) * room.size ** 2
    # the targets are the true box's depth along the camera axis
    truth = []
    for v in tg["views"].unique().tolist():
        m = tg["views"] == v
        rays = generate_rays(room.cameras, v, pixels=torch.stack([tg["cols"][m], tg["rows"][m]], -1))
        t, _ = box_depth(room.layout, rays.origins, rays.directions)
        truth.append((t * rays.z_scale).float())
    assert (tg["depth"] - torch.cat(truth)).abs().median() < 0.08
    # each target's normal is the inward normal of the true face its ray leaves through
    truth_n = []
    true_inward = torch.from_numpy(face_normals(room.layout)).float()
    for v in tg["views"].unique().tolist():
        m = tg["views"] == v
        rays = generate_rays(room.cameras, v, pixels=torch.stack([tg["cols"][m], tg["rows"][m]], -1))
        _, f = box_depth(room.layout, rays.origins, rays.directions)
        truth_n.append(true_inward[f])
    cos = (tg["normal"] * torch.cat(truth_n)).sum(-1)
    assert tg["normal"].shape == (len(tg["depth"]), 3)
    assert (cos > math.cos(math.radians(2.0))).float().mean() > 0.9, cos.quantile(torch.tensor([0.05, 0.5]))


def test_face_normals_point_into_the_box():
    """A low face's inward normal is its axis, a high face's the axis negated: from the box's centre, every face
    lies against its normal; the floor's is up."""
    lay = RoomLayout(origin=np.array([0.5, -1.0, 0.0]), axes=np.array([[0.6, 0.8, 0.0], [-0.8, 0.6, 0.0], [0, 0, 1.0]]),
                     lo=np.array([-2.0, -1.5, 0.0]), hi=np.array([3.0, 2.0, 2.5]), confident=np.ones(6, bool),
                     contrast=np.ones(6), coverage=np.ones(6))
    n = face_normals(lay)
    centre = lay.origin + lay.axes.T @ ((lay.lo + lay.hi) / 2)
    for f in range(6):
        q = (lay.lo + lay.hi) / 2
        q[f // 2] = (lay.hi if f % 2 else lay.lo)[f // 2]
        on_face = lay.origin + lay.axes.T @ q
        assert (centre - on_face) @ n[f] > 0, FACE_NAMES[f]
    np.testing.assert_allclose(n[FACE_NAMES.index("floor")], [0, 0, 1])
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)


def test_layout_normal_loss_is_zero_on_the_face_and_grows_with_the_angle():
    from toolkit.losses import layout_normal_loss

    t = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    w = torch.ones(2)
    assert float(layout_normal_loss(t * 3.0, t, w)) < 1e-6  # length does not matter
    tilt = [float(layout_normal_loss(torch.tensor([[math.sin(a), 0.0, math.cos(a)], [math.cos(a), math.sin(a), 0.0]]),
                                     t, w)) for a in (0.1, 0.5, 1.0)]
    assert tilt == sorted(tilt) and abs(tilt[0] - (1 - math.cos(0.1))) < 1e-5
    # a ray that ends in the background (opacity 0) does not count
    assert float(layout_normal_loss(torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), t, torch.tensor([0.0, 1.0]))) < 1e-6
    n = torch.tensor([[0.3, 0.1, 0.9]], requires_grad=True)
    layout_normal_loss(n, t[:1], torch.ones(1)).backward()
    assert n.grad is not None and torch.isfinite(n.grad).all() and n.grad.abs().sum() > 0


def test_a_glossy_walls_reflections_do_not_draw_it_behind_itself():
    """A dark glossy wall shows the room's reflection, which lines up between the photos behind the wall. Raw
    colours follow it (the wall lands ~0.3 m too far here, as gallery 1000002's did); the cross-checked fit takes
    the high-passed fit's nearer position for that wall only, where its painting and its edges are."""
    room = _BoxRoom(glossy=True)
    raw = fit_room_layout(room, room.points, LayoutConfig(max_side=64, max_views=16, highpass=0.0))
    lay = fit_room_layout(room, room.points, CFG)
    e_raw, e = _face_errors(raw), _face_errors(lay)
    wall = int(np.argmax(e_raw[:4]))  # which face the fit labels +a depends on the axes' order and sign
    assert e_raw[wall] > 0.2, dict(zip(FACE_NAMES, e_raw.round(3)))  # the failure is real in this room
    assert (e[:5] < 0.12).all() and lay.confident[:5].all(), dict(zip(FACE_NAMES, e.round(3)))
    assert lay.band[wall] == "high-pass" and lay.band.count("high-pass") == 1, lay.band  # the others: colour


def _yaw_error(axes: np.ndarray) -> float:
    """Degrees between the fitted horizontal axes and the room's (modulo 90°)."""
    a = math.degrees(math.atan2(axes[0][1], axes[0][0])) - math.degrees(YAW)
    return abs((a + 45.0) % 90.0 - 45.0)


def test_line_yaw_reads_the_rooms_turn_from_its_edges():
    room = _BoxRoom()
    angle, peak, segments = line_yaw(room, np.array([0.0, 0.0, 1.0]))
    assert segments >= 20 and peak > LayoutConfig().min_line_peak, (segments, peak)
    assert abs(angle - 20.0) < 0.5, angle  # in [-45, 45): the turn nearest the frame's axes
    # featureless photos have no edges: nothing votes
    angle, peak, segments = line_yaw(_BoxRoom(n=4, plain=True), np.array([0.0, 0.0, 1.0]))
    assert segments == 0 and not math.isfinite(angle) and peak == 0.0


def test_the_edges_set_the_yaw_where_the_points_would_not():
    room = _BoxRoom()
    # sparse points that say nothing about the walls (a blob in the middle of the room): their sharpest histograms
    # fall at any turn
    blob = np.random.default_rng(3).normal(size=(200, 3)) * 0.4 + np.array([0.5, 0.2, 1.3])
    by_points = fit_room_layout(room, blob, LayoutConfig(max_side=64, max_views=16, yaw_from="points"))
    by_lines = fit_room_layout(room, blob, CFG)
    assert by_points.yaw == "points" and by_lines.yaw == "lines"
    assert _yaw_error(by_lines.axes) < 0.5, _yaw_error(by_lines.axes)
    assert _yaw_error(by_points.axes) > 2.0, _yaw_error(by_points.axes)  # what the edges fixed
    assert (_face_errors(by_lines)[:5] < 0.12).all(), _face_errors(by_lines).round(3)
    assert RoomLayout.from_json(json.loads(json.dumps(by_lines.to_json()))).yaw == "lines"
    # no clear peak (a threshold no histogram reaches): the points decide, and the box says so
    fallback = fit_room_layout(room, blob, LayoutConfig(max_side=64, max_views=16, min_line_peak=1e9))
    assert fallback.yaw == "points" and np.allclose(fallback.axes, by_points.axes)


def test_the_edge_yaw_and_the_sweep_read_each_photo_once(monkeypatch):
    """fit_room_layout decodes a photo once for both the edge yaw and the sweep: the box is the one fitted when each
    reads its own copy (the sweep's images built from the photos as the sweep itself would)."""
    import toolkit.layout as lay_mod

    room = _BoxRoom()
    reads = []
    load = room.load_image
    monkeypatch.setattr(room, "load_image", lambda v: reads.append(int(v)) or load(v), raising=False)
    shared = fit_room_layout(room, room.points, CFG)
    assert sorted(reads) == sorted(set(reads)) and len(reads) == min(len(room), CFG.max_views), reads
    sweep = lay_mod._Sweep

    def own_copies(scene, views, cfg, layout, images=None):  # the sweep ignores the shared images: reads its own
        assert images is not None and len(images) == len(views)
        return sweep(scene, views, cfg, layout)

    monkeypatch.setattr(lay_mod, "_Sweep", own_copies)
    apart = fit_room_layout(room, room.points, CFG)
    np.testing.assert_array_equal(shared.lo, apart.lo)
    np.testing.assert_array_equal(shared.hi, apart.hi)


def test_featureless_walls_give_no_face_and_no_target():
    room = _BoxRoom(plain=True)
    lay = fit_room_layout(room, room.points, CFG)
    assert not lay.confident.any(), lay.to_json()
    tg = layout_depth_targets(room, lay, regions=lambda v: np.ones((room.size, room.size), np.int32))
    assert len(tg["depth"]) == 0


def test_bad_layout_config_raises():
    with pytest.raises(ConfigError):
        LayoutConfig(rise_ratio=1.0)
    with pytest.raises(ConfigError):
        LayoutConfig(candidates=2)
    with pytest.raises(ConfigError):
        LayoutConfig(min_pixels=1.0)
    for stride in (0, 9):
        with pytest.raises(ConfigError, match="stride"):
            LayoutConfig(stride=stride)
    for hp in (-0.1, 1.5):
        with pytest.raises(ConfigError, match="highpass"):
            LayoutConfig(highpass=hp)
    with pytest.raises(ConfigError, match="yaw_from"):
        LayoutConfig(yaw_from="edges")
    with pytest.raises(ConfigError, match="min_line_peak"):
        LayoutConfig(min_line_peak=0.5)


def test_room_layout_json_round_trip_and_bad_record():
    room = _BoxRoom(n=4, size=16)
    lay = RoomLayout(origin=np.array([0.1, 0.2, 0.3]), axes=R.T.copy(), lo=LO, hi=HI,
                     confident=np.array([1, 0, 1, 1, 0, 1], bool), contrast=np.linspace(0, 0.5, 6),
                     coverage=np.linspace(0.1, 0.6, 6), photos=7, band=["colour"] * 5 + ["high-pass"])
    back = RoomLayout.from_json(json.loads(json.dumps(lay.to_json())))
    for k in ("origin", "axes", "lo", "hi", "confident", "photos"):
        np.testing.assert_allclose(getattr(back, k), getattr(lay, k))
    assert back.band == lay.band
    old = lay.to_json()  # a record written before the cross-check (2026-11-29) has no band: unknown, not refused
    for f in old["faces"].values():
        del f["band"]
    assert RoomLayout.from_json(old).band == []
    rays = generate_rays(room.cameras, [0])
    np.testing.assert_allclose(box_depth(back, rays.origins, rays.directions)[0],
                               box_depth(lay, rays.origins, rays.directions)[0])
    bad = lay.to_json()
    del bad["faces"]["ceiling"]
    with pytest.raises(ConfigError, match="ceiling"):
        RoomLayout.from_json(bad)


def test_a_run_saved_before_the_layout_loss_existed_resumes_without_it():
    """config.json of a run made before 2026-11-28 has no layout_depth: it trained without the term, and a resumed
    run must not switch it on (today's room default is 0.1)."""
    from toolkit.train import TrainConfig, make_config

    old = make_config("fast").to_dict()
    assert old["losses"]["layout_depth"] is None  # by scene type: 0.1 for a room
    del old["losses"]["layout_depth"]
    assert TrainConfig.from_dict(old).losses.layout_depth == 0.0
    del old["losses"]["layout_normal"]  # likewise the normal term (2026-12-06)
    assert TrainConfig.from_dict(old).losses.layout_normal == 0.0
    kept = make_config("fast").to_dict()
    assert TrainConfig.from_dict(kept).losses.layout_depth is None  # a stored value (here None) is kept


def test_layout_depth_option_trains_logs_and_is_recorded(sample_scene_path, tmp_path, capsys, monkeypatch):
    """`dars train --layout-depth W`: the box fitted from the photos, the term logged each step, the weight and the
    box in config.json; --resume reuses the recorded box. `--orientation W` is recorded the same way."""
    from toolkit.cli import main

    run = tmp_path / "l"
    assert main(["train", str(sample_scene_path), "--out", str(run), "--steps", "3", "--batch-rays", "256",
                 "--quiet", "--no-auto-priors", "--layout-depth", "0.1", "--orientation", "0.3"]) == 0
    meta = json.load(open(run / "config.json"))
    assert meta["config"]["losses"]["layout_depth"] == 0.1
    assert meta["config"]["losses"]["orientation"] == 0.3  # --orientation (a room's default 1.0)
    faces = meta["room_layout"]["faces"]
    assert set(faces) == set(FACE_NAMES) and any(f["confident"] for f in faces.values())
    rows = [json.loads(line) for line in open(run / "log.jsonl")]
    vals = [r["layout_depth"] for r in rows if r.get("kind") == "train" and "layout_depth" in r]
    assert vals and all(math.isfinite(v) and v >= 0 for v in vals), vals
    # the layout normal term rides on the same rays (a room's default weight, 0.1, recorded as resolved)
    assert meta["config"]["losses"]["layout_normal"] == 0.1
    nv = [r["layout_normal"] for r in rows if r.get("kind") == "train" and "layout_normal" in r]
    assert nv and all(math.isfinite(v) and 0 <= v <= 2 for v in nv), nv
    assert main(["train", "--out", str(run), "--steps", "4", "--resume", "--layout-depth", "0.5", "--quiet"]) == 2
    assert "--layout-depth" in capsys.readouterr().err

    # --resume takes the recorded box: the same targets, no second fit
    def refit(*a, **k):
        raise AssertionError("the box was fitted again on --resume")

    monkeypatch.setattr("toolkit.layout.fit_room_layout", refit)
    assert main(["train", "--out", str(run), "--steps", "4", "--resume", "--layout-depth", "0.1"]) == 0
    assert "the box recorded in the run's config.json" in capsys.readouterr().err
    assert json.load(open(run / "config.json"))["room_layout"] == meta["room_layout"]


def test_priors_layout_stage_writes_the_box_and_training_reads_it(tmp_path, capsys, monkeypatch):
    """`dars priors layout SCENE --out DIR/layout` writes layout.json and layout.png; `dars train --layout-depth W
    --priors DIR` takes that box (no second fit) and records it; a box from another frame is refused by name."""
    from synthetic import make_scene
    from toolkit.cli import main

    scene = make_scene(tmp_path / "s", n_train=12, n_test=2)
    pri = tmp_path / "p"
    assert main(["priors", "layout", str(scene), "--out", str(pri / "layout")]) == 0
    out = capsys.readouterr().out
    assert "room box of" in out and "layout.png" in out
    doc = json.load(open(pri / "layout" / "layout.json"))
    assert doc["photos"] == 12 and len(doc["cameras"]) == 12 and set(doc["faces"]) == set(FACE_NAMES)
    assert doc["ground_truth_inputs"] == "none" and set(doc["curves"]) <= set(FACE_NAMES)
    from PIL import Image

    assert Image.open(pri / "layout" / "layout.png").size[0] > 600

    def refit(*a, **k):
        raise AssertionError("training fitted the box again")

    monkeypatch.setattr("toolkit.layout.fit_room_layout", refit)
    run = tmp_path / "r"
    assert main(["train", str(scene), "--out", str(run), "--steps", "2", "--batch-rays", "256", "--priors", str(pri),
                 "--layout-depth", "0.1"]) == 0
    assert "the box of `dars priors layout`" in capsys.readouterr().err
    rec = json.load(open(run / "config.json"))["room_layout"]
    assert rec["lo"] == doc["lo"] and rec["hi"] == doc["hi"]

    doc["cameras"][next(iter(doc["cameras"]))][0] += 1.0  # as if fitted with the scene in another frame
    (pri / "layout" / "layout.json").write_text(json.dumps(doc))
    assert main(["train", str(scene), "--out", str(tmp_path / "r2"), "--steps", "2", "--batch-rays", "256",
                 "--priors", str(pri), "--layout-depth", "0.1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "fitted in another frame" in err and "dars priors layout" in err


def test_priors_layout_yaw_from_is_chosen_on_the_command_line_and_recorded(tmp_path, capsys):
    """`dars priors layout --yaw-from points` fits the walls' directions from the sparse points (never the edges),
    records the choice in layout.json's config and says where the directions came from; a bad choice is refused."""
    from synthetic import make_scene
    from toolkit.cli import main

    scene = make_scene(tmp_path / "s", n_train=12, n_test=2)
    for how in ("points", "lines"):
        assert main(["priors", "layout", str(scene), "--out", str(tmp_path / how), "--yaw-from", how]) == 0
        out = capsys.readouterr().out
        doc = json.load(open(tmp_path / how / "layout.json"))
        assert doc["config"]["yaw_from"] == how and "walls' directions from the" in out
        if how == "points":
            assert doc["yaw"] in ("points", "cameras") and "photos' edges" not in out
    assert main(["priors", "layout", str(scene), "--out", str(tmp_path / "x"), "--yaw-from", "walls"]) == 2
    assert "invalid choice: 'walls'" in capsys.readouterr().err


def test_layout_targets_only_on_pixels_labelled_wall_or_floor(sample_scene_path):
    """A plain pedestal side is textureless too, but the box's depth there is the wall behind it: with labels, the
    layout targets keep to pixels labelled wall or floor (predicted labels by default; the ground truth here, asked
    for explicitly, so the test knows the classes); without labels some land on the pedestal."""
    from dataclasses import replace

    from toolkit.scene import load_scene
    from toolkit.train import make_config
    from toolkit.train.data import LAYOUT_CLASSES, prepare_data

    scene = load_scene(sample_scene_path, "train")
    cfg = make_config("fast", steps=1, labels="ground-truth")
    cfg = replace(cfg, losses=replace(cfg.losses, layout_depth=0.1))
    logs: list[str] = []
    data = prepare_data(scene, cfg, log=logs.append)
    room = RoomLayout.from_json(data.room_layout)
    bare = prepare_data(scene, replace(cfg, labels="none", semantics=False, mat_labels=False), log=logs.append,
                        room_layout=room)

    def classes(t):
        return np.concatenate([scene.load_extra(v, "semantic").numpy()[t["rows"][t["views"] == v].numpy(),
                                                                     t["cols"][t["views"] == v].numpy()]
                               for v in t["views"].unique().tolist()])

    kept, every = classes(data.layout_depth), classes(bare.layout_depth)
    assert len(kept) > 0.5 * len(every), (len(kept), len(every))
    assert np.isin(kept, LAYOUT_CLASSES).all()
    assert (~np.isin(every, LAYOUT_CLASSES)).sum() > 1000  # the filter has something to remove on the sample
    assert data.priors_used["layout_targets"] == "textureless pixels labelled wall or floor"
    assert "no labels" in bare.priors_used["layout_targets"]
