"""The evaluation harness behind ``eval.py``: trials, controllers, metrics, tables, figures, resume, parallel units.

A run evaluates **rows** (configurations: a policy, a policy behind the HOCBF shield, or a baseline) on **units**:
one (row, scene, target speed) with ``trials_per_scene`` trials. Every unit is independent: its trials are batched
in one :class:`envs.navigation.NavigationEnv` (``autoreset=False``, curriculum off, randomization off unless the
config asks for it), its result is written to ``<out>/units/<unit>.json`` as soon as it finishes, and a re-run of
the same command skips the units already on disk. ``workers > 1`` runs units in separate processes.

Trials are pinned: trial ``j`` of scene ``k`` at speed ``v`` draws its start and goal uniformly in the scene's
1 x 32 x 2 m start and goal boxes (rejecting points with ESDF < vehicle radius + 0.4 m, as the env does) from the
seed ``SeedSequence([seed, family_id, k, round(100 v), j])``. Every row sees the same trials (paired comparison),
and nothing depends on batching or on the number of workers. Yaw starts towards the goal, speed from rest.

Control never reads privileged information, except for the labelled oracle baseline. The privileged fields are
read for **metrics** only: ESDF clearance along the trajectory and the geodesic (Dijkstra) length.

Metrics (per trial; aggregated per unit and per (row, speed) cell over scenes):

* outcome: success (within ``goal_radius`` = 5 m of the goal, no collision), collision, out of bounds, timeout;
* success rate with a 95 % Wilson interval; collision and timeout rates;
* Vel: mean over successful trials of the trial's mean speed |v| (the paper's "average velocity");
* clearance: mean and minimum ESDF at the vehicle centre along the trajectory;
* path ratio: path length / (Phi(start) - Phi(end)), Phi the geodesic distance to the goal region (successes);
* shield: activation fraction of control steps, correction |a* - a_raw| (mean over active steps, max), relaxed
  fraction (the hard QP was infeasible: slack or braking fallback), QP solve time mean and max [us].
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import csv
import dataclasses
import glob
import hashlib
import io
import json
import math
import multiprocessing as mp
import os
import platform
import signal
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import yaml

from envs.config import ConfigError, load_config, require, to_dict
from envs.navigation.config import NavConfig
from envs.scenes import FAMILIES, make_scene
from shield_nav.baselines import BaselineConfig, Controller, make_baseline
from shield_nav.shield import STATUS_FALLBACK, STATUS_RELAXED, HOCBFShield, ShieldConfig

EVAL_FORMAT_VERSION = 1
"""Version of the unit/manifest JSON layout; bump when it changes."""
Z95 = 1.959963984540054
"""Standard normal quantile for a two-sided 95 % interval."""


class EvalError(RuntimeError):
    """Bad evaluation input (checkpoint, configuration name, scenes, output folder); raised before long work."""


# ============================================================================================ configuration
@dataclass
class RowConfig:
    """One configuration (a row of the table)."""

    label: str = ""
    """Name shown in the table."""
    controller: str = "policy"
    """``policy`` (an exported depth actor), ``teacher`` (a privileged MLP teacher's PPO checkpoint: it reads the
    local ESDF map, so the row is privileged like the oracle), or a baseline: ``oracle`` (privileged),
    ``oracle_euclidean`` (the same oracle descending the Euclidean distance to the goal instead of Phi; privileged),
    ``reactive``, ``reactive_geodesic`` (aligned with -grad Phi instead of the goal direction; privileged),
    ``goal``."""
    policy: str = ""
    """Checkpoint name (a key of ``checkpoints``) for ``controller: policy`` or ``teacher``."""
    shield: bool = False
    """Filter the commands through the HOCBF shield."""


POLICY_CONTROLLERS = ("policy", "teacher")
"""Row controllers that run a checkpoint named by ``RowConfig.policy``."""

ROWS_FILE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "configs", "eval", "rows.yaml")
"""The registry of named rows and the policy files they fly (YAML: ``rows:`` and ``checkpoints:``)."""


def load_registry(path: str = ROWS_FILE) -> tuple[dict[str, RowConfig], dict[str, str]]:
    """``(rows, checkpoints)`` of a registry file; a bad or unknown key is an :class:`EvalError` naming it."""
    if not os.path.isfile(path):
        raise EvalError(f"row registry {path!r} not found (it ships in the repository: configs/eval/rows.yaml)")
    with open(path) as fh:
        raw = yaml.safe_load(fh) or {}
    unknown = set(raw) - {"rows", "checkpoints"}
    if unknown:
        raise EvalError(f"{path}: unknown top-level key(s) {sorted(unknown)}; expected 'rows' and 'checkpoints'")
    names = {f.name for f in dataclasses.fields(RowConfig)}
    rows = {}
    for name, spec in (raw.get("rows") or {}).items():
        bad = set(spec or {}) - names
        if bad:
            raise EvalError(f"{path}: rows.{name}: unknown key(s) {sorted(bad)}; known: {sorted(names)}")
        rows[name] = RowConfig(**(spec or {}))
    checkpoints = {str(k): str(v) for k, v in (raw.get("checkpoints") or {}).items()}
    return rows, checkpoints


BUILTIN_ROWS, BUILTIN_CHECKPOINTS = load_registry()
"""Configurations known by name (:data:`ROWS_FILE`). A config's ``rows`` may add or override entries."""


@dataclass
class SceneSelection:
    """Which scenes a run uses."""

    family: str = "ablation"
    """Scene family (ablation, benchmark, dynamic, forest; train and train_shapes are allowed but were trained on)."""
    indices: list[int] = field(default_factory=list)
    """Scene indices; empty means the whole family."""


@dataclass
class EvalConfig:
    """An evaluation run. Loaded from ``configs/eval/*.yaml``; the CLI flags override single fields."""

    name: str = "eval"
    """Run name (default output folder ``eval_out/<name>``)."""
    title: str = ""
    """Table caption."""
    configurations: list[str] = field(default_factory=lambda: ["oracle", "reactive", "shield_only"])
    """Rows, by name: :data:`BUILTIN_ROWS` or ``rows``."""
    rows: dict[str, RowConfig] = field(default_factory=dict)
    """Extra (or overriding) row definitions."""
    checkpoints: dict[str, str] = field(default_factory=lambda: dict(BUILTIN_CHECKPOINTS))
    """Policy name -> exported policy (``policy.onnx`` / ``policy.pt``, or the folder holding it)."""
    missing_checkpoints: str = "error"
    """``error``: a row whose checkpoint is missing stops the run. ``skip``: the row is shown as missing."""
    scenes: SceneSelection = field(default_factory=SceneSelection)
    """Scenes."""
    speeds: list[float] = field(default_factory=lambda: [3.0, 5.0, 7.0, 9.0])
    """Target speeds [m/s]."""
    trials_per_scene: int = 10
    """Trials per (row, scene, speed) unit."""
    batch_size: int = 25
    """Trials flown together in one env (a unit with more trials runs in several batches)."""
    seed: int = 0
    """Seed of the trial sampling (and of each batch's env)."""
    workers: int = 1
    """Processes running units in parallel (does not change any result)."""
    randomization: bool = False
    """Keep the env's domain randomization and observation/depth noise (False: all switched off)."""
    env_overrides: list[str] = field(default_factory=lambda: ["episode.timeout_factor=1.5"])
    """Dotted ``NavConfig`` overrides (``a.b=value``) applied to every unit's env."""
    shield: ShieldConfig = field(default_factory=ShieldConfig)
    """HOCBF shield of rows with ``shield: true``."""
    baselines: BaselineConfig = field(default_factory=BaselineConfig)
    """Baseline controller parameters."""
    plots: bool = True
    """Write figures."""
    trajectory_scenes: int = 2
    """Scenes (the first ones) that get a top-down trajectory figure."""
    trajectory_every: int = 10
    """Record one trajectory point per this many control steps in the unit files (for figures)."""

    def validate(self, prefix: str = "") -> None:
        """Cross-field checks naming the key."""
        require(self.scenes.family in FAMILIES, f"{prefix}scenes.family",
                f"unknown family {self.scenes.family!r}; known: {sorted(FAMILIES)}")  # fmt: skip
        size = FAMILIES[self.scenes.family].size
        bad = [i for i in self.scenes.indices if not 0 <= i < size]
        require(not bad, f"{prefix}scenes.indices", f"{bad} out of range 0..{size - 1} for {self.scenes.family!r}")
        require(len(self.speeds) >= 1 and min(self.speeds) > 0, f"{prefix}speeds", "need at least one speed > 0")
        require(self.trials_per_scene >= 1, f"{prefix}trials_per_scene", "must be >= 1")
        require(self.batch_size >= 1, f"{prefix}batch_size", "must be >= 1")
        require(self.workers >= 1, f"{prefix}workers", "must be >= 1")
        require(self.trajectory_every >= 1, f"{prefix}trajectory_every", "must be >= 1")
        require(self.missing_checkpoints in ("error", "skip"), f"{prefix}missing_checkpoints",
                "must be 'error' or 'skip'")  # fmt: skip
        require(len(self.configurations) >= 1, f"{prefix}configurations", "need at least one configuration")
        for o in self.env_overrides:
            require("=" in o, f"{prefix}env_overrides", f"{o!r} is not of the form a.b=value")

    @property
    def scene_indices(self) -> list[int]:
        """The selected indices (the whole family when ``scenes.indices`` is empty)."""
        return list(self.scenes.indices) or list(range(FAMILIES[self.scenes.family].size))


