"""Success against realised speed: where each evaluated row sits on the speed-safety plane at one target speed.

``python -m shield_nav.tools.frontier LABEL=OUT_DIR:ROW [LABEL=OUT_DIR:ROW ...] [--speed 7] [--bar-speed 0.85]
[--bar-success 93] [--plot PNG] [--json]``, e.g. the expert's variants on one validation set:
``python -m shield_nav.tools.frontier default=eval_out/va:expert preview=eval_out/va_preview:expert --plot f.png``

For each row it reads the trials flown at ``--speed`` (an ``eval.py`` output folder, as :mod:`shield_nav.tools.paired`
does) and reports the success rate with its 95 % Wilson interval and the realised speed of the successes as a share
of the target (the mean of their ``metrics.mean_speed``, the table's ``Vel`` column, divided by the target). A
variant that only trades one for the other moves along a curve; a better one moves up and to the right of it. The
bars (``--bar-speed``, ``--bar-success``; by default the high-speed issue's 0.85 x and the ablation's 93 % at 7 m/s)
are drawn as lines, so the corner where a row meets both is visible. Rows are compared on the same pinned trials
only if they come from the same scenes and seeds; the tool reports each row's trial count and refuses an empty one.
"""

from __future__ import annotations

import argparse
import json
import sys

from shield_nav.evaluation import wilson_interval
from shield_nav.tools.paired import row_trials

__all__ = ["frontier_point", "main"]


def frontier_point(spec: str, speed: float) -> dict:
    """Success (share, Wilson interval) and realised speed / target of row ``OUT_DIR:ROW`` at ``speed``.

    Raises:
        ValueError: The spec is malformed, the row has no trial at ``speed``, or a success lacks
            ``metrics.mean_speed``.
    """
    trials = row_trials(spec, [speed])
    n = len(trials)
    speeds = []
    for key, t in sorted(trials.items()):
        if t["outcome"] != "success":
            continue
        v = t.get("metrics", {}).get("mean_speed")
        if v is None:
            raise ValueError(f"trial {key} of {spec} has no metrics.mean_speed")
        speeds.append(float(v))
    k = len(speeds)
    return {
        "spec": spec, "speed": speed, "n": n, "successes": k, "success": k / n,
        "interval": list(wilson_interval(k, n)),
        "realised": (sum(speeds) / k / speed) if k else None,
    }  # fmt: skip


def _plot(points: list[dict], bar_speed: float, bar_success: float, speed: float, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for i, p in enumerate(points):
        if p["realised"] is None:
            continue
        y, (lo, hi) = 100 * p["success"], p["interval"]
        ax.errorbar(p["realised"], y, yerr=[[y - 100 * lo], [100 * hi - y]], fmt="o", capsize=3)
        ax.annotate(
            p["label"], (p["realised"], y), textcoords="offset points", xytext=(5, 4 if i % 2 else -11), fontsize=8
        )
    ax.axvline(bar_speed, color="grey", ls="--", lw=1)
    ax.axhline(bar_success, color="grey", ls="--", lw=1)
    ax.set_xlabel(f"realised speed of the successes / target ({speed:g} m/s)")
    ax.set_ylabel("success % (95 % Wilson interval)")
    ax.set_title(f"Success against realised speed at {speed:g} m/s (bars dashed)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point."""
    ap = argparse.ArgumentParser(prog="python -m shield_nav.tools.frontier", description=__doc__.split("\n")[0])
    ap.add_argument("rows", nargs="+", metavar="LABEL=OUT_DIR:ROW")
    ap.add_argument("--speed", type=float, default=7.0, help="target speed [m/s] (default 7)")
    ap.add_argument("--bar-speed", type=float, default=0.85, help="realised-speed bar, share of target (0.85)")
    ap.add_argument("--bar-success", type=float, default=93.0, help="success bar [%%] (93)")
    ap.add_argument("--plot", default="", help="write the figure to this PNG")
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    args = ap.parse_args(argv)
    points = []
    for item in args.rows:
        label, sep, spec = item.partition("=")
        if not sep or not label or not spec:
            ap.error(f"expected LABEL=OUT_DIR:ROW, got {item!r}")
        try:
            points.append({"label": label, **frontier_point(spec, args.speed)})
        except (ValueError, FileNotFoundError) as err:
            ap.error(f"{label}: {err}")
    for p in points:
        lo, hi = p["interval"]
        real = "-" if p["realised"] is None else f"{p['realised']:.3f}"
        print(f"{p['label']}: {100 * p['success']:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}] of {p['n']}, "
              f"realised {real} x {args.speed:g} m/s", file=sys.stderr if args.json else sys.stdout)  # fmt: skip
    if args.plot:
        _plot(points, args.bar_speed, args.bar_success, args.speed, args.plot)
    if args.json:
        print(json.dumps({"speed": args.speed, "points": points}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
