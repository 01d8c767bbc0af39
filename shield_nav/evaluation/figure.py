"""Our rows beside the paper's: success rate and realised speed against target speed, for Tables I and II.

``python -m shield_nav.evaluation.figure --table1 OUT[:ROW,ROW] [...] --table2 OUT[:ROW,ROW] [...] --out PNG``

Each ``OUT`` is an ``eval.py`` output folder (its ``summary.json``); ``:ROW,ROW`` keeps only those rows, otherwise
every row of the folder is drawn; ``ROW=AS`` draws row ``ROW`` as row ``AS`` (its colour, order, paper row and, for a
row of configs/eval/rows.yaml, label), e.g. ``docs/data/t1_full:full_local_map=full`` for a run flown under an
earlier row name. Rows from several folders are merged (a row in two folders is refused: which one
would be the table's?), and an unfinished run is refused, so a figure never shows part of a table. One column of
panels per table: success rate with its 95 % Wilson interval on top, the mean realised speed of the successful flights
below (with the target speed as a dashed line). Where a row reproduces one of the paper's (``distance``,
``dijkstra``, ``dijkstra_cbf``, ``full``) the paper's numbers (:mod:`shield_nav.evaluation.paper`) are drawn dashed
in the same colour; ``--paper-methods`` adds the paper's other Table II methods (default: DiffPhys, its strongest).
The README's figure is made this way (docs/results.md gives the command).

``--seeds`` draws training replicates instead: every ``OUT`` given to a table is one training seed of the same rows
(``OUT+OUT2`` joins one seed's folders, e.g. a seed whose 3 m/s cell was flown apart; a speed in two of them is
refused). Each seed's success rate is drawn thin, and the rate pooled over the seeds (all their trials summed, with
the 95 % Wilson interval of the sum and the realised speed weighted by successes) thick, so one sees at a glance
whether two rows differ by more than the seeds of one row do. docs/results.md's "Ordering at 5-9 m/s" figure is made
this way.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from shield_nav.evaluation.config import BUILTIN_ROWS
from shield_nav.evaluation.metrics import wilson_interval
from shield_nav.evaluation.paper import PAPER_SPEEDS, PAPER_TABLE_I, PAPER_TABLE_II
from shield_nav.evaluation.plots import _plt, cell_series

__all__ = ["load_rows", "load_seed", "main", "plot_seeds", "plot_tables", "pool_cells", "row_series"]

#: Fixed colours, so a row looks the same in every panel and every figure.
_COLOURS = {
    "distance": "tab:blue",
    "dijkstra": "tab:orange",
    "dijkstra_cbf": "tab:green",
    "full": "tab:red",
    "expert": "0.25",
}
_ORDER = ("distance", "dijkstra", "dijkstra_cbf", "full", "expert")


def load_rows(specs: list[str]) -> dict[str, dict]:
    """Read ``OUT[:ROW,ROW]`` specs into ``{row: {"label", "cells", "source"}}``, cells keyed by speed (``"9"``)."""
    rows: dict[str, dict] = {}
    for spec in specs:
        out, _, names = spec.partition(":")
        path = os.path.join(out, "summary.json")
        if not os.path.isfile(path):
            raise ValueError(f"{spec!r}: no {path} (not an eval.py output folder, or the run has not finished)")
        with open(path) as f:
            summary = json.load(f)
        done, total = summary.get("units_done"), summary.get("units_total")
        if done is not None and total is not None and done < total:
            raise ValueError(f"{spec!r}: the run is unfinished ({done} of {total} units); resume it first")
        wanted = [n for n in names.split(",") if n] if names else list(summary["rows"])
        for item in wanted:
            name, renamed, alias = item.partition("=")
            if renamed and not (alias and alias.replace("_", "").isalnum()):
                raise ValueError(f"{spec!r}: {item!r} must be ROW=AS with AS a row name, e.g. full_local_map=full")
            if name not in summary["rows"]:
                raise ValueError(f"{spec!r}: no row {name!r} in {path} (rows: {', '.join(summary['rows'])})")
            if renamed:  # drawn as row ``alias``: its label from configs/eval/rows.yaml where it is one of those
                key, label = alias, (BUILTIN_ROWS[alias].label if alias in BUILTIN_ROWS else "") or alias
            else:
                key, label = name, summary["rows"][name].get("label") or name
            if key in rows:
                raise ValueError(f"row {key!r} is in both {rows[key]['source']} and {out}: name one with OUT:ROW")
            rows[key] = {"label": label, "cells": summary["cells"][name], "source": out}
    return rows


def load_seed(spec: str) -> dict[str, dict]:
    """One training replicate, ``OUT[+OUT2...][:ROWS]``: :func:`load_rows` of each folder, a row's cells merged.

    Raises:
        ValueError: A row and speed in two of the folders (which one is the seed's?), or any :func:`load_rows` error.
    """
    folders, sep, names = spec.partition(":")
    merged: dict[str, dict] = {}
    for out in folders.split("+"):
        for name, row in load_rows([out + sep + names]).items():
            if name not in merged:
                merged[name] = {"label": row["label"], "cells": dict(row["cells"]), "source": out}
                continue
            clash = sorted(set(merged[name]["cells"]) & set(row["cells"]), key=float)
            if clash:
                raise ValueError(f"{spec!r}: row {name!r} has {', '.join(clash)} m/s in both {merged[name]['source']} "
                                 f"and {out}")  # fmt: skip
            merged[name]["cells"].update(row["cells"])
    return merged


def pool_cells(cells: list[dict]) -> dict[str, dict]:
    """One row's cells of several replicates pooled by speed.

    Trials and successes summed, the Wilson interval of the sum, the realised speed weighted by each replicate's
    successes, and ``seeds`` (how many replicates flew that speed).
    """
    pooled: dict[str, dict] = {}
    for speed in sorted({k for c in cells for k, v in c.items() if v is not None}, key=float):
        flown = [c[speed] for c in cells if c.get(speed) is not None]
        n, k = sum(int(c["n"]) for c in flown), sum(int(c["successes"]) for c in flown)
        with_vel = [c for c in flown if c["successes"] and c.get("vel") is not None]
        wk = sum(c["successes"] for c in with_vel)
        lo, hi = wilson_interval(k, n)
        pooled[speed] = {
            "n": n, "successes": k, "success_rate": k / n, "sr_lo": lo, "sr_hi": hi, "seeds": len(flown),
            "vel": sum(c["vel"] * c["successes"] for c in with_vel) / wk if wk else None,
        }  # fmt: skip
    return pooled


def row_series(row: dict) -> dict[str, np.ndarray]:
    """The plotted arrays of one loaded row (:func:`shield_nav.evaluation.plots.cell_series` of its cells)."""
    return cell_series(row["cells"])


def _ordered(rows: dict[str, dict]) -> list[str]:
    return [n for n in _ORDER if n in rows] + [n for n in rows if n not in _ORDER]


def plot_tables(tables: dict[str, dict[str, dict]], path: str, paper_methods: tuple[str, ...] = ("diffphys",)) -> None:
    """Draw ``{"Table I": rows, "Table II": rows}`` (either may be absent) with the paper's rows, to ``path``."""
    unknown = [m for m in paper_methods if m not in PAPER_TABLE_II]
    if unknown:
        raise ValueError(f"--paper-methods: unknown {', '.join(unknown)} (known: {', '.join(PAPER_TABLE_II)})")
    if not tables:
        raise ValueError("nothing to draw: give --table1 and/or --table2")
    plt = _plt()
    fig, axes = plt.subplots(2, len(tables), figsize=(5.6 * len(tables), 8.0), squeeze=False, sharex=True)
    others = iter(f"C{k}" for k in range(4, 10))
    colours = dict(_COLOURS)
    for col, (title, rows) in enumerate(tables.items()):
        paper = PAPER_TABLE_I if title == "Table I" else PAPER_TABLE_II
        ax_sr, ax_v = axes[0, col], axes[1, col]
        trials = set()
        for name in _ordered(rows):
            colour = colours.setdefault(name, next(others, "k"))
            s = row_series(rows[name])
            trials.update(s["n"].tolist())
            label = rows[name]["label"]
            ax_sr.errorbar(s["speed"], s["sr"], yerr=s["err"], color=colour, marker="o", capsize=3, label=label)
            ax_v.plot(s["speed"], s["vel"], color=colour, marker="o", label=label)
            if name in paper:
                _paper_lines(ax_sr, ax_v, paper[name], colour)
        if title == "Table II":
            for method in paper_methods:
                if method not in rows:
                    _paper_lines(ax_sr, ax_v, PAPER_TABLE_II[method], "0.6")
        n = "/".join(str(t) for t in sorted(trials))
        ax_sr.set_title(f"{title}: success rate ({n} trials per cell, 95 % Wilson)", fontsize=9)
        ax_sr.set_ylabel("success rate [%]")
        ax_sr.set_ylim(-3, 103)
        ax_v.plot(PAPER_SPEEDS, PAPER_SPEEDS, "k:", lw=0.8, label="target speed")
        ax_v.set_title(f"{title}: mean speed of the successful flights", fontsize=9)
        ax_v.set_ylabel("realised speed [m/s]")
        ax_v.set_xlabel("target speed [m/s]")
        ax_v.set_xticks(PAPER_SPEEDS)
        ax_sr.grid(alpha=0.3)
        ax_v.grid(alpha=0.3)
        # One legend per table, under its column, so no curve hides behind it: ours first, the paper's after.
        legend: dict[str, object] = {}
        for ax in (ax_sr, ax_v):
            for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
                legend.setdefault(label, handle)
        labels = sorted(legend, key=lambda k: (k.endswith(", paper"), k == "target speed"))
        ax_v.legend(
            [legend[k] for k in labels], labels, fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.16)
        )
    fig.suptitle("solid: this repository, held-out scenes; dashed, open markers: the paper's numbers", fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_seeds(tables: dict[str, list[dict[str, dict]]], path: str) -> None:
    """Draw ``{"Table I": [seed rows, ...], ...}``: every seed of a row thin, the pooled rate thick, the paper dashed.

    Only rows present in every seed are drawn (a row missing from one would pool fewer seeds unnoticed).
    """
    if not tables:
        raise ValueError("nothing to draw: give --table1 and/or --table2")
    plt = _plt()
    fig, axes = plt.subplots(1, len(tables), figsize=(5.6 * len(tables), 4.6), squeeze=False)
    others = iter(f"C{k}" for k in range(4, 10))
    colours = dict(_COLOURS)
    for col, (title, seeds) in enumerate(tables.items()):
        common = [n for n in _ordered(seeds[0]) if all(n in s for s in seeds)]
        if not common:
            raise ValueError(f"{title}: no row is in every seed's folders")
        paper = PAPER_TABLE_I if title == "Table I" else PAPER_TABLE_II
        ax = axes[0, col]
        for name in common:
            colour = colours.setdefault(name, next(others, "k"))
            for seed in seeds:
                s = row_series(seed[name])
                ax.plot(s["speed"], s["sr"], color=colour, lw=0.9, alpha=0.45, marker=".", ms=4)
            cells = pool_cells([seed[name]["cells"] for seed in seeds])
            pooled = cell_series(cells)
            lo, hi = min(c["seeds"] for c in cells.values()), max(c["seeds"] for c in cells.values())
            label = f"{seeds[0][name]['label']}, {lo if lo == hi else f'{lo}-{hi}'} seeds pooled"
            ax.errorbar(pooled["speed"], pooled["sr"], yerr=pooled["err"], color=colour, lw=2.2, marker="o",
                        capsize=3, label=label)  # fmt: skip
            if name in paper:
                _paper_lines(ax, None, paper[name], colour)
        ax.set_title(f"{title}: success rate, each training seed (thin) and pooled (thick, 95 % Wilson)", fontsize=8)
        ax.set_ylabel("success rate [%]")
        ax.set_xlabel("target speed [m/s]")
        ax.set_xticks(PAPER_SPEEDS)
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _paper_lines(ax_sr, ax_v, row: dict, colour: str) -> None:  # noqa: ANN001
    label = f"{row['label']}, paper"
    ax_sr.plot(PAPER_SPEEDS, row["sr"], ls="--", color=colour, marker="o", mfc="none", label=label)
    if ax_v is not None and "vel" in row:
        vel = [np.nan if v is None else v for v in row["vel"]]
        ax_v.plot(PAPER_SPEEDS, vel, ls="--", color=colour, marker="o", mfc="none", label=label)


def main(argv: list[str] | None = None) -> int:
    """Command line: see the module docstring."""
    ap = argparse.ArgumentParser(prog="python -m shield_nav.evaluation.figure", description=__doc__.split("\n")[0])
    ap.add_argument(
        "--table1", nargs="+", default=[], metavar="OUT[:ROWS]", help="ablation (Table I) outputs; ROWS: ROW[=AS],..."
    )
    ap.add_argument(
        "--table2", nargs="+", default=[], metavar="OUT[:ROWS]", help="benchmark (Table II) outputs; ROWS: ROW[=AS],..."
    )
    ap.add_argument(
        "--paper-methods", default=None, help="the paper's other Table II methods, comma list (default: diffphys)"
    )
    ap.add_argument(
        "--seeds",
        action="store_true",
        help="each OUT (OUT+OUT2: one seed's folders) is one training seed of the same rows: seeds thin, pooled thick",
    )
    ap.add_argument("--out", required=True, help="PNG to write")
    args = ap.parse_args(argv)
    if args.seeds and args.paper_methods is not None:
        ap.error(
            "--paper-methods draws beside the tables figure; the --seeds figure shows the formulations' paper rows only"
        )
    try:
        if args.seeds:
            seeded = {
                t: [load_seed(s) for s in specs]
                for t, specs in (("Table I", args.table1), ("Table II", args.table2))
                if specs
            }
            plot_seeds(seeded, args.out)
        else:
            tables = {}
            if args.table1:
                tables["Table I"] = load_rows(args.table1)
            if args.table2:
                tables["Table II"] = load_rows(args.table2)
            methods = tuple(m for m in (args.paper_methods or "diffphys").split(",") if m)
            plot_tables(tables, args.out, paper_methods=methods)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
