"""Is row B better than row A? A paired comparison of two evaluated rows over the same seeded trials.

``python -m shield_nav.tools.paired OUT_A:ROW_A OUT_B:ROW_B [OUT_A2:ROW_A2 OUT_B2:ROW_B2 ...] [--speeds 3]
[--below-tops] [--json]``, e.g.
``python -m shield_nav.tools.paired eval_out/ablation:oracle_distilled eval_out/ablation:oracle_distilled_shield``

Every ``eval.py`` row flies the same pinned trials (trial ``j`` of scene ``k`` at speed ``v`` has one seed, start and
goal, whatever the row, the worker count or the output folder). Two rows can therefore be compared trial by trial,
which is far more sensitive than comparing two success rates with their separate intervals. The tool matches the
trials of two rows (in one output folder or in two) by family, scene, speed and trial index, refuses pairs whose
seeds, starts or goals differ (different ``--seed`` or scenes), and reports:

* the paired success rates and their 95 % Wilson intervals;
* the discordant pairs: ``a_only`` (A succeeded, B did not) and ``b_only``;
* the exact two-sided McNemar test: under "A and B are equally good" each discordant pair is a fair coin, so
  ``p = min(1, 2 P(X <= min(a_only, b_only)))`` with ``X ~ Binomial(a_only + b_only, 1/2)``.

An ``OUT_DIR`` is an ``eval.py`` output with its ``units/``, or a kept run (``docs/data/``) with its
``outcomes.csv.gz`` (:mod:`shield_nav.evaluation.outcomes`).

Trials repeat bit for bit only with the same package versions (``shield_nav.provenance``): when the two sides' manifests
record different ones, the report names them, since some discordant pairs are then floating-point divergence rather
than a difference between the rows (docs/evaluation.md, "Reproducing a table").

When the two rows fly different trained checkpoints (their manifests' ``checkpoint_sha256``), a single pair's
report adds a note: its p-value is about those two policies over these trials, not about the recipes or the code
that trained them, since two training seeds of one recipe often disagree on as many trials; such a claim needs
training seeds as replicates (below).

``--below-tops`` counts a success only where the flight stayed below the obstacles' tops (the trial's
``metrics.flew_over`` is 0): a shield or policy that lets the vehicle climb over the clutter can gain successes that
way, which the plain comparison would credit (docs/evaluation.md). A trial recorded without the metric is refused.
Without the flag the report still counts each side's successes over the tops (``a_over``, ``b_over``) and warns when
the flights over the tops could account for B's lead (or A's), so such a gain is not credited unnoticed.

``--by-scene`` adds where the two rows differ: one line per scene with each speed's trials as letters in trial order,
A's then B's (``s`` success, ``S`` success over the obstacles' tops, ``c`` collision, ``t`` time-out, ``o`` out of
bounds), and B's discordant pairs won / lost in that scene (counted as ``--below-tops`` says); ``--json`` then holds
the same under ``by_scene``.

Several pairs (``A1 B1 A2 B2 ...``) are replicates of one comparison, e.g. the same two training recipes run with
two training seeds: each pair is reported on its own, then **pooled**, the discordant pairs of all replicates summed
into one exact McNemar test. Under "A and B are equally good" every discordant pair is still a fair coin whichever
replicate it comes from, so the pooled test is exact, and it folds the replicates' training noise into the
comparison instead of resting on one training run. But it counts trials, not replicates: when replicates differ
from each other more than the trials of one replicate do (two training seeds of one recipe often disagree on as
many trials as two recipes), a pooled p-value can be small where a claim about the *recipes* is not supported. So
the pooled report adds a **replicate-level** test, each replicate one observation: B's success rate minus A's, in
points, per replicate; the two-sided one-sample t-test of their mean against 0 (``p_t``, at least two replicates)
and the exact sign test of how many are positive against negative (``p_sign``, ties left out). A claim that one
recipe is better than another should hold at this level.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
from typing import Any

from shield_nav.evaluation import BUILTIN_ROWS, wilson_interval
from shield_nav.evaluation.outcomes import OUTCOMES_FILE, read_outcomes
from shield_nav.provenance import format_differences, manifest_record, version_differences

__all__ = [
    "by_scene",
    "compare",
    "compare_pooled",
    "mcnemar_exact",
    "over_tops_note",
    "paired_outcomes",
    "paired_trials",
    "replicate_test",
    "row_trials",
]


def mcnemar_exact(a_only: int, b_only: int) -> float:
    """Exact two-sided McNemar p-value of ``a_only`` vs ``b_only`` discordant pairs (1.0 when there are none)."""
    if a_only < 0 or b_only < 0:
        raise ValueError(f"discordant counts must be >= 0, got {a_only}, {b_only}")
    n, k = a_only + b_only, min(a_only, b_only)
    if n == 0:
        return 1.0
    from scipy.stats import binomtest

    # Under "equally good" each discordant pair is a fair coin: the exact two-sided binomial test of k of n.
    return min(1.0, float(binomtest(k, n, 0.5).pvalue))


def row_trials(spec: str, speeds: list[float] | None = None) -> dict[tuple, dict]:
    """``OUT_DIR:ROW`` -> {(family, scene, speed, trial): trial record}."""
    out_dir, sep, row = spec.rpartition(":")
    if not sep or not out_dir or not row:
        raise ValueError(f"expected OUT_DIR:ROW, got {spec!r}")
    files = sorted(glob.glob(os.path.join(out_dir, "units", "*.json")))
    kept = os.path.join(out_dir, OUTCOMES_FILE)
    found: dict[tuple, dict] = {}
    if files:
        for path in files:
            with open(path) as fh:
                unit = json.load(fh)
            if unit["row"] != row or (speeds and float(unit["speed"]) not in speeds):
                continue
            for t in unit["trials"]:
                found[(unit["family"], int(unit["scene"]), float(unit["speed"]), int(t["trial"]))] = t
        rows = sorted({os.path.basename(f).split("__")[0] for f in files})
    elif os.path.isfile(kept):  # a kept run (docs/data/): its trials' outcomes without the unit files
        records = read_outcomes(kept)
        for t in records:
            if t["row"] == row and not (speeds and t["speed"] not in speeds):
                found[(t["family"], t["scene"], t["speed"], t["trial"])] = t
        rows = sorted({t["row"] for t in records})
    else:
        raise FileNotFoundError(f"no unit files under {os.path.join(out_dir, 'units')!r} and no {OUTCOMES_FILE} in "
                                f"{out_dir!r}: not an eval.py output")  # fmt: skip
    if not found:
        raise ValueError(f"no trials of row {row!r} in {out_dir!r}" + (f" at speeds {speeds}" if speeds else "")
                         + f"; its rows: {', '.join(rows)}")  # fmt: skip
    return found


def _manifest(spec: str) -> dict | None:
    """``OUT_DIR``'s ``manifest.json`` (None where there is none)."""
    path = os.path.join(spec.rpartition(":")[0], "manifest.json")
    if not os.path.exists(path):
        return None
    with open(path) as fh:
        return json.load(fh)


