"""Collision breakdown: hit classes against hand-placed surfaces, and the CLI over an eval output folder."""

import json
import math

import numpy as np
import pytest

from envs.scenes import Box, Capsule, Cylinder, Scene, Sphere, make_scene
from envs.scenes.sdf import union_sdf
from shield_nav.tools.collisions import (
    approach_bearing,
    bearings,
    breakdown,
    camera_angles,
    circling,
    classify_hit,
    format_bearings,
    format_circling,
    format_sides,
    format_table,
    format_timeouts,
    last_progress,
    main,
    max_turns,
    point_times,
    primitive_class,
    shield_share_before,
    sides,
    timeouts,
    yaw_rate_before,
)

PRIMS = (
    Cylinder((10.0, 0.0, 0.0), (10.0, 0.0, 3.0), 0.3),  # vertical post
    Cylinder((20.0, -1.0, 1.5), (20.0, 1.0, 1.5), 0.05),  # thin horizontal bar
    Capsule((30.0, 0.0, 0.1), (30.8, 0.0, 2.5), 0.05),  # thin pole tilted 18.4 deg from vertical
    Box((40.0, 0.0, 1.5), (0.5, 0.5, 1.5)),
    Sphere((50.0, 0.0, 1.5), 0.5),
)


def test_primitive_classes_follow_kind_radius_and_axis():
    assert [primitive_class(p) for p in PRIMS] == [
        "cylinder vertical", "cylinder thin horizontal", "capsule thin inclined", "box", "sphere",
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("pos", "want"),
    [
        ((10.0 - 0.3 - 0.19, 0.0, 1.5), "cylinder vertical"),  # 0.19 m in front of the post's side
        ((20.0 - 0.05 - 0.19, 0.0, 1.5), "cylinder thin horizontal"),
        ((40.0 - 0.5 - 0.19, 0.0, 1.5), "box"),
        ((50.0 - 0.5 - 0.19, 0.0, 1.5), "sphere"),
        ((60.0, 0.0, 0.19), "floor"),  # nothing within 10 m but the floor, 0.19 m below
    ],
)
def test_classify_hit_names_the_nearest_surface(pos, want):
    scene = Scene(primitives=PRIMS)
    got, dist = classify_hit(scene, np.array(pos))
    assert got == want and dist == pytest.approx(0.19, abs=1e-9)


def test_classify_hit_inclined_pole_and_unresolved_and_bad_input():
    scene = Scene(primitives=PRIMS)
    # Axis direction (0.8, 0, 2.4) ~ (1, 0, 3)/sqrt(10); its unit normal in the xz plane is (3, 0, -1)/sqrt(10).
    mid = np.array([30.4, 0.0, 1.3])
    pos = mid - (0.05 + 0.19) * np.array([3.0, 0.0, -1.0]) / math.sqrt(10.0)
    got, dist = classify_hit(scene, pos)
    assert got == "capsule thin inclined" and dist == pytest.approx(0.19, abs=1e-9)
    assert classify_hit(scene, np.array([25.0, 8.0, 1.5]))[0] == "unresolved"  # 1.5 m from the floor, >4 m else
    with pytest.raises(ValueError, match="finite"):
        classify_hit(scene, np.array([np.nan, 0.0, 1.0]))


def _unit(tmp_path, trials):
    units = tmp_path / "units"
    units.mkdir()
    for t in trials:  # as eval.py records them: a point every 10 control steps
        t.setdefault("steps", 10 * (len(t["traj"]) - 1))
    unit = {"row": "r", "family": "ablation", "scene": 0, "speed": 3.0, "trials": trials}
    (units / "r__ablation-00__v3.json").write_text(json.dumps(unit))


