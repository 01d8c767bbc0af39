"""Units: pinned trials, the env of a unit, and flying a batch of trials (controllers, shield, metrics)."""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml

from envs.config import ConfigError, load_config
from envs.navigation.config import NavConfig
from envs.scenes import FAMILIES, make_scene
from shield_nav.algorithms.baselines import Controller, make_baseline
from shield_nav.evaluation.config import (
    EVAL_FORMAT_VERSION,
    EvalConfig,
    EvalError,
    RowConfig,
    row_escape_config,
    row_shield_config,
)
from shield_nav.evaluation.metrics import aggregate, max_turns, trajectory_metrics
from shield_nav.evaluation.policies import LoadedPolicy, LoadedTeacher, PolicyInfo, load_policy, load_teacher
from shield_nav.safety.escape import StallEscape
from shield_nav.safety.shield import STATUS_FALLBACK, STATUS_RELAXED, HOCBFShield


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
    if cfg.scenes.seed is not None:
        forced["scenes.seed"] = cfg.scenes.seed
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
    """The scene a unit of ``cfg`` flies: ``family``/``index`` with the eval's scene seed, if any.

    That seed is ``scenes.seed`` of the eval config or, equally, ``scenes.seed`` in its ``env_overrides``. Trial
    sampling, figures, videos and the collision analysis use it, so they show the scene that was flown, not the
    family's default.
    """
    return make_scene(family, index, scene_seed(cfg))


def scene_seed(cfg: EvalConfig) -> int | None:
    """The scene generator seed ``cfg``'s units fly (None: the family's own)."""
    return nav_config(cfg, cfg.scenes.family, cfg.scene_indices[0], cfg.speeds[0], 1).scenes.seed


_POLICY_CACHE: dict[tuple[str, str], LoadedPolicy] = {}


