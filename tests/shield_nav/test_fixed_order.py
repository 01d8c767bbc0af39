"""The fixed-order network runtime (``network: fixed_order``): its exponential against libm, its actor against the
TorchScript export it reads (an independent implementation), the same bits from a baseline x86-64 build as from the
host build, refusals that name what they do not run, and a flight through the harness."""

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from envs.config import ConfigError
from shield_nav import evaluation as E
from shield_nav.evaluation.fixed_order import ACTIVATIONS, FixedOrderActor, fixed_exp

torch = pytest.importorskip("torch")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _export(out_dir, num_hypotheses=1, seed=0):
    from tensordict import TensorDict

    from shield_nav.policies.export import export_policy
    from shield_nav.policies.models import DepthGRUModel

    torch.manual_seed(seed)
    obs = TensorDict({"depth": torch.rand(2, 1, 60, 100), "state": torch.randn(2, 21)}, [2])
    model = DepthGRUModel(obs, {"actor": ["depth", "state"]}, "actor", 4, rnn_hidden_dim=16,
                          num_hypotheses=num_hypotheses,
                          distribution_cfg={"class_name": "GaussianDistribution", "init_std": 0.5})  # fmt: skip
    with torch.no_grad():  # a normaliser that is not the identity, so its arithmetic is checked too
        model.obs_normalizer._mean.copy_(torch.linspace(-0.5, 0.5, 21))
        model.obs_normalizer._std.copy_(torch.linspace(0.5, 2.0, 21))
        if num_hypotheses > 1:  # scores far apart, so the choice is not decided by the last bits
            model.mlp[0][-1].bias[-num_hypotheses:] = torch.arange(num_hypotheses, dtype=torch.float32)[[1, 2, 0]] * 3
    return export_policy(model, os.path.join(out_dir, "exported"))


def _inputs(n=5, seed=1):
    rng = np.random.default_rng(seed)
    state = rng.normal(size=(n, 21)).astype(np.float32)
    depth = rng.uniform(size=(n, 1, 60, 100)).astype(np.float32)
    h = rng.normal(size=(1, n, 16)).astype(np.float32) * 0.5
    return state, depth, h


def test_fixed_exp_against_libm_and_at_its_edges():
    xs = np.concatenate((np.linspace(-740.0, 709.0, 20001), np.linspace(-1.0, 1.0, 2001), [0.5 * math.log(2)]))
    got = np.array([fixed_exp(float(x)) for x in xs])
    want = np.exp(xs)
    nz = want > 1e-300  # relative error where the result is a normal number
    assert np.max(np.abs(got[nz] - want[nz]) / want[nz]) < 5e-16
    assert fixed_exp(0.0) == 1.0
    assert fixed_exp(1.0) == pytest.approx(math.e, rel=2.3e-16)
    assert fixed_exp(710.0) == math.inf and fixed_exp(-746.0) == 0.0
    assert math.isnan(fixed_exp(float("nan")))


@pytest.mark.parametrize("k", [1, 3])
def test_fixed_order_actor_equals_the_torchscript_export(tmp_path, k):
    paths = _export(str(tmp_path), num_hypotheses=k)
    jit = E.load_policy(paths["jit"], "p")
    fixed = E.load_policy(paths["jit"], "p", network="fixed_order")
    assert fixed.info.kind == "fixed_order" and fixed.num_hypotheses() == k
    assert (fixed.info.obs_dim, fixed.info.hidden_size) == (21, 16)
    state, depth, h = _inputs()
    a_jit, h_jit = jit.step(state, depth, h)
    a_fix, h_fix = fixed.step(state, depth, h)
    assert a_fix.dtype == np.float64 and h_fix.shape == (1, 5, 16)
    # float32 kernels against float64 sums: the same numbers to float32 rounding.
    np.testing.assert_allclose(a_fix, a_jit, atol=2e-6)
    np.testing.assert_allclose(h_fix, h_jit, atol=2e-6)
    # A second step from the returned state (the hidden state threads through).
    a2_jit, _ = jit.step(state, depth, h_jit)
    a2_fix, _ = fixed.step(state, depth, h_fix)
    np.testing.assert_allclose(a2_fix, a2_jit, atol=4e-6)
    if k > 1:  # the candidates in score order, the first being step's choice
        chosen, others, h1 = fixed.step_hypotheses(state, depth, h)
        c_jit, o_jit, _ = jit.step_hypotheses(state, depth, h)
        np.testing.assert_array_equal(chosen, a_fix)
        np.testing.assert_array_equal(h1, h_fix)
        np.testing.assert_allclose(others, o_jit, atol=2e-6)


