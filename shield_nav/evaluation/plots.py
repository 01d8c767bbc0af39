"""Evaluation figures: success rate vs target speed, realised velocity, top-down trajectories over the ESDF.

All functions take the harness's summary/unit dicts (see :mod:`shield_nav.evaluation`) and write PNGs with the
Agg backend (no display needed).

``eval.py`` draws the trajectories of its first scenes at its top speed. Any other scene and speed of a finished
output folder, without flying again:

``python -m shield_nav.evaluation.plots eval_out/<name> [eval_out/<other> ...] --scenes 12,13 [--speeds 3,5]
[--rows full] [--xlim 0,40] [--out DIR]``

writes one figure per scene, a panel per (row, speed) flown there (:func:`trajectory_figures`); given several
folders that flew the same scenes (two variants, or a row with and without its shield), their panels stack in one
figure, in the order the folders are given.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
from typing import Any

import numpy as np


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def cell_series(cells: dict) -> dict[str, np.ndarray]:
    """One row's cells (``{"9": cell, ...}`` as ``summary.json`` holds them) as arrays sorted by target speed.

    ``sr``, ``lo``, ``hi`` in %, ``err`` the error bars below and above ``sr`` (float round-off at 0 or 100 % clipped),
    ``vel`` the mean realised speed of the successful trials (NaN where none succeeded), ``n`` the trials per cell.
    """
    keys = sorted((k for k, c in cells.items() if c is not None), key=float)
    cs = [cells[k] for k in keys]
    sr = np.array([100.0 * c["success_rate"] for c in cs])
    lo = np.array([100.0 * c["sr_lo"] for c in cs])
    hi = np.array([100.0 * c["sr_hi"] for c in cs])
    return {
        "speed": np.array([float(k) for k in keys]),
        "sr": sr,
        "lo": lo,
        "hi": hi,
        "err": np.maximum(np.stack((sr - lo, hi - sr)), 0.0).reshape(2, len(keys)),
        "vel": np.array([np.nan if c.get("vel") is None else float(c["vel"]) for c in cs]),
        "n": np.array([int(c["n"]) for c in cs]),
    }


def plot_success_vs_speed(summary: dict, path: str) -> None:
    """Success rate (with the 95 % Wilson interval as error bars) against target speed, one line per row."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    speeds = [float(v) for v in summary["speeds"]]
    for rname, row in summary["rows"].items():
        s = cell_series(summary["cells"][rname])
        if len(s["speed"]):
            ax.errorbar(s["speed"], s["sr"], yerr=s["err"], marker="o", capsize=3, label=row.get("label") or rname)
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
        s = cell_series(summary["cells"][rname])
        ok = np.isfinite(s["vel"])
        if ok.any():
            ax.plot(s["speed"][ok], s["vel"][ok], marker="o", label=row.get("label") or rname)
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
    scene: Any,
    fields: Any,
    units: list[dict],
    labels: dict[str, str],
    path: str,
    vmax: float | None = None,
    xlim: tuple[float, float] | None = None,
) -> None:
    """Top-down trajectories over the scene's ESDF (one panel per unit), coloured by speed; collisions as red X.

    Args:
        scene: The :class:`envs.scenes.Scene`.
        fields: Its :class:`envs.fields.SceneFields` (ESDF shading and geodesic contours).
        units: Unit records of this scene (their trials carry ``traj`` rows [x, y, z, |v|]).
        labels: Row name -> label.
        path: PNG path.
        vmax: Top of the speed colour scale (default: the largest speed flown).
        xlim: The x range [m] drawn (default: the scene's); a unit's ``label`` key, if any, names its panel.
    """
    plt = _plt()
    from matplotlib.collections import LineCollection

    from envs.scenes.plot import draw_scene

    n = len(units)
    w = 10.0
    span = (xlim[1] - xlim[0]) if xlim else scene.size[0]
    h = 0.78 * w * scene.size[1] / span + 0.9
    fig, axes = plt.subplots(n, 1, figsize=(w, h * n), squeeze=False, layout="constrained")
    vmax = vmax or max((max((p[3] for p in t["traj"]), default=1.0) for u in units for t in u["trials"]), default=1.0)
    lc = None
    for ax, unit in zip(axes[:, 0], units, strict=True):
        draw_scene(ax, scene, fields)
        if xlim:
            ax.set_xlim(*xlim)
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
        label = unit.get("label") or labels.get(unit["row"], unit["row"])
        ax.set_title(
            f"{label}: {scene.family} {scene.index} at {unit['speed']:g} m/s, "
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
    from shield_nav.evaluation.rollout import nav_config

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
        scene = make_scene(cfg.scenes.family, idx, nav.scenes.seed)  # the eval's scene seed, if any
        fields = build_fields(scene, resolution=nav.scenes.field_resolution,
                              vehicle_radius=nav.vehicle.airframe.collision_radius)  # fmt: skip
        p = os.path.join(out_dir, f"trajectories_{cfg.scenes.family}-{idx:02d}_v{speed:g}.png")
        plot_trajectories(scene, fields, here, labels, p)
        paths.append(p)
    return paths


class ChaseRecorder:
    """Chase-camera frames of vehicle 0 from MuJoCo's offscreen renderer, with the depth image inset.

    Raises whatever MuJoCo raises when no OpenGL context can be made (the caller falls back to a top-down plot).
    """

    def __init__(self, env: Any, size: tuple[int, int] = (360, 640)) -> None:  # noqa: D107
        import mujoco

        self._mj = mujoco
        self.renderer = mujoco.Renderer(env.vehicles.model, size[0], size[1])
        self.cam = mujoco.MjvCamera()
        self.cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.cam.distance = 2.0
        self.cam.elevation = -15.0
        self.opt = mujoco.MjvOption()
        self.opt.geomgroup[:] = 1  # the vehicle's visual parts are in geom group 3, hidden by default

    def frame(self, env: Any, t: int, shield_active: bool) -> np.ndarray:
        """One RGB frame (H, W, 3) uint8 at the current state of vehicle 0."""
        from PIL import Image, ImageDraw

        r = env.vehicles.R_wb[0]
        self.cam.lookat[:] = env.vehicles.pos_w[0]
        self.cam.azimuth = float(np.degrees(np.arctan2(r[1, 0], r[0, 0])))  # look along the heading, from behind
        self.renderer.update_scene(env.vehicles.data, self.cam, self.opt)
        rgb = self.renderer.render().copy()
        # Depth inset: near = bright (inverse depth), invalid = black, upscaled 2x with nearest neighbours.
        d = env.sensor_depth_buf[0, 0]
        cam = env.cfg.camera
        inv = np.where((d > 0) & (d < cam.max_range), cam.min_range / np.maximum(d, 1e-6), 0.0)
        import matplotlib

        inset = (matplotlib.colormaps["magma"](np.clip(inv, 0, 1))[:, :, :3] * 255).astype(np.uint8)
        inset = inset.repeat(2, axis=0).repeat(2, axis=1)
        h, w = inset.shape[:2]
        rgb[8 : 8 + h, 8 : 8 + w] = inset
        img = Image.fromarray(rgb)
        draw = ImageDraw.Draw(img)
        speed = float(np.linalg.norm(env.vehicles.vel_w[0]))
        text = f"t {t * 0.01:5.2f} s   |v| {speed:4.1f} m/s   target {env.target_speed_buf[0]:.0f} m/s"
        draw.text((8, 12 + h), text + ("   SHIELD ACTIVE" if shield_active else ""), fill=(255, 255, 255))
        return np.asarray(img)


def write_video(frames: list[np.ndarray], base: str, fps: int) -> str:
    """Write frames as ``base.mp4`` (imageio + imageio-ffmpeg) or, without them, ``base.gif`` (Pillow)."""
    try:
        import imageio.v2 as imageio

        path = base + ".mp4"
        imageio.mimwrite(path, frames, fps=fps, macro_block_size=8)
        return path
    except Exception:
        from PIL import Image

        path = base + ".gif"
        imgs = [Image.fromarray(f) for f in frames[::2]]
        imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=int(2000 / fps), loop=0)
        return path


