"""Top-down scene figures: obstacles, ESDF shading, geodesic contours, start and goal regions.

:func:`draw_scene` draws onto a caller's matplotlib ``Axes`` (x to the right, y up, metres) so the evaluation
harness can overlay trajectories afterwards; :func:`save_scene_png` is the one-call PNG helper.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from envs.scenes.primitives import Box, Sphere
from envs.scenes.scene import Scene


def _footprint_polygon(prim: Any) -> np.ndarray:
    """Outline (M, 2) in the xy plane of a primitive's full projection seen from above."""
    from envs.scenes.scene import primitive_mesh

    if isinstance(prim, Sphere):
        t = np.linspace(0, 2 * np.pi, 24)
        return np.asarray(prim.center[:2]) + prim.radius * np.stack([np.cos(t), np.sin(t)], axis=1)
    if isinstance(prim, Box):
        corners = np.array([[sx, sy, 0.0] for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]) * np.asarray(prim.half)
        return (corners @ prim.rotation().T)[:, :2] + np.asarray(prim.center[:2])
    verts = primitive_mesh(prim).vertices[:, :2]
    from scipy.spatial import ConvexHull

    hull = ConvexHull(verts)
    return verts[hull.vertices]


def draw_scene(
    ax: Any,
    scene: Scene,
    fields: Any | None = None,
    z: float | None = None,
    esdf_max: float = 2.0,
    contour_step: float = 4.0,
    show_moving: bool = True,
) -> Any:
    """Draw a top-down view of ``scene`` on ``ax``.

    Args:
        ax: A matplotlib Axes.
        scene: The scene.
        fields: Optional :class:`envs.fields.SceneFields`: adds ESDF shading and geodesic contours, taken in the
            horizontal slice nearest ``z``.
        z: Slice height (m); default the middle of the start region.
        esdf_max: ESDF value (m) at which the shading saturates.
        contour_step: Spacing (m) of the geodesic contour lines.
        show_moving: Draw moving obstacles at t = 0 with velocity arrows.

    Returns:
        The ESDF image artist (for a colour bar) or None without fields.
    """
    from matplotlib.patches import Polygon, Rectangle

    lo, hi = scene.bounds_lo, scene.bounds_hi
    if z is None:
        z = 0.5 * (scene.start_region[0][2] + scene.start_region[1][2])
    img = None
    if fields is not None:
        k = int(np.clip(round((z - fields.origin[2]) / fields.res), 0, fields.shape[2] - 1))
        extent = (
            fields.origin[0] - 0.5 * fields.res,
            fields.origin[0] + (fields.shape[0] - 0.5) * fields.res,
            fields.origin[1] - 0.5 * fields.res,
            fields.origin[1] + (fields.shape[1] - 0.5) * fields.res,
        )
        esdf = fields.esdf[:, :, k].T
        img = ax.imshow(
            np.clip(esdf, 0.0, esdf_max), origin="lower", extent=extent, cmap="viridis", vmin=0, vmax=esdf_max
        )
        phi = np.where(fields.phi[:, :, k] < fields.phi_unreachable, fields.phi[:, :, k], np.nan).T
        xs = fields.origin[0] + fields.res * np.arange(fields.shape[0])
        ys = fields.origin[1] + fields.res * np.arange(fields.shape[1])
        if np.isfinite(phi).any():
            levels = np.arange(0.0, np.nanmax(phi) + contour_step, contour_step)
            ax.contour(xs, ys, phi, levels=levels, colors="white", linewidths=0.4, alpha=0.7)
    for prim in scene.primitives:
        poly = _footprint_polygon(prim)
        ax.add_patch(Polygon(poly, closed=True, facecolor="0.25", edgecolor="black", linewidth=0.3, alpha=0.85))
    if show_moving and scene.moving:
        pos = scene.moving_positions(0.0)
        for mob, p in zip(scene.moving, pos, strict=True):
            t = np.linspace(0, 2 * np.pi, 24)
            circ = p[:2] + mob.cylinder.radius * np.stack([np.cos(t), np.sin(t)], axis=1)
            ax.add_patch(Polygon(circ, closed=True, facecolor="tab:red", edgecolor="black", linewidth=0.3))
            ax.arrow(p[0], p[1], mob.velocity[0], mob.velocity[1], color="tab:red", width=0.05, head_width=0.3)
    regions = ((scene.start_region, "tab:green", "start"), (scene.goal_region, "tab:orange", "goal"))
    for (r_lo, r_hi), color, label in regions:
        ax.add_patch(
            Rectangle(
                r_lo[:2], r_hi[0] - r_lo[0], r_hi[1] - r_lo[1], facecolor=color, alpha=0.35, edgecolor=color,
                label=label,
            )
        )  # fmt: skip
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{scene.family} {scene.index}  ({len(scene.primitives)} primitives)")
    return img


def save_scene_png(
    scene: Scene, path: str | os.PathLike, fields: Any | None = None, dpi: int = 110, **kwargs: Any
) -> None:
    """Save :func:`draw_scene` of ``scene`` (with ``fields`` shading if given) as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w = 10.0
    h = w * scene.size[1] / scene.size[0] + 1.0
    fig, ax = plt.subplots(figsize=(w, h))
    img = draw_scene(ax, scene, fields, **kwargs)
    if img is not None:
        fig.colorbar(img, ax=ax, fraction=0.025, pad=0.01, label="ESDF [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
