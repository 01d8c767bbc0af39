"""AnchoredPPO (shield_nav.algorithms.anchored): PPO with a penalty on the actor's drift from a frozen reference."""

import copy
import os
import subprocess
import sys

import pytest
import torch
from rsl_rl.algorithms import PPO
from rsl_rl.models import MLPModel
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from envs.config import ConfigError
from shield_nav.algorithms.anchored import ANCHOR_KEY, AnchoredPPO, _AnchorGradient, anchor_loss
from shield_nav.policies.models import DepthGRUModel
from shield_nav.training import ANCHORED_ALGORITHM, load_train_config, rsl_rl_train_cfg

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
S, A = 5, 4
GROUPS = {"actor": ["depth", "state"], "critic": ["critic"]}
SMALL = {"cnn_channels": [4], "cnn_kernel_sizes": [4], "cnn_strides": [4], "cnn_max_pool": [False],
         "cnn_feature_dim": 8, "rnn_hidden_dim": 16, "hidden_dims": [16]}  # fmt: skip
GAUSS = {"class_name": "GaussianDistribution", "init_std": 0.2}


def _obs(n, gen):
    return TensorDict(
        {"depth": torch.rand(n, 1, 60, 100, generator=gen), "state": torch.randn(n, S, generator=gen),
         "critic": torch.randn(n, 3, generator=gen), "expert": 2 * torch.rand(n, A, generator=gen) - 1},
        batch_size=[n],
    )  # fmt: skip


def test_anchor_loss_and_its_gradient_by_hand():
    mean = torch.tensor([[1.0, 2.0], [0.0, -1.0]])
    ref = torch.tensor([[0.0, 0.0], [0.0, 1.0]])
    assert anchor_loss(mean, ref).item() == pytest.approx((1 + 4 + 0 + 4) / 4)
    # The identity with an added gradient is the gradient of "loss + coef * anchor_loss".
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(3, 5, A, generator=gen, requires_grad=True)
    w, r = torch.randn(3, 5, A, generator=gen), torch.randn(3, 5, A, generator=gen)
    (g_hook,) = torch.autograd.grad((w * _AnchorGradient.apply(x, r, 0.7)).sum(), x)
    (g_ref,) = torch.autograd.grad((w * x).sum() + 0.7 * anchor_loss(x, r), x)
    torch.testing.assert_close(g_hook, g_ref)
    torch.testing.assert_close(g_hook, w + 0.7 * 2 * (x - r).detach() / x.numel())  # d/dx by hand


def _algorithms(n, steps, coef, k=1, **anchored):
    """rsl-rl's PPO and AnchoredPPO(coef) over identical actors; the anchor is the actor *before* a perturbation,
    so that the anchor term has a gradient. Plain SGD without clipping, so one step is ``-lr * gradient``."""
    gen = torch.Generator().manual_seed(1)
    obs = _obs(n, gen)
    torch.manual_seed(0)
    actor = DepthGRUModel(obs, GROUPS, "actor", A, distribution_cfg=GAUSS, num_hypotheses=k, **SMALL)
    critic = MLPModel(obs, GROUPS, "critic", 1, hidden_dims=[8])
    kw = {"num_learning_epochs": 1, "num_mini_batches": 1, "learning_rate": 0.1, "optimizer": "sgd",
          "max_grad_norm": 1e9, "schedule": "fixed", "entropy_coef": 0.0}  # fmt: skip
    ppo = PPO(copy.deepcopy(actor), copy.deepcopy(critic), RolloutStorage("rl", n, steps, obs, [A]), **kw)
    extended = obs.clone()
    extended[ANCHOR_KEY] = torch.zeros(n, A)
    ours = AnchoredPPO(actor, critic, RolloutStorage("rl", n, steps, extended, [A]), anchor_coef=coef, **anchored,
                       **kw)  # fmt: skip
    if ours.anchor_target == "actor_init":
        ours.set_anchor()
    with torch.no_grad():
        for a, b in zip(ours.actor.parameters(), ppo.actor.parameters(), strict=True):
            a.add_(0.05 * torch.randn(a.shape, generator=gen))
            b.copy_(a)
    return ppo, ours


def _rollout(alg, n, steps, done_at=3):
    """The same seeded rollout for any algorithm: env 0 is done at step ``done_at``."""
    gen = torch.Generator().manual_seed(2)
    torch.manual_seed(3)  # the action noise
    obs = _obs(n, gen)
    with torch.inference_mode():
        for t in range(steps):
            alg.act(obs)
            obs = _obs(n, gen)
            dones = torch.zeros(n, dtype=torch.long)
            dones[0] = int(t == done_at)
            alg.process_env_step(obs, torch.randn(n, generator=gen), dones, {})
        alg.compute_returns(obs)