def _packages(manifest: dict | None) -> dict | None:
    """The package versions (and SIMD extensions) a manifest records (None before they were recorded)."""
    return None if manifest is None else manifest_record(manifest)


def _checkpoint_sha(manifest: dict | None, row: str) -> str | None:
    """The sha256 of the checkpoint that ``row`` flies, from its output's manifest.

    None without a manifest, for a row that flies no checkpoint (a baseline or the expert), or where the manifest
    does not record it. The row's checkpoint key is its definition's ``policy``: the run's own ``rows:`` first, then
    the registry (configs/eval/rows.yaml).
    """
    if manifest is None:
        return None
    custom = (manifest.get("config") or {}).get("rows") or {}
    if row in custom:
        policy = (custom[row] or {}).get("policy", "")
    elif row in BUILTIN_ROWS:
        policy = BUILTIN_ROWS[row].policy
    else:
        return None
    return (manifest.get("checkpoint_sha256") or {}).get(policy) if policy else None


def _over_tops(pairs_trials: list[tuple[tuple, dict, dict]], side: int) -> int | None:
    """How many of one side's successes passed over the obstacles' tops (None if a success lacks the metric)."""
    n = 0
    for _key, *trials in pairs_trials:
        t = trials[side]
        if t["outcome"] != "success":
            continue
        over = t.get("metrics", {}).get("flew_over")
        if over is None:
            return None
        n += bool(over)
    return n


