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


def run_pipeline(recipe, root):
    """``train.py --config recipe`` under ``root``: (the finished process, its one pipeline folder's name and path)."""
    res = run_train(["--config", recipe, "--log-dir", root])
    assert res.returncode == 0, res.stderr[-3000:]
    (folder,) = os.listdir(os.path.join(root, "quick"))
    return res, folder, os.path.join(root, "quick", folder)


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
    res, folder, top = run_pipeline(recipe, root)
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


def test_choose_keeps_the_most_successes_and_the_lower_seed_on_a_tie():
    def res(*successes, trials=320):
        return [{"successes": s, "trials": trials} for s in successes]

    assert pipeline.choose(res(201, 214, 199)) == 1
    assert pipeline.choose(res(214, 214, 199)) == 0  # a tie keeps the earliest (lowest) seed
    assert pipeline.choose(res(0, 0)) == 0
    assert pipeline.choose(res(7)) == 0
    with pytest.raises(RuntimeError, match="different or no trials"):
        pipeline.choose([{"successes": 5, "trials": 320}, {"successes": 9, "trials": 160}])
    with pytest.raises(RuntimeError, match="different or no trials"):
        pipeline.choose(res(0, 0, trials=0))
    with pytest.raises(ValueError, match="no candidates"):
        pipeline.choose([])


def _pick_eval(tmp_path, **scenes):
    path = tmp_path / "pick.yaml"
    body = {"name": "pick", "configurations": ["dijkstra_cbf"],
            "scenes": {"family": "benchmark", "indices": [0], **scenes}, "speeds": [3.0], "trials_per_scene": 2,
            "plots": False,
            "env_overrides": ["episode.timeout_factor=0.05"]}  # fmt: skip
    path.write_text(yaml.safe_dump(body, sort_keys=False))
    return str(path)


def test_candidates_train_by_seed_fly_validation_and_the_best_is_kept(tmp_path):
    """Two seeds of one stage, each flown on a validation eval; the stage folder holds the kept one; resume works."""
    evalcfg = _pick_eval(tmp_path, seed=1150000)
    recipe = write_pipeline(tmp_path, {
        "name": "pick",
        "stages": [{"name": "ppo", "config": QUICK, "set": [*TINY, "max_iterations=2"], "candidates": 2,
                    "select": {"eval": evalcfg, "configuration": "dijkstra_cbf", "set": ["workers=1"]}}],
    })  # fmt: skip
    root = str(tmp_path / "logs")
    res, folder, top = run_pipeline(recipe, root)
    stage = os.path.join(top, "00_ppo")
    assert {"seed_0", "seed_1", "select_seed_0", "select_seed_1", "selection.json", "stage.json", "model_1.pt",
            "exported", "params"} <= set(os.listdir(stage))  # fmt: skip
    # the candidates differ only in the seed, and the seed is what each checkpoint stored
    ck = [torch.load(os.path.join(stage, f"seed_{s}", "model_1.pt"), weights_only=False) for s in (0, 1)]
    assert [(c["infos"]["config"]["seed"], c["infos"]["config"]["env"]["seed"]) for c in ck] == [(0, 0), (1, 1)]
    a, b = (c["actor_state_dict"] for c in ck)
    assert any(not torch.equal(a[k], b[k]) for k in a if not k.startswith("obs_normalizer."))
    # the selection record against the flights themselves: successes counted from each candidate's trials.json
    counts = []
    for s in (0, 1):
        with open(os.path.join(stage, f"select_seed_{s}", "trials.json")) as f:
            trials = json.load(f)
        assert len(trials) == 2
        counts.append(sum(t["outcome"] == "success" for t in trials))
    with open(os.path.join(stage, "selection.json")) as f:
        sel = json.load(f)
    assert [(c["seed"], c["successes"], c["trials"]) for c in sel["candidates"]] == [(0, counts[0], 2),
                                                                                      (1, counts[1], 2)]  # fmt: skip
    kept = 1 if counts[1] > counts[0] else 0
    assert sel["chosen_seed"] == kept and sel["scene_seed"] == 1150000
    with (
        open(os.path.join(stage, f"seed_{kept}", "model_1.pt"), "rb") as f,
        open(os.path.join(stage, "model_1.pt"), "rb") as g,
    ):
        assert f.read() == g.read()
    with (
        open(os.path.join(stage, f"seed_{kept}", "exported", "policy.onnx"), "rb") as f,
        open(os.path.join(stage, "exported", "policy.onnx"), "rb") as g,
    ):
        assert f.read() == g.read()
    with open(os.path.join(top, "summary.json")) as f:
        (record,) = json.load(f)["stages"]
    assert record["candidates"] == [0, 1] and record["chosen_seed"] == kept
    assert record["env_steps"] == 2 * (2 * 4 * 8) and record["select_time_s"] > 0
    assert f"keeps seed {kept}" in res.stdout

    # A kill while the second candidate trained: it resumes; the first is neither retrained nor re-flown.
    for name in ("stage.json", "selection.json", os.path.join("seed_1", "candidate.json"),
                 os.path.join("seed_1", "model_1.pt")):  # fmt: skip
        os.remove(os.path.join(stage, name))
    before = os.path.getmtime(os.path.join(stage, "seed_0", "model_1.pt"))
    res = run_train(["--resume", top])
    assert res.returncode == 0, res.stderr[-3000:]
    assert "candidate 1/2 (seed 0): finished before, skipped" in res.stdout
    assert "candidate 2/2 (seed 1) (2 iterations): resuming from model_0.pt" in res.stdout
    assert "resuming: 1/1 units already" in res.stdout  # seed 0's validation flights were kept
    assert os.path.getmtime(os.path.join(stage, "seed_0", "model_1.pt")) == before
    assert os.path.isfile(os.path.join(stage, "selection.json"))


