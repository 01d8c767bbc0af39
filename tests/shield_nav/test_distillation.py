"""Multi-hypothesis DAgger: the winner-takes-all loss by hand, and rsl-rl's own Distillation / RolloutStorage learning
a two-mode expert (a single head averages the modes, the candidates cover both), plus the config checks."""

import math
import os

import numpy as np
import pytest
import torch
from rsl_rl.algorithms import Distillation
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from envs.config import ConfigError
from shield_nav.algorithms.distillation import (
    MultiHypothesisDistillation,
    ScheduledDistillation,
    scheduled_lr,
    wta_loss,
)
from shield_nav.policies.models import DepthGRUModel, ExpertTeacher
from shield_nav.training import MULTI_HYPOTHESIS_ALGORITHM, SCHEDULED_ALGORITHM, load_train_config

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
S, A = 21, 4
GROUPS = {"student": ["depth", "state"], "teacher": ["expert"]}
SMALL = {"rnn_hidden_dim": 16, "hidden_dims": [32], "cnn_feature_dim": 16}
GAUSS = {"class_name": "GaussianDistribution", "init_std": 0.1, "std_type": "scalar"}


def test_wta_loss_by_hand():
    # Two samples, K = 2 candidates of one action value each.
    hyps = torch.tensor([[[0.0], [1.0]], [[0.0], [1.0]]])
    scores = torch.tensor([[0.0, 0.0], [2.0, 0.0]])
    target = torch.tensor([[0.9], [-0.2]])
    loss, parts = wta_loss(hyps, scores, target, epsilon=0.1, selection_coef=0.5)
    # Sample 1: errors 0.81, 0.01 -> winner 1: 0.9 * 0.01 + 0.1 * 0.81 = 0.09; CE([0, 0], 1) = ln 2; picks 0 (tie).
    # Sample 2: errors 0.04, 1.44 -> winner 0: 0.9 * 0.04 + 0.1 * 1.44 = 0.18; CE([2, 0], 0) = ln(1 + e^-2).
    wta = (0.09 + 0.18) / 2
    ce = (math.log(2.0) + math.log1p(math.exp(-2.0))) / 2
    assert parts["wta"].item() == pytest.approx(wta, abs=1e-6)
    assert parts["selection"].item() == pytest.approx(ce, abs=1e-6)
    assert loss.item() == pytest.approx(wta + 0.5 * ce, abs=1e-6)
    assert parts["chosen"].item() == pytest.approx((0.81 + 0.04) / 2, abs=1e-6)
    assert parts["accuracy"].item() == pytest.approx(0.5)
    # epsilon 0: only the winners' errors count.
    _, parts = wta_loss(hyps, scores, target, epsilon=0.0, selection_coef=0.0)
    assert parts["wta"].item() == pytest.approx((0.01 + 0.04) / 2, abs=1e-6)


def _obs(n, gen, label):
    return TensorDict(
        {"depth": torch.rand(n, 1, 60, 100, generator=gen), "state": torch.randn(n, S, generator=gen),
         "expert": label.expand(n, A).clone()},
        batch_size=[n],
    )  # fmt: skip


