"""The route-in-view diagnostic (:mod:`shield_nav.tools.route_view`): hand-computed prefixes, bearings and the CLI."""

import json

import numpy as np
import pytest

from shield_nav.tools import route_view
from shield_nav.tools.route_view import bearing_deg, seen_prefix


def _straight(n=6, ds=0.5):
    return np.stack((np.arange(n) * ds, np.zeros(n), np.zeros(n)), axis=1)[None]


def test_seen_prefix_by_hand():
    path = np.concatenate([_straight()] * 3)  # samples every 0.5 m, 2.5 m long
    seen = np.array([[1, 1, 1, 0, 1, 1],  # first unseen at sample 3: prefix to sample 2 = 1.0 m
                     [1, 1, 1, 1, 1, 1],  # seen to the end: 2.5 m
                     [1, 0, 1, 1, 1, 1]], dtype=bool)  # fmt: skip
    in_fov = np.array([[1, 1, 1, 1, 1, 1],  # sample 3 in the frustum: occluded
                       [1, 1, 1, 1, 1, 1],
                       [1, 0, 1, 1, 1, 1]], dtype=bool)  # fmt: skip
    m, occ, whole = seen_prefix(path, seen, in_fov)
    np.testing.assert_allclose(m, [1.0, 2.5, 0.0])
    assert occ.tolist() == [True, False, False]  # a whole path is not occluded; row 3 left the frustum
    assert whole.tolist() == [False, True, False]
    # Samples nearer than 0.6 m along the path count as seen: row 3's sample 1 (0.5 m) no longer ends its prefix.
    m, occ, whole = seen_prefix(path, seen, in_fov, near_m=0.6)
    np.testing.assert_allclose(m, [1.0, 2.5, 2.5])


def test_bearing_deg_by_hand():
    a = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 5.0], [0.0, 0.0, 1.0], [-2.0, 0.0, 0.0]])
    b = np.array([[0.0, 3.0, 0.0], [1.0, 0.0, -2.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    # 90 deg; 45 deg (heights ignored); a vertical vector has no bearing (0); opposite: 180 deg.
    np.testing.assert_allclose(bearing_deg(a, b), [90.0, 45.0, 0.0, 180.0], atol=1e-9)


def test_cli_rejects_bad_scenes_and_speeds(capsys):
    with pytest.raises(SystemExit):
        route_view.main(["--scenes", "nosuch:0"])
    assert "unknown scene family 'nosuch'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        route_view.main(["--scenes", "benchmark:a-3"])
    assert "'a-3'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        route_view.main(["--speed", "nan"])
    assert "--speed" in capsys.readouterr().err


def test_measure_on_an_ablation_scene(capsys):
    """A short real flight: the seen prefix is never longer than the path, shares are shares, one row per scene."""
    route_view.main(
        ["--scenes", "train_shapes:0", "--scene-seed", "default", "--steps", "30", "--num-envs", "2", "--json"]
    )
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    row = res["scenes"]["0"]
    assert row["samples"] == 60
    assert 0.0 <= row["seen_m_p10"] <= row["seen_m_median"] <= 14.0 + 0.35
    assert all(0.0 <= row[k] <= 1.0 for k in ("short", "occluded_share", "away"))


def test_cli_names_a_seed_outside_the_family_split(capsys):
    with pytest.raises(SystemExit):
        route_view.main(["--scenes", "ablation:0", "--scene-seed", "0", "--steps", "1"])
    assert "seed 0 is not in the eval seed range" in capsys.readouterr().err


def test_route_away_by_hand():
    from shield_nav.tools.route_view import route_away

    ds = 0.5
    straight = _straight(n=9, ds=ds)[0]  # along +x, 4 m
    bent = straight.copy()
    bent[4:, 1] = (np.arange(5) + 1) * ds  # from sample 4 (2 m) on, steps of 0.5 m along +y: turns left 90 deg
    bent[4:, 0] = 1.5
    paths = np.stack((straight, bent, bent))
    # Goal bearings: +x for the first two; for the third, 60 deg left of +x.
    to_goal = np.array([[10.0, 0.0, 0.0], [10.0, 0.0, 0.0], [5.0, 5.0 * np.sqrt(3.0), 0.0]])
    # 2.5 m along the bent path is sample 5 at (1.5, 1.0): 33.7 deg off +x, 26.3 deg off the third's 60 deg.
    assert route_away(paths, to_goal, at_m=2.5).tolist() == [False, False, False]
    # 3.5 m along: sample 7 at (1.5, 2.0): 53.1 deg off +x -> away; 6.9 deg off 60 deg -> not.
    assert route_away(paths, to_goal, at_m=3.5).tolist() == [False, True, False]