@pytest.mark.parametrize("name", ["full", "student"])
def test_a_training_checkpoint_flies_with_the_bits_of_its_export(name):
    """The shipped policy's training checkpoint (model.pt, actor rebuilt from its stored config, no TorchScript) and
    its TorchScript export (policy.pt, read independently) give the same bits over three chained steps, all three
    candidates included: the fixed-order runtime does not need TorchScript."""
    folder = os.path.join(ROOT, "checkpoints", name)
    via_jit = E.load_policy(os.path.join(folder, "policy.pt"), "jit", network="fixed_order")
    via_ckpt = E.load_policy(os.path.join(folder, "model.pt"), "ckpt", network="fixed_order")
    assert via_ckpt.info.kind == "fixed_order" and via_ckpt.info.path.endswith("model.pt")
    layout = ("obs_dim", "depth_shape", "num_layers", "hidden_size")
    assert [getattr(via_ckpt.info, k) for k in layout] == [getattr(via_jit.info, k) for k in layout]
    assert via_ckpt.info.train_speeds == via_jit.info.train_speeds == (3.0, 9.0)
    assert via_ckpt.info.train_env == via_jit.info.train_env and via_ckpt.info.state_groups == via_jit.info.state_groups
    assert via_ckpt.num_hypotheses() == via_jit.num_hypotheses() == 3
    rng = np.random.default_rng(7)
    state = rng.normal(size=(4, via_jit.info.obs_dim)).astype(np.float32)
    depth = rng.uniform(0.0, 1.0, size=(4, *via_jit.info.depth_shape)).astype(np.float32)
    h_a = h_b = via_jit.initial_state(4)
    for _ in range(3):
        c_a, o_a, h_a = via_jit.step_hypotheses(state, depth, h_a)
        c_b, o_b, h_b = via_ckpt.step_hypotheses(state, depth, h_b)
        assert np.array_equal(c_a.view(np.int64), c_b.view(np.int64))
        assert np.array_equal(o_a.view(np.int64), o_b.view(np.int64))
        assert np.array_equal(np.asarray(h_a, np.float64).view(np.int64), np.asarray(h_b, np.float64).view(np.int64))
        assert np.abs(np.asarray(h_a)).max() > 0  # the recurrent state moves, so the chain tests the GRU too


def test_a_packaged_folder_without_its_torchscript_file_flies_from_its_checkpoint(tmp_path):
    """A packaged folder whose policy.pt is gone (or was never written) flies its model.pt with the same bits."""
    import shutil

    src = os.path.join(ROOT, "checkpoints", "student")
    folder = tmp_path / "student"
    shutil.copytree(src, folder, ignore=shutil.ignore_patterns("policy.pt"))
    assert not (folder / "policy.pt").exists()
    via_ckpt = E.load_policy(str(folder), "ckpt", network="fixed_order")
    assert via_ckpt.info.path == str(folder / "model.pt") and via_ckpt.info.kind == "fixed_order"
    via_jit = E.load_policy(os.path.join(src, "policy.pt"), "jit", network="fixed_order")
    state, depth = np.full((2, 21), 0.1, np.float32), np.full((2, 1, 60, 100), 0.5, np.float32)
    a_ckpt, _ = via_ckpt.step(state, depth, via_ckpt.initial_state(2))
    a_jit, _ = via_jit.step(state, depth, via_jit.initial_state(2))
    assert np.array_equal(a_ckpt.view(np.int64), a_jit.view(np.int64))


