"""The policy ensemble: its exports against the members' own rsl-rl models, its hidden-state layout, its bad input,
and a short flight through the evaluation harness."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from shield_nav import evaluation as E
from shield_nav.policies.models import DepthGRUModel
from shield_nav.tools.ensemble import ExportedEnsemble, build_ensemble, member_checkpoint
from shield_nav.training.actor import actor_from_checkpoint

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# Three real trained depth actors of one observation layout and one training env (the shipped release).
MEMBERS = [os.path.join(ROOT, "checkpoints", n) for n in ("full", "dijkstra_cbf", "student")]


@pytest.fixture(scope="module")
def ensemble_dir(tmp_path_factory):
    return build_ensemble(MEMBERS, str(tmp_path_factory.mktemp("ens") / "ens"))


def test_ensemble_is_the_mean_of_the_members_clipped_actions(ensemble_dir):
    onnx = E.load_policy(ensemble_dir, "ens")
    jit = E.load_policy(os.path.join(ensemble_dir, "policy.pt"), "ens")
    assert onnx.info.kind == "onnx" and jit.info.kind == "torchscript"
    assert (onnx.info.obs_dim, onnx.info.depth_shape, onnx.info.num_layers, onnx.info.hidden_size) == (
        21, (1, 60, 100), 1, 3 * 128)  # fmt: skip
    assert onnx.info.train_speeds == (3.0, 9.0) and onnx.info.train_env is not None
    # The reference: each member's rsl-rl model with its own internal hidden state, clipped, averaged by hand.
    models = [actor_from_checkpoint(member_checkpoint(m))[0] for m in MEMBERS]
    for m in models:
        m.reset()
    rng = np.random.default_rng(1)
    n = 3
    h_onnx, h_jit = onnx.initial_state(n), jit.initial_state(n)
    clipped_somewhere = False
    for _ in range(4):
        state = rng.normal(scale=3.0, size=(n, 21)).astype(np.float32)
        depth = rng.uniform(0.0, 1.0, (n, 1, 60, 100)).astype(np.float32)
        td = TensorDict({"state": torch.from_numpy(state), "depth": torch.from_numpy(depth)}, batch_size=[n])
        with torch.no_grad():
            raw = [m(td, stochastic_output=False).numpy().astype(np.float64) for m in models]
        clipped_somewhere |= any(bool((np.abs(r) > 1.0).any()) for r in raw)
        expected = (np.clip(raw[0], -1, 1) + np.clip(raw[1], -1, 1) + np.clip(raw[2], -1, 1)) / 3.0
        a_onnx, h_onnx = onnx.step(state, depth, h_onnx)
        a_jit, h_jit = jit.step(state, depth, h_jit)
        np.testing.assert_allclose(a_onnx, expected, atol=2e-5)
        np.testing.assert_allclose(a_jit, expected, atol=2e-5)
        # Member k's slice of the ensemble's hidden state is member k's own GRU state.
        for k, m in enumerate(models):
            own = m.get_hidden_state().numpy()
            np.testing.assert_allclose(h_onnx[:, :, 128 * k : 128 * (k + 1)], own, atol=2e-5)
    assert clipped_somewhere, "the inputs should drive some member outside the action box, so the clip is tested"
    with open(os.path.join(ensemble_dir, "meta.json")) as fh:
        meta = json.load(fh)
    assert meta["kind"] == "ensemble" and len(meta["members"]) == 3 and set(meta["sha256"]) >= {"policy.onnx"}


def test_ensemble_of_one_policy_twice_is_that_policy_clipped():
    torch.manual_seed(0)
    obs = TensorDict({"depth": torch.rand(2, 1, 60, 100), "state": torch.randn(2, 21)}, batch_size=[2])
    model = DepthGRUModel(obs, {"actor": ["depth", "state"]}, "actor", 4, rnn_hidden_dim=16,
                          distribution_cfg={"class_name": "GaussianDistribution", "init_std": 1.0})  # fmt: skip
    with torch.no_grad():
        model.mlp[-1].bias.fill_(3.0)  # a mean far outside [-1, 1]
    single = model.as_jit()
    ens = ExportedEnsemble([model.as_jit(), model.as_jit()])
    h = torch.zeros(1, 2, 32)
    a, h2 = ens(obs["state"], obs["depth"], h)
    a1, h1 = single(obs["state"], obs["depth"], torch.zeros(1, 2, 16))
    torch.testing.assert_close(a, torch.clamp(a1, -1, 1))
    torch.testing.assert_close(h2, torch.cat([h1, h1], dim=2))
    assert bool((a == 1.0).all())


def test_ensemble_bad_input_is_named(tmp_path):
    torch.manual_seed(0)
    obs = TensorDict({"depth": torch.rand(1, 1, 60, 100), "state": torch.randn(1, 21)}, batch_size=[1])
    small = DepthGRUModel(obs, {"actor": ["depth", "state"]}, "actor", 4, rnn_hidden_dim=16)
    big = DepthGRUModel(obs, {"actor": ["depth", "state"]}, "actor", 4, rnn_hidden_dim=32)
    with pytest.raises(ValueError, match="member 1 has obs 21, depth .* GRU 1 x 32; member 0 has .* 1 x 16"):
        ExportedEnsemble([small.as_jit(), big.as_jit()])
    with pytest.raises(ValueError, match="at least two members, got 1"):
        ExportedEnsemble([small.as_jit()])
    with pytest.raises(FileNotFoundError, match="'nowhere' does not exist"):
        member_checkpoint("nowhere")
    with pytest.raises(FileNotFoundError, match="holds no model.pt or model_<it>.pt"):
        member_checkpoint(str(tmp_path))
    (tmp_path / "model_2.pt").write_bytes(b"")
    (tmp_path / "model_10.pt").write_bytes(b"")
    assert member_checkpoint(str(tmp_path)) == str(tmp_path / "model_10.pt")  # numerically latest, not by name
    cmd = [sys.executable, "-m", "shield_nav.tools.ensemble", MEMBERS[0], "--out", str(tmp_path / "o")]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 2 and "at least two members, got 1" in res.stderr
    assert not (tmp_path / "o").exists()


def test_ensemble_flies_behind_the_shield_in_the_harness(ensemble_dir, tmp_path):
    cfg = E.load_eval_config(None, ["name=tiny", "configurations=[full]", "scenes.family=ablation",
                                    "scenes.indices=[7]", "speeds=[9.0]", "trials_per_scene=1", "plots=false",
                                    f"checkpoints.full={ensemble_dir}", "network=export",
                                    "env_overrides=[episode.timeout_factor=0.05]"])  # fmt: skip
    E.evaluate(cfg, str(tmp_path / "out"), progress=False)  # an ensemble flies through its export (not fixed_order)
    man = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert man["checkpoints"]["full"]["sha256"] == E.load_policy(ensemble_dir).info.sha256
    (trial,) = json.loads((tmp_path / "out" / "trials.json").read_text())
    assert trial["outcome"] in ("success", "collision", "timeout", "out_of_bounds") and trial["steps"] > 0
    assert trial["shield"]["steps"] == trial["steps"]  # the full row flies it behind the shield