def test_breakdown_over_an_eval_folder_and_cli(tmp_path, capsys):
    scene = make_scene("ablation", 0)
    box = next(p for p in scene.primitives if p.kind == "box")
    # A point 0.19 m outside the box's +x face (box frame rotated by its yaw quaternion (w, 0, 0, z)).
    w, z = box.quat[0], box.quat[3]
    yaw = 2.0 * math.atan2(z, w)
    near_box = np.array(box.center) + (box.half[0] + 0.19) * np.array([math.cos(yaw), math.sin(yaw), 0.0])
    assert union_sdf(scene.primitives, near_box[None])[0] == pytest.approx(0.19, abs=1e-6)
    # An open spot 0.15 m above the floor: every primitive farther than 0.5 m.
    xs = np.stack(np.meshgrid(np.arange(5.0, 60.0, 0.5), np.arange(-15.0, 15.0, 0.5)), -1).reshape(-1, 2)
    pts = np.c_[xs, np.full(len(xs), 0.15)]
    near_floor = pts[np.argmax(union_sdf(scene.primitives, pts) > 0.5)]
    traj = lambda p: [[0.0, 0.0, 1.5, 0.0], [*p, 3.0]]  # noqa: E731
    _unit(tmp_path, [
        {"trial": 0, "outcome": "collision", "traj": traj(near_box.tolist())},
        {"trial": 1, "outcome": "collision", "traj": traj(near_floor.tolist())},
        {"trial": 2, "outcome": "success", "traj": traj([63.0, 0.0, 1.5])},
    ])  # fmt: skip
    res = breakdown(str(tmp_path))
    assert res == {("r", 3.0): {"box": 1, "floor": 1}}
    assert "| r | 3 | 2 | 50 | 50 |" in format_table(res)
    assert breakdown(str(tmp_path), speeds=[5.0]) == {}
    main([str(tmp_path), "--json"])
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == [
        {"row": "r", "speed": 3.0, "n": 2, "hits": {"box": 1, "floor": 1}}
    ]


def test_breakdown_rejects_a_folder_without_units(tmp_path):
    with pytest.raises(FileNotFoundError, match="not an eval.py output"):
        breakdown(str(tmp_path))


@pytest.mark.parametrize(
    ("last", "want"),
    [
        ((9.5, 0.0), 0.0),  # head-on into the post (axis at x = 10, y = 0, radius 0.3)
        ((10.0, 0.49), 90.0),  # beside it: the surface is straight to the right of the travel direction
        ((10.0 - 0.49 / math.sqrt(2), 0.49 / math.sqrt(2)), 45.0),  # towards its centre at 45 deg
        ((10.0 - 0.49 / math.sqrt(2), -0.49 / math.sqrt(2)), 45.0),  # the other side: the angle is unsigned
    ],
)
def test_approach_bearing_against_a_hand_placed_post(last, want):
    scene = Scene(primitives=PRIMS)
    traj = np.array([[last[0] - 0.3, last[1], 1.5, 3.0], [last[0], last[1], 1.5, 3.0]])  # travelling along +x
    cls, deg = approach_bearing(scene, traj)
    assert cls == "cylinder vertical" and deg == pytest.approx(want, abs=1e-3)


def test_approach_bearing_has_no_angle_for_the_floor_or_a_hover_and_rejects_short_trajectories():
    scene = Scene(primitives=PRIMS)
    assert approach_bearing(scene, np.array([[60.0, 0.0, 0.3], [60.5, 0.0, 0.2]])) == ("floor", None)
    assert approach_bearing(scene, np.array([[9.5, 0.0, 1.5], [9.5, 0.0, 1.5]])) == ("cylinder vertical", None)
    with pytest.raises(ValueError, match="2 points"):
        approach_bearing(scene, np.array([[9.5, 0.0, 1.5]]))


def _box_face():
    """Ablation scene 0, its first box's yaw, +x face normal, a point 0.19 m off that face, and the face's direction."""
    scene = make_scene("ablation", 0)
    box = next(p for p in scene.primitives if p.kind == "box")
    w, z = box.quat[0], box.quat[3]
    yaw = 2.0 * math.atan2(z, w)
    normal = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    hit = np.array(box.center) + (box.half[0] + 0.19) * normal
    along = np.array([-normal[1], normal[0], 0.0])  # parallel to the face
    return scene, yaw, normal, hit, along


