"""Evaluation configs: rows, the row registry (configs/eval/rows.yaml), scene selection, the CLI flags."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from typing import Any, ClassVar

import yaml

from envs.config import ConfigError, load_config, require
from envs.scenes import FAMILIES
from shield_nav.algorithms.baselines import BaselineConfig, make_baseline
from shield_nav.safety.escape import EscapeConfig
from shield_nav.safety.shield import ShieldConfig

EVAL_FORMAT_VERSION = 1
"""Version of the unit/manifest JSON layout; bump when it changes."""
Z95 = 1.959963984540054
"""Standard normal quantile for a two-sided 95 % interval."""


class EvalError(RuntimeError):
    """Bad evaluation input (checkpoint, configuration name, scenes, output folder); raised before long work."""


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
    ``reactive_map`` (aligned with a plan over the map of what its own camera has shown; depth only), ``goal``,
    ``expert`` (the planning expert; privileged), ``expert_cammap`` (the expert routed by its own camera's map; its
    local geometry privileged)."""
    policy: str = ""
    """Checkpoint name (a key of ``checkpoints``) for ``controller: policy`` or ``teacher``."""
    shield: bool = False
    """Filter the commands through the HOCBF shield."""
    shield_overrides: dict[str, Any] = field(default_factory=dict)
    """This row's shield settings over the run's ``shield`` section (keys of ``ShieldConfig``), e.g. the paper's
    formulation beside the default shield in one table (``full_paper_shield`` in configs/eval/rows.yaml)."""
    escape: bool = False
    """Put the stall escape (:mod:`shield_nav.safety.escape`, the run's ``escape`` section) between the goal and the
    policy; ``controller: policy`` only."""
    escape_overrides: dict[str, Any] = field(default_factory=dict)
    """This row's stall-escape settings over the run's ``escape`` section (keys of ``EscapeConfig``), e.g. the
    handover of the ``full`` row beside ``full_escape``'s sideways form in one table; needs ``escape: true``."""


def _overridden(base: Any, overrides: dict[str, Any], key: str) -> Any:
    """``base`` (a config dataclass with ``validate(prefix)``) with ``overrides`` applied and checked.

    Errors name ``key`` (``rows.<name>.<field>``) and the unknown key or the bad value.
    """
    known = {f.name for f in dataclasses.fields(base)}
    bad = sorted(set(overrides) - known)
    if bad:
        raise EvalError(f"{key}: unknown key(s) {bad}; known: {sorted(known)}")
    out = dataclasses.replace(base, **overrides)
    try:
        out.validate(f"{key}.")
    except ConfigError as err:
        raise EvalError(str(err)) from None
    return out


def row_shield_config(base: ShieldConfig, row: RowConfig, name: str = "") -> ShieldConfig:
    """``base`` with ``row.shield_overrides`` applied and checked; an unknown key or bad value names the row."""
    return _overridden(base, row.shield_overrides, f"rows.{name}.shield_overrides")


def row_escape_config(base: EscapeConfig, row: RowConfig, name: str = "") -> EscapeConfig:
    """``base`` with ``row.escape_overrides`` applied and checked; an unknown key or bad value names the row."""
    return _overridden(base, row.escape_overrides, f"rows.{name}.escape_overrides")


POLICY_CONTROLLERS = ("policy", "teacher")
"""Row controllers that run a checkpoint named by ``RowConfig.policy``."""
NETWORKS = ("export", "fixed_order")
"""Values of :attr:`EvalConfig.network`."""

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
"""The repository root (the package is installed editable from it)."""
ROWS_FILE = os.path.join(REPO_ROOT, "configs", "eval", "rows.yaml")
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
    seed: int | None = None
    """Scene generator seed (None: the family's own, which for ``ablation`` and ``benchmark`` are the held-out
    test scenes). A validation config names its own here; ``--scenes`` and ``env_overrides`` leave it in place."""