def load_eval_config(path: str | os.PathLike | None = None, overrides: list[str] | None = None) -> EvalConfig:
    """Load an :class:`EvalConfig` from a YAML file (or defaults) and dotted overrides; strict keys."""
    return load_config(EvalConfig, files=path, overrides=overrides)


def parse_scenes(spec: str) -> SceneSelection:
    """``FAMILY`` or ``FAMILY:INDICES`` with INDICES like ``0,2,5`` or ``0-3`` (inclusive) -> SceneSelection."""
    family, _, idx = spec.partition(":")
    if family not in FAMILIES:
        raise EvalError(f"--scenes: unknown scene family {family!r}; known: {sorted(FAMILIES)}")
    indices: list[int] = []
    for part in filter(None, idx.split(",")):
        try:
            if "-" in part:
                a, b = part.split("-", 1)
                indices += list(range(int(a), int(b) + 1))
            else:
                indices.append(int(part))
        except ValueError:
            raise EvalError(f"--scenes: bad index list {idx!r} (use e.g. 0,2,5 or 0-3)") from None
    size = FAMILIES[family].size
    bad = [i for i in indices if not 0 <= i < size]
    if bad:
        raise EvalError(f"--scenes: indices {bad} out of range 0..{size - 1} for family {family!r}")
    return SceneSelection(family, indices)


def resolve_rows(cfg: EvalConfig) -> dict[str, RowConfig]:
    """Row name -> definition, in the config's order. Unknown names raise :class:`EvalError`."""
    known = {**BUILTIN_ROWS, **cfg.rows}
    out: dict[str, RowConfig] = {}
    for name in cfg.configurations:
        if name not in known:
            raise EvalError(f"unknown configuration {name!r}; known: {sorted(known)} (or define it under 'rows:')")
        row = known[name]
        if row.controller in POLICY_CONTROLLERS and not row.policy:
            raise EvalError(f"configuration {name!r} is a {row.controller} row but names no checkpoint ('policy:')")
        if row.controller not in POLICY_CONTROLLERS:
            make_baseline(row.controller, cfg.baselines)  # raises on an unknown controller name
        out[name] = row
    return out


# ============================================================================================ policies
@dataclass
class PolicyInfo:
    """What the harness knows about an exported policy."""

    name: str
    """Checkpoint name."""
    path: str
    """The file that runs (``.onnx`` or TorchScript ``.pt``)."""
    kind: str
    """``onnx`` or ``torchscript``."""
    sha256: str
    """SHA-256 of that file."""
    obs_dim: int
    """State vector length S the policy expects."""
    depth_shape: tuple[int, int, int]
    """Depth image shape (C, H, W) the policy expects."""
    num_layers: int
    """GRU layers L."""
    hidden_size: int
    """GRU hidden size Hd."""
    train_config: str | None
    """The resolved training config found next to the checkpoint, if any."""
    train_speeds: tuple[float, float] | None
    """Target-speed range [lo, hi] the policy was trained for (from that config), if known."""
    train_env: dict | None = None
    """The ``action``, ``camera`` and ``vehicle`` sections of the training env config (evaluation flies the policy
    with these, so its actions mean what they meant in training), if found."""


