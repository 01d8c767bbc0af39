"""Tables of a run: the paper-shaped markdown table, the detail table, LaTeX and CSV."""

from __future__ import annotations

import csv
import io

import numpy as np

from shield_nav.evaluation.rollout import Prepared


def _pct(x: float | None) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{100 * x:.1f}"


def _num(x: float | None, fmt: str = ".2f") -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, fmt)


def _header_lines(prep: Prepared, summary: dict) -> list[str]:
    cfg = prep.cfg
    n_sc = len(cfg.scene_indices)
    seed = summary.get("scene_seed")
    at = f" at scene seed {seed}" if seed is not None else " (the family's own scenes)"
    lines = [
        f"{cfg.title or cfg.name}: family `{cfg.scenes.family}`{at}, scenes {cfg.scene_indices}, "
        f"{cfg.trials_per_scene} trials per scene and speed ({n_sc * cfg.trials_per_scene} per cell), seed {cfg.seed}.",
        "Observation noise and domain randomization: " + ("ON (training ranges)." if cfg.randomization else "off."),
        # The title is free text; the overrides as run (a CLI --set can change e.g. the scene seed a title names).
        "Env overrides: " + (", ".join(f"`{o}`" for o in cfg.env_overrides) if cfg.env_overrides else "none") + ".",
        "SR: success rate % [95 % Wilson interval]; Vel: mean speed of successful trials [m/s].",
    ]
    if any(r.controller.startswith("oracle") for r in prep.rows.values()):
        lines.append("The oracle reads the privileged map (geodesic field and ESDF): an upper bound, not a competitor.")
    if any(r.controller == "reactive_geodesic" for r in prep.rows.values()):
        lines.append("The geodesic-guided reactive planner reads the privileged geodesic field for its goal direction.")
    if any(r.controller == "teacher" for r in prep.rows.values()):
        lines.append("Teacher rows read the privileged local ESDF map (no depth): the policy each student imitates.")
    for name, info in prep.policies.items():
        lines.append(f"Checkpoint `{name}`: {info.path} (sha256 {info.sha256[:12]}, {info.kind}).")
    if prep.missing:
        lines.append(
            "MISSING policy rows (no checkpoint): " + ", ".join(f"{k} ({v})" for k, v in prep.missing.items()) + "."
        )
    lines += [f"WARNING (marked !): {m}." for m in dict.fromkeys(prep.speed_flags.values())]  # once per policy
    done, total = summary.get("units_done", 0), summary.get("units_total", 0)
    if done < total:
        lines.append(f"PARTIAL: {done} of {total} units finished; re-run the same command to complete the table.")
    return lines


def paper_table(prep: Prepared, summary: dict) -> str:
    """The paper-shaped Markdown table: rows = configurations, per speed SR [CI] and Vel."""
    speeds = prep.cfg.speeds
    head = "| Configuration | " + " | ".join(f"{v:g} m/s SR | {v:g} m/s Vel" for v in speeds) + " |"
    sep = "|---|" + "---:|---:|" * len(speeds)
    lines = [head, sep]
    for rname, row in prep.rows.items():
        label = row.label or rname
        cells = []
        for v in speeds:
            c = summary["cells"][rname].get(f"{v:g}")
            flag = " !" if (rname, v) in prep.speed_flags else ""
            if rname in prep.missing:
                cells += ["missing", "-"]
            elif c is None:
                cells += ["(not run)", "-"]
            else:
                cells += [f"{_pct(c['success_rate'])} [{_pct(c['sr_lo'])}, {_pct(c['sr_hi'])}]{flag}",
                          _num(c["vel"])]  # fmt: skip
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