def _train_on_two_modes(k, iterations=15, n=8, steps=8, seed=0):
    """DAgger against an expert that says +0.8 or -0.8 at random (nothing in the input tells which)."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)

    def label():
        return torch.where(torch.rand(n, 1, generator=gen) < 0.5, 0.8, -0.8)

    obs = _obs(n, gen, label())
    student = DepthGRUModel(obs, GROUPS, "student", A, distribution_cfg=GAUSS, num_hypotheses=k, **SMALL)
    teacher = ExpertTeacher(obs, GROUPS, "teacher", A)
    storage = RolloutStorage("distillation", n, steps, obs, [A])
    common = {"num_learning_epochs": 2, "gradient_length": 8, "learning_rate": 5e-3}
    if k > 1:
        alg = MultiHypothesisDistillation(student, teacher, storage, wta_epsilon=0.05, selection_coef=0.1, **common)
    else:
        alg = Distillation(student, teacher, storage, **common)
    alg.teacher_loaded = True
    for _ in range(iterations):
        with torch.inference_mode():
            for _ in range(steps):
                alg.act(obs)
                obs = _obs(n, gen, label())
                alg.process_env_step(obs, torch.zeros(n), torch.zeros(n, dtype=torch.long), {})
        losses = alg.update()
    return student, losses, obs


def test_multi_hypothesis_distillation_covers_both_modes_a_single_head_averages():
    single, losses1, obs = _train_on_two_modes(1)
    with torch.no_grad():
        single.eval()
        mean = single(obs)
    # MSE on +-0.8 labels: the single head learns their mean, ~0, with a loss near 0.64.
    assert mean.abs().mean() < 0.25 and losses1["behavior"] > 0.5
    assert ((mean - obs["expert"]) ** 2).mean() > 0.5

    multi, losses, obs = _train_on_two_modes(2)
    assert set(losses) == {"behavior", "wta", "selection", "chosen", "accuracy"}
    assert all(math.isfinite(v) for v in losses.values())
    with torch.no_grad():
        multi.eval()
        multi(obs)
    cand = multi.last_hypotheses  # (n, 2, A)
    hi, lo = cand.mean(-1).max(-1).values, cand.mean(-1).min(-1).values
    # One candidate per mode, for every input; each label is near one of them. (The relaxed loss stays near
    # eps * 1.6^2 = 0.128: the losing candidate sits near the other mode.)
    assert (hi > 0.5).all() and (lo < -0.5).all()
    nearest = ((cand - obs["expert"].unsqueeze(1)) ** 2).mean(-1).min(-1).values
    assert nearest.mean() < 0.05
    assert 0.1 < losses["wta"] < 0.2


def test_multi_hypothesis_algorithm_rejects_a_single_head_and_bad_settings():
    gen = torch.Generator().manual_seed(0)
    obs = _obs(2, gen, torch.zeros(1, A))
    teacher = ExpertTeacher(obs, GROUPS, "teacher", A)
    storage = RolloutStorage("distillation", 2, 4, obs, [A])
    single = DepthGRUModel(obs, GROUPS, "student", A, **SMALL)
    with pytest.raises(ValueError, match="num_hypotheses >= 2"):
        MultiHypothesisDistillation(single, teacher, storage)
    multi = DepthGRUModel(obs, GROUPS, "student", A, num_hypotheses=2, **SMALL)
    with pytest.raises(ValueError, match="wta_epsilon"):
        MultiHypothesisDistillation(multi, teacher, storage, wta_epsilon=1.0)
    with pytest.raises(ValueError, match="selection_coef"):
        MultiHypothesisDistillation(multi, teacher, storage, selection_coef=-1.0)


def test_scheduled_lr_by_hand():
    assert scheduled_lr(7, 1e-3, "constant", 1e-5, 10) == 1e-3
    # cosine: lr_final + (lr - lr_final) (1 + cos(pi u / N)) / 2, N = 10
    assert scheduled_lr(0, 1e-3, "cosine", 1e-5, 10) == pytest.approx(1e-3)
    assert scheduled_lr(5, 1e-3, "cosine", 1e-5, 10) == pytest.approx((1e-3 + 1e-5) / 2)
    at_2 = 1e-5 + 0.99e-3 * (1 + math.cos(0.2 * math.pi)) / 2
    assert scheduled_lr(2, 1e-3, "cosine", 1e-5, 10) == pytest.approx(at_2)
    assert scheduled_lr(10, 1e-3, "cosine", 1e-5, 10) == pytest.approx(1e-5)
    assert scheduled_lr(25, 1e-3, "cosine", 1e-5, 10) == pytest.approx(1e-5)  # held after the cosine
    with pytest.raises(ValueError, match="lr_schedule"):
        scheduled_lr(0, 1e-3, "linear", 1e-5, 10)


def test_scheduled_distillation_sets_the_rate_and_a_resume_continues_it():
    gen = torch.Generator().manual_seed(0)
    n, steps = 4, 4
    obs = _obs(n, gen, torch.zeros(1, A))

    def build():
        torch.manual_seed(0)
        student = DepthGRUModel(obs, GROUPS, "student", A, distribution_cfg=GAUSS, **SMALL)
        teacher = ExpertTeacher(obs, GROUPS, "teacher", A)
        storage = RolloutStorage("distillation", n, steps, obs, [A])
        alg = ScheduledDistillation(student, teacher, storage, learning_rate=1e-3, lr_schedule="cosine",
                                    lr_final=1e-5, lr_schedule_iterations=4, gradient_length=4)  # fmt: skip
        alg.teacher_loaded = True
        return alg

    def one_update(alg):
        with torch.inference_mode():
            for _ in range(steps):
                alg.act(obs)
                alg.process_env_step(obs, torch.zeros(n), torch.zeros(n, dtype=torch.long), {})
        alg.update()
        return alg.learning_rate, alg.optimizer.param_groups[0]["lr"]

    expected = [1e-5 + 0.99e-3 * (1 + math.cos(math.pi * u / 4)) / 2 for u in range(6)]
    alg = build()
    for u in range(2):
        logged, used = one_update(alg)
        assert logged == pytest.approx(expected[u]) and used == pytest.approx(expected[u])
    saved = alg.save()
    assert saved["num_updates"] == 2
    resumed = build()
    assert resumed.load(saved, {"student": True, "optimizer": True, "iteration": True}, strict=True)
    assert [one_update(resumed)[1] for _ in range(4)] == pytest.approx(expected[2:4] + [1e-5, 1e-5])
    warm = build()  # weights only (a warm start): the schedule starts afresh
    warm.load(saved, {"student": True}, strict=True)
    assert one_update(warm)[1] == pytest.approx(1e-3)
    with pytest.raises(ValueError, match="lr_final"):
        ScheduledDistillation(alg.student, alg.teacher, alg.storage, learning_rate=1e-4, lr_schedule="cosine",
                              lr_final=1e-3)  # fmt: skip
    ScheduledDistillation(alg.student, alg.teacher, alg.storage, learning_rate=0.0, gradient_length=4)  # constant


def _filled(alg, n, steps, gen, done_at=3):
    """Collect ``steps`` transitions with fresh random observations; env 0 is done at step ``done_at``."""
    obs = _obs(n, gen, torch.randn(1, A, generator=gen))
    with torch.inference_mode():
        for t in range(steps):
            alg.act(obs)
            obs = _obs(n, gen, torch.randn(1, A, generator=gen))
            dones = torch.zeros(n, dtype=torch.long)
            dones[0] = int(t == done_at)
            alg.process_env_step(obs, torch.zeros(n), dones, {})


def _pair(n, steps, **kwargs):
    """A plain rsl-rl Distillation and a ScheduledDistillation(**kwargs) over identical students."""
    gen = torch.Generator().manual_seed(1)
    obs = _obs(n, gen, torch.zeros(1, A))
    algs = []
    for cls, extra in ((Distillation, {}), (ScheduledDistillation, kwargs)):
        torch.manual_seed(0)
        student = DepthGRUModel(obs, GROUPS, "student", A, distribution_cfg=GAUSS, **SMALL)
        storage = RolloutStorage("distillation", n, steps, obs, [A])
        alg = cls(student, ExpertTeacher(obs, GROUPS, "teacher", A), storage, num_learning_epochs=1,
                  gradient_length=4, learning_rate=1e-3, **extra)  # fmt: skip
        alg.teacher_loaded = True
        algs.append(alg)
    return algs


def test_replaying_a_kept_rollout_is_one_epoch_of_rsl_rl_distillation():
    """A replay pass does exactly what rsl-rl's own update does with one epoch over the same rollout."""
    n, steps = 3, 8
    ref, ours = _pair(n, steps, replay_rollouts=1, replay_passes=1)
    _filled(ref, n, steps, torch.Generator().manual_seed(2))
    rollout = {"observations": ref.storage.observations.clone(), "labels": ref.storage.privileged_actions.clone(),
               "dones": ref.storage.dones.clone(), "hidden": None}  # fmt: skip
    assert rollout["dones"].sum() == 1  # a reset inside the window
    loss = ours._fit_rollout(rollout)
    ref_loss = ref.update()["behavior"]
    assert loss == pytest.approx(ref_loss, rel=1e-6)
    for (name, p), q in zip(ref.student.named_parameters(), ours.student.parameters(), strict=True):
        assert torch.allclose(p, q, atol=1e-7), name


