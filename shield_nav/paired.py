"""Is row B better than row A? A paired comparison of two evaluated rows over the same seeded trials.

``python -m shield_nav.paired OUT_A:ROW_A OUT_B:ROW_B [--speeds 3] [--json]``, e.g.
``python -m shield_nav.paired eval_out/ablation:oracle_distilled eval_out/ablation:oracle_distilled_shield``

Every ``eval.py`` row flies the same pinned trials (trial ``j`` of scene ``k`` at speed ``v`` has one seed, start and
goal, whatever the row, the worker count or the output folder). Two rows can therefore be compared trial by trial,
which is far more sensitive than comparing two success rates with their separate intervals. The tool matches the
trials of two rows (in one output folder or in two) by family, scene, speed and trial index, refuses pairs whose
seeds, starts or goals differ (different ``--seed`` or scenes), and reports:

* the paired success rates and their 95 % Wilson intervals;
* the discordant pairs: ``a_only`` (A succeeded, B did not) and ``b_only``;
* the exact two-sided McNemar test: under "A and B are equally good" each discordant pair is a fair coin, so
  ``p = min(1, 2 P(X <= min(a_only, b_only)))`` with ``X ~ Binomial(a_only + b_only, 1/2)``.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os

from shield_nav.evaluation import wilson_interval

__all__ = ["compare", "mcnemar_exact", "paired_outcomes"]


def mcnemar_exact(a_only: int, b_only: int) -> float:
    """Exact two-sided McNemar p-value of ``a_only`` vs ``b_only`` discordant pairs (1.0 when there are none)."""
    if a_only < 0 or b_only < 0:
        raise ValueError(f"discordant counts must be >= 0, got {a_only}, {b_only}")
    n, k = a_only + b_only, min(a_only, b_only)
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)


def _trials(spec: str, speeds: list[float] | None) -> dict[tuple, dict]:
    """``OUT_DIR:ROW`` -> {(family, scene, speed, trial): trial record}."""
    out_dir, sep, row = spec.rpartition(":")
    if not sep or not out_dir or not row:
        raise ValueError(f"expected OUT_DIR:ROW, got {spec!r}")
    files = sorted(glob.glob(os.path.join(out_dir, "units", "*.json")))
    if not files:
        raise FileNotFoundError(f"no unit files under {os.path.join(out_dir, 'units')!r}: not an eval.py output")
    found: dict[tuple, dict] = {}
    for path in files:
        with open(path) as fh:
            unit = json.load(fh)
        if unit["row"] != row or (speeds and float(unit["speed"]) not in speeds):
            continue
        for t in unit["trials"]:
            found[(unit["family"], int(unit["scene"]), float(unit["speed"]), int(t["trial"]))] = t
    if not found:
        rows = sorted({os.path.basename(f).split("__")[0] for f in files})
        raise ValueError(f"no trials of row {row!r} in {out_dir!r}" + (f" at speeds {speeds}" if speeds else "")
                         + f"; its rows: {', '.join(rows)}")  # fmt: skip
    return found


def paired_outcomes(a: str, b: str, speeds: list[float] | None = None) -> list[tuple[tuple, bool, bool]]:
    """The trials both rows flew: ``(key, a_succeeded, b_succeeded)``, sorted by key.

    Raises:
        ValueError: No common trial, or a common trial whose seed, start or goal differ between the two.
    """
    ta, tb = _trials(a, speeds), _trials(b, speeds)
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
        pairs.append((key, x["outcome"] == "success", y["outcome"] == "success"))
    return pairs


def compare(a: str, b: str, speeds: list[float] | None = None) -> dict:
    """Paired success rates, discordant counts and the exact McNemar p-value of rows ``a`` and ``b``."""
    pairs = paired_outcomes(a, b, speeds)
    n = len(pairs)
    sa, sb = sum(p[1] for p in pairs), sum(p[2] for p in pairs)
    a_only = sum(p[1] and not p[2] for p in pairs)
    b_only = sum(p[2] and not p[1] for p in pairs)
    return {
        "a": a, "b": b, "n": n,
        "a_success": sa / n, "a_interval": list(wilson_interval(sa, n)),
        "b_success": sb / n, "b_interval": list(wilson_interval(sb, n)),
        "a_only": a_only, "b_only": b_only, "p_mcnemar": mcnemar_exact(a_only, b_only),
        "speeds": sorted({p[0][2] for p in pairs}),
    }  # fmt: skip


def format_report(res: dict) -> str:
    """Human-readable lines of :func:`compare`'s result."""

    def pct(x: float) -> str:
        return f"{100 * x:.1f}"

    lo_a, hi_a = res["a_interval"]
    lo_b, hi_b = res["b_interval"]
    return "\n".join([
        f"{res['n']} paired trials at {', '.join(f'{s:g}' for s in res['speeds'])} m/s",
        f"A {res['a']}: {pct(res['a_success'])} % [{pct(lo_a)}, {pct(hi_a)}]",
        f"B {res['b']}: {pct(res['b_success'])} % [{pct(lo_b)}, {pct(hi_b)}]",
        f"discordant: A only {res['a_only']}, B only {res['b_only']}; exact McNemar p = {res['p_mcnemar']:.2g}",
    ])  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """CLI entry point."""
    ap = argparse.ArgumentParser(prog="python -m shield_nav.paired", description=__doc__.split("\n")[0])
    ap.add_argument("a", help="OUT_DIR:ROW, e.g. eval_out/ablation:oracle_distilled_shapes_3ms")
    ap.add_argument("b", help="OUT_DIR:ROW")
    ap.add_argument("--speeds", default="", help="comma-separated target speeds (default: all in common)")
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    args = ap.parse_args(argv)
    try:
        speeds = [float(s) for s in args.speeds.split(",") if s] or None
    except ValueError:
        ap.error(f"--speeds must be numbers, got {args.speeds!r}")
    try:
        res = compare(args.a, args.b, speeds)
    except (ValueError, FileNotFoundError) as err:
        ap.error(str(err))
    print(json.dumps(res) if args.json else format_report(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
