"""Policies the harness flies: exported depth actors (ONNX, TorchScript) and privileged teachers."""

from __future__ import annotations

import glob
import hashlib
import json
import os
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml

from envs.config import stored_config, to_dict
from shield_nav.evaluation.config import EvalError


@dataclass
class PolicyInfo:
    """What the harness knows about an exported policy."""

    name: str
    """Checkpoint name."""
    path: str
    """The file that runs (``.onnx``, TorchScript ``.pt``, or with ``fixed_order`` a training checkpoint ``.pt``)."""
    kind: str
    """``onnx``, ``torchscript`` or ``fixed_order`` (the weights of the TorchScript file, or of a training checkpoint,
    run by :mod:`shield_nav.evaluation.fixed_order`)."""
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
    """The ``action``, ``camera``, ``vehicle`` and ``scene_memory`` sections of the training env config (evaluation
    flies the policy with these, so its actions and inputs mean what they meant in training), if found."""
    state_groups: tuple[str, ...] = ("state",)
    """The env's 1-D observation groups whose concatenation is the policy's state input, in order (from the
    training config's actor or student set; ``("state",)`` when none is found)."""


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

    def state_of(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The policy's state input (N, S) from an env observation: its :attr:`PolicyInfo.state_groups` in order."""
        missing = [g for g in self.info.state_groups if g not in obs]
        if missing:
            raise EvalError(f"checkpoint {self.info.name!r} reads observation groups {missing} the env does not "
                            f"give (it has {sorted(obs)}); enable them in its env config")  # fmt: skip
        if len(self.info.state_groups) == 1:
            return obs[self.info.state_groups[0]]
        return np.concatenate([obs[g] for g in self.info.state_groups], axis=-1)

    def step(self, state: np.ndarray, depth: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One deterministic policy step for a batch (see the class docstring)."""
        if self.info.kind == "fixed_order":  # float64 inside; the state and image arrive as the env gives them
            return self._runner.act(np.asarray(state, dtype=np.float32), np.asarray(depth, dtype=np.float32), h)
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

    def num_hypotheses(self) -> int:
        """``K``, the candidate actions the actor scores (1 for a single-head actor, and for an ONNX export)."""
        if self.info.kind == "onnx":
            return 1
        if self.info.kind == "fixed_order":
            return int(self._runner.num_hypotheses)
        select = dict(self._runner.mlp.named_children()).get("1")  # HypothesisSelect after the MLP core, if any
        return int(select.num_hypotheses) if select is not None and hasattr(select, "num_hypotheses") else 1

    def step_hypotheses(
        self, state: np.ndarray, depth: np.ndarray, h: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One step that also returns the actor's other candidates: ``(chosen (N, A), others (N, K - 1, A), h)``.

        ``chosen`` is :meth:`step`'s action (the best-scored candidate); ``others`` are the remaining candidates in
        descending score order. TorchScript exports of multi-hypothesis actors only (an ONNX export holds the
        selection inside its graph).
        """
        k = self.num_hypotheses()
        if k < 2:
            why = "an ONNX export gives only its chosen action" if self.info.kind == "onnx" else "it has one head"
            raise EvalError(f"checkpoint {self.info.name!r} ({self.info.path}): the shield's 'hypotheses' option "
                            f"needs a multi-hypothesis actor's TorchScript export (policy.pt); {why}")  # fmt: skip
        if self.info.kind == "fixed_order":
            head, h_out = self._runner.forward(np.asarray(state, dtype=np.float32),
                                               np.asarray(depth, dtype=np.float32), h)  # fmt: skip
            ranked = _by_score(*self._runner.candidates(head))
            return ranked[:, 0], ranked[:, 1:], h_out
        import torch

        m = self._runner
        with torch.no_grad():
            obs = torch.from_numpy(np.ascontiguousarray(state, dtype=np.float32))
            img = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))
            _, h_out = m(obs, img, torch.from_numpy(np.ascontiguousarray(h, dtype=np.float32)))
            # One step of a GRU: its output is the last layer's new hidden state, which feeds the MLP head.
            raw = getattr(m.mlp, "0")(h_out[-1])
        a = (raw.shape[-1] - k) // k
        cands = m.deterministic_output(raw[:, : k * a].reshape(-1, k, a)).numpy().astype(np.float64)
        ranked = _by_score(cands, raw[:, k * a :].numpy())
        return ranked[:, 0], ranked[:, 1:], h_out.numpy().astype(np.float32)


