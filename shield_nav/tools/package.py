"""Package a training checkpoint as a committed policy: ``checkpoints/<name>/``.

``python -m shield_nav.tools.package logs/shield_nav/<run>/model_<it>.pt --name dijkstra_cbf``

writes ``checkpoints/<name>/`` with the rsl-rl checkpoint (``model.pt``: actor, critic and optimizer, resumable
with ``train.py --resume``), the resolved training config (``params/config.yaml``), the exported actor
(``policy.onnx`` and TorchScript ``policy.pt``), the run's tensorboard scalars up to that iteration
(``curves.csv``, the reference for ``shield_nav.tools.compare_runs``) and a ``meta.json`` (iteration, env steps,
wall time, source run, sha256 of every file).

A distillation checkpoint packages its student (the deployable CNN+GRU). A privileged teacher (an ``MLPModel`` over
the local ESDF map) is packaged without exports: it cannot fly from depth, it is kept to distil from
(``runner.teacher_checkpoint: checkpoints/teacher_<formulation>/model.pt``); ``meta.json`` says
``"deployable": false``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil

from envs.config import to_yaml
from shield_nav.evaluation.policies import _sha256
from shield_nav.policies.export import export_policy
from shield_nav.tools.compare_runs import read_events, write_csv
from shield_nav.training.actor import actor_from_checkpoint


def package(ckpt_path: str, name: str, out_root: str = "checkpoints") -> str:
    """Write ``<out_root>/<name>/`` from a training checkpoint; return the folder.

    ``meta.json`` hashes the files written here (checkpoint, exports, curves). A model card (``README.md``)
    already in the folder is kept and not hashed: it is written by hand after packaging. A stale export or
    ``curves.csv`` that this checkpoint does not produce is removed, so the folder holds one policy only.
    """
    model, cfg, meta = actor_from_checkpoint(ckpt_path)
    out = os.path.join(out_root, name)
    os.makedirs(os.path.join(out, "params"), exist_ok=True)
    written = ["model.pt"]
    shutil.copyfile(ckpt_path, os.path.join(out, "model.pt"))
    with open(os.path.join(out, "params", "config.yaml"), "w") as fh:
        fh.write(to_yaml(cfg))
    if model is not None:
        export_policy(model, out)
        written += ["policy.onnx", "policy.pt"]
    run_dir = os.path.dirname(os.path.abspath(ckpt_path))
    try:
        series = read_events(run_dir)
    except FileNotFoundError:
        print(f"[package] no tensorboard events in {run_dir}: no curves.csv")
    else:
        series = {k: [(s, v) for s, v in pts if s <= meta["iter"]] for k, pts in series.items()}
        write_csv(series, os.path.join(out, "curves.csv"))
        written.append("curves.csv")
    for stale in ("policy.onnx", "policy.pt", "curves.csv"):
        if stale not in written and os.path.isfile(os.path.join(out, stale)):
            os.remove(os.path.join(out, stale))
    meta.update(
        {
            "name": name,
            "deployable": model is not None,
            "kind": "distilled"
            if cfg.runner.class_name == "DistillationRunner"
            else ("ppo" if model is not None else "privileged_teacher"),
            "source_run": os.path.relpath(run_dir),
            "source_checkpoint": os.path.basename(ckpt_path),
            "sha256": {f: _sha256(os.path.join(out, f)) for f in sorted(written)},
        }
    )
    with open(os.path.join(out, "meta.json"), "w") as fh:
        json.dump(meta, fh, indent=2, default=str)
    return out


def main(argv: list[str] | None = None) -> None:
    """CLI entry point."""
    p = argparse.ArgumentParser(prog="python -m shield_nav.tools.package", description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", help="model_<it>.pt of a training run")
    p.add_argument("--name", required=True, help="policy name (folder under --out)")
    p.add_argument("--out", default="checkpoints", help="root folder (default: checkpoints)")
    args = p.parse_args(argv)
    print(f"packaged {package(args.checkpoint, args.name, args.out)}")


if __name__ == "__main__":
    main()
