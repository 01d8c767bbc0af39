"""Every shipped YAML config loads against its schema (strict keys) and names only known rows/classes."""

import glob
import os

import pytest

from shield_nav import evaluation as E
from shield_nav.training import load_train_config, rsl_rl_train_cfg
from shield_nav.training import pipeline as P

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.parametrize("path", sorted(glob.glob(os.path.join(REPO, "configs", "train", "*.yaml")))
                         + sorted(glob.glob(os.path.join(REPO, "configs", "experiments", "*.yaml"))))  # fmt: skip
def test_train_configs_load(path):
    """The release configs and the experiments' (whose start checkpoints may have left the tree) load strictly.

    A pipeline file is checked stage by stage: each stage's config resolves (``${stage}`` references included).
    """
    if P.is_pipeline_file(path):
        pipeline = P.load_pipeline(path)
        configs = P.resolve(pipeline, "/nonexistent-root")
        assert len(configs) == len(pipeline.stages) >= 1
        for cfg in configs:
            _check_train_config(cfg, path)
        for stage in pipeline.stages:  # a stage that keeps the best of its seeds flies them on validation scenes
            if stage.select is not None:
                ecfg = P.selection_eval_config(stage.name, stage.select)
                assert ecfg.scenes.seed is not None and ecfg.configurations == [stage.select.configuration]
        if pipeline.chains > 1:  # so does a pipeline that keeps the best of its chains
            ecfg = P.selection_eval_config("", pipeline.select, where="chains")
            assert ecfg.scenes.seed is not None and ecfg.configurations == [pipeline.select.configuration]
        return
    _check_train_config(load_train_config(path), path)


def _check_train_config(cfg, path):
    d = rsl_rl_train_cfg(cfg)
    if cfg.runner.class_name == "DistillationRunner":
        assert {"student", "teacher"} <= set(d) and "critic" not in d
        if cfg.runner.expert.kind:  # a scripted expert labels the states: no map, no teacher checkpoint
            assert d["obs_groups"]["teacher"] == ["expert"] and not cfg.env.local_map.enabled
        else:
            assert cfg.env.local_map.enabled
            assert cfg.runner.teacher_checkpoint or os.path.basename(path) == "distill.yaml"  # the shared partial
    else:
        assert {"actor", "critic"} <= set(d)
    if os.path.basename(path).startswith("teacher_"):
        assert not cfg.env.render_depth and d["actor"]["class_name"] == "MLPModel"
        assert "cnn_channels" not in d["actor"]  # keys MLPModel does not take are dropped


@pytest.mark.parametrize("path", sorted(glob.glob(os.path.join(REPO, "configs", "eval", "*.yaml"))))
def test_eval_configs_load_and_name_known_rows(path):
    cfg = E.load_eval_config(path)
    rows = E.resolve_rows(cfg)
    for row in rows.values():
        if row.controller == "policy":
            assert row.policy in cfg.checkpoints