def test_bad_selections_fail_by_key_before_any_folder(tmp_path):
    root = tmp_path / "logs"
    good = {"eval": _pick_eval(tmp_path, seed=1150000), "configuration": "full"}
    stage = {"name": "a", "config": QUICK}
    cases = [
        ({**stage, "candidates": 0}, "'stages[0].candidates'"),
        ({**stage, "candidates": "3"}, "'stages[0].candidates'"),
        ({**stage, "candidates": 2}, "needs a 'select'"),
        ({**stage, "select": good}, "a selection needs 'candidates' >= 2"),
        ({**stage, "candidates": 2, "select": {**good, "rows": 1}}, "'stages[0].select.rows'"),
        ({**stage, "candidates": 2, "select": {**good, "eval": "nope.yaml"}}, "'stages[0].select.eval'"),
        ({**stage, "candidates": 2, "select": {**good, "configuration": 3}}, "'stages[0].select.configuration'"),
    ]
    for body, expected in cases:
        with pytest.raises(ConfigError, match=expected.replace("[", r"\[")):
            pipeline.load_pipeline(write_pipeline(tmp_path, {"name": "x", "stages": [body]}))
    # at the start, before any folder: an unknown row, a row without a policy, an eval on the test scenes, a bad
    # eval key (in-process; the first also through train.py, which exits 2 with the message)
    test_scenes = _pick_eval(tmp_path)  # the benchmark family at its own seed: Table II's scenes
    for select, expected in [
        ({**good, "configuration": "fulll"}, "unknown configuration 'fulll'"),
        ({**good, "configuration": "oracle"}, "not a trained policy"),
        ({**good, "eval": test_scenes}, "held-out test scenes"),
        ({**good, "set": ["trials_per_scen=3"]}, "trials_per_scen"),
    ]:
        recipe = write_pipeline(tmp_path, {"name": "x", "stages": [{**stage, "candidates": 2, "select": select}]})
        with pytest.raises(ConfigError, match="pipeline stage 'a': select") as err:
            pipeline.start(pipeline.load_pipeline(recipe), [f"log_root={root}"])
        assert expected in str(err.value)
        assert not root.exists()
    bad = {**stage, "candidates": 2, "select": {**good, "configuration": "fulll"}}
    recipe = write_pipeline(tmp_path, {"name": "x", "stages": [bad]})
    res = run_train(["--config", recipe, "--log-dir", str(root)], timeout=120)
    assert res.returncode == 2 and "pipeline stage 'a': select: unknown configuration 'fulll'" in res.stderr
    assert not root.exists()


