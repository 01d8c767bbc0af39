"""``build_fields``: a scene's privileged fields, with an on-disk cache.

Cache: one ``<key>.npz`` file per (scene, resolution, vehicle radius, stencil, format version), where ``key`` is
the SHA-256 of that tuple serialised as canonical JSON (the scene through :meth:`Scene.to_dict`). The file holds
the ESDF and Phi (float32) and a JSON metadata string; the gradient is recomputed on load (cheap). Directory:
``cache_dir`` if given, else ``$SHIELD_NAV_CACHE``, else ``~/.cache/shield_nav/fields``. Files are written to a
temporary name and renamed, so concurrent builders never read half a file.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from envs.fields.esdf import Grid, add_floor_ceiling, esdf_gradient, obstacle_esdf
from envs.fields.geodesic import geodesic_field
from envs.fields.lookup import FieldStack
from envs.scenes.scene import Scene

FIELDS_FORMAT_VERSION = 1
"""Bump to invalidate every cached field file (part of the cache key)."""

DEFAULT_RESOLUTION = 0.1
"""Default node spacing (m)."""

DEFAULT_VEHICLE_RADIUS = 0.2
"""Default vehicle radius (m) inflating obstacles for the geodesic field (half the paper's doubled 0.4 m margin)."""

DEFAULT_STENCIL = "extended"
"""Default Dijkstra stencil (see :mod:`envs.fields.geodesic`)."""


def default_cache_dir() -> Path:
    """``$SHIELD_NAV_CACHE`` if set, else ``~/.cache/shield_nav/fields``."""
    env = os.environ.get("SHIELD_NAV_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "shield_nav" / "fields"


@dataclass
class SceneFields:
    """The privileged fields of one scene on a node-centred grid (see :mod:`envs.fields.esdf`).

    Attributes:
        origin: World position (3,) of node (0, 0, 0) (the scene's ``bounds_lo``).
        res: Node spacing (m).
        shape: ``(nx, ny, nz)``.
        vehicle_radius: Radius (m) obstacles were inflated by for Phi.
        esdf: Signed distance (nx, ny, nz) float32, metres, negative inside; includes floor and ceiling.
        grad: ESDF gradient (nx, ny, nz, 3) float32.
        phi: Geodesic distance to the goal region (nx, ny, nz) float32, metres, finite everywhere.
        phi_unreachable: The value given to traversable nodes that cannot reach the goal (m).
        info: Build facts: digest, build seconds, occupancy/ESDF statistics, cache hit or not.
    """

    origin: tuple[float, float, float]
    res: float
    shape: tuple[int, int, int]
    vehicle_radius: float
    esdf: np.ndarray
    grad: np.ndarray
    phi: np.ndarray
    phi_unreachable: float
    info: dict = field(default_factory=dict)

    @property
    def grid(self) -> Grid:
        """The grid the fields are sampled on."""
        return Grid(self.origin, self.res, self.shape)

    @property
    def occupancy(self) -> np.ndarray:
        """Occupied nodes (ESDF <= 0, floor and ceiling included), bool (nx, ny, nz)."""
        return self.esdf <= 0.0

    @property
    def traversable(self) -> np.ndarray:
        """Nodes the vehicle centre may occupy (ESDF > vehicle radius), bool (nx, ny, nz)."""
        return self.esdf > self.vehicle_radius

    def stack(self) -> FieldStack:
        """A one-scene :class:`FieldStack` (scene id 0) for lookups."""
        return FieldStack([self])


def cache_key(scene: Scene, resolution: float, vehicle_radius: float, stencil: str) -> str:
    """SHA-256 hex key of everything the fields depend on."""
    blob = json.dumps(
        {
            "scene": scene.to_dict(),
            "resolution": float(resolution),
            "vehicle_radius": float(vehicle_radius),
            "stencil": stencil,
            "version": FIELDS_FORMAT_VERSION,
        },
        sort_keys=True,
        separators=(",", ":"),
    )
    return hashlib.sha256(blob.encode()).hexdigest()


def region_mask(grid: Grid, region: tuple) -> np.ndarray:
    """Nodes inside the closed box ``region = (lo, hi)``, bool (nx, ny, nz)."""
    lo, hi = np.asarray(region[0]), np.asarray(region[1])
    eps = 1e-6
    ax = [(grid.axis(k) >= lo[k] - eps) & (grid.axis(k) <= hi[k] + eps) for k in range(3)]
    return ax[0][:, None, None] & ax[1][None, :, None] & ax[2][None, None, :]


def build_fields(
    scene: Scene,
    resolution: float = DEFAULT_RESOLUTION,
    vehicle_radius: float = DEFAULT_VEHICLE_RADIUS,
    cache_dir: str | os.PathLike | None = None,
    use_cache: bool = True,
    stencil: str = DEFAULT_STENCIL,
) -> SceneFields:
    """Occupancy, signed ESDF (+ gradient) and geodesic field Phi of ``scene``, cached on disk.

    Args:
        scene: The scene (static primitives, floor, ceiling; moving obstacles are ignored).
        resolution: Node spacing in metres.
        vehicle_radius: Obstacle inflation (m) for Phi's traversable space; 0 allowed, negative is an error.
        cache_dir: Cache directory (default :func:`default_cache_dir`).
        use_cache: Read and write the cache (``False``: always build, write nothing).
        stencil: Dijkstra stencil, ``"extended"`` (default) or ``"26"``.

    Raises:
        ValueError: Non-positive resolution, negative vehicle radius, or a goal region with no traversable node.
    """
    _check_resolution(resolution)
    if not (math.isfinite(vehicle_radius) and vehicle_radius >= 0):
        raise ValueError(f"vehicle_radius must be a non-negative number of metres, got {vehicle_radius}")
    key = cache_key(scene, resolution, vehicle_radius, stencil)
    path = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    file = path / f"{key[:40]}.npz"
    grid = Grid.for_scene(scene, resolution)
    if use_cache and file.is_file():
        try:
            return _load(file, grid, vehicle_radius)
        except (OSError, ValueError, KeyError) as err:  # corrupt or foreign file: rebuild and overwrite
            print(f"[fields] ignoring unreadable cache file {file}: {err}")
    t0 = time.perf_counter()
    report(f"{scene.family}/{scene.index}: building ESDF and geodesic field (cold cache) ...")
    fields = _build(scene, grid, vehicle_radius, stencil)
    report(f"{scene.family}/{scene.index}: ESDF and geodesic field built in {time.perf_counter() - t0:.1f} s", True)
    fields.info["cache_key"] = key
    if use_cache:
        _save(file, fields)
    return fields


def _check_resolution(resolution: float) -> None:
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"field resolution must be a positive number of metres, got {resolution}")


def scene_field_stack(
    scenes: Sequence[Scene],
    resolution: float = DEFAULT_RESOLUTION,
    vehicle_radius: float = DEFAULT_VEHICLE_RADIUS,
    cache_dir: str | os.PathLike | None = None,
    stencil: str = DEFAULT_STENCIL,
    lazy: bool = True,
) -> FieldStack:
    """A :class:`FieldStack` over ``scenes`` (scene id = position in the list), fields from :func:`build_fields`.

    ``lazy``: a scene is built (or read from the cache) on the first query that names it, so an env starts with only
    the scenes it flies; otherwise all are built now.
    """
    scenes = list(scenes)
    _check_resolution(resolution)

    def build(s: int) -> SceneFields:
        return build_fields(scenes[s], resolution, vehicle_radius, cache_dir=cache_dir, stencil=stencil)

    if not lazy:
        return FieldStack([build(s) for s in range(len(scenes))])
    return FieldStack.lazy([Grid.for_scene(sc, resolution) for sc in scenes], build)


def report(message: str, done: bool = False) -> None:
    """One progress line of a field build on stderr, so a cold start never looks hung.

    On a terminal the line is rewritten in place; otherwise only ``done`` lines are printed.
    """
    if sys.stderr.isatty():
        sys.stderr.write(f"\r\033[K[fields] {message}" + ("\n" if done else ""))
        sys.stderr.flush()
    elif done:
        print(f"[fields] {message}", file=sys.stderr, flush=True)


def _build(scene: Scene, grid: Grid, vehicle_radius: float, stencil: str) -> SceneFields:
    t0 = time.perf_counter()
    esdf_obs = obstacle_esdf(scene, grid)
    t_esdf = time.perf_counter() - t0
    # Statistics on the obstacle-only ESDF (floor and ceiling excluded), as the paper's difficulty measure.
    free_obs = esdf_obs > 0.0
    info = {
        "digest": scene.digest(),
        "occupied_fraction": float(1.0 - free_obs.mean()),
        "median_free_esdf": float(np.median(esdf_obs[free_obs])) if free_obs.any() else 0.0,
    }
    esdf = add_floor_ceiling(scene, grid, esdf_obs)
    del esdf_obs, free_obs
    grad = esdf_gradient(esdf, grid.res)
    t1 = time.perf_counter()
    goal = region_mask(grid, scene.goal_region)
    if not (goal & (esdf > vehicle_radius)).any():
        raise ValueError(
            f"goal region {scene.goal_region} of scene {scene.family}/{scene.index} is fully blocked: no point in it "
            f"is more than vehicle_radius={vehicle_radius} m from an obstacle"
        )
    diag = float(np.linalg.norm(scene.size))
    phi, phi_unreachable, reachable = geodesic_field(esdf > vehicle_radius, goal, grid.res, diag, stencil)
    start = region_mask(grid, scene.start_region) & (esdf > vehicle_radius)
    info.update(
        {
            "start_reachable_fraction": float(reachable[start].mean()) if start.any() else 0.0,
            "build_s_esdf": t_esdf,
            "build_s_geodesic": time.perf_counter() - t1,
            "build_s": time.perf_counter() - t0,
            "cache_hit": False,
        }
    )
    return SceneFields(grid.origin, grid.res, grid.shape, float(vehicle_radius), esdf, grad, phi, phi_unreachable, info)


def _save(file: Path, fields: SceneFields) -> None:
    file.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "origin": list(fields.origin),
        "res": fields.res,
        "shape": list(fields.shape),
        "vehicle_radius": fields.vehicle_radius,
        "phi_unreachable": fields.phi_unreachable,
        "info": fields.info,
        "version": FIELDS_FORMAT_VERSION,
    }
    fd, tmp = tempfile.mkstemp(dir=file.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, esdf=fields.esdf, phi=fields.phi, meta=np.array(json.dumps(meta)))
        os.replace(tmp, file)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _load(file: Path, grid: Grid, vehicle_radius: float) -> SceneFields:
    t0 = time.perf_counter()
    with np.load(file) as z:
        meta = json.loads(str(z["meta"]))
        esdf, phi = z["esdf"], z["phi"]
    if meta["version"] != FIELDS_FORMAT_VERSION or tuple(meta["shape"]) != grid.shape or esdf.shape != grid.shape:
        raise ValueError("cache file does not match the requested grid")
    info = dict(meta["info"])
    info["cache_hit"] = True
    info["load_s"] = time.perf_counter() - t0
    grad = esdf_gradient(esdf, grid.res)
    return SceneFields(
        tuple(meta["origin"]), float(meta["res"]), tuple(meta["shape"]), float(vehicle_radius),
        esdf, grad, phi, float(meta["phi_unreachable"]), info,
    )  # fmt: skip
