"""DepthGRUModel: shapes, hidden-state handling, padded-chunk batch mode == step-by-step, exports, one PPO update.

All data is synthetic (TensorDicts of the env's shapes); rsl-rl's own PPO, RolloutStorage and MLPModel are used.
"""

import numpy as np
import onnxruntime as ort
import pytest
import torch
from rsl_rl.algorithms import PPO
from rsl_rl.models import MLPModel
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from shield_nav.policies.export import export_policy
from shield_nav.policies.models import (
    DepthEncoder,
    DepthGRUModel,
    HypothesisSelect,
    expand_single_head,
    expand_state_inputs,
    widen_encoder,
)

S, C_DIM, A = 21, 40, 4  # state, critic and action sizes
GROUPS = {"actor": ["depth", "state"], "critic": ["critic"]}
GAUSS = {"class_name": "GaussianDistribution", "init_std": 0.5, "std_type": "scalar"}
SMALL = {"rnn_hidden_dim": 16, "hidden_dims": [32], "cnn_feature_dim": 16}


def make_obs(n, gen, lead=()):
    shape = (*lead, n)
    return TensorDict(
        {
            "depth": torch.rand(*shape, 1, 60, 100, generator=gen),
            "state": torch.randn(*shape, S, generator=gen),
            "critic": torch.randn(*shape, C_DIM, generator=gen),
        },
        batch_size=list(shape),
    )


def make_actor(n=4, seed=0, **kw):
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    cfg = {**SMALL, **kw}
    model = DepthGRUModel(make_obs(n, gen), GROUPS, "actor", A, distribution_cfg=GAUSS, **cfg)
    # Non-trivial normaliser statistics so the exports must carry them (mean ~ 2, std ~ 3).
    model.update_normalization(TensorDict({"state": 2.0 + 3.0 * torch.randn(256, S, generator=gen)}, [256]))
    return model, gen


def test_encoder_shapes_and_parameter_count_by_hand():
    enc = DepthEncoder((60, 100), 1, (8, 16, 32), (4, 3, 3), (4, 1, 1), (False, True, True), 64)
    # 60x100 -conv4/4-> 15x25 -conv3 (pad 1)-> 15x25 -pool-> 7x12 -conv3-> 7x12 -pool-> 3x6
    assert enc.conv_out_shape == (32, 3, 6)
    assert enc(torch.zeros(5, 1, 60, 100)).shape == (5, 64)
    # conv1 8*1*4*4+8 = 136; conv2 16*8*9+16 = 1168; conv3 32*16*9+32 = 4640; linear 576*64+64 = 36928
    assert sum(p.numel() for p in enc.parameters()) == 136 + 1168 + 4640 + 36928


def test_default_model_parameter_count_by_hand():
    gen = torch.Generator().manual_seed(0)
    m = DepthGRUModel(make_obs(2, gen), GROUPS, "actor", A, distribution_cfg=GAUSS)
    enc = 42872
    gru = 3 * (128 * (S + 64) + 128 * 128 + 2 * 128)  # 3 gates: W_ih (128 x 85), W_hh (128 x 128), two biases
    mlp = (128 * 128 + 128) + (128 * 64 + 64) + (64 * A + A)
    std = A
    assert sum(p.numel() for p in m.parameters()) == enc + gru + mlp + std


def test_shapes_rollout_and_batch_mode():
    m, gen = make_actor(n=5)
    obs = make_obs(5, gen)
    assert m.get_hidden_state() is None
    act = m(obs, stochastic_output=True)
    assert act.shape == (5, A)
    assert m.get_hidden_state().shape == (1, 5, 16)
    assert m.get_output_log_prob(act).shape == (5,)
    # Batch mode: (T, B) padded chunks, masks (T, B); output is unpadded to (T, N_mb, A).
    T = 6
    chunk = make_obs(3, gen, lead=(T,))
    masks = torch.ones(T, 3, dtype=torch.bool)
    out = m(chunk, masks=masks, hidden_state=torch.zeros(1, 3, 16))
    assert out.shape == (T, 3, A)


def test_rejects_bad_group_layouts():
    gen = torch.Generator().manual_seed(0)
    obs = make_obs(2, gen)
    obs["depth2"] = torch.zeros(2, 1, 8, 8)
    with pytest.raises(ValueError, match="exactly one image group"):
        DepthGRUModel(obs, {"actor": ["depth", "depth2", "state"]}, "actor", A)
    with pytest.raises(ValueError, match="at least one 1-D state group"):
        DepthGRUModel(obs, {"actor": ["depth"]}, "actor", A)