def test_a_run_export_without_its_torchscript_file_flies_the_checkpoint_its_source_file_names(tmp_path):
    """Training writes ``exported/source.json`` (the checkpoint's name and sha256). A run folder whose
    ``exported/policy.pt`` is gone flies that checkpoint; a checkpoint that is missing or changed is refused."""
    import hashlib
    import shutil

    src = os.path.join(ROOT, "checkpoints", "full")
    run = tmp_path / "run"
    (run / "exported").mkdir(parents=True)
    shutil.copy(os.path.join(src, "model.pt"), run / "model_299.pt")
    shutil.copy(os.path.join(src, "policy.onnx"), run / "exported" / "policy.onnx")
    digest = hashlib.sha256((run / "model_299.pt").read_bytes()).hexdigest()
    record = {"checkpoint": "model_299.pt", "iteration": 299, "sha256": digest}
    (run / "exported" / "source.json").write_text(json.dumps(record))
    via_src = E.load_policy(str(run / "exported" / "policy.onnx"), "run", network="fixed_order")
    assert via_src.info.path == str(run / "model_299.pt")
    via_jit = E.load_policy(os.path.join(src, "policy.pt"), "jit", network="fixed_order")
    state, depth = np.full((2, 21), 0.1, np.float32), np.full((2, 1, 60, 100), 0.5, np.float32)
    a_src, _ = via_src.step(state, depth, via_src.initial_state(2))
    a_jit, _ = via_jit.step(state, depth, via_jit.initial_state(2))
    assert np.array_equal(a_src.view(np.int64), a_jit.view(np.int64))

    (run / "exported" / "source.json").write_text(json.dumps({**record, "sha256": "0" * 64}))
    with pytest.raises(E.EvalError, match="not the checkpoint the export was made from"):
        E.load_policy(str(run / "exported" / "policy.onnx"), "run", network="fixed_order")
    (run / "exported" / "source.json").write_text(json.dumps({**record, "checkpoint": "model_300.pt"}))
    with pytest.raises(E.EvalError, match="'model_300.pt'.*does not exist"):
        E.load_policy(str(run), "run", network="fixed_order")
    # With the TorchScript export there, a checkpoint that no longer matches gives way to it (the export's weights).
    shutil.copy(os.path.join(src, "policy.pt"), run / "exported" / "policy.pt")
    assert E.load_policy(str(run), "run", network="fixed_order").info.path == str(run / "exported" / "policy.pt")
    (run / "exported" / "source.json").write_text(json.dumps(record))  # the checkpoint matches again: it comes first
    assert E.load_policy(str(run), "run", network="fixed_order").info.path == str(run / "model_299.pt")


def test_fixed_order_reads_a_packaged_folder_through_its_checkpoint_not_torchscript():
    """``checkpoints/<name>`` holds ``model.pt`` beside ``policy.pt``: the default runtime reads the checkpoint (no
    deprecated ``torch.jit.load`` on the default path); ``--set network=export`` flies the ONNX file."""
    folder = os.path.join(ROOT, "checkpoints", "full")
    assert E.load_policy(folder, "full", network="fixed_order").info.path == os.path.join(folder, "model.pt")
    assert E.load_policy(folder, "full", network="export").info.path == os.path.join(folder, "policy.onnx")