@pytest.mark.parametrize("k", [1, 3])
def test_anchored_update_is_the_ppo_step_plus_the_anchor_gradient(k):
    """Against rsl-rl's own PPO on the same rollout: with coef 0 the same weights; with coef c the weights differ by
    exactly ``-lr * c * grad(anchor_loss)``, computed here by stepping the actor through the rollout by hand."""
    n, steps, coef, lr = 3, 8, 5.0, 0.1
    ppo, zero = _algorithms(n, steps, 0.0, k)
    _rollout(ppo, n, steps)
    _rollout(zero, n, steps)
    ppo_loss, zero_loss = ppo.update(), zero.update()
    assert zero_loss["surrogate"] == pytest.approx(ppo_loss["surrogate"], rel=1e-6)
    assert zero_loss["anchor"] > 0.0  # measured, though not weighted
    for (name, p), q in zip(ppo.actor.named_parameters(), zero.actor.parameters(), strict=True):
        torch.testing.assert_close(p, q, atol=1e-7, rtol=0, msg=name)

    ppo, ours = _algorithms(n, steps, coef, k)
    _rollout(ppo, n, steps)
    _rollout(ours, n, steps)
    before = copy.deepcopy(ours.actor)
    reference = ours.storage.observations[ANCHOR_KEY].clone()  # (T, N, A): the anchor's means in the rollout
    observations, dones = ours.storage.observations.clone(), ours.storage.dones.clone()
    # By hand: the pre-update actor stepped through the stored observations, reset where the env was done.
    before.reset()
    means = []
    for t in range(steps):
        means.append(before(observations[t]))
        before.reset(dones[t].squeeze(-1))
    loss = anchor_loss(torch.stack(means), reference)
    grads = torch.autograd.grad(coef * loss, list(before.parameters()), allow_unused=True)
    ppo.update()
    parts = ours.update()
    assert parts["anchor"] == pytest.approx(loss.item(), rel=1e-5)
    for (name, p), q, g in zip(ppo.actor.named_parameters(), ours.actor.parameters(), grads, strict=True):
        expected = p if g is None else p - lr * g
        torch.testing.assert_close(q, expected, atol=1e-6, rtol=1e-5, msg=name)


@pytest.mark.parametrize("k", [1, 3])
def test_kickstarting_adds_the_gradient_of_the_distillation_loss_towards_the_expert(k):
    """anchor_target 'expert': against rsl-rl's PPO on the same rollout, the weights differ by exactly
    ``-lr * c * grad``, where the loss is the expert's distillation loss computed by hand on the pre-update actor:
    the mean's squared error for one head, ``wta_loss`` over the candidates for K = 3 (not the selected mean's)."""
    n, steps, coef, lr, eps, sel = 3, 8, 5.0, 0.1, 0.1, 0.3
    ppo, ours = _algorithms(n, steps, coef, k, anchor_target="expert", wta_epsilon=eps, selection_coef=sel)
    _rollout(ppo, n, steps)
    _rollout(ours, n, steps)
    observations, dones = ours.storage.observations.clone(), ours.storage.dones.clone()
    torch.testing.assert_close(observations[ANCHOR_KEY], observations["expert"])  # the reference is the expert
    before = copy.deepcopy(ours.actor)
    before.reset()
    outputs = []
    for t in range(steps):
        mean = before(observations[t])
        outputs.append((mean, before.last_hypotheses, before.last_scores) if k > 1 else (mean,))
        before.reset(dones[t].squeeze(-1))
    target = observations["expert"]
    if k == 1:
        loss = (torch.stack([o[0] for o in outputs]) - target).pow(2).mean()
    else:
        hyps = torch.stack([o[1] for o in outputs])  # (T, N, K, A)
        scores = torch.stack([o[2] for o in outputs])  # (T, N, K)
        # wta_loss by hand: per sample the closest candidate gets 1 - eps, the others eps / (K - 1); plus sel x the
        # cross-entropy of the scores against that candidate.
        err = (hyps - target.unsqueeze(-2)).pow(2).mean(-1).reshape(-1, k)
        winner = err.argmin(-1)
        weights = torch.full_like(err, eps / (k - 1))
        weights[torch.arange(len(winner)), winner] = 1 - eps
        logp = torch.log_softmax(scores.reshape(-1, k), -1)
        loss = (weights * err).sum(-1).mean() - sel * logp[torch.arange(len(winner)), winner].mean()
    grads = torch.autograd.grad(coef * loss, list(before.parameters()), allow_unused=True)
    ppo.update()
    parts = ours.update()
    assert parts["anchor"] == pytest.approx(loss.item(), rel=1e-5)
    moved = 0
    for (name, p), q, g in zip(ppo.actor.named_parameters(), ours.actor.parameters(), grads, strict=True):
        expected = p if g is None else p - lr * g
        torch.testing.assert_close(q, expected, atol=1e-6, rtol=1e-5, msg=name)
        moved += int(g is not None and g.abs().max() > 1e-4)
    assert moved >= 4  # the term reaches the encoder, the GRU and the head, not only the last layer
    assert ours.anchor is None and "anchor_state_dict" not in ours.save()  # nothing frozen to keep


