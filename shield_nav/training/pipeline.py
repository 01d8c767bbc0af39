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
A pipeline folder may be moved (committed for a later session, copied to another clone): the inputs its own earlier
stages produced are read from where the folder is now.
"""

from __future__ import annotations

import datetime
import glob
import json
import os
import re
import signal
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import yaml

from envs.config import ConfigError, stored_config, to_dict
from shield_nav.training.config import TrainConfig, load_train_config

PIPELINE_FILE = "pipeline.yaml"
STAGE_FILE = "stage.json"
_PIPELINE_KEYS = {"name", "stages"}
_STAGE_KEYS = {"name", "config", "set"}
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_REF = re.compile(r"\$\{([^}]*)\}")
_INPUT_KEYS = ("actor_init", "student_init", "teacher_checkpoint")


@dataclass
class Stage:
    """One stage: a train config file and the overrides applied on top of it (``${stage}`` references allowed)."""

    name: str
    config: str
    overrides: list[str] = field(default_factory=list)


@dataclass
class Pipeline:
    """The stages of one recipe, in the order they run."""

    name: str
    stages: list[Stage]
    source: str = ""


def _check_name(value: Any, key: str, where: str) -> str:
    if not isinstance(value, str) or not _NAME.match(value):
        raise ConfigError(f"pipeline key '{key}' {where}: must be a lower-case identifier, got {value!r}")
    return value


def is_pipeline_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a pipeline file (a YAML mapping with a ``stages`` key) rather than a train config."""
    try:
        with open(path, encoding="utf-8") as f:
            raw = yaml.safe_load(f)
    except (OSError, yaml.YAMLError):
        return False  # the train-config loader reports the file's problem by name
    return isinstance(raw, dict) and "stages" in raw


def load_pipeline(path: str | os.PathLike) -> Pipeline:
    """Read and check a pipeline file: known keys, unique stage names, existing configs, backward references only.

    Raises:
        ConfigError: Naming the pipeline key at fault.
    """
    src = str(path)
    with open(src, encoding="utf-8") as f:
        raw = yaml.safe_load(f)
    where = f"(from {src})"
    if not isinstance(raw, dict):
        raise ConfigError(f"pipeline {src!r}: expected a mapping with 'name' and 'stages'")
    unknown = sorted(set(raw) - _PIPELINE_KEYS)
    if unknown:
        raise ConfigError(f"pipeline key {unknown[0]!r} {where}: unknown; known: {sorted(_PIPELINE_KEYS)}")
    name = _check_name(raw.get("name"), "name", where)
    items = raw.get("stages")
    if not isinstance(items, list) or not items:
        raise ConfigError(f"pipeline key 'stages' {where}: must be a non-empty list of stages")
    stages: list[Stage] = []
    for i, item in enumerate(items):
        key = f"stages[{i}]"
        if not isinstance(item, dict):
            raise ConfigError(f"pipeline key '{key}' {where}: must be a mapping with 'name' and 'config'")
        unknown = sorted(set(item) - _STAGE_KEYS)
        if unknown:
            raise ConfigError(f"pipeline key '{key}.{unknown[0]}' {where}: unknown; known: {sorted(_STAGE_KEYS)}")
        sname = _check_name(item.get("name"), f"{key}.name", where)
        if any(s.name == sname for s in stages):
            raise ConfigError(f"pipeline key '{key}.name' {where}: stage name {sname!r} is used twice")
        config = item.get("config")
        if not isinstance(config, str):
            raise ConfigError(f"pipeline key '{key}.config' {where}: must be a path to a train config")
        config_path = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(src)), config))
        if not os.path.isfile(config_path):
            raise ConfigError(f"pipeline key '{key}.config' {where}: no such file {config_path!r}")
        overrides = item.get("set", [])
        if not isinstance(overrides, list) or not all(isinstance(o, str) and "=" in o for o in overrides):
            raise ConfigError(f"pipeline key '{key}.set' {where}: must be a list of 'dotted.key=value' strings")
        for o in overrides:
            for ref in _REF.findall(o):
                if not any(s.name == ref for s in stages):
                    raise ConfigError(f"pipeline key '{key}.set' {where}: '${{{ref}}}' in {o!r} is not an earlier "
                                      f"stage; earlier: {[s.name for s in stages]}")  # fmt: skip
        stages.append(Stage(sname, config_path, list(overrides)))
    return Pipeline(name, stages, src)


def stage_dir(root: str, index: int, stage: Stage | str) -> str:
    """The run folder of stage ``index`` inside the pipeline folder ``root``."""
    name = stage if isinstance(stage, str) else stage.name
    return os.path.join(root, f"{index:02d}_{name}")


def final_checkpoint(run_dir: str, cfg: TrainConfig) -> str:
    """The checkpoint a finished run of ``cfg`` leaves: ``model_<max_iterations - 1>.pt``."""
    return os.path.join(run_dir, f"model_{cfg.max_iterations - 1}.pt")


def resolve(pipeline: Pipeline, root: str, overrides: Sequence[str] = ()) -> list[TrainConfig]:
    """Every stage's resolved config, with ``${stage}`` replaced by that stage's final checkpoint under ``root``.

    ``overrides`` (the command line's ``--set`` and shorthand flags) apply to every stage, after the stage's own.
    """
    outputs: dict[str, str] = {}
    configs = []
    for i, stage in enumerate(pipeline.stages):
        own = [_REF.sub(lambda m: outputs[m.group(1)], o) for o in stage.overrides]
        try:
            cfg = load_train_config(files=stage.config, overrides=[*own, *overrides])
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


