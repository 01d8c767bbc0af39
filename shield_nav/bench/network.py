"""Cost of the policy network per step: ``python -m shield_nav.bench network --json``.

The shipped Full policy (or ``--checkpoint``) is run on one batch of recorded-size inputs (a random state, a random
depth image, a random hidden state; ``--batch`` envs, the evaluation's batch of 25 by default) by each runtime the
harness offers (``eval.py --set network=...``): the ONNX export through onnxruntime and the TorchScript export through
torch, both on one thread as the harness runs them, and the fixed-order float64 kernels
(:mod:`shield_nav.evaluation.fixed_order`). Reported: microseconds per env per step for each, and the largest
action difference of the fixed-order runtime from the ONNX export on these inputs.
"""

from __future__ import annotations

import numpy as np

from shield_nav.bench.common import emit, machine, parser, time_it


def main(argv: list[str]) -> dict:
    """Time one policy step per runtime on the same batch."""
    p = parser("network", __doc__.splitlines()[0])
    p.add_argument(
        "--checkpoint", default="checkpoints/full", help="a checkpoint folder with policy.onnx and policy.pt"
    )
    p.add_argument("--batch", type=int, default=25, help="envs per step (the evaluation's batch_size)")
    p.add_argument("--min-time", type=float, default=2.0, help="seconds each runtime is timed for, at least")
    args = p.parse_args(argv)
    if args.batch < 1:
        p.error(f"--batch must be >= 1, got {args.batch}")
    import torch

    from shield_nav.evaluation.policies import load_policy

    torch.set_num_threads(1)
    runtimes = {"onnx": load_policy(args.checkpoint, "bench"), "fixed_order": None, "torchscript": None}
    pt = runtimes["onnx"].info.path.replace("policy.onnx", "policy.pt")
    runtimes["torchscript"] = load_policy(pt, "bench")
    runtimes["fixed_order"] = load_policy(pt, "bench", network="fixed_order")
    info = runtimes["onnx"].info
    rng = np.random.default_rng(0)
    n = args.batch
    state = rng.normal(size=(n, info.obs_dim)).astype(np.float32)
    depth = rng.uniform(size=(n, *info.depth_shape)).astype(np.float32)
    h = (0.3 * rng.normal(size=(info.num_layers, n, info.hidden_size))).astype(np.float32)
    result: dict = {"benchmark": "network", "checkpoint": args.checkpoint, "batch": n}
    actions = {}
    for name, pol in runtimes.items():
        actions[name] = pol.step(state, depth, h)[0]  # compiles / warms up outside the timing
        sec, reps = time_it(lambda pol=pol: pol.step(state, depth, h), min_time=args.min_time)
        result[f"{name}_us_per_env"] = round(1e6 * sec / n, 2)
        print(f"{name}: {1e3 * sec:.2f} ms per step of {n} envs ({reps} steps)", flush=True)
    result["fixed_order_over_onnx"] = round(result["fixed_order_us_per_env"] / result["onnx_us_per_env"], 2)
    result["fixed_order_max_action_diff_vs_onnx"] = float(np.abs(actions["fixed_order"] - actions["onnx"]).max())
    result.update(machine())
    emit(result, args.json)
    return result