def _succeeded(trial: dict, below_tops: bool, key: tuple) -> bool:
    """Whether ``trial`` reached the goal (and, with ``below_tops``, did so without passing over the obstacles)."""
    if trial["outcome"] != "success":
        return False
    if not below_tops:
        return True
    over = trial.get("metrics", {}).get("flew_over")
    if over is None:
        raise ValueError(f"trial {key} has no metrics.flew_over: --below-tops needs an eval.py output that records it")
    return not over


def paired_trials(a: str, b: str, speeds: list[float] | None = None) -> list[tuple[tuple, dict, dict]]:
    """The trials both rows flew: ``(key, trial_a, trial_b)``, sorted by key.

    Raises:
        ValueError: No common trial, or a common trial whose seed, start or goal differ between the two.
    """
    ta, tb = row_trials(a, speeds), row_trials(b, speeds)
    common = sorted(set(ta) & set(tb))
    if not common:
        raise ValueError(f"{a} and {b} have no trial in common (different scenes or speeds?)")
    pairs = []
    for key in common:
        x, y = ta[key], tb[key]
        for field in ("seed", "start", "goal"):
            if field in x and field in y and x[field] != y[field]:
                raise ValueError(f"trial {key} differs in {field!r} between {a} and {b}: not the same trials "
                                 "(different eval --seed?)")  # fmt: skip
        pairs.append((key, x, y))
    return pairs


def paired_outcomes(
    a: str, b: str, speeds: list[float] | None = None, below_tops: bool = False
) -> list[tuple[tuple, bool, bool]]:
    """The trials both rows flew: ``(key, a_succeeded, b_succeeded)``, sorted by key.

    With ``below_tops`` a success over the obstacles' tops counts as a failure.

    Raises:
        ValueError: No common trial, or a common trial whose seed, start or goal differ between the two.
    """
    return [(key, _succeeded(x, below_tops, key), _succeeded(y, below_tops, key))
            for key, x, y in paired_trials(a, b, speeds)]  # fmt: skip


def compare(a: str, b: str, speeds: list[float] | None = None, below_tops: bool = False) -> dict:
    """Paired success rates, discordant counts and the exact McNemar p-value of rows ``a`` and ``b``.

    ``a_over`` and ``b_over`` count each side's successes that passed over the obstacles' tops (before
    ``below_tops`` discounts them; None where a success does not record ``metrics.flew_over``).
    ``different_checkpoints``: whether the two rows fly different trained checkpoints (None where a side's manifest
    does not say).
    """
    man_a, man_b = _manifest(a), _manifest(b)
    sha_a, sha_b = _checkpoint_sha(man_a, a.rpartition(":")[2]), _checkpoint_sha(man_b, b.rpartition(":")[2])
    trials = paired_trials(a, b, speeds)
    pairs = [(key, _succeeded(x, below_tops, key), _succeeded(y, below_tops, key)) for key, x, y in trials]
    n = len(pairs)
    sa, sb = sum(p[1] for p in pairs), sum(p[2] for p in pairs)
    a_only = sum(p[1] and not p[2] for p in pairs)
    b_only = sum(p[2] and not p[1] for p in pairs)
    return {
        "a": a, "b": b, "n": n,
        "a_success": sa / n, "a_interval": list(wilson_interval(sa, n)),
        "b_success": sb / n, "b_interval": list(wilson_interval(sb, n)),
        "a_only": a_only, "b_only": b_only, "p_mcnemar": mcnemar_exact(a_only, b_only),
        "speeds": sorted({p[0][2] for p in pairs}), "below_tops": below_tops,
        "a_over": _over_tops(trials, 0), "b_over": _over_tops(trials, 1),
        "package_differences": version_differences(_packages(man_a), _packages(man_b)),
        "different_checkpoints": None if sha_a is None or sha_b is None else sha_a != sha_b,
    }  # fmt: skip