def test_chains_train_every_stage_per_seed_and_keep_the_chain_that_flies_best(tmp_path):
    """Two chains of two stages: each chain's second stage starts from its own first stage; each chain's last stage
    is flown on a validation eval; the pipeline folder holds the kept chain's policy; a re-run retrains nothing."""
    evalcfg = _pick_eval(tmp_path, seed=1150000)
    recipe = write_pipeline(tmp_path, {
        "name": "chained",
        "chains": 2,
        "select": {"eval": evalcfg, "configuration": "dijkstra_cbf", "set": ["workers=1"]},
        "stages": [
            {"name": "first", "config": QUICK, "set": [*TINY, "max_iterations=1"]},
            {"name": "second", "config": QUICK, "set": [*TINY, "max_iterations=2", "runner.actor_init=${first}"]},
        ],
    })  # fmt: skip
    root = str(tmp_path / "logs")
    res, folder, top = run_pipeline(recipe, root)
    assert sorted(os.listdir(top)) == ["01_second", "chain_0", "chain_1", "pipeline.yaml", "select_chain_0",
                                       "select_chain_1", "summary.json"]  # fmt: skip
    for k in (0, 1):
        chain = os.path.join(top, f"chain_{k}")
        # every stage of chain k ran with seed k, and its second stage started from its own first stage
        for stage, it in (("00_first", 0), ("01_second", 1)):
            ck = torch.load(os.path.join(chain, stage, f"model_{it}.pt"), weights_only=False)
            assert (ck["infos"]["config"]["seed"], ck["infos"]["config"]["env"]["seed"]) == (k, k)
        assert f"actor initialised from {os.path.join(chain, '00_first', 'model_0.pt')}" in res.stdout
    a, b = (torch.load(os.path.join(top, f"chain_{k}", "01_second", "model_1.pt"), weights_only=False)
            for k in (0, 1))  # fmt: skip
    assert any(not torch.equal(a["actor_state_dict"][n], b["actor_state_dict"][n]) for n in a["actor_state_dict"])
    counts = []
    for k in (0, 1):
        with open(os.path.join(top, f"select_chain_{k}", "trials.json")) as f:
            counts.append(sum(t["outcome"] == "success" for t in json.load(f)))
    kept_dir = os.path.join(top, "01_second")
    with open(os.path.join(kept_dir, "selection.json")) as f:
        sel = json.load(f)
    assert [(c["chain"], c["successes"], c["trials"]) for c in sel["candidates"]] == [(0, counts[0], 2),
                                                                                      (1, counts[1], 2)]  # fmt: skip
    kept = 1 if counts[1] > counts[0] else 0
    assert sel["chosen_chain"] == kept and f"keeps chain {kept}" in res.stdout
    for rel in ("model_1.pt", os.path.join("exported", "policy.onnx")):
        with open(os.path.join(top, f"chain_{kept}", "01_second", rel), "rb") as f, \
                open(os.path.join(kept_dir, rel), "rb") as g:  # fmt: skip
            assert f.read() == g.read()
    with open(os.path.join(top, "summary.json")) as f:
        summary = json.load(f)
    assert summary["chosen_chain"] == kept and summary["checkpoint"] == os.path.join(kept_dir, "model_1.pt")
    assert [[r["stage"] for r in c["stages"]] for c in summary["chains"]] == [["first", "second"]] * 2
    assert summary["train_time_s"] > 0 and summary["select_time_s"] > 0

    # Resumed after it finished: every stage is skipped, the flights are read back, nothing is retrained.
    before = os.path.getmtime(os.path.join(top, "chain_1", "01_second", "model_1.pt"))
    res = run_train(["--resume", top])
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("finished before, skipped") == 4
    assert res.stdout.count("resuming: 1/1 units already") == 2
    assert os.path.getmtime(os.path.join(top, "chain_1", "01_second", "model_1.pt")) == before


