"""Staged recipes: one ``train.py`` command runs a policy's stages (e.g. DAgger distillation, then PPO) in sequence.

A pipeline file is a YAML mapping with ``name`` and ``stages``; each stage names a train config (a path relative to
the pipeline file), optional dotted overrides (``set``), and may use an earlier stage's final checkpoint as
``${<stage name>}``::

    name: dijkstra_cbf
    stages:
      - name: student
        config: ../experiments/distill_expert.yaml
      - name: ppo
        config: recipe_dijkstra_cbf.yaml
        set: ["runner.actor_init=${student}"]

``python train.py --config <pipeline>.yaml`` resolves and checks every stage's config first (a bad key or a missing
input fails before any work), then runs the stages in
``<log_root>/<experiment_name>/<YYYY-mm-dd_HH-MM-SS>_<name>/<NN>_<stage>/``, each an ordinary run folder. The
pipeline folder keeps ``pipeline.yaml`` (the resolved configs) and, per finished stage, ``<NN>_<stage>/stage.json``
(its final checkpoint and training time). ``python train.py --resume <pipeline folder>`` skips finished stages,
continues the interrupted one from its newest ``model_<it>.pt``, and runs the rest with the stored configs.
Command-line overrides apply to every stage, or as ``<stage>:<a.b>=<value>`` to one (:func:`stage_overrides`).
A pipeline folder may be moved (committed for a later session, copied to another clone): the inputs its own earlier
stages produced are read from where the folder is now.

**Candidates and selection.** A stage may train several candidates that differ only in their seed and keep the one
that flies best on validation scenes::

      - name: full
        config: recipe_full.yaml
        set: ["runner.actor_init=${student}"]
        candidates: 3                     # seeds seed, seed + 1, seed + 2 (seed: the stage's resolved config)
        select:
          eval: ../eval/validation_benchmark.yaml   # never the test scenes
          configuration: full             # the eval.py row that flies each candidate's exported policy
          set: ["workers=2"]              # dotted eval-config overrides

Each candidate is an ordinary run folder ``<NN>_<stage>/seed_<s>/`` that resumes after a kill; each is flown by the
evaluation harness into ``<NN>_<stage>/select_seed_<s>/`` (resumable by unit). The candidate with the most successes
over all the eval's trials is kept (a tie keeps the lower seed): its final checkpoint, ``exported/`` and ``params/``
are copied into ``<NN>_<stage>/``, so a later stage's ``${stage}`` and the stage folder read like a one-run stage's.
``<NN>_<stage>/selection.json`` records every candidate's successes per speed and the choice.

**Chains.** Candidates of the last stage share the earlier stages' result (e.g. one depth student). A pipeline may
instead train its whole chain of stages several times and keep the chain whose last stage flies best::

    name: full_chains
    chains: 3                             # every stage's seed and env.seed raised by 0, 1, 2
    select:
      eval: ../eval/validation_benchmark.yaml
      configuration: full
    stages: [...]

Each chain is an ordinary pipeline folder ``chain_<k>/`` (its stages read their own earlier stages' checkpoints, and
it resumes after a kill); each chain's last stage is flown into ``select_chain_<k>/``, and the kept chain's last
checkpoint, ``exported/`` and ``params/`` are copied into ``<NN>_<last stage>/`` of the pipeline folder, with
``selection.json`` beside them.
"""

from __future__ import annotations

import dataclasses
import datetime
import glob
import json
import os
import re
import shutil
import signal
import time
from collections.abc import Callable, Sequence
from typing import Any

import yaml

from envs.config import ConfigError, stored_config, to_dict
from shield_nav.jsonio import write_json
from shield_nav.training.config import TrainConfig, load_train_config, migrate_class_paths
from shield_nav.training.pipeline_file import (
    _INPUT_KEYS,
    _REF,
    CANDIDATE_FILE,
    PIPELINE_FILE,
    SELECTION_FILE,
    STAGE_FILE,
    Pipeline,
    Selection,
    Stage,
    final_checkpoint,
    is_pipeline_file,
    load_pipeline,
    stage_dir,
    stage_overrides,
)

