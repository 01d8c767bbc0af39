"""Several worker processes step one batch of envs: :class:`ShardedVecEnv`, an ``rsl_rl.env.VecEnv`` over K shards.

The navigation env steps all of its N vehicles in one process. Its ray caster and the planning expert split their
loops over numba threads, but the depth sensor model, the physics substeps and the training-loop shield's QPs run on
one core, so a machine with many cores collects little faster than two (docs/training.md, "Hardware and
throughput"). With ``env_shards: K`` in a train config, K worker processes each build and step N / K of the envs
(an :class:`envs.rsl_rl.RslRlVecEnv` of their own, with its expert and command filter), and this class joins their
observations, rewards, dones and logs into one batch in shard order, so the learner sees N envs as before.

Shard k is the env a single process would build with ``N / K`` envs and ``seed + k``: a sharded run is not the
unsharded run of the same seed (its scenes, starts and noise are drawn by K streams), but each shard repeats its
single-process counterpart step for step (``tests/envs/test_sharded.py``).

Observations travel through one shared-memory buffer per group (each shard writes its rows), rewards, dones and
logs through pipes. Workers are started with the ``spawn`` method (no forked torch or numba thread pools), use one
torch thread and ``numba_threads`` numba threads each, ignore SIGINT and SIGTERM (a Ctrl-C reaches the whole
process group, and the parent finishes its iteration and saves before it closes them), and leave when the parent
closes the env, when the parent dies (their pipe ends), or after an error, which the parent raises with the
shard's traceback.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
import traceback
from collections.abc import Callable
from multiprocessing import shared_memory
from typing import Any

import numpy as np
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict


def _numpy(x: Any) -> Any:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _write(views: dict[str, np.ndarray], obs: Any) -> None:
    for key, view in views.items():
        np.copyto(view, _numpy(obs[key]))


def _worker(conn: Any, factory: Callable[[], VecEnv], numba_threads: int) -> None:
    """Build one shard with ``factory`` and serve the parent's commands until ``close`` or the pipe ends."""
    # The parent owns shutdown: a Ctrl-C or SIGTERM sent to the whole process group must not end a shard mid-step
    # while the parent finishes its iteration and saves; a shard leaves when the parent closes it or dies.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        torch.set_num_threads(1)
        import numba

        numba.set_num_threads(max(1, min(numba_threads, numba.config.NUMBA_NUM_THREADS)))
        env = factory()
        if str(env.device) != "cpu":
            raise ValueError(f"a shard's env must hold its tensors on the CPU, got device {env.device}")
        views: dict[str, np.ndarray] = {}
        blocks: list[Any] = []
        obs = env.get_observations()
        conn.send(("ok", {"num_envs": env.num_envs, "num_actions": env.num_actions,
                          "obs": {k: _numpy(v) for k, v in obs.items()}}))  # fmt: skip
        while True:
            try:
                cmd, arg = conn.recv()
            except EOFError:  # the parent is gone
                return
            if cmd == "step":
                obs, rew, dones, extras = env.step(torch.from_numpy(arg))
                _write(views, obs)
                log = {k: _numpy(v) for k, v in extras.get("log", {}).items()}
                out = (_numpy(rew), _numpy(dones), _numpy(extras["time_outs"]), log)
            elif cmd == "attach":  # the parent's shared observation buffers: this shard's rows of each
                for key, (name, shape, dtype, start, stop) in arg.items():
                    block = shared_memory.SharedMemory(name=name)
                    blocks.append(block)
                    views[key] = np.ndarray(shape, dtype=np.dtype(dtype), buffer=block.buf)[start:stop]
                out = None
            elif cmd == "get":
                value = getattr(env, arg)
                out = _numpy(value) if isinstance(value, torch.Tensor) else value
            elif cmd == "set":
                name, value = arg
                setattr(env, name, torch.from_numpy(value) if isinstance(value, np.ndarray) else value)
                out = None
            elif cmd == "call":
                name, args = arg
                out = getattr(env, name)(*args)
                if name == "set_curriculum_levels":  # it restarts every episode: the new observations
                    _write(views, env.get_observations())
            elif cmd == "close":
                conn.send(("ok", None))
                return
            else:
                raise ValueError(f"unknown shard command {cmd!r}")
            conn.send(("ok", out))
    except BaseException:  # noqa: BLE001 (sent to the parent, which raises it with the shard's index)
        with contextlib.suppress(BrokenPipeError, OSError):
            conn.send(("error", traceback.format_exc()))


