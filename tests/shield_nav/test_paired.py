"""Paired comparison of two evaluated rows: matching by trial, the exact McNemar test by hand, refusals."""

import json
import math

import pytest

from shield_nav.tools.paired import (
    by_scene,
    compare,
    compare_pooled,
    main,
    mcnemar_exact,
    over_tops_note,
    paired_outcomes,
    replicate_test,
)


def test_mcnemar_exact_by_hand():
    assert mcnemar_exact(0, 0) == 1.0
    assert mcnemar_exact(3, 0) == pytest.approx(2 * 0.5**3)  # 0.25
    # 1 vs 5: 2 * (C(6,0) + C(6,1)) / 2^6 = 2 * 7 / 64
    assert mcnemar_exact(1, 5) == pytest.approx(14 / 64) and mcnemar_exact(5, 1) == mcnemar_exact(1, 5)
    assert mcnemar_exact(4, 4) == 1.0  # the two-sided tail is capped at 1
    # 45 vs 120 (the 3 m/s single- vs multi-hypothesis students): the sum of the lower tail
    tail = sum(math.comb(165, i) for i in range(46)) / 2.0**165
    assert mcnemar_exact(45, 120) == pytest.approx(2 * tail) and 1e-9 < mcnemar_exact(45, 120) < 1e-8
    with pytest.raises(ValueError, match=">= 0"):
        mcnemar_exact(-1, 2)


def _write(root, row, outcomes, speed=3.0, scene=0, seed_offset=0, over=None):
    units = root / "units"
    units.mkdir(parents=True, exist_ok=True)
    trials = [{"trial": j, "seed": 100 + j + seed_offset, "start": [0.0, float(j), 1.5], "goal": [60.0, 0.0, 1.5],
               "outcome": o} for j, o in enumerate(outcomes)]  # fmt: skip
    if over is not None:
        for t, f in zip(trials, over, strict=True):
            t["metrics"] = {"flew_over": float(f)}
    unit = {"row": row, "family": "ablation", "scene": scene, "speed": speed, "trials": trials}
    (units / f"{row}__ablation-{scene:02d}__v{speed:g}.json").write_text(json.dumps(unit))