__all__ = [  # the file's schema and parser (pipeline_file) with the runner (here): what train.py and a user import
    "PIPELINE_FILE", "STAGE_FILE", "CANDIDATE_FILE", "SELECTION_FILE", "Pipeline", "Selection", "Stage",
    "is_pipeline_file", "load_pipeline", "stage_dir", "final_checkpoint", "stage_overrides", "resolve",
    "check_inputs", "selection_eval_config", "candidate_configs", "chain_dir", "choose", "start", "load_stored", "run",
]  # fmt: skip


def resolve(pipeline: Pipeline, root: str, overrides: Sequence[str] = ()) -> list[TrainConfig]:
    """Every stage's resolved config, with ``${stage}`` replaced by that stage's final checkpoint under ``root``.

    ``overrides`` (the command line's ``--set`` and shorthand flags) apply after the stage's own: to every stage, or
    as ``<stage>:<a.b>=<value>`` to that stage only (:func:`stage_overrides`).
    """
    outputs: dict[str, str] = {}
    configs = []
    names = [s.name for s in pipeline.stages]
    for i, stage in enumerate(pipeline.stages):
        own = [_REF.sub(lambda m: outputs[m.group(1)], o) for o in stage.overrides]
        given = stage_overrides(overrides, stage.name, names)
        try:
            cfg = load_train_config(files=stage.config, overrides=[*own, *given])
        except ConfigError as err:
            raise ConfigError(f"pipeline stage '{stage.name}': {err}") from None
        if getattr(cfg.runner.algorithm, "lr_schedule_iterations", None) == 0:
            cfg.runner.algorithm.lr_schedule_iterations = cfg.max_iterations  # as train.py does for one run
        outputs[stage.name] = final_checkpoint(stage_dir(root, i, stage), cfg)
        configs.append(cfg)
    return configs


def check_inputs(names: Sequence[str], configs: Sequence[TrainConfig], produced: set[str]) -> None:
    """Fail before any work on a missing input or device.

    A stage's input file (``runner.actor_init``, ...) must exist or be produced by an earlier stage of the pipeline.
    """
    from shield_nav.training.checks import check_device

    for name, cfg in zip(names, configs, strict=True):
        check_device(cfg.device)
        r = cfg.runner
        for key in _INPUT_KEYS:
            path = getattr(r, key)
            if key == "teacher_checkpoint" and (r.class_name != "DistillationRunner" or r.expert.kind):
                continue  # not read by this stage
            if path and path not in produced and not os.path.isfile(path):
                raise ConfigError(f"pipeline stage '{name}': config key 'runner.{key}': no such file {path!r}")


def _latest_checkpoint(run_dir: str) -> str | None:
    found = []
    for path in glob.glob(os.path.join(run_dir, "model_*.pt")):
        m = re.match(r"model_(\d+)\.pt$", os.path.basename(path))
        if m:
            found.append((int(m.group(1)), path))
    return max(found)[1] if found else None