def test_the_eager_export_keeps_every_slot_of_a_shared_activation():
    """rsl-rl's MLP puts one activation module in each of its slots; ``named_children`` yields a shared module once,
    which would drop the second ELU. The actor read from an eager export has an ELU after each hidden layer, as the
    TorchScript file of the same weights has."""
    from shield_nav.policies.export import ExportedDepthGRU
    from shield_nav.training.actor import actor_from_checkpoint

    model, _, _ = actor_from_checkpoint(os.path.join(ROOT, "checkpoints", "student", "model.pt"))
    module = ExportedDepthGRU(model)
    core = dict(module.mlp.named_children())["0"]
    assert len(list(core.named_children())) < len(core._modules)  # the sharing this test is about
    fixed = FixedOrderActor(module, "student")
    jit = FixedOrderActor(torch.jit.load(os.path.join(ROOT, "checkpoints", "student", "policy.pt")), "student")
    assert [act for _, act in fixed.mlp] == [act for _, act in jit.mlp]
    assert [act for _, act in fixed.mlp][:-1] == [ACTIVATIONS["ELU"]] * (len(fixed.mlp) - 1)


_SCRIPT = """
import sys
import numpy as np
import torch
from shield_nav.evaluation.fixed_order import FixedOrderActor
m = torch.jit.load(sys.argv[1])
d = np.load(sys.argv[2])
head, h = FixedOrderActor(m, sys.argv[1]).forward(d["state"], d["depth"], d["h"])
np.savez(sys.argv[3], head=head, h=h)
"""


def _ordered_conv(x, w, b, stride, pad):
    """``nn.Conv2d`` in plain Python floats: each output's sum from the bias over (c, ky, kx) in order, one rounded
    multiply and one rounded add per term (the order the fixed-order runtime promises)."""
    c_in, n_b, h, wd = x.shape
    n_out, _, k, _ = w.shape
    ho, wo = (h + 2 * pad - k) // stride + 1, (wd + 2 * pad - k) // stride + 1
    out = np.empty((n_out, n_b, ho, wo))
    for o in range(n_out):
        for i in range(n_b):
            for oy in range(ho):
                for ox in range(wo):
                    acc = float(b[o])
                    for c in range(c_in):
                        for ky in range(k):
                            for kx in range(k):
                                iy, ix = oy * stride - pad + ky, ox * stride - pad + kx
                                v = float(x[c, i, iy, ix]) if 0 <= iy < h and 0 <= ix < wd else 0.0
                                acc += float(w[o, c, ky, kx]) * v
                    out[o, i, oy, ox] = acc
    return out


@pytest.mark.parametrize(("c_out", "k", "stride", "pad"), [(11, 3, 1, 1), (8, 4, 4, 0), (5, 3, 2, 1), (16, 2, 1, 0)])
def test_the_vector_convolution_gives_the_ordered_sums_bits(c_out, k, stride, pad):
    """The convolution's vector kernels (direct for stride 1, gathered patches otherwise; whole tiles of 8 output
    channels and the channels past them one by one) against the ordered sums in Python, bit for bit, ReLU
    included; a second batch size through the same workspace, then the first again."""
    from shield_nav.evaluation.fixed_order import _Conv, _convolve, _Workspace

    rng = np.random.default_rng(c_out + k)
    w = rng.normal(size=(c_out, 3, k, k))
    b = rng.normal(size=c_out)
    conv = _Conv(np.ascontiguousarray(w.reshape(c_out, -1).T), b, k, stride, pad, True, False)
    work = _Workspace()
    for n_b in (2, 3, 2):
        x = rng.normal(size=(3, n_b, 9, 13))
        want = np.maximum(_ordered_conv(x, w, b, stride, pad), 0.0)
        got = _convolve(x, conv, work, 0)
        assert got.shape == want.shape
        assert np.array_equal(got.view(np.int64), want.view(np.int64))


