"""The realised-speed ceiling: minimum-time profiles against closed forms, and the CLI over an eval folder."""

import json
import math

import numpy as np
import pytest
from scipy.integrate import quad

from shield_nav.algorithms.expert_paths import windowed_curvature
from shield_nav.tools.speed_bound import (
    DEFAULT_ACCEL,
    flight_ceiling,
    main,
    profile_time,
    resample,
    time_optimal_profile,
)


def straight_time(length: float, v: float, a: float, lag: float) -> float:
    """Hover start, full acceleration to v, then cruise: lag + v / a + (L - v^2 / 2a) / v."""
    return lag + v / a + (length - v * v / (2 * a)) / v


def test_straight_route_ceiling_is_the_start_alone():
    pts = np.stack([np.linspace(0.0, 60.0, 601), np.zeros(601), np.full(601, 2.0)], axis=1)
    c = flight_ceiling(pts, v_max=7.0, accel=11.7, lag=0.154)
    expected = 60.0 / straight_time(60.0, 7.0, 11.7, 0.154)  # 6.52 m/s
    assert c["length"] == pytest.approx(60.0, rel=1e-9)
    assert c["bound"] == pytest.approx(expected, rel=1e-3)
    assert c["straight"] == pytest.approx(expected, rel=1e-3)


def test_circle_ceiling_matches_the_friction_circle_closed_form():
    # On a circle of radius R, v^2 = w(s) with dw/ds = 2 sqrt(a^2 - w^2 / R^2) from w(0) = 0: w = a R sin(2 s / R),
    # which reaches the bend's cap a R at s = pi R / 4; then it cruises at sqrt(a R) (below v_max).
    r, a, v_max, lag = 10.0, 11.7, 20.0, 0.1
    length = 55.0
    theta = np.linspace(0.0, length / r, 2201)
    pts = np.stack([r * np.cos(theta), r * np.sin(theta), np.full_like(theta, 2.0)], axis=1)
    s_acc = math.pi * r / 4
    t_acc, _ = quad(lambda s: 1.0 / math.sqrt(a * r * math.sin(2 * s / r)), 0.0, s_acc)
    t = lag + t_acc + (length - s_acc) / math.sqrt(a * r)
    c = flight_ceiling(pts, v_max=v_max, accel=a, lag=lag)
    assert c["length"] == pytest.approx(length, rel=1e-3)  # the chords of 2,200 pieces
    assert c["bound"] == pytest.approx(c["length"] / t, rel=0.01)
    assert c["straight"] == pytest.approx(c["length"] / straight_time(c["length"], v_max, a, lag), rel=1e-3)
    assert c["bound"] < c["straight"]


def test_profile_brakes_into_a_tight_sample_at_full_deceleration():
    ds, a = 0.1, 10.0
    kappa = np.zeros(101)
    kappa[60] = 2.5  # cap sqrt(a / kappa) = 2 m/s there
    v = time_optimal_profile(kappa, ds, v_max=50.0, accel=a)
    assert v[0] == 0.0
    assert v[60] == pytest.approx(2.0)
    # The segment into the tight sample is flown at its cap (the bend uses all of a sideways, none is left to
    # brake); before it the path is straight, so braking takes the full a: v^2 = 4 + 2 a (distance to sample 59).
    assert v[59] == pytest.approx(2.0)
    for k in (50, 55, 58):
        assert v[k] ** 2 == pytest.approx(4.0 + 2 * a * ds * (59 - k))
    # and accelerating from rest at the full a: v^2 = 2 a s
    assert v[10] ** 2 == pytest.approx(2 * a * ds * 10)


def test_profile_time_is_exact_for_constant_acceleration_and_refuses_standing_still():
    ds, a = 0.5, 4.0
    v = np.sqrt(2 * a * ds * np.arange(11))  # from rest at a over 5 m: t = sqrt(2 x 5 / a)
    assert profile_time(v, ds) == pytest.approx(math.sqrt(2 * 5.0 / a))
    with pytest.raises(ValueError, match="stands still"):
        profile_time(np.zeros(3), ds)