def test_reset_on_done_touches_only_done_envs():
    m, gen = make_actor(n=6)
    with torch.inference_mode():
        m(make_obs(6, gen))
        m(make_obs(6, gen))
    before = m.get_hidden_state().clone()
    assert (before.abs().sum(-1) > 0).all()
    dones = torch.tensor([0, 1, 0, 0, 1, 0])
    with torch.inference_mode():  # as in the rollout, where PPO.process_env_step calls reset(dones)
        m.reset(dones)
    after = m.get_hidden_state()
    assert torch.equal(after[:, dones == 1], torch.zeros(1, 2, 16))
    assert torch.equal(after[:, dones == 0], before[:, dones == 0])
    # A full reset clears the state; a given state is installed as is.
    m.reset()
    assert m.get_hidden_state() is None
    m.reset(hidden_state=before)
    assert torch.equal(m.get_hidden_state(), before)


def _fill_storage(m, n, T, gen, dones_tn):
    """Roll the actor step by step like PPO.act/process_env_step; return the storage and per-step means."""
    obs0 = make_obs(n, gen)
    storage = RolloutStorage("rl", n, T, obs0, [A])
    means = torch.zeros(T, n, A)
    m.reset()
    with torch.inference_mode():
        obs = obs0
        for t in range(T):
            tr = RolloutStorage.Transition()
            tr.hidden_states = (m.get_hidden_state(), None)  # recorded before the step, as PPO.act does
            tr.actions = m(obs, stochastic_output=True)
            means[t] = m.output_mean
            tr.values = torch.zeros(n, 1)
            tr.actions_log_prob = m.get_output_log_prob(tr.actions)
            tr.distribution_params = tuple(p.clone() for p in m.output_distribution_params)
            tr.observations = obs
            tr.rewards = torch.zeros(n)
            tr.dones = dones_tn[t]
            storage.add_transition(tr)
            m.reset(dones_tn[t])  # zero the state of envs whose episode ended at this step
            obs = make_obs(n, gen)
    return storage, means


@pytest.mark.parametrize("k", [1, 3])
def test_batched_padded_chunks_equal_step_by_step(k):
    # The PPO update path: storage.recurrent_mini_batch_generator splits the rollout at dones, pads the pieces,
    # and hands the hidden state recorded at each piece's start. The batch forward must equal the rollout.
    n, T = 4, 7
    m, gen = make_actor(n=n, num_hypotheses=k)
    dones = torch.zeros(T, n, dtype=torch.long)
    dones[2, 0] = dones[5, 0] = 1  # env 0: three pieces (3, 3, 1 steps)
    dones[0, 2] = 1  # env 2: a 1-step piece, then 6 steps
    dones[6, 3] = 1  # env 3: ends on the last step
    storage, means = _fill_storage(m, n, T, gen, dones)
    m.reset(hidden_state=torch.full((1, n, 16), 7.0))  # the live state must not leak into the batch pass
    seen = 0
    for batch in storage.recurrent_mini_batch_generator(num_mini_batches=2, num_epochs=1):
        out = m(batch.observations, masks=batch.masks, hidden_state=batch.hidden_states[0])
        lo = seen
        seen += out.shape[1]
        torch.testing.assert_close(out, means[:, lo:seen], rtol=1e-5, atol=1e-5)
        assert batch.masks.sum() == T * out.shape[1]  # every valid step encoded once
    assert seen == n


def test_batch_mode_gradient_flows_to_all_parts():
    m, gen = make_actor(n=3)
    T = 5
    # Two envs over 5 steps; the second one's episode ended after step 3: pieces of 5, 3 and 2 steps.
    chunk = make_obs(3, gen, lead=(T,))
    masks = torch.ones(T, 3, dtype=torch.bool)
    masks[3:, 1] = False
    masks[2:, 2] = False
    out = m(chunk, masks=masks, hidden_state=torch.zeros(1, 3, 16), stochastic_output=True)
    assert out.shape == (T, 2, A)
    m.output_mean.square().sum().backward()
    for name, mod in (("encoder", m.encoder), ("rnn", m.rnn), ("mlp", m.mlp)):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in mod.parameters()), name