DETAIL_COLUMNS = [
    ("n", "n", lambda c: str(c["n"])),
    ("SR %", "success_rate", lambda c: _pct(c["success_rate"])),
    ("95% CI", "ci", lambda c: f"{_pct(c['sr_lo'])}-{_pct(c['sr_hi'])}"),
    ("coll %", "collision_rate", lambda c: _pct(c["collision_rate"])),
    ("timeout %", "timeout_rate", lambda c: _pct(c["timeout_rate"])),
    ("OOB %", "oob_rate", lambda c: _pct(c["oob_rate"])),
    ("circling %", "circling", lambda c: _pct(c.get("circling"))),
    ("Vel", "vel", lambda c: _num(c["vel"])),
    ("clear mean", "clearance_mean", lambda c: _num(c["clearance_mean"])),
    ("clear min", "clearance_min", lambda c: _num(c["clearance_min"])),
    ("path/geo", "path_ratio", lambda c: _num(c["path_ratio"], ".3f")),
    ("over top % of SR", "over_top", lambda c: _pct(c.get("over_top"))),
    ("shield act %", "shield_active", lambda c: _pct(c.get("shield_active"))),
    ("corr mean", "corr_mean", lambda c: _num(c.get("corr_mean"))),
    ("corr max", "corr_max", lambda c: _num(c.get("corr_max"))),
    ("relaxed %", "relaxed", lambda c: _pct(c.get("relaxed"))),
    ("QP us mean", "qp_us_mean", lambda c: _num(c.get("qp_us_mean"), ".0f")),
    ("QP us max", "qp_us_max", lambda c: _num(c.get("qp_us_max"), ".0f")),
]
"""Columns of the detailed table (header, summary key, formatter)."""


def detail_table(prep: Prepared, summary: dict) -> str:
    """Every metric per (configuration, speed) cell."""
    lines = ["| Configuration | speed | " + " | ".join(h for h, _, _ in DETAIL_COLUMNS) + " |",
             "|---|---:|" + "---:|" * len(DETAIL_COLUMNS)]  # fmt: skip
    for rname, row in prep.rows.items():
        for v in prep.cfg.speeds:
            c = summary["cells"][rname].get(f"{v:g}")
            if c is None:
                continue
            lines.append(f"| {row.label or rname} | {v:g} | " + " | ".join(f(c) for _, _, f in DETAIL_COLUMNS) + " |")
    return "\n".join(lines)


def latex_table(prep: Prepared, summary: dict) -> str:
    """The paper-shaped table as LaTeX (booktabs), SR in % and Vel in m/s per speed."""
    speeds = prep.cfg.speeds
    cols = "l " + " ".join("cc" for _ in speeds)
    out = [
        "\\begin{tabular}{" + cols + "}",
        "\\toprule",
        "\\multirow{2}{*}{\\textbf{Configuration}} & "
        + " & ".join(f"\\multicolumn{{2}}{{c}}{{\\textbf{{{v:g} m/s}}}}" for v in speeds)
        + " \\\\",
        " ".join(f"\\cmidrule{{{2 + 2 * i}-{3 + 2 * i}}}" for i in range(len(speeds))),
        " & " + " & ".join("SR$\\uparrow$ & Vel" for _ in speeds) + " \\\\ \\midrule",
    ]
    for rname, row in prep.rows.items():
        cells = []
        for v in speeds:
            c = summary["cells"][rname].get(f"{v:g}")
            if c is None:
                cells += ["--", "--"]
            else:
                cells += [_pct(c["success_rate"]), _num(c["vel"]).replace("-", "--")]
        label = (row.label or rname).replace("&", "\\&").replace("%", "\\%")
        out.append(f"{label} & " + " & ".join(cells) + " \\\\")
    out += ["\\bottomrule", "\\end{tabular}"]
    return "\n".join(out)


def csv_table(prep: Prepared, summary: dict) -> str:
    """One CSV line per (configuration, speed) cell with every metric."""
    keys = ["n", "successes", "success_rate", "sr_lo", "sr_hi", "collision_rate", "timeout_rate", "oob_rate",
            "circling", "vel", "clearance_mean", "clearance_min", "path_ratio", "over_top", "shield_active",
            "corr_mean", "corr_max", "relaxed", "qp_us_mean", "qp_us_max", "shield_us_mean", "switched"]  # fmt: skip
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["configuration", "label", "speed", *keys])
    for rname, row in prep.rows.items():
        for v in prep.cfg.speeds:
            c = summary["cells"][rname].get(f"{v:g}")
            if c is None:
                continue
            w.writerow([rname, row.label, v, *[c.get(k, "") for k in keys]])
    return buf.getvalue()