def test_bearings_over_an_eval_folder_and_cli(tmp_path, capsys):
    _, _, normal, hit, along = _box_face()
    head_on = [[*(hit + 0.5 * normal), 3.0], [*hit, 3.0]]  # flying into the face
    grazing = [[*(hit - 0.5 * along), 3.0], [*hit, 3.0]]  # flying along it
    _unit(tmp_path, [
        {"trial": 0, "outcome": "collision", "traj": head_on},
        {"trial": 1, "outcome": "collision", "traj": grazing},
        {"trial": 2, "outcome": "success", "traj": grazing},
    ])  # fmt: skip
    res = bearings(str(tmp_path))
    r = res[("r", 3.0)]
    assert r["n"] == 2 and r["in_view"] == pytest.approx(0.5)
    assert sorted(d for _, d in r["bearings"]) == pytest.approx([0.0, 90.0], abs=1e-3)
    assert "| r | 3 | 2 | 45 | 50 % | 50 % |" in format_bearings(res, 87.0)
    main([str(tmp_path), "--bearing", "--json", "--hfov", "60"])
    (row,) = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["n"] == 2 and row["in_view"] == pytest.approx(0.5) and row["median_deg"] == pytest.approx(45.0, abs=1e-3)
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--bearing", "--hfov", "200"])


def test_camera_angles_and_bearings_from_the_recorded_heading(tmp_path, capsys):
    scene, yaw, normal, hit, along = _box_face()
    facing_box, facing_along = yaw + math.pi, yaw + math.pi / 2  # camera axis -normal, and +along

    def traj(p0: np.ndarray, heading: float) -> list:
        return [[*p0, 3.0, heading], [*hit, 3.0, heading]]

    looking = traj(hit + 0.5 * normal, facing_box)  # flies into the face, camera on it: in view, not blind
    sideways = traj(hit + 0.5 * normal, facing_along)  # flies into the face looking along it: 90 deg, blind
    grazing = traj(hit - 0.5 * along, facing_along)  # slides along the face looking ahead: face beside, not blind
    assert camera_angles(scene, np.array(looking)) == pytest.approx((0.0, 0.0), abs=1e-3)
    assert camera_angles(scene, np.array(sideways)) == pytest.approx((90.0, 90.0), abs=1e-3)
    assert camera_angles(scene, np.array(grazing)) == pytest.approx((90.0, 0.0), abs=1e-3)
    floor = np.array([[60.0, 0.0, 0.3, 3.0, 0.0], [60.5, 0.0, 0.2, 3.0, math.pi]])
    assert camera_angles(scene, floor) == (None, pytest.approx(180.0))
    with pytest.raises(ValueError, match="heading column"):
        camera_angles(scene, np.array(looking)[:, :4])
    _unit(tmp_path, [
        {"trial": 0, "outcome": "collision", "traj": looking},
        {"trial": 1, "outcome": "collision", "traj": sideways},
        {"trial": 2, "outcome": "collision", "traj": grazing},
        {"trial": 3, "outcome": "success", "traj": sideways},
    ])  # fmt: skip
    r = bearings(str(tmp_path))[("r", 3.0)]
    assert r["n"] == 3 and r["in_view"] == pytest.approx(2 / 3)  # travel cone: the two head-on flights
    assert r["in_camera"] == pytest.approx(1 / 3) and r["blind"] == pytest.approx(1 / 3)
    main([str(tmp_path), "--bearing"])
    # no crash turned; no shield column: no shield share
    assert "| r | 3 | 3 | 0 | 67 % | 33 % | 33 % | 33 % | 0 | - |" in capsys.readouterr().out