def test_replay_keeps_the_last_rollouts_fits_them_and_leaves_the_live_hidden_state_alone():
    n, steps = 3, 8
    plain, ours = _pair(n, steps, replay_rollouts=2, replay_passes=1)
    for it in range(4):
        for alg in (plain, ours):
            _filled(alg, n, steps, torch.Generator().manual_seed(10 + it))
        out_plain, out = plain.update(), ours.update()
        assert len(ours.replay_buffer) == min(it + 1, 2)
        assert ("replay" in out) == (it > 0) and math.isfinite(out.get("replay", 0.0))
        if it == 1:  # identical weights until the first replay: the live hidden state must match
            assert out["behavior"] == pytest.approx(out_plain["behavior"], rel=1e-6)
            assert torch.allclose(ours.student.get_hidden_state(), plain.student.get_hidden_state(), atol=1e-7)
            pairs = zip(plain.student.parameters(), ours.student.parameters(), strict=True)
            assert any(not torch.equal(p, q) for p, q in pairs)  # the replay pass moved the weights
    assert ours.replay_buffer[-1]["labels"].shape == (steps, n, A)
    with pytest.raises(ValueError, match="replay_passes"):
        ScheduledDistillation(ours.student, ours.teacher, ours.storage, replay_rollouts=2, replay_passes=3)
    with pytest.raises(ValueError, match="replay_passes"):
        ScheduledDistillation(ours.student, ours.teacher, ours.storage, replay_rollouts=2, replay_passes=0)


