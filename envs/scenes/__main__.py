"""Scene command line.

Usage::

    python -m envs.scenes stats --family benchmark [--resolution 0.1] [--seed S] [--json]
    python -m envs.scenes plot --family ablation --index 3 --out scene.png
    python -m envs.scenes export --family forest --index 0 --out forest0.glb   # or .obj, .json, .xml
"""

from __future__ import annotations

import argparse
import json
import sys

from envs.scenes.families import FAMILIES, make_scene


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    p = argparse.ArgumentParser(prog="python -m envs.scenes", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("stats", help="print the statistics table of a family")
    s.add_argument("--family", required=True, choices=sorted(FAMILIES))
    s.add_argument("--indices", default=None, help="comma-separated indices (default: all)")
    s.add_argument("--resolution", type=float, default=0.1)
    s.add_argument("--vehicle-radius", type=float, default=0.2)
    s.add_argument("--seed", type=int, default=None, help="scene seed (default: the family's own, held-out scenes)")
    s.add_argument("--json", action="store_true", help="print one JSON list as the last line")
    q = sub.add_parser("plot", help="save a top-down PNG of one scene")
    q.add_argument("--family", required=True, choices=sorted(FAMILIES))
    q.add_argument("--index", type=int, required=True)
    q.add_argument("--resolution", type=float, default=0.1)
    q.add_argument("--out", required=True)
    e = sub.add_parser("export", help="write one scene as .json, .xml (MJCF), .obj or .glb")
    e.add_argument("--family", required=True, choices=sorted(FAMILIES))
    e.add_argument("--index", type=int, required=True)
    e.add_argument("--out", required=True)
    args = p.parse_args(argv)

    if args.cmd == "stats":
        from envs.fields import build_fields
        from envs.scenes.stats import format_table, scene_stats

        fam = FAMILIES[args.family]
        idx = range(fam.size) if args.indices is None else [int(i) for i in args.indices.split(",")]
        rows = []
        for i in idx:
            scene = make_scene(args.family, i, seed=args.seed)
            fields = build_fields(scene, args.resolution, args.vehicle_radius)
            rows.append(scene_stats(scene, fields))
            print(f"[stats] {args.family}/{i}: built in {fields.info.get('build_s', 0.0):.2f} s "
                  f"(cache hit: {fields.info['cache_hit']})", file=sys.stderr)  # fmt: skip
        print(format_table(rows))
        if args.json:
            print(json.dumps(rows))
        return 0
    scene = make_scene(args.family, args.index)
    if args.cmd == "plot":
        from envs.fields import build_fields
        from envs.scenes.plot import save_scene_png

        save_scene_png(scene, args.out, fields=build_fields(scene, args.resolution))
    elif args.out.endswith(".json"):
        scene.save(args.out)
    elif args.out.endswith(".xml"):
        with open(args.out, "w") as f:
            f.write(scene.to_mjcf())
    else:
        scene.to_trimesh(include_slabs=True).export(args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
