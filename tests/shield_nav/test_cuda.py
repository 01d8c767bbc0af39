"""``--device cuda``: the learner on a GPU, the env on the CPU. Skipped where torch sees no CUDA device (CI here).

Run on a machine with a GPU: ``python -m pytest tests/shield_nav/test_cuda.py``. The reference for each check is the
same computation on the CPU (the env's tensors) or the CPU copy of the trained weights (checkpoints and exports).
"""

import os

import numpy as np
import onnxruntime as ort
import pytest
import torch
from test_train_cli import REPO, run_train  # pytest prepends this folder to sys.path

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

SMALL = ["--num-envs", "4", "--set", "runner.num_steps_per_env=8", "env.scenes.indices=[0,1]", "num_threads=0"]


def only_run_dir(root):
    (name,) = os.listdir(root)
    (run,) = os.listdir(os.path.join(root, name))
    return os.path.join(root, name, run)


def test_env_tensors_on_cuda_equal_the_cpu_env():
    """Same seed, same actions: every observation group, reward and done is the CPU env's, on the GPU."""
    from shield_nav.training import load_train_config, make_env

    over = ["env.num_envs=3", "env.scenes.indices=[0,1]", "runner.expert.kind=planner"]
    cfg = os.path.join(REPO, "configs", "train", "recipe_student.yaml")
    envs = {d: make_env(load_train_config(cfg, overrides=[*over, f"device={d}"])) for d in ("cpu", "cuda")}
    rng = np.random.default_rng(0)
    obs = {d: e.get_observations() for d, e in envs.items()}
    for _ in range(12):
        assert obs["cuda"].device.type == "cuda"
        assert set(obs["cuda"].keys()) == set(obs["cpu"].keys()) >= {"depth", "state", "expert"}
        for k in obs["cpu"].keys():  # noqa: SIM118 (iterating a TensorDict walks its batch, not its keys)
            torch.testing.assert_close(obs["cuda"][k].cpu(), obs["cpu"][k], rtol=0, atol=0)
        act = torch.from_numpy(rng.uniform(-1, 1, (3, 4)).astype(np.float32))
        out = {d: e.step(act.to(d)) for d, e in envs.items()}
        obs = {d: o[0] for d, o in out.items()}
        for i in (1, 2):  # rewards, dones
            assert out["cuda"][i].device.type == "cuda"
            torch.testing.assert_close(out["cuda"][i].cpu(), out["cpu"][i], rtol=0, atol=0)
        assert out["cuda"][3]["time_outs"].device.type == "cuda"


def test_ppo_on_cuda_checkpoints_resume_on_either_device_and_export_the_trained_actor(tmp_path):
    root = str(tmp_path / "logs")
    res = run_train(["--config", "configs/train/quick.yaml", *SMALL, "--device", "cuda", "--max-iterations", "2",
                     "--log-dir", root])  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    run = only_run_dir(root)
    ckpt = torch.load(os.path.join(run, "model_1.pt"), map_location="cpu", weights_only=False)
    assert ckpt["iter"] == 1 and ckpt["infos"]["config"]["device"] == "cuda"

    # The export is the trained actor: the ONNX file and the checkpoint's weights (rebuilt on the CPU) agree.
    from tensordict import TensorDict

    from shield_nav.training.actor import actor_from_checkpoint

    model, _, _ = actor_from_checkpoint(os.path.join(run, "model_1.pt"))
    rng = np.random.default_rng(1)
    sess = ort.InferenceSession(os.path.join(run, "exported", "policy.onnx"), providers=["CPUExecutionProvider"])
    state = rng.normal(size=(2, sess.get_inputs()[0].shape[1])).astype(np.float32)
    depth = rng.uniform(0, 1, (2, 1, 60, 100)).astype(np.float32)
    act, _ = sess.run(None, {"obs": state, "depth": depth, "h_in": np.zeros((1, 2, 128), np.float32)})
    with torch.no_grad():
        ref = model(TensorDict({"state": torch.from_numpy(state), "depth": torch.from_numpy(depth)}, batch_size=[2]))
    np.testing.assert_allclose(act, ref.numpy(), atol=1e-5)

    # Resume on the GPU, then the GPU's checkpoint on the CPU: the iteration count continues each time.
    res = run_train(["--resume", os.path.join(run, "model_1.pt"), "--max-iterations", "3"])
    assert res.returncode == 0, res.stderr[-3000:]
    assert "continuing at iteration 2" in res.stdout
    res = run_train(["--resume", os.path.join(run, "model_2.pt"), "--max-iterations", "4", "--device", "cpu"])
    assert res.returncode == 0, res.stderr[-3000:]
    last = torch.load(os.path.join(run, "model_3.pt"), weights_only=False)
    assert last["iter"] == 3 and last["infos"]["tot_timesteps"] == 4 * 4 * 8
    assert all(v.device.type == "cpu" for v in last["actor_state_dict"].values())


@pytest.mark.parametrize("config", ["recipe_student.yaml", "recipe_full.yaml"])
def test_dagger_and_shielded_ppo_recipes_run_on_cuda(tmp_path, config):
    """The shipped recipes' learners (DAgger from the planning expert; PPO behind the training-loop shield)."""
    root = str(tmp_path / "logs")
    res = run_train(["--config", f"configs/train/{config}", *SMALL, "--device", "cuda", "--max-iterations", "1",
                     "--log-dir", root])  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    run = only_run_dir(root)
    ckpt = torch.load(os.path.join(run, "model_0.pt"), map_location="cpu", weights_only=False)
    weights = ckpt["student_state_dict" if config == "recipe_student.yaml" else "actor_state_dict"]
    assert all(torch.isfinite(v).all() for v in weights.values() if v.is_floating_point())
    assert os.path.isfile(os.path.join(run, "exported", "policy.onnx"))