OUTCOME_LETTERS = {"success": "s", "collision": "c", "timeout": "t", "out_of_bounds": "o"}
"""One letter per trial outcome in :func:`by_scene` (a success over the obstacles' tops is ``S``)."""


def _letter(trial: dict) -> str:
    """``trial``'s outcome as one letter (:data:`OUTCOME_LETTERS`; ``S`` for a success over the tops)."""
    out = trial["outcome"]
    if out not in OUTCOME_LETTERS:
        raise ValueError(f"unknown trial outcome {out!r}; expected one of {sorted(OUTCOME_LETTERS)}")
    if out == "success" and trial.get("metrics", {}).get("flew_over"):
        return "S"
    return OUTCOME_LETTERS[out]


def by_scene(a: str, b: str, speeds: list[float] | None = None, below_tops: bool = False) -> list[dict]:
    """Per scene of the trials both rows flew: each speed's outcome letters (A's, B's) and B's won / lost pairs.

    Returns ``[{"family", "scene", "speeds": {speed: [a_letters, b_letters]}, "b_won", "b_lost"}, ...]`` sorted by
    family and scene; letters in trial order (:data:`OUTCOME_LETTERS`), won / lost as :func:`compare` counts them.
    """
    rows: dict[tuple, dict] = {}
    for key, x, y in paired_trials(a, b, speeds):
        fam, scene, speed, _trial = key
        r = rows.setdefault((fam, scene), {"family": fam, "scene": scene, "speeds": {}, "b_won": 0, "b_lost": 0})
        cell = r["speeds"].setdefault(speed, ["", ""])
        cell[0] += _letter(x)
        cell[1] += _letter(y)
        sa, sb = _succeeded(x, below_tops, key), _succeeded(y, below_tops, key)
        r["b_won"] += sb and not sa
        r["b_lost"] += sa and not sb
    return [rows[k] for k in sorted(rows)]


def format_by_scene(table: list[dict]) -> str:
    """Markdown table of :func:`by_scene`: one line per scene, ``A / B`` letters per speed, B's won / lost."""
    speeds = sorted({v for r in table for v in r["speeds"]})
    lines = ["| scene | " + " | ".join(f"{v:g} m/s A / B" for v in speeds) + " | B won / lost |",
             "|---|" + "---|" * len(speeds) + "---:|"]  # fmt: skip
    for r in table:
        cells = [" / ".join(r["speeds"][v]) if v in r["speeds"] else "-" for v in speeds]
        lines.append(f"| {r['family']} {r['scene']} | " + " | ".join(cells) + f" | {r['b_won']} / {r['b_lost']} |")
    return "\n".join(lines)


def compare_pooled(specs: list[tuple[str, str]], speeds: list[float] | None = None, below_tops: bool = False) -> dict:
    """:func:`compare` of every ``(a, b)`` pair, and the pooled counts and exact McNemar test over all of them."""
    if not specs:
        raise ValueError("no (A, B) pair to compare")
    pairs = [compare(a, b, speeds, below_tops) for a, b in specs]
    n = sum(r["n"] for r in pairs)
    sa = round(sum(r["a_success"] * r["n"] for r in pairs))
    sb = round(sum(r["b_success"] * r["n"] for r in pairs))
    a_only, b_only = sum(r["a_only"] for r in pairs), sum(r["b_only"] for r in pairs)
    pooled = {
        "n": n, "replicates": len(pairs),
        "a_success": sa / n, "a_interval": list(wilson_interval(sa, n)),
        "b_success": sb / n, "b_interval": list(wilson_interval(sb, n)),
        "a_only": a_only, "b_only": b_only, "p_mcnemar": mcnemar_exact(a_only, b_only),
        "a_over": _sum_or_none(r["a_over"] for r in pairs), "b_over": _sum_or_none(r["b_over"] for r in pairs),
        "below_tops": below_tops,
    }  # fmt: skip
    pooled["replicate_level"] = replicate_test([100.0 * (r["b_success"] - r["a_success"]) for r in pairs])
    return {"pairs": pairs, "pooled": pooled}