def test_config_errors_name_the_key():
    path = os.path.join(REPO, "configs", "experiments", "distill_oracle_shapes_3ms_mh.yaml")
    cfg = load_train_config(path)
    assert cfg.runner.actor.num_hypotheses == 3 and cfg.runner.algorithm.class_name == MULTI_HYPOTHESIS_ALGORITHM
    # Distillation's section has no multi-hypothesis keys: the file's first one is named.
    with pytest.raises(ConfigError, match=r"runner\.algorithm\.selection_coef.*not in 'DistillationConfig'"):
        load_train_config(path, overrides=["runner.algorithm.class_name=Distillation"])
    with pytest.raises(ConfigError, match="runner.algorithm.class_name"):
        load_train_config(path, overrides=["runner.actor.num_hypotheses=1"])
    with pytest.raises(ConfigError, match="runner.actor.num_hypotheses"):
        load_train_config(path, overrides=["runner.actor.num_hypotheses=0"])
    with pytest.raises(ConfigError, match="runner.algorithm.wta_epsilon"):
        load_train_config(path, overrides=["runner.algorithm.wta_epsilon=1.5"])
    with pytest.raises(ConfigError, match="runner.algorithm.selection_coef"):
        load_train_config(path, overrides=["runner.algorithm.selection_coef=-0.1"])
    with pytest.raises(ConfigError, match="runner.algorithm.lr_schedule"):
        load_train_config(path, overrides=["runner.algorithm.lr_schedule=linear"])
    with pytest.raises(ConfigError, match="runner.algorithm.lr_final"):
        load_train_config(path, overrides=["runner.algorithm.lr_final=0.1", "runner.algorithm.lr_schedule=cosine"])
    # A constant rate ignores lr_final, even with learning_rate 0 (a frozen student).
    assert load_train_config(path, overrides=["runner.algorithm.learning_rate=0.0"]).runner.algorithm.learning_rate == 0
    single = os.path.join(REPO, "configs", "experiments", "distill_oracle_shapes_3ms.yaml")
    with pytest.raises(ConfigError, match="runner.algorithm.lr_schedule"):  # rsl-rl's Distillation has no schedule
        load_train_config(single, overrides=["runner.algorithm.lr_schedule=cosine"])
    cfg = load_train_config(single, overrides=["runner.algorithm.lr_schedule=cosine",
                                               f"runner.algorithm.class_name={SCHEDULED_ALGORITHM}"])  # fmt: skip
    assert cfg.runner.algorithm.lr_schedule == "cosine"
    with pytest.raises(ConfigError, match="runner.algorithm.replay_rollouts"):
        load_train_config(single, overrides=["runner.algorithm.replay_rollouts=4", "runner.algorithm.replay_passes=1"])
    with pytest.raises(ConfigError, match="runner.algorithm.replay_passes"):
        load_train_config(path, overrides=["runner.algorithm.replay_rollouts=4", "runner.algorithm.replay_passes=5"])
    quick = os.path.join(REPO, "configs", "train", "quick.yaml")
    with pytest.raises(ConfigError, match="runner.actor.num_hypotheses"):
        load_train_config(quick, overrides=["runner.actor.num_hypotheses=3"])


