"""A staged recipe's file: its schema, parser and per-stage overrides.

:class:`Pipeline`, :class:`Stage`, :class:`Selection`; the format is described in :mod:`shield_nav.training.pipeline`.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import yaml

from envs.config import ConfigError
from shield_nav.training.config import TrainConfig

PIPELINE_FILE = "pipeline.yaml"
STAGE_FILE = "stage.json"
CANDIDATE_FILE = "candidate.json"
SELECTION_FILE = "selection.json"
_PIPELINE_KEYS = {"name", "stages", "chains", "select"}
_STAGE_KEYS = {"name", "config", "set", "candidates", "select"}
_SELECT_KEYS = {"eval", "configuration", "set"}
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_REF = re.compile(r"\$\{([^}]*)\}")
_INPUT_KEYS = ("actor_init", "student_init", "teacher_checkpoint")


@dataclass
class Selection:
    """How a stage with candidates keeps one.

    An eval config on validation scenes, the row that flies each candidate's exported policy, and dotted overrides
    of the eval config.
    """

    eval: str
    configuration: str
    overrides: list[str] = field(default_factory=list)


@dataclass
class Stage:
    """One stage: a train config file and the overrides applied on top of it (``${stage}`` references allowed).

    Optionally several candidates (seeds) and the selection that keeps one.
    """

    name: str
    config: str
    overrides: list[str] = field(default_factory=list)
    candidates: int = 1
    select: Selection | None = None


@dataclass
class Pipeline:
    """The stages of one recipe, in the order they run."""

    name: str
    stages: list[Stage]
    source: str = ""
    chains: int = 1
    select: Selection | None = None


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
        candidates, select = _parse_candidates(item, key, where, os.path.dirname(os.path.abspath(src)))
        stages.append(Stage(sname, config_path, list(overrides), candidates, select))
    chains, select = _parse_candidates(raw, "", where, os.path.dirname(os.path.abspath(src)), "chains")
    return Pipeline(name, stages, src, chains, select)


def _parse_candidates(
    item: dict, key: str, where: str, folder: str, count_key: str = "candidates"
) -> tuple[int, Selection | None]:
    """A stage's ``candidates`` and ``select`` keys (or the pipeline's ``chains`` and ``select``), checked by name."""

    def k(sub: str) -> str:
        return f"{key}.{sub}" if key else sub

    candidates = item.get(count_key, 1)
    if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1:
        raise ConfigError(f"pipeline key '{k(count_key)}' {where}: must be an integer >= 1, got {candidates!r}")
    raw = item.get("select")
    if candidates == 1:
        if raw is not None:
            raise ConfigError(f"pipeline key '{k('select')}' {where}: a selection needs '{count_key}' >= 2")
        return 1, None
    if not isinstance(raw, dict):
        raise ConfigError(
            f"pipeline key '{k('select')}' {where}: '{count_key}: {candidates}' needs a 'select' "
            "mapping with 'eval' (an eval config on validation scenes) and 'configuration' (its row)"
        )
    unknown = sorted(set(raw) - _SELECT_KEYS)
    if unknown:
        raise ConfigError(f"pipeline key '{k('select')}.{unknown[0]}' {where}: unknown; known: {sorted(_SELECT_KEYS)}")
    path = raw.get("eval")
    if not isinstance(path, str):
        raise ConfigError(f"pipeline key '{k('select')}.eval' {where}: must be a path to an eval config")
    path = os.path.normpath(os.path.join(folder, path))
    if not os.path.isfile(path):
        raise ConfigError(f"pipeline key '{k('select')}.eval' {where}: no such file {path!r}")
    row = raw.get("configuration")
    if not isinstance(row, str) or not row:
        raise ConfigError(f"pipeline key '{k('select')}.configuration' {where}: must name one eval.py row")
    overrides = raw.get("set", [])
    if not isinstance(overrides, list) or not all(isinstance(o, str) and "=" in o for o in overrides):
        raise ConfigError(f"pipeline key '{k('select')}.set' {where}: must be a list of 'dotted.key=value' strings")
    return candidates, Selection(path, row, list(overrides))


def stage_dir(root: str, index: int, stage: Stage | str) -> str:
    """The run folder of stage ``index`` inside the pipeline folder ``root``."""
    name = stage if isinstance(stage, str) else stage.name
    return os.path.join(root, f"{index:02d}_{name}")


def final_checkpoint(run_dir: str, cfg: TrainConfig) -> str:
    """The checkpoint a finished run of ``cfg`` leaves: ``model_<max_iterations - 1>.pt``."""
    return os.path.join(run_dir, f"model_{cfg.max_iterations - 1}.pt")


def stage_overrides(overrides: Sequence[str], stage: str, stages: Sequence[str]) -> list[str]:
    """The command-line overrides that apply to ``stage``, in their order, each without its stage prefix.

    An override ``<stage>:<a.b>=<value>`` applies to that stage only; ``<a.b>=<value>`` to every stage. A prefix
    that names no stage of ``stages`` is an error naming it (a dotted key never holds ``:``; a value may).

    Raises:
        ConfigError: On a prefix that is not one of ``stages``.
    """
    kept = []
    for item in overrides:
        key, eq, value = item.partition("=")
        prefix, colon, dotted = key.partition(":")
        if not colon:
            kept.append(item)
            continue
        if prefix not in stages:
            raise ConfigError(f"override '{item}': '{prefix}' is not a stage of this pipeline (stages: "
                              f"{', '.join(stages)})")  # fmt: skip
        if prefix == stage:
            kept.append(f"{dotted}{eq}{value}")
    return kept