def replicate_test(differences: list[float]) -> dict:
    """Each replicate one observation: tests of ``differences`` (B's success rate minus A's, points) against 0.

    ``p_t`` is the two-sided one-sample t-test of their mean (None with fewer than two replicates; with all
    differences equal it is 1 when they are 0 and 0 otherwise, the limit of the t statistic); ``p_sign`` the exact
    two-sided sign test of the positive against the negative differences (zeros left out).
    """
    d = [float(x) for x in differences]
    if not d or not all(math.isfinite(x) for x in d):
        raise ValueError(f"replicate differences must be finite and not empty, got {d}")
    k = len(d)
    mean = sum(d) / k
    p_t: float | None = None
    if k >= 2:
        sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (k - 1))
        if sd == 0.0:
            p_t = 1.0 if mean == 0.0 else 0.0
        else:
            from scipy.stats import t as student_t

            p_t = float(2.0 * student_t.sf(abs(mean) / (sd / math.sqrt(k)), k - 1))
    positive, negative = sum(x > 0 for x in d), sum(x < 0 for x in d)
    return {
        "differences": d, "mean": mean, "p_t": p_t,
        "positive": positive, "negative": negative, "p_sign": mcnemar_exact(positive, negative),
    }  # fmt: skip


def _sum_or_none(values: Any) -> int | None:
    """The sum of ``values``, or None if any is None."""
    values = list(values)
    return None if any(v is None for v in values) else sum(values)


def over_tops_note(res: dict) -> str | None:
    """A warning when the flights over the obstacles' tops could account for one side's lead, else None.

    The lead is the difference of the two success counts; the note is written when the leading side has at least
    that many more successes over the tops than the other (without them the comparison may then be level or
    reverse); when the two are level, the side with more of them is named. Not for
    a ``below_tops`` comparison, which has already discounted them, nor where the metric is missing.
    """
    a_over, b_over = res.get("a_over"), res.get("b_over")
    if res.get("below_tops") or a_over is None or b_over is None:
        return None
    sa, sb = round(res["a_success"] * res["n"]), round(res["b_success"] * res["n"])
    if sb == sa:  # level: warn if one side is level only by its flights over the tops
        side, extra = ("B", b_over - a_over) if b_over >= a_over else ("A", a_over - b_over)
        if extra == 0:
            return None
        return (f"note: level, {side} with {extra} more flights over the obstacles' tops; compare with --below-tops "
                "before crediting it")  # fmt: skip
    lead, extra = abs(sb - sa), (b_over - a_over) if sb > sa else (a_over - b_over)
    if extra <= 0 or extra < lead:
        return None
    side = "B" if sb > sa else "A"
    return (
        f"note: {side}'s lead ({lead} successes) is within its extra flights over the obstacles' tops ({extra}); "
        "compare with --below-tops before crediting it"
    )


