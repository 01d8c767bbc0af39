"""Training curves: export a run's tensorboard scalars to CSV, and overlay a run on a committed reference.

``python -m shield_nav.tools.compare_runs RUN_DIR --reference checkpoints/dijkstra_cbf [--out FIG.png]`` reads the
run's tensorboard events and the reference's ``curves.csv`` and plots the curves that explain a run (success rate,
collisions, return, curriculum level, speed) against iterations, then prints where the run stands at the last
iteration both share. ``--export RUN_DIR OUT.csv`` writes a run's scalars to CSV (how the references were made).
"""

from __future__ import annotations

import argparse
import csv
import glob
import os
from collections import defaultdict

KEY_TAGS = (
    ("episode/success", "success rate (finished episodes)"),
    ("episode/collision", "collision rate"),
    ("Train/mean_reward", "mean episode return"),
    ("curriculum/mean_level", "curriculum level (mean)"),
    ("episode/mean_speed", "mean speed [m/s]"),
    ("Train/mean_episode_length", "episode length [steps]"),
)


def read_events(run_dir: str) -> dict[str, list[tuple[int, float]]]:
    """All scalar series of a run folder's tensorboard event files: tag -> [(step, value), ...] sorted by step."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = sorted(glob.glob(os.path.join(run_dir, "**", "events.out.tfevents*"), recursive=True))
    if not files:
        raise FileNotFoundError(f"no tensorboard event files under {run_dir!r}")
    series: dict[str, dict[int, float]] = defaultdict(dict)
    for f in files:
        acc = EventAccumulator(f, size_guidance={"scalars": 0})
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            for ev in acc.Scalars(tag):
                series[tag][ev.step] = ev.value  # a resumed run's later file wins for repeated steps
    return {tag: sorted(d.items()) for tag, d in series.items()}


def write_csv(series: dict[str, list[tuple[int, float]]], path: str) -> None:
    """Write ``tag,step,value`` rows."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["tag", "step", "value"])
        for tag in sorted(series):
            for step, value in series[tag]:
                w.writerow([tag, step, f"{value:.6g}"])


def read_csv(path: str) -> dict[str, list[tuple[int, float]]]:
    """Inverse of :func:`write_csv`."""
    out: dict[str, list[tuple[int, float]]] = defaultdict(list)
    with open(path, newline="") as fh:
        for row in csv.DictReader(fh):
            out[row["tag"]].append((int(row["step"]), float(row["value"])))
    return {k: sorted(v) for k, v in out.items()}


def _load(path: str) -> dict[str, list[tuple[int, float]]]:
    """A run folder (events) or a reference (folder with curves.csv, or a CSV file)."""
    if path.endswith(".csv"):
        return read_csv(path)
    ref = os.path.join(path, "curves.csv")
    if os.path.isfile(ref):
        return read_csv(ref)
    return read_events(path)


def smooth(values: list[float], window: int = 10) -> list[float]:
    """Trailing moving average (the curves are noisy per iteration)."""
    out, acc = [], []
    for v in values:
        acc.append(v)
        if len(acc) > window:
            acc.pop(0)
        out.append(sum(acc) / len(acc))
    return out


def compare(run: str, references: list[str], out: str | None) -> list[dict]:
    """Overlay ``run`` on each reference; print the last shared iteration's values. Returns the table rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = {os.path.basename(os.path.normpath(p)) or p: _load(p) for p in [*references, run]}
    run_name = list(curves)[-1]
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
    rows = []
    for ax, (tag, label) in zip(axes.ravel(), KEY_TAGS, strict=True):
        for name, series in curves.items():
            if tag not in series:
                continue
            steps, vals = zip(*series[tag], strict=True)
            ls = "-" if name == run_name else "--"
            ax.plot(steps, smooth(list(vals)), ls, label=f"{name}{' (yours)' if name == run_name else ' (ref)'}")
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("iteration", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        # Last iteration that every curve with this tag reaches.
        have = [s[tag] for s in curves.values() if tag in s]
        if len(have) >= 2:
            last = min(s[-1][0] for s in have)
            row = {"tag": tag, "iteration": last}
            for name, s in curves.items():
                if tag in s:
                    window = [v for st, v in s[tag] if last - 20 < st <= last]
                    row[name] = sum(window) / max(len(window), 1)
            rows.append(row)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"training curves: {run_name} against reference(s)", fontsize=10)
    fig.tight_layout()
    out = out or os.path.join(run, "compare.png")
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"figure: {out}")
    for row in rows:
        vals = "  ".join(f"{k}={v:.3f}" for k, v in row.items() if k not in ("tag", "iteration"))
        print(f"{row['tag']:<28} (mean of the 20 iterations up to {row['iteration']}): {vals}")
    return rows


def main(argv: list[str] | None = None) -> None:
    """CLI entry point."""
    p = argparse.ArgumentParser(prog="python -m shield_nav.tools.compare_runs", description=__doc__.splitlines()[0])
    p.add_argument("run", help="your run folder (logs/<experiment>/<timestamp>_<name>)")
    p.add_argument("--reference", action="append", default=[], help="committed checkpoint folder(s) or CSV")
    p.add_argument("--out", default=None, help="figure path (default RUN/compare.png)")
    p.add_argument("--export", default=None, metavar="CSV", help="only write the run's scalars to this CSV")
    args = p.parse_args(argv)
    if args.export:
        write_csv(read_events(args.run), args.export)
        print(f"wrote {args.export}")
        return
    if not args.reference:
        p.error("give --reference (or --export)")
    compare(args.run, args.reference, args.out)


if __name__ == "__main__":
    main()
