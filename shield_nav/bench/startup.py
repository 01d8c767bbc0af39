"""Start-up benchmark: the first ``gymnasium.make_vec("ShieldNav-v0")``, its first reset and step, cold and warm.

``python -m shield_nav.bench startup [--json] [--num-envs 8] [--config CFG]``

Each pass runs in a fresh Python process (so imports, numba's cached kernels and the field files are read as a new
user's first call reads them) with ``SHIELD_NAV_CACHE`` pointed at a new empty folder for the *cold* pass and at
the folder it filled for the *warm* pass. Reported per pass: import, ``make_vec``, first ``reset``, first
``step`` and their total, and how many scene and goal-anchor fields were built. Fields are built lazily, for the
scenes and goals the envs draw, so the cold total depends on how many distinct ones the first reset draws.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

from shield_nav.bench.common import emit, machine, parser

_CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
import gymnasium, numpy as np
import envs  # registers ShieldNav-v0
t1 = time.perf_counter()
kw = {"num_envs": int(sys.argv[1])}
if sys.argv[2]:
    kw["config"] = sys.argv[2]
vec = gymnasium.make_vec("ShieldNav-v0", **kw)
t2 = time.perf_counter()
vec.reset(seed=0)
t3 = time.perf_counter()
vec.step(np.zeros(vec.action_space.shape, dtype=np.float32))
t4 = time.perf_counter()
env = vec.unwrapped if hasattr(vec, "unwrapped") else vec
a = env.anchor_fields
print(json.dumps({
    "import_s": t1 - t0, "make_vec_s": t2 - t1, "reset_s": t3 - t2, "step_s": t4 - t3, "total_s": t4 - t1,
    "scenes": int(env.field_stack.num_scenes), "scenes_built": int(env.field_stack.ready.sum()),
    "anchor_fields_built": int(a._ready.sum()) if a is not None else 0,
    "anchor_fields": int(a._ready.size) if a is not None else 0,
}))
"""


def _pass(num_envs: int, config: str, cache: str) -> dict:
    env = dict(os.environ, SHIELD_NAV_CACHE=cache)
    out = subprocess.run([sys.executable, "-c", _CHILD, str(num_envs), config], env=env, capture_output=True,
                         text=True, check=False)  # fmt: skip
    if out.returncode != 0:
        raise RuntimeError(f"start-up pass failed (exit {out.returncode}):\n{out.stderr[-3000:]}")
    sys.stderr.write(out.stderr)
    return {
        k: round(v, 3) if isinstance(v, float) else v
        for k, v in json.loads(out.stdout.strip().splitlines()[-1]).items()
    }


def main(argv: list[str]) -> dict:
    """Run the benchmark; returns (and prints) the result dict."""
    p = parser("startup", __doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, default=8)
    p.add_argument("--config", default="", help="an env config file (default: ShieldNav-v0's defaults)")
    args = p.parse_args(argv)
    if args.num_envs < 1:
        p.error(f"--num-envs must be >= 1, got {args.num_envs}")
    with tempfile.TemporaryDirectory(prefix="shield_nav_cache_") as cache:
        cold = _pass(args.num_envs, args.config, cache)
        print(f"cold: {cold}", flush=True)
        warm = _pass(args.num_envs, args.config, cache)
        print(f"warm: {warm}", flush=True)
    result = {
        "benchmark": "startup",
        "num_envs": args.num_envs,
        "cold_total_s": cold["total_s"],
        "warm_total_s": warm["total_s"],
        "cold": cold,
        "warm": warm,
        **machine(),
    }
    emit(result, args.json)
    return result