def test_shield_share_before_a_crash_by_hand(tmp_path, capsys):
    # Points at 0, 0.1, ..., 0.6 and 0.65 s; the sixth column is the share of the steps since the previous point
    # with the shield acting.
    t = point_times(65, 10, 0.01)
    share = np.array([0.0, 1.0, 1.0, 0.0, 0.5, 0.5, 1.0, 0.4])
    tr = np.column_stack([np.zeros((8, 5)), share])
    # Intervals ending in the last 0.5 s (after 0.15 s): (0.1, 0.2] ... (0.6, 0.65], lengths 0.1 x 5 and 0.05.
    want = (0.1 * (1.0 + 0.0 + 0.5 + 0.5 + 1.0) + 0.05 * 0.4) / 0.55
    assert shield_share_before(tr, t) == pytest.approx(want)
    assert shield_share_before(tr[:, :5], t) is None  # an unshielded row's output
    assert shield_share_before(tr[:1], t[:1]) is None
    with pytest.raises(ValueError, match="times"):
        shield_share_before(tr, t[:3])
    # Over a folder: the mean of the crashes' shares; successes do not count.
    _, yaw, normal, hit, _ = _box_face()
    p0 = [*(hit + 0.5 * normal), 3.0, yaw + math.pi]
    _unit(tmp_path, [
        {"trial": 0, "outcome": "collision", "traj": [[*p0, 0.0], [*hit, 3.0, yaw + math.pi, 1.0]]},
        {"trial": 1, "outcome": "collision", "traj": [[*p0, 0.0], [*hit, 3.0, yaw + math.pi, 0.5]]},
        {"trial": 2, "outcome": "success", "traj": [[*p0, 0.0], [*hit, 3.0, yaw + math.pi, 0.0]]},
    ])  # fmt: skip
    assert bearings(str(tmp_path))[("r", 3.0)]["shield_share"] == pytest.approx(0.75)
    main([str(tmp_path), "--bearing", "--json"])
    (row,) = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["shield_share"] == pytest.approx(0.75)


def test_yaw_rate_before_a_crash_by_hand():
    # Points every 0.1 s (10 steps of 10 ms) and a last one 0.05 s later (steps not a multiple of 10).
    t = point_times(65, 10, 0.01)
    np.testing.assert_allclose(t, [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.65])
    heading = np.array([0.0, 0.0, 0.0, 0.1, 0.2, 0.3, 0.4, 0.45])  # turning at 1 rad/s from t = 0.2 s
    tr = np.column_stack([np.zeros((8, 4)), heading])
    # The last 0.5 s holds the points at 0.2 ... 0.65 s: 0.45 rad in 0.45 s.
    assert yaw_rate_before(tr, t) == pytest.approx(np.degrees(1.0))
    # Across the +-pi seam: 3.1 -> -3.1 rad is a turn of 0.083 rad, not 6.2.
    tr2 = np.column_stack([np.zeros((3, 4)), [3.0, 3.1, -3.1]])
    assert yaw_rate_before(tr2, np.array([0.0, 0.1, 0.2])) == pytest.approx(np.degrees((0.1 + (2 * np.pi - 6.2)) / 0.2))
    assert yaw_rate_before(tr2[:1], np.array([0.0])) is None  # a single point: no rate
    with pytest.raises(ValueError, match="5"):
        yaw_rate_before(tr2[:, :4], np.array([0.0, 0.1, 0.2]))


def test_timeouts_tell_a_stall_from_a_slow_flight_by_hand(tmp_path, capsys):
    """Two time-outs of 30 s (a point every 0.1 s), the goal 50 m ahead. A: 0.06 m per point for 10 s, then a hover:
    its distance goes more than 1 m below its best at points 17, 34, 51, 68 and 85 (1.02 m each), so it last closed at
    8.5 s, stalled, 44 m left. B: 1 m/s throughout: closing at 1 m/s, 20 m left. The success is not counted."""
    k = np.arange(301)
    a = np.c_[np.minimum(0.06 * k, 6.0), np.zeros(301), np.full(301, 1.5)]
    b = np.c_[0.1 * k, np.zeros(301), np.full(301, 1.5)]
    goal = [50.0, 0.0, 1.5]
    assert last_progress(k * 0.1, 50.0 - a[:, 0], 1.0) == pytest.approx(8.5)
    _unit(tmp_path, [
        {"trial": 0, "outcome": "timeout", "goal": goal, "traj": a.tolist()},
        {"trial": 1, "outcome": "timeout", "goal": goal, "traj": b.tolist()},
        {"trial": 2, "outcome": "success", "goal": goal, "traj": b[:10].tolist()},
    ])  # fmt: skip
    res = timeouts(str(tmp_path))
    assert list(res) == [("r", 3.0)]
    v = res[("r", 3.0)]
    assert (v["n"], v["stalled"]) == (2, 1)
    assert v["stalled_since_s"] == pytest.approx(8.5) and v["stalled_left_m"] == pytest.approx(44.0)
    assert v["closing_left_m"] == pytest.approx(20.0) and v["closing_m_s"] == pytest.approx(1.0)
    assert "| r | 3 | 2 | 1 | 8.5 | 44.0 | 20.0 | 1.0 | - |" in format_timeouts(res)  # no heading: circling unknown
    assert v["circling"] is None
    # A longer window: A's 21.5 s without progress still count as a stall; a 25 s window does not.
    assert timeouts(str(tmp_path), window_s=25.0)[("r", 3.0)]["stalled"] == 0
    main([str(tmp_path), "--timeouts", "--json"])
    assert json.loads(capsys.readouterr().out.strip())[0]["stalled"] == 1
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--timeouts", "--bearing"])