def test_train_cli_warm_starts_a_multi_hypothesis_student_and_exports_it(tmp_path):
    """train.py: a single-head checkpoint initialises the K = 3 student, which trains, resumes (its cosine learning
    rate included) and exports."""
    import subprocess
    import sys

    import onnxruntime as ort

    from shield_nav.training.actor import actor_from_checkpoint

    # A single-head student to start from (none ships in the release): one DAgger iteration from the oracle.
    single = str(tmp_path / "single")
    tiny = ["--num-envs", "4", "--max-iterations", "1", "--set", "runner.num_steps_per_env=8",
            "env.scenes.indices=[0,1]"]  # fmt: skip
    first = [sys.executable, "train.py", "--config", "configs/experiments/distill_oracle.yaml", "--log-dir", single]
    res = subprocess.run([*first, *tiny], cwd=REPO, capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stderr[-3000:]
    (srun,) = os.listdir(os.path.join(single, "shield_nav"))
    start = os.path.join(single, "shield_nav", srun, "model_0.pt")
    root = str(tmp_path / "logs")
    args = [sys.executable, "train.py", "--config", "configs/experiments/distill_oracle_shapes_3ms_mh_cosine.yaml",
            "--log-dir", root, *tiny, f"runner.student_init={start}"]  # fmt: skip
    res = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "single-head student expanded to 3 hypotheses" in res.stdout
    (run,) = os.listdir(os.path.join(root, "shield_nav"))
    run_dir = os.path.join(root, "shield_nav", run)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(run_dir)
    acc.Reload()
    assert {"Loss/behavior", "Loss/chosen", "Loss/accuracy"} <= set(acc.Tags()["scalars"])
    ckpt_path = os.path.join(run_dir, "model_0.pt")
    res = subprocess.run([sys.executable, "train.py", "--resume", ckpt_path, "--max-iterations", "2"], cwd=REPO,
                         capture_output=True, text=True, timeout=240)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "continuing at iteration 1" in res.stdout
    # The cosine spans the first invocation's --max-iterations (1), frozen in the stored config: iteration 0 runs at
    # 1e-3 and the resumed iteration 1 at lr_final (it would restart at 1e-3 if the update count were lost).
    model, cfg, _ = actor_from_checkpoint(os.path.join(run_dir, "model_1.pt"))
    assert cfg.runner.algorithm.lr_schedule_iterations == 1
    acc = EventAccumulator(run_dir)
    acc.Reload()
    rates = {e.step: e.value for e in acc.Scalars("Loss/learning_rate")}
    assert rates[0] == pytest.approx(1e-3) and rates[1] == pytest.approx(1e-5)
    assert model.num_hypotheses == 3
    # The ONNX export flies the best-scored candidate, as the torch model does.
    sess = ort.InferenceSession(os.path.join(run_dir, "exported", "policy.onnx"), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    state = rng.normal(size=(5, S)).astype(np.float32)
    depth = rng.uniform(0, 1, (5, 1, 60, 100)).astype(np.float32)
    act, _ = sess.run(None, {"obs": state, "depth": depth, "h_in": np.zeros((1, 5, 128), np.float32)})
    with torch.no_grad():
        ref = model(TensorDict({"state": torch.from_numpy(state), "depth": torch.from_numpy(depth)}, batch_size=[5]))
    np.testing.assert_allclose(act, ref.numpy(), atol=1e-5)


def test_imitation_gap_metrics_by_hand():
    from shield_nav.tools.imitation import gap_metrics

    # Four samples. Roll (dim 1): the expert turns hard on samples 0-2 (|a| > 0.3): the student turns the other way
    # on sample 0, by less than half on sample 1, fully on sample 2.
    expert = np.zeros((4, 4))
    student = np.zeros((4, 4))
    expert[:, 1] = [0.5, -0.6, 0.4, 0.1]
    student[:, 1] = [-0.1, -0.2, 0.4, 0.1]
    expert[:, 0] = [0.0, 0.2, 0.0, 0.2]  # thrust: student constant 0 -> error 0.04 on two samples
    res = gap_metrics(student, expert)
    roll = res["per_dim"]["roll"]
    assert roll["mse"] == pytest.approx((0.36 + 0.16 + 0 + 0) / 4)
    assert roll["hard_turn_share"] == pytest.approx(0.75)
    assert roll["wrong_sign"] == pytest.approx(1 / 3) and roll["weak"] == pytest.approx(1 / 3)
    assert roll["wrong_sign_mse_share"] == pytest.approx(0.36 / 0.52)
    assert res["per_dim"]["thrust"]["mse"] == pytest.approx(0.02)
    assert res["per_dim"]["thrust"]["expert_var"] == pytest.approx(0.01)
    assert res["per_dim"]["thrust"]["bias"] == pytest.approx(-0.1)
    assert math.isnan(res["per_dim"]["thrust"]["corr"])  # a constant student has no correlation
    assert res["mse"] == pytest.approx((0.52 + 0.08) / 16)
    with pytest.raises(ValueError, match="finite"):
        gap_metrics(student, expert * np.nan)


def test_imitation_selection_metrics_by_hand():
    from shield_nav.tools.imitation import selection_metrics

    # Two envs, three steps, two candidates of one action value. Env 1's episode ends at step 0, so its change of
    # candidate into step 1 is not a switch.
    cands = np.array([[[0.0, 1.0], [0.5, -0.5]], [[0.0, 1.0], [0.5, -0.5]], [[0.2, 1.0], [0.4, -0.5]]])[..., None]
    scores = np.array([[[1.0, 0.0], [0.0, 0.0]], [[0.0, 2.0], [0.0, 1.0]], [[3.0, 0.0], [0.0, 1.5]]])
    expert = np.array([[0.9, 0.5], [0.9, 0.5], [0.0, -0.5]])[..., None]
    dones = np.array([[False, True], [False, False], [False, False]])
    res = selection_metrics(cands, scores, expert, dones)
    # Flown: env 0 candidates 0, 1, 0; env 1 candidates 0 (a tie: the first), 1, 1.
    # Squared errors (flown / nearest): env 0 0.81 / 0.01, 0.01 / 0.01, 0.04 / 0.04; env 1 0 / 0, 1 / 0, 0 / 0.
    assert res["samples"] == 6 and res["candidates"] == 2
    assert res["nearest_share"] == pytest.approx(4 / 6)
    assert res["chosen_mse"] == pytest.approx(1.86 / 6)
    assert res["nearest_mse"] == pytest.approx(0.06 / 6)
    assert res["uniform_mse"] == pytest.approx(5.49 / 12)
    # Score gaps 1, 2, 3 and 0, 1, 1.5.
    assert res["score_gap_median"] == pytest.approx(1.25) and res["score_gap_below_0_5"] == pytest.approx(1 / 6)
    # Three steps follow a step of their episode; env 0 changes on both (jumps 1.0 and 0.8), env 1 stays (jump 0).
    assert res["switch_rate"] == pytest.approx(2 / 3)
    assert res["jump_switch"] == pytest.approx(0.9) and res["jump_stay"] == pytest.approx(0.0)
    assert res["share"] == pytest.approx([0.5, 0.5])
    with pytest.raises(ValueError, match="K >= 2"):
        selection_metrics(cands[:, :, :1], scores[:, :, :1], expert, dones)
    with pytest.raises(ValueError, match="finite"):
        selection_metrics(cands, scores * np.nan, expert, dones)
    with pytest.raises(ValueError, match=r"dones \(T, N\)"):
        selection_metrics(cands, scores, expert, dones[:2])


def test_imitation_cli_on_the_committed_student():
    import json
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-m", "shield_nav.tools.imitation", "checkpoints/student",
                          "--steps", "20", "--num-envs", "4", "--level", "2", "--json"],
                         cwd=REPO, capture_output=True, text=True, timeout=240)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["samples"] == 80 and out["level"] == 2 and out["speed"] == 3.0
    per = out["per_dim"]
    assert out["mse"] == pytest.approx(np.mean([per[k]["mse"] for k in per]))
    # The student was distilled from the planning expert: its samples are split by the expert's route, and the
    # two parts hold every sample in the share reported.
    assert 0.0 <= out["away_share"] <= 1.0
    assert sum(sub["samples"] for sub in out["split"].values()) == 80
    if "away" in out["split"]:
        assert out["split"]["away"]["samples"] == pytest.approx(80 * out["away_share"])
    # The committed student has three candidates and flies the best-scored one: the candidate choice's "flown" error
    # is the imitation error above, and no choice beats always taking the nearest candidate.
    sel = out["selection"]
    assert sel["samples"] == 80 and sel["candidates"] == 3
    assert sel["chosen_mse"] == pytest.approx(out["mse"], rel=1e-5)
    assert sel["nearest_mse"] <= min(sel["chosen_mse"], sel["uniform_mse"])
    assert 0.0 <= sel["nearest_share"] <= 1.0 and 0.0 <= sel["switch_rate"] <= 1.0
    assert sum(sel["share"]) == pytest.approx(1.0)
    res = subprocess.run([sys.executable, "-m", "shield_nav.tools.imitation", "checkpoints/student",
                          "--level", "99"], cwd=REPO, capture_output=True, text=True, timeout=240)  # fmt: skip
    assert res.returncode == 2 and "level must be in [0, 16)" in res.stderr and "Traceback" not in res.stderr
    # An evaluation family is refused by name (its scenes are held out), before any flight.
    res = subprocess.run([sys.executable, "-m", "shield_nav.tools.imitation", "checkpoints/student",
                          "--family", "benchmark"], cwd=REPO, capture_output=True, text=True, timeout=240)  # fmt: skip
    assert res.returncode == 2 and "must be a training family" in res.stderr and "'benchmark'" in res.stderr