def _by_score(cands: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Candidates (N, K, A) in descending score order (N, K); ties keep the first, as ``HypothesisSelect``."""
    order = np.argsort(-scores, axis=1, kind="stable")
    return np.take_along_axis(cands, order[:, :, None], axis=1)


def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


POLICY_FILES = ("policy.onnx", "exported/policy.onnx", "policy.pt", "exported/policy.pt")
"""Where an exported actor is looked for inside a checkpoint folder, in this order."""


def _find_policy_file(path: str, name: str) -> str:
    if not os.path.exists(path):
        raise EvalError(f"checkpoint {name!r}: {path!r} does not exist")
    if os.path.isfile(path):
        return path
    for rel in POLICY_FILES:
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


POLICY_ENV_SECTIONS = ("action", "camera", "vehicle", "scene_memory")
"""Env config sections taken from a policy's training config when it is evaluated (and of ``episode`` only
``clock_input``: the evaluation's own episode settings, its time limit among them, stay)."""


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
    episode = env.get("episode")
    if isinstance(episode, dict) and episode.get("clock_input"):
        out["episode"] = {"clock_input": True}
    return out or None


def _state_groups_from_config(path: str | None) -> tuple[str, ...]:
    """The 1-D groups of the actor's (PPO) or student's (distillation) observation set, ``depth`` left out."""
    data = _read_policy_config(path, "its observation groups") if path is not None else None
    runner = data.get("runner") if isinstance(data, dict) else None
    groups = runner.get("obs_groups") if isinstance(runner, dict) else None
    if isinstance(groups, dict):
        key = "student" if runner.get("class_name") == "DistillationRunner" else "actor"
        names = groups.get(key)
        if isinstance(names, list) and names:
            return tuple(str(g) for g in names if g != "depth")
    return ("state",)


def _dim(value: Any, what: str, path: str) -> int:
    if not isinstance(value, int):
        raise EvalError(f"policy {path!r}: {what} has no fixed size ({value!r}); cannot check the layout")
    return value


EXPORT_SOURCE_FILE = "source.json"
"""Written by training beside its exports (``exported/source.json``): the checkpoint they were made from."""


def _fixed_order_file(file: str, name: str) -> str:
    """The file whose weights ``network: fixed_order`` reads, preferring one that needs no TorchScript.

    ``file`` itself if it is a ``.pt``; else, beside the ONNX file, the packaged training checkpoint ``model.pt``
    (``checkpoints/<name>/``), then the run's checkpoint that ``exported/source.json`` names when it is there with
    the recorded sha256 (a run's ``exported/``), both rebuilt by :func:`load_policy` without TorchScript (the same
    weights, so the same bits, as the TorchScript export); else the TorchScript export ``policy.pt`` (beside the
    ONNX file, or in an ``exported/`` folder beside it); else the checkpoint ``source.json`` names, which must then
    exist and match.
    """
    if file.endswith(".pt"):
        return file
    d = os.path.dirname(os.path.abspath(file))
    sources = [s for s in (os.path.join(d, EXPORT_SOURCE_FILE), os.path.join(d, "exported", EXPORT_SOURCE_FILE))
               if os.path.isfile(s)]  # fmt: skip
    if os.path.isfile(os.path.join(d, "model.pt")):
        return os.path.join(d, "model.pt")
    for src in sources:
        ckpt = _export_source_checkpoint(src, name, strict=False)
        if ckpt is not None:
            return ckpt
    for cand in (os.path.join(d, "policy.pt"), os.path.join(d, "exported", "policy.pt")):
        if os.path.isfile(cand):
            return cand
    if sources:
        return _export_source_checkpoint(sources[0], name)  # type: ignore[return-value]  # raises, naming why
    raise EvalError(f"checkpoint {name!r}: network 'fixed_order' reads the TorchScript export policy.pt (or a "
                    f"packaged model.pt, or the run checkpoint an exported/{EXPORT_SOURCE_FILE} names), and there is "
                    f"none beside {file!r}; point --checkpoint at a policy.pt or a training checkpoint model_<it>.pt, "
                    "or fly the ONNX file with --set network=export")  # fmt: skip


def _export_source_checkpoint(src: str, name: str, strict: bool = True) -> str | None:
    """The run's checkpoint that ``src`` (``<run>/exported/source.json``) names, checked against its sha256.

    With ``strict`` a missing or changed checkpoint is an :class:`EvalError`; without, None.
    """
    with open(src) as f:
        rec = json.load(f)
    ckpt = os.path.join(os.path.dirname(os.path.dirname(src)), str(rec.get("checkpoint", "")))
    if not os.path.isfile(ckpt):
        if not strict:
            return None
        raise EvalError(f"checkpoint {name!r}: {src} says the export was made from {rec.get('checkpoint')!r}, and "
                        f"{ckpt!r} does not exist; point --checkpoint at a policy.pt or a model_<it>.pt")  # fmt: skip
    if _sha256(ckpt) != rec.get("sha256"):
        if not strict:
            return None
        raise EvalError(f"checkpoint {name!r}: {ckpt!r} is not the checkpoint the export was made from (sha256 "
                        f"differs from {src}); point --checkpoint at the checkpoint to fly")  # fmt: skip
    return ckpt


def load_policy(path: str | os.PathLike, name: str = "policy", network: str = "export") -> LoadedPolicy:
    """Load an exported actor (ONNX through onnxruntime, or TorchScript ``policy.pt``) and read its layout.

    ``path`` is a file or a folder holding ``policy.onnx`` / ``exported/policy.onnx`` / ``policy.pt``. The ONNX
    graph's inputs are told apart by rank (state (B, S), depth (B, C, H, W), hidden (L, B, Hd)) and its outputs
    by rank (actions (B, A), hidden), so the names are read from the model rather than assumed. With ``network``
    ``fixed_order`` the TorchScript export's weights are run by :class:`~shield_nav.evaluation.fixed_order.
    FixedOrderActor` instead (the ``policy.pt`` beside an ONNX file); ``path`` may then also be a training checkpoint
    ``model*.pt``, whose actor is rebuilt from its stored config without TorchScript (the same weights, so the same
    bits as its export).

    Raises:
        EvalError: missing file, a training checkpoint instead of an export, an unreadable model, or a network the
            fixed-order runtime does not run.
    """
    file = _find_policy_file(os.fspath(path), name)
    if network == "fixed_order":
        file = _fixed_order_file(file, name)
    elif network != "export":
        raise EvalError(f"network: {network!r}; known: 'export', 'fixed_order'")
    cfg_path = _find_train_config(file)
    speeds = _speeds_from_config(cfg_path)
    train_env = _env_from_config(cfg_path)
    groups = _state_groups_from_config(cfg_path)
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
                          cfg_path, speeds, train_env, groups)  # fmt: skip
        return LoadedPolicy(info, sess, names)
    if network == "fixed_order" and _is_training_checkpoint(file):
        mod = _checkpoint_export(file, name)
    else:
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
    kind, runner = "torchscript", mod
    if network == "fixed_order":
        from shield_nav.evaluation.fixed_order import FixedOrderActor

        try:
            kind, runner = "fixed_order", FixedOrderActor(mod, file)
        except ValueError as err:
            raise EvalError(f"checkpoint {name!r}: {err}") from None
    info = PolicyInfo(name, file, kind, _sha256(file), obs_dim, depth_shape, num_layers, hidden,  # type: ignore[arg-type]
                      cfg_path, speeds, train_env, groups)  # fmt: skip
    return LoadedPolicy(info, runner)


