"""envs.sharded.ShardedVecEnv: K worker processes step one batch; each shard repeats its single-process env."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import torch

from envs.config import ConfigError
from envs.sharded import ShardedVecEnv

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SMALL = ["env.num_envs=4", "env.scenes.indices=[0,1]", "num_threads=1", "env_shards=2"]


def _config(*extra):
    from shield_nav.training import load_train_config

    return load_train_config(os.path.join(REPO, "configs", "train", "recipe_full.yaml"), overrides=[*SMALL, *extra])


def _joined(parts, key):
    return torch.cat([p[key] for p in parts])


def test_two_shards_repeat_their_single_process_envs_step_for_step_through_episode_ends():
    """The shielded PPO recipe (training-loop shield, planning expert's labels, critic vector) in 2 shards of 2 envs
    against the two envs a single process builds with seeds s and s + 1: every observation group, reward, done and
    time-out equal, also across the resets of episodes pushed to their time limit."""
    from shield_nav.training import make_env
    from shield_nav.training.runner import shard_env

    cfg = _config()
    sharded = make_env(cfg)
    try:
        singles = [shard_env(cfg, k) for k in range(2)]
        assert sharded.num_envs == 4 and sharded.shard_sizes == [2, 2]
        assert sharded.cfg == cfg.env  # VecEnv.cfg: the task's config, as the single-process adapter's
        assert {s.env.cfg.seed for s in singles} == {cfg.env.seed, cfg.env.seed + 1}
        obs = sharded.get_observations()
        assert set(obs.keys()) >= {"depth", "state", "critic", "expert"}
        for key in obs.keys():  # noqa: SIM118 (a TensorDict iterates its batch, not its keys)
            assert torch.equal(obs[key], _joined([s.get_observations() for s in singles], key)), key
        # two envs (one per shard) one step short of their time limit: they end by time-out on the next step
        limit = sharded.episode_length_buf.clone()
        lengths = [s.env.max_episode_length_buf.copy() for s in singles]
        limit[[0, 3]] = torch.tensor([int(lengths[0][0]) - 1, int(lengths[1][1]) - 1])
        sharded.episode_length_buf = limit
        for k, s in enumerate(singles):
            s.episode_length_buf = limit[2 * k : 2 * k + 2]
        assert torch.equal(sharded.episode_length_buf, limit)
        rng = np.random.default_rng(0)
        ended = 0
        for step in range(6):
            act = torch.from_numpy(rng.uniform(-1, 1, (4, 4)).astype(np.float32))
            obs, rew, dones, extras = sharded.step(act)
            outs = [s.step(act[2 * k : 2 * k + 2]) for k, s in enumerate(singles)]
            for key in obs.keys():  # noqa: SIM118
                assert torch.equal(obs[key], _joined([o[0] for o in outs], key)), (step, key)
            assert torch.equal(rew, torch.cat([o[1] for o in outs]))
            assert torch.equal(dones, torch.cat([o[2] for o in outs]))
            assert torch.equal(extras["time_outs"], torch.cat([o[3]["time_outs"] for o in outs]))
            if step == 0:
                assert dones.tolist() == [True, False, False, True] and extras["time_outs"].tolist()[0]
                # each shard ended one episode: the joined log holds both, shard after shard
                assert extras["log"]["episode/timeout"].tolist() == [1.0, 1.0]
                assert torch.equal(extras["log"]["episode/target_speed"],
                                   torch.cat([o[3]["log"]["episode/target_speed"] for o in outs]))  # fmt: skip
            ended += int(dones.sum())
        assert ended >= 2
        assert sharded.curriculum_levels == [lv for s in singles for lv in s.curriculum_levels]
        assert sharded.num_scenes == singles[0].num_scenes == 2
    finally:
        sharded.close()


def _bare(sizes):
    env = ShardedVecEnv.__new__(ShardedVecEnv)
    env.shard_sizes, env._procs, env._conns = list(sizes), [], []
    return env


def test_logs_join_by_hand():
    """Per-step scalars: the mean weighted by each shard's envs (a ``max`` key: the max); episode arrays: in order."""
    env = _bare([2, 6])
    a = {"reward/navigation": np.float64(1.0), "curriculum/max_level": np.float64(3.0),
         "episode/success": np.array([1.0, 0.0])}  # fmt: skip
    b = {"reward/navigation": np.float64(3.0), "curriculum/max_level": np.float64(7.0),
         "episode/success": np.array([1.0]), "shield/active": np.float64(0.5)}  # fmt: skip
    log = env._join_log([a, b])
    assert log["reward/navigation"].item() == pytest.approx((2 * 1.0 + 6 * 3.0) / 8)
    assert log["curriculum/max_level"].item() == 7.0
    assert log["episode/success"].tolist() == [1.0, 0.0, 1.0]
    assert log["shield/active"].item() == 0.5  # only shard 1 logged it: its own value
    # a shard with no episode end this step: the other's episodes alone
    assert env._join_log([{"episode/success": np.array([0.0])}, {}])["episode/success"].tolist() == [0.0]


class _Broken:
    """A shard factory that fails while building (picklable: a module-level class)."""

    def __call__(self):
        raise ValueError("scene index 99 is out of range")


def test_a_shard_that_fails_to_build_raises_with_its_index_and_traceback():
    with pytest.raises(RuntimeError, match=r"env shard 0 failed:(.|\n)*scene index 99 is out of range"):
        ShardedVecEnv([_Broken()])


def test_env_shards_must_divide_the_env_count():
    with pytest.raises(ConfigError, match="env_shards"):
        _config("env_shards=3")
    with pytest.raises(ConfigError, match="env_shards"):
        _config("env_shards=0")


def test_workers_leave_when_the_parent_is_killed(tmp_path):
    """SIGKILL to the training process: its shard workers see their pipe end and exit (no orphans)."""
    script = tmp_path / "parent.py"
    script.write_text(
        textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {REPO!r})
        from shield_nav.training import load_train_config, make_env
        if __name__ == "__main__":
            cfg = load_train_config({os.path.join(REPO, "configs", "train", "quick.yaml")!r},
                                    overrides={[*SMALL[:3], "env_shards=2"]!r})
            env = make_env(cfg)
            print(" ".join(str(p.pid) for p in env._procs), flush=True)
            time.sleep(600)
    """)
    )
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        pids = [int(p) for p in proc.stdout.readline().split()]
        assert len(pids) == 2
        for pid in pids:
            os.kill(pid, 0)  # alive while the parent is
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stdout.close()

    def alive(pid):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        try:  # a zombie child of a dead parent is reaped by init; treat a zombie as gone
            with open(f"/proc/{pid}/stat") as f:
                return f.read().split(") ")[1][0] != "Z"
        except FileNotFoundError:
            return False

    deadline = time.monotonic() + 30
    while any(alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(alive(p) for p in pids)


def test_train_py_runs_and_resumes_a_sharded_run(tmp_path):
    """rsl-rl's own runner on 2 shards through train.py: events, checkpoint, and a resume that restores the levels."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from shield_nav.training import read_checkpoint_infos

    def train(*args):
        res = subprocess.run([sys.executable, "train.py", *args], cwd=REPO, capture_output=True, text=True, timeout=240)
        assert res.returncode == 0, res.stderr[-3000:]
        return res

    root = str(tmp_path / "logs")
    tiny = ["--config", "configs/train/quick.yaml", "--num-envs", "4", "--set", "runner.num_steps_per_env=8",
            "env_shards=2", "--log-dir", root]  # fmt: skip
    train(*tiny, "--max-iterations", "2")
    (name,) = os.listdir(os.path.join(root, "quick"))
    run = os.path.join(root, "quick", name)
    infos = read_checkpoint_infos(os.path.join(run, "model_1.pt"))
    assert infos["config"]["env_shards"] == 2 and len(infos["curriculum_levels"]) == 4
    res = train("--resume", os.path.join(run, "model_1.pt"), "--max-iterations", "3")
    assert "continuing at iteration 2" in res.stdout and "curriculum levels restored" in res.stdout
    acc = EventAccumulator(run)
    acc.Reload()
    assert sorted({e.step for e in acc.Scalars("reward/navigation")}) == [0, 1, 2]  # the joined logs reached it
    assert torch.load(os.path.join(run, "model_2.pt"), weights_only=False)["infos"]["tot_timesteps"] == 3 * 4 * 8


def test_sigterm_to_the_process_group_saves_and_leaves_no_worker(tmp_path):
    """A Ctrl-C or kill of the whole group reaches the shards too: they ignore it, the parent finishes its iteration,
    saves and closes them."""
    from shield_nav.training import read_checkpoint_infos

    root = str(tmp_path / "logs")
    args = ["--config", "configs/train/quick.yaml", "--num-envs", "4", "--set", "runner.num_steps_per_env=8",
            "env_shards=2", "--max-iterations", "10000", "--log-dir", root]  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-u", "train.py", *args], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)  # fmt: skip
    try:
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if "Learning iteration 1/" in line:
                os.killpg(proc.pid, signal.SIGTERM)
                break
        out = proc.communicate(timeout=180)[0]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + signal.SIGTERM, "".join(lines) + out
    (name,) = os.listdir(os.path.join(root, "quick"))
    run = os.path.join(root, "quick", name)
    last = max((f for f in os.listdir(run) if f.startswith("model_")), key=lambda f: int(f[6:-3]))
    assert read_checkpoint_infos(os.path.join(run, last))["interrupted"] is True
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        try:
            os.killpg(proc.pid, 0)  # anything left in the group?
        except ProcessLookupError:
            break
        time.sleep(0.2)
    else:
        pytest.fail("processes of the training's group outlived it")