def test_the_vector_linear_layer_gives_the_ordered_sums_bits():
    """A linear layer through the 4-row by 4-vector tiles, a leftover vector and leftover rows (6 rows, 45 outputs
    padded to 48), against the ordered sums in Python, bit for bit."""
    from shield_nav.evaluation.fixed_order import _t

    rng = np.random.default_rng(7)
    w, b, x = rng.normal(size=(45, 19)), rng.normal(size=45), rng.normal(size=(6, 19))
    want = np.empty((6, 45))
    for i in range(6):
        for o in range(45):
            acc = float(b[o])
            for j in range(19):
                acc += float(x[i, j]) * float(w[o, j])
            want[i, o] = acc
    got = _t(torch.from_numpy(w), torch.from_numpy(b))(x)
    assert got.shape == (6, 45)
    assert np.array_equal(got.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize(("name", "digest"), [
    ("full", "1a862f17420a7bd2d28ddb0b6eec075406da929389ba42df176acf1d332c557d"),
    ("student", "61f47e6d6802a6f3f917964cb0b5c8d1ff6005ce6edc60fa8bda6edb7447e41b"),
])  # fmt: skip
def test_the_shipped_policies_give_the_bits_that_flew_the_tables(name, digest):
    """The SHA-256 of a shipped policy's head and hidden state on a seeded batch, as computed by the scalar loops
    that flew every table (git 10ea86d, before the vector kernels): the runtime's speed-ups may not move a bit.
    A new release changes the weights, and with them these digests."""
    import hashlib

    pol = E.load_policy(os.path.join(ROOT, "checkpoints", name), "p", network="fixed_order")
    info = pol.info
    rng = np.random.default_rng(2026)
    state = rng.normal(size=(7, info.obs_dim)).astype(np.float32)
    depth = (8.0 * rng.uniform(size=(7, *info.depth_shape))).astype(np.float32)
    h = (0.3 * rng.normal(size=(info.num_layers, 7, info.hidden_size))).astype(np.float32)
    head, h_out = pol._runner.forward(state, depth, h)
    assert hashlib.sha256(head.tobytes() + h_out.tobytes()).hexdigest() == digest


def test_a_baseline_x86_64_build_gives_the_host_builds_bits(tmp_path):
    """The point of the runtime: no instruction set changes a bit. The kernels compiled for the generic x86-64 CPU
    (no AVX, no FMA), in a fresh cache, give the same bits as this process's host build."""
    paths = _export(str(tmp_path), num_hypotheses=3)
    state, depth, h = _inputs(n=7, seed=4)
    np.savez(tmp_path / "in.npz", state=state, depth=depth, h=h)
    head, h_out = FixedOrderActor(torch.jit.load(paths["jit"]), paths["jit"]).forward(state, depth, h)
    env = {**os.environ, "NUMBA_CPU_NAME": "generic", "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}  # fmt: skip
    subprocess.run([sys.executable, "-c", _SCRIPT, paths["jit"], str(tmp_path / "in.npz"), str(tmp_path / "out.npz")],
                   check=True, env=env, cwd=ROOT, timeout=600)  # fmt: skip
    other = np.load(tmp_path / "out.npz")
    assert np.array_equal(other["head"].view(np.int64), head.view(np.int64))
    assert np.array_equal(other["h"].view(np.int64), h_out.view(np.int64))


def test_what_the_fixed_order_runtime_does_not_run_is_refused_by_name(tmp_path):
    class Other(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.lin = torch.nn.Linear(3, 2)

        def forward(self, x):
            return self.lin(x)

    with pytest.raises(ValueError, match="fixed_order.*no 'obs_normalizer' submodule"):
        FixedOrderActor(torch.jit.script(Other()), "other.pt")
    # An ONNX file is read through the TorchScript export beside it; without one the loader says what it reads.
    paths = _export(str(tmp_path))
    via_onnx = E.load_policy(paths["onnx"], "p", network="fixed_order")
    assert via_onnx.info.kind == "fixed_order" and via_onnx.info.path == paths["jit"]
    lone = tmp_path / "lone"
    lone.mkdir()
    os.replace(paths["onnx"], lone / "policy.onnx")
    what = r"TorchScript export policy.pt \(or a packaged model.pt, or the run checkpoint an exported/source.json"
    with pytest.raises(E.EvalError, match=what):
        E.load_policy(lone / "policy.onnx", "p", network="fixed_order")
    with pytest.raises(ConfigError, match="config key 'network': 'fast'; known"):
        E.load_eval_config(None, ["network=fast"])


def test_a_fixed_order_run_records_its_network_and_repeats(tmp_path):
    _export(str(tmp_path / "ckpt"))
    extra = ["name=tiny", "configurations=[mine]", "rows.mine.label=Mine", "rows.mine.policy=mine",
             f"checkpoints.mine={tmp_path / 'ckpt'}", "scenes.family=ablation", "scenes.indices=[7]", "speeds=[9.0]",
             "trials_per_scene=2", "plots=false", "network=fixed_order",
             "env_overrides=[episode.timeout_factor=0.05]"]  # fmt: skip
    for out in ("a", "b"):
        E.evaluate(E.load_eval_config(None, extra), str(tmp_path / out), progress=False)
    man = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert man["config"]["network"] == "fixed_order"
    assert man["checkpoints"]["mine"]["path"].endswith("policy.pt")
    a, b = (json.loads((tmp_path / o / "trials.json").read_text()) for o in ("a", "b"))
    assert [t["steps"] for t in a] == [t["steps"] for t in b] and all(t["steps"] > 0 for t in a)


def test_the_pinned_arithmetic_environment_by_hand():
    from shield_nav.provenance import BLAS_CORE
    from shield_nav.provenance import pinned_arithmetic_environment as pin

    assert BLAS_CORE == "Prescott"
    env = pin({"A": "1"}, "x86_64", ["X86_V3", "X86_V4"])
    assert env == {"A": "1", "OPENBLAS_CORETYPE": "Prescott", "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4"}
    assert pin({"A": "1"}, "x86_64", []) == {"A": "1", "OPENBLAS_CORETYPE": "Prescott"}  # a baseline-only numpy
    assert pin({"OPENBLAS_CORETYPE": "Haswell"}, "x86_64", [])["OPENBLAS_CORETYPE"] == "Prescott"
    assert pin({"OPENBLAS_CORETYPE": "Prescott"}, "x86_64", []) is None  # already pinned
    # A target numpy still uses is switched off beside one the caller had switched off already.
    env = pin({"OPENBLAS_CORETYPE": "Prescott", "NPY_DISABLE_CPU_FEATURES": "AVX512_SPR"}, "x86_64", ["X86_V4"])
    assert env["NPY_DISABLE_CPU_FEATURES"] == "AVX512_SPR X86_V4"
    assert pin({}, "aarch64", ["ASIMD"]) is None  # other kernel names; no claim off x86-64


def test_eval_cli_restarts_a_fixed_order_run_with_the_pinned_blas_kernels(tmp_path):
    import platform

    import yaml

    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(yaml.safe_dump({"name": "tiny", "configurations": ["goal_seeking"], "scenes": {"family": "ablation",
                                   "indices": [7]}, "speeds": [9.0], "trials_per_scene": 1, "plots": False,
                                   "network": "fixed_order"}))  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")}
    cmd = [sys.executable, "eval.py", "--config", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 0, res.stderr[-2000:]
    man = json.loads((tmp_path / "out" / "manifest.json").read_text())
    if platform.machine().lower() in ("x86_64", "amd64"):
        assert "restarting with OPENBLAS_CORETYPE=Prescott NPY_DISABLE_CPU_FEATURES=" in res.stderr
        assert man["openblas_coretype"] == "Prescott" and man["numpy_simd"] == []  # numpy's baseline loops only
    else:
        assert man["openblas_coretype"] is None
    # The default network leaves OpenBLAS to choose (the tables' flights).
    cfg.write_text(cfg.read_text().replace("fixed_order", "export"))
    res = subprocess.run([*cmd[:-3], "--out", str(tmp_path / "out2"), "--no-progress"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300, env=env)  # fmt: skip
    assert res.returncode == 0 and "restarting" not in res.stderr
    man2 = json.loads((tmp_path / "out2" / "manifest.json").read_text())
    from shield_nav.provenance import numpy_simd_targets

    assert man2["openblas_coretype"] is None and man2["numpy_simd"] == numpy_simd_targets()