def _headed(heading):
    """A trajectory (T, 5) at rest whose fifth column is ``heading`` [rad]."""
    return np.column_stack([np.zeros((len(heading), 4)), heading])


def test_max_turns_by_hand():
    """Points every 0.1 s. An orbit at 1 rad/s turns 10 rad across any 10 s; a weave of +-1 rad less than 2 rad."""
    t = np.arange(201) * 0.1  # 20 s
    orbit = (t + np.pi) % (2 * np.pi) - np.pi  # wrapped at +-pi 3 times
    assert max_turns(_headed(orbit), t) == pytest.approx(10.0 / (2 * np.pi))
    assert max_turns(_headed(orbit), t, window_s=5.0) == pytest.approx(5.0 / (2 * np.pi))
    assert max_turns(_headed(-orbit), t) == pytest.approx(10.0 / (2 * np.pi))  # the other way round counts the same
    weave = np.sin(t)  # +-1 rad: across 10 s the net change sin(t + 10) - sin(t) is at most 2 |sin 5| = 1.918 rad
    assert max_turns(_headed(weave), t) == pytest.approx(2 * abs(math.sin(5.0)) / (2 * np.pi), abs=1e-3)
    # A flight shorter than the window is taken end to end: 4 s of orbit, 4 rad.
    assert max_turns(_headed(orbit[:41]), t[:41]) == pytest.approx(4.0 / (2 * np.pi))
    # Turning round once (2 pi) and back again: one turn at the most across any window, not the two it yawed through.
    there_and_back = np.r_[np.linspace(0, 2 * np.pi, 50), np.linspace(2 * np.pi, 0, 50)]
    wrapped = (there_and_back + np.pi) % (2 * np.pi) - np.pi
    assert max_turns(_headed(wrapped), np.arange(100) * 0.1, window_s=100.0) == pytest.approx(1.0)
    assert max_turns(_headed(wrapped), np.arange(100) * 0.1, window_s=1.0) == pytest.approx(
        10 * 2 * np.pi / 49 / (2 * np.pi)
    )
    assert max_turns(np.zeros((5, 4)), np.arange(5) * 0.1) is None  # no heading column
    assert max_turns(_headed([0.0]), np.zeros(1)) is None  # one point
    with pytest.raises(ValueError, match="non-finite"):
        max_turns(_headed([0.0, np.nan]), np.array([0.0, 0.1]))
    with pytest.raises(ValueError, match="window_s"):
        max_turns(_headed(orbit), t, window_s=0.0)
    with pytest.raises(ValueError, match="shapes"):
        max_turns(_headed(orbit), t[:-1])