@pytest.mark.parametrize("k", [1, 3])
def test_jit_and_onnx_exports_match_torch_actor(tmp_path, k):
    n, steps = 3, 5
    m, gen = make_actor(n=n, num_hypotheses=k)
    if k > 1:  # input-dependent choices: amplify the score rows of the head's last layer and centre them
        with torch.no_grad():
            last = m.mlp[0][-1]
            last.weight[-k:] *= 100.0
            m(make_obs(64, gen))
            last.bias[-k:] -= m.last_scores.mean(0)
            m.reset()
    m.eval()
    picked = set()
    paths = export_policy(m, str(tmp_path))
    jit = torch.jit.load(paths["jit"])
    sess = ort.InferenceSession(paths["onnx"], providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["obs", "depth", "h_in"]
    assert [o.name for o in sess.get_outputs()] == ["actions", "h_out"]
    h_jit = jit.initial_state(n)
    h_onnx = np.zeros((1, n, 16), dtype=np.float32)
    m.reset()
    for t in range(steps):
        obs = make_obs(n, gen)
        with torch.no_grad():
            ref = m(obs)  # deterministic output (the mean)
        if k > 1:  # the exports must pick the candidate the model picked, whichever it is
            picked.update(m.last_scores.argmax(-1).tolist())
            torch.testing.assert_close(ref, m.last_hypotheses[torch.arange(n), m.last_scores.argmax(-1)])
        a_jit, h_jit = jit(obs["state"], obs["depth"], h_jit)
        a_onnx, h_onnx = sess.run(None, {"obs": obs["state"].numpy(), "depth": obs["depth"].numpy(), "h_in": h_onnx})
        torch.testing.assert_close(a_jit, ref, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(a_onnx, ref.numpy(), rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(h_jit, m.get_hidden_state(), rtol=1e-5, atol=1e-5)
        if t == 2:  # env 1's episode ends: every implementation zeroes its row
            dones = torch.tensor([0, 1, 0])
            m.reset(dones)
            h_jit = h_jit.clone()
            h_jit[:, 1] = 0.0
            h_onnx = h_onnx.copy()
            h_onnx[:, 1] = 0.0
    assert k == 1 or len(picked) > 1  # more than one candidate was chosen over the 15 (env, step) pairs
    # The batch is dynamic (the export's example had two rows), and a second export writes the same ONNX bytes.
    big = make_obs(7, gen)
    m.reset()
    with torch.no_grad():
        ref = m(big)
    a7, _ = sess.run(None, {"obs": big["state"].numpy(), "depth": big["depth"].numpy(),
                            "h_in": np.zeros((1, 7, 16), dtype=np.float32)})  # fmt: skip
    np.testing.assert_allclose(a7, ref.numpy(), rtol=1e-4, atol=1e-5)
    again = export_policy(m, str(tmp_path / "again"))
    with open(paths["onnx"], "rb") as f1, open(again["onnx"], "rb") as f2:
        assert f1.read() == f2.read()


def test_one_real_ppo_update_changes_the_actor():
    n, T = 8, 6
    gen = torch.Generator().manual_seed(1)
    torch.manual_seed(1)
    obs = make_obs(n, gen)
    actor = DepthGRUModel(obs, GROUPS, "actor", A, distribution_cfg=GAUSS, **SMALL)
    critic = MLPModel(obs, GROUPS, "critic", 1, hidden_dims=[32], obs_normalization=True)
    storage = RolloutStorage("rl", n, T, obs, [A])
    ppo = PPO(actor, critic, storage, num_learning_epochs=2, num_mini_batches=2, learning_rate=1e-3)
    before = {k: v.clone() for k, v in actor.state_dict().items()}
    with torch.inference_mode():
        for t in range(T):
            ppo.act(obs)
            obs = make_obs(n, gen)
            dones = torch.zeros(n, dtype=torch.long)
            dones[t % n] = 1
            extras = {"time_outs": (torch.arange(n) == (t + 3) % n) & (dones == 1)}
            ppo.process_env_step(obs, torch.randn(n, generator=gen), dones, extras)
        ppo.compute_returns(obs)
    losses = ppo.update()
    assert set(losses) >= {"value", "surrogate", "entropy"}
    assert all(np.isfinite(v) for v in losses.values())
    after = actor.state_dict()
    for k in ("encoder.conv.0.weight", "rnn.rnn.weight_hh_l0", "mlp.0.weight"):
        assert not torch.equal(before[k], after[k]), k
    # PPO updated the state normaliser from the rollout (T * n samples).
    assert int(after["obs_normalizer.count"]) == int(before["obs_normalizer.count"]) + T * n


def test_hypothesis_select_by_hand():
    sel = HypothesisSelect(3, 2)
    # Candidates (1, 2), (3, 4), (5, 6) with scores 0.1, 0.5, 0.2 -> (3, 4); equal scores -> the first candidate.
    x = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.1, 0.5, 0.2], [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.0, 0.0, 0.0]])
    assert torch.equal(sel(x), torch.tensor([[3.0, 4.0], [1.0, 2.0]]))
    hyps, scores = sel.split(x)
    assert torch.equal(hyps[0], torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]))
    assert torch.equal(scores[0], torch.tensor([0.1, 0.5, 0.2]))
    # Leading dims (T, B) are kept: the batch mode of the recurrent update.
    lead = torch.stack([x, x.flip(0)])  # (2, 2, 9)
    assert torch.equal(sel(lead), torch.stack([sel(x), sel(x.flip(0))]))
    with pytest.raises(ValueError, match="num_hypotheses must be >= 1"):
        make_actor(num_hypotheses=0)


