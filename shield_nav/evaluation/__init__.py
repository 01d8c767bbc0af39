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

Modules: :mod:`~shield_nav.evaluation.config` (the schema, the row registry ``configs/eval/rows.yaml``, the CLI
flags), :mod:`~shield_nav.evaluation.policies` (ONNX / TorchScript actors, privileged teachers),
:mod:`~shield_nav.evaluation.metrics` (per-trial metrics, aggregation, Wilson intervals),
:mod:`~shield_nav.evaluation.rollout` (pinned trials, one unit's flights), :mod:`~shield_nav.evaluation.run`
(prepare, workers, resume, outputs), :mod:`~shield_nav.evaluation.report` (tables),
:mod:`~shield_nav.evaluation.plots` (figures), :mod:`~shield_nav.evaluation.video`,
:mod:`~shield_nav.evaluation.paper` (the paper's Tables I and II as numbers) and
:mod:`~shield_nav.evaluation.figure` (our rows beside the paper's, ``python -m shield_nav.evaluation.figure``).
Everything public of the harness is re-exported here; ``paper`` and ``figure`` are imported from their modules.
"""

from envs.config import ConfigError
from shield_nav.evaluation.config import (
    BUILTIN_CHECKPOINTS,
    BUILTIN_ROWS,
    EVAL_FORMAT_VERSION,
    POLICY_CONTROLLERS,
    ROWS_FILE,
    Z95,
    EvalConfig,
    EvalError,
    RowConfig,
    SceneSelection,
    config_from_args,
    load_eval_config,
    load_registry,
    parse_scenes,
    resolve_rows,
    row_escape_config,
)
from shield_nav.evaluation.metrics import (
    aggregate,
    trajectory_metrics,
    wilson_interval,
)
from shield_nav.evaluation.policies import (
    POLICY_ENV_SECTIONS,
    LoadedPolicy,
    LoadedTeacher,
    PolicyInfo,
    _env_from_config,
    _speeds_from_config,
    check_layout,
    load_policy,
    load_teacher,
)
from shield_nav.evaluation.report import (
    DETAIL_COLUMNS,
    csv_table,
    detail_table,
    latex_table,
    paper_table,
)
from shield_nav.evaluation.rollout import (
    Prepared,
    UnitSpec,
    flown_scene,
    nav_config,
    run_unit,
    sample_trial,
    scene_seed,
    trial_seed,
    unit_key,
)
from shield_nav.evaluation.run import (
    evaluate,
    load_units,
    open_output,
    plan_units,
    prepare,
    summarize,
    write_outputs,
)
from shield_nav.evaluation.video import (
    record_videos,
)

__all__ = [
    "BUILTIN_CHECKPOINTS",
    "BUILTIN_ROWS",
    "ConfigError",
    "DETAIL_COLUMNS",
    "EVAL_FORMAT_VERSION",
    "EvalConfig",
    "EvalError",
    "LoadedPolicy",
    "LoadedTeacher",
    "POLICY_CONTROLLERS",
    "POLICY_ENV_SECTIONS",
    "PolicyInfo",
    "Prepared",
    "ROWS_FILE",
    "RowConfig",
    "SceneSelection",
    "UnitSpec",
    "Z95",
    "_env_from_config",
    "_speeds_from_config",
    "aggregate",
    "check_layout",
    "config_from_args",
    "csv_table",
    "detail_table",
    "evaluate",
    "flown_scene",
    "latex_table",
    "load_eval_config",
    "load_policy",
    "load_registry",
    "load_teacher",
    "load_units",
    "nav_config",
    "open_output",
    "paper_table",
    "parse_scenes",
    "plan_units",
    "prepare",
    "record_videos",
    "resolve_rows",
    "row_escape_config",
    "run_unit",
    "sample_trial",
    "scene_seed",
    "summarize",
    "trajectory_metrics",
    "trial_seed",
    "unit_key",
    "wilson_interval",
    "write_outputs",
]
