"""Staged recipes (shield_nav/training/pipeline.py): stages in sequence through train.py, resume, bad input."""

import json
import os
import subprocess
import sys

import pytest
import torch
import yaml

from envs.config import ConfigError
from shield_nav.training import pipeline

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
QUICK = os.path.join(REPO, "configs", "train", "quick.yaml")
TINY = ["env.num_envs=4", "runner.num_steps_per_env=8", "runner.save_interval=1"]


def write_pipeline(tmp_path, body):
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(body, sort_keys=False))
    return str(path)


def run_train(args, timeout=300):
    return subprocess.run([sys.executable, "train.py", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip


def test_two_stages_run_in_sequence_and_resume_skips_the_finished_one(tmp_path):
    """Stage 2 starts from stage 1's final checkpoint; a resumed pipeline skips stage 1 and continues stage 2."""
    recipe = write_pipeline(tmp_path, {
        "name": "two",
        "stages": [
            {"name": "first", "config": QUICK, "set": [*TINY, "max_iterations=2"]},
            {"name": "second", "config": QUICK, "set": [*TINY, "max_iterations=3", "runner.actor_init=${first}",
                                                         "runner.critic_warmup_iterations=3",
                                                         "runner.algorithm.schedule=fixed"]},
        ],
    })  # fmt: skip
    root = str(tmp_path / "logs")
    res = run_train(["--config", recipe, "--log-dir", root])
    assert res.returncode == 0, res.stderr[-3000:]
    (folder,) = os.listdir(os.path.join(root, "quick"))
    top = os.path.join(root, "quick", folder)
    assert folder.endswith("_two") and sorted(os.listdir(top)) == ["00_first", "01_second", "pipeline.yaml",
                                                                    "summary.json"]  # fmt: skip
    first = os.path.join(top, "00_first", "model_1.pt")
    assert f"actor initialised from {first}" in res.stdout
    # the second stage's actor is the first stage's final actor (frozen by the critic warm-up, so its weights stay
    # equal; the observation normaliser keeps counting), not a fresh initialisation
    a = torch.load(first, weights_only=False)["actor_state_dict"]
    b = torch.load(os.path.join(top, "01_second", "model_2.pt"), weights_only=False)["actor_state_dict"]
    weights = [k for k in a if not k.startswith("obs_normalizer.")]
    assert len(weights) > 10 and all(torch.equal(a[k], b[k]) for k in weights)
    assert b["obs_normalizer.count"] == a["obs_normalizer.count"] + 3 * 4 * 8
    with open(os.path.join(top, "summary.json")) as f:
        records = json.load(f)["stages"]
    assert [(r["stage"], r["iterations"], r["env_steps"]) for r in records] == [("first", 2, 2 * 4 * 8),
                                                                                 ("second", 3, 3 * 4 * 8)]  # fmt: skip
    assert all(r["train_time_s"] > 0 for r in records)

    # A kill in stage 2 after its first checkpoint: the marker and later checkpoints are gone.
    os.remove(os.path.join(top, "01_second", "stage.json"))
    for it in (1, 2):
        os.remove(os.path.join(top, "01_second", f"model_{it}.pt"))
    before = os.path.getmtime(first)
    res = run_train(["--resume", top])
    assert res.returncode == 0, res.stderr[-3000:]
    assert "stage 1/2 'first': finished before, skipped" in res.stdout
    assert "stage 2/2 'second' (3 iterations): resuming from model_0.pt" in res.stdout
    assert "continuing at iteration 1" in res.stdout
    assert os.path.getmtime(first) == before  # the finished stage was not retrained
    assert torch.load(os.path.join(top, "01_second", "model_2.pt"), weights_only=False)["iter"] == 2
    assert os.path.isfile(os.path.join(top, "01_second", "exported", "policy.onnx"))

    # Moved elsewhere (a folder committed for a later session, another clone) before stage 2 began: stage 2 reads
    # stage 1's checkpoint where it now is; the stored absolute path no longer exists.
    moved = str(tmp_path / "committed" / folder)
    os.makedirs(os.path.dirname(moved))
    os.rename(top, moved)
    subprocess.run(["rm", "-r", os.path.join(moved, "01_second"), os.path.join(moved, "summary.json")], check=True)
    res = run_train(["--resume", moved])
    assert res.returncode == 0, res.stderr[-3000:]
    assert f"actor initialised from {os.path.join(moved, '00_first', 'model_1.pt')}" in res.stdout
    with open(os.path.join(moved, "summary.json")) as f:
        records = json.load(f)["stages"]
    assert [r["checkpoint"] for r in records] == [os.path.join(moved, "00_first", "model_1.pt"),
                                                  os.path.join(moved, "01_second", "model_2.pt")]  # fmt: skip


def test_bad_pipelines_fail_by_key_before_any_folder(tmp_path):
    root = tmp_path / "logs"
    cases = [
        ({"name": "x", "stages": [{"name": "a", "config": QUICK}], "seed": 1}, "pipeline key 'seed'"),
        ({"name": "x", "stages": []}, "pipeline key 'stages'"),
        ({"name": "x", "stages": [{"name": "a", "config": "nope.yaml"}]}, "pipeline key 'stages[0].config'"),
        ({"name": "x", "stages": [{"name": "a", "config": QUICK, "iterations": 3}]}, "'stages[0].iterations'"),
        (
            {"name": "x", "stages": [{"name": "a", "config": QUICK}, {"name": "a", "config": QUICK}]},
            "stage name 'a' is used twice",
        ),
        (
            {
                "name": "x",
                "stages": [
                    {"name": "a", "config": QUICK, "set": ["runner.actor_init=${b}"]},
                    {"name": "b", "config": QUICK},
                ],
            },
            "'${b}'",
        ),  # fmt: skip
    ]
    for body, expected in cases:
        with pytest.raises(ConfigError, match=expected.replace("[", r"\[").replace("$", r"\$")):
            pipeline.load_pipeline(write_pipeline(tmp_path, body))
    # a bad key inside a stage is named with its stage, through train.py, before anything is written
    recipe = write_pipeline(
        tmp_path,
        {
            "name": "x",
            "stages": [
                {"name": "a", "config": QUICK},
                {"name": "b", "config": QUICK, "set": ["env.reward.navigaton=geodesic"]},
            ],
        },
    )
    res = run_train(["--config", recipe, "--log-dir", str(root)], timeout=120)
    assert res.returncode == 2 and "pipeline stage 'b'" in res.stderr and "env.reward.navigaton" in res.stderr
    assert not root.exists()
    # a missing input that no earlier stage produces
    recipe = write_pipeline(
        tmp_path,
        {"name": "x", "stages": [{"name": "a", "config": QUICK, "set": ["runner.actor_init=missing/model.pt"]}]},
    )
    res = run_train(["--config", recipe, "--log-dir", str(root)], timeout=120)
    assert res.returncode == 2 and "runner.actor_init': no such file 'missing/model.pt'" in res.stderr
    assert not root.exists()
    res = run_train(["--config", recipe, "--max-iterations", "5"], timeout=120)
    assert res.returncode == 2 and "--max-iterations" in res.stderr
    res = run_train(["--resume", str(tmp_path)], timeout=120)
    assert res.returncode == 2 and "not a pipeline folder" in res.stderr


def test_shipped_pipelines_resolve_with_every_input_present_or_produced():
    """Every staged recipe in configs/train resolves (typed keys) and each input exists or is an earlier output."""
    folder = os.path.join(REPO, "configs", "train")
    names = [f for f in os.listdir(folder) if pipeline.is_pipeline_file(os.path.join(folder, f))]
    assert "pipeline_full.yaml" in names
    for name in names:
        pipe = pipeline.load_pipeline(os.path.join(REPO, "configs", "train", name))
        configs = pipeline.resolve(pipe, "root")
        produced = {pipeline.final_checkpoint(pipeline.stage_dir("root", i, s), c)
                    for i, (s, c) in enumerate(zip(pipe.stages, configs, strict=True))}  # fmt: skip
        pipeline.check_inputs([s.name for s in pipe.stages], configs, produced)
