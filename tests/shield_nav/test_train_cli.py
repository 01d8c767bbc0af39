"""train.py end to end (subprocess, the real task with 4 envs on 2 scenes): run folder, resume, bad keys, SIGTERM."""

import dataclasses
import hashlib
import json
import os
import signal
import subprocess
import sys
import warnings

import numpy as np
import onnxruntime as ort
import pytest
import torch

from envs.config import stored_config
from shield_nav.provenance import cpu_model, cpu_simd
from shield_nav.training import CHECKPOINT_FORMAT_VERSION, TrainConfig, load_train_config, read_checkpoint_infos

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TINY = ["--config", "configs/train/quick.yaml", "--num-envs", "4", "--set", "runner.num_steps_per_env=8"]


def run_train(args, timeout=240):
    return subprocess.run(
        [sys.executable, "train.py", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout
    )


def only_run_dir(root):
    runs = [os.path.join(root, "quick", d) for d in os.listdir(os.path.join(root, "quick"))]
    assert len(runs) == 1, runs
    return runs[0]


def scalar_steps(run_dir, tag):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(run_dir)
    acc.Reload()
    return sorted({e.step for e in acc.Scalars(tag)})


def test_quick_run_writes_events_checkpoint_exports_and_resume_continues(tmp_path):
    root = str(tmp_path / "logs")
    res = run_train([*TINY, "--max-iterations", "2", "--log-dir", root])
    assert res.returncode == 0, res.stderr[-3000:]
    run = only_run_dir(root)
    files = set(os.listdir(run))
    assert {"params", "git", "exported", "model_0.pt", "model_1.pt"} <= files
    assert any(f.startswith("events.out.tfevents") for f in files)
    assert os.path.isfile(os.path.join(run, "params", "config.yaml"))
    assert os.listdir(os.path.join(run, "git"))  # revision + diff of this repository
    assert scalar_steps(run, "Loss/value") == [0, 1]
    assert scalar_steps(run, "reward/navigation") == [0, 1]  # the env's extras["log"] reached tensorboard
    infos = read_checkpoint_infos(os.path.join(run, "model_1.pt"))
    assert infos["format_version"] == CHECKPOINT_FORMAT_VERSION
    assert infos["config"]["env"]["num_envs"] == 4 and infos["config"]["name"] == "quick"
    assert infos["packages"]["torch"] == torch.__version__ and infos["packages"]["numpy"] == np.__version__
    assert infos["cpu_model"] == cpu_model() and infos["cpu_simd"] == cpu_simd()
    assert infos["cpu_kernels"] == torch.backends.cpu.get_cpu_capability()  # e.g. AVX2 / AVX512
    assert torch.load(os.path.join(run, "model_1.pt"), weights_only=False)["iter"] == 1

    # The exported actor runs in onnxruntime on the env's shapes with an explicit GRU state.
    sess = ort.InferenceSession(os.path.join(run, "exported", "policy.onnx"), providers=["CPUExecutionProvider"])
    state_dim = sess.get_inputs()[0].shape[1]
    h = np.zeros((1, 2, 128), np.float32)
    act, h = sess.run(
        None, {"obs": np.zeros((2, state_dim), np.float32), "depth": np.ones((2, 1, 60, 100), np.float32), "h_in": h}
    )
    assert act.shape == (2, 4) and np.isfinite(act).all() and h.shape == (1, 2, 128)
    # exported/source.json names the checkpoint the export was made from, with its sha256.
    with open(os.path.join(run, "exported", "source.json")) as f:
        source = json.load(f)
    with open(os.path.join(run, "model_1.pt"), "rb") as f:
        assert source == {"checkpoint": "model_1.pt", "iteration": 1, "sha256": hashlib.sha256(f.read()).hexdigest()}

    # Resume: same folder, iteration count and curves continue at 2.
    res = run_train(["--resume", os.path.join(run, "model_1.pt"), "--max-iterations", "3"])
    assert res.returncode == 0, res.stderr[-3000:]
    assert "continuing at iteration 2" in res.stdout
    assert "curriculum levels restored" in res.stdout
    assert len(read_checkpoint_infos(os.path.join(run, "model_1.pt"))["curriculum_levels"]) == 4
    assert only_run_dir(root) == run
    ckpt = torch.load(os.path.join(run, "model_2.pt"), weights_only=False)
    assert ckpt["iter"] == 2
    with open(os.path.join(run, "exported", "source.json")) as f:
        assert json.load(f)["checkpoint"] == "model_2.pt"  # the resumed run's export
    assert ckpt["infos"]["tot_timesteps"] == 3 * 4 * 8  # 3 iterations x 4 envs x 8 steps, across both processes
    assert scalar_steps(run, "Loss/value") == [0, 1, 2]


def test_repeated_set_flags_all_apply():
    from shield_nav.training import build_parser, config_from_args

    quick = os.path.join(REPO, "configs", "train", "quick.yaml")
    args = build_parser().parse_args(["--config", quick, "--set", "seed=3", "env.num_envs=8", "--set", "name=other"])
    cfg = config_from_args(args)
    assert (cfg.seed, cfg.env.num_envs, cfg.name) == (3, 8, "other")  # the first --set is not dropped by the second


def test_bad_config_key_fails_fast_with_the_key_path(tmp_path):
    root = str(tmp_path / "logs")
    res = run_train([*TINY, "--set", "env.reward.navigaton=geodesic", "--log-dir", root], timeout=120)
    assert res.returncode == 2
    assert "env.reward.navigaton" in res.stderr
    assert not os.path.exists(root)  # nothing was built or written
    res = run_train([*TINY, "--set", "runner.algorithm.num_mini_batches=3", "--log-dir", root], timeout=120)
    assert res.returncode == 2 and "runner.algorithm.num_mini_batches" in res.stderr


def test_the_cli_checks_a_config_without_importing_torch(tmp_path):
    """--help, a bad key and a good config's checks run on the light path (shield_nav.training.cli): torch, rsl-rl
    and tensordict (~5 s of imports) are loaded only to train. Checked in a fresh interpreter, which records what
    the CLI imported before it returned."""
    probe = (
        "import sys\n"
        "from shield_nav.training.cli import build_parser, config_from_args\n"
        "from shield_nav.training.checks import check_files\n"
        "from shield_nav import training\n"
        "assert training.load_train_config is not None and 'train' in dir(training)\n"
        "cfg = config_from_args(build_parser().parse_args(sys.argv[1:]))\n"
        "check_files(cfg)\n"
        "print(sorted(m for m in ('torch', 'rsl_rl', 'tensordict') if m in sys.modules))\n"
    )
    res = subprocess.run([sys.executable, "-c", probe, "--config", "configs/train/recipe_full.yaml"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"
    # The lazy names resolve to the objects of the modules that define them.
    from shield_nav import training
    from shield_nav.training import checks, cli, config, rsl_rl_cfg, runner

    modules = {"checks": checks, "cli": cli, "config": config, "rsl_rl_cfg": rsl_rl_cfg, "runner": runner}
    for name in training.__all__:
        assert getattr(training, name) is getattr(modules[training._WHERE[name]], name), name
    with pytest.raises(AttributeError, match="no_such_name"):
        training.no_such_name  # noqa: B018


@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
def test_sigterm_saves_a_checkpoint_and_exports(tmp_path):
    root = str(tmp_path / "logs")
    proc = subprocess.Popen(
        [sys.executable, "-u", "train.py", *TINY, "--max-iterations", "10000", "--log-dir", root],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if "Learning iteration 0/" in line:
                proc.send_signal(signal.SIGTERM)
                break
        out = proc.communicate(timeout=180)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, "".join(lines) + out
    run = only_run_dir(root)
    saved = sorted(f for f in os.listdir(run) if f.startswith("model_"))
    last = max(saved, key=lambda f: int(f[6:-3]))
    infos = read_checkpoint_infos(os.path.join(run, last))
    assert infos["interrupted"] is True
    assert os.path.isfile(os.path.join(run, "exported", "policy.onnx"))


def test_teacher_then_distillation_with_rsl_rl_runners(tmp_path):
    """A privileged MLP teacher (PPO, nothing rendered), then the CNN+GRU student distilled from it."""
    root = str(tmp_path / "logs")
    small = ["--num-envs", "4", "--max-iterations", "1", "--log-dir", root, "--set", "runner.num_steps_per_env=8",
             "env.scenes.indices=[0,1]"]  # fmt: skip
    res = run_train(["--config", "configs/experiments/teacher_dijkstra_cbf.yaml", *small, "runner.save_interval=1",
                     "runner.algorithm.num_mini_batches=2"])  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "not exported: the policy is a MLPModel" in res.stdout  # a privileged teacher is not deployable
    (teacher_dir,) = [os.path.join(root, "shield_nav", d) for d in os.listdir(os.path.join(root, "shield_nav"))]
    teacher_ckpt = os.path.join(teacher_dir, "model_0.pt")
    assert not os.path.exists(os.path.join(teacher_dir, "exported"))

    res = run_train(["--config", "configs/experiments/distill_dijkstra_cbf.yaml", *small,
                     f"runner.teacher_checkpoint={teacher_ckpt}"])  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    (student_dir,) = [d for d in os.listdir(os.path.join(root, "shield_nav")) if d.endswith("_distilled")]
    student_dir = os.path.join(root, "shield_nav", student_dir)
    ckpt = torch.load(os.path.join(student_dir, "model_0.pt"), weights_only=False)
    teacher = torch.load(teacher_ckpt, weights_only=False)["actor_state_dict"]
    for k, v in teacher.items():  # the teacher's weights were loaded, unchanged by distillation
        torch.testing.assert_close(ckpt["teacher_state_dict"][k], v)
    assert scalar_steps(student_dir, "Loss/behavior") == [0]
    onnx_path = os.path.join(student_dir, "exported", "policy.onnx")
    sess = ort.InferenceSession(onnx_path, providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()][1] == "depth"  # the deployable student reads depth, not the map

    # Re-distillation warm start: runner.student_init loads that student (learning rate 0 keeps it as loaded).
    res = run_train(["--config", "configs/experiments/distill_dijkstra_cbf.yaml", *small, "--set", "name=warm",
                     f"runner.teacher_checkpoint={teacher_ckpt}", "runner.algorithm.learning_rate=0.0",
                     f"runner.student_init={os.path.join(student_dir, 'model_0.pt')}"])  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "student initialised from" in res.stdout and "curriculum levels restored" in res.stdout
    (warm_dir,) = [os.path.join(root, "shield_nav", d) for d in os.listdir(os.path.join(root, "shield_nav"))
                   if d.endswith("_warm")]  # fmt: skip
    warm = torch.load(os.path.join(warm_dir, "model_0.pt"), weights_only=False)["student_state_dict"]
    assert warm.keys() == ckpt["student_state_dict"].keys()
    for k, v in ckpt["student_state_dict"].items():
        if "normalizer" not in k:  # the observation normaliser keeps updating its running statistics
            torch.testing.assert_close(warm[k], v)

    # A warm start onto uniform sampling over one scene (curriculum off): the stored levels, which may name the
    # second scene, are not installed (they used to raise when they did not fit the new scene list).
    res = run_train(["--config", "configs/experiments/distill_dijkstra_cbf.yaml", *small, "env.scenes.indices=[1]",
                     "env.curriculum.enabled=false", "name=uniform", f"runner.teacher_checkpoint={teacher_ckpt}",
                     f"runner.student_init={os.path.join(student_dir, 'model_0.pt')}"])  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "curriculum off: the levels stored in" in res.stdout and "curriculum levels restored" not in res.stdout

    # Packaging: the teacher without exports (not deployable), the student with an ONNX that matches its weights.
    from shield_nav.tools.package import package
    from shield_nav.training.actor import actor_from_checkpoint

    out_t = package(teacher_ckpt, "teacher", str(tmp_path / "ck"))
    assert "policy.onnx" not in os.listdir(out_t) and actor_from_checkpoint(teacher_ckpt)[0] is None
    out_s = package(os.path.join(student_dir, "model_0.pt"), "student", str(tmp_path / "ck"))
    model, _, meta = actor_from_checkpoint(os.path.join(out_s, "model.pt"))
    assert meta["iter"] == 0
    for k, v in model.state_dict().items():
        torch.testing.assert_close(v, ckpt["student_state_dict"][k])
    sess = ort.InferenceSession(os.path.join(out_s, "policy.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(1)
    state = rng.normal(size=(2, 21)).astype(np.float32)
    depth = rng.uniform(0, 1, (2, 1, 60, 100)).astype(np.float32)
    act, _ = sess.run(None, {"obs": state, "depth": depth, "h_in": np.zeros((1, 2, 128), np.float32)})
    from tensordict import TensorDict

    with torch.no_grad():
        ref = model(TensorDict({"state": torch.from_numpy(state), "depth": torch.from_numpy(depth)}, batch_size=[2]))
    np.testing.assert_allclose(act, ref.numpy(), atol=1e-5)


def tiny_actor(tmp_path):
    """A one-iteration TINY PPO run's checkpoint path and actor weights (the source of a warm start)."""
    root = str(tmp_path / "logs")
    res = run_train([*TINY, "--max-iterations", "1", "--log-dir", root])
    assert res.returncode == 0, res.stderr[-3000:]
    src_path = os.path.join(only_run_dir(root), "model_0.pt")
    return src_path, torch.load(src_path, weights_only=False)["actor_state_dict"]


def test_actor_init_widens_a_narrower_actor_onto_a_clock_input_and_the_deadline_terminates(tmp_path):
    """PPO from a 21-value actor onto ``[depth, state, clock]``: the clock enters through zero weights."""
    src_path, src = tiny_actor(tmp_path)
    root2 = str(tmp_path / "logs2")
    res = run_train([*TINY, "--max-iterations", "1", "--log-dir", root2, "--set", "env.episode.deadline=terminate",
                     "env.episode.clock_input=true", "runner.obs_groups.actor=[depth,state,clock]",
                     f"runner.actor_init={src_path}", "runner.critic_warmup_iterations=1",
                     "runner.algorithm.schedule=fixed"])  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "actor state widened from 21 to 22 values" in res.stdout
    ckpt = torch.load(os.path.join(only_run_dir(root2), "model_0.pt"), weights_only=False)
    widened = ckpt["actor_state_dict"]
    w_old, w_new = src["rnn.rnn.weight_ih_l0"], widened["rnn.rnn.weight_ih_l0"]  # (3 Hd, S + F)
    assert w_new.shape[1] == w_old.shape[1] + 1
    # The actor was frozen for the critic's warm-up iteration: the old inputs' weights as loaded, the clock's zero.
    torch.testing.assert_close(w_new[:, :21], w_old[:, :21])
    torch.testing.assert_close(w_new[:, 22:], w_old[:, 21:])
    assert (w_new[:, 21] == 0).all()
    sess = ort.InferenceSession(os.path.join(only_run_dir(root2), "exported", "policy.onnx"),
                                providers=["CPUExecutionProvider"])  # fmt: skip
    assert sess.get_inputs()[0].shape[1] == 22


def test_actor_init_widens_a_narrower_depth_encoder_and_refuses_a_wider_one(tmp_path):
    """PPO from the 8-16-32 / 64 encoder onto 12-16-48 / 80: it flies as the source; the other way is a clear error."""
    src_path, src = tiny_actor(tmp_path)
    wide = ["runner.actor.cnn_channels=[12,16,48]", "runner.actor.cnn_feature_dim=80"]
    root2 = str(tmp_path / "logs2")
    res = run_train([*TINY, "--max-iterations", "1", "--log-dir", root2, "--set", *wide,
                     f"runner.actor_init={src_path}", "runner.critic_warmup_iterations=1",
                     "runner.algorithm.schedule=fixed"])  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "actor depth encoder widened from [8, 16, 32, 64] to [12, 16, 48, 80]" in res.stdout
    wide_path = os.path.join(only_run_dir(root2), "model_0.pt")
    widened = torch.load(wide_path, weights_only=False)["actor_state_dict"]
    # Frozen for the critic's warm-up iteration: the old filters as loaded, the new features read through zeros.
    torch.testing.assert_close(widened["encoder.conv.0.weight"][:8], src["encoder.conv.0.weight"])
    torch.testing.assert_close(widened["encoder.proj.1.weight"][:64, : 32 * 18], src["encoder.proj.1.weight"])
    assert (widened["rnn.rnn.weight_ih_l0"][:, 21 + 64 :] == 0).all()
    sess = ort.InferenceSession(os.path.join(only_run_dir(root2), "exported", "policy.onnx"),
                                providers=["CPUExecutionProvider"])  # fmt: skip
    rng = np.random.default_rng(2)
    feed = {"obs": rng.normal(size=(2, 21)).astype(np.float32),
            "depth": rng.uniform(0, 1, (2, 1, 60, 100)).astype(np.float32),
            "h_in": np.zeros((1, 2, 128), np.float32)}  # fmt: skip
    act, _ = sess.run(None, feed)  # the wider export runs (its equality to the source: test_models)
    assert act.shape == (2, 4) and np.isfinite(act).all()
    # The wider actor onto the default encoder: refused by name before any work.
    res = run_train([*TINY, "--max-iterations", "1", "--log-dir", str(tmp_path / "logs3"), "--set",
                     f"runner.actor_init={wide_path}"])  # fmt: skip
    assert res.returncode == 2 and "runner.actor.cnn_channels" in res.stderr and "[12, 16, 48]" in res.stderr
    assert not os.path.exists(tmp_path / "logs3")  # refused before a run folder or an env was made


def test_distillation_inputs_fail_fast(tmp_path):
    root = str(tmp_path / "logs")
    res = run_train(["--config", "configs/experiments/distill_dijkstra_cbf.yaml", "--log-dir", root,
                     "--set", "runner.teacher_checkpoint=nowhere/model.pt"], timeout=120)  # fmt: skip
    assert res.returncode == 2 and "runner.teacher_checkpoint" in res.stderr and "nowhere/model.pt" in res.stderr
    res = run_train([*TINY, "--log-dir", root, "--set", "runner.class_name=DistillationRunner"], timeout=120)
    assert res.returncode == 2 and "runner.algorithm.class_name" in res.stderr
    res = run_train([*TINY, "--log-dir", root, "--set", "runner.obs_groups.actor=[teacher]"], timeout=120)
    assert res.returncode == 2 and "env.local_map.enabled" in res.stderr
    res = run_train(["--config", "configs/experiments/distill_dijkstra_cbf.yaml", "--log-dir", root, "--set",
                     "runner.teacher_checkpoint=checkpoints/student/model.pt",
                     "runner.student_init=nowhere/student.pt"], timeout=120)  # fmt: skip
    assert res.returncode == 2 and "runner.student_init" in res.stderr and "nowhere/student.pt" in res.stderr
    res = run_train([*TINY, "--log-dir", root, "--set", "runner.student_init=checkpoints/dijkstra_cbf/model.pt"])
    assert res.returncode == 2 and "runner.student_init" in res.stderr and "DistillationRunner" in res.stderr
    assert not os.path.exists(root)  # nothing was started


def test_a_failed_export_keeps_the_checkpoint_and_says_how_to_re_export(tmp_path, monkeypatch, capsys):
    import shield_nav.policies.export
    from shield_nav.training import load_train_config, train

    def broken_export(*args, **kwargs):
        raise RuntimeError("simulated export failure")

    monkeypatch.setattr(shield_nav.policies.export, "export_policy", broken_export)
    small = ["env.num_envs=4", "max_iterations=1", f"log_root={tmp_path}", "runner.num_steps_per_env=8",
             "runner.algorithm.num_mini_batches=2"]  # fmt: skip
    cfg = load_train_config(os.path.join(REPO, "configs", "train", "quick.yaml"), overrides=small)
    with pytest.raises(RuntimeError, match="simulated export failure"):
        train(cfg)
    run_dir = only_run_dir(str(tmp_path))
    assert os.path.isfile(os.path.join(run_dir, "model_0.pt"))
    err = capsys.readouterr().err
    assert f"python -m shield_nav.tools.package {os.path.join(run_dir, 'model_0.pt')}" in err


def _is_pipeline(name):
    from shield_nav.training.pipeline_file import is_pipeline_file

    return is_pipeline_file(os.path.join(REPO, "configs", "train", name))


TRAIN_CONFIGS = sorted(
    f for f in os.listdir(os.path.join(REPO, "configs", "train")) if f.endswith(".yaml") and not _is_pipeline(f)
)  # staged recipes: tests/.../test_pipeline.py


@pytest.mark.parametrize("name", TRAIN_CONFIGS)
def test_shipped_train_configs_load_and_their_inputs_exist(name):
    """Every shipped train config passes the checks run before training, and the committed files it starts from exist
    (a partial base such as finetune.yaml may leave its actor_init to the configs that include it)."""
    from shield_nav.training import load_train_config

    cfg = load_train_config(os.path.join(REPO, "configs", "train", name))
    r = cfg.runner
    for key in ("actor_init", "student_init"):
        path = getattr(r, key)
        assert not path or os.path.isfile(os.path.join(REPO, path)), f"{name}: runner.{key} {path!r} missing"
    if name in ("recipe_distance.yaml", "recipe_dijkstra.yaml", "recipe_dijkstra_cbf.yaml"):
        # the shipped formulations: PPO at 3-9 m/s from the shipped student, kickstarted by the planning expert; the
        # three differ in the reward only (and the expert's narrow field, see recipe_dijkstra_cbf.yaml)
        assert cfg.env.scenes.family == "train_shapes" and r.expert.kind == "planner"
        assert sorted(set(cfg.env.episode.target_speeds)) == [3.0, 5.0, 7.0, 9.0]
        assert r.algorithm.anchor_target == "expert" and r.actor_init == "checkpoints/student/model.pt"
        want = {"recipe_distance.yaml": "euclidean"}.get(name, "geodesic")
        assert cfg.env.reward.navigation == want
        assert (cfg.env.reward.scales["safety"] > 0) == (name == "recipe_dijkstra_cbf.yaml")
    if name == "recipe_full.yaml":  # the Dijkstra + CBF recipe, trained behind the shield (0.5 m radius)
        from envs.config import to_dict

        base = to_dict(load_train_config(os.path.join(REPO, "configs", "train", "recipe_dijkstra_cbf.yaml")))
        full = to_dict(cfg)
        assert {k for k in full if full[k] != base[k]} == {"name", "seed", "env", "shield_in_loop", "shield"}
        assert cfg.shield_in_loop and cfg.seed == 1 and cfg.env.seed == 1
        # its env differs from the formulation's in the seed, the training time limit (the evaluation's 1.5 x) and
        # the shield's commands flown without the action latency, as the shipped run was trained
        assert {k for k in full["env"] if full["env"][k] != base["env"][k]} == {"seed", "episode", "randomization"}
        rnd, base_rnd = full["env"]["randomization"], base["env"]["randomization"]
        assert {k for k in rnd if rnd[k] != base_rnd[k]} == {"command_latency"}
        assert not cfg.env.randomization.command_latency and base["env"]["randomization"]["command_latency"]
        assert {k for k in full["env"]["episode"] if full["env"]["episode"][k] != base["env"]["episode"][k]} == {
            "timeout_factor"}  # fmt: skip
        assert cfg.env.episode.timeout_factor == 1.5 and base["env"]["episode"]["timeout_factor"] == 2.5
        # the shield it trains behind: the default but for the radius, memory, planned braking deceleration and
        # ground row the shipped run was trained with, and no local map (the deploy defaults changed after it: 0.3 m,
        # 50 steps, a_b 10, ground row at 0.35 m, a 2 s local map)
        assert {k for k in full["shield"] if full["shield"][k] != base["shield"][k]} == {
            "r_safe", "memory_steps", "brake_accel", "min_altitude", "map_seconds"}  # fmt: skip
        assert cfg.shield.r_safe == 0.5 and cfg.shield.memory_steps == 0 and cfg.shield.brake_accel == 8.0
        assert cfg.shield.min_altitude == 0.0 and cfg.shield.map_seconds == 0.0
        ckpt = torch.load(os.path.join(REPO, "checkpoints", "full", "model.pt"), weights_only=False)
        # the recipe rebuilds the shipped run: its stored config, read back with the defaults of any keys added since,
        # equals the recipe but for the name and the folder the run was written under (--log-dir)
        infos = read_checkpoint_infos(os.path.join(REPO, "checkpoints", "full", "model.pt"))  # as every reader does
        stored = to_dict(load_train_config(overrides=stored_config(TrainConfig, infos["config"])))
        assert {k for k in full if full[k] != stored.get(k)} <= {"name", "log_root"}
        assert not ckpt["infos"]["config"]["shield"]["passing"] and not cfg.shield.passing
    else:
        assert not cfg.shield_in_loop
    if name == "recipe_student.yaml":  # DAgger from the planning expert at 3-9 m/s, from the shipped third cycle
        assert r.class_name == "DistillationRunner" and r.expert.kind == "planner"
        assert r.student_init == "checkpoints/student_cycle3/model.pt"
        assert sorted(set(cfg.env.episode.target_speeds)) == [3.0, 5.0, 7.0, 9.0]


def test_runs_started_in_the_same_second_get_their_own_folders(tmp_path, monkeypatch):
    """Seeds launched together must not share (and overwrite) one run folder."""
    import datetime

    from shield_nav.training import load_train_config
    from shield_nav.training import runner as training  # the module that stamps run folders

    frozen = datetime.datetime(2026, 1, 2, 3, 4, 5)

    class Clock(datetime.datetime):
        @classmethod
        def now(cls, tz=None):
            return frozen

    monkeypatch.setattr(training.datetime, "datetime", Clock)
    cfg = load_train_config(os.path.join(REPO, "configs", "train", "quick.yaml"))
    cfg.log_root = str(tmp_path)
    dirs = [training._new_run_dir(cfg) for _ in range(3)]
    stem = os.path.join(str(tmp_path), cfg.experiment_name, f"2026-01-02_03-04-05_{cfg.name}")
    assert dirs == [stem, stem + "_2", stem + "_3"]
    assert all(os.path.isdir(os.path.join(d, "params")) for d in dirs)


def test_truncated_resume_checkpoint_fails_fast_by_name(tmp_path):
    """A checkpoint cut short by an interrupted copy: a clear error naming --resume, no traceback, no run folder."""
    good = os.path.join(REPO, "checkpoints", "student", "model.pt")
    cut = tmp_path / "model_10.pt"
    with open(good, "rb") as f:
        cut.write_bytes(f.read()[:5000])
    root = tmp_path / "logs"
    res = run_train([*TINY, "--log-dir", str(root), "--resume", str(cut)], timeout=120)
    assert res.returncode == 2
    assert "--resume" in res.stderr and "not a readable torch checkpoint" in res.stderr and "5000 bytes" in res.stderr
    assert "Traceback" not in res.stderr
    assert not root.exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_on_a_machine_without_it_fails_before_any_folder(tmp_path):
    root = tmp_path / "logs"
    res = run_train([*TINY, "--log-dir", str(root), "--device", "cuda"], timeout=120)
    assert res.returncode == 2
    assert "config key 'device'" in res.stderr and "--device cpu" in res.stderr
    assert "Traceback" not in res.stderr and "AssertionError" not in res.stderr
    assert not root.exists()


def test_progress_line_by_hand():
    from types import SimpleNamespace

    from shield_nav.training import episode_means, progress_line

    extras = [{"episode/success": torch.tensor([1.0, 0.0]), "curriculum/mean_level": torch.tensor(3.0)},
              {"episode/success": torch.tensor(1.0), "curriculum/mean_level": torch.tensor(5.0)}, {}]  # fmt: skip
    means = episode_means(extras, ("episode/success", "curriculum/mean_level"))
    assert means["episode/success"] == (pytest.approx(2 / 3), 3)
    assert means["curriculum/mean_level"] == (pytest.approx(4.0), 2)
    # 10 iterations done of 40 in 100 s with 30,720 steps: 307 steps/s, ETA 30 x 10 s = 0:05:00.
    logger = SimpleNamespace(tot_timesteps=30720, tot_time=100.0)
    line = progress_line(logger, 9, 40, means)
    assert line == (
        "[train] it 10/40 |     307 env-steps/s | success  66.7 % of   3 ep | level  4.00 | "
        "0:01:40 elapsed, ETA 0:05:00"
    )
    empty = progress_line(logger, 9, 40, episode_means([], ("episode/success",)))
    assert "no episode ended" in empty and "level   -  " in empty


def test_inapplicable_algorithm_key_fails_by_name(tmp_path):
    """runner.algorithm is typed by its class_name: a key of another algorithm is an unknown key naming it, from
    the command line and from a file; the same key on the algorithm that defines it loads."""
    from envs.config import ConfigError
    from shield_nav.training import (
        MultiHypothesisDistillationConfig,
        PPOConfig,
        load_train_config,
    )

    with pytest.raises(ConfigError, match=r"runner\.algorithm\.wta_epsilon.*not in 'PPOConfig'"):
        load_train_config(os.path.join(REPO, "configs/train/dijkstra_cbf.yaml"),
                          overrides=["runner.algorithm.wta_epsilon=0.9"])  # fmt: skip
    mh = load_train_config(os.path.join(REPO, "configs/experiments/distill_oracle_shapes_3ms_mh.yaml"),
                           overrides=["runner.algorithm.wta_epsilon=0.9"])  # fmt: skip
    assert type(mh.runner.algorithm) is MultiHypothesisDistillationConfig and mh.runner.algorithm.wta_epsilon == 0.9
    ppo = load_train_config(os.path.join(REPO, "configs/train/dijkstra_cbf.yaml"))
    assert type(ppo.runner.algorithm) is PPOConfig and not hasattr(ppo.runner.algorithm, "gradient_length")
    with pytest.raises(ConfigError, match=r"runner\.algorithm\.class_name': unknown algorithm 'SAC'"):
        load_train_config(overrides=["runner.algorithm.class_name=SAC"])
    # A PPO-only key on a distillation run, from a file: named with the file it came from.
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"defaults: [{REPO}/configs/experiments/distill_oracle_shapes_3ms_mh.yaml]\n"
                   "runner:\n  algorithm:\n    clip_param: 0.1\n")  # fmt: skip
    with pytest.raises(ConfigError, match=r"runner\.algorithm\.clip_param' \(from .*bad\.yaml\)"):
        load_train_config(bad)
    res = run_train([*TINY, "--set", "runner.algorithm.replay_rollouts=4"], timeout=120)
    assert res.returncode == 2 and "runner.algorithm.replay_rollouts" in res.stderr


def test_algorithm_sections_match_their_classes():
    """Every key of a typed section is a constructor parameter of its class (the runner passes the section as it
    is), and each section's class_name default is its own registry name."""
    import inspect

    from rsl_rl.utils import resolve_callable

    from shield_nav.training import ALGORITHM_CONFIGS

    for name, schema in ALGORITHM_CONFIGS.items():
        assert schema().class_name == name
        takes: set[str] = set()
        for klass in resolve_callable(name).__mro__:
            if "__init__" in vars(klass):
                takes |= set(inspect.signature(vars(klass)["__init__"]).parameters)
        missing = [f.name for f in dataclasses.fields(schema) if f.name not in takes and f.name != "class_name"]
        assert not missing, (name, missing)


def test_format_1_checkpoint_config_is_migrated(tmp_path):
    """A format-1 checkpoint stored the flat algorithm section: its keys outside the class's section are dropped
    (they were dropped by the runner when it trained), with a warning for one that was not at the flat default;
    the migrated config loads and keeps the values of the keys the class defines."""
    from shield_nav.training import PPOConfig, load_train_config, migrate_flat_algorithm

    flat = {"class_name": "PPO", "learning_rate": 1e-4, "clip_param": 0.3, "gradient_length": 24,
            "loss_type": "mse", "wta_epsilon": 0.05, "lr_schedule": "constant", "replay_rollouts": 0,
            "anchor_coef": 0.0}  # fmt: skip
    stored = {"name": "old", "runner": {"algorithm": flat}}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # defaults only: no warning
        out = migrate_flat_algorithm(stored)
    assert out["runner"]["algorithm"] == {"class_name": "PPO", "learning_rate": 1e-4, "clip_param": 0.3}
    assert stored["runner"]["algorithm"]["gradient_length"] == 24  # the input is not mutated
    cfg = load_train_config(overrides=out)
    assert type(cfg.runner.algorithm) is PPOConfig and cfg.runner.algorithm.clip_param == 0.3
    with pytest.warns(UserWarning, match=r"runner\.algorithm\.wta_epsilon = 0\.9 was not taken by 'PPO'"):
        migrate_flat_algorithm({"runner": {"algorithm": {**flat, "wta_epsilon": 0.9}}})


def test_stored_config_reads_a_pre_hysteresis_config_as_it_ran():
    """A stored config without runner.expert.params.expert.commit_dist ran without route hysteresis: read back, it
    gets 0 (ExpertConfig.PRE_FIELD_VALUES), not today's default; a stored value is kept; other absent keys take
    their defaults; the input is left as it is."""
    from envs.config import to_dict

    full = to_dict(TrainConfig())
    assert full["runner"]["expert"]["params"]["expert"]["commit_dist"] == 1.0
    del full["runner"]["expert"]["params"]["expert"]["commit_dist"], full["runner"]["expert"]["params"]["expert"]["k_v"]
    back = load_train_config(overrides=stored_config(TrainConfig, full))
    assert back.runner.expert.params.expert.commit_dist == 0.0 and back.runner.expert.params.expert.k_v == 4.0
    assert "commit_dist" not in full["runner"]["expert"]["params"]["expert"]
    full["runner"]["expert"]["params"]["expert"]["commit_dist"] = 2.5
    assert load_train_config(overrides=stored_config(TrainConfig, full)).runner.expert.params.expert.commit_dist == 2.5


def test_weight_averaging_writes_the_mean_actor_as_the_final_checkpoint_and_resumes(tmp_path):
    """``runner.average_iterations=2`` of 4: model_3.pt holds the mean of iterations 2 and 3's actors."""
    root = str(tmp_path / "logs")
    args = [*TINY, "--max-iterations", "4", "--log-dir", root, "--set", "runner.save_interval=1",
            "runner.average_iterations=2"]  # fmt: skip
    res = run_train(args)
    assert res.returncode == 0, res.stderr[-3000:]
    run = only_run_dir(root)

    def check(run):
        raw2 = torch.load(os.path.join(run, "model_2.pt"), weights_only=False)  # saved inside the window
        last = torch.load(os.path.join(run, "snapshot_3.pt"), weights_only=False)
        final = torch.load(os.path.join(run, "model_3.pt"), weights_only=False)
        assert raw2["infos"]["weight_average"]["iterations"] == [2]
        assert final["iter"] == 3 and final["infos"]["weight_average"] == {"first": 2, "last": 3, "count": 2,
                                                                           "applied": True}  # fmt: skip
        a, b, m = raw2["actor_state_dict"], last["actor_state_dict"], final["actor_state_dict"]
        moved = 0
        for k, v in m.items():
            if k == "obs_normalizer._std":
                torch.testing.assert_close(v, torch.sqrt(m["obs_normalizer._var"]))
            elif v.is_floating_point():
                torch.testing.assert_close(v, ((a[k].double() + b[k].double()) / 2).float())
                moved += not torch.equal(a[k], b[k])
            else:
                assert torch.equal(v, b[k])  # the normaliser's count: the last iteration's
        assert moved >= 10  # the two iterations' actors differ, so the mean is neither of them
        torch.testing.assert_close(final["critic_state_dict"], last["critic_state_dict"])  # the critic: the last
        with open(os.path.join(run, "exported", "source.json")) as f:
            source = json.load(f)
        with open(os.path.join(run, "model_3.pt"), "rb") as f:
            assert source["checkpoint"] == "model_3.pt" and source["sha256"] == hashlib.sha256(f.read()).hexdigest()
        return m

    check(run)
    assert "model_3.pt holds the mean actor of iterations 2-3" in res.stdout
    # A kill after iteration 2: resume from model_2.pt continues the stored mean (iteration 2 is not retrained).
    for f in ("model_3.pt", "snapshot_3.pt"):
        os.remove(os.path.join(run, f))
    res = run_train(["--resume", os.path.join(run, "model_2.pt"), "--max-iterations", "4"])
    assert res.returncode == 0, res.stderr[-3000:]
    assert "the mean of iterations 2-3 (1 averaged so far)" in res.stdout
    check(run)
    # Resuming the finished run averages nothing twice.
    res = run_train(["--resume", os.path.join(run, "model_3.pt"), "--max-iterations", "4"])
    assert res.returncode == 0, res.stderr[-3000:]
    assert "already holds the average of iterations 2-3" in res.stdout
    check(run)


def test_weight_averaging_longer_than_the_run_or_past_a_resume_fails_by_name(tmp_path):
    res = run_train([*TINY, "--max-iterations", "3", "--log-dir", str(tmp_path), "--set",
                     "runner.average_iterations=4"])  # fmt: skip
    assert res.returncode != 0
    assert "runner.average_iterations" in res.stderr and "got 4" in res.stderr
    assert not os.path.exists(os.path.join(tmp_path, "quick"))
    # A run trained without averaging, resumed after iteration 1 with an average of iterations 1-3: iteration 1 is
    # not in the checkpoint, so the resume is refused before it trains anything.
    res = run_train([*TINY, "--max-iterations", "2", "--log-dir", str(tmp_path)])
    assert res.returncode == 0, res.stderr[-3000:]
    run = only_run_dir(str(tmp_path))
    res = run_train(["--resume", os.path.join(run, "model_1.pt"), "--max-iterations", "4", "--set",
                     "runner.average_iterations=3"])  # fmt: skip
    assert res.returncode != 0
    assert "runner.average_iterations" in res.stderr and "needs iteration 1 on" in res.stderr
    assert not os.path.exists(os.path.join(run, "model_2.pt"))


def test_resuming_a_packaged_policy_continues_under_logs_not_its_trainers_log_root(tmp_path):
    """A checkpoint without a run folder (a packaged policy) stored its trainer's log_root, a path of that machine:
    ``--resume`` continues in a new run folder under ``logs`` of the working directory, or under ``--log-dir``."""
    trained = str(tmp_path / "trainer_machine")
    res = run_train([*TINY, "--max-iterations", "2", "--log-dir", trained])
    assert res.returncode == 0, res.stderr[-3000:]
    package = tmp_path / "package"
    package.mkdir()
    with open(os.path.join(only_run_dir(trained), "model_1.pt"), "rb") as f:
        (package / "model.pt").write_bytes(f.read())
    work = tmp_path / "work"
    work.mkdir()
    res = subprocess.run([sys.executable, os.path.join(REPO, "train.py"), "--resume", str(package / "model.pt"),
                          "--max-iterations", "3"], cwd=work, capture_output=True, text=True, timeout=240)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "is not in a run folder; continuing in a new one under 'logs'" in res.stdout
    assert f"the stored log_root {trained!r}" in res.stdout
    run = only_run_dir(str(work / "logs"))
    assert torch.load(os.path.join(run, "model_2.pt"), weights_only=False)["iter"] == 2
    assert len(os.listdir(os.path.join(trained, "quick"))) == 1  # nothing new where it was trained
    assert sorted(os.listdir(package)) == ["model.pt"]  # nor beside the packaged policy
    chosen = str(tmp_path / "chosen")
    res = run_train(["--resume", str(package / "model.pt"), "--max-iterations", "3", "--log-dir", chosen])
    assert res.returncode == 0, res.stderr[-3000:]
    assert "is not in a run folder" not in res.stdout
    assert torch.load(os.path.join(only_run_dir(chosen), "model_2.pt"), weights_only=False)["iter"] == 2