def test_kickstarting_without_the_expert_observation_fails_by_name():
    _, ours = _algorithms(3, 8, 1.0, anchor_target="expert")
    obs = _obs(3, torch.Generator().manual_seed(0))
    del obs["expert"]
    with pytest.raises(KeyError, match="runner.expert"), torch.inference_mode():
        ours.act(obs)
    with pytest.raises(ValueError, match="anchor_target"):
        _algorithms(3, 8, 1.0, anchor_target="teacher")


def test_the_anchor_is_saved_and_restored_and_leaves_the_actor_alone():
    n, steps = 3, 8
    _, ours = _algorithms(n, steps, 1.0)
    anchor = {k: v.clone() for k, v in ours.anchor.state_dict().items()}
    _rollout(ours, n, steps)
    ours.update()
    saved = ours.save()
    _, fresh = _algorithms(n, steps, 1.0)
    fresh.anchor = None
    fresh.load(saved, None, strict=True)
    for k, v in anchor.items():
        torch.testing.assert_close(fresh.anchor.state_dict()[k], v)  # the reference, not the trained actor
    assert any(not torch.equal(fresh.actor.state_dict()[k], v) for k, v in anchor.items() if "normalizer" not in k)
    assert all(not p.requires_grad for p in fresh.anchor.parameters())


def test_config_checks_name_the_key():
    def load(*sets):
        return load_train_config("configs/experiments/finetune_3ms_dijkstra_cbf.yaml", list(sets))

    cfg = load()
    assert cfg.runner.algorithm.class_name == ANCHORED_ALGORITHM and cfg.runner.algorithm.anchor_coef > 0
    algorithm = rsl_rl_train_cfg(cfg)["algorithm"]  # rsl-rl PPO's keys plus anchor_coef; no distillation keys
    assert algorithm["anchor_coef"] == cfg.runner.algorithm.anchor_coef and "gradient_length" not in algorithm
    with pytest.raises(ConfigError, match="runner.algorithm.anchor_coef"):
        load("runner.algorithm.anchor_coef=-1")
    with pytest.raises(ConfigError, match="runner.algorithm.anchor_coef"):
        load("runner.algorithm.class_name=PPO")  # a weight PPO would silently ignore
    with pytest.raises(ConfigError, match="runner.actor_init"):
        load("runner.actor_init=")
    with pytest.raises(ConfigError, match="runner.actor.num_hypotheses"):
        load_train_config("configs/train/dijkstra_cbf.yaml", ["runner.actor.num_hypotheses=3"])
    with pytest.raises(ValueError, match="anchor_coef"):
        _algorithms(3, 8, float("nan"))
    kick = load_train_config("configs/train/recipe_dijkstra_cbf.yaml")
    assert kick.runner.algorithm.anchor_target == "expert" and kick.runner.expert.kind == "planner"
    assert rsl_rl_train_cfg(kick)["algorithm"]["anchor_target"] == "expert"
    with pytest.raises(ConfigError, match="runner.algorithm.anchor_target"):
        load("runner.algorithm.anchor_target=oracle")
    with pytest.raises(ConfigError, match="runner.expert.kind"):
        load("runner.algorithm.anchor_target=expert")  # no expert to be held near
    with pytest.raises(ConfigError, match="runner.expert.kind"):
        load("runner.expert.kind=oracle")  # an expert PPO would compute and ignore