def animate_topdown(scene: Any, fields: Any, trial: dict, path: str, fps: int = 10) -> str:
    """Animated top-down plot of one trial's recorded trajectory over the ESDF (the no-OpenGL fallback)."""
    plt = _plt()
    from matplotlib.animation import FuncAnimation, PillowWriter

    from envs.scenes.plot import draw_scene

    tr = np.asarray(trial["traj"])
    fig, ax = plt.subplots(figsize=(10, 10 * scene.size[1] / scene.size[0] + 0.8), layout="constrained")
    draw_scene(ax, scene, fields)
    (line,) = ax.plot([], [], color="tab:red", lw=1.5)
    (dot,) = ax.plot([], [], "o", color="tab:red")

    def update(k: int) -> tuple:
        line.set_data(tr[: k + 1, 0], tr[: k + 1, 1])
        dot.set_data(tr[k : k + 1, 0], tr[k : k + 1, 1])
        ax.set_title(f"{trial['row']} trial {trial['trial']}: |v| {tr[k, 3]:.1f} m/s ({trial['outcome']})")
        return line, dot

    FuncAnimation(fig, update, frames=len(tr), blit=False).save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path


def trajectory_figures(
    out_dir: str | list[str],
    scenes: list[int],
    speeds: list[float] | None = None,
    rows: list[str] | None = None,
    dest: str | None = None,
    xlim: tuple[float, float] | None = None,
) -> list[str]:
    """Top-down trajectory figures of ``eval.py`` output folders: one PNG per scene in ``scenes``.

    Each figure has a panel per unit (row and speed) of that scene, filtered by ``speeds`` and ``rows`` (default
    all), drawn over the scene the folder flew (its config's scene seed) with :func:`plot_trajectories`. Several
    folders (a list) stack their panels in the order given; they must have flown the same scene (its content
    digest is compared), and a row name flown in more than one of them is labelled with its folder's name too.
    Written to ``dest`` (default ``<first folder>/figures``) as ``trajectories_<family>-<index>_<speeds>.png``.

    Raises:
        FileNotFoundError: A folder has no ``config.yaml`` or no unit files.
        ValueError: A scene, speed or row was not flown in a folder (the message names it and what was flown
            there), the folders flew different scenes under one index, or ``xlim`` is not an increasing pair.
    """
    from envs.fields import build_fields
    from shield_nav.evaluation.config import load_eval_config
    from shield_nav.evaluation.rollout import flown_scene, nav_config

    dirs = [out_dir] if isinstance(out_dir, str) else list(out_dir)
    if not dirs:
        raise ValueError("trajectory_figures: no output folder given")
    if xlim is not None and not (len(xlim) == 2 and all(np.isfinite(xlim)) and xlim[0] < xlim[1]):
        raise ValueError(f"xlim must be two finite numbers lo < hi [m], got {xlim!r}")
    runs = []  # (folder, config, units, labels)
    for d in dirs:
        cfg_path = os.path.join(d, "config.yaml")
        if not os.path.isfile(cfg_path):
            raise FileNotFoundError(f"no config.yaml in {d!r}: not an eval.py output folder")
        files = sorted(glob.glob(os.path.join(d, "units", "*.json")))
        if not files:
            raise FileNotFoundError(f"no unit files under {os.path.join(d, 'units')!r}")
        units = []
        for path in files:
            with open(path) as fh:
                units.append(json.load(fh))
        flown_scenes = sorted({int(u["scene"]) for u in units})
        flown_speeds = sorted({float(u["speed"]) for u in units})
        flown_rows = sorted({u["row"] for u in units})
        for name, want, have in (("scene", scenes, flown_scenes), ("speed", speeds or [], flown_speeds),
                                 ("row", rows or [], flown_rows)):  # fmt: skip
            missing = [w for w in want if w not in have]
            if missing:
                raise ValueError(f"{d}: {name}(s) {missing} not flown there; flown: {have}")
        labels: dict[str, str] = {}
        summary_path = os.path.join(d, "summary.json")
        if os.path.isfile(summary_path):  # a finished run names its rows' labels (a stopped one flies without)
            with open(summary_path) as fh:
                labels = {k: r.get("label") or k for k, r in json.load(fh).get("rows", {}).items()}
        runs.append((d, load_eval_config(cfg_path), units, labels))
    row_dirs: dict[str, set[str]] = {}
    for d, _, units, _ in runs:
        for u in units:
            row_dirs.setdefault(u["row"], set()).add(d)
    dest = dest or os.path.join(dirs[0], "figures")
    os.makedirs(dest, exist_ok=True)
    paths = []
    for idx in scenes:
        panels, scene, nav = [], None, None
        for d, cfg, units, labels in runs:
            here = [u for u in units if int(u["scene"]) == idx and (not speeds or float(u["speed"]) in speeds)
                    and (not rows or u["row"] in rows)]  # fmt: skip
            if not here:
                raise ValueError(f"{d}: scene {idx} was not flown at speeds {speeds} by rows {rows}")
            here.sort(key=lambda u: (u["row"], float(u["speed"])))
            family = here[0]["family"]
            flown = flown_scene(cfg, family, idx)
            if scene is None:
                scene, nav = flown, nav_config(cfg, family, idx, float(here[0]["speed"]), 1)
            elif flown.digest() != scene.digest():
                raise ValueError(f"{d} flew another scene as {family} {idx} than {dirs[0]} (another family or "
                                 "scene seed): their flights cannot share a figure")  # fmt: skip
            for u in here:
                name = labels.get(u["row"], u["row"])
                if len(row_dirs[u["row"]]) > 1:
                    name = f"{name} ({os.path.basename(os.path.normpath(d))})"
                panels.append({**u, "label": name})
        fields = build_fields(scene, resolution=nav.scenes.field_resolution,
                              vehicle_radius=nav.vehicle.airframe.collision_radius)  # fmt: skip
        tag = "_".join(f"v{v:g}" for v in sorted({float(u["speed"]) for u in panels}))
        path = os.path.join(dest, f"trajectories_{scene.family}-{idx:02d}_{tag}.png")
        plot_trajectories(scene, fields, panels, {}, path, xlim=xlim)
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> None:
    """CLI entry point (see the module docstring)."""
    ap = argparse.ArgumentParser(description="Top-down trajectories of chosen scenes of eval.py output folders")
    ap.add_argument("out_dirs", nargs="+", help="eval.py output folders (eval_out/<name>); several stack their panels")
    ap.add_argument("--scenes", required=True, help="comma-separated scene indices, e.g. 12,13")
    ap.add_argument("--speeds", default="", help="comma-separated target speeds (default: all flown)")
    ap.add_argument("--rows", default="", help="comma-separated rows (default: all flown)")
    ap.add_argument("--xlim", default="", help="x range drawn [m], LO,HI (default: the whole scene)")
    ap.add_argument("--out", default=None, help="folder for the PNGs (default: <first folder>/figures)")
    a = ap.parse_args(argv)
    try:
        scenes = [int(x) for x in a.scenes.split(",") if x]
        speeds = [float(x) for x in a.speeds.split(",") if x] or None
    except ValueError:
        ap.error(f"--scenes must be integers and --speeds numbers, got {a.scenes!r} and {a.speeds!r}")
    xlim = None
    if a.xlim:
        try:
            lo, hi = (float(x) for x in a.xlim.split(","))
        except ValueError:
            ap.error(f"--xlim must be two numbers LO,HI, got {a.xlim!r}")
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            ap.error(f"--xlim must be finite with LO < HI, got {a.xlim!r}")
        xlim = (lo, hi)
    if not scenes:
        ap.error("--scenes names no scene")
    rows = [r for r in a.rows.split(",") if r] or None
    for p in trajectory_figures(a.out_dirs, scenes, speeds, rows, a.out, xlim):
        print(p)


if __name__ == "__main__":
    main()