def format_report(res: dict, single: bool = True) -> str:
    """Human-readable lines of :func:`compare`'s result (``single``: the only pair, with no replicate-level test)."""

    def pct(x: float) -> str:
        return f"{100 * x:.1f}"

    lo_a, hi_a = res["a_interval"]
    lo_b, hi_b = res["b_interval"]
    lines = [
        f"{res['n']} paired trials at {', '.join(f'{s:g}' for s in res['speeds'])} m/s"
        + (" (successes below the obstacles' tops only)" if res.get("below_tops") else ""),
        f"A {res['a']}: {pct(res['a_success'])} % [{pct(lo_a)}, {pct(hi_a)}]",
        f"B {res['b']}: {pct(res['b_success'])} % [{pct(lo_b)}, {pct(hi_b)}]",
        f"discordant: A only {res['a_only']}, B only {res['b_only']}; exact McNemar p = {res['p_mcnemar']:.2g}",
    ]
    if not res.get("below_tops") and (res.get("a_over") or res.get("b_over")):
        lines.append(f"successes over the obstacles' tops: A {res['a_over']}, B {res['b_over']}")
    if note := over_tops_note(res):
        lines.append(note)
    if diff := res.get("package_differences"):
        lines.append(f"note: flown with different package versions (A / B: {format_differences(diff)}); some "
                     "discordant pairs may be floating-point divergence, not the rows (docs/evaluation.md, "
                     "'Reproducing a table')")  # fmt: skip
    if single and res.get("different_checkpoints"):
        lines.append("note: A and B fly different trained checkpoints; p compares these two policies over these "
                     "trials, not the recipes or code that trained them (two training seeds of one recipe often "
                     "disagree on as many trials): for that claim give training seeds as replicates (A1 B1 A2 B2 "
                     "...) and read the replicate-level test")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point."""
    ap = argparse.ArgumentParser(prog="python -m shield_nav.tools.paired", description=__doc__.split("\n")[0])
    ap.add_argument("specs", nargs="+", metavar="OUT_DIR:ROW",
                    help="A then B, e.g. eval_out/ablation:oracle_distilled_shapes_3ms eval_out/ablation:oracle; "
                         "more A B pairs (replicates, e.g. training seeds) are reported and pooled")  # fmt: skip
    ap.add_argument("--speeds", default="", help="comma-separated target speeds (default: all in common)")
    ap.add_argument("--below-tops", action="store_true",
                    help="count a success only where the flight stayed below the obstacles' tops")  # fmt: skip
    ap.add_argument("--by-scene", action="store_true",
                    help="also list each scene's outcomes per speed as letters (s S c t o), A's and B's")  # fmt: skip
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    args = ap.parse_args(argv)
    try:
        speeds = [float(s) for s in args.speeds.split(",") if s] or None
    except ValueError:
        ap.error(f"--speeds must be numbers, got {args.speeds!r}")
    if len(args.specs) % 2:
        ap.error(f"expected A B pairs of OUT_DIR:ROW, got an odd count ({len(args.specs)})")
    specs = list(zip(args.specs[::2], args.specs[1::2], strict=True))
    try:
        if len(specs) == 1:
            res = compare(*specs[0], speeds, args.below_tops)
        else:
            res = compare_pooled(specs, speeds, args.below_tops)
        scenes = [by_scene(a, b, speeds, args.below_tops) for a, b in specs] if args.by_scene else []
    except (ValueError, FileNotFoundError) as err:
        ap.error(str(err))
    if scenes:  # JSON keys are strings: the speeds as eval.py's unit names write them
        json_scenes = [[{**r, "speeds": {f"{v:g}": c for v, c in r["speeds"].items()}} for r in t] for t in scenes]
        for r, t in zip(res["pairs"] if len(specs) > 1 else [res], json_scenes, strict=True):
            r["by_scene"] = t
    if args.json:
        print(json.dumps(res))
    elif len(specs) == 1:
        print(format_report(res))
        if scenes:
            print("\n" + format_by_scene(scenes[0]))
    else:
        print("\n\n".join(format_report(r, single=False) + ("\n\n" + format_by_scene(t) if scenes else "")
                           for r, t in zip(res["pairs"], scenes or [None] * len(specs), strict=True)))  # fmt: skip
        p = res["pooled"]
        print(f"\npooled over {p['replicates']} replicates, {p['n']} paired trials: "
              f"A {100 * p['a_success']:.1f} %, B {100 * p['b_success']:.1f} %; discordant: A only {p['a_only']}, "
              f"B only {p['b_only']}; exact McNemar p = {p['p_mcnemar']:.2g}")  # fmt: skip
        r = p["replicate_level"]
        p_t = "n/a (one replicate)" if r["p_t"] is None else f"{r['p_t']:.2g}"
        print(f"replicate level (each replicate one observation; B - A in points): "
              f"{', '.join(f'{x:+.1f}' for x in r['differences'])}; mean {r['mean']:+.1f}; one-sample t p = {p_t}; "
              f"signs {r['positive']}+ / {r['negative']}- p = {r['p_sign']:.2g}")  # fmt: skip
        if note := over_tops_note(p):
            print(note)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