def test_imitation_flies_the_requested_level_when_the_checkpoint_trained_without_curriculum(monkeypatch):
    # A student trained with the curriculum off (scenes sampled uniformly per episode) used to be measured on every
    # scene of its list whatever --level said: resets ignored the level. Every episode must be on scene indices[k]
    # (4 envs on 3 scenes all land on the requested one by chance with probability 1/81).
    import shield_nav.training as training
    import shield_nav.training.actor as actor
    from shield_nav.tools.imitation import measure

    real_load, real_make = actor.actor_from_checkpoint, training.make_env

    def load_uniform(path):
        model, cfg, meta = real_load(path)
        cfg.env.curriculum.enabled = False
        cfg.env.scenes.indices = [3, 5, 7]
        return model, cfg, meta

    seen = []

    def make_recording(cfg):
        env = real_make(cfg)
        step = env.step

        def recording_step(actions):
            out = step(actions)
            seen.append([env.env.scenes[int(i)].index for i in env.env.scene_id_buf])
            return out

        env.step = recording_step
        return env

    monkeypatch.setattr(actor, "actor_from_checkpoint", load_uniform)
    monkeypatch.setattr(training, "make_env", make_recording)
    out = measure("checkpoints/student", level=2, steps=40, num_envs=4)
    assert {s for step in seen for s in step} == {7}
    assert out["scene"] == "train_shapes/7" and out["samples"] == 160