def test_bad_chains_fail_by_key_before_any_folder(tmp_path):
    root = tmp_path / "logs"
    good = {"eval": _pick_eval(tmp_path, seed=1150000), "configuration": "full"}
    body = {"name": "x", "stages": [{"name": "a", "config": QUICK}]}
    for extra, expected in [
        ({"chains": 0}, "'chains'"),
        ({"chains": True}, "'chains'"),
        ({"chains": 2}, "'chains: 2' needs a 'select'"),
        ({"select": good}, "a selection needs 'chains' >= 2"),
        ({"chains": 2, "select": {**good, "rows": 1}}, "'select.rows'"),
        ({"chains": 2, "select": {**good, "eval": "nope.yaml"}}, "'select.eval'"),
    ]:
        with pytest.raises(ConfigError, match=expected):
            pipeline.load_pipeline(write_pipeline(tmp_path, {**body, **extra}))
    for select, expected in [
        ({**good, "configuration": "oracle"}, "not a trained policy"),
        ({**good, "eval": _pick_eval(tmp_path)}, "held-out test scenes"),
    ]:
        recipe = write_pipeline(tmp_path, {**body, "chains": 2, "select": select})
        with pytest.raises(ConfigError, match=r"pipeline key 'select' \(chains\)") as err:
            pipeline.start(pipeline.load_pipeline(recipe), [f"log_root={root}"])
        assert expected in str(err.value)
        assert not root.exists()


def test_stage_prefixed_overrides_reach_their_stage_only(tmp_path):
    """``--set <stage>:a.b=v`` changes that stage's config, at start and on resume; a plain override every stage's."""
    recipe = write_pipeline(tmp_path, {
        "name": "two",
        "stages": [
            {"name": "first", "config": QUICK, "set": ["max_iterations=2"]},
            {"name": "second", "config": QUICK, "set": ["max_iterations=3", "runner.actor_init=${first}"]},
        ],
    })  # fmt: skip
    pipe = pipeline.load_pipeline(recipe)
    given = ["second:max_iterations=7", "env.num_envs=6", "first:runner.algorithm.class_name=PPO"]
    assert pipeline.stage_overrides(given, "first", ["first", "second"]) == [
        "env.num_envs=6",
        "runner.algorithm.class_name=PPO",
    ]
    assert pipeline.stage_overrides(given, "second", ["first", "second"]) == ["max_iterations=7", "env.num_envs=6"]
    # a colon in the value is not a prefix; one in the key is
    value = "runner.algorithm.class_name=shield_nav.algorithms.anchored:AnchoredPPO"
    assert pipeline.stage_overrides([value, f"second:{value}"], "first", ["first", "second"]) == [value]
    assert pipeline.stage_overrides([value, f"second:{value}"], "second", ["first", "second"]) == [value, value]
    first, second = pipeline.resolve(pipe, "root", given)
    assert (first.max_iterations, second.max_iterations) == (2, 7)  # the stage's own 3, then the prefixed 7
    assert (first.env.num_envs, second.env.num_envs) == (6, 6)
    # the second stage's input is the first stage's final checkpoint, whose name follows the first's 2 iterations
    assert second.runner.actor_init == os.path.join("root", "00_first", "model_1.pt")

    root = pipeline.start(pipe, [f"log_root={tmp_path / 'logs'}", "first:seed=11"])
    names, (a, b) = pipeline.load_stored(root, ["second:env.num_envs=8"])
    assert names == ["first", "second"] and (a.seed, b.seed) == (11, 0)  # quick.yaml keeps base.yaml's seed 0
    assert (a.env.num_envs, b.env.num_envs) == (16, 8)  # quick.yaml's 16 envs; the resume's override on the second
    for bad in (["third:seed=1"], ["firs:env.num_envs=2"]):
        with pytest.raises(ConfigError, match=f"'{bad[0].partition(':')[0]}' is not a stage of this pipeline"):
            pipeline.resolve(pipe, "root", bad)
        with pytest.raises(ConfigError, match="is not a stage of this pipeline"):
            pipeline.load_stored(root, bad)
    # through train.py: refused before any folder, and refused on a single run, both naming the override
    logs = tmp_path / "fresh"
    res = run_train(["--config", recipe, "--log-dir", str(logs), "--set", "thrid:seed=3"], timeout=120)
    assert res.returncode == 2 and "override 'thrid:seed=3': 'thrid' is not a stage" in res.stderr
    assert not logs.exists()
    res = run_train(["--config", QUICK, "--log-dir", str(logs), "--set", "first:seed=3"], timeout=120)
    assert res.returncode == 2 and "override 'first:seed=3': a '<stage>:' prefix applies to a pipeline" in res.stderr
    assert not logs.exists()
