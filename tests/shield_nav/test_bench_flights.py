"""``python -m shield_nav.bench flights``: one real flight through the harness, its JSON line, the profile's shares
(each part inside the one that contains it), and bad input named before any flight."""

import json

import pytest

from shield_nav.bench.flights import main


def test_the_flights_bench_flies_times_and_splits_an_evaluation(capsys):
    res = main(["--trials", "1", "--scenes", "0", "--speed", "9", "--profile", "--json"])
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line == res
    assert res["flights"] == 1 and res["scenes"] == [0] and res["network"] == "fixed_order" and res["profiled"]
    assert res["vehicle_steps"] > 0 and res["seconds"] > 0
    assert res["vehicle_steps_per_s"] == pytest.approx(res["vehicle_steps"] / res["seconds"], rel=0.01)
    shares = res["shares"]
    assert set(shares) == {"env_step", "vehicle", "observations", "rendering", "shield", "shield_selection",
                           "shield_qp", "network"}  # fmt: skip
    assert all(0.0 < v <= 1.0 for v in shares.values())
    # parts inside parts: the vehicle and the observations are in the env step, the selection and QP in the shield
    assert shares["vehicle"] + shares["observations"] <= shares["env_step"] + 0.002
    assert shares["rendering"] <= shares["observations"] + 0.001
    assert shares["shield_selection"] + shares["shield_qp"] <= shares["shield"] + 0.002
    assert shares["env_step"] + shares["shield"] + shares["network"] <= 1.0 + 0.003


def test_the_flights_bench_names_bad_input_before_flying(capsys):
    with pytest.raises(SystemExit):
        main(["--trials", "0"])
    assert "--trials must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--configurations", "fulll", "--trials", "1"])
    assert "fulll" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--scenes", "0,x"])
    assert "--scenes" in capsys.readouterr().err
