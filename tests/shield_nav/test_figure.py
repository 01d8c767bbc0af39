"""The tables figure (our rows beside the paper's) and the paper's numbers it quotes."""

from __future__ import annotations

import json
import os
import re

import numpy as np
import pytest

from shield_nav.evaluation.figure import load_rows, load_seed, main, pool_cells, row_series
from shield_nav.evaluation.metrics import wilson_interval
from shield_nav.evaluation.paper import PAPER_TABLE_I, PAPER_TABLE_II

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _cell(n: int, k: int, vel: float | None) -> dict:
    return {"n": n, "successes": k, "success_rate": k / n, "sr_lo": k / n - 0.1, "sr_hi": k / n + 0.05, "vel": vel}


def _write_run(folder, rows: dict[str, dict], done: int = 4, total: int = 4) -> str:
    os.makedirs(folder, exist_ok=True)
    summary = {
        "rows": {name: {"label": name.title()} for name in rows},
        "cells": rows,
        "units_done": done,
        "units_total": total,
    }
    with open(os.path.join(folder, "summary.json"), "w") as f:
        json.dump(summary, f)
    return str(folder)


def _paper_cells(path: str) -> dict[str, list[float | None]]:
    """The italic paper rows of docs/results.md (``| *Full, paper* | *88.75* | ...``) as numbers."""
    out = {}
    with open(path) as f:
        for line in f:
            m = re.match(r"\| \*(.+), paper\* \|(.*)\|\s*$", line)
            if m:
                cells = [c.strip().strip("*") for c in m.group(2).split("|")]
                out[m.group(1)] = [None if c == "-" else float(c) for c in cells]
    return out


def test_the_paper_numbers_agree_with_the_ones_results_md_quotes():
    # Two transcriptions of the paper's tables, made apart: the module and the italic rows of docs/results.md.
    docs = _paper_cells(os.path.join(ROOT, "docs", "results.md"))
    for row in PAPER_TABLE_I.values():
        interleaved = [x for pair in zip(row["sr"], row["vel"], strict=True) for x in pair]
        assert docs[row["label"]] == interleaved, row["label"]
    assert docs["Ours (Full)"] == list(PAPER_TABLE_II["full"]["sr"])
    assert docs["DiffPhys"] == list(PAPER_TABLE_II["diffphys"]["sr"])


def test_row_series_from_a_hand_made_run(tmp_path):
    cells = {"9": _cell(160, 52, 4.47), "3": _cell(160, 123, 2.89), "5": _cell(160, 0, None)}
    rows = load_rows([_write_run(tmp_path / "t2", {"full": cells})])
    s = row_series(rows["full"])
    np.testing.assert_array_equal(s["speed"], [3.0, 5.0, 9.0])  # sorted by speed, not by key order
    np.testing.assert_allclose(s["sr"], [76.875, 0.0, 32.5])
    np.testing.assert_allclose(s["lo"], [66.875, -10.0, 22.5])
    np.testing.assert_allclose(s["hi"], [81.875, 5.0, 37.5])
    assert s["vel"][0] == 2.89 and np.isnan(s["vel"][1]) and s["vel"][2] == 4.47
    assert rows["full"]["label"] == "Full"


def test_rows_are_merged_from_several_runs_and_can_be_picked(tmp_path):
    a = _write_run(tmp_path / "a", {"full": {"3": _cell(10, 9, 3.0)}, "student": {"3": _cell(10, 5, 3.0)}})
    b = _write_run(tmp_path / "b", {"distance": {"3": _cell(10, 4, 3.0)}})
    assert sorted(load_rows([a + ":full", b])) == ["distance", "full"]


def test_a_row_can_be_drawn_under_another_name(tmp_path):
    # A run flown under an earlier row name (full_local_map) drawn as the Full row: its cells, Full's label from
    # configs/eval/rows.yaml; an unknown target name keeps the name as its label.
    cells = {"3": _cell(160, 133, 2.84)}
    a = _write_run(tmp_path / "a", {"full_local_map": cells, "student": {"3": _cell(10, 5, 3.0)}})
    rows = load_rows([a + ":full_local_map=full,student=mine"])
    assert sorted(rows) == ["full", "mine"] and rows["full"]["cells"] == cells
    assert rows["full"]["label"] == "Full" and rows["mine"]["label"] == "mine"
    b = _write_run(tmp_path / "b", {"full": cells})
    with pytest.raises(ValueError, match="row 'full' is in both"):
        load_rows([a + ":full_local_map=full", b])
    with pytest.raises(ValueError, match="'full_local_map=' must be ROW=AS"):
        load_rows([a + ":full_local_map="])
    with pytest.raises(ValueError, match="no row 'fulll'"):
        load_rows([a + ":fulll=full"])