def _policy(path: str, network: str = "export") -> LoadedPolicy:
    if (path, network) not in _POLICY_CACHE:
        _POLICY_CACHE[(path, network)] = load_policy(path, network=network)
    return _POLICY_CACHE[(path, network)]


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
        policy = _policy(spec.policy_path, cfg.network)  # type: ignore[arg-type]
        h = policy.initial_state(n)
    elif row.controller == "teacher":
        teacher = _teacher(spec.policy_path)  # type: ignore[arg-type]
    else:
        ctrl = make_baseline(row.controller, cfg.baselines)
        ctrl.reset(env)
    shield = HOCBFShield(row_shield_config(cfg.shield, row, spec.row_name), env.cfg.camera) if row.shield else None
    escape = (
        StallEscape(row_escape_config(cfg.escape, row, spec.row_name), n, env.cfg.vehicle.command_dt, env.cfg.camera)
        if row.escape
        else None
    )
    handover = None  # escape.kind 'handover': a stalled flight is flown by escape.handover_planner from then on
    if escape is not None and escape.cfg.kind == "handover":
        handover = make_baseline(escape.cfg.handover_planner, cfg.baselines)
        handover.reset(env)
    volume = (np.asarray(env.scenes[0].bounds_lo[:2]), np.asarray(env.scenes[0].bounds_hi[:2]))  # one scene per unit
    pick_hypotheses = shield is not None and policy is not None and shield.cfg.hypotheses != "top"
    ids = np.zeros(n, dtype=np.int64)
    pos0 = env.local_pos.copy()
    phi_start = env.field_stack.geodesic(ids, pos0)
    track_pos = [pos0]
    track_heading = [env.headings]
    track_speed: list[np.ndarray] = []
    track_esdf = [env.field_stack.esdf(ids, pos0)]
    track_active: list[np.ndarray] = []
    end_step = np.full(n, -1)
    outcome = [""] * n
    sh = {"steps": np.zeros(n, int), "active_steps": np.zeros(n, int), "corr_sum": np.zeros(n),
          "corr_max": np.zeros(n), "relaxed_steps": np.zeros(n, int), "solve_us_sum": np.zeros(n),
          "solve_us_max": np.zeros(n), "total_us_sum": np.zeros(n), "switched_steps": np.zeros(n, int)}  # fmt: skip
    t = 0
    zeros = np.zeros((n, 4))
    if on_step is not None:
        on_step(env, 0, np.zeros(n, dtype=bool))
    while (end_step < 0).any():
        live = end_step < 0
        alt_act = alt_cmd = None
        if escape is not None:  # the policy reads the escape's goal input while a flight escapes
            state = escape.apply(obs["state"], env.local_pos, env.goal_buf, env.sensor_depth_buf, t, live, volume,
                                 env.vehicles.R_wb, float(env.scenes[0].bounds_lo[2]))  # fmt: skip
            obs = {**obs, "state": state}
        if policy is not None or teacher is not None:
            if policy is not None and pick_hypotheses:
                act, alt_act, h = policy.step_hypotheses(policy.state_of(obs), obs["depth"], h)
                alt_cmd = np.stack([env.action_to_command(np.clip(alt_act[:, j], -1.0, 1.0))
                                    for j in range(alt_act.shape[1])], axis=1)  # fmt: skip
            elif policy is not None:
                act, h = policy.step(policy.state_of(obs), obs["depth"], h)
            else:
                act = teacher.step(priv["teacher"])  # type: ignore[union-attr]
            cmd = env.action_to_command(np.clip(act, -1.0, 1.0)) if shield is not None or handover else None
        else:
            act, cmd = zeros, ctrl.commands(env)  # type: ignore[union-attr]
        if handover is not None:  # called every step: the planner maps every flight's images from the start
            handed = escape.guided & live  # type: ignore[union-attr]
            planned = handover.commands(env, among=handed)
            cmd[handed] = planned[handed]  # type: ignore[index]
        step_active = np.zeros(n, dtype=bool)
        if shield is not None:
            li = np.flatnonzero(live)
            out = shield.filter_env(env, cmd[li], li, None if alt_cmd is None else alt_cmd[li])
            cmd[li] = out.command
            if alt_act is not None:  # the env records the action flown (the next state's last action)
                switched = out.choice > 0
                act = act.copy()
                act[li[switched]] = alt_act[li[switched], out.choice[switched] - 1]
                sh["switched_steps"][li] += switched
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
            track_active.append(step_active)
        obs, _, term, trunc, info = env.step(act, commands=cmd)
        priv = info
        t += 1
        if on_step is not None:
            on_step(env, t, step_active)
        pos = env.local_pos.copy()
        track_pos.append(pos)
        track_heading.append(env.headings)
        track_speed.append(np.linalg.norm(env.vehicles.vel_w, axis=1))
        track_esdf.append(env.field_stack.esdf(ids, pos))
        for name, flag in (("success", info["success"]), ("collision", info["collision"]),
                           ("out_of_bounds", info["out_of_bounds"]), ("timeout", info["time_outs"])):  # fmt: skip
            for i in np.flatnonzero(flag & live):
                if end_step[i] < 0:
                    end_step[i], outcome[i] = t, name
    P, V, E = np.stack(track_pos), np.stack(track_speed), np.stack(track_esdf)  # (T+1, n, 3), (T, n), (T+1, n)
    H = np.stack(track_heading)  # (T+1, n)
    if shield is not None:  # control steps with the shield acting before each position: steps 0 .. t-1 (T+1, n)
        A = np.concatenate((np.zeros((1, n)), np.cumsum(np.stack(track_active), axis=0)), axis=0)
    records = []
    every = cfg.trajectory_every
    dt = env.cfg.vehicle.command_dt
    top, radius = float(env.scenes[0].bounds_hi[2]), env.cfg.vehicle.airframe.collision_radius  # one scene per unit
    for i, trial in enumerate(trials):
        T = int(end_step[i])
        pos_i = P[: T + 1, i]
        phi_end = float(env.field_stack.geodesic(np.zeros(1, np.int64), pos_i[-1:])[0])
        m = trajectory_metrics(pos_i, V[:T, i], E[: T + 1, i], float(phi_start[i]), phi_end, top, radius)
        m["duration"] = T * dt
        m["final_goal_dist"] = float(np.linalg.norm(pos_i[-1] - np.asarray(trial["goal"])))
        keep = list(range(0, T + 1, every)) + ([T] if T % every else [])
        cols = [pos_i[keep], np.r_[0.0, V[:T, i]][keep, None], H[keep, i, None]]
        if shield is not None:  # the share of the control steps since the previous point on which the shield acted
            acted = np.diff(A[keep, i], prepend=0.0)
            cols.append((acted / np.maximum(np.diff(keep, prepend=0), 1))[:, None])
        traj = np.round(np.concatenate(cols, axis=1), 3)
        # The largest net heading rotation in 10 s [turns], on the recorded points, as `collisions --circling` reads
        # them back from the unit file (so the two agree trial for trial).
        turns = max_turns(traj, np.asarray(keep, dtype=np.float64) * dt)
        m["max_turns"] = float("nan") if turns is None else turns
        rec = {
            **trial,
            "row": spec.row_name,
            "family": spec.family,
            "scene": spec.index,
            "speed": spec.speed,
            "outcome": outcome[i],
            "steps": T,
            "metrics": m,
            "traj": traj.tolist(),
        }
        if shield is not None:
            rec["shield"] = {k: (v[i].item()) for k, v in sh.items()}
        if escape is not None:
            rec["escape"] = {"escapes": int(escape.count[i]), "escape_steps": int(escape.escape_steps[i]),
                             "by_circling": int(escape.circled[i])}  # fmt: skip
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