def test_multi_hypothesis_head_parameter_count_by_hand():
    single, _ = make_actor()
    multi, _ = make_actor(num_hypotheses=3)
    # Only the head's last layer grows: 32 -> A outputs becomes 32 -> 3 * A + 3 (candidates and scores).
    extra = (32 * (3 * A + 3) + 3 * A + 3) - (32 * A + A)
    assert sum(p.numel() for p in multi.parameters()) == sum(p.numel() for p in single.parameters()) + extra


def test_expand_single_head_starts_every_candidate_as_the_single_head():
    single, gen = make_actor(n=3, seed=4)
    multi, _ = make_actor(n=3, seed=5, num_hypotheses=3)
    multi.load_state_dict(expand_single_head(single.state_dict(), multi, noise_std=0.0))
    single.eval()
    multi.eval()
    with torch.no_grad():
        for _ in range(4):  # the GRU state follows too: same actions step after step
            obs = make_obs(3, gen)
            want = single(obs)
            torch.testing.assert_close(multi(obs), want)
            for c in range(3):
                torch.testing.assert_close(multi.last_hypotheses[:, c], want)
            assert torch.equal(multi.last_scores, torch.zeros(3, 3))
    # With noise the candidates differ (the winner-takes-all loss needs to tell them apart), scores stay zero.
    multi.load_state_dict(expand_single_head(single.state_dict(), multi, noise_std=0.02))
    multi.reset()
    with torch.no_grad():
        multi(make_obs(3, gen))
    h = multi.last_hypotheses
    assert (h[:, 0] - h[:, 1]).abs().max() > 1e-3 and torch.equal(multi.last_scores, torch.zeros(3, 3))
    with pytest.raises(ValueError, match="not a single-head"):
        expand_single_head(multi.state_dict(), multi)


def test_encoder_runs_channels_last_with_the_values_of_a_plain_nchw_stack():
    """The filters are stored channels-last (the speed-up); the features equal an NCHW re-computation.

    Reference: the same weights copied into contiguous (NCHW) tensors and applied with ``F.conv2d`` /
    ``F.max_pool2d`` / ``F.linear`` in float64, so only float summation order may differ. A state dict saved by
    an NCHW encoder (every checkpoint before the change) loads without changing the layout.
    """
    import torch.nn.functional as F

    torch.manual_seed(0)
    enc = DepthEncoder((60, 100), 1, [8, 16, 32], [4, 3, 3], [4, 1, 1], [False, True, True], 64)
    convs = [m for m in enc.conv if isinstance(m, torch.nn.Conv2d)]
    assert all(c.weight.is_contiguous(memory_format=torch.channels_last) for c in convs[1:])  # C_in > 1
    x = torch.rand(5, 1, 60, 100, generator=torch.Generator().manual_seed(1))
    h = x.double()
    for conv, pool in zip(convs, [False, True, True], strict=True):
        w, b = conv.weight.detach().contiguous().double(), conv.bias.detach().double()
        h = F.relu(F.conv2d(h, w, b, stride=conv.stride, padding=conv.padding))
        h = F.max_pool2d(h, 2) if pool else h
    lin = enc.proj[1]
    ref = F.relu(F.linear(h.flatten(1), lin.weight.detach().double(), lin.bias.detach().double()))
    with torch.no_grad():
        got = enc(x)
    assert got.shape == (5, 64)
    assert torch.allclose(got.double(), ref, atol=1e-5, rtol=1e-5)

    plain = {k: v.contiguous() for k, v in enc.state_dict().items()}  # NCHW copies, as older checkpoints hold
    other = DepthEncoder((60, 100), 1, [8, 16, 32], [4, 3, 3], [4, 1, 1], [False, True, True], 64)
    other.load_state_dict(plain)
    assert other.conv[2].weight.is_contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        assert torch.allclose(other(x), got, atol=1e-6)


