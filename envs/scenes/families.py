"""Scene families: deterministic procedural generators and the train/evaluation seed split.

``make_scene(family, index, seed)`` is a pure function of its arguments. Every family draws all of its
randomness from ``np.random.default_rng(SeedSequence([seed, family_id, index]))``.

Seed split (enforced, tested): the training family only accepts seeds in :data:`TRAIN_SEEDS`, every evaluation
family only seeds in :data:`EVAL_SEEDS`; the two ranges are disjoint, and the family id is mixed into the
entropy as well, so no training scene can share a random stream with an evaluation scene.

Difficulty rises with the index in every family through a level ``u = index / (size - 1)`` in [0, 1]: more
obstacles and a smaller minimum clearance between their footprints (see :mod:`envs.scenes.composites`; the
clearance never drops below :data:`MIN_GAP`, which keeps the geometric scenes traversable by construction).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from envs.scenes import composites as C
from envs.scenes.perlin import merge_cells, perlin2d
from envs.scenes.primitives import Box, Capsule, Cylinder, Primitive
from envs.scenes.scene import MovingObstacle, Scene, default_goal_region, default_start_region

TRAIN_SEEDS = range(0, 1_000_000)
"""Seeds the training family accepts."""
EVAL_SEEDS = range(1_000_000, 2_000_000)
"""Seeds every evaluation family (ablation, benchmark, dynamic, forest, traps) accepts. Disjoint from TRAIN_SEEDS."""

MIN_GAP = 0.6
"""Smallest footprint clearance (m) any geometric family uses: 1.5x the diameter of a 0.2 m vehicle."""

OBSTACLE_X_MARGIN = 4.0
"""Obstacles keep this distance (m) from the start and goal ends of the scene."""


@dataclass(frozen=True)
class Family:
    """A registered scene family.

    Attributes:
        name: Family name (``make_scene``'s first argument).
        size: Number of scenes; valid indices are ``0 .. size-1``.
        split: ``"train"`` or ``"eval"``: which seed range the family accepts.
        default_seed: Base seed used when ``make_scene`` gets ``seed=None``.
        family_id: Integer mixed into the RNG entropy (unique per family).
        description: One line for docs and the stats CLI.
        generate: ``generate(rng, index, u) -> dict`` of Scene keyword arguments.
    """

    name: str
    size: int
    split: str
    default_seed: int
    family_id: int
    description: str
    generate: Callable[[np.random.Generator, int, float], dict]


# --------------------------------------------------------------------------- geometric clutter


def _clutter(
    rng: np.random.Generator,
    placer: C.Placer,
    weights: dict[str, float],
    n: int,
    z_lo: float,
    z_hi: float,
    max_failures: int = 30,
) -> list[Primitive]:
    """Place ``n`` obstacles whose kinds are drawn from ``weights`` (stops early if the scene saturates)."""
    kinds = list(weights)
    p = np.array([weights[k] for k in kinds], dtype=float)
    p /= p.sum()
    prims: list[Primitive] = []
    placed = failures = 0
    while placed < n and failures < max_failures:
        kind = kinds[rng.choice(len(kinds), p=p)]
        make, hint = _maker(rng, kind, z_lo, z_hi)
        got = placer.place(make, hint)
        if got:
            prims.extend(got)
            placed += 1
            failures = 0
        else:
            failures += 1
    return prims


def _maker(rng: np.random.Generator, kind: str, z_lo: float, z_hi: float) -> tuple[Callable, float]:
    """A ``make(x, y)`` closure for one obstacle of ``kind`` with its size parameters drawn now."""
    H = z_hi - z_lo
    if kind == "vcyl":
        r = rng.uniform(0.15, 0.5)
        return (lambda x, y: C.vertical_cylinder(x, y, r, z_lo, z_hi)), r
    if kind == "icyl":
        r, tilt, head = rng.uniform(0.1, 0.3), np.deg2rad(rng.uniform(10, 35)), rng.uniform(0, 2 * np.pi)
        return (lambda x, y: C.inclined_segment(Cylinder, x, y, r, tilt, head, z_lo, z_hi)), 1.0
    if kind == "pole":
        r, tilt, head = rng.uniform(0.03, 0.06), np.deg2rad(rng.choice([0.0, rng.uniform(5, 30)])), rng.uniform(0, 6.3)
        if tilt == 0.0:
            return (lambda x, y: C.vertical_cylinder(x, y, r, z_lo, z_hi)), r
        return (lambda x, y: C.inclined_segment(Capsule, x, y, r, tilt, head, z_lo, z_hi)), 1.0
    if kind == "box":
        hx, hy, yaw = rng.uniform(0.2, 0.8), rng.uniform(0.2, 0.8), rng.uniform(0, np.pi)
        return (lambda x, y: C.box_column(x, y, hx, hy, yaw, z_lo, z_hi)), math.hypot(hx, hy)
    if kind == "wall":
        hx, hy, yaw = rng.uniform(1.0, 2.5), rng.uniform(0.08, 0.15), rng.uniform(0, np.pi)
        return (lambda x, y: C.box_column(x, y, hx, hy, yaw, z_lo, z_hi)), hx
    if kind == "sphere":
        r = rng.uniform(0.3, 0.7)
        z = rng.uniform(z_lo + r, z_hi - r)
        return (lambda x, y: C.sphere_blob(x, y, z, r)), r
    if kind == "frame":
        width, yaw = rng.uniform(1.2, 2.2), rng.uniform(0.5 * np.pi - 0.6, 0.5 * np.pi + 0.6)
        if rng.random() < 0.5:  # door: one bar high up
            bars: tuple[float, ...] = (z_lo + rng.uniform(0.55, 0.8) * H,)
        else:  # window: a low and a high bar
            bars = (z_lo + rng.uniform(0.2, 0.35) * H, z_lo + rng.uniform(0.7, 0.85) * H)
        return (lambda x, y: C.frame(x, y, width, yaw, z_lo, z_hi, bars)), 0.5 * width
    if kind == "utrap":
        w, d, yaw = rng.uniform(1.5, 3.0), rng.uniform(1.5, 3.5), rng.uniform(-0.5, 0.5)
        return (lambda x, y: C.u_trap(x, y, w, d, yaw, z_lo, z_hi)), 0.5 * math.hypot(w, d) + 0.3
    if kind == "deadend":  # a long, narrow U: a corridor that ends in a wall
        w, d, yaw = rng.uniform(1.2, 1.8), rng.uniform(4.0, 7.0), rng.uniform(-0.3, 0.3)
        return (lambda x, y: C.u_trap(x, y, w, d, yaw, z_lo, z_hi)), 0.5 * d + 0.5
    if kind == "tree":
        tr, cr, clo = rng.uniform(0.1, 0.25), rng.uniform(0.4, 0.9), z_lo + rng.uniform(0.4, 0.7) * H
        return (lambda x, y: C.tree(x, y, tr, cr, clo, z_lo, z_hi)), cr
    raise ValueError(f"unknown obstacle kind {kind!r}")


def _placer(rng: np.random.Generator, lo: tuple, hi: tuple, gap: float) -> C.Placer:
    return C.Placer(rng, (lo[0] + OBSTACLE_X_MARGIN, hi[0] - OBSTACLE_X_MARGIN), (lo[1], hi[1]), gap)


def _lerp(a: float, b: float, u: float) -> float:
    return a + (b - a) * u


LO, HI = (0.0, -16.0, 0.0), (64.0, 16.0, 3.0)


def _gen_train(rng: np.random.Generator, index: int, u: float) -> dict:
    # Trees and cylinders only; density rises with the level (paper, "Training Results").
    gap = _lerp(1.6, MIN_GAP, u)
    placer = _placer(rng, LO, HI, gap)
    n = int(round(_lerp(40, 330, u)))
    prims = _clutter(rng, placer, {"tree": 0.55, "vcyl": 0.45}, n, LO[2], HI[2])
    return {"primitives": tuple(prims)}


TRAIN_SHAPES_KINDS = {
    "tree": 0.22, "vcyl": 0.18, "icyl": 0.14, "pole": 0.12, "frame": 0.12, "box": 0.08, "wall": 0.08, "sphere": 0.06,
}  # fmt: skip
"""Obstacle mix of the ``train_shapes`` family: the training family's trees and cylinders plus every other kind."""


def _gen_train_shapes(rng: np.random.Generator, index: int, u: float) -> dict:
    # Not the paper's training set (trees and cylinders only): the same density ramp over every obstacle kind the
    # evaluation families use, with U-traps from level 5 and dead ends from level 8. Seeds stay in the training
    # range, so the evaluation scenes remain held out; only their obstacle kinds are no longer unseen.
    gap = _lerp(1.6, MIN_GAP, u)
    placer = _placer(rng, LO, HI, gap)
    prims = _clutter(rng, placer, {"utrap": 1.0}, max(0, round(_lerp(-1.0, 4.0, u))), LO[2], HI[2])
    prims += _clutter(rng, placer, {"deadend": 1.0}, max(0, round(_lerp(-0.5, 2.0, u))), LO[2], HI[2])
    prims += _clutter(rng, placer, TRAIN_SHAPES_KINDS, int(round(_lerp(40, 330, u))), LO[2], HI[2])
    return {"primitives": tuple(prims)}


def _gen_ablation(rng: np.random.Generator, index: int, u: float) -> dict:
    # Inclined and vertical cylinders, frames, thin poles; U-traps and dead-end corridors are always present
    # (placed first so the scene never saturates before they fit).
    placer = _placer(rng, LO, HI, _lerp(0.9, MIN_GAP, u))
    prims = _clutter(rng, placer, {"utrap": 1.0}, 2 + index // 3, LO[2], HI[2])
    prims += _clutter(rng, placer, {"deadend": 1.0}, 1 + index // 4, LO[2], HI[2])
    weights = {"icyl": 0.3, "vcyl": 0.2, "frame": 0.25, "pole": 0.25}
    prims += _clutter(rng, placer, weights, int(round(_lerp(170, 300, u))), LO[2], HI[2])
    return {"primitives": tuple(prims)}


TRAP_COLUMNS_X = (16.0, 32.0, 48.0)
"""x of the three columns of wide cups in the ``traps`` family [m]."""


def _gen_traps(rng: np.random.Generator, index: int, u: float) -> dict:
    # Not in the paper: a probe of global guidance. Three columns of wide U-traps (inner width 4.5-7 m, depth
    # 3-5 m, opening towards the start) across the flight direction, staggered, with gaps of at least MIN_GAP
    # between their footprints, so a straight line from the start runs into a cup in most trials, and the route
    # around them is 1.1-1.3x the straight distance. Sparse clutter fills the rest; it is placed after the cups
    # and keeps out of their footprint circles, so every cup is an empty dead end. Where the ``ablation`` scenes'
    # smaller traps sit off the routes a local avoider takes (docs/lab-log.md, "Do these scenes reward global
    # guidance?"), here the Euclidean distance's local minima lie on them. ``train_traps`` draws the same layout
    # from training seeds (16 levels), so the ``traps`` scenes stay held out.
    placer = _placer(rng, LO, HI, MIN_GAP)
    prims: list[Primitive] = []
    for xc in TRAP_COLUMNS_X:
        y = LO[1] + rng.uniform(0.0, 4.0)  # lower edge of the next cup's footprint circle
        while True:
            w, d = rng.uniform(4.5, 7.0), _lerp(3.0, 5.0, u) + rng.uniform(-0.5, 0.5)
            r = math.hypot(0.5 * d + 0.2, 0.5 * w + 0.2)  # u_trap's footprint radius (0.2 m walls)
            if y + 2 * r > HI[1]:
                break
            cup, fp = C.u_trap(xc + rng.uniform(-2.0, 2.0), y + r, w, d, rng.uniform(-0.15, 0.15), LO[2], HI[2])
            if placer.free(fp):
                placer.add(fp)
                prims.extend(cup)
            y += 2 * r + rng.uniform(MIN_GAP, 2.5)
    weights = {"tree": 0.3, "vcyl": 0.3, "icyl": 0.2, "pole": 0.2}
    prims += _clutter(rng, placer, weights, int(round(_lerp(40, 140, u))), LO[2], HI[2])
    return {"primitives": tuple(prims)}


BENCH_GEOMETRIC = 12
"""Benchmark indices ``0 .. 11`` are geometric clutter, ``12 .. 15`` Perlin-noise fields."""


def _gen_benchmark(rng: np.random.Generator, index: int, u: float) -> dict:
    if index >= BENCH_GEOMETRIC:
        return _gen_perlin(rng, (index - BENCH_GEOMETRIC) / 3.0)
    ug = index / (BENCH_GEOMETRIC - 1)
    placer = _placer(rng, LO, HI, _lerp(1.2, MIN_GAP, ug))
    prims = _clutter(rng, placer, {"utrap": 0.5, "deadend": 0.5}, 1 + index // 4, LO[2], HI[2])
    # Harder levels: more obstacles and a larger share of bulky ones (boxes, walls), fewer thin poles.
    weights = {
        "vcyl": 0.22, "icyl": 0.16, "box": 0.14 + 0.16 * ug, "wall": 0.08 + 0.12 * ug, "sphere": 0.08,
        "frame": 0.1, "pole": 0.2 - 0.1 * ug,
    }  # fmt: skip
    n = int(round(_lerp(150, 520, ug**1.2)))
    prims += _clutter(rng, placer, weights, n, LO[2], HI[2])
    return {"primitives": tuple(prims)}


PERLIN_CELL = 0.5
"""Lattice cell (m) of the Perlin obstacle fields."""


def _gen_perlin(rng: np.random.Generator, u: float) -> dict:
    """Full-height box columns where fractal Perlin noise exceeds a threshold; occupancy rises with ``u``.

    The threshold is the noise quantile giving the target occupied fraction. If no route with clearance above
    :data:`PERLIN_CLEARANCE` links the start side to the goal side, the target fraction is lowered by 0.02 and
    the threshold recomputed, until one does.
    """
    x0, x1 = LO[0] + OBSTACLE_X_MARGIN, HI[0] - OBSTACLE_X_MARGIN
    xs = np.arange(x0 + 0.5 * PERLIN_CELL, x1, PERLIN_CELL)
    ys = np.arange(LO[1] + 0.5 * PERLIN_CELL, HI[1], PERLIN_CELL)
    noise = perlin2d(rng, xs, ys, scale=_lerp(4.0, 2.5, u), octaves=3)
    frac = _lerp(0.2, 0.36, u)
    while True:
        occ = noise > np.quantile(noise, 1.0 - frac)
        if _perlin_passable(occ):
            break
        frac -= 0.02
    prims: list[Primitive] = []
    zc, hz = 0.5 * (LO[2] + HI[2]), 0.5 * (HI[2] - LO[2])
    for i0, j0, i1, j1 in merge_cells(occ):
        cx = x0 + 0.5 * (i0 + i1) * PERLIN_CELL
        cy = LO[1] + 0.5 * (j0 + j1) * PERLIN_CELL
        prims.append(Box((cx, cy, zc), (0.5 * (i1 - i0) * PERLIN_CELL, 0.5 * (j1 - j0) * PERLIN_CELL, hz)))
    return {"primitives": tuple(prims)}


PERLIN_CLEARANCE = 0.35
"""Required free-space clearance (m) along some start-to-goal route of a Perlin field (vehicle 0.2 m + slack)."""


def _perlin_passable(occ: np.ndarray, up: int = 5) -> bool:
    """Whether a route with clearance > PERLIN_CLEARANCE links the first and last x columns of the lattice.

    The cell grid is refined ``up`` times (0.1 m), distances to occupied cells come from the exact EDT, and
    the points with enough clearance are labelled (8-connected) to see if one component touches both ends.
    """
    fine = np.repeat(np.repeat(occ, up, axis=0), up, axis=1)
    clear = ndimage.distance_transform_edt(~fine, sampling=PERLIN_CELL / up) > PERLIN_CLEARANCE
    labels, _ = ndimage.label(clear, structure=np.ones((3, 3), dtype=bool))
    first, last = set(labels[0][clear[0]].tolist()), set(labels[-1][clear[-1]].tolist())
    return bool(first & last)


def _gen_dynamic(rng: np.random.Generator, index: int, u: float) -> dict:
    # Moderate static clutter plus vertical cylinders moving at 0.5 .. 2 m/s, bouncing inside the bounds.
    placer = _placer(rng, LO, HI, 1.0)
    weights = {"vcyl": 0.35, "icyl": 0.2, "box": 0.2, "pole": 0.25}
    prims = _clutter(rng, placer, weights, int(round(_lerp(70, 140, u))), LO[2], HI[2])
    moving = []
    for _ in range(int(round(_lerp(8, 20, u)))):
        r = rng.uniform(0.2, 0.45)
        x = rng.uniform(LO[0] + OBSTACLE_X_MARGIN, HI[0] - OBSTACLE_X_MARGIN)
        y = rng.uniform(LO[1] + r, HI[1] - r)
        speed, heading = rng.uniform(0.5, _lerp(1.5, 2.5, u)), rng.uniform(0, 2 * np.pi)
        moving.append(
            MovingObstacle(
                Cylinder((x, y, LO[2]), (x, y, HI[2]), r), (speed * math.cos(heading), speed * math.sin(heading))
            )
        )
    return {"primitives": tuple(prims), "moving": tuple(moving)}


TRAIN_PERLIN_FIELDS = 8
"""``train_shapes_perlin``: indices ``16 .. 23`` are Perlin-noise fields (occupancy rising), ``0 .. 15`` all-shapes."""


def _gen_train_shapes_perlin(rng: np.random.Generator, index: int, u: float) -> dict:
    # Not the paper's training set: the all-shapes levels (the train_shapes generator, its own random stream) plus
    # the benchmark's second kind of scene, Perlin-noise fields of full-height box columns, at training seeds. Meant
    # for uniform sampling (curriculum off): the indices are two difficulty ramps, not one.
    n_shapes = 16
    if index < n_shapes:
        return _gen_train_shapes(rng, index, index / (n_shapes - 1))
    return _gen_perlin(rng, (index - n_shapes) / (TRAIN_PERLIN_FIELDS - 1))


FOREST_LO, FOREST_HI = (0.0, -16.0, 0.0), (100.0, 16.0, 4.0)


def _gen_forest(rng: np.random.Generator, index: int, u: float) -> dict:
    # Sparse, long, outdoor-like: trees with high canopies and some bare trunks, 100 m long, 4 m tall.
    placer = _placer(rng, FOREST_LO, FOREST_HI, _lerp(2.0, 1.2, u))
    n = int(round(_lerp(150, 260, u)))
    prims = _clutter(rng, placer, {"tree": 0.8, "vcyl": 0.2}, n, FOREST_LO[2], FOREST_HI[2])
    return {
        "primitives": tuple(prims),
        "bounds_lo": FOREST_LO,
        "bounds_hi": FOREST_HI,
        "start_region": default_start_region(FOREST_LO, FOREST_HI),
        "goal_region": default_goal_region(FOREST_LO, FOREST_HI),
    }


FAMILIES: dict[str, Family] = {
    f.name: f
    for f in (
        Family("train", 16, "train", 0, 1, "16 training levels: trees and cylinders, density rising", _gen_train),
        Family(
            "train_shapes", 16, "train", 0, 6,
            "16 training levels over every obstacle kind (not the paper's training set), density rising",
            _gen_train_shapes,
        ),
        Family(
            "train_shapes_perlin", 16 + TRAIN_PERLIN_FIELDS, "train", 0, 9,
            "train_shapes' 16 levels plus 8 Perlin-noise fields (occupancy rising), for uniform sampling; not the "
            "paper's training set", _gen_train_shapes_perlin,
        ),
        Family(
            "ablation", 8, "eval", 1_000_000, 2,
            "8 unseen scenes: inclined/vertical cylinders, frames, thin poles, U-traps and dead ends", _gen_ablation,
        ),
        Family(
            "benchmark", 16, "eval", 1_100_000, 3,
            "16 unseen scenes: 12 geometric clutter + 4 Perlin-noise fields, difficulty rising", _gen_benchmark,
        ),
        Family(
            "dynamic", 4, "eval", 1_200_000, 4, "4 scenes: geometric clutter plus bouncing moving cylinders",
            _gen_dynamic,
        ),
        Family(
            "forest", 4, "eval", 1_300_000, 5, "4 long (100 m) sparse tree fields for high-speed flight", _gen_forest,
        ),
        Family(
            "train_traps", 16, "train", 0, 8,
            "16 training levels of the traps layout (not in the paper): wide U-traps across the route, clutter rising",
            _gen_traps,
        ),
        Family(
            "traps", 8, "eval", 1_400_000, 7,
            "8 unseen scenes (not in the paper): three staggered columns of wide U-traps across the route, sparse "
            "clutter; a probe of global guidance", _gen_traps,
        ),
    )
}  # fmt: skip
"""All registered families by name."""


def is_training_family(family: str) -> bool:
    """Whether ``family`` draws from the training seed range (its indices are curriculum levels)."""
    return _family(family).split == "train"


def family_seed_range(family: str) -> range:
    """The seed range a family accepts (``TRAIN_SEEDS`` or ``EVAL_SEEDS``)."""
    return TRAIN_SEEDS if _family(family).split == "train" else EVAL_SEEDS


def _family(family: str) -> Family:
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family {family!r}; known families: {sorted(FAMILIES)}")
    return FAMILIES[family]


def make_scene(family: str, index: int, seed: int | None = None) -> Scene:
    """Generate scene ``index`` of ``family``; a pure function of ``(family, index, seed)``.

    Args:
        family: One of :data:`FAMILIES`.
        index: ``0 .. FAMILIES[family].size - 1``; difficulty rises with it.
        seed: Base seed; ``None`` uses the family's default. Must lie in the family's split range
            (training: :data:`TRAIN_SEEDS`, evaluation: :data:`EVAL_SEEDS`).

    Raises:
        ValueError: Unknown family, index out of range, or a seed from the other split.
    """
    fam = _family(family)
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
        raise ValueError(f"scene index must be an integer, got {index!r}")
    if not 0 <= index < fam.size:
        raise ValueError(f"scene index {index} out of range for family {family!r} (valid: 0..{fam.size - 1})")
    seed = fam.default_seed if seed is None else seed
    allowed = family_seed_range(family)
    if int(seed) not in allowed:
        raise ValueError(
            f"seed {seed} is not in the {fam.split} seed range [{allowed.start}, {allowed.stop}) of family "
            f"{family!r}: training and evaluation seeds are kept disjoint"
        )
    return _make_scene_cached(family, int(index), int(seed))


@functools.lru_cache(maxsize=256)
def _make_scene_cached(family: str, index: int, seed: int) -> Scene:
    fam = FAMILIES[family]
    rng = np.random.default_rng(np.random.SeedSequence([seed, fam.family_id, index]))
    u = index / max(fam.size - 1, 1)
    kwargs = fam.generate(rng, index, u)
    return Scene(family=family, index=index, seed=seed, **kwargs)


def family_scenes(family: str, seed: int | None = None) -> list[Scene]:
    """All scenes of a family, in index order."""
    return [make_scene(family, i, seed) for i in range(_family(family).size)]
