"""Evaluation figures: success rate vs target speed, realised velocity, top-down trajectories over the ESDF.

All functions take the harness's summary/unit dicts (see :mod:`shield_nav.evaluation`) and write PNGs with the
Agg backend (no display needed).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_success_vs_speed(summary: dict, path: str) -> None:
    """Success rate (with the 95 % Wilson interval as error bars) against target speed, one line per row."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    speeds = [float(v) for v in summary["speeds"]]
    for rname, row in summary["rows"].items():
        cells = [summary["cells"][rname].get(f"{v:g}") for v in speeds]
        pts = [(v, c) for v, c in zip(speeds, cells, strict=True) if c is not None]
        if not pts:
            continue
        x = np.array([v for v, _ in pts])
        sr = np.array([100 * c["success_rate"] for _, c in pts])
        lo = np.array([100 * c["sr_lo"] for _, c in pts])
        hi = np.array([100 * c["sr_hi"] for _, c in pts])
        err = np.maximum(np.stack((sr - lo, hi - sr)), 0.0)  # clip float round-off at SR = 0 or 100 %
        ax.errorbar(x, sr, yerr=err, marker="o", capsize=3, label=row.get("label") or rname)
    ax.set_xlabel("target speed [m/s]")
    ax.set_ylabel("success rate [%]")
    ax.set_ylim(-3, 103)
    ax.set_xticks(speeds)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(f"{summary['name']}: success vs speed (95 % Wilson)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_velocity(summary: dict, path: str) -> None:
    """Mean realised speed of successful trials against target speed, one line per row, with y = x."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    speeds = [float(v) for v in summary["speeds"]]
    ax.plot(speeds, speeds, "k--", lw=0.8, label="target")
    for rname, row in summary["rows"].items():
        pts = [(v, summary["cells"][rname].get(f"{v:g}")) for v in speeds]
        pts = [(v, c["vel"]) for v, c in pts if c is not None and np.isfinite(c["vel"])]
        if pts:
            ax.plot(*zip(*pts, strict=True), marker="o", label=row.get("label") or rname)
    ax.set_xlabel("target speed [m/s]")
    ax.set_ylabel("realised speed of successful trials [m/s]")
    ax.set_xticks(speeds)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(f"{summary['name']}: realised velocity")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_trajectories(
    scene: Any, fields: Any, units: list[dict], labels: dict[str, str], path: str, vmax: float | None = None
) -> None:
    """Top-down trajectories over the scene's ESDF (one panel per unit), coloured by speed; collisions as red X.

    Args:
        scene: The :class:`envs.scenes.Scene`.
        fields: Its :class:`envs.fields.SceneFields` (ESDF shading and geodesic contours).
        units: Unit records of this scene (their trials carry ``traj`` rows [x, y, z, |v|]).
        labels: Row name -> label.
        path: PNG path.
        vmax: Top of the speed colour scale (default: the largest speed flown).
    """
    plt = _plt()
    from matplotlib.collections import LineCollection

    from envs.scenes.plot import draw_scene

    n = len(units)
    w = 10.0
    h = w * scene.size[1] / scene.size[0] + 0.9
    fig, axes = plt.subplots(n, 1, figsize=(w, h * n), squeeze=False, layout="constrained")
    vmax = vmax or max((max((p[3] for p in t["traj"]), default=1.0) for u in units for t in u["trials"]), default=1.0)
    lc = None
    for ax, unit in zip(axes[:, 0], units, strict=True):
        draw_scene(ax, scene, fields)
        for t in unit["trials"]:
            tr = np.asarray(t["traj"])
            if len(tr) < 2:
                continue
            seg = np.stack((tr[:-1, :2], tr[1:, :2]), axis=1)
            lc = LineCollection(seg, cmap="plasma", linewidths=1.2)
            lc.set_array(tr[1:, 3])
            lc.set_clim(0.0, vmax)
            ax.add_collection(lc)
            if t["outcome"] == "collision":
                ax.plot(tr[-1, 0], tr[-1, 1], "x", color="red", ms=8, mew=2)
            ax.plot(*t["goal"][:2], "*", color="tab:orange", ms=6)
        s = unit["summary"]
        ax.set_title(
            f"{labels.get(unit['row'], unit['row'])}: {scene.family} {scene.index} at {unit['speed']:g} m/s, "
            f"SR {100 * s['success_rate']:.0f}% (n={s['n']}, red X = collision)",
            fontsize=9,
        )
    if lc is not None:
        fig.colorbar(lc, ax=axes[:, 0].tolist(), fraction=0.02, pad=0.01, label="speed [m/s]")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_figures(prep: Any, summary: dict, results: list[dict], out_dir: str) -> list[str]:
    """All figures of a run: success vs speed, velocity, and trajectories for the first scenes at the top speed."""
    from envs.fields import build_fields
    from envs.scenes import make_scene
    from shield_nav.evaluation import nav_config

    os.makedirs(out_dir, exist_ok=True)
    paths = [os.path.join(out_dir, "success_vs_speed.png"), os.path.join(out_dir, "velocity.png")]
    plot_success_vs_speed(summary, paths[0])
    plot_velocity(summary, paths[1])
    cfg = prep.cfg
    labels = {k: r.label or k for k, r in prep.rows.items()}
    nav = nav_config(cfg, cfg.scenes.family, cfg.scene_indices[0], cfg.speeds[0], 1)
    for idx in cfg.scene_indices[: cfg.trajectory_scenes]:
        here = [u for u in results if u["scene"] == idx]
        if not here:
            continue
        speed = max(u["speed"] for u in here)
        here = [u for u in here if u["speed"] == speed]
        scene = make_scene(cfg.scenes.family, idx)
        fields = build_fields(scene, resolution=nav.scenes.field_resolution,
                              vehicle_radius=nav.vehicle.airframe.collision_radius)  # fmt: skip
        p = os.path.join(out_dir, f"trajectories_{cfg.scenes.family}-{idx:02d}_v{speed:g}.png")
        plot_trajectories(scene, fields, here, labels, p)
        paths.append(p)
    return paths