def _hms(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def selection_eval_config(stage_name: str, select: Selection | dict, where: str | None = None) -> Any:
    """The :class:`shield_nav.evaluation.EvalConfig` that flies a stage's candidates, checked before any work.

    ``select`` is the pipeline file's :class:`Selection` or the dict a pipeline folder stored. Raises
    :class:`ConfigError` naming the stage: a bad eval key, an unknown row, a row that flies no policy, or an eval on
    the held-out test scenes (selection is made on validation scenes only).
    """
    from shield_nav.evaluation.config import POLICY_CONTROLLERS, EvalConfig, EvalError, load_eval_config, resolve_rows

    where = where or f"pipeline stage '{stage_name}': select"
    try:
        if isinstance(select, Selection):
            cfg = load_eval_config(select.eval, select.overrides)
            row_name = select.configuration
        else:
            cfg = load_eval_config(overrides=stored_config(EvalConfig, select["eval_config"]))
            row_name = select["configuration"]
        cfg.configurations = [row_name]
        row = resolve_rows(cfg)[row_name]
    except (ConfigError, EvalError) as err:
        raise ConfigError(f"{where}: {err}") from None
    if row.controller not in POLICY_CONTROLLERS:
        raise ConfigError(f"{where}.configuration: row {row_name!r} flies the {row.controller!r} controller, not a "
                          "trained policy")  # fmt: skip
    if cfg.scenes.seed is None and cfg.scenes.family in ("ablation", "benchmark"):
        raise ConfigError(
            f"{where}.eval: it flies the held-out test scenes ({cfg.scenes.family!r} at its own "
            "seed); choose among candidates on validation scenes (configs/eval/validation_*.yaml)"
        )
    return cfg


def _seeded(cfg: TrainConfig, offset: int) -> TrainConfig:
    """``cfg`` with ``seed`` and ``env.seed`` raised by ``offset``."""
    if not offset:
        return cfg
    return load_train_config(overrides=[f"seed={cfg.seed + offset}", f"env.seed={cfg.env.seed + offset}"], base=cfg)


def candidate_configs(cfg: TrainConfig, candidates: int) -> list[tuple[int, TrainConfig]]:
    """(seed, config) of each candidate: the stage's config with ``seed`` and ``env.seed`` raised by 0, 1, ..."""
    return [(cfg.seed + k, _seeded(cfg, k)) for k in range(candidates)]


def chain_dir(root: str, k: int) -> str:
    """The pipeline folder of chain ``k`` inside a pipeline folder with ``chains``."""
    return os.path.join(root, f"chain_{k}")


_CHAINS_WHERE = "pipeline key 'select' (chains)"


def choose(results: Sequence[dict[str, Any]]) -> int:
    """Index of the candidate with the most successes (a tie keeps the earliest, i.e. the lowest seed).

    Every candidate must have been flown on the same number of trials (the same pinned trials).
    """
    if not results:
        raise ValueError("no candidates to choose from")
    trials = {r["trials"] for r in results}
    if len(trials) != 1 or 0 in trials:
        raise RuntimeError(f"candidates were flown on different or no trials: {sorted(trials)}")
    best = max(r["successes"] for r in results)
    return next(i for i, r in enumerate(results) if r["successes"] == best)


def start(pipeline: Pipeline, overrides: Sequence[str] = ()) -> str:
    """Check every stage, create the pipeline folder and store the resolved configs; return the folder."""
    probe = resolve(pipeline, "<pipeline>", overrides)  # fails on a bad key before any folder exists
    pairs = enumerate(zip(pipeline.stages, probe, strict=True))
    produced = {final_checkpoint(stage_dir("<pipeline>", i, s), c) for i, (s, c) in pairs}
    check_inputs([s.name for s in pipeline.stages], probe, produced)
    selections = {s.name: selection_eval_config(s.name, s.select) for s in pipeline.stages if s.select is not None}
    chain_eval = None
    if pipeline.chains > 1:
        assert pipeline.select is not None  # load_pipeline refuses chains without a selection
        chain_eval = selection_eval_config("", pipeline.select, where=_CHAINS_WHERE)
    from shield_nav.training.runner import new_stamped_dir

    root = new_stamped_dir(probe[0], pipeline.name)
    if chain_eval is None:
        _store(root, pipeline, overrides, selections, 0)
        return root
    for k in range(pipeline.chains):
        os.makedirs(chain_dir(root, k))
        _store(chain_dir(root, k), pipeline, overrides, selections, k)
    record = {
        "name": pipeline.name,
        "source": os.path.relpath(pipeline.source) if pipeline.source else "",
        "overrides": list(overrides),
        "chains": pipeline.chains,
        "select": _select_record(pipeline.select, chain_eval),
        "stages": [s.name for s in pipeline.stages],
    }
    with open(os.path.join(root, PIPELINE_FILE), "w", encoding="utf-8") as f:
        yaml.safe_dump(record, f, sort_keys=False)
    return root


def _select_record(select: Selection, ecfg: Any) -> dict[str, Any]:
    """How a pipeline folder stores a selection: its row, the eval file it came from and the resolved eval config."""
    return {"configuration": select.configuration, "source": os.path.relpath(select.eval), "eval_config": to_dict(ecfg)}


def _store(root: str, pipeline: Pipeline, overrides: Sequence[str], selections: dict[str, Any], offset: int) -> None:
    """Write ``root/pipeline.yaml``: every stage's config resolved under ``root``, seeds raised by ``offset``."""
    configs = [_seeded(c, offset) for c in resolve(pipeline, root, overrides)]
    stages = []
    for s, c in zip(pipeline.stages, configs, strict=True):
        entry: dict[str, Any] = {"name": s.name, "config": to_dict(c)}
        if s.select is not None:
            entry["candidates"] = s.candidates
            entry["select"] = _select_record(s.select, selections[s.name])
        stages.append(entry)
    record = {
        "name": pipeline.name,
        "source": os.path.relpath(pipeline.source) if pipeline.source else "",
        "overrides": list(overrides),
        **({"seed_offset": offset} if offset else {}),
        "stages": stages,
    }
    with open(os.path.join(root, PIPELINE_FILE), "w", encoding="utf-8") as f:
        yaml.safe_dump(record, f, sort_keys=False)


def _relocated(path: str, root: str, stage_dirs: set[str]) -> str:
    """An earlier stage's checkpoint (``<old root>/<NN>_<stage>/model_<it>.pt``) under ``root``.

    A pipeline folder stores its stages' inputs as absolute paths; read back from another place (a copy committed
    for a later session, another clone), the inputs an earlier stage of the same folder produced are found there.
    Any other path is returned unchanged.
    """
    parent, name = os.path.split(path)
    old_root, stage = os.path.split(parent)
    moved = os.path.abspath(old_root) != os.path.abspath(root)
    if moved and stage in stage_dirs and re.fullmatch(r"model_\d+\.pt", name):
        return os.path.join(root, stage, name)
    return path


def load_stored(root: str, overrides: Sequence[str] = ()) -> tuple[list[str], list[TrainConfig]]:
    """The stage names and resolved configs a pipeline folder stored (``overrides`` apply on top, e.g. ``device``)."""
    path = os.path.join(root, PIPELINE_FILE)
    if not os.path.isfile(path):
        raise ConfigError(f"--resume: {root!r} is a folder without {PIPELINE_FILE}: not a pipeline folder (to resume "
                          "one run, pass its model_<it>.pt)")  # fmt: skip
    with open(path, encoding="utf-8") as f:
        record = yaml.safe_load(f)
    if "chains" in record:  # every chain is checked; the first one's stages are returned
        found = [load_stored(chain_dir(root, k), overrides) for k in range(int(record["chains"]))]
        return found[0]
    names, configs = [], []
    stages = [s["name"] for s in record["stages"]]
    for i, stage in enumerate(record["stages"]):
        runner = stage["config"].get("runner", {})
        earlier = {os.path.basename(stage_dir(root, j, s["name"])) for j, s in enumerate(record["stages"][:i])}
        for key in _INPUT_KEYS:
            if isinstance(runner.get(key), str):
                runner[key] = _relocated(runner[key], root, earlier)
        given = stage_overrides(overrides, stage["name"], stages)
        try:
            stored = stored_config(TrainConfig, migrate_class_paths(stage["config"]))
            cfg = load_train_config(overrides=given, base=load_train_config(overrides=stored))
        except ConfigError as err:
            raise ConfigError(f"pipeline stage '{stage['name']}': {err}") from None
        names.append(stage["name"])
        configs.append(cfg)
    return names, configs


def _train_stage(train_fn: Callable[..., str], cfg: TrainConfig, run_dir: str, label: str, root: str) -> dict[str, Any]:
    """Train (or continue) one run folder to its final checkpoint; return its record (written by the caller)."""
    latest = _latest_checkpoint(run_dir) if os.path.isdir(run_dir) else None
    os.makedirs(run_dir, exist_ok=True)
    how = f"resuming from {os.path.basename(latest)}" if latest else "starting"
    print(f"[pipeline] {label} ({cfg.max_iterations} iterations): {how}", flush=True)
    try:
        train_fn(cfg, resume=latest, run_dir=run_dir)
    except SystemExit as stop:
        if stop.code == 128 + signal.SIGINT or stop.code == 128 + signal.SIGTERM:
            print(f"[pipeline] interrupted in {label}; continue with: python train.py --resume {root}", flush=True)
        raise
    final = final_checkpoint(run_dir, cfg)
    if not os.path.isfile(final):
        raise RuntimeError(f"pipeline {label} ended without its final checkpoint {final!r}")
    from shield_nav.training.checks import read_checkpoint_infos

    infos = read_checkpoint_infos(final)
    return {
        "checkpoint": final,
        "iterations": cfg.max_iterations,
        "env_steps": int(infos.get("tot_timesteps", 0)),
        "train_time_s": round(float(infos.get("tot_time", 0.0)), 1),
        "finished_at": datetime.datetime.now().isoformat(timespec="seconds"),
    }


def _run_candidates(
    train_fn: Callable[..., str],
    eval_fn: Callable[..., dict],
    root: str,
    label: str,
    name: str,
    cfg: TrainConfig,
    run_dir: str,
    entry: dict[str, Any],
) -> dict[str, Any]:
    """Train a stage's candidates, fly each on the validation eval, keep the best in the stage folder."""
    n = int(entry["candidates"])
    ecfg = selection_eval_config(name, entry["select"])
    row_name = entry["select"]["configuration"]
    from shield_nav.evaluation.config import resolve_rows

    policy = resolve_rows(ecfg)[row_name]
    os.makedirs(run_dir, exist_ok=True)
    trained = []
    for k, (seed, ccfg) in enumerate(candidate_configs(cfg, n)):
        cdir = os.path.join(run_dir, f"seed_{seed}")
        marker = os.path.join(cdir, CANDIDATE_FILE)
        clabel = f"{label} candidate {k + 1}/{n} (seed {seed})"
        if os.path.isfile(marker):
            with open(marker, encoding="utf-8") as f:
                rec = {**json.load(f), "checkpoint": final_checkpoint(cdir, ccfg)}
            print(f"[pipeline] {clabel}: finished before, skipped", flush=True)
        else:
            stale = os.path.join(run_dir, f"select_seed_{seed}")
            if os.path.isdir(stale):  # flights of a checkpoint that is being replaced (a kill before its marker)
                shutil.rmtree(stale)
            rec = {"seed": seed, **_train_stage(train_fn, ccfg, cdir, clabel, root)}
            write_json(marker, rec)
        trained.append((seed, cdir, rec))
    t0 = time.monotonic()
    items = [
        (seed, cdir, rec["checkpoint"], os.path.join(run_dir, f"select_seed_{seed}")) for seed, cdir, rec in trained
    ]
    results = _fly(eval_fn, ecfg, row_name, policy.policy, items, label, "seed")
    best = choose(results)
    chosen_seed, chosen_dir, chosen_rec = trained[best]
    final = final_checkpoint(run_dir, cfg)
    _keep(chosen_rec["checkpoint"], chosen_dir, final, ecfg, entry["select"]["source"], row_name, results,
          {"chosen_seed": chosen_seed}, "seed")  # fmt: skip
    select_time = round(time.monotonic() - t0, 1)
    print(f"[pipeline] {label}: keeps seed {chosen_seed} ({results[best]['successes']} of {results[best]['trials']}); "
          f"copied to {final}", flush=True)  # fmt: skip
    return {
        "checkpoint": final,
        "iterations": cfg.max_iterations,
        "env_steps": sum(r["env_steps"] for _, _, r in trained),
        "train_time_s": round(sum(r["train_time_s"] for _, _, r in trained), 1),
        "select_time_s": select_time,
        "candidates": [s for s, _, _ in trained],
        "chosen_seed": chosen_seed,
        "finished_at": datetime.datetime.now().isoformat(timespec="seconds"),
    }


def _fly(
    eval_fn: Callable[..., dict],
    ecfg: Any,
    row_name: str,
    policy_name: str,
    items: Sequence[tuple[int, str, str, str]],
    label: str,
    what: str,
) -> list[dict[str, Any]]:
    """Fly each candidate's exported policy as ``row_name`` on ``ecfg``; its successes per speed.

    ``items``: (id, run folder holding ``exported/policy.onnx``, final checkpoint, flight folder). Flights resume by
    unit; a flight folder older than its candidate's export (the candidate was retrained) is flown again.
    """
    results = []
    for ident, cdir, ckpt, out in items:
        onnx = os.path.join(cdir, "exported", "policy.onnx")
        if not os.path.isfile(onnx):
            raise RuntimeError(f"pipeline {label}: candidate {what} {ident} has no exported policy {onnx!r} to fly")
        manifest = os.path.join(out, "manifest.json")
        if os.path.isfile(manifest) and os.path.getmtime(manifest) < os.path.getmtime(onnx):
            shutil.rmtree(out)  # flights of an export that has since been replaced
        one = dataclasses.replace(ecfg, checkpoints={**ecfg.checkpoints, policy_name: onnx})
        trials = len(one.scene_indices) * one.trials_per_scene * len(one.speeds)
        print(f"[pipeline] {label} selection: flying candidate {what} {ident} as '{row_name}' on {one.name} "
              f"({trials} trials, {one.workers} worker(s))", flush=True)  # fmt: skip
        summary = eval_fn(one, out, (policy_name,), progress=False)
        cells = summary["cells"][row_name]
        per_speed = {v: (c["successes"] if c else 0) for v, c in cells.items()}
        n_trials = sum(c["n"] for c in cells.values() if c)
        results.append({what: ident, "checkpoint": ckpt, "successes": sum(per_speed.values()),
                        "trials": n_trials, "successes_per_speed": per_speed})  # fmt: skip
        rates = ", ".join(f"{v} m/s {s}" for v, s in per_speed.items())
        print(f"[pipeline] {label} selection: {what} {ident}: {results[-1]['successes']} of {n_trials} ({rates})",
              flush=True)  # fmt: skip
    return results


def _keep(
    checkpoint: str,
    src_dir: str,
    final: str,
    ecfg: Any,
    source: str,
    row_name: str,
    results: list[dict[str, Any]],
    choice: dict[str, Any],
    what: str,
) -> None:
    """Copy the kept checkpoint to ``final``, its ``exported/`` and ``params/`` beside it; write ``selection.json``."""
    dest = os.path.dirname(final)
    os.makedirs(dest, exist_ok=True)
    shutil.copy2(checkpoint, final)
    for sub in ("exported", "params"):
        if os.path.isdir(os.path.join(src_dir, sub)):
            shutil.copytree(os.path.join(src_dir, sub), os.path.join(dest, sub), dirs_exist_ok=True)
    write_json(os.path.join(dest, SELECTION_FILE), {
        "eval": source,
        "configuration": row_name,
        "scene_family": ecfg.scenes.family,
        "scene_seed": ecfg.scenes.seed,
        "candidates": results,
        **choice,
        "rule": f"most successes over all trials; a tie keeps the lower {what}",
    })  # fmt: skip


def _run_chains(
    root: str,
    record: dict[str, Any],
    overrides: Sequence[str],
    train_fn: Callable[..., str] | None,
    eval_fn: Callable[..., dict],
) -> list[dict[str, Any]]:
    """Run (or continue) every chain, fly each chain's last stage on the validation eval, keep the best chain."""
    n = int(record["chains"])
    finished = []
    for k in range(n):
        print(f"[pipeline] chain {k + 1}/{n}: {chain_dir(root, k)}", flush=True)
        finished.append(run(chain_dir(root, k), overrides, train_fn, eval_fn))
    ecfg = selection_eval_config("", record["select"], where=_CHAINS_WHERE)
    row_name = record["select"]["configuration"]
    from shield_nav.evaluation.config import resolve_rows

    policy = resolve_rows(ecfg)[row_name]
    t0 = time.monotonic()
    items = [(k, os.path.dirname(recs[-1]["checkpoint"]), recs[-1]["checkpoint"],
              os.path.join(root, f"select_chain_{k}")) for k, recs in enumerate(finished)]  # fmt: skip
    results = _fly(eval_fn, ecfg, row_name, policy.policy, items, "chains", "chain")
    best = choose(results)
    names = record["stages"]
    kept_dir = stage_dir(root, len(names) - 1, names[-1])
    chosen_dir, chosen_ckpt = items[best][1], items[best][2]
    final = os.path.join(kept_dir, os.path.basename(chosen_ckpt))
    _keep(chosen_ckpt, chosen_dir, final, ecfg, record["select"]["source"], row_name, results,
          {"chosen_chain": best}, "chain")  # fmt: skip
    select_time = round(time.monotonic() - t0, 1)
    print(f"[pipeline] chains: keeps chain {best} ({results[best]['successes']} of {results[best]['trials']}); "
          f"copied to {final}", flush=True)  # fmt: skip
    train_time = sum(r["train_time_s"] for recs in finished for r in recs)
    inner_select = sum(r.get("select_time_s", 0.0) for recs in finished for r in recs)
    for k, recs in enumerate(finished):
        print(
            f"[pipeline]   chain {k}: {sum(r['train_time_s'] for r in recs) / 60:.1f} min of training, "
            f"{results[k]['successes']} of {results[k]['trials']}{'  (kept)' if k == best else ''}",
            flush=True,
        )
    print(f"[pipeline]   total training time {_hms(train_time)}; selection (validation flights) "
          f"{_hms(select_time + inner_select)}", flush=True)  # fmt: skip
    write_json(os.path.join(root, "summary.json"), {
        "chains": [{"chain": k, "stages": recs, "train_time_s": round(sum(r["train_time_s"] for r in recs), 1)}
                   for k, recs in enumerate(finished)],
        "chosen_chain": best,
        "checkpoint": final,
        "train_time_s": round(train_time, 1),
        "select_time_s": round(select_time + inner_select, 1),
    })  # fmt: skip
    return [*finished[best][:-1], {**finished[best][-1], "checkpoint": final, "chosen_chain": best}]


def run(
    root: str,
    overrides: Sequence[str] = (),
    train_fn: Callable[..., str] | None = None,
    eval_fn: Callable[..., dict] | None = None,
) -> list[dict[str, Any]]:
    """Run (or continue) the pipeline stored in ``root``; return each stage's record (``stage.json``).

    Args:
        root: A pipeline folder made by :func:`start`.
        overrides: Dotted overrides on top of the stored configs (``--set`` on ``--resume``).
        train_fn: The trainer, :func:`shield_nav.training.runner.train` by default (tests pass one with a small env).
        eval_fn: The evaluation of a stage's candidates, :func:`shield_nav.evaluation.evaluate` by default.
    """
    from shield_nav.training.runner import train

    train_fn = train if train_fn is None else train_fn
    if eval_fn is None:
        from shield_nav.evaluation import evaluate as eval_fn
    with open(os.path.join(root, PIPELINE_FILE), encoding="utf-8") as f:
        stored = yaml.safe_load(f)
    if "chains" in stored:
        return _run_chains(root, stored, overrides, train_fn, eval_fn)
    names, configs = load_stored(root, overrides)
    entries = stored["stages"]
    records = []
    for i, (name, cfg, entry) in enumerate(zip(names, configs, entries, strict=True)):
        run_dir = stage_dir(root, i, name)
        marker = os.path.join(run_dir, STAGE_FILE)
        label = f"stage {i + 1}/{len(names)} '{name}'"
        if os.path.isfile(marker):
            with open(marker, encoding="utf-8") as f:
                records.append({**json.load(f), "checkpoint": final_checkpoint(run_dir, cfg)})  # where it is now
            print(f"[pipeline] {label}: finished before, skipped", flush=True)
            continue
        if entry.get("candidates", 1) > 1:
            record = {"stage": name, **_run_candidates(train_fn, eval_fn, root, label, name, cfg, run_dir, entry)}
        else:
            record = {"stage": name, **_train_stage(train_fn, cfg, run_dir, label, root)}
        write_json(marker, record)
        records.append(record)
    total = sum(r["train_time_s"] for r in records)
    selecting = sum(r.get("select_time_s", 0.0) for r in records)
    print(f"[pipeline] finished: {root}", flush=True)
    for r in records:
        chosen = f"  (kept seed {r['chosen_seed']} of {r['candidates']})" if "chosen_seed" in r else ""
        print(f"[pipeline]   {r['stage']:<16} {r['iterations']:>5} it  {r['env_steps']:>10} steps  "
              f"{_hms(r['train_time_s'])}  {r['checkpoint']}{chosen}", flush=True)  # fmt: skip
    print(f"[pipeline]   total training time {_hms(total)}", flush=True)
    if selecting:
        print(f"[pipeline]   selection (validation flights) {_hms(selecting)}", flush=True)
    out = {"stages": records, "train_time_s": round(total, 1)}
    if selecting:
        out["select_time_s"] = round(selecting, 1)
    write_json(os.path.join(root, "summary.json"), out)
    return records