@dataclass
class EvalConfig:
    """An evaluation run. Loaded from ``configs/eval/*.yaml``; the CLI flags override single fields."""

    PRE_FIELD_VALUES: ClassVar[dict[str, Any]] = {"network": "export"}
    """Output folders and pipeline selections written before ``network`` existed flew the exported network."""

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
    network: str = "fixed_order"
    """How a policy's network is run. ``fixed_order`` (the default since 2026-12-02): the policy's weights (read from a
    packaged folder's ``model.pt`` or a run's checkpoint without TorchScript, else from the TorchScript export
    ``policy.pt``) run by :mod:`shield_nav.evaluation.fixed_order` in one fixed order of float64 operations;
    ``eval.py`` then also pins OpenBLAS's and numpy's kernels
    (:func:`shield_nav.provenance.pinned_arithmetic_environment`), so its flights do not depend on the x86-64
    processor (docs/evaluation.md, "A flight that does not depend on the processor"). An evaluation called in a
    process that is not pinned (a training pipeline's selection, :func:`~shield_nav.evaluation.evaluate` from your
    own code) runs the same network with the kernels that process has; its manifest records them. ``export``: the
    exported file found (``policy.onnx`` through onnxruntime, else TorchScript ``policy.pt``) with the processor's
    fastest kernels (the network about 4 x cheaper per env and step), whose sums differ in the last bits from one
    processor kind to another."""
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
    escape: EscapeConfig = field(default_factory=EscapeConfig)
    """Stall escape of rows with ``escape: true`` (:mod:`shield_nav.safety.escape`)."""
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
        require(self.network in NETWORKS, f"{prefix}network", f"{self.network!r}; known: {list(NETWORKS)}")
        require(self.missing_checkpoints in ("error", "skip"), f"{prefix}missing_checkpoints",
                "must be 'error' or 'skip'")  # fmt: skip
        require(len(self.configurations) >= 1, f"{prefix}configurations", "need at least one configuration")
        for o in self.env_overrides:
            require("=" in o, f"{prefix}env_overrides", f"{o!r} is not of the form a.b=value")
            key, _, value = o.partition("=")
            if self.scenes.seed is not None and key.strip() == "scenes.seed":
                require(yaml.safe_load(value) == self.scenes.seed, f"{prefix}env_overrides", f"{o!r} contradicts "
                        f"scenes.seed ({self.scenes.seed}); set the scene seed in one place")  # fmt: skip

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
            hint = ""
            if name in cfg.rows and name in BUILTIN_ROWS:  # e.g. --set rows.full.shield_overrides.r_safe=0.5
                hint = (f"; rows.{name} in the config replaces the registry's row {name!r} whole (configs/eval/"
                        f"rows.yaml), so restate its keys, or define a row of another name")  # fmt: skip
            raise EvalError(
                f"configuration {name!r} is a {row.controller} row but names no checkpoint ('policy:'){hint}"
            )
        if row.controller not in POLICY_CONTROLLERS:
            make_baseline(row.controller, cfg.baselines)  # raises on an unknown controller name
        if row.shield_overrides and not row.shield:
            raise EvalError(f"configuration {name!r} has shield_overrides but no shield ('shield: true')")
        if row.escape and row.controller != "policy":
            raise EvalError(f"configuration {name!r} has escape: true but controller {row.controller!r}; the stall "
                            f"escape steers a depth policy's goal input ('controller: policy')")  # fmt: skip
        if row.escape_overrides and not row.escape:
            raise EvalError(f"configuration {name!r} has escape_overrides but no stall escape ('escape: true')")
        row_shield_config(cfg.shield, row, name)  # raises on a bad key or value
        escape = row_escape_config(cfg.escape, row, name)  # raises on a bad key or value
        if row.escape and escape.plan_delay_steps:
            raise EvalError(
                f"configuration {name!r}: escape.plan_delay_steps must be 0, the stall escape plans inline; a "
                "handover planner's delay is baselines.reactive.camera_map.plan_delay_steps"
            )
        out[name] = row
    return out


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
        cfg.scenes = dataclasses.replace(parse_scenes(args.scenes), seed=cfg.scenes.seed)
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