class LoadedPolicy:
    """A runnable exported actor: ``step(state (N, S), depth (N, C, H, W), h (L, N, Hd)) -> (actions (N, 4), h)``.

    The GRU state is threaded explicitly by the caller (zeros at the start of each trial, as in training).
    """

    def __init__(self, info: PolicyInfo, runner: Any, names: dict[str, str] | None = None) -> None:  # noqa: D107
        self.info = info
        self._runner = runner
        self._names = names or {}

    def initial_state(self, n: int) -> np.ndarray:
        """Zero hidden state (L, n, Hd), float32."""
        return np.zeros((self.info.num_layers, n, self.info.hidden_size), dtype=np.float32)

    def step(self, state: np.ndarray, depth: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One deterministic policy step for a batch (see the class docstring)."""
        state = np.ascontiguousarray(state, dtype=np.float32)
        depth = np.ascontiguousarray(depth, dtype=np.float32)
        if self.info.kind == "onnx":
            n = self._names
            act, h_out = self._runner.run(
                [n["actions"], n["h_out"]], {n["obs"]: state, n["depth"]: depth, n["h_in"]: h}
            )
            return np.asarray(act, dtype=np.float64), np.asarray(h_out, dtype=np.float32)
        import torch

        with torch.no_grad():
            act, h_out = self._runner(torch.from_numpy(state), torch.from_numpy(depth), torch.from_numpy(h))
        return act.numpy().astype(np.float64), h_out.numpy().astype(np.float32)


def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _find_policy_file(path: str, name: str) -> str:
    if not os.path.exists(path):
        raise EvalError(f"checkpoint {name!r}: {path!r} does not exist")
    if os.path.isfile(path):
        return path
    for rel in ("policy.onnx", "exported/policy.onnx", "policy.pt", "exported/policy.pt"):
        cand = os.path.join(path, rel)
        if os.path.isfile(cand):
            return cand
    has_ckpt = glob.glob(os.path.join(path, "model_*.pt"))
    hint = " It holds training checkpoints (model_*.pt) but no export;" if has_ckpt else ""
    raise EvalError(
        f"checkpoint {name!r}: folder {path!r} has no policy.onnx / exported/policy.onnx / policy.pt.{hint} "
        "export the actor (train.py writes exported/policy.onnx) and point --checkpoint at it"
    )


def _find_train_config(policy_file: str) -> str | None:
    """The resolved training config near an exported policy: params/*.yaml or *.yaml, up to two folders up."""
    d = os.path.dirname(os.path.abspath(policy_file))
    for _ in range(3):
        for pattern in ("params/env.yaml", "params/*.yaml", "config.yaml", "*.yaml"):
            hits = sorted(glob.glob(os.path.join(d, pattern)))
            if hits:
                return hits[0]
        d = os.path.dirname(d)
    return None


def _read_policy_config(path: str, lost: str) -> Any:
    """A policy's resolved training config, or None with a warning that names the file and what is lost."""
    try:
        with open(path) as f:
            return yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as err:
        warnings.warn(f"cannot read the policy's training config {path!r} ({type(err).__name__}: {err}); "
                      f"evaluating without {lost}", stacklevel=3)  # fmt: skip
        return None


def _speeds_from_config(path: str | None) -> tuple[float, float] | None:
    """Target-speed range from a resolved config: the first ``episode`` mapping with target_speeds/speed_range."""
    if path is None:
        return None
    data = _read_policy_config(path, "the out-of-range speed flag")
    if data is None:
        return None
    stack = [data]
    while stack:
        node = stack.pop()
        if isinstance(node, dict):
            ep = node.get("episode")
            if isinstance(ep, dict) and ("target_speeds" in ep or "speed_range" in ep):
                rng = ep.get("speed_range") or []
                if len(rng) == 2:
                    return float(rng[0]), float(rng[1])
                sp = [float(s) for s in ep.get("target_speeds") or []]
                return (min(sp), max(sp)) if sp else None
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
    return None


POLICY_ENV_SECTIONS = ("action", "camera", "vehicle")
"""Env config sections taken from a policy's training config when it is evaluated."""


def _env_from_config(path: str | None) -> dict | None:
    """The :data:`POLICY_ENV_SECTIONS` of the ``env`` mapping of a resolved training config (TrainConfig layout)."""
    if path is None:
        return None
    data = _read_policy_config(path, "its training env's action, camera and vehicle settings")
    if data is None:
        return None
    env = data.get("env") if isinstance(data, dict) else None
    if not isinstance(env, dict):
        return None
    out = {k: env[k] for k in POLICY_ENV_SECTIONS if isinstance(env.get(k), dict)}
    return out or None


def _dim(value: Any, what: str, path: str) -> int:
    if not isinstance(value, int):
        raise EvalError(f"policy {path!r}: {what} has no fixed size ({value!r}); cannot check the layout")
    return value


def load_policy(path: str | os.PathLike, name: str = "policy") -> LoadedPolicy:
    """Load an exported actor (ONNX through onnxruntime, or TorchScript ``policy.pt``) and read its layout.

    ``path`` is a file or a folder holding ``policy.onnx`` / ``exported/policy.onnx`` / ``policy.pt``. The ONNX
    graph's inputs are told apart by rank (state (B, S), depth (B, C, H, W), hidden (L, B, Hd)) and its outputs
    by rank (actions (B, A), hidden), so the names are read from the model rather than assumed.

    Raises:
        EvalError: missing file, a training checkpoint instead of an export, or an unreadable model.
    """
    file = _find_policy_file(os.fspath(path), name)
    cfg_path = _find_train_config(file)
    speeds = _speeds_from_config(cfg_path)
    train_env = _env_from_config(cfg_path)
    if file.endswith(".onnx"):
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.inter_op_num_threads = 1
        try:
            sess = ort.InferenceSession(file, opts, providers=["CPUExecutionProvider"])
        except Exception as err:
            raise EvalError(f"checkpoint {name!r}: {file!r} is not a loadable ONNX model: {err}") from None
        by_rank = {len(i.shape): i for i in sess.get_inputs()}
        outs = {len(o.shape): o for o in sess.get_outputs()}
        if sorted(by_rank) != [2, 3, 4] or sorted(outs) != [2, 3]:
            raise EvalError(
                f"checkpoint {name!r}: {file!r} has inputs {[(i.name, i.shape) for i in sess.get_inputs()]} and "
                f"outputs {[(o.name, o.shape) for o in sess.get_outputs()]}; expected state (B, S), depth "
                "(B, C, H, W), hidden (L, B, Hd) -> actions (B, A), hidden (the DepthGRUModel export)"
            )
        obs_dim = _dim(by_rank[2].shape[1], "state input", file)
        depth_shape = tuple(_dim(v, "depth input", file) for v in by_rank[4].shape[1:])
        num_layers = _dim(by_rank[3].shape[0], "hidden input", file)
        hidden = _dim(by_rank[3].shape[2], "hidden input", file)
        names = {"obs": by_rank[2].name, "depth": by_rank[4].name, "h_in": by_rank[3].name,
                 "actions": outs[2].name, "h_out": outs[3].name}  # fmt: skip
        info = PolicyInfo(name, file, "onnx", _sha256(file), obs_dim, depth_shape, num_layers, hidden,  # type: ignore[arg-type]
                          cfg_path, speeds, train_env)  # fmt: skip
        return LoadedPolicy(info, sess, names)
    import torch

    try:
        mod = torch.jit.load(file, map_location="cpu")
    except Exception as err:
        raise EvalError(_torch_file_problem(file, name, err)) from None
    try:
        obs_dim, depth_shape = int(mod.obs_dim), tuple(int(v) for v in mod.depth_shape)
        num_layers, hidden = int(mod.num_layers), int(mod.hidden_size)
    except Exception:
        raise EvalError(f"checkpoint {name!r}: {file!r} lacks obs_dim/depth_shape/num_layers/hidden_size") from None
    mod.eval()
    info = PolicyInfo(name, file, "torchscript", _sha256(file), obs_dim, depth_shape, num_layers, hidden,  # type: ignore[arg-type]
                      cfg_path, speeds, train_env)  # fmt: skip
    return LoadedPolicy(info, mod)


def _torch_file_problem(file: str, name: str, err: Exception) -> str:
    """Why a ``.pt`` file did not load as TorchScript: truncated/corrupt, a training checkpoint, or something else."""
    import zipfile

    size = os.path.getsize(file)
    intact = False
    if zipfile.is_zipfile(file):
        try:
            with zipfile.ZipFile(file) as z:
                intact = z.testzip() is None
        except (zipfile.BadZipFile, OSError, EOFError):
            intact = False
    if not intact:
        return (f"checkpoint {name!r}: {file!r} ({size} bytes) is truncated or corrupt: not a complete torch archive "
                "(an interrupted copy or save?); re-copy or re-export it")  # fmt: skip
    with zipfile.ZipFile(file) as z:
        if any(n.endswith("/constants.pkl") or n.endswith("/code/__torch__.py") for n in z.namelist()):
            return f"checkpoint {name!r}: {file!r} is a TorchScript archive that failed to load: {err}"
    return (f"checkpoint {name!r}: {file!r} is not a TorchScript export ({type(err).__name__}); a training "
            "checkpoint (model_<it>.pt) cannot be run directly: use the exported policy.onnx or policy.pt")  # fmt: skip


class LoadedTeacher:
    """A privileged MLP teacher: ``step(teacher_obs (N, T)) -> actions (N, 4)``, deterministic (the mean action).

    ``teacher_obs`` is the env's ``info["teacher"]`` (the clean state and the local ESDF map), so a teacher row is
    privileged (the policy its student imitates), never a deployable controller.
    """

    def __init__(self, info: PolicyInfo, model: Any, group: str) -> None:  # noqa: D107
        self.info = info
        self._model = model
        self._group = group

    def step(self, teacher_obs: np.ndarray) -> np.ndarray:
        """Mean action for a batch of teacher observations."""
        import torch
        from tensordict import TensorDict

        x = torch.from_numpy(np.ascontiguousarray(teacher_obs, dtype=np.float32))
        with torch.no_grad():
            act = self._model(TensorDict({self._group: x}, batch_size=[x.shape[0]]))
        return act.numpy().astype(np.float64)


def load_teacher(path: str | os.PathLike, name: str = "teacher") -> LoadedTeacher:
    """Load a privileged teacher from its PPO checkpoint (``model.pt``, or the packaged folder holding it).

    The actor is rebuilt with rsl-rl's own ``MLPModel`` from the resolved config stored in the checkpoint. Its
    training env's ``local_map`` section comes along in ``train_env``, so evaluation samples the same map.

    Raises:
        EvalError: missing file, not a PPO checkpoint, or an actor that does not read the ``teacher`` group only.
    """
    import torch
    from rsl_rl.models import MLPModel
    from tensordict import TensorDict

    from shield_nav.training import load_train_config, read_checkpoint_infos, rsl_rl_train_cfg

    path = os.fspath(path)
    file = os.path.join(path, "model.pt") if os.path.isdir(path) else path
    if not os.path.isfile(file):
        raise EvalError(f"checkpoint {name!r}: no teacher checkpoint at {file!r} (model.pt of a teacher_* run)")
    try:
        ckpt = torch.load(file, map_location="cpu", weights_only=False)
        tcfg = load_train_config(overrides=read_checkpoint_infos(file)["config"])
    except Exception as err:
        raise EvalError(f"checkpoint {name!r}: {file!r} is not a readable training checkpoint: {err}") from None
    groups = tcfg.runner.obs_groups.get("actor", [])
    if "actor_state_dict" not in ckpt or tcfg.runner.actor.class_name != "MLPModel" or groups != ["teacher"]:
        raise EvalError(
            f"checkpoint {name!r}: {file!r} is not a privileged teacher (a PPO checkpoint whose actor is an MLPModel "
            f"over the 'teacher' group; got {tcfg.runner.actor.class_name} over {groups})"
        )
    dim = ckpt["actor_state_dict"]["mlp.0.weight"].shape[1]
    kwargs = {k: v for k, v in rsl_rl_train_cfg(tcfg)["actor"].items() if k != "class_name"}
    model = MLPModel(TensorDict({"teacher": torch.zeros(1, dim)}, batch_size=[1]), {"actor": ["teacher"]}, "actor",
                     4, **kwargs)  # fmt: skip
    model.load_state_dict(ckpt["actor_state_dict"])
    model.eval()
    env = to_dict(tcfg.env)
    train_env = {k: env[k] for k in (*POLICY_ENV_SECTIONS, "local_map")}
    cfg_path = os.path.join(os.path.dirname(file), "params", "config.yaml")
    cfg_path = cfg_path if os.path.isfile(cfg_path) else None
    speeds = tcfg.env.episode.speed_range or tcfg.env.episode.target_speeds
    info = PolicyInfo(name, file, "teacher", _sha256(file), dim, (0, 0, 0), 0, 0, cfg_path,
                      (min(speeds), max(speeds)), train_env)  # fmt: skip
    return LoadedTeacher(info, model, "teacher")


def check_layout(info: PolicyInfo, state_dim: int, depth_shape: tuple[int, int, int]) -> None:
    """Raise :class:`EvalError` unless the policy's observation layout matches the env's."""
    problems = []
    if info.obs_dim != state_dim:
        problems.append(f"state vector has {info.obs_dim} values, the env gives {state_dim}")
    if tuple(info.depth_shape) != tuple(depth_shape):
        problems.append(f"depth image is {tuple(info.depth_shape)}, the env gives {tuple(depth_shape)}")
    if problems:
        raise EvalError(
            f"checkpoint {info.name!r} ({info.path}) does not match the env's observation layout: "
            + "; ".join(problems)
            + ". Evaluate it with the env config it was trained with (env_overrides), or retrain."
        )


# ============================================================================================ metrics
def wilson_interval(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for k successes in n trials.

    p = k/n, c = (p + z^2/(2n)) / (1 + z^2/n), h = z / (1 + z^2/n) * sqrt(p(1-p)/n + z^2/(4n^2));
    the interval is [c - h, c + h] (never outside [0, 1]). n = 0 gives (0, 1).
    """
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    # At k = 0 (k = n) the lower (upper) bound is exactly 0 (1); set it so round-off cannot leave 3e-17.
    lo = 0.0 if k == 0 else max(0.0, centre - half)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return lo, hi


def trajectory_metrics(
    pos: np.ndarray, speed: np.ndarray, esdf: np.ndarray, phi_start: float, phi_end: float
) -> dict[str, float]:
    """Per-trial geometry of one trajectory.

    Inputs: positions (T+1, 3) (start included), speeds |v| (T,) after each step, and the ESDF (T+1,) at those
    positions.

    path_length = sum_t |p_{t+1} - p_t|; mean_speed = mean_t |v_t|; clearance_mean/min = mean/min of the ESDF;
    path_ratio = path_length / (Phi(start) - Phi(end)) (Phi: geodesic distance to the goal region; NaN when the
    trajectory made no geodesic progress).
    """
    steps = np.diff(pos, axis=0)
    length = float(np.linalg.norm(steps, axis=1).sum())
    progress = phi_start - phi_end
    return {
        "path_length": length,
        "mean_speed": float(np.mean(speed)) if len(speed) else 0.0,
        "clearance_mean": float(np.mean(esdf)),
        "clearance_min": float(np.min(esdf)),
        "geodesic_progress": float(progress),
        "path_ratio": float(length / progress) if progress > 1e-6 else float("nan"),
    }


def _nanmean(values: list[float]) -> float:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    return float(v.mean()) if len(v) else float("nan")


def aggregate(trials: list[dict]) -> dict[str, Any]:
    """Cell metrics over trials (see the module docstring). Shield rates pool control steps over trials."""
    n = len(trials)
    outcomes = [t["outcome"] for t in trials]
    k = outcomes.count("success")
    lo, hi = wilson_interval(k, n)
    succ = [t for t in trials if t["outcome"] == "success"]
    sh = [t["shield"] for t in trials if t.get("shield")]
    steps = sum(s["steps"] for s in sh)
    active = sum(s["active_steps"] for s in sh)
    out: dict[str, Any] = {
        "n": n,
        "successes": k,
        "success_rate": k / n if n else float("nan"),
        "sr_lo": lo,
        "sr_hi": hi,
        "collision_rate": outcomes.count("collision") / n if n else float("nan"),
        "timeout_rate": outcomes.count("timeout") / n if n else float("nan"),
        "oob_rate": outcomes.count("out_of_bounds") / n if n else float("nan"),
        "vel": _nanmean([t["metrics"]["mean_speed"] for t in succ]),
        "clearance_mean": _nanmean([t["metrics"]["clearance_mean"] for t in trials]),
        "clearance_min": float(np.min([t["metrics"]["clearance_min"] for t in trials])) if n else float("nan"),
        "path_ratio": _nanmean([t["metrics"]["path_ratio"] for t in succ]),
    }
    if sh:
        out.update(
            {
                "shield_active": active / steps if steps else 0.0,
                "corr_mean": sum(s["corr_sum"] for s in sh) / active if active else 0.0,
                "corr_max": max(s["corr_max"] for s in sh),
                "relaxed": sum(s["relaxed_steps"] for s in sh) / steps if steps else 0.0,
                "qp_us_mean": sum(s["solve_us_sum"] for s in sh) / active if active else 0.0,
                "qp_us_max": max(s["solve_us_max"] for s in sh),
                "shield_us_mean": sum(s["total_us_sum"] for s in sh) / steps if steps else 0.0,
            }
        )
    return out


# ============================================================================================ units
def trial_seed(seed: int, family: str, index: int, speed: float, j: int) -> int:
    """Seed of trial j of scene (family, index) at ``speed``; independent of the row, batching and workers."""
    ss = np.random.SeedSequence([seed, FAMILIES[family].family_id, index, int(round(100 * speed)), j])
    return int(ss.generate_state(1)[0])


def sample_trial(scene: Any, field_stack: Any, scene_id: int, seed: int, need: float) -> dict[str, Any]:
    """Start and goal uniform in the scene's start/goal boxes with ESDF > ``need`` (best of 50 draws each)."""
    rng = np.random.default_rng(seed)
    out: dict[str, Any] = {"seed": seed}
    for key, region in (("start", scene.start_region), ("goal", scene.goal_region)):
        lo, hi = np.asarray(region[0]), np.asarray(region[1])
        pts = rng.uniform(lo, hi, (50, 3))
        d = field_stack.esdf(np.full(50, scene_id), pts)
        ok = np.flatnonzero(d > need)
        out[key] = pts[ok[0] if len(ok) else int(np.argmax(d))].tolist()
    s, g = np.asarray(out["start"]), np.asarray(out["goal"])
    out["yaw"] = float(math.atan2(g[1] - s[1], g[0] - s[0]))
    return out


def unit_key(row: str, family: str, index: int, speed: float) -> str:
    """File-name-safe id of a unit."""
    return f"{row}__{family}-{index:02d}__v{speed:g}"


@dataclass
class UnitSpec:
    """One (row, scene, speed) unit, everything a worker needs (picklable)."""

    key: str
    row_name: str
    row: dict
    family: str
    index: int
    speed: float
    cfg: dict
    policy_path: str | None
    policy_env: dict | None = None


def nav_config(
    cfg: EvalConfig, family: str, index: int, speed: float, n: int, policy_env: dict | None = None
) -> NavConfig:
    """The env config of a unit batch: the eval's env_overrides, one scene, one speed, no curriculum/autoreset.

    ``policy_env`` (a policy's training ``action``/``camera``/``vehicle`` sections) is merged first, so a policy
    is flown with the action scaling, camera and vehicle it was trained with; the eval's overrides come after.
    """
    forced = {
        "num_envs": n,
        "scenes.family": family,
        "scenes.indices": [index],
        "curriculum.enabled": False,
        "autoreset": False,
        "episode.target_speeds": [float(speed)],
        "episode.speed_range": [],
    }
    extra = dict(o.split("=", 1) for o in cfg.env_overrides)
    try:
        base = load_config(NavConfig, overrides=policy_env) if policy_env else None
        nav = load_config(
            NavConfig, overrides={**{k: yaml.safe_load(v) for k, v in extra.items()}, **forced}, base=base
        )
    except ConfigError as err:
        raise EvalError(f"env_overrides: {err}") from None
    if not cfg.randomization:
        nav.randomization.disable()
    return nav


def flown_scene(cfg: EvalConfig, family: str, index: int) -> Any:
    """The scene a unit of ``cfg`` flies: ``family``/``index`` with the seed of its env overrides, if any.

    Trial sampling, figures, videos and the collision analysis use it, so they show the scene that was flown (an
    eval with ``scenes.seed`` in ``env_overrides``), not the family's default.
    """
    seed = nav_config(cfg, family, index, cfg.speeds[0], 1).scenes.seed
    return make_scene(family, index, seed)


_POLICY_CACHE: dict[str, LoadedPolicy] = {}


def _policy(path: str) -> LoadedPolicy:
    if path not in _POLICY_CACHE:
        _POLICY_CACHE[path] = load_policy(path)
    return _POLICY_CACHE[path]


_TEACHER_CACHE: dict[str, LoadedTeacher] = {}


def _teacher(path: str) -> LoadedTeacher:
    if path not in _TEACHER_CACHE:
        _TEACHER_CACHE[path] = load_teacher(path)
    return _TEACHER_CACHE[path]


def _run_batch(spec: UnitSpec, cfg: EvalConfig, trials: list[dict], env: Any, on_step: Any | None = None) -> list[dict]:
    """Fly one batch of pinned trials to the end; returns per-trial records.

    ``on_step(env, t, active)`` (optional) is called after the reset (t = 0) and after every control step, with
    ``active`` (N,) the shield's activity of that step (all False without a shield); video recording uses it.
    """
    row = RowConfig(**spec.row)
    n = len(trials)
    env.sim_time = 0.0  # moving obstacles start from their t = 0 positions in every batch (determinism)
    obs, priv = env.reset(
        seed=trials[0]["seed"] % (2**31),
        options={
            "scene_ids": np.zeros(n, dtype=np.int64),
            "start": np.array([t["start"] for t in trials]),
            "goal": np.array([t["goal"] for t in trials]),
            "speed": np.full(n, spec.speed),
            "yaw": np.array([t["yaw"] for t in trials]),
        },
    )
    policy: LoadedPolicy | None = None
    teacher: LoadedTeacher | None = None
    ctrl: Controller | None = None
    if row.controller == "policy":
        policy = _policy(spec.policy_path)  # type: ignore[arg-type]
        h = policy.initial_state(n)
    elif row.controller == "teacher":
        teacher = _teacher(spec.policy_path)  # type: ignore[arg-type]
    else:
        ctrl = make_baseline(row.controller, cfg.baselines)
        ctrl.reset(env)
    shield = HOCBFShield(cfg.shield, env.cfg.camera) if row.shield else None
    ids = np.zeros(n, dtype=np.int64)
    pos0 = env.local_pos.copy()
    phi_start = env.field_stack.geodesic(ids, pos0)
    track_pos = [pos0]
    track_speed: list[np.ndarray] = []
    track_esdf = [env.field_stack.esdf(ids, pos0)]
    end_step = np.full(n, -1)
    outcome = [""] * n
    sh = {"steps": np.zeros(n, int), "active_steps": np.zeros(n, int), "corr_sum": np.zeros(n),
          "corr_max": np.zeros(n), "relaxed_steps": np.zeros(n, int), "solve_us_sum": np.zeros(n),
          "solve_us_max": np.zeros(n), "total_us_sum": np.zeros(n)}  # fmt: skip
    t = 0
    zeros = np.zeros((n, 4))
    if on_step is not None:
        on_step(env, 0, np.zeros(n, dtype=bool))
    while (end_step < 0).any():
        live = end_step < 0
        if policy is not None or teacher is not None:
            if policy is not None:
                act, h = policy.step(obs["state"], obs["depth"], h)
            else:
                act = teacher.step(priv["teacher"])  # type: ignore[union-attr]
            cmd = env.action_to_command(np.clip(act, -1.0, 1.0)) if shield is not None else None
        else:
            act, cmd = zeros, ctrl.commands(env)  # type: ignore[union-attr]
        step_active = np.zeros(n, dtype=bool)
        if shield is not None:
            li = np.flatnonzero(live)
            out = shield.filter(cmd[li], env.local_pos[li], env.vehicles.vel_w[li],
                                depth=env.sensor_depth_buf[li], R_wb=env.vehicles.R_wb[li], ids=li)  # fmt: skip
            cmd[li] = out.command
            step_active[li] = out.active
            corr = np.linalg.norm(out.accel_safe - out.accel_raw, axis=1)
            sh["steps"][li] += 1
            sh["active_steps"][li] += out.active
            sh["corr_sum"][li] += np.where(out.active, corr, 0.0)
            sh["corr_max"][li] = np.maximum(sh["corr_max"][li], np.where(out.active, corr, 0.0))
            sh["relaxed_steps"][li] += (out.status == STATUS_RELAXED) | (out.status == STATUS_FALLBACK)
            sh["solve_us_sum"][li] += out.solve_us
            sh["solve_us_max"][li] = np.maximum(sh["solve_us_max"][li], out.solve_us)
            sh["total_us_sum"][li] += out.total_us
        obs, _, term, trunc, info = env.step(act, commands=cmd)
        priv = info
        t += 1
        if on_step is not None:
            on_step(env, t, step_active)
        pos = env.local_pos.copy()
        track_pos.append(pos)
        track_speed.append(np.linalg.norm(env.vehicles.vel_w, axis=1))
        track_esdf.append(env.field_stack.esdf(ids, pos))
        for name, flag in (("success", info["success"]), ("collision", info["collision"]),
                           ("out_of_bounds", info["out_of_bounds"]), ("timeout", info["time_outs"])):  # fmt: skip
            for i in np.flatnonzero(flag & live):
                if end_step[i] < 0:
                    end_step[i], outcome[i] = t, name
    P, V, E = np.stack(track_pos), np.stack(track_speed), np.stack(track_esdf)  # (T+1, n, 3), (T, n), (T+1, n)
    records = []
    every = cfg.trajectory_every
    dt = env.cfg.vehicle.command_dt
    for i, trial in enumerate(trials):
        T = int(end_step[i])
        pos_i = P[: T + 1, i]
        phi_end = float(env.field_stack.geodesic(np.zeros(1, np.int64), pos_i[-1:])[0])
        m = trajectory_metrics(pos_i, V[:T, i], E[: T + 1, i], float(phi_start[i]), phi_end)
        m["duration"] = T * dt
        m["final_goal_dist"] = float(np.linalg.norm(pos_i[-1] - np.asarray(trial["goal"])))
        keep = list(range(0, T + 1, every)) + ([T] if T % every else [])
        rec = {
            **trial,
            "row": spec.row_name,
            "family": spec.family,
            "scene": spec.index,
            "speed": spec.speed,
            "outcome": outcome[i],
            "steps": T,
            "metrics": m,
            "traj": np.round(np.concatenate((pos_i[keep], np.r_[0.0, V[:T, i]][keep, None]), axis=1), 3).tolist(),
        }
        if shield is not None:
            rec["shield"] = {k: (v[i].item()) for k, v in sh.items()}
        records.append(rec)
    return records


def run_unit(spec: UnitSpec) -> dict:
    """Run one unit (all its trials, in batches); returns the unit record (written by the caller)."""
    from envs.navigation import NavigationEnv

    cfg = _from_dict(spec.cfg)
    t0 = time.perf_counter()
    scene = flown_scene(cfg, spec.family, spec.index)
    n_all = cfg.trials_per_scene
    seeds = [trial_seed(cfg.seed, spec.family, spec.index, spec.speed, j) for j in range(n_all)]
    records: list[dict] = []
    batches = [b for b in np.array_split(np.arange(n_all), math.ceil(n_all / cfg.batch_size)) if len(b)]
    for b in batches:
        env = NavigationEnv(config=nav_config(cfg, spec.family, spec.index, spec.speed, len(b), spec.policy_env))
        need = env.cfg.vehicle.airframe.collision_radius + 0.4
        trials = [sample_trial(scene, env.field_stack, 0, seeds[j], need) for j in b]
        for tr, j in zip(trials, b, strict=True):
            tr["trial"] = int(j)
        records += _run_batch(spec, cfg, trials, env)
        env.close()
    return {
        "format": EVAL_FORMAT_VERSION,
        "key": spec.key,
        "row": spec.row_name,
        "family": spec.family,
        "scene": spec.index,
        "speed": spec.speed,
        "trials": records,
        "summary": aggregate(records),
        "wall_s": time.perf_counter() - t0,
    }


def _from_dict(d: dict) -> EvalConfig:
    """Rebuild an EvalConfig from its plain dict (workers receive dicts)."""
    from omegaconf import OmegaConf

    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(EvalConfig), d))  # type: ignore[return-value]


def _worker_init() -> None:
    """One thread per worker process: the units run in parallel, not the math inside them."""
    with contextlib.suppress(Exception):
        import numba

        numba.set_num_threads(1)
    with contextlib.suppress(Exception):
        import torch

        torch.set_num_threads(1)


# ============================================================================================ the run
@dataclass
class Prepared:
    """Checked inputs of a run (everything validated before any flying)."""

    cfg: EvalConfig
    rows: dict[str, RowConfig]
    policies: dict[str, PolicyInfo]
    missing: dict[str, str]
    """Row name -> why it is missing (``missing_checkpoints: skip``)."""
    warnings: list[str]
    speed_flags: dict[tuple[str, float], str]
    """(row, speed) -> warning marker text for speeds outside a policy's training range."""


def prepare(cfg: EvalConfig, explicit_checkpoints: tuple[str, ...] = ()) -> Prepared:
    """Validate rows and checkpoints before any work: unknown rows, missing or mismatching checkpoints, speeds.

    Args:
        cfg: The run config.
        explicit_checkpoints: Checkpoint names given on the command line: a missing one is always an error.
    """
    from envs.navigation.env import STATE_DIM

    rows = resolve_rows(cfg)
    probe = nav_config(cfg, cfg.scenes.family, cfg.scene_indices[0], cfg.speeds[0], 1)
    depth_shape = (1, probe.camera.height, probe.camera.width)
    policies: dict[str, PolicyInfo] = {}
    missing: dict[str, str] = {}
    notes: list[str] = []
    flags: dict[tuple[str, float], str] = {}
    needed = {r.policy: r.controller for r in rows.values() if r.controller in POLICY_CONTROLLERS}
    for pname in sorted(needed):
        if pname not in cfg.checkpoints:
            raise EvalError(f"no checkpoint path for policy {pname!r}; give --checkpoint {pname}=PATH")
        try:
            loader = load_teacher if needed[pname] == "teacher" else load_policy
            pol = loader(cfg.checkpoints[pname], pname)
        except EvalError as err:
            if cfg.missing_checkpoints == "skip" and pname not in explicit_checkpoints and \
                    not os.path.exists(cfg.checkpoints[pname]):  # fmt: skip
                for rname, r in rows.items():
                    if r.policy == pname:
                        missing[rname] = f"no checkpoint at {cfg.checkpoints[pname]}"
                continue
            raise err
        nav = nav_config(cfg, cfg.scenes.family, cfg.scene_indices[0], cfg.speeds[0], 1, pol.info.train_env)
        cam = nav.camera
        if pol.info.kind == "teacher":
            lm = nav.local_map
            want = STATE_DIM + len(lm.xs) * len(lm.ys) * len(lm.zs)
            if pol.info.obs_dim != want:
                raise EvalError(f"checkpoint {pname!r} ({pol.info.path}) reads {pol.info.obs_dim} teacher values; "
                                f"its local map config gives {want}")  # fmt: skip
        else:
            check_layout(pol.info, STATE_DIM, (1, cam.height, cam.width))
        if pol.info.kind != "teacher" and (cam.height, cam.width) != depth_shape[1:]:
            notes.append(f"policy {pname!r} flies with its training camera {cam.width}x{cam.height}")
        policies[pname] = pol.info
        if pol.info.train_speeds is None:
            notes.append(f"policy {pname!r}: no training config found next to {pol.info.path}; speed range unchecked")
        else:
            lo, hi = pol.info.train_speeds
            for rname, r in rows.items():
                if r.policy != pname:
                    continue
                for v in cfg.speeds:
                    if not lo - 1e-9 <= v <= hi + 1e-9:
                        flags[(rname, v)] = f"{v:g} m/s is outside {pname!r}'s training range [{lo:g}, {hi:g}]"
    for msg in flags.values():
        warnings.warn(msg, stacklevel=2)
    return Prepared(cfg, rows, policies, missing, notes, flags)


def plan_units(prep: Prepared) -> list[UnitSpec]:
    """Every (row, scene, speed) unit to run, rows outermost (so a partial run has whole rows first)."""
    cfg = prep.cfg
    d = to_dict(cfg)
    units = []
    for rname, row in prep.rows.items():
        if rname in prep.missing:
            continue
        pol = prep.policies[row.policy] if row.controller in POLICY_CONTROLLERS else None
        env = pol and pol.train_env
        if row.controller == "teacher":  # the map replaces the camera; render only if the shield needs depth
            env = {**env, "local_map": {**env["local_map"], "enabled": True}, "render_depth": bool(row.shield)}
        for v in cfg.speeds:
            for k in cfg.scene_indices:
                units.append(UnitSpec(unit_key(rname, cfg.scenes.family, k, v), rname, dataclasses.asdict(row),
                                      cfg.scenes.family, k, float(v), d, pol and pol.path, env))  # fmt: skip
    return units


def _git_info() -> dict[str, Any]:
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10).stdout
        except Exception:
            return ""

    diff = git("diff", "HEAD")
    return {"rev": git("rev-parse", "HEAD").strip() or "unknown", "dirty": bool(diff.strip()),
            "diff_sha256": hashlib.sha256(diff.encode()).hexdigest() if diff else ""}  # fmt: skip


def _identity(prep: Prepared) -> dict:
    """What must match for a re-run to resume into an existing folder (workers excluded: it changes nothing)."""
    d = to_dict(prep.cfg)
    d.pop("workers", None)
    return {"config": d, "checkpoint_sha256": {k: v.sha256 for k, v in prep.policies.items()}}


def _write_json(path: str, data: Any) -> None:
    """Atomic write (tmp + rename): a crash never leaves a half-written file that resume would trust."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1, default=_json_default)
    os.replace(tmp, path)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def open_output(prep: Prepared, out_dir: str, argv: list[str] | None = None) -> None:
    """Create (or check, for resume) the output folder and its manifest: git revision, configs, checkpoint hashes."""
    os.makedirs(os.path.join(out_dir, "units"), exist_ok=True)
    ident = _identity(prep)
    digest = hashlib.sha256(json.dumps(ident, sort_keys=True, default=str).encode()).hexdigest()
    man_path = os.path.join(out_dir, "manifest.json")
    if os.path.exists(man_path):
        with open(man_path) as f:
            old = json.load(f)
        if old.get("identity_sha256") != digest:
            raise EvalError(
                f"{out_dir!r} holds results of a different run (config, seed or checkpoints differ); resume needs "
                "the same command. Use another --out or delete the folder."
            )
        return
    manifest = {
        "format": EVAL_FORMAT_VERSION,
        "identity_sha256": digest,
        "created": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": argv if argv is not None else sys.argv,
        "git": _git_info(),
        "python": platform.python_version(),
        "machine": f"{platform.machine()} {os.cpu_count()} cpus",
        "checkpoints": {k: dataclasses.asdict(v) for k, v in prep.policies.items()},
        "missing_rows": prep.missing,
        **ident,
    }
    _write_json(man_path, manifest)
    with open(os.path.join(out_dir, "config.yaml"), "w") as f:
        yaml.safe_dump(to_dict(prep.cfg), f, sort_keys=False)


def evaluate(
    cfg: EvalConfig,
    out_dir: str,
    explicit_checkpoints: tuple[str, ...] = (),
    progress: bool = True,
    argv: list[str] | None = None,
) -> dict:
    """Run (or resume) an evaluation and write every output. Returns the summary dict.

    Units already in ``<out_dir>/units`` are skipped; each finished unit is written at once, so an interruption
    loses at most the units in flight.
    """
    prep = prepare(cfg, explicit_checkpoints)
    open_output(prep, out_dir, argv)
    units = plan_units(prep)
    unit_dir = os.path.join(out_dir, "units")
    todo = [u for u in units if not os.path.exists(os.path.join(unit_dir, u.key + ".json"))]
    done_n = len(units) - len(todo)
    for msg in list(prep.missing.values())[:1]:
        print(f"NOTE: policy rows {sorted(prep.missing)} are missing ({msg}); running the other rows.", flush=True)
    if done_n:
        print(f"resuming: {done_n}/{len(units)} units already in {unit_dir}", flush=True)
    from tqdm import tqdm

    bar = tqdm(total=len(todo) * cfg.trials_per_scene, unit="trial", disable=not progress, dynamic_ncols=True,
               desc=cfg.name, file=sys.stderr)  # fmt: skip

    def finish(res: dict) -> None:
        _write_json(os.path.join(unit_dir, res["key"] + ".json"), res)
        bar.update(len(res["trials"]))
        s = res["summary"]
        bar.set_postfix_str(f"{res['row']} s{res['scene']} {res['speed']:g}m/s SR {100 * s['success_rate']:.0f}%")

    previous_term = _sigterm_as_interrupt()
    try:
        if cfg.workers <= 1 or len(todo) <= 1:
            for u in todo:
                finish(run_unit(u))
        else:
            ctx = mp.get_context("spawn")
            pool = cf.ProcessPoolExecutor(cfg.workers, mp_context=ctx, initializer=_worker_init)
            futures = [pool.submit(run_unit, u) for u in todo]
            try:
                for fut in cf.as_completed(futures):
                    finish(fut.result())
            finally:
                # On an interrupt or a failed unit: drop queued units and stop the ones in flight (no orphans).
                _stop_pool(pool)
    except KeyboardInterrupt:
        bar.close()
        print(f"\ninterrupted: finished units are saved in {unit_dir}; re-run the same command to resume.")
        with contextlib.suppress(Exception):
            write_outputs(prep, out_dir, units)  # a partial table, marked as such in its header
        raise
    finally:
        if previous_term is not None:
            signal.signal(signal.SIGTERM, previous_term)
    bar.close()
    return write_outputs(prep, out_dir, units)


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def _sigterm_as_interrupt() -> Any:
    """Handle SIGTERM like Ctrl-C (finished units kept, workers stopped); returns the previous handler or None."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_interrupt)


def _stop_pool(pool: cf.ProcessPoolExecutor) -> None:
    """Cancel queued units and terminate the worker processes (a unit in flight is lost, finished ones are on disk)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=10)


def load_units(out_dir: str, units: list[UnitSpec]) -> list[dict]:
    """The unit records of ``units`` found on disk (in plan order)."""
    res = []
    for u in units:
        p = os.path.join(out_dir, "units", u.key + ".json")
        if os.path.exists(p):
            with open(p) as f:
                res.append(json.load(f))
    return res


def summarize(prep: Prepared, unit_results: list[dict]) -> dict:
    """Cells per (row, speed) over scenes, with per-unit summaries; plus pooled shield statistics per row."""
    cells: dict[str, dict[str, Any]] = {}
    for rname in prep.rows:
        cells[rname] = {}
        for v in prep.cfg.speeds:
            trials = [t for u in unit_results if u["row"] == rname and u["speed"] == v for t in u["trials"]]
            cells[rname][f"{v:g}"] = aggregate(trials) if trials else None
    return {
        "name": prep.cfg.name,
        "family": prep.cfg.scenes.family,
        "scenes": prep.cfg.scene_indices,
        "speeds": prep.cfg.speeds,
        "trials_per_scene": prep.cfg.trials_per_scene,
        "rows": {k: dataclasses.asdict(r) for k, r in prep.rows.items()},
        "cells": cells,
        "units": {u["key"]: u["summary"] for u in unit_results},
        "missing": prep.missing,
        "speed_flags": {f"{r}@{v:g}": m for (r, v), m in prep.speed_flags.items()},
        "notes": prep.warnings,
        "units_done": len(unit_results),
        "units_total": len(plan_units(prep)),
    }


def _pct(x: float | None) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{100 * x:.1f}"


def _num(x: float | None, fmt: str = ".2f") -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, fmt)


def _header_lines(prep: Prepared, summary: dict) -> list[str]:
    cfg = prep.cfg
    n_sc = len(cfg.scene_indices)
    lines = [
        f"{cfg.title or cfg.name}: family `{cfg.scenes.family}` scenes {cfg.scene_indices}, "
        f"{cfg.trials_per_scene} trials per scene and speed ({n_sc * cfg.trials_per_scene} per cell), seed {cfg.seed}.",
        "Observation noise and domain randomization: " + ("ON (training ranges)." if cfg.randomization else "off."),
        "SR: success rate % [95 % Wilson interval]; Vel: mean speed of successful trials [m/s].",
    ]
    if any(r.controller.startswith("oracle") for r in prep.rows.values()):
        lines.append("The oracle reads the privileged map (geodesic field and ESDF): an upper bound, not a competitor.")
    if any(r.controller == "reactive_geodesic" for r in prep.rows.values()):
        lines.append("The geodesic-guided reactive planner reads the privileged geodesic field for its goal direction.")
    if any(r.controller == "teacher" for r in prep.rows.values()):
        lines.append("Teacher rows read the privileged local ESDF map (no depth): the policy each student imitates.")
    for name, info in prep.policies.items():
        lines.append(f"Checkpoint `{name}`: {info.path} (sha256 {info.sha256[:12]}, {info.kind}).")
    if prep.missing:
        lines.append(
            "MISSING policy rows (no checkpoint): " + ", ".join(f"{k} ({v})" for k, v in prep.missing.items()) + "."
        )
    lines += [f"WARNING (marked !): {m}." for m in prep.speed_flags.values()]
    done, total = summary.get("units_done", 0), summary.get("units_total", 0)
    if done < total:
        lines.append(f"PARTIAL: {done} of {total} units finished; re-run the same command to complete the table.")
    return lines


def paper_table(prep: Prepared, summary: dict) -> str:
    """The paper-shaped Markdown table: rows = configurations, per speed SR [CI] and Vel."""
    speeds = prep.cfg.speeds
    head = "| Configuration | " + " | ".join(f"{v:g} m/s SR | {v:g} m/s Vel" for v in speeds) + " |"
    sep = "|---|" + "---:|---:|" * len(speeds)
    lines = [head, sep]
    for rname, row in prep.rows.items():
        label = row.label or rname
        cells = []
        for v in speeds:
            c = summary["cells"][rname].get(f"{v:g}")
            flag = " !" if (rname, v) in prep.speed_flags else ""
            if rname in prep.missing:
                cells += ["missing", "-"]
            elif c is None:
                cells += ["(not run)", "-"]
            else:
                cells += [f"{_pct(c['success_rate'])} [{_pct(c['sr_lo'])}, {_pct(c['sr_hi'])}]{flag}",
                          _num(c["vel"])]  # fmt: skip
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


DETAIL_COLUMNS = [
    ("n", "n", lambda c: str(c["n"])),
    ("SR %", "success_rate", lambda c: _pct(c["success_rate"])),
    ("95% CI", "ci", lambda c: f"{_pct(c['sr_lo'])}-{_pct(c['sr_hi'])}"),
    ("coll %", "collision_rate", lambda c: _pct(c["collision_rate"])),
    ("timeout %", "timeout_rate", lambda c: _pct(c["timeout_rate"])),
    ("OOB %", "oob_rate", lambda c: _pct(c["oob_rate"])),
    ("Vel", "vel", lambda c: _num(c["vel"])),
    ("clear mean", "clearance_mean", lambda c: _num(c["clearance_mean"])),
    ("clear min", "clearance_min", lambda c: _num(c["clearance_min"])),
    ("path/geo", "path_ratio", lambda c: _num(c["path_ratio"], ".3f")),
    ("shield act %", "shield_active", lambda c: _pct(c.get("shield_active"))),
    ("corr mean", "corr_mean", lambda c: _num(c.get("corr_mean"))),
    ("corr max", "corr_max", lambda c: _num(c.get("corr_max"))),
    ("relaxed %", "relaxed", lambda c: _pct(c.get("relaxed"))),
    ("QP us mean", "qp_us_mean", lambda c: _num(c.get("qp_us_mean"), ".0f")),
    ("QP us max", "qp_us_max", lambda c: _num(c.get("qp_us_max"), ".0f")),
]
"""Columns of the detailed table (header, summary key, formatter)."""


def detail_table(prep: Prepared, summary: dict) -> str:
    """Every metric per (configuration, speed) cell."""
    lines = ["| Configuration | speed | " + " | ".join(h for h, _, _ in DETAIL_COLUMNS) + " |",
             "|---|---:|" + "---:|" * len(DETAIL_COLUMNS)]  # fmt: skip
    for rname, row in prep.rows.items():
        for v in prep.cfg.speeds:
            c = summary["cells"][rname].get(f"{v:g}")
            if c is None:
                continue
            lines.append(f"| {row.label or rname} | {v:g} | " + " | ".join(f(c) for _, _, f in DETAIL_COLUMNS) + " |")
    return "\n".join(lines)


def latex_table(prep: Prepared, summary: dict) -> str:
    """The paper-shaped table as LaTeX (booktabs), SR in % and Vel in m/s per speed."""
    speeds = prep.cfg.speeds
    cols = "l " + " ".join("cc" for _ in speeds)
    out = [
        "\\begin{tabular}{" + cols + "}",
        "\\toprule",
        "\\multirow{2}{*}{\\textbf{Configuration}} & "
        + " & ".join(f"\\multicolumn{{2}}{{c}}{{\\textbf{{{v:g} m/s}}}}" for v in speeds)
        + " \\\\",
        " ".join(f"\\cmidrule{{{2 + 2 * i}-{3 + 2 * i}}}" for i in range(len(speeds))),
        " & " + " & ".join("SR$\\uparrow$ & Vel" for _ in speeds) + " \\\\ \\midrule",
    ]
    for rname, row in prep.rows.items():
        cells = []
        for v in speeds:
            c = summary["cells"][rname].get(f"{v:g}")
            if c is None:
                cells += ["--", "--"]
            else:
                cells += [_pct(c["success_rate"]), _num(c["vel"]).replace("-", "--")]
        label = (row.label or rname).replace("&", "\\&").replace("%", "\\%")
        out.append(f"{label} & " + " & ".join(cells) + " \\\\")
    out += ["\\bottomrule", "\\end{tabular}"]
    return "\n".join(out)


def csv_table(prep: Prepared, summary: dict) -> str:
    """One CSV line per (configuration, speed) cell with every metric."""
    keys = ["n", "successes", "success_rate", "sr_lo", "sr_hi", "collision_rate", "timeout_rate", "oob_rate", "vel",
            "clearance_mean", "clearance_min", "path_ratio", "shield_active", "corr_mean", "corr_max", "relaxed",
            "qp_us_mean", "qp_us_max", "shield_us_mean"]  # fmt: skip
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["configuration", "label", "speed", *keys])
    for rname, row in prep.rows.items():
        for v in prep.cfg.speeds:
            c = summary["cells"][rname].get(f"{v:g}")
            if c is None:
                continue
            w.writerow([rname, row.label, v, *[c.get(k, "") for k in keys]])
    return buf.getvalue()


def write_outputs(prep: Prepared, out_dir: str, units: list[UnitSpec]) -> dict:
    """Tables (md, csv, tex), trials.json, summary.json and figures from the unit files on disk."""
    results = load_units(out_dir, units)
    summary = summarize(prep, results)
    header = _header_lines(prep, summary)
    md = "\n".join(
        [f"# {prep.cfg.title or prep.cfg.name}", "", *[f"{h}  " for h in header], "", paper_table(prep, summary), "",
         "## All metrics", "", detail_table(prep, summary), ""]
    )  # fmt: skip
    with open(os.path.join(out_dir, "table.md"), "w") as f:
        f.write(md)
    with open(os.path.join(out_dir, "table.csv"), "w") as f:
        f.write(csv_table(prep, summary))
    with open(os.path.join(out_dir, "table.tex"), "w") as f:
        f.write(latex_table(prep, summary) + "\n")
    trials = [{k: v for k, v in t.items() if k != "traj"} for u in results for t in u["trials"]]
    _write_json(os.path.join(out_dir, "trials.json"), trials)
    _write_json(os.path.join(out_dir, "summary.json"), summary)
    summary["markdown"] = md
    summary["paper_table"] = paper_table(prep, summary)
    summary["header"] = header
    if prep.cfg.plots and results:
        from shield_nav import plots

        try:
            plots.write_figures(prep, summary, results, os.path.join(out_dir, "figures"))
        except Exception as err:  # a figure must never cost the tables
            print(f"WARNING: figures failed: {type(err).__name__}: {err}", flush=True)
    return summary


def config_from_args(args: Any) -> tuple[EvalConfig, tuple[str, ...]]:
    """EvalConfig from eval.py's parsed arguments: the YAML, then ``--set``, then the dedicated flags.

    Returns the config and the checkpoint names given explicitly (whose absence is always an error).
    """
    over: list[str] = list(args.set)
    cfg = load_eval_config(args.config, over)
    explicit = []
    for item in args.checkpoint:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise EvalError(f"--checkpoint {item!r}: expected NAME=PATH")
        cfg.checkpoints[name] = path
        explicit.append(name)
        known = {**BUILTIN_ROWS, **cfg.rows}
        if not any(r.policy == name for r in known.values()):
            # A new policy name: evaluate it as its own row (policy alone, no shield).
            cfg.rows[name] = RowConfig(name, "policy", name)
            cfg.configurations.append(name)
        elif not any(known[c].policy == name for c in cfg.configurations if c in known):
            cfg.configurations += [c for c, r in BUILTIN_ROWS.items() if r.policy == name and c not in cfg.rows]
    if args.speeds:
        try:
            cfg.speeds = [float(v) for v in args.speeds.split(",") if v.strip()]
        except ValueError:
            raise EvalError(f"--speeds {args.speeds!r}: expected numbers like 3,5,7,9") from None
    if args.trials is not None:
        cfg.trials_per_scene = args.trials
    if args.scenes:
        cfg.scenes = parse_scenes(args.scenes)
    if getattr(args, "configurations", None):
        cfg.configurations = [c.strip() for c in args.configurations.split(",") if c.strip()]
    if args.workers is not None:
        cfg.workers = args.workers
    if args.seed is not None:
        cfg.seed = args.seed
    try:
        cfg = load_config(EvalConfig, base=cfg)  # re-validate after the flags
    except ConfigError as err:
        raise EvalError(str(err)) from None
    return cfg, tuple(explicit)


# ============================================================================================ videos
def record_videos(prep: Prepared, out_dir: str, fps: int = 25, size: tuple[int, int] = (360, 640)) -> list[str]:
    """Re-fly trial 0 of the first scene at the top speed for every row and record it (issue #8, "watching a flight").

    A chase view from MuJoCo's offscreen renderer (``MUJOCO_GL=egl`` on a machine without a display) with the
    sensor depth image inset, the speed and the shield's activity written on each frame, saved as MP4 (imageio +
    imageio-ffmpeg) or, without them, as an animated GIF. If MuJoCo cannot render here, the fallback is an animated
    top-down plot of the same trial over the ESDF; the message says which one was written. The re-flown trial is
    the one in the tables (same seed, same pinned start and goal; the flight is deterministic).
    """
    from envs.navigation import NavigationEnv
    from shield_nav import plots

    cfg = prep.cfg
    os.makedirs(os.path.join(out_dir, "videos"), exist_ok=True)
    paths = []
    speed, idx = max(cfg.speeds), cfg.scene_indices[0]
    every = max(1, round(1.0 / (fps * 0.01)))  # control steps per frame (100 Hz control)
    for spec in plan_units(prep):
        if spec.index != idx or spec.speed != speed:
            continue
        env = NavigationEnv(config=nav_config(cfg, spec.family, idx, speed, 1, spec.policy_env))
        need = env.cfg.vehicle.airframe.collision_radius + 0.4
        trial = sample_trial(env.scenes[0], env.field_stack, 0,
                             trial_seed(cfg.seed, spec.family, idx, speed, 0), need)  # fmt: skip
        trial["trial"] = 0
        base = os.path.join(out_dir, "videos", f"{spec.key}__trial0")
        try:
            rec = plots.ChaseRecorder(env, size)
        except Exception as err:  # no OpenGL here: say so and fall back to the top-down animation
            print(f"NOTE: MuJoCo offscreen rendering is unavailable ({type(err).__name__}: {err}); "
                  "writing an animated top-down plot instead.", flush=True)  # fmt: skip
            rec = None
        frames: list[np.ndarray] = []

        def on_step(env: Any, t: int, active: np.ndarray, rec: Any = rec, frames: list = frames) -> None:
            if rec is not None and t % every == 0:
                frames.append(rec.frame(env, t, bool(active[0])))

        (record,) = _run_batch(spec, cfg, [trial], env, on_step)
        if rec is not None:
            paths.append(plots.write_video(frames, base, fps))
        else:
            from envs.fields import build_fields

            fields = build_fields(env.scenes[0], resolution=env.cfg.scenes.field_resolution,
                                  vehicle_radius=env.cfg.vehicle.airframe.collision_radius)  # fmt: skip
            paths.append(plots.animate_topdown(env.scenes[0], fields, record, base + ".gif"))
        print(f"video: {paths[-1]} ({spec.row_name}, outcome {record['outcome']})", flush=True)
    return paths