def test_compare_matches_trials_across_folders_and_counts_discordant_pairs(tmp_path, capsys):
    s, c = "success", "collision"
    _write(tmp_path / "a", "old", [s, s, c, c, c, s])
    _write(tmp_path / "a", "old", [s, c], speed=5.0)
    _write(tmp_path / "b", "new", [s, c, s, s, s, s, s])  # one more trial than A: unmatched, left out
    res = compare(f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new")
    # Pairs (A, B): (s,s) (s,c) (c,s) (c,s) (c,s) (s,s): A only 1, B only 3; the 5 m/s unit has no partner.
    assert res["n"] == 6 and res["speeds"] == [3.0]
    assert res["a_success"] == pytest.approx(3 / 6) and res["b_success"] == pytest.approx(5 / 6)
    assert (res["a_only"], res["b_only"]) == (1, 3)
    assert res["p_mcnemar"] == pytest.approx(2 * (1 + 4) / 16)
    assert len(paired_outcomes(f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new", speeds=[3.0])) == 6
    main([f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new", "--json"])
    assert json.loads(capsys.readouterr().out.strip())["b_only"] == 3
    main([f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new"])
    assert "discordant: A only 1, B only 3; exact McNemar p = 0.62" in capsys.readouterr().out


def test_compare_refuses_different_trials_unknown_rows_and_bad_specs(tmp_path):
    _write(tmp_path / "a", "old", ["success"] * 3)
    _write(tmp_path / "b", "new", ["success"] * 3, seed_offset=7)  # another eval --seed
    with pytest.raises(ValueError, match="differs in 'seed'"):
        compare(f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new")
    with pytest.raises(ValueError, match="no trials of row 'nope'.*its rows: old"):
        compare(f"{tmp_path / 'a'}:nope", f"{tmp_path / 'a'}:old")
    with pytest.raises(ValueError, match="OUT_DIR:ROW"):
        compare(str(tmp_path / "a"), f"{tmp_path / 'a'}:old")
    with pytest.raises(FileNotFoundError, match="not an eval.py output"):
        compare(f"{tmp_path}:old", f"{tmp_path / 'a'}:old")
    with pytest.raises(SystemExit) as exc:
        main([f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new"])
    assert exc.value.code == 2


def test_replicates_are_reported_and_pooled(tmp_path, capsys):
    """Two replicates (e.g. training seeds) of the same comparison: each on its own, and the discordant pairs summed
    into one exact test."""
    s, c = "success", "collision"
    _write(tmp_path / "seed1", "a", [s, s, c, c, c, s])  # vs b: A only 1, B only 3 (as above)
    _write(tmp_path / "seed1", "b", [s, c, s, s, s, s])
    _write(tmp_path / "seed2", "a", [c, c, s, c])  # vs b: A only 1 (trial 2), B only 2 (trials 0, 1)
    _write(tmp_path / "seed2", "b", [s, s, c, c])
    specs = [(f"{tmp_path / d}:a", f"{tmp_path / d}:b") for d in ("seed1", "seed2")]
    res = compare_pooled(specs)
    assert [(r["a_only"], r["b_only"]) for r in res["pairs"]] == [(1, 3), (1, 2)]
    pooled = res["pooled"]
    assert (pooled["n"], pooled["replicates"], pooled["a_only"], pooled["b_only"]) == (10, 2, 2, 5)
    assert pooled["a_success"] == pytest.approx((3 + 1) / 10) and pooled["b_success"] == pytest.approx((5 + 2) / 10)
    # 2 vs 5 discordant: 2 * (C(7,0) + C(7,1) + C(7,2)) / 2^7 = 2 * 29 / 128
    assert pooled["p_mcnemar"] == pytest.approx(58 / 128)
    main([*specs[0], *specs[1]])
    out = capsys.readouterr().out
    assert "pooled over 2 replicates, 10 paired trials: A 40.0 %, B 70.0 %; discordant: A only 2, B only 5" in out
    # Replicate level: B - A = 100 (5/6 - 3/6) = 33.3 and 100 (2/4 - 1/4) = 25 points; mean 175/6, sd 25/(3 sqrt 2),
    # so t = 7 on one degree of freedom (a Cauchy variable): p = 1 - (2/pi) atan(7).
    level = pooled["replicate_level"]
    assert level["differences"] == pytest.approx([100 / 3, 25.0]) and level["mean"] == pytest.approx(175 / 6)
    assert level["p_t"] == pytest.approx(1 - 2 / math.pi * math.atan(7.0))
    assert (level["positive"], level["negative"], level["p_sign"]) == (2, 0, pytest.approx(0.5))
    assert "B - A in points): +33.3, +25.0; mean +29.2; one-sample t p = 0.09; signs 2+ / 0- p = 0.5" in out
    main([*specs[0], *specs[1], "--json"])
    assert json.loads(capsys.readouterr().out.strip())["pooled"]["b_only"] == 5
    with pytest.raises(SystemExit) as exc:
        main([*specs[0], specs[1][0]])  # an A without its B
    assert exc.value.code == 2


def test_replicate_level_test_counts_each_replicate_once(tmp_path):
    """Three replicates of 10 trials whose B - A differ by 1, 2 and 6 successes: the pooled trial-level test and the
    replicate-level t and sign tests, by hand."""
    s, c = "success", "collision"
    for name, (a_wins, b_wins) in {"r1": (5, 6), "r2": (5, 7), "r3": (2, 8)}.items():
        _write(tmp_path / name, "a", [s] * a_wins + [c] * (10 - a_wins))
        _write(tmp_path / name, "b", [s] * b_wins + [c] * (10 - b_wins))
    pooled = compare_pooled([(f"{tmp_path / r}:a", f"{tmp_path / r}:b") for r in ("r1", "r2", "r3")])["pooled"]
    assert (pooled["a_only"], pooled["b_only"]) == (0, 9) and pooled["p_mcnemar"] == pytest.approx(2 * 0.5**9)
    level = pooled["replicate_level"]
    # Differences 10, 20, 60 points: mean 30, variance (400 + 100 + 900) / 2 = 700, t^2 = 900 / (700 / 3) = 27 / 7.
    # On two degrees of freedom P(|T| > t) = 1 - t / sqrt(2 + t^2) = 1 - sqrt(27 / 41).
    assert level["differences"] == pytest.approx([10.0, 20.0, 60.0]) and level["mean"] == pytest.approx(30.0)
    assert level["p_t"] == pytest.approx(1 - math.sqrt(27 / 41))
    assert (level["positive"], level["negative"]) == (3, 0) and level["p_sign"] == pytest.approx(2 * 0.5**3)
    # So nine discordant trials all one way (p = 0.0039) are three replicates (p = 0.25 by signs, 0.19 by t).


def test_replicate_test_edge_cases_and_bad_input():
    one = replicate_test([5.0])
    assert one["p_t"] is None and (one["positive"], one["negative"], one["p_sign"]) == (1, 0, 1.0)
    assert replicate_test([0.0, 0.0])["p_t"] == 1.0 and replicate_test([0.0, 0.0])["p_sign"] == 1.0
    assert replicate_test([4.0, 4.0, 4.0])["p_t"] == 0.0  # no spread at all: the t statistic's limit
    mixed = replicate_test([3.0, -1.0, 0.0, 2.0])  # the zero is a tie: 2 positive, 1 negative
    assert (mixed["positive"], mixed["negative"], mixed["p_sign"]) == (2, 1, 1.0)
    with pytest.raises(ValueError, match="finite"):
        replicate_test([1.0, float("nan")])
    with pytest.raises(ValueError, match="not empty"):
        replicate_test([])


def test_mcnemar_exact_equals_the_hand_sum_of_binomial_terms():
    """The scipy-based test against the two-sided fair-coin tail summed by hand, over a grid of counts."""
    import math

    for a in range(0, 40, 3):
        for b in range(0, 40, 4):
            n, k = a + b, min(a, b)
            want = 1.0 if n == 0 else min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2**n)
            assert mcnemar_exact(a, b) == pytest.approx(want, rel=1e-12)


def test_below_tops_counts_a_success_over_the_obstacles_as_a_failure(tmp_path, capsys):
    s, c = "success", "collision"
    _write(tmp_path / "a", "old", [s, s, c, c, s], over=[0, 0, 0, 0, 0])
    _write(tmp_path / "b", "new", [s, s, s, s, c], over=[0, 1, 1, 0, 0])
    a, b = f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new"
    plain = compare(a, b)  # (s,s) (s,s) (c,s) (c,s) (s,c): A only 1, B only 2
    assert (plain["a_only"], plain["b_only"]) == (1, 2) and plain["b_success"] == pytest.approx(4 / 5)
    tops = compare(a, b, below_tops=True)  # B's trials 1 and 2 flew over: (s,s) (s,c) (c,c) (c,s) (s,c)
    assert (tops["a_only"], tops["b_only"]) == (2, 1) and tops["b_success"] == pytest.approx(2 / 5)
    assert tops["a_success"] == pytest.approx(3 / 5) and tops["below_tops"] and not plain["below_tops"]
    pooled = compare_pooled([(a, b), (a, b)], below_tops=True)["pooled"]
    assert (pooled["a_only"], pooled["b_only"], pooled["n"]) == (4, 2, 10)
    main([a, b, "--below-tops"])
    out = capsys.readouterr().out
    assert "below the obstacles' tops only" in out and "A only 2, B only 1" in out
    _write(tmp_path / "c", "bare", [s, s, c, c, s])  # an output without the metric
    with pytest.raises(ValueError, match="no metrics.flew_over"):
        compare(a, f"{tmp_path / 'c'}:bare", below_tops=True)


def test_report_names_the_packages_the_two_sides_were_flown_with_when_they_differ(tmp_path, capsys):
    s, c = "success", "collision"
    _write(tmp_path / "a", "full", [s, c])
    _write(tmp_path / "b", "full", [s, s])
    a, b = f"{tmp_path / 'a'}:full", f"{tmp_path / 'b'}:full"
    # Outputs written before the manifests recorded versions (or without a manifest): nothing is claimed.
    assert compare(a, b)["package_differences"] == {}
    man = {"packages": {"python": "3.11.7", "numpy": "2.4.6", "mujoco": "4.0.0", "scipy": "1.17.1"}}
    (tmp_path / "a" / "manifest.json").write_text(json.dumps(man))
    assert compare(a, b)["package_differences"] == {}  # only one side knows its versions
    man["packages"].update(numpy="2.5.2", scipy="1.18.1")
    (tmp_path / "b" / "manifest.json").write_text(json.dumps(man))
    res = compare(a, b)
    assert res["package_differences"] == {"numpy": ["2.4.6", "2.5.2"], "scipy": ["1.17.1", "1.18.1"]}
    main([a, b])
    out = capsys.readouterr().out
    assert "numpy 2.4.6 / 2.5.2, scipy 1.17.1 / 1.18.1" in out and "floating-point" in out
    # The same versions on both sides: no note.
    (tmp_path / "a" / "manifest.json").write_text(json.dumps(man))
    main([a, b])
    assert "package versions" not in capsys.readouterr().out
    # The same packages on two processors with different SIMD extensions: named; on one side only: unknown, not named.
    (tmp_path / "a" / "manifest.json").write_text(json.dumps({**man, "cpu_simd": "avx avx2 fma"}))
    assert compare(a, b)["package_differences"] == {}
    (tmp_path / "b" / "manifest.json").write_text(json.dumps({**man, "cpu_simd": "avx avx2 fma avx512f"}))
    assert compare(a, b)["package_differences"] == {"cpu_simd": ["avx avx2 fma", "avx avx2 fma avx512f"]}


def test_plain_report_counts_flights_over_the_tops_and_warns_when_they_carry_the_lead(tmp_path, capsys):
    s, c = "success", "collision"
    # A: 3 successes, none over. B: 5 successes, 3 of them over the tops: B leads by 2, with 3 extra over the tops.
    _write(tmp_path / "a", "old", [s, s, s, c, c, c], over=[0, 0, 0, 0, 0, 0])
    _write(tmp_path / "b", "new", [s, s, s, s, s, c], over=[0, 0, 1, 1, 1, 0])
    a, b = f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new"
    res = compare(a, b)
    assert (res["a_over"], res["b_over"]) == (0, 3)
    assert over_tops_note(res) == ("note: B's lead (2 successes) is within its extra flights over the obstacles' tops "
                                   "(3); compare with --below-tops before crediting it")  # fmt: skip
    main([a, b])
    out = capsys.readouterr().out
    assert "successes over the obstacles' tops: A 0, B 3" in out and "note: B's lead (2 successes)" in out
    # Below the tops the note has nothing left to say: B 2 of 6 against A's 3.
    tops = compare(a, b, below_tops=True)
    assert tops["b_success"] == pytest.approx(2 / 6) and over_tops_note(tops) is None
    # A lead larger than the extra flights over the tops is not flagged (B 5, 1 over; A 3, none).
    _write(tmp_path / "d", "new", [s, s, s, s, s, c], over=[0, 0, 0, 0, 1, 0])
    assert over_tops_note(compare(a, f"{tmp_path / 'd'}:new")) is None
    # Pooled over two replicates: the counts add up (0 + 0 against 3 + 3), and so does the lead (4 <= 6).
    pooled = compare_pooled([(a, b), (a, b)])["pooled"]
    assert (pooled["a_over"], pooled["b_over"]) == (0, 6) and "lead (4 successes)" in over_tops_note(pooled)
    # Level (3 against 3), B with 2 more over the tops.
    _write(tmp_path / "f", "new", [s, s, s, c, c, c], over=[0, 1, 1, 0, 0, 0])
    assert over_tops_note(compare(a, f"{tmp_path / 'f'}:new")) == (
        "note: level, B with 2 more flights over the obstacles' tops; compare with --below-tops before crediting it"
    )
    # A trial file without the metric: the counts are unknown and nothing is claimed.
    _write(tmp_path / "e", "bare", [s, s, s, s, s, c])
    bare = compare(a, f"{tmp_path / 'e'}:bare")
    assert bare["b_over"] is None and over_tops_note(bare) is None


def test_a_kept_outcomes_file_pairs_like_the_unit_files_it_was_written_from(tmp_path):
    """docs/data keeps a run's outcomes.csv.gz without its unit files: paired reads it to the same comparison, and
    still refuses trials whose seeds differ."""
    import gzip
    import shutil
    from pathlib import Path

    from shield_nav.evaluation.outcomes import OUTCOMES_FILE, read_outcomes, write_outcomes

    s, c, t = "success", "collision", "timeout"
    _write(tmp_path / "a", "old", [s, s, c, t, c, s], over=[0, 1, 0, 0, 0, 0])
    _write(tmp_path / "a", "old", [s, c], speed=5.0, scene=2)
    _write(tmp_path / "b", "new", [s, c, s, s, s, s])
    units = [json.loads(p.read_text()) for p in sorted((tmp_path / "a" / "units").glob("*.json"))]
    for u in units:
        for j, trial in enumerate(u["trials"]):
            trial["steps"] = 100 + j
    path = write_outcomes(str(tmp_path / "a"), units)
    with gzip.open(path, "rt") as f:
        lines = f.read().splitlines()
    # Hand-written: the header, then one line per trial in unit order (scene 0 at 3 m/s, then scene 2 at 5 m/s,
    # which records no flew_over).
    assert lines[0] == "row,family,scene,speed,trial,seed,outcome,steps,flew_over"
    assert lines[2] == "old,ablation,0,3.0,1,101,success,101,1.0"
    assert lines[7] == "old,ablation,2,5.0,0,100,success,100," and len(lines) == 1 + 8
    assert read_outcomes(path)[1]["metrics"] == {"flew_over": 1.0} and read_outcomes(path)[6]["metrics"] == {}
    before = compare(f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new")
    kept = tmp_path / "kept"
    kept.mkdir()
    shutil.copy(path, kept / OUTCOMES_FILE)
    after = compare(f"{kept}:old", f"{tmp_path / 'b'}:new")
    counts = ("n", "a_only", "b_only")
    assert [after[k] for k in counts] == [before[k] for k in counts] == [6, 1, 3]
    assert after["a_success"] == before["a_success"]
    # flew_over comes back: below the tops, the kept side's 3 m/s successes are 2 of 6, as from its unit files.
    tops = compare(f"{kept}:old", f"{tmp_path / 'a'}:old", below_tops=True, speeds=[3.0])
    assert tops["a_success"] == tops["b_success"] == pytest.approx(2 / 6) and tops["a_only"] == tops["b_only"] == 0
    # The same bytes for the same trials (zero gzip time stamp).
    again = write_outcomes(str(kept), units)
    assert (kept / OUTCOMES_FILE).read_bytes() == Path(path).read_bytes() and again.endswith(OUTCOMES_FILE)
    # Another seed is another trial: refused as from the unit files.
    _write(tmp_path / "d", "new", [s, c], seed_offset=7)
    with pytest.raises(ValueError, match="differs in 'seed'"):
        compare(f"{kept}:old", f"{tmp_path / 'd'}:new")
    with pytest.raises(ValueError, match="no row|no trials of row"):
        compare(f"{kept}:nosuchrow", f"{tmp_path / 'b'}:new")
    with pytest.raises(FileNotFoundError, match=OUTCOMES_FILE):
        compare(f"{tmp_path / 'nothing'}:old", f"{tmp_path / 'b'}:new")


def test_by_scene_lists_each_scenes_outcome_letters_and_bs_won_and_lost(tmp_path, capsys):
    s, c, t, o = "success", "collision", "timeout", "out_of_bounds"
    _write(tmp_path / "a", "old", [s, s, c, t], over=[0, 1, 0, 0])
    _write(tmp_path / "a", "old", [o, s], scene=3, speed=5.0, over=[0, 0])
    _write(tmp_path / "b", "new", [s, s, s, s], over=[1, 0, 0, 0])
    _write(tmp_path / "b", "new", [s, s], scene=3, speed=5.0, over=[0, 0])
    a, b = f"{tmp_path / 'a'}:old", f"{tmp_path / 'b'}:new"
    # Scene 0 at 3 m/s: pairs (s,S) (S,s) (c,s) (t,s): B wins 2 (trials 2, 3); scene 3 at 5 m/s: (o,s) (s,s): B wins
    # 1. Below the tops B's trial 0 and A's trial 1 are failures: B loses trial 0 and wins trial 1 too.
    assert by_scene(a, b) == [
        {"family": "ablation", "scene": 0, "speeds": {3.0: ["sSct", "Ssss"]}, "b_won": 2, "b_lost": 0},
        {"family": "ablation", "scene": 3, "speeds": {5.0: ["os", "ss"]}, "b_won": 1, "b_lost": 0},
    ]
    low = by_scene(a, b, below_tops=True)
    assert (low[0]["b_won"], low[0]["b_lost"]) == (3, 1) and low[0]["speeds"] == {3.0: ["sSct", "Ssss"]}
    main([a, b, "--by-scene"])
    out = capsys.readouterr().out
    assert "| scene | 3 m/s A / B | 5 m/s A / B | B won / lost |" in out
    assert "| ablation 0 | sSct / Ssss | - | 2 / 0 |" in out and "| ablation 3 | - | os / ss | 1 / 0 |" in out
    main([a, b, "--by-scene", "--json"])
    res = json.loads(capsys.readouterr().out.strip())
    assert res["by_scene"][1]["speeds"] == {"5": ["os", "ss"]} and res["b_only"] == 3
    main([a, b, a, b, "--by-scene", "--json"])  # replicates: each pair carries its own table
    assert [len(p["by_scene"]) for p in json.loads(capsys.readouterr().out.strip())["pairs"]] == [2, 2]
    _write(tmp_path / "c", "odd", ["crashed", s, c, t])
    with pytest.raises(ValueError, match="unknown trial outcome 'crashed'"):
        by_scene(f"{tmp_path / 'c'}:odd", b)


def test_a_single_pair_of_different_checkpoints_is_reported_as_two_policies_not_two_recipes(tmp_path, capsys):
    s, c = "success", "collision"
    _write(tmp_path / "a", "student_shield", [s, c, c])
    _write(tmp_path / "b", "student_shield", [s, s, s])
    _write(tmp_path / "b", "mine", [s, s, c])
    a, b, mine = f"{tmp_path / 'a'}:student_shield", f"{tmp_path / 'b'}:student_shield", f"{tmp_path / 'b'}:mine"
    assert compare(a, b)["different_checkpoints"] is None  # no manifests: nothing is claimed
    man = {"config": {"rows": {}}, "checkpoint_sha256": {"student": "aa" * 32}}
    (tmp_path / "a" / "manifest.json").write_text(json.dumps(man))
    (tmp_path / "b" / "manifest.json").write_text(json.dumps(man))
    assert compare(a, b)["different_checkpoints"] is False  # the same student (e.g. two shield settings)
    main([a, b])
    assert "different trained checkpoints" not in capsys.readouterr().out
    # Another training run's student on B's side; a run's own row resolves through its 'rows:' to its checkpoint key.
    rows = {"mine": {"label": "Mine", "controller": "policy", "policy": "other", "shield": True}}
    man_b = {"config": {"rows": rows}, "checkpoint_sha256": {"student": "bb" * 32, "other": "aa" * 32}}
    (tmp_path / "b" / "manifest.json").write_text(json.dumps(man_b))
    assert compare(a, b)["different_checkpoints"] is True
    assert compare(a, mine)["different_checkpoints"] is False
    main([a, b])
    assert "note: A and B fly different trained checkpoints" in capsys.readouterr().out
    # As replicates the pooled report carries the replicate-level test instead, so the pairs carry no note.
    main([a, b, a, b])
    out = capsys.readouterr().out
    assert "different trained checkpoints" not in out and "replicate level" in out
    # A baseline row flies no checkpoint: unknown, not different.
    _write(tmp_path / "b", "oracle", [s, s, s])
    assert compare(a, f"{tmp_path / 'b'}:oracle")["different_checkpoints"] is None