def _checkpoint_export(file: str, name: str) -> Any:
    """The eager :class:`~shield_nav.policies.export.ExportedDepthGRU` of a training checkpoint's actor or student.

    Rebuilt from the config stored in the checkpoint: the same weights as its TorchScript export, read without
    TorchScript.
    """
    from shield_nav.policies.export import ExportedDepthGRU
    from shield_nav.training.actor import actor_from_checkpoint

    try:
        model, _, _ = actor_from_checkpoint(file)
    except Exception as err:  # re-raised with the file and the cause: a bad checkpoint stops the run here
        raise EvalError(f"checkpoint {name!r}: {file!r} did not rebuild as a depth actor: "
                        f"{type(err).__name__}: {err}") from None  # fmt: skip
    if model is None:
        raise EvalError(f"checkpoint {name!r}: {file!r} is a privileged teacher's checkpoint (its actor reads the "
                        "map, not the depth image); it has no depth actor to fly")  # fmt: skip
    return ExportedDepthGRU(model)


def _has_torchscript_code(names: list[str]) -> bool:
    """Whether a torch zip archive's member ``names`` are a TorchScript export's (compiled code and constants)."""
    return any(n.endswith("/constants.pkl") or n.endswith("/code/__torch__.py") for n in names)


def _is_training_checkpoint(file: str) -> bool:
    """Whether ``file`` is a ``torch.save`` archive (a training checkpoint) rather than a TorchScript export."""
    import zipfile

    if not file.endswith(".pt") or not zipfile.is_zipfile(file):
        return False
    try:
        with zipfile.ZipFile(file) as z:
            names = z.namelist()
    except (zipfile.BadZipFile, OSError, EOFError):
        return False
    return not _has_torchscript_code(names) and any(n.endswith("/data.pkl") for n in names)


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
        if _has_torchscript_code(z.namelist()):
            return f"checkpoint {name!r}: {file!r} is a TorchScript archive that failed to load: {err}"
    return (f"checkpoint {name!r}: {file!r} is not a TorchScript export ({type(err).__name__}); a training "
            "checkpoint (model_<it>.pt) runs only with network 'fixed_order' (the default); with network 'export' "
            "use the exported policy.onnx or policy.pt")  # fmt: skip


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

    from shield_nav.training import TrainConfig, load_train_config, read_checkpoint_infos, rsl_rl_train_cfg

    path = os.fspath(path)
    file = os.path.join(path, "model.pt") if os.path.isdir(path) else path
    if not os.path.isfile(file):
        raise EvalError(f"checkpoint {name!r}: no teacher checkpoint at {file!r} (model.pt of a teacher_* run)")
    try:
        ckpt = torch.load(file, map_location="cpu", weights_only=False)
        tcfg = load_train_config(overrides=stored_config(TrainConfig, read_checkpoint_infos(file)["config"]))
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