def start(pipeline: Pipeline, overrides: Sequence[str] = ()) -> str:
    """Check every stage, create the pipeline folder and store the resolved configs; return the folder."""
    probe = resolve(pipeline, "<pipeline>", overrides)  # fails on a bad key before any folder exists
    pairs = enumerate(zip(pipeline.stages, probe, strict=True))
    produced = {final_checkpoint(stage_dir("<pipeline>", i, s), c) for i, (s, c) in pairs}
    check_inputs([s.name for s in pipeline.stages], probe, produced)
    from shield_nav.training.runner import new_stamped_dir

    root = new_stamped_dir(probe[0], pipeline.name)
    configs = resolve(pipeline, root, overrides)
    record = {
        "name": pipeline.name,
        "source": os.path.relpath(pipeline.source) if pipeline.source else "",
        "overrides": list(overrides),
        "stages": [{"name": s.name, "config": to_dict(c)} for s, c in zip(pipeline.stages, configs, strict=True)],
    }
    with open(os.path.join(root, PIPELINE_FILE), "w", encoding="utf-8") as f:
        yaml.safe_dump(record, f, sort_keys=False)
    return root


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
    names, configs = [], []
    for i, stage in enumerate(record["stages"]):
        runner = stage["config"].get("runner", {})
        earlier = {os.path.basename(stage_dir(root, j, s["name"])) for j, s in enumerate(record["stages"][:i])}
        for key in _INPUT_KEYS:
            if isinstance(runner.get(key), str):
                runner[key] = _relocated(runner[key], root, earlier)
        try:
            stored = stored_config(TrainConfig, stage["config"])
            cfg = load_train_config(overrides=list(overrides), base=load_train_config(overrides=stored))
        except ConfigError as err:
            raise ConfigError(f"pipeline stage '{stage['name']}': {err}") from None
        names.append(stage["name"])
        configs.append(cfg)
    return names, configs


def run(
    root: str,
    overrides: Sequence[str] = (),
    train_fn: Callable[..., str] | None = None,
) -> list[dict[str, Any]]:
    """Run (or continue) the pipeline stored in ``root``; return each stage's record (``stage.json``).

    Args:
        root: A pipeline folder made by :func:`start`.
        overrides: Dotted overrides on top of the stored configs (``--set`` on ``--resume``).
        train_fn: The trainer, :func:`shield_nav.training.runner.train` by default (tests pass one with a small env).
    """
    from shield_nav.training.runner import train

    train_fn = train if train_fn is None else train_fn
    names, configs = load_stored(root, overrides)
    records = []
    for i, (name, cfg) in enumerate(zip(names, configs, strict=True)):
        run_dir = stage_dir(root, i, name)
        marker = os.path.join(run_dir, STAGE_FILE)
        if os.path.isfile(marker):
            with open(marker, encoding="utf-8") as f:
                records.append({**json.load(f), "checkpoint": final_checkpoint(run_dir, cfg)})  # where it is now
            print(f"[pipeline] stage {i + 1}/{len(names)} '{name}': finished before, skipped", flush=True)
            continue
        latest = _latest_checkpoint(run_dir) if os.path.isdir(run_dir) else None
        os.makedirs(run_dir, exist_ok=True)
        how = f"resuming from {os.path.basename(latest)}" if latest else "starting"
        print(f"[pipeline] stage {i + 1}/{len(names)} '{name}' ({cfg.max_iterations} iterations): {how}", flush=True)
        try:
            train_fn(cfg, resume=latest, run_dir=run_dir)
        except SystemExit as stop:
            if stop.code == 128 + signal.SIGINT or stop.code == 128 + signal.SIGTERM:
                print(f"[pipeline] interrupted in stage '{name}'; continue with: python train.py --resume {root}",
                      flush=True)  # fmt: skip
            raise
        final = final_checkpoint(run_dir, cfg)
        if not os.path.isfile(final):
            raise RuntimeError(f"pipeline stage '{name}' ended without its final checkpoint {final!r}")
        from shield_nav.training.checks import read_checkpoint_infos

        infos = read_checkpoint_infos(final)
        record = {
            "stage": name,
            "checkpoint": final,
            "iterations": cfg.max_iterations,
            "env_steps": int(infos.get("tot_timesteps", 0)),
            "train_time_s": round(float(infos.get("tot_time", 0.0)), 1),
            "finished_at": datetime.datetime.now().isoformat(timespec="seconds"),
        }
        with open(marker, "w", encoding="utf-8") as f:
            json.dump(record, f, indent=2)
        records.append(record)
    total = sum(r["train_time_s"] for r in records)
    print(f"[pipeline] finished: {root}", flush=True)
    for r in records:
        print(f"[pipeline]   {r['stage']:<16} {r['iterations']:>5} it  {r['env_steps']:>10} steps  "
              f"{_hms(r['train_time_s'])}  {r['checkpoint']}", flush=True)  # fmt: skip
    print(f"[pipeline]   total training time {_hms(total)}", flush=True)
    with open(os.path.join(root, "summary.json"), "w", encoding="utf-8") as f:
        json.dump({"stages": records, "train_time_s": round(total, 1)}, f, indent=2)
    return records