class ShardedVecEnv(VecEnv):
    """K worker processes, each stepping the env that ``factories[k]()`` builds; one ``VecEnv`` of all their envs.

    Args:
        factories: One picklable callable per shard (e.g. a ``functools.partial`` of a module-level function), each
            returning a VecEnv on the CPU (an :class:`envs.rsl_rl.RslRlVecEnv`).
        device: Torch device of the joined tensors (the learner's).
        cfg: The task's config (``VecEnv.cfg``; the shards' env config, as the single-process adapter holds).
        numba_threads: numba threads per worker (default: this machine's cores / K, at least 1).
    """

    def __init__(
        self,
        factories: list[Callable[[], VecEnv]],
        device: str | torch.device = "cpu",
        cfg: Any = None,
        numba_threads: int | None = None,
    ) -> None:  # noqa: D107
        if len(factories) < 1:
            raise ValueError("ShardedVecEnv needs at least one shard factory")
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        threads = numba_threads if numba_threads is not None else max(1, cores // len(factories))
        ctx = mp.get_context("spawn")
        self._conns: list[Any] = []
        self._procs: list[Any] = []
        self.device = torch.device(device)
        self.cfg = cfg
        try:
            for k, factory in enumerate(factories):
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=_worker, args=(child, factory, threads), name=f"env-shard-{k}", daemon=True)
                proc.start()
                child.close()
                self._conns.append(parent)
                self._procs.append(proc)
            first = [self._recv(k) for k in range(len(factories))]
        except BaseException:
            self.close()
            raise
        self.shard_sizes = [int(f["num_envs"]) for f in first]
        self.num_envs = sum(self.shard_sizes)
        self.num_actions = int(first[0]["num_actions"])
        self._bounds = np.cumsum([0, *self.shard_sizes])
        self._blocks: list[Any] = []
        self._views: dict[str, np.ndarray] = {}
        try:
            self._share([f["obs"] for f in first])
        except BaseException:
            self.close()
            raise
        self._obs = self._read_obs()

    # -------------------------------------------------------------------------------------------- plumbing

    def _recv(self, k: int) -> Any:
        try:
            status, value = self._conns[k].recv()
        except EOFError:
            raise RuntimeError(f"env shard {k} exited without a reply (exit code {self._procs[k].exitcode})") from None
        if status == "error":
            raise RuntimeError(f"env shard {k} failed:\n{value}")
        return value

    def _all(self, cmd: str, args: list[Any]) -> list[Any]:
        for conn, arg in zip(self._conns, args, strict=True):
            conn.send((cmd, arg))
        return [self._recv(k) for k in range(len(self._conns))]

    def _split(self, x: np.ndarray) -> list[np.ndarray]:
        return [np.ascontiguousarray(x[a:b]) for a, b in zip(self._bounds[:-1], self._bounds[1:], strict=True)]

    def _share(self, parts: list[dict[str, np.ndarray]]) -> None:
        """One shared buffer per observation group for all N envs, filled from the shards' first observations.

        Each shard then writes its rows there every step; only rewards, dones and logs go through the pipes.
        """
        attach: list[dict[str, tuple]] = [{} for _ in parts]
        for key in parts[0]:
            first = np.concatenate([p[key] for p in parts])
            block = shared_memory.SharedMemory(create=True, size=max(1, first.nbytes))
            self._blocks.append(block)
            view = np.ndarray(first.shape, dtype=first.dtype, buffer=block.buf)
            view[...] = first
            self._views[key] = view
            for k, (a, b) in enumerate(zip(self._bounds[:-1], self._bounds[1:], strict=True)):
                attach[k][key] = (block.name, first.shape, first.dtype.str, int(a), int(b))
        self._all("attach", attach)

    def _read_obs(self) -> TensorDict:
        """The shared buffers' current observations, copied (the shards overwrite them on the next step)."""
        data = {k: torch.from_numpy(v.copy()) for k, v in self._views.items()}
        return TensorDict(data, batch_size=[self.num_envs], device=self.device)

    def _join_log(self, logs: list[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
        """Per-step scalars: the env-weighted mean (``*max*`` keys: the max); per-episode arrays: concatenated."""
        out: dict[str, torch.Tensor] = {}
        for key in dict.fromkeys(k for log in logs for k in log):
            have = [(log[key], n) for log, n in zip(logs, self.shard_sizes, strict=True) if key in log]
            if all(np.ndim(v) == 0 for v, _ in have):
                vals = np.array([float(v) for v, _ in have])
                if "max" in key.rsplit("/", 1)[-1]:
                    value = vals.max()
                else:
                    weights = np.array([n for _, n in have], dtype=np.float64)
                    value = float((vals * weights).sum() / weights.sum())
                out[key] = torch.as_tensor(value, dtype=torch.float32)
            else:
                out[key] = torch.from_numpy(np.concatenate([np.atleast_1d(v) for v, _ in have]))
        return out

    # --------------------------------------------------------------------------------------------- VecEnv

    def get_observations(self) -> TensorDict:
        """The current observation groups of every env, shard after shard."""
        return self._obs

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Every shard steps its slice of ``actions`` (N, A) at once; returns the joined batch as one env would."""
        act = actions.detach().cpu().numpy().astype(np.float32)
        out = self._all("step", self._split(act))
        self._obs = self._read_obs()
        rew = torch.from_numpy(np.concatenate([o[0] for o in out])).to(self.device)
        dones = torch.from_numpy(np.concatenate([o[1] for o in out])).to(self.device)
        extras = {"time_outs": torch.from_numpy(np.concatenate([o[2] for o in out])).to(self.device),
                  "log": self._join_log([o[3] for o in out])}  # fmt: skip
        return self._obs, rew, dones, extras

    @property
    def max_episode_length(self) -> int:
        """The longest per-env time limit over the shards, in steps."""
        return max(int(v) for v in self._all("get", ["max_episode_length"] * len(self._conns)))

    @property
    def episode_length_buf(self) -> torch.Tensor:
        """Current episode lengths (N,); assigning to it writes each shard's slice."""
        parts = self._all("get", ["episode_length_buf"] * len(self._conns))
        return torch.from_numpy(np.concatenate(parts)).to(self.device)

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        self._all("set", [("episode_length_buf", v) for v in self._split(_numpy(value))])

    @property
    def curriculum_active(self) -> bool:
        """Whether the shards draw scenes from their curriculum levels (the first shard's answer; all agree)."""
        return bool(self._all("get", ["curriculum_active"] * len(self._conns))[0])

    @property
    def curriculum_levels(self) -> list[int]:
        """Each env's curriculum level, shard after shard."""
        return [int(v) for part in self._all("get", ["curriculum_levels"] * len(self._conns)) for v in part]

    @property
    def num_scenes(self) -> int:
        """Length of the training scene list (the same in every shard)."""
        return int(self._all("get", ["num_scenes"] * len(self._conns))[0])

    def set_curriculum_levels(self, levels: list[int]) -> None:
        """Install saved levels (a resumed run): each shard takes its slice and restarts its episodes."""
        lv = np.asarray(levels, dtype=np.int64)
        if lv.shape != (self.num_envs,):
            raise ValueError(f"curriculum levels must be {self.num_envs} ints, got shape {lv.shape}")
        self._all("call", [("set_curriculum_levels", (part.tolist(),)) for part in self._split(lv)])
        self._obs = self._read_obs()

    def close(self) -> None:
        """Stop every worker (a polite ``close``, then terminate what is left after 10 s)."""
        for conn in self._conns:
            with contextlib.suppress(BrokenPipeError, OSError):
                conn.send(("close", None))
        for proc in self._procs:
            proc.join(timeout=10)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=5)
        for conn in self._conns:
            conn.close()
        self._views = {}
        for block in getattr(self, "_blocks", []):
            block.close()
            with contextlib.suppress(FileNotFoundError):
                block.unlink()
        self._conns, self._procs, self._blocks = [], [], []

    def __del__(self) -> None:  # noqa: D105
        if getattr(self, "_procs", None) or getattr(self, "_blocks", None):
            self.close()