def test_train_cli_fine_tunes_the_committed_student_and_a_resume_keeps_its_anchor(tmp_path):
    """train.py end to end with the shipped config: the anchor is the committed student, tensorboard gets
    Loss/anchor, and a resume restores the same anchor from the checkpoint."""
    root = str(tmp_path / "logs")
    small = [
        "--num-envs",
        "4",
        "--log-dir",
        root,
        "--set",
        "runner.num_steps_per_env=8",
        "env.scenes.indices=[0,1]",
        "runner.algorithm.num_mini_batches=2",
        "runner.critic_warmup_iterations=1",
        "runner.save_interval=1",
    ]

    def run(*args):
        return subprocess.run([sys.executable, "train.py", *args], cwd=REPO, capture_output=True, text=True,
                              timeout=240)  # fmt: skip

    res = run(
        "--config",
        "configs/experiments/finetune_3ms_dijkstra_cbf.yaml",
        "--max-iterations",
        "2",
        *small,
        "runner.actor_init=checkpoints/student/model.pt",
    )  # its own start left the tree with the release
    assert res.returncode == 0, res.stderr[-3000:]
    (run_name,) = os.listdir(os.path.join(root, "shield_nav"))
    run_dir = os.path.join(root, "shield_nav", run_name)
    student = torch.load("checkpoints/student/model.pt", weights_only=False)
    student = student.get("student_state_dict") or student["actor_state_dict"]
    ckpt = torch.load(os.path.join(run_dir, "model_1.pt"), weights_only=False)
    assert ckpt["anchor_state_dict"].keys() == student.keys()
    for k, v in student.items():
        torch.testing.assert_close(ckpt["anchor_state_dict"][k], v)
    res = run("--resume", os.path.join(run_dir, "model_1.pt"), "--max-iterations", "3")
    assert res.returncode == 0, res.stderr[-3000:]
    resumed = torch.load(os.path.join(run_dir, "model_2.pt"), weights_only=False)
    for k, v in student.items():
        torch.testing.assert_close(resumed["anchor_state_dict"][k], v)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(run_dir)
    acc.Reload()
    assert sorted({e.step for e in acc.Scalars("Loss/anchor")}) == [0, 1, 2]


def test_train_cli_kickstarts_the_committed_student_with_the_expert(tmp_path):
    """train.py with a shipped recipe (PPO kickstarted by the planning expert): the env adapter computes the expert's
    labels, the actor trains against them after the critic's warm-up, and tensorboard gets Loss/anchor (DAgger's
    loss, > 0)."""
    root = str(tmp_path / "logs")
    res = subprocess.run(
        [sys.executable, "train.py", "--config", "configs/train/recipe_dijkstra_cbf.yaml",
         "--max-iterations", "2", "--num-envs", "4", "--log-dir", root, "--set", "runner.num_steps_per_env=8",
         "env.scenes.indices=[0,1]", "runner.algorithm.num_mini_batches=2", "runner.critic_warmup_iterations=1"],
        cwd=REPO, capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    (run_name,) = os.listdir(os.path.join(root, "shield_nav"))
    run_dir = os.path.join(root, "shield_nav", run_name)
    ckpt = torch.load(os.path.join(run_dir, "model_1.pt"), weights_only=False)
    assert "anchor_state_dict" not in ckpt  # the reference is the expert, not a frozen actor
    start = torch.load("checkpoints/student/model.pt", weights_only=False)
    start = start.get("student_state_dict") or start["actor_state_dict"]
    moved = [k for k, v in ckpt["actor_state_dict"].items() if "normalizer" not in k and not torch.equal(v, start[k])]
    assert moved  # the second iteration (after the warm-up) moved the actor
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(run_dir)
    acc.Reload()
    anchor = acc.Scalars("Loss/anchor")
    assert [e.step for e in anchor] == [0, 1] and all(0.0 < e.value < 10.0 for e in anchor)
    assert os.path.isfile(os.path.join(run_dir, "exported", "policy.onnx"))

    # --resume continues this actor and critic (until 2026-12-05 a run kickstarted by a scripted expert resumed with
    # its optimizer and iteration count but freshly initialised networks): one more update at learning rate 1e-4
    # moves the weights by well under 1 % of their norm; a fresh initialisation lies ~100 % away.
    res = subprocess.run([sys.executable, "train.py", "--resume", os.path.join(run_dir, "model_1.pt"),
                          "--max-iterations", "3"], cwd=REPO, capture_output=True, text=True, timeout=240)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    resumed = torch.load(os.path.join(run_dir, "model_2.pt"), weights_only=False)
    for part in ("actor_state_dict", "critic_state_dict"):
        keys = [k for k, v in ckpt[part].items() if "normalizer" not in k and v.is_floating_point()]
        norm = sum(float((ckpt[part][k].double() ** 2).sum()) for k in keys) ** 0.5
        step = sum(float(((resumed[part][k] - ckpt[part][k]).double() ** 2).sum()) for k in keys) ** 0.5
        assert 0.0 < step / norm < 0.01, (part, step / norm)
