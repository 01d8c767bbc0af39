"""Packaging a training checkpoint as a committed policy, loading it back, and resuming from it."""

import json
import os
import subprocess
import sys

import numpy as np
import onnxruntime as ort
import torch

from shield_nav.tools.package import package
from shield_nav.training.actor import actor_from_checkpoint

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TINY = ["--config", "configs/train/quick.yaml", "--num-envs", "4", "--set", "runner.num_steps_per_env=8"]


def test_package_export_matches_the_checkpoint_and_resume_starts_a_new_run(tmp_path):
    logs = str(tmp_path / "logs")
    res = subprocess.run([sys.executable, "train.py", *TINY, "--max-iterations", "1", "--log-dir", logs],
                         cwd=REPO, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    run = os.path.join(logs, "quick", os.listdir(os.path.join(logs, "quick"))[0])
    # A folder that already holds a model card (written by hand after packaging) keeps it, unhashed.
    os.makedirs(tmp_path / "checkpoints" / "tiny")
    (tmp_path / "checkpoints" / "tiny" / "README.md").write_text("card\n")
    out = package(os.path.join(run, "model_0.pt"), "tiny", str(tmp_path / "checkpoints"))
    assert {"model.pt", "policy.onnx", "policy.pt", "curves.csv", "meta.json", "README.md"} <= set(os.listdir(out))
    with open(os.path.join(out, "meta.json")) as fh:
        meta = json.load(fh)
    assert meta["iter"] == 0 and set(meta["sha256"]) == {"model.pt", "policy.onnx", "policy.pt", "curves.csv"}
    import hashlib

    with open(os.path.join(out, "policy.onnx"), "rb") as fh:
        assert meta["sha256"]["policy.onnx"] == hashlib.sha256(fh.read()).hexdigest()
    assert (tmp_path / "checkpoints" / "tiny" / "README.md").read_text() == "card\n"
    # The packaged ONNX reproduces the checkpoint's deterministic actor over a few steps.
    model, _, _ = actor_from_checkpoint(os.path.join(out, "model.pt"))
    sess = ort.InferenceSession(os.path.join(out, "policy.onnx"), providers=["CPUExecutionProvider"])
    names = [i.name for i in sess.get_inputs()]
    rng = np.random.default_rng(0)
    h = np.zeros(sess.get_inputs()[2].shape[:1] + [1] + sess.get_inputs()[2].shape[2:], np.float32)
    from tensordict import TensorDict

    for _ in range(3):
        state = rng.normal(size=(1, 21)).astype(np.float32)
        depth = rng.uniform(0, 1, (1, 1, 60, 100)).astype(np.float32)
        act, h = sess.run(None, {names[0]: state, names[1]: depth, names[2]: h})
        td = TensorDict({"state": torch.from_numpy(state), "depth": torch.from_numpy(depth)}, batch_size=[1])
        with torch.no_grad():
            ref = model(td, stochastic_output=False)
        np.testing.assert_allclose(act, ref.numpy(), atol=1e-5)
    # Resuming from a packaged policy continues the iteration count in a new run folder.
    res = subprocess.run([sys.executable, "train.py", "--resume", os.path.join(out, "model.pt"), "--max-iterations",
                          "2", "--log-dir", logs], cwd=REPO, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    assert "continuing at iteration 1" in res.stdout
    assert len(os.listdir(os.path.join(logs, "quick"))) == 2
