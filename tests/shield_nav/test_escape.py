"""The stall escape (shield_nav/safety/escape.py): its timing, side choice and heading-frame goal input against
hand-worked cases, bad input, and a real evaluation row that flies the shipped Full policy with it."""

import dataclasses
import math

import numpy as np
import pytest

from envs.config import ConfigError
from envs.navigation.env import STATE_DIM
from shield_nav import evaluation as E
from shield_nav.safety.camera_map import CameraMap
from shield_nav.safety.escape import GOAL_COLUMNS, ROT_COLUMNS, EscapeConfig, StallEscape

DT = 0.01


def _state(n, psi=0.0, goal_input=(0.7, 0.1)):
    """A state batch whose rotation is a yaw of ``psi`` and whose goal input is ``goal_input``."""
    s = np.zeros((n, STATE_DIM), dtype=np.float32)
    c, si = math.cos(psi), math.sin(psi)
    s[:, ROT_COLUMNS] = np.array([c, -si, 0.0, si, c, 0.0, 0.0, 0.0, 1.0], dtype=np.float32)
    s[:, GOAL_COLUMNS] = goal_input
    return s


def _depth(n, left, right, h=6, w=10):
    """Metric depth images whose left columns read ``left`` and right columns ``right``."""
    d = np.empty((n, 1, h, w), dtype=np.float32)
    d[..., : w // 2], d[..., w // 2 :] = left, right
    return d


def test_state_columns_are_the_layouts():
    assert (GOAL_COLUMNS.start, GOAL_COLUMNS.stop) == (16, 18)  # vel 3 + R 9 + action 4
    assert (ROT_COLUMNS.start, ROT_COLUMNS.stop) == (3, 12)


def test_a_hovering_flight_escapes_after_the_window_then_on_the_other_side_for_longer():
    """Goal 30 m ahead along +x, heading +x, the vehicle never moves; the image's left half is free (20 m, capped at
    10), its right half 2 m away. First escape at t = window (5 s) to the left (+y: heading-frame input (0, 1)) for
    4 s; the true input returns at 9 s; the next window ends at 14 s, then the right side (0, -1) for 6 s, to 20 s."""
    esc = StallEscape(EscapeConfig(), 1, DT)
    pos, goal = np.zeros((1, 3)), np.array([[30.0, 0.0, 0.0]])
    state, depth = _state(1), _depth(1, 20.0, 2.0)
    inputs, counts = [], []
    for t in range(2200):
        out = esc.apply(state, pos, goal, depth, t)
        inputs.append(out[0, GOAL_COLUMNS].copy())
        counts.append(esc.count[0])
    inputs = np.array(inputs)
    steps_of = lambda s: int(round(s / DT))  # noqa: E731
    np.testing.assert_allclose(inputs[: steps_of(5.0)], [[0.7, 0.1]] * steps_of(5.0), rtol=1e-6)
    np.testing.assert_allclose(inputs[steps_of(5.0) : steps_of(9.0)], [[0.0, 1.0]] * steps_of(4.0), atol=1e-7)
    np.testing.assert_allclose(inputs[steps_of(9.0) : steps_of(14.0)], [[0.7, 0.1]] * steps_of(5.0), rtol=1e-6)
    np.testing.assert_allclose(inputs[steps_of(14.0) : steps_of(20.0)], [[0.0, -1.0]] * steps_of(6.0), atol=1e-7)
    np.testing.assert_allclose(inputs[steps_of(20.0) :], [[0.7, 0.1]] * (2200 - steps_of(20.0)), rtol=1e-6)
    assert counts[steps_of(5.0) - 1] == 0 and counts[steps_of(5.0)] == 1 and counts[steps_of(14.0)] == 2
    assert esc.escape_steps[0] == steps_of(4.0) + steps_of(6.0)


def test_a_flight_closing_on_its_goal_never_escapes_and_reads_its_own_state():
    """1 m of progress every 4 s (0.25 m/s) keeps a 5 s window from expiring; the state comes back unchanged."""
    esc = StallEscape(EscapeConfig(), 2, DT)
    goal = np.array([[100.0, 0.0, 1.0], [0.0, 100.0, 1.0]])
    state, depth = _state(2), _depth(2, 5.0, 5.0)
    for t in range(3000):
        pos = np.array([[0.25 * t * DT, 0.0, 1.0], [0.0, 0.25 * t * DT, 1.0]])
        assert esc.apply(state, pos, goal, depth, t) is state
    assert esc.count.tolist() == [0, 0] and esc.escape_steps.tolist() == [0, 0]


def test_the_side_follows_the_image_half_it_lies_in_and_the_input_is_in_the_heading_frame():
    """Goal along +x. Vehicle 0 heads +x (psi 0): the +90 deg side (+y) is the image's left half; its right half is
    free, so it escapes to -y, heading-frame input (0, -1). Vehicle 1 heads -x (psi pi): +y lies in the image's right
    half, which is free, so it escapes to +y; in its heading frame +y is to the right: Rz(-pi) (0, 1) = (0, -1).
    Vehicle 2 heads +y (psi pi/2): +y is straight ahead (heading-frame y = 0 counts as the left half, free there),
    so it escapes to +y: input Rz(-pi/2) (0, 1) = (1, 0)."""
    cfg = EscapeConfig(window_s=0.05)
    esc = StallEscape(cfg, 3, DT)
    state = np.concatenate([_state(1, 0.0), _state(1, math.pi), _state(1, math.pi / 2)])
    depth = np.concatenate([_depth(1, 1.0, 30.0), _depth(1, 1.0, 30.0), _depth(1, 30.0, 1.0)])
    pos, goal = np.zeros((3, 3)), np.tile([[40.0, 0.0, 2.0]], (3, 1))
    for t in range(6):
        out = esc.apply(state, pos, goal, depth, t)
    assert esc.count.tolist() == [1, 1, 1]
    np.testing.assert_allclose(esc.direction, [[0.0, -1.0], [0.0, 1.0], [0.0, 1.0]], atol=1e-12)
    np.testing.assert_allclose(out[:, GOAL_COLUMNS], [[0.0, -1.0], [0.0, -1.0], [1.0, 0.0]], atol=1e-6)
    # Everything but the goal input is the policy's own state.
    keep = np.ones(STATE_DIM, bool)
    keep[GOAL_COLUMNS] = False
    np.testing.assert_array_equal(out[:, keep], state[:, keep])


def test_the_flight_volume_turns_the_side_and_ends_the_hold():
    """Volume x in [0, 60], y in [-16, 16]; goal along +x; heading +x; the image favours the left (+y) side.
    Vehicle 0 at y = 12: +y has 4 m of room (< 10 m), -y 28 m: it escapes to -y. Vehicle 1 at y = 0: both sides
    have 16 m: the image's choice (+y) stands. Without bounds_margin both take +y. Then vehicle 1 moves to y = 14.5
    during its hold: 1.5 m of room ahead (< 2 m) ends the hold at once and the true goal input returns."""
    lo, hi = np.array([0.0, -16.0]), np.array([60.0, 16.0])
    state, depth = _state(2), _depth(2, 30.0, 1.0)
    pos = np.array([[5.0, 12.0, 1.0], [5.0, 0.0, 1.0]])
    goal = np.array([[55.0, 12.0, 1.0], [55.0, 0.0, 1.0]])
    plain = StallEscape(EscapeConfig(window_s=0.05), 2, DT)
    fenced = StallEscape(EscapeConfig(window_s=0.05, bounds_margin=10.0), 2, DT)
    for t in range(6):
        plain.apply(state, pos, goal, depth, t, bounds=(lo, hi))
        out = fenced.apply(state, pos, goal, depth, t, bounds=(lo, hi))
    np.testing.assert_allclose(plain.direction, [[0.0, 1.0], [0.0, 1.0]], atol=1e-12)
    np.testing.assert_allclose(fenced.direction, [[0.0, -1.0], [0.0, 1.0]], atol=1e-12)
    np.testing.assert_allclose(out[:, GOAL_COLUMNS], [[0.0, -1.0], [0.0, 1.0]], atol=1e-6)
    pos[1, 1] = 14.5
    out = fenced.apply(state, pos, goal, depth, 6, bounds=(lo, hi))
    np.testing.assert_allclose(out[1, GOAL_COLUMNS], [0.7, 0.1], rtol=1e-6)  # the hold ended
    np.testing.assert_allclose(out[0, GOAL_COLUMNS], [0.0, -1.0], atol=1e-6)  # vehicle 0 still escapes
    assert fenced.until[1] == pytest.approx(0.06)
    with pytest.raises(ValueError, match="bounds_margin > 0 needs the flight volume"):
        StallEscape(EscapeConfig(bounds_margin=10.0), 1, DT).apply(_state(1), pos[:1], goal[:1], depth[:1], 0)


def _guide(grid_m=(20.0, 10.0)):
    """A camera map over a 20 x 10 m volume, empty, of 0.2 m cells (n = 1), as the map-kind escape keeps."""
    from envs.camera.config import CameraConfig

    cfg = EscapeConfig(kind="map", lookahead=3.0, map_inflate=0.4, goal_radius=1.0)
    return CameraMap(cfg, 1, CameraConfig(), np.zeros(2), np.array(grid_m))


def test_the_map_plan_goes_round_a_mapped_wall_through_its_gap():
    """Vehicle at (2, 5.1), goal at (18, 5.1). Empty map: the plan's point lies straight ahead on y = 5, 3 m or a little
    more away (15 grid steps). A mapped wall at x = 10 for y < 8 (the gap at y 8-10): the shortest way passes the
    wall's end at (10, 8), inflated by 0.4 m, so the plan's point lies up and to the right of the vehicle, and the
    straight segment to it stays clear of the wall. A goal region the map fills: NaN (fly the true goal)."""
    pos, goal = np.array([2.0, 5.1, 1.5]), np.array([18.0, 5.1, 1.5])  # on the centre line of cell row 25
    esc = _guide()
    p = esc.plan(0, pos, goal)
    assert p[1] == pytest.approx(5.1) and 3.0 <= p[0] - pos[0] <= 3.3
    esc.grid[0, 50, :40] = True  # the cell column x in [10, 10.2), y in [0, 8)
    p = esc.plan(0, pos, goal)
    assert p[0] > pos[0] + 1.0 and p[1] > pos[1] + 1.0
    angle = math.degrees(math.atan2(p[1] - pos[1], p[0] - pos[0]))
    corner = math.degrees(math.atan2(8.4 - pos[1], 9.6 - pos[0]))  # the inflated wall's end, seen from the vehicle
    assert angle >= corner - 12.0  # the segment aims at or above the wall's end (grid steps: 45 deg sectors)
    esc.grid[0, 85:95, 20:30] = True  # 2 x 2 m of mapped obstacle over the 1 m goal region
    assert np.isnan(esc.plan(0, pos, goal)).all()


def test_the_camera_map_marks_a_wall_the_image_shows_and_the_plan_goes_round_its_end():
    """One flight at (2, 5, 1.5) m, level, heading +x, its whole image at 4 m depth: a wall across the view at
    x = 2 + 0.1 (the camera's mount) + 4 = 6.1 m, cell column 30 of 0.2 m cells, as wide as the 87 deg view at
    4 m, y = 5 -+ 4 tan(43.5 deg) = 1.2 .. 8.8 m (cell rows 6 .. 43). Nothing else is marked. The goal at
    (18, 5.1): the plan's point turns off the straight line towards one of the wall's ends, and stays in front of
    it."""
    from envs.camera.config import CameraConfig

    cam = CameraConfig()
    cmap = CameraMap(
        EscapeConfig(kind="map", lookahead=3.0, goal_radius=1.0), 1, cam, np.zeros(2), np.array([20.0, 10.0])
    )
    pos = np.array([[2.0, 5.0, 1.5]])
    depth = np.full((1, 1, cam.height, cam.width), 4.0, dtype=np.float32)
    cmap.observe(np.array([0]), pos, np.eye(3)[None], depth, 0.0)
    marked = np.argwhere(cmap.grid[0])
    assert set(marked[:, 0].tolist()) == {30}
    assert marked[:, 1].min() in (5, 6) and marked[:, 1].max() in (43, 44)
    assert np.all(cmap.grid[0, 30, 7:43])
    p = cmap.plan(0, pos[0], np.array([18.0, 5.1, 1.5]))
    assert abs(p[1] - 5.0) > 1.0 and p[0] < 6.0
    with pytest.raises(ValueError, match="upper corner"):
        CameraMap(EscapeConfig(kind="map"), 1, cam, np.zeros(2), np.array([20.0, 0.0]))


def test_the_camera_map_keeps_what_the_image_showed_and_a_costly_unknown_turns_the_plan_to_seen_ways():
    """``map_unknown_cost`` > 1. The flight at (2, 5, 1.5) m, level, heading +x, its image at 4 m: the wall at x =
    6.1 m (test above). Shown: the 87 deg wedge from the camera at (2.1, 5) to the wall: (4, 5) and (6, 6.5) (21 deg
    off the axis), not (3, 8.5) (75 deg), not behind the vehicle (1, 5), not beyond the wall (8, 5). An image without
    returns shows the band free to the camera's range, 10 m along the axis: (11.5, 5) shown, (13, 5) not. The plan:
    the goal at (18, 5), a mapped wall at x = 10 for 2 < y < 8 (gaps below and above); seen space only up the
    y > 8 gap. At cost 1 the two ways are mirror images and the plan may take either; at cost 5 the unseen way costs
    four times more per metre, so the plan's point lies up towards the seen gap."""
    from envs.camera.config import CameraConfig

    cam = CameraConfig()
    cfg = EscapeConfig(kind="map", lookahead=3.0, goal_radius=1.0, map_unknown_cost=5.0)
    cmap = CameraMap(cfg, 1, cam, np.zeros(2), np.array([20.0, 10.0]))
    pos = np.array([[2.0, 5.0, 1.5]])
    cmap.observe(np.array([0]), pos, np.eye(3)[None], np.full((1, 1, cam.height, cam.width), 4.0), 0.0)

    def shown(x, y):
        return bool(cmap.seen[0, int(x / 0.2), int(y / 0.2)])

    assert shown(4.0, 5.0) and shown(6.0, 6.5)
    assert not shown(3.0, 8.5) and not shown(1.0, 5.0) and not shown(8.0, 5.0)
    cmap.seen[:] = False
    cmap.grid[:] = False
    cmap.observe(np.array([0]), pos, np.eye(3)[None], np.zeros((1, 1, cam.height, cam.width)), 0.0)
    assert not cmap.grid.any() and shown(11.5, 5.0) and not shown(13.0, 5.0)
    cmap.seen[:] = False
    cmap.grid[0, 50, 10:40] = True  # the wall x in [10, 10.2), y in [2, 8)
    cmap.seen[0, :, 40:] = True  # seen: the strip y >= 8 along the whole volume
    cmap.seen[0, :12, :] = True  # and round the vehicle
    goal = np.array([18.0, 5.0, 1.5])
    p = cmap.plan(0, pos[0], goal)
    assert p[1] > pos[0, 1] + 1.0, p
    optimistic = CameraMap(EscapeConfig(kind="map", lookahead=3.0, goal_radius=1.0), 1, cam, np.zeros(2),
                           np.array([20.0, 10.0]))  # fmt: skip
    assert optimistic.seen is None
    optimistic.grid[0, 50, 10:40] = True
    q = optimistic.plan(0, pos[0], goal)
    assert q[0] > pos[0, 0] + 2.0 and abs(q[1] - pos[0, 1]) < abs(p[1] - pos[0, 1])  # the straighter way on
    with pytest.raises(ConfigError, match="map_unknown_cost"):
        EscapeConfig(kind="map", map_unknown_cost=0.5).validate("escape.")


def test_a_circling_flight_escapes_before_the_distance_rule_and_a_weaving_one_does_not():
    """Two flights closing on their goal at 1 m/s (the distance rule never fires). Flight 0 yaws at 2 rad/s: its net
    turn reaches one full turn (2 pi rad) at t = pi s, the first step >= 314.16, 315, where its escape starts (4 s,
    to 715). Its heading history restarts then; it keeps spinning, so at the hold's end it has turned 8 rad since:
    a second escape at 715, for 6 s. Flight 1 weaves, 1.5 sin(2t) rad: at most 3 rad net in any window, never an
    escape. Without ``circle_turns`` neither escapes."""
    cfg = EscapeConfig(circle_turns=1.0, circle_window_s=6.0)
    for c, expect in ((cfg, [2, 0]), (EscapeConfig(), [0, 0])):
        esc = StallEscape(c, 2, DT)
        goal, depth = np.tile([[100.0, 0.0, 0.0]], (2, 1)), _depth(2, 5.0, 5.0)
        starts = []
        for t in range(1000):
            tt = t * DT
            state = np.concatenate([_state(1, psi=math.remainder(2.0 * tt, 2 * math.pi)),
                                    _state(1, psi=1.5 * math.sin(2.0 * tt))])  # fmt: skip
            pos = np.array([[tt, 0.0, 0.0], [tt, 0.0, 0.0]])
            before = esc.count.copy()
            esc.apply(state, pos, goal, depth, t)
            starts += [(t, i) for i in np.flatnonzero(esc.count > before)]
        assert esc.count.tolist() == expect
        if c.circle_turns > 0:
            assert starts == [(315, 0), (715, 0)]
            assert esc.circled.tolist() == [2, 0]
            assert esc.escape_steps.tolist() == [400 + 285, 0]  # the second hold runs past t = 999
        else:
            assert esc.circled.tolist() == [0, 0]


def test_the_circling_rule_turns_the_map_guide_on_and_needs_every_step():
    """Map kind: a hovering flight spinning at 2 rad/s is guided from step 315, the distance rule's 5 s not awaited."""
    from envs.camera.config import CameraConfig

    esc = StallEscape(EscapeConfig(kind="map", circle_turns=1.0), 1, DT, CameraConfig())
    pos, goal = np.array([[2.0, 5.0, 1.5]]), np.array([[18.0, 5.0, 1.5]])
    depth = np.zeros((1, 1, 60, 100), dtype=np.float32)  # no return: nothing mapped
    bounds = (np.zeros(2), np.array([20.0, 10.0]))
    for t in range(320):
        psi = math.remainder(2.0 * t * DT, 2 * math.pi)
        r = np.array([[[math.cos(psi), -math.sin(psi), 0.0], [math.sin(psi), math.cos(psi), 0.0], [0.0, 0.0, 1.0]]])
        esc.apply(_state(1, psi=psi), pos, goal, depth, t, bounds=bounds, R_wb=r)
        assert esc.guided[0] == (t >= 315), t
    assert esc.circled[0] == 1
    with pytest.raises(ValueError, match="one call per control step"):
        esc.apply(_state(1), pos, goal, depth, 400, bounds=bounds, R_wb=np.eye(3)[None])


def test_finished_flights_start_no_escape_and_bad_input_is_named():
    esc = StallEscape(EscapeConfig(window_s=0.05), 2, DT)
    state, depth = _state(2), _depth(2, 5.0, 5.0)
    pos, goal = np.zeros((2, 3)), np.tile([[10.0, 0.0, 0.0]], (2, 1))
    for t in range(10):
        esc.apply(state, pos, goal, depth, t, live=np.array([True, False]))
    assert esc.count.tolist() == [1, 0] and esc.escape_steps[1] == 0
    with pytest.raises(ConfigError, match=r"escape\.window_s"):
        StallEscape(EscapeConfig(window_s=0.0), 1, DT)
    with pytest.raises(ConfigError, match=r"escape\.hold_growth_s"):
        StallEscape(EscapeConfig(hold_growth_s=-1.0), 1, DT)
    with pytest.raises(ConfigError, match=r"escape\.bounds_margin"):
        StallEscape(EscapeConfig(bounds_margin=-1.0), 1, DT)
    with pytest.raises(ConfigError, match=r"escape\.kind"):
        StallEscape(EscapeConfig(kind="maps"), 1, DT)
    with pytest.raises(ValueError, match="needs the camera"):
        StallEscape(EscapeConfig(kind="map"), 1, DT)
    with pytest.raises(ConfigError, match=r"escape\.circle_turns"):
        StallEscape(EscapeConfig(circle_turns=-1.0), 1, DT)
    with pytest.raises(ConfigError, match=r"escape\.circle_window_s"):
        StallEscape(EscapeConfig(circle_window_s=0.0), 1, DT)
    with pytest.raises(ConfigError, match=r"escape\.min_progress"):
        StallEscape(EscapeConfig(min_progress=math.nan), 1, DT)
    bad = _state(2)
    bad[1, 0] = np.nan
    with pytest.raises(FloatingPointError, match="non-finite"):
        StallEscape(EscapeConfig(), 2, DT).apply(bad, pos, goal, depth, 0)


def test_the_handover_kind_only_marks_stalled_flights_and_leaves_the_state():
    """``kind: handover``: a hovering flight is marked at the 5 s window (step 500) and stays marked; a flight that
    closes on its goal never is; the policy's state comes back unchanged (the harness swaps the commands)."""
    esc = StallEscape(EscapeConfig(kind="handover"), 2, DT)
    goal = np.array([[30.0, 0.0, 1.0], [30.0, 0.0, 1.0]])
    state, depth = _state(2), _depth(2, 5.0, 5.0)
    for t in range(800):
        pos = np.array([[0.0, 0.0, 1.0], [0.5 * t * DT, 0.0, 1.0]])
        assert esc.apply(state, pos, goal, depth, t) is state
        assert esc.guided.tolist() == [t >= 500, False], t
    assert esc.count.tolist() == [1, 0] and esc.escape_steps.tolist() == [300, 0]


def test_escape_rows_fly_the_shipped_full_and_change_only_stalled_flights():
    """A window longer than any flight never fires: the flights are Full's, step for step. A window of 0.2 s with
    1 km of progress asked fires in every flight at 0.2 s, and the flights differ. Only a depth policy may escape.
    The flights are cut at 5 s (500 steps; the 9 m/s flights of scene 0 run to 958-1564 steps at the evaluation's
    time limit): every rule below acts in the first 0.2 s."""
    base = ["scenes.family=ablation", "scenes.indices=[0]", "speeds=[9.0]", "trials_per_scene=2", "plots=false",
            "network=fixed_order", "env_overrides=[episode.timeout_factor=0.0]"]  # fmt: skip
    cfg = E.load_eval_config(None, [*base, "configurations=[full,full_escape]", "escape.window_s=1000.0"])
    runs = {s.row_name: E.run_unit(s)["trials"] for s in E.plan_units(E.prepare(cfg))}
    plain, never = runs["full"], runs["full_escape"]
    assert [t["steps"] for t in never] == [t["steps"] for t in plain]
    assert [t["outcome"] for t in never] == [t["outcome"] for t in plain]
    assert [t["traj"] for t in never] == [t["traj"] for t in plain]
    assert all(t["escape"] == {"escapes": 0, "escape_steps": 0, "by_circling": 0} for t in never)
    cfg = E.load_eval_config(None, [*base, "configurations=[full_escape]", "escape.window_s=1000.0", "escape.kind=map"])
    (spec,) = E.plan_units(E.prepare(cfg))
    mapped = E.run_unit(spec)["trials"]  # the map is built all flight long; it steers nothing until a stall
    assert [t["traj"] for t in mapped] == [t["traj"] for t in plain]
    cfg = E.load_eval_config(None, [*base, "configurations=[full_escape]", "escape.window_s=0.2",
                                    "escape.min_progress=1000.0"])  # fmt: skip
    (spec,) = E.plan_units(E.prepare(cfg))
    fired = E.run_unit(dataclasses.replace(spec))["trials"]
    assert all(t["escape"]["escapes"] >= 1 for t in fired)
    for t, p in zip(fired, plain, strict=True):  # a point every 10 steps: the same up to 0.2 s, the first to
        assert t["traj"][:3] == p["traj"][:3] and t["traj"][3] != p["traj"][3]  # see an escaped step differs
    cfg = E.load_eval_config(None, [*base, "configurations=[full_escape]", "escape.window_s=1000.0",
                                    "escape.kind=handover"])  # fmt: skip
    (spec,) = E.plan_units(E.prepare(cfg))
    kept = E.run_unit(spec)["trials"]  # the planner maps every flight all along; it flies none until a stall
    assert [t["traj"] for t in kept] == [t["traj"] for t in plain]
    cfg = E.load_eval_config(None, [*base, "configurations=[full_escape]", "escape.window_s=0.2",
                                    "escape.min_progress=1000.0", "escape.kind=handover"])  # fmt: skip
    (spec,) = E.plan_units(E.prepare(cfg))
    handed = E.run_unit(spec)["trials"]
    for t, p in zip(handed, plain, strict=True):  # handed over at step 20 (0.2 s), flown by the planner to the end
        assert t["escape"] == {"escapes": 1, "escape_steps": t["steps"] - 20, "by_circling": 0}
        assert t["traj"][:3] == p["traj"][:3] and t["traj"][3] != p["traj"][3]
    # escape.handover_planner names the flyer: reactive_map is the default; the privileged expert (a bound) flies the
    # same handed flights otherwise from the handover on.
    by_planner = {}
    for planner in ("reactive_map", "expert"):
        cfg = E.load_eval_config(None, [*base, "configurations=[full_escape]", "escape.window_s=0.2",
                                        "escape.min_progress=1000.0", "escape.kind=handover",
                                        f"escape.handover_planner={planner}"])  # fmt: skip
        (spec,) = E.plan_units(E.prepare(cfg))
        by_planner[planner] = E.run_unit(spec)["trials"]
    assert [t["traj"] for t in by_planner["reactive_map"]] == [t["traj"] for t in handed]
    for t, p in zip(by_planner["expert"], handed, strict=True):
        assert t["escape"]["escapes"] == 1 and t["traj"][:3] == p["traj"][:3] and t["traj"][3] != p["traj"][3]
    # The shipped row `full_handover` carries the handover in its own escape_overrides (kind, circling rule), over
    # the run's sideways default: with the same window it flies the flights handed over above.
    cfg = E.load_eval_config(None, [*base, "configurations=[full_handover]", "escape.window_s=0.2",
                                    "escape.min_progress=1000.0"])  # fmt: skip
    (spec,) = E.plan_units(E.prepare(cfg))
    assert (
        cfg.escape.kind == "sideways"
        and E.row_escape_config(cfg.escape, E.resolve_rows(cfg)["full_handover"], "full_handover").kind == "handover"
    )
    row_handed = E.run_unit(spec)["trials"]
    assert [t["traj"] for t in row_handed] == [t["traj"] for t in handed]
    assert [t["escape"] for t in row_handed] == [t["escape"] for t in handed]
    with pytest.raises(E.EvalError, match="has escape: true but controller 'oracle'"):
        E.resolve_rows(E.load_eval_config(None, [*base, "configurations=[mine]", "rows.mine.controller=oracle",
                                                 "rows.mine.escape=true"]))  # fmt: skip


def test_row_escape_overrides_are_checked_by_name_before_any_flight():
    """A row's escape_overrides: an unknown key, a bad value and overrides without the escape each fail naming the
    row and key; the run's own escape section is left as it was for the other rows."""
    base = ["scenes.family=ablation", "scenes.indices=[0]", "speeds=[9.0]", "trials_per_scene=1", "plots=false"]
    cfg = E.load_eval_config(None, [*base, "configurations=[full_escape,full_handover]"])
    rows = E.resolve_rows(cfg)
    assert E.row_escape_config(cfg.escape, rows["full_escape"], "full_escape") == cfg.escape
    handover = E.row_escape_config(cfg.escape, rows["full_handover"], "full_handover")
    assert (handover.kind, handover.circle_turns, handover.circle_window_s) == ("handover", 1.5, 10.0)
    assert dataclasses.replace(handover, kind="sideways", circle_turns=0.0, circle_window_s=6.0) == cfg.escape
    with pytest.raises(E.EvalError, match=r"rows\.full_handover in the config replaces the registry's row"):
        E.resolve_rows(E.load_eval_config(None, [*base, "configurations=[full_handover]",
                                                 "rows.full_handover.escape_overrides.window_s=3.0"]))  # fmt: skip
    mine = ["configurations=[mine]", "rows.mine.policy=full", "rows.mine.shield=true"]
    for extra, match in (
        (["rows.mine.escape=true", "rows.mine.escape_overrides.window=3.0"],
         r"rows\.mine\.escape_overrides: unknown key.*window"),
        (["rows.mine.escape=true", "rows.mine.escape_overrides.kind=handoff"], r"rows\.mine\.escape_overrides\.kind"),
        (["rows.mine.escape_overrides.kind=handover"], r"'mine' has escape_overrides but no stall escape"),
    ):  # fmt: skip
        with pytest.raises(E.EvalError, match=match):
            E.resolve_rows(E.load_eval_config(None, [*base, *mine, *extra]))