def test_circling_by_outcome_over_a_folder_and_cli(tmp_path, capsys):
    """Three flights of 20 s: a straight success, a time-out that orbits at 1 rad/s for its middle 12 s (12 rad >= 1.5
    turns within 10 s: 10 rad), a collision that weaves. Only the time-out circles; the time-out breakdown says so too.
    """
    t = np.arange(201) * 0.1
    straight = np.c_[t * 2.0, np.zeros(201), np.full(201, 1.5), np.full(201, 2.0), np.zeros(201)]
    turn = np.clip(t - 4.0, 0.0, 12.0)  # 0 rad until 4 s, then 1 rad/s until 16 s
    orbit = straight.copy()
    orbit[:, 0] = 1.0  # going nowhere
    orbit[:, 4] = (turn + np.pi) % (2 * np.pi) - np.pi
    weave = straight.copy()
    weave[:, 4] = 0.8 * np.sin(t)
    goal = [50.0, 0.0, 1.5]
    _unit(tmp_path, [
        {"trial": 0, "outcome": "success", "goal": goal, "traj": straight.tolist()},
        {"trial": 1, "outcome": "timeout", "goal": goal, "traj": orbit.tolist()},
        {"trial": 2, "outcome": "collision", "goal": goal, "traj": weave.tolist()},
    ])  # fmt: skip
    res = circling(str(tmp_path))
    assert res == {("r", 3.0): {"success": [1, 0], "collision": [1, 0], "timeout": [1, 1], "out_of_bounds": [0, 0]}}
    assert "| r | 3 | 3 | 1 | 0 / 1 | 0 / 1 | 1 / 1 | 0 / 0 |" in format_circling(res)
    # 12 rad in all: not 2 turns (12.57 rad) even end to end.
    assert circling(str(tmp_path), window_s=30.0, turns=2.0)[("r", 3.0)]["timeout"] == [1, 0]
    assert timeouts(str(tmp_path))[("r", 3.0)]["circling"] == 1
    main([str(tmp_path), "--circling", "--json"])
    assert json.loads(capsys.readouterr().out.strip())[0]["by_outcome"]["timeout"] == [1, 1]
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--circling", "--timeouts"])
    with pytest.raises(ValueError, match="turns"):
        circling(str(tmp_path), turns=-1.0)


def test_circling_needs_the_heading_column(tmp_path):
    k = np.arange(11)
    _unit(tmp_path, [{"trial": 0, "outcome": "timeout", "goal": [9.0, 0.0, 1.5],
                      "traj": np.c_[k * 0.1, np.zeros(11), np.ones(11)].tolist()}])  # fmt: skip
    with pytest.raises(ValueError, match="heading"):
        circling(str(tmp_path))


def test_sides_share_of_each_success_by_hand(tmp_path, capsys):
    """Ablation scene 0's volume spans y in [-16, 16]. Three successes of 11 points each: along y = 0 (none beside
    the sides), along y = 15.0 (1.0 m from the side: all beside within 1.5 m, none within 0.5 m), and one whose first
    4 points run at y = -15.2 and the other 7 at y = -10 (4 of 11 beside); a time-out along the side is not counted.
    """
    x = np.linspace(0.0, 60.0, 11)
    line = lambda y: np.c_[x, np.broadcast_to(y, x.shape), np.full(11, 1.5), np.full(11, 3.0)].tolist()  # noqa: E731
    goal = [63.0, 0.0, 1.5]
    _unit(tmp_path, [
        {"trial": 0, "outcome": "success", "goal": goal, "traj": line(0.0)},
        {"trial": 1, "outcome": "success", "goal": goal, "traj": line(15.0)},
        {"trial": 2, "outcome": "success", "goal": goal, "traj": line(np.r_[np.full(4, -15.2), np.full(7, -10.0)])},
        {"trial": 3, "outcome": "timeout", "goal": goal, "traj": line(15.5)},
    ])  # fmt: skip
    res = sides(str(tmp_path))
    assert res.keys() == {("r", 3.0, 0)}
    np.testing.assert_allclose(res[("r", 3.0, 0)], [0.0, 1.0, 4.0 / 11.0])
    np.testing.assert_allclose(sides(str(tmp_path), margin=0.5)[("r", 3.0, 0)], [0.0, 0.0, 0.0])
    assert "| r | 3 | 0 | 3 | 0.00 / 0.36 / 1.00 | 1 |" in format_sides(res)
    assert sides(str(tmp_path), speeds=[5.0]) == {}
    main([str(tmp_path), "--sides", "--margin", "0.9", "--json"])
    got = json.loads(capsys.readouterr().out.strip())
    assert got[0]["scene"] == 0 and got[0]["shares"] == pytest.approx([0.0, 0.0, 4.0 / 11.0])
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--sides", "--circling"])
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--sides", "--margin", "-1"])
    with pytest.raises(ValueError, match="margin"):
        sides(str(tmp_path), margin=math.nan)
