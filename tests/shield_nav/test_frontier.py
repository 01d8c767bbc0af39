"""Rows on the speed-safety plane: success with its interval and realised speed by hand, the plot, refusals."""

import json

import pytest

from shield_nav.evaluation import wilson_interval
from shield_nav.tools.frontier import frontier_point, main


def _write(root, row, trials, speed=7.0, scene=0):
    units = root / "units"
    units.mkdir(parents=True, exist_ok=True)
    recs = [{"trial": j, "seed": 100 + j, "outcome": o, "metrics": {} if v is None else {"mean_speed": v}}
            for j, (o, v) in enumerate(trials)]  # fmt: skip
    unit = {"row": row, "family": "ablation", "scene": scene, "speed": speed, "trials": recs}
    (units / f"{row}__ablation-{scene:02d}__v{speed:g}.json").write_text(json.dumps(unit))


def test_frontier_point_by_hand(tmp_path):
    s, c = "success", "collision"
    _write(tmp_path, "expert", [(s, 6.3), (s, 5.6), (c, 4.0), (s, 5.95)])
    _write(tmp_path, "expert", [(s, 7.0), (s, 7.0)], scene=1)
    _write(tmp_path, "expert", [(c, 1.0)], speed=3.0)  # another speed: not counted at 7 m/s
    p = frontier_point(f"{tmp_path}:expert", 7.0)
    # 5 of 6 at 7 m/s; successes' mean speed (6.3 + 5.6 + 5.95 + 7 + 7) / 5 = 6.37 -> 0.91 of 7.
    assert (p["n"], p["successes"]) == (6, 5)
    assert p["success"] == pytest.approx(5 / 6) and p["interval"] == pytest.approx(list(wilson_interval(5, 6)))
    assert p["realised"] == pytest.approx(0.91)
    none = frontier_point(f"{tmp_path}:expert", 3.0)
    assert none["successes"] == 0 and none["realised"] is None


def test_frontier_cli_prints_plots_and_names_bad_input(tmp_path, capsys):
    s = "success"
    _write(tmp_path / "a", "expert", [(s, 5.6), ("timeout", None)])
    png = tmp_path / "f.png"
    assert main([f"fast={tmp_path / 'a'}:expert", "--plot", str(png), "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["points"][0]["label"] == "fast" and out["points"][0]["realised"] == pytest.approx(0.8)
    assert png.stat().st_size > 1000 and png.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(SystemExit):
        main([f"{tmp_path / 'a'}:expert"])  # no label
    assert "expected LABEL=OUT_DIR:ROW" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([f"x={tmp_path / 'a'}:student"])
    assert "x: no trials of row 'student'" in capsys.readouterr().err
    _write(tmp_path / "b", "expert", [(s, None)])
    with pytest.raises(SystemExit):
        main([f"y={tmp_path / 'b'}:expert"])
    assert "has no metrics.mean_speed" in capsys.readouterr().err
