"""Fields benchmark: cold build time per family scene and batched lookup throughput.

``python -m shield_nav.bench fields [--json] [--resolution 0.1] [--families train,benchmark,...]``

* Build: for one scene per family (the hardest index: most obstacles), :func:`envs.fields.build_fields` with
  ``use_cache=False`` (cold: no cache read or write; the numba kernels are compiled beforehand, so compile
  time is excluded and reported separately).
* Lookups: a :class:`envs.fields.FieldStack` of the built scenes, queried with 64 envs x 1000 points
  (64 000 random points spread over the stacked scenes), ESDF + gradient + geodesic in one pass, and also
  64 points (one per env, the per-control-step case).
"""

from __future__ import annotations

import time

import numpy as np

from shield_nav.bench.common import emit, machine, parser, peak_rss_mb, time_it


def main(argv: list[str]) -> dict:
    """Run the benchmark; returns (and prints) the result dict."""
    p = parser("fields", __doc__.splitlines()[0])
    p.add_argument("--resolution", type=float, default=0.1)
    p.add_argument("--families", default="train,ablation,benchmark,dynamic,forest")
    p.add_argument("--envs", type=int, default=64)
    p.add_argument("--points", type=int, default=1000)
    args = p.parse_args(argv)

    from envs.fields import FieldStack, build_fields
    from envs.scenes import FAMILIES, Scene, make_scene

    t0 = time.perf_counter()  # compile (or load from numba's cache) the kernels on a tiny scene
    tiny = Scene(bounds_lo=(0, -2, 0), bounds_hi=(4, 2, 3))
    FieldStack([build_fields(tiny, 0.25, use_cache=False)]).query(np.zeros(1, int), np.zeros((1, 3)))
    warmup_s = time.perf_counter() - t0

    build, fields = {}, []
    for fam in args.families.split(","):
        idx = FAMILIES[fam].size - 1
        scene = make_scene(fam, idx)
        t = time.perf_counter()
        f = build_fields(scene, args.resolution, use_cache=False)
        dt = time.perf_counter() - t
        build[f"{fam}/{idx}"] = {
            "s": round(dt, 3), "esdf_s": round(f.info["build_s_esdf"], 3),
            "geodesic_s": round(f.info["build_s_geodesic"], 3), "nodes": int(np.prod(f.shape)),
            "primitives": len(scene.primitives),
        }  # fmt: skip
        print(f"build {fam}/{idx}: {dt:.2f} s  ({build[f'{fam}/{idx}']})")
        fields.append(f)
    stack = FieldStack(fields)
    rng = np.random.default_rng(0)
    res = {}
    for label, n in (("batch", args.envs * args.points), ("per_step", args.envs)):
        ids = rng.integers(0, len(fields), n)
        lo, hi = stack.origin[ids], stack.origin[ids] + (stack.shape[ids] - 1) * stack.res[ids, None]
        pts = rng.uniform(lo, hi)
        sec, reps = time_it(lambda ids=ids, pts=pts: stack.query(ids, pts), min_time=1.0)
        res[label] = {"points": n, "s_per_call": sec, "lookups_per_s": n / sec, "reps": reps}
        print(f"lookup {label}: {n} points in {sec * 1e6:.1f} us -> {n / sec:.3e} points/s")
    result = {
        "benchmark": "fields",
        "resolution": args.resolution,
        "build_s": {k: v["s"] for k, v in build.items()},
        "build": build,
        "build_s_max": max(v["s"] for v in build.values()),
        "lookups_per_s": res["batch"]["lookups_per_s"],
        "lookup_64x1000_ms": 1e3 * res["batch"]["s_per_call"],
        "lookup_64_us": 1e6 * res["per_step"]["s_per_call"],
        "warmup_s": round(warmup_s, 3),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        **machine(),
    }
    emit(result, args.json)
    return result