def test_widen_encoder_starts_as_the_narrow_model_and_then_trains_its_new_channels():
    """A wider encoder warm-started from a narrow one acts as it, then the new channels learn."""
    old, gen = make_actor(n=3, seed=8, cnn_channels=[4, 8, 8], cnn_feature_dim=8)
    torch.manual_seed(9)
    new = DepthGRUModel(make_obs(3, gen), GROUPS, "actor", A, distribution_cfg=GAUSS,
                        **{**SMALL, "cnn_channels": [6, 10, 12], "cnn_feature_dim": 20})  # fmt: skip
    sd = widen_encoder(old.state_dict(), new)
    new.load_state_dict(sd)
    old.eval()
    new.eval()
    with torch.no_grad():
        for _ in range(3):  # the GRU state follows too
            step = make_obs(3, gen)
            torch.testing.assert_close(new(step), old(step))
        # The old filters of conv 2 (layer index 2 in the Sequential: conv, relu, conv) read only the 4 old inputs;
        # the old features read only old channels' 3 x 6 cells (channel-major flatten: the first 8 * 18 columns).
        w2 = sd["encoder.conv.2.weight"]
        assert torch.equal(w2[:8, 4:], torch.zeros(8, 2, 3, 3))
        assert torch.equal(w2[:8, :4], old.state_dict()["encoder.conv.2.weight"])
        assert torch.count_nonzero(w2[8:]) > 0  # the 2 new filters keep their own initial weights
        proj = sd["encoder.proj.1.weight"]
        assert proj.shape == (20, 12 * 18)
        assert torch.equal(proj[:8, 8 * 18 :], torch.zeros(8, 4 * 18))
        assert torch.equal(proj[:8, : 8 * 18], old.state_dict()["encoder.proj.1.weight"])
        gru = sd["rnn.rnn.weight_ih_l0"]  # (3 Hd, S + F): the 12 new features are read through zeros
        assert torch.equal(gru[:, S + 8 :], torch.zeros(3 * SMALL["rnn_hidden_dim"], 12))
    # One gradient step moves the GRU's weights on the new features (their activations are not zero).
    new.train()
    new.reset()
    loss = new(make_obs(3, gen)).square().sum()
    loss.backward()
    assert new.rnn.rnn.weight_ih_l0.grad[:, S + 8 :].abs().sum() > 0
    with pytest.raises(ValueError, match="narrowing is not a warm start"):
        widen_encoder(new.state_dict(), old)
    other, _ = make_actor(n=3, seed=8, cnn_channels=[4, 8, 8], cnn_kernel_sizes=[4, 5, 3], cnn_feature_dim=8)
    with pytest.raises(ValueError, match="convolution 2 is"):
        widen_encoder(other.state_dict(), new)


def test_expand_state_inputs_adds_inputs_that_start_without_effect():
    """A student with a ``memory`` group after ``state`` starts as the student without it (zero weights on it)."""
    old, gen = make_actor(n=3, seed=6)
    torch.manual_seed(7)
    obs = make_obs(3, gen)
    obs["memory"] = torch.rand(3, 5, generator=gen)
    groups = {"actor": ["depth", "state", "memory"], "critic": ["critic"]}
    new = DepthGRUModel(obs, groups, "actor", A, distribution_cfg=GAUSS, **SMALL)
    assert new.obs_dim == S + 5
    new.load_state_dict(expand_state_inputs(old.state_dict(), new))
    old.eval()
    new.eval()
    with torch.no_grad():
        for _ in range(3):  # the GRU state follows too
            step = make_obs(3, gen)
            step["memory"] = torch.rand(3, 5, generator=gen) * 10.0  # any memory: no effect yet
            torch.testing.assert_close(new(step), old(step))
    sd = new.state_dict()
    assert torch.equal(sd["rnn.rnn.weight_ih_l0"][:, S : S + 5], torch.zeros(3 * SMALL["rnn_hidden_dim"], 5))
    torch.testing.assert_close(sd["obs_normalizer._mean"][0, S:], torch.full((5,), 1.0))
    torch.testing.assert_close(sd["obs_normalizer._std"][0, S:], torch.full((5,), 0.25))
    torch.testing.assert_close(sd["obs_normalizer._mean"][0, :S], old.state_dict()["obs_normalizer._mean"][0])
    with pytest.raises(ValueError, match="state has 26 values; the model's 26"):
        expand_state_inputs(new.state_dict(), new)