def test_resample_and_the_curvature_it_feeds_by_hand():
    pts = resample(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]]), 0.25)
    assert len(pts) == 9 and np.allclose(pts[4], [1.0, 0.0, 0.0]) and np.allclose(pts[-1], [1.0, 1.0, 0.0])
    k = windowed_curvature(pts[None], 1)[0]
    # The corner: 90 deg between the segments either side, whose midpoints lie 0.25 m of arc apart.
    assert k[4] == pytest.approx((math.pi / 2) / 0.25)
    assert k[1] == pytest.approx(0.0) and k[7] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="no length"):
        resample(np.zeros((3, 3)), 0.25)


def write_unit(folder, speed, trials):
    (folder / "units").mkdir(parents=True, exist_ok=True)
    unit = {"format": "1", "key": f"expert__x__v{speed:g}", "row": "expert", "family": "train_shapes", "scene": "8",
            "speed": str(float(speed)), "trials": trials}  # fmt: skip
    (folder / "units" / f"expert__x__v{speed:g}.json").write_text(json.dumps(unit))


def test_cli_reads_successes_of_an_eval_folder(tmp_path, capsys):
    line = [[float(x), 0.0, 2.0, 7.0, 0.0] for x in np.linspace(0.0, 60.0, 121)]
    trials = [
        {"trial": 0, "outcome": "success", "metrics": {"mean_speed": 5.6}, "traj": line},
        {"trial": 1, "outcome": "collision", "metrics": {"mean_speed": 6.9}, "traj": line[:20]},
    ]
    write_unit(tmp_path, 7.0, trials)
    assert main([str(tmp_path), "--json", "--lag", "0.154"]) == 0
    out = json.loads(capsys.readouterr().out)
    expected = 60.0 / straight_time(60.0, 7.0, DEFAULT_ACCEL, 0.154) / 7.0
    assert out["successes"] == 1
    assert out["realised"] == pytest.approx(0.8)
    assert out["bound"] == pytest.approx(expected, rel=1e-3)
    assert out["straight"] == pytest.approx(expected, rel=1e-3)
    assert out["below_bar"] == 0.0
    assert main([str(tmp_path), "--bar", "0.95", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["below_bar"] == 1.0


def test_cli_merges_folders_refuses_a_row_twice_and_draws(tmp_path, capsys):
    line = [[float(x), 0.0, 2.0, 7.0, 0.0] for x in np.linspace(0.0, 60.0, 121)]
    a, b = tmp_path / "a", tmp_path / "b"
    write_unit(a, 7.0, [{"trial": 0, "outcome": "success", "metrics": {"mean_speed": 5.6}, "traj": line}])
    write_unit(b, 5.0, [{"trial": 0, "outcome": "success", "metrics": {"mean_speed": 4.5}, "traj": line}])
    png = tmp_path / "ceiling.png"
    assert main([str(a), str(b), "--json", "--plot", str(png)]) == 0
    out = [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]
    assert [(r["speed"], r["realised"]) for r in out] == [(7.0, pytest.approx(0.8)), (5.0, pytest.approx(0.9))]
    from matplotlib.image import imread

    assert imread(str(png)).shape[:2] == (408, 504)  # one row's panel at 120 dpi
    assert main([str(a), str(a)]) == 2
    assert "in more than one folder" in capsys.readouterr().err


def test_cli_names_bad_input(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "no unit files" in capsys.readouterr().err
    write_unit(tmp_path, 7.0, [{"trial": 0, "outcome": "success", "metrics": {"mean_speed": 5.0}, "traj": []}])
    assert main([str(tmp_path)]) == 2
    assert "has no trajectory" in capsys.readouterr().err
    assert main([str(tmp_path), "--speeds", "5"]) == 2
    assert "matches rows" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--accel", "nan"])
    assert "--accel" in capsys.readouterr().err