def test_bad_inputs_are_refused_by_name(tmp_path):
    a = _write_run(tmp_path / "a", {"full": {"3": _cell(10, 9, 3.0)}})
    b = _write_run(tmp_path / "b", {"full": {"3": _cell(10, 8, 3.0)}})
    with pytest.raises(ValueError, match="no .*nowhere.*summary.json"):
        load_rows([str(tmp_path / "nowhere")])
    with pytest.raises(ValueError, match="no row 'dijkstra'.*rows: full"):
        load_rows([a + ":dijkstra"])
    with pytest.raises(ValueError, match="row 'full' is in both"):
        load_rows([a, b])
    c = _write_run(tmp_path / "c", {"full": {"3": _cell(10, 9, 3.0)}}, done=3, total=64)
    with pytest.raises(ValueError, match="unfinished \\(3 of 64 units\\)"):
        load_rows([c])


def test_the_command_writes_a_png_and_refuses_an_unknown_paper_method(tmp_path, capsys):
    cells = {f"{v:g}": _cell(40, 30, 0.5 * v) for v in (3.0, 5.0, 7.0, 9.0)}
    a = _write_run(tmp_path / "t1", {"full": cells, "expert": cells})
    b = _write_run(tmp_path / "t2", {"full": cells})
    out = tmp_path / "fig" / "tables.png"
    assert main(["--table1", a, "--table2", b, "--out", str(out)]) == 0
    with open(out, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    assert main(["--table2", b, "--paper-methods", "diffphys,rrt", "--out", str(tmp_path / "x.png")]) == 2
    assert "unknown rrt" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_seeds_are_pooled_by_speed_and_a_seed_can_span_folders(tmp_path, capsys):
    # Seed 0 flew 3 and 5 m/s in one folder; seed 1 flew 5 m/s in one folder and 3 m/s in another.
    s0 = _write_run(tmp_path / "s0", {"dijkstra": {"3": _cell(40, 30, 2.9), "5": _cell(40, 10, 4.0)}})
    s1 = _write_run(tmp_path / "s1", {"dijkstra": {"5": _cell(40, 20, 4.6)}})
    s1_3 = _write_run(tmp_path / "s1_3", {"dijkstra": {"3": _cell(40, 0, None)}})
    seed1 = load_seed(f"{s1}+{s1_3}:dijkstra")
    assert sorted(seed1["dijkstra"]["cells"], key=float) == ["3", "5"]
    pooled = pool_cells([load_seed(s0)["dijkstra"]["cells"], seed1["dijkstra"]["cells"]])
    # 3 m/s: 30 + 0 of 80, realised speed from seed 0's successes alone; 5 m/s: 30 of 80, (10 * 4.0 + 20 * 4.6) / 30.
    assert (pooled["3"]["n"], pooled["3"]["successes"], pooled["3"]["seeds"]) == (80, 30, 2)
    assert pooled["3"]["vel"] == pytest.approx(2.9) and pooled["5"]["vel"] == pytest.approx(132.0 / 30)
    assert pooled["5"]["success_rate"] == pytest.approx(30 / 80)
    assert (pooled["5"]["sr_lo"], pooled["5"]["sr_hi"]) == pytest.approx(wilson_interval(30, 80))
    # A lone seed at a speed is pooled over that one seed.
    assert pool_cells([{"9": _cell(10, 1, 6.0)}, {}])["9"]["seeds"] == 1
    with pytest.raises(ValueError, match="row 'dijkstra' has 5 m/s in both"):
        load_seed(f"{s0}+{s1}")
    out = tmp_path / "seeds.png"
    assert main(["--seeds", "--table1", s0, f"{s1}+{s1_3}", "--out", str(out)]) == 0
    with open(out, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    other = _write_run(tmp_path / "other", {"distance": {"3": _cell(40, 30, 2.9)}})
    assert main(["--seeds", "--table1", s0, other, "--out", str(tmp_path / "x.png")]) == 2
    assert "no row is in every seed" in capsys.readouterr().err and not (tmp_path / "x.png").exists()
    with pytest.raises(SystemExit) as exc:  # not dropped in silence: the seeds figure draws no other method
        main(["--seeds", "--table1", s0, "--paper-methods", "diffphys", "--out", str(tmp_path / "x.png")])
    assert exc.value.code == 2 and "--paper-methods" in capsys.readouterr().err
