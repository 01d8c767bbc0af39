"""Evaluation harness: metrics against hand-computed values, baselines' geometry, bad input, a tiny real run that
renders the table, resume, determinism, the exported-policy path, and the ``eval.py`` CLI in a subprocess.

The tiny runs fly the goal-seeking baseline at 9 m/s in the hardest ablation scene: it hits something within a
few hundred control steps, so a run takes seconds.
"""

import dataclasses
import glob
import json
import math
import os
import subprocess
import sys

import mujoco
import numpy as np
import pytest
import yaml

from shield_nav import evaluation as E
from shield_nav.algorithms.baselines import TrackingConfig, accel_to_command, free_distances
from shield_nav.evaluation.outcomes import read_outcomes
from shield_nav.provenance import cpu_simd
from shield_nav.safety.shield import ShieldConfig

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TINY = [
    "name=tiny",
    "configurations=[goal_seeking]",
    "scenes.family=ablation",
    "scenes.indices=[7]",
    "speeds=[9.0]",
    "trials_per_scene=2",
    "plots=false",
]


def tiny_cfg(*extra):
    return E.load_eval_config(None, [*TINY, *extra])


# ----------------------------------------------------------------------------------------------- metrics by hand
def test_wilson_interval_hand_computed():
    # 8/10: p = 0.8, z^2 = 3.841459, z^2/n = 0.3841459, denom = 1.3841459
    # centre = (0.8 + 0.1920729) / 1.3841459 = 0.716740; half = 1.959964 / 1.3841459 * sqrt(0.016 + 0.0096036)
    #        = 1.416010 * 0.160011 = 0.226578  ->  [0.490162, 0.943318]
    lo, hi = E.wilson_interval(8, 10)
    assert lo == pytest.approx(0.490162, abs=2e-6)
    assert hi == pytest.approx(0.943318, abs=2e-6)
    # 0/12: centre = (3.841459 / 24) / (1 + 3.841459 / 12) = 0.160061 / 1.320122 = 0.121247 = half -> [0, 0.242494]
    lo, hi = E.wilson_interval(0, 12)
    assert lo == 0.0 and hi == pytest.approx(0.242494, abs=2e-6)
    # k = n mirrors k = 0; no trials says nothing.
    assert E.wilson_interval(12, 12) == pytest.approx((1 - 0.242494, 1.0), abs=2e-6)
    assert E.wilson_interval(0, 0) == (0.0, 1.0)
    # The scipy-based interval equals the closed form above on a grid of counts.
    for n in range(1, 60, 7):
        for k in range(n + 1):
            p, z = k / n, E.Z95
            d = 1 + z * z / n
            c, h = (p + z * z / (2 * n)) / d, z / d * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
            assert E.wilson_interval(k, n) == pytest.approx((max(0.0, c - h), min(1.0, c + h)), abs=1e-12)


def test_trajectory_metrics_hand_made():
    # Two 3-4-5 legs with a pause: length 5 + 0 + 5 = 10; speeds 5, 0, 5 -> mean 10/3.
    pos = np.array([[0, 0, 1], [3, 4, 1], [3, 4, 1], [6, 8, 1]], dtype=float)
    esdf = np.array([1.0, 0.5, 0.25, 2.0])  # mean 3.75 / 4 = 0.9375, min 0.25
    m = E.trajectory_metrics(pos, np.array([5.0, 0.0, 5.0]), esdf, phi_start=20.0, phi_end=12.0)
    assert m["path_length"] == pytest.approx(10.0)
    assert m["mean_speed"] == pytest.approx(10.0 / 3.0)
    assert m["clearance_mean"] == pytest.approx(0.9375)
    assert m["clearance_min"] == pytest.approx(0.25)
    assert m["path_ratio"] == pytest.approx(10.0 / 8.0)  # 10 m flown for 8 m of geodesic progress
    assert math.isnan(E.trajectory_metrics(pos, np.ones(3), esdf, 5.0, 6.0)["path_ratio"])  # no progress
    # Over the obstacles: the flight peaks at z = 1; obstacles 0.7 m tall, vehicle radius 0.2 -> its sphere cleared
    # them (1 > 0.9); 0.8 m tall -> it did not (1 = 1.0 is not above).
    assert m["flew_over"] == 0.0  # no top given: nothing to fly over
    assert E.trajectory_metrics(pos, np.ones(3), esdf, 20.0, 12.0, top=0.7, radius=0.2)["flew_over"] == 1.0
    assert E.trajectory_metrics(pos, np.ones(3), esdf, 20.0, 12.0, top=0.8, radius=0.2)["flew_over"] == 0.0


def _trial(outcome, speed, clear_mean, clear_min, ratio, shield=None, over=None):
    t = {"outcome": outcome, "metrics": {"mean_speed": speed, "clearance_mean": clear_mean,
                                         "clearance_min": clear_min, "path_ratio": ratio}}  # fmt: skip
    if over is not None:
        t["metrics"]["flew_over"] = over
    if shield:
        t["shield"] = shield
    return t


def test_aggregate_hand_made():
    sh = lambda steps, act, corr, cmax, rel, us, usmax: {  # noqa: E731
        "steps": steps, "active_steps": act, "corr_sum": corr, "corr_max": cmax, "relaxed_steps": rel,
        "solve_us_sum": us, "solve_us_max": usmax, "total_us_sum": 10.0 * steps}  # fmt: skip
    trials = [
        _trial("success", 4.0, 1.0, 0.5, 1.1, sh(100, 10, 5.0, 2.0, 0, 1000.0, 300.0)),
        _trial("success", 5.0, 0.8, 0.3, 1.3, sh(100, 30, 9.0, 1.0, 3, 2000.0, 200.0)),
        _trial("collision", 9.0, 0.6, 0.1, float("nan"), sh(50, 10, 6.0, 4.0, 1, 500.0, 100.0)),
        _trial("timeout", 1.0, 1.2, 0.7, 2.0, sh(50, 0, 0.0, 0.0, 0, 0.0, 0.0)),
    ]
    c = E.aggregate(trials)
    assert (c["n"], c["successes"], c["success_rate"]) == (4, 2, 0.5)
    assert c["collision_rate"] == 0.25 and c["timeout_rate"] == 0.25 and c["oob_rate"] == 0.0
    assert c["vel"] == pytest.approx(4.5)  # successes only: (4 + 5) / 2
    assert c["path_ratio"] == pytest.approx(1.2)  # successes only: (1.1 + 1.3) / 2
    assert c["clearance_mean"] == pytest.approx(0.9)  # (1 + 0.8 + 0.6 + 1.2) / 4
    assert c["clearance_min"] == pytest.approx(0.1)
    assert c["shield_active"] == pytest.approx(50 / 300)  # pooled control steps
    assert c["corr_mean"] == pytest.approx(20.0 / 50)  # per active step
    assert c["corr_max"] == 4.0
    assert c["relaxed"] == pytest.approx(4 / 300)
    assert c["qp_us_mean"] == pytest.approx(3500.0 / 50) and c["qp_us_max"] == 300.0
    assert c["switched"] == 0.0  # trial files without the hypotheses option's count
    trials[0]["shield"]["switched_steps"] = 12
    assert E.aggregate(trials)["switched"] == pytest.approx(12 / 300)
    del trials[0]["shield"]["switched_steps"]
    assert (c["sr_lo"], c["sr_hi"]) == pytest.approx(E.wilson_interval(2, 4))
    assert math.isnan(c["over_top"])  # trial files from before the metric: unknown, not 0
    # Over the top counts successes only: one of the two successes flew over; the collision's flight does not count.
    trials = [_trial("success", 4.0, 1.0, 0.5, 1.1, over=1.0), _trial("success", 5.0, 0.8, 0.3, 1.3, over=0.0),
              _trial("collision", 9.0, 0.6, 0.1, float("nan"), over=1.0)]  # fmt: skip
    assert E.aggregate(trials)["over_top"] == pytest.approx(0.5)
    # Circling counts every outcome, over the trials that carry the metric: 2.0 turns circles, 1.4 does not (the
    # threshold is 1.5), a NaN (too short a record to tell) and a trial file from before the metric are left out.
    assert math.isnan(E.aggregate(trials)["circling"])
    for t, turns in zip(trials, (2.0, 1.4, float("nan")), strict=True):
        t["metrics"]["max_turns"] = turns
    trials.append(_trial("timeout", 1.0, 1.2, 0.7, 2.0))
    assert E.aggregate(trials)["circling"] == pytest.approx(0.5)
    trials[2]["metrics"]["max_turns"] = 1.5
    assert E.aggregate(trials)["circling"] == pytest.approx(2 / 3)


def test_accel_to_command_and_free_distance_by_hand():
    cfg = TrackingConfig()
    g = 9.81
    # Zero acceleration: hover, level, yaw kept.
    assert accel_to_command(np.zeros((1, 3)), np.array([0.3]), cfg, g)[0] == pytest.approx([g, 0, 0, 0.3])
    # a = (g, 0, 0): T = (g, 0, g) is tilted 45 deg > 40 deg, so T_xy is cut to g tan 40; pitch +40 deg (nose down
    # accelerates +x in ZYX), f_n = g / cos 40.
    cmd = accel_to_command(np.array([[g, 0.0, 0.0]]), np.zeros(1), cfg, g)[0]
    assert cmd == pytest.approx([g / math.cos(math.radians(40)), 0.0, math.radians(40), 0.0], abs=1e-9)
    # Free distance: a point at (5, 0.3, 0), radius 0.5: along +x the ray comes within 0.5 at t = 5 - sqrt(0.25 -
    # 0.09) = 4.6; along +y it passes 5 m away (never), so the cap (8) is returned; along -x it is behind.
    dirs = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0]])
    free = free_distances(np.array([[5.0, 0.3, 0.0]]), np.zeros(3), dirs, 0.5, 8.0)
    assert free == pytest.approx([4.6, 8.0, 8.0])


# ----------------------------------------------------------------------------------------------- bad input
def test_bad_input_errors(tmp_path):
    with pytest.raises(E.EvalError, match="unknown configuration 'nope'"):
        E.prepare(tiny_cfg("configurations=[nope]"))
    with pytest.raises(E.EvalError, match="unknown scene family"):
        E.parse_scenes("woods:0")
    with pytest.raises(E.EvalError, match="out of range"):
        E.parse_scenes("ablation:0,8")
    assert E.parse_scenes("benchmark:0-2,7").indices == [0, 1, 2, 7]
    with pytest.raises(E.ConfigError, match="trials_per_scene"):
        tiny_cfg("trials_per_scene=0")
    with pytest.raises(E.ConfigError, match="no_such_key"):
        tiny_cfg("no_such_key=1")
    with pytest.raises(E.ConfigError, match="baselines.reactive.guidance"):
        tiny_cfg("baselines.reactive.guidance=straight")
    with pytest.raises(E.ConfigError, match="baselines.oracle.guidance"):
        tiny_cfg("baselines.oracle.guidance=straight")
    # An unquoted list inside a list is not YAML: the error names the override, and the quoted form loads.
    nested = "env_overrides=[episode.timeout_factor=1.5,randomization.action_latency_steps=[0,0]]"
    with pytest.raises(E.ConfigError, match=r"override 'env_overrides=\[episode.*not valid YAML.*quote"):
        tiny_cfg(nested)
    quoted = tiny_cfg("env_overrides=[episode.timeout_factor=1.5,'randomization.action_latency_steps=[0,0]']")
    assert quoted.env_overrides == ["episode.timeout_factor=1.5", "randomization.action_latency_steps=[0,0]"]
    # A missing checkpoint: an error with 'error' (the default) and for explicitly given ones; 'skip' marks the row.
    missing = str(tmp_path / "nowhere")
    with pytest.raises(E.EvalError, match="does not exist"):
        E.prepare(tiny_cfg("configurations=[full]", f"checkpoints.full={missing}"))
    prep = E.prepare(tiny_cfg("configurations=[full,goal_seeking]", f"checkpoints.full={missing}",
                              "missing_checkpoints=skip"))  # fmt: skip
    assert list(prep.missing) == ["full"] and [u.row_name for u in E.plan_units(prep)] == ["goal_seeking"]
    with pytest.raises(E.EvalError, match="does not exist"):
        E.prepare(tiny_cfg("configurations=[full]", f"checkpoints.full={missing}",
                           "missing_checkpoints=skip"), explicit_checkpoints=("full",))  # fmt: skip
    # A folder with training checkpoints but no export.
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "model_10.pt").write_bytes(b"x")
    with pytest.raises(E.EvalError, match="no export|export the actor"):
        E.load_policy(tmp_path / "run", "p")


# ----------------------------------------------------------------------------------------------- policies
def export_fresh_policy(out_dir, state_dim=21, train_speeds=None):
    """Export a freshly initialised DepthGRUModel (a real ONNX/TorchScript model, untrained)."""
    torch = pytest.importorskip("torch")
    from tensordict import TensorDict

    from shield_nav.policies.export import export_policy
    from shield_nav.policies.models import DepthGRUModel

    torch.manual_seed(0)
    obs = TensorDict({"depth": torch.rand(2, 1, 60, 100), "state": torch.randn(2, state_dim)}, [2])
    model = DepthGRUModel(obs, {"actor": ["depth", "state"]}, "actor", 4, rnn_hidden_dim=16,
                          distribution_cfg={"class_name": "GaussianDistribution", "init_std": 0.5})  # fmt: skip
    paths = export_policy(model, os.path.join(out_dir, "exported"))
    if train_speeds is not None:
        os.makedirs(os.path.join(out_dir, "params"), exist_ok=True)
        with open(os.path.join(out_dir, "params", "config.yaml"), "w") as f:
            yaml.safe_dump({"env": {"episode": {"target_speeds": train_speeds}, "action": {"max_tilt_deg": 40.0}}}, f)
    return paths


def test_exported_policy_loads_matches_torchscript_and_flies(tmp_path):
    paths = export_fresh_policy(str(tmp_path / "ckpt"), train_speeds=[3.0, 5.0])
    onnx = E.load_policy(tmp_path / "ckpt", "mine")  # the folder: finds exported/policy.onnx
    jit = E.load_policy(paths["jit"], "mine")
    assert onnx.info.kind == "onnx" and jit.info.kind == "torchscript"
    assert (onnx.info.obs_dim, onnx.info.depth_shape, onnx.info.hidden_size) == (21, (1, 60, 100), 16)
    assert onnx.info.train_speeds == (3.0, 5.0) and onnx.info.train_env == {"action": {"max_tilt_deg": 40.0}}
    rng = np.random.default_rng(0)
    state, depth = rng.normal(size=(3, 21)).astype(np.float32), rng.uniform(size=(3, 1, 60, 100)).astype(np.float32)
    h = onnx.initial_state(3)
    a1, h1 = onnx.step(state, depth, h)
    a2, h2 = jit.step(state, depth, h)
    assert a1.shape == (3, 4) and h1.shape == (1, 3, 16)
    np.testing.assert_allclose(a1, a2, atol=1e-5)
    np.testing.assert_allclose(h1, h2, atol=1e-5)
    # Through the harness (the onnx file, network: export; the default flies policy.pt, test_fixed_order.py): 9 m/s
    # is outside the trained [3, 5] -> a marked warning; the policy flies a short trial.
    cfg = tiny_cfg("configurations=[mine]", "rows.mine.label=Mine", "rows.mine.policy=mine",
                   f"checkpoints.mine={tmp_path / 'ckpt'}", "trials_per_scene=1", "network=export",
                   "env_overrides=[episode.timeout_factor=0.05]")  # fmt: skip
    with pytest.warns(UserWarning, match="outside 'mine'"):
        summary = E.evaluate(cfg, str(tmp_path / "out"), progress=False)
    assert "9 m/s is outside" in summary["markdown"] and " !" in summary["paper_table"]
    man = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert man["checkpoints"]["mine"]["sha256"] == onnx.info.sha256
    (trial,) = json.loads((tmp_path / "out" / "trials.json").read_text())
    assert trial["outcome"] in ("success", "collision", "timeout", "out_of_bounds") and trial["steps"] > 0


def test_layout_mismatch_is_a_clear_error(tmp_path):
    export_fresh_policy(str(tmp_path / "ckpt"), state_dim=20)
    cfg = tiny_cfg("configurations=[full]", f"checkpoints.full={tmp_path / 'ckpt'}")
    with pytest.raises(E.EvalError, match="state vector has 20 values, the env gives 21"):
        E.prepare(cfg)


@pytest.fixture(scope="module")
def tiny_teacher(tmp_path_factory):
    """A privileged MLP teacher trained for one PPO iteration by train.py (no teacher ships in the release)."""
    root = tmp_path_factory.mktemp("teacher")
    res = subprocess.run([sys.executable, "train.py", "--config", "configs/experiments/teacher_dijkstra_cbf.yaml",
                          "--max-iterations", "1", "--num-envs", "4", "--log-dir", str(root), "--set",
                          "runner.num_steps_per_env=8", "env.scenes.indices=[0,1]",
                          "runner.algorithm.num_mini_batches=2"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    (run,) = os.listdir(os.path.join(root, "shield_nav"))
    return os.path.join(root, "shield_nav", run, "model_0.pt")


def test_teacher_row_runs_the_privileged_mlp(tmp_path, tiny_teacher):
    import torch

    path = tiny_teacher
    teacher = E.load_teacher(path, "teacher_dijkstra_cbf")
    assert teacher.info.kind == "teacher" and teacher.info.obs_dim == 21 + 9 * 9 * 3
    assert teacher.info.train_env["local_map"]["enabled"] is True
    # Independent forward from the raw weights: normalise (eps 0.01, rsl-rl's), three ELU layers, a linear head.
    sd = {k: v.double().numpy() for k, v in torch.load(path, weights_only=False)[
        "actor_state_dict"].items() if v.dim() > 0}  # fmt: skip
    x = np.random.default_rng(0).normal(size=(3, 264))
    z = (x - sd["obs_normalizer._mean"]) / (sd["obs_normalizer._std"] + 0.01)
    for i in (0, 2, 4):
        z = z @ sd[f"mlp.{i}.weight"].T + sd[f"mlp.{i}.bias"]
        z = np.where(z > 0, z, np.expm1(np.minimum(z, 0.0)))
    z = z @ sd["mlp.6.weight"].T + sd["mlp.6.bias"]
    np.testing.assert_allclose(teacher.step(x), z, atol=1e-4)
    # A student is not a teacher.
    with pytest.raises(E.EvalError, match="not a privileged teacher"):
        E.load_teacher(os.path.join(ROOT, "checkpoints", "dijkstra_cbf"), "s")
    with pytest.raises(E.EvalError, match="no teacher checkpoint"):
        E.load_teacher(str(tmp_path), "nothing")
    # Through the harness: the unit enables the map and skips rendering; the header says the row is privileged.
    cfg = tiny_cfg("configurations=[teacher_dijkstra_cbf]", f"checkpoints.teacher_dijkstra_cbf={path}",
                   "rows={teacher_dijkstra_cbf: {label: Teacher, controller: teacher, policy: teacher_dijkstra_cbf}}",
                   "trials_per_scene=1", "speeds=[3.0]", "env_overrides=[episode.timeout_factor=0.05]")  # fmt: skip
    (unit,) = E.plan_units(E.prepare(cfg))
    assert unit.policy_env["local_map"]["enabled"] is True and unit.policy_env["render_depth"] is False
    summary = E.evaluate(cfg, str(tmp_path / "out"), progress=False)
    assert "privileged local ESDF map" in summary["markdown"]
    # The header names the env overrides as run (the free-text title may name other values).
    assert "Env overrides: `episode.timeout_factor=0.05`." in summary["markdown"]
    (trial,) = json.loads((tmp_path / "out" / "trials.json").read_text())
    assert trial["outcome"] in ("success", "collision", "timeout", "out_of_bounds") and trial["steps"] > 0


# ----------------------------------------------------------------------------------------------- real tiny runs
def test_tiny_run_table_outputs_resume_and_determinism(tmp_path, monkeypatch, capsys):
    out1, out2 = str(tmp_path / "a"), str(tmp_path / "b")
    s1 = E.evaluate(tiny_cfg(), out1, progress=False)
    # Paper-shaped table with the row and the speed columns; every output file; every trial traceable.
    assert "| Goal-seeking (no shield) |" in s1["paper_table"] and "9 m/s SR" in s1["paper_table"]
    for f in ("table.md", "table.csv", "table.tex", "trials.json", "summary.json", "manifest.json", "config.yaml"):
        assert os.path.exists(os.path.join(out1, f)), f
    with open(os.path.join(out1, "trials.json")) as f:
        trials = json.load(f)
    assert len(trials) == 2 and {"seed", "start", "goal", "outcome", "metrics", "scene"} <= set(trials[0])
    # The kept-trials file holds each trial's pinning keys and outcome, as trials.json does.
    kept = read_outcomes(os.path.join(out1, "outcomes.csv.gz"))
    pick = ("row", "scene", "trial", "seed", "outcome", "steps")
    assert [{k: r[k] for k in pick} for r in kept] == [{k: t[k] for k in pick} for t in trials]
    assert [r["metrics"]["flew_over"] for r in kept] == [t["metrics"]["flew_over"] for t in trials]
    # Each trial's max_turns is what `collisions --circling` reads back from its unit file's recorded points.
    from shield_nav.tools.collisions import max_turns, point_times

    units = []
    for path in sorted(glob.glob(os.path.join(out1, "units", "*.json"))):
        with open(path) as fh:
            units.append(json.load(fh))
    every, dt = tiny_cfg().trajectory_every, 0.01
    for t in (t for u in units for t in u["trials"]):
        again = max_turns(np.asarray(t["traj"]), point_times(t["steps"], every, dt))
        assert np.isfinite(again) and t["metrics"]["max_turns"] == again
    with open(os.path.join(out1, "manifest.json")) as f:
        man = json.load(f)
    assert len(man["git"]["rev"]) >= 7 and man["config"]["seed"] == 0
    assert man["packages"]["numpy"] == np.__version__ and man["packages"]["mujoco"] == mujoco.__version__
    assert isinstance(man["cpu"], str) and man["cpu_simd"] == cpu_simd()
    # Each recorded trajectory point is x, y, z, speed, heading; the first heading is the trial's start yaw.
    with open(os.path.join(out1, "units", "goal_seeking__ablation-07__v9.json")) as f:
        unit_trials = json.load(f)["trials"]
    for t in unit_trials:
        tr = np.asarray(t["traj"])
        assert tr.shape[1] == 5 and np.all(np.abs(tr[:, 4]) <= math.pi + 1e-3)
        assert tr[0, 4] == pytest.approx(math.remainder(t["yaw"], 2 * math.pi), abs=1e-3)
    # Starts and goals lie in the scene's regions.
    from envs.scenes import make_scene

    scene = make_scene("ablation", 7)
    for t in trials:
        assert np.all(np.asarray(t["start"]) >= scene.start_region[0]) and np.all(
            t["start"] <= np.asarray(scene.start_region[1])
        )
        assert np.all(np.asarray(t["goal"]) >= scene.goal_region[0]) and np.all(
            t["goal"] <= np.asarray(scene.goal_region[1])
        )
    # Determinism: the same command and seed reproduce the table and every trial (timings aside).
    s2 = E.evaluate(tiny_cfg(), out2, progress=False)
    assert s2["paper_table"] == s1["paper_table"]
    with open(os.path.join(out2, "trials.json")) as f:
        t2 = json.load(f)
    assert [(t["seed"], t["outcome"], t["steps"], t["metrics"]) for t in t2] == [
        (t["seed"], t["outcome"], t["steps"], t["metrics"]) for t in trials
    ]
    # A different seed gives different trials.
    assert E.trial_seed(1, "ablation", 7, 9.0, 0) != trials[0]["seed"]
    # Resume: finished units are skipped (run_unit is never called) and the table is rebuilt from disk.
    calls = []
    real = E.run_unit
    import shield_nav.evaluation.run as run_module  # evaluate() looks run_unit up there

    monkeypatch.setattr(run_module, "run_unit", lambda spec: calls.append(spec.key) or real(spec))
    s3 = E.evaluate(tiny_cfg(), out1, progress=False)
    assert calls == [] and s3["paper_table"] == s1["paper_table"]
    # A lost unit (e.g. interrupted) is the only one re-run.
    os.remove(os.path.join(out1, "units", "goal_seeking__ablation-07__v9.json"))
    prep = E.prepare(tiny_cfg())
    partial = E.write_outputs(prep, out1, E.plan_units(prep))  # what an interrupted run leaves: a marked table
    assert "PARTIAL: 0 of 1 units finished" in partial["markdown"]
    capsys.readouterr()
    E.evaluate(tiny_cfg(), out1, progress=False)
    assert calls == ["goal_seeking__ablation-07__v9"]
    assert "other code" not in capsys.readouterr().err  # the same code: no warning
    # A resume with other code than the folder's first units says so, naming both revisions.
    man_path = os.path.join(out1, "manifest.json")
    with open(man_path) as f:
        man = json.load(f)
    man["git"] = {"rev": "0123456789abcdef", "dirty": False, "diff_sha256": ""}
    with open(man_path, "w") as f:
        json.dump(man, f)
    E.evaluate(tiny_cfg(), out1, progress=False)
    err = capsys.readouterr().err
    assert "with other code than its first units were flown with (git 0123456789ab then," in err
    # Another configuration into the same folder is refused instead of mixing results.
    with pytest.raises(E.EvalError, match="different run"):
        E.evaluate(tiny_cfg("seed=5"), out1, progress=False)


def test_resume_with_other_package_versions_names_them(tmp_path, monkeypatch, capsys):
    """A folder first flown with other package versions resumes (the config and checkpoints are the same run), and
    the versions that changed are named, since the units flown from now on may differ trial by trial."""
    out = str(tmp_path / "out")
    E.evaluate(tiny_cfg(), out, progress=False)
    capsys.readouterr()
    man_path = os.path.join(out, "manifest.json")
    with open(man_path) as f:
        man = json.load(f)
    E.evaluate(tiny_cfg(), out, progress=False)  # the same versions: nothing to say
    assert "package versions" not in capsys.readouterr().err
    man["packages"]["numpy"] = "1.0.0"
    with open(man_path, "w") as f:
        json.dump(man, f)
    E.evaluate(tiny_cfg(), out, progress=False)
    assert f"numpy 1.0.0 / {np.__version__}" in capsys.readouterr().err
    # Another processor's SIMD extensions with the same packages are named too (2026-12-01: they move trials).
    man["packages"]["numpy"] = np.__version__
    man["cpu_simd"] = "sse4_2 no-such-extension"
    with open(man_path, "w") as f:
        json.dump(man, f)
    E.evaluate(tiny_cfg(), out, progress=False)
    err = capsys.readouterr().err
    assert "cpu_simd sse4_2 no-such-extension / " in err and "numpy" not in err


def test_resume_of_a_folder_written_before_a_config_key_existed(tmp_path, monkeypatch, capsys):
    """A folder whose manifest lacks config keys added since resumes while those keys sit at their defaults (the
    units are not re-flown, the keys are named); a non-default value there, or a key the config no longer has, is
    another run."""
    out = str(tmp_path / "old")
    E.evaluate(tiny_cfg(), out, progress=False)
    man_path = os.path.join(out, "manifest.json")
    with open(man_path) as f:
        man = json.load(f)
    # What a folder written before scenes.seed and baselines.expert.mppi_narrow_clearance existed holds.
    del man["config"]["scenes"]["seed"], man["config"]["baselines"]["expert"]["mppi_narrow_clearance"]
    man["identity_sha256"] = "0" * 64
    with open(man_path, "w") as f:
        json.dump(man, f)
    import shield_nav.evaluation.run as run_module

    calls = []
    real = E.run_unit
    monkeypatch.setattr(run_module, "run_unit", lambda spec: calls.append(spec.key) or real(spec))
    E.evaluate(tiny_cfg(), out, progress=False)
    assert calls == []
    assert "baselines.expert.mppi_narrow_clearance, scenes.seed" in capsys.readouterr().err
    with pytest.raises(E.EvalError, match="different run"):
        E.evaluate(tiny_cfg("baselines.expert.mppi_narrow_clearance=0.35"), out, progress=False)
    man["config"]["no_longer_a_key"] = 1
    with open(man_path, "w") as f:
        json.dump(man, f)
    with pytest.raises(E.EvalError, match="different run"):
        E.evaluate(tiny_cfg(), out, progress=False)


def test_a_folder_written_before_route_hysteresis_is_not_resumed_with_it(tmp_path, monkeypatch, capsys):
    """baselines.expert.commit_dist came on by default when it was added: a manifest without it meant 0 (its
    PRE_FIELD_VALUES), so today's default (1 m) is another run, and commit_dist=0 resumes it."""
    out = str(tmp_path / "old")
    E.evaluate(tiny_cfg("baselines.expert.commit_dist=0"), out, progress=False)
    man_path = os.path.join(out, "manifest.json")
    with open(man_path) as f:
        man = json.load(f)
    del man["config"]["baselines"]["expert"]["commit_dist"]
    man["identity_sha256"] = "0" * 64
    with open(man_path, "w") as f:
        json.dump(man, f)
    with pytest.raises(E.EvalError, match="different run"):
        E.evaluate(tiny_cfg(), out, progress=False)
    import shield_nav.evaluation.run as run_module

    calls = []
    monkeypatch.setattr(run_module, "run_unit", lambda spec: calls.append(spec.key))
    E.evaluate(tiny_cfg("baselines.expert.commit_dist=0"), out, progress=False)
    assert calls == []
    assert "baselines.expert.commit_dist" in capsys.readouterr().err


def test_a_folder_flown_with_another_network_is_refused_with_the_flag_that_resumes_it(tmp_path, monkeypatch):
    """A folder flown with one ``network`` is another run for the other; the refusal names the flag. A manifest
    written before the key existed flew the exported network (its PRE_FIELD_VALUES)."""
    out = str(tmp_path / "old")
    E.evaluate(tiny_cfg("network=fixed_order"), out, progress=False)
    with pytest.raises(E.EvalError, match="flown with network: fixed_order; add --set network=fixed_order to resume"):
        E.evaluate(tiny_cfg("network=export"), out, progress=False)
    man_path = os.path.join(out, "manifest.json")
    with open(man_path) as f:
        man = json.load(f)
    del man["config"]["network"]
    man["identity_sha256"] = "0" * 64
    with open(man_path, "w") as f:
        json.dump(man, f)
    with pytest.raises(E.EvalError, match="flown with network: export; add --set network=export to resume it"):
        E.evaluate(tiny_cfg("network=fixed_order"), out, progress=False)
    import shield_nav.evaluation.run as run_module

    calls = []
    monkeypatch.setattr(run_module, "run_unit", lambda spec: calls.append(spec.key))
    E.evaluate(tiny_cfg("network=export"), out, progress=False)
    assert calls == []


def test_eval_cli_subprocess(tmp_path):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(
        yaml.safe_dump({"name": "tiny", "configurations": ["goal_seeking"], "scenes": {"family": "ablation",
                        "indices": [7]}, "speeds": [9.0], "trials_per_scene": 2, "plots": False})
    )  # fmt: skip
    cmd = [sys.executable, "eval.py", "--config", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "| Goal-seeking (no shield) |" in res.stdout and "2 trials per scene" in res.stdout
    bad = subprocess.run([*cmd, "--configurations", "nope"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "unknown configuration 'nope'" in bad.stderr


def test_video_writers_without_rendering(tmp_path):
    # The MP4/GIF writer and the no-OpenGL fallback (an animated top-down plot of a recorded trajectory).
    from envs.fields import build_fields
    from envs.scenes import make_scene
    from shield_nav.evaluation import plots

    frames = [np.full((16, 16, 3), 40 * k, dtype=np.uint8) for k in range(4)]
    path = plots.write_video(frames, str(tmp_path / "clip"), fps=10)
    assert path.endswith((".mp4", ".gif")) and os.path.getsize(path) > 0
    scene = make_scene("ablation", 0)
    fields = build_fields(scene, resolution=0.2, vehicle_radius=0.2)
    trial = {"row": "oracle", "trial": 0, "outcome": "success",
             "traj": [[0.5, 0.0, 1.0, 0.0], [2.0, 0.5, 1.0, 3.0], [4.0, 1.0, 1.0, 4.0]]}  # fmt: skip
    gif = plots.animate_topdown(scene, fields, trial, str(tmp_path / "top.gif"))
    assert os.path.getsize(gif) > 0


EVAL_CONFIGS = sorted(f for f in os.listdir(os.path.join(ROOT, "configs", "eval")) if f.endswith(".yaml"))


@pytest.mark.parametrize("name", EVAL_CONFIGS)
def test_shipped_eval_configs_resolve(name):
    """Every shipped eval config loads, and its rows and committed checkpoints pass the checks run before flying."""
    cfg = E.load_eval_config(os.path.join(ROOT, "configs", "eval", name))
    prep = E.prepare(cfg)
    assert set(prep.rows) == set(cfg.configurations) and not prep.missing


def test_truncated_torchscript_export_is_called_truncated(tmp_path):
    """A policy.pt cut short by an interrupted copy is reported as truncated, not as 'not a TorchScript export';
    a training checkpoint given instead of an export keeps its own message."""
    good = os.path.join(ROOT, "checkpoints", "student", "policy.pt")
    cut = tmp_path / "policy.pt"
    with open(good, "rb") as f:
        cut.write_bytes(f.read()[:20000])
    with pytest.raises(E.EvalError, match=r"\(20000 bytes\) is truncated or corrupt"):
        E.load_policy(str(cut), "cut")
    train_ckpt = os.path.join(ROOT, "checkpoints", "student", "model.pt")
    with pytest.raises(E.EvalError, match="is not a TorchScript export.*runs only with network 'fixed_order'"):
        E.load_policy(train_ckpt, "ckpt")
    assert E.load_policy(good, "good").info.obs_dim > 0


def _children(pid):
    kids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                kids.append(int(entry))
    return kids


def _alive(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads worker processes from /proc")
def test_sigterm_stops_the_workers_and_keeps_finished_units(tmp_path):
    """SIGTERM is handled like Ctrl-C: the worker processes are terminated (no orphans burning CPU) and every
    finished unit stays on disk for a resume."""
    import signal
    import time

    out = tmp_path / "ev"
    cmd = [sys.executable, "eval.py", "--config", "configs/eval/expert.yaml", "--configurations", "goal_seeking",
           "--scenes", "ablation:0,1,2,3,4,5,6,7", "--speeds", "9,7,5,3", "--trials", "2", "--workers", "2",
           "--out", str(out)]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    units = out / "units"
    deadline = time.time() + 240
    while time.time() < deadline and not (units.is_dir() and any(units.iterdir())):
        assert proc.poll() is None, proc.stdout.read()
        time.sleep(0.2)
    assert units.is_dir() and any(units.iterdir()), "no unit finished in time"
    workers = _children(proc.pid)
    assert workers, "expected worker processes"
    proc.send_signal(signal.SIGTERM)
    text, _ = proc.communicate(timeout=60)
    assert proc.returncode != 0
    assert "interrupted: finished units are saved" in text
    time.sleep(0.5)
    assert not [w for w in workers if _alive(w)], "worker processes outlived eval.py"
    saved = list(units.iterdir())
    assert 1 <= len(saved) < 32
    for f in saved:
        assert json.loads(f.read_text())["trials"]


def test_figures_and_trials_use_the_scene_seed_that_was_flown():
    """With scenes.seed in env_overrides, the scene used for trials, figures and videos is that seed's scene."""
    from envs.scenes import make_scene

    cfg = E.load_eval_config(os.path.join(ROOT, "configs", "eval", "expert.yaml"))
    default = E.flown_scene(cfg, "ablation", 2)
    cfg.env_overrides = [*cfg.env_overrides, "scenes.seed=1234567"]
    seeded = E.flown_scene(cfg, "ablation", 2)
    ref = make_scene("ablation", 2, 1234567)
    key = lambda sc: [p.to_mjcf() for p in sc.primitives]  # noqa: E731
    assert key(seeded) == key(ref)
    assert key(seeded) != key(default)


def test_unreadable_policy_config_warns_with_its_name(tmp_path):
    bad = tmp_path / "config.yaml"
    bad.write_text("env: {action: [unclosed\n")
    with pytest.warns(UserWarning, match=r"config\.yaml.*out-of-range speed flag"):
        assert E._speeds_from_config(str(bad)) is None
    with pytest.warns(UserWarning, match=r"config\.yaml.*action, camera and vehicle"):
        assert E._env_from_config(str(bad)) is None


def test_row_registry_is_yaml_with_the_paper_names_and_rejects_unknown_keys(tmp_path):
    rows, checkpoints = E.load_registry()
    assert [rows[k].label for k in ("distance", "dijkstra", "dijkstra_cbf", "full")] == [
        "Distance", "Dijkstra", "Dijkstra + CBF", "Full"]  # fmt: skip
    assert rows["full"].policy == "full" and rows["full"].shield and not rows["dijkstra_cbf"].shield
    # the paper's literal Full (the Dijkstra + CBF policy trained alone, behind the shield) stays a row of its own
    assert rows["dijkstra_cbf_shield"].policy == "dijkstra_cbf" and rows["dijkstra_cbf_shield"].shield
    assert all(os.path.isdir(os.path.join(ROOT, p)) for p in checkpoints.values())  # every shipped policy is there
    bad = tmp_path / "rows.yaml"
    bad.write_text("rows:\n  mine: {label: x, controler: oracle}\n")
    with pytest.raises(E.EvalError, match=r"rows.mine: unknown key\(s\) \['controler'\]"):
        E.load_registry(str(bad))
    bad.write_text("row: {}\n")
    with pytest.raises(E.EvalError, match=r"unknown top-level key\(s\) \['row'\]"):
        E.load_registry(str(bad))


def test_rows_that_read_no_image_skip_the_ray_casting_and_fly_the_same_trials(tmp_path):
    cfg = tiny_cfg("configurations=[oracle,goal_seeking,expert,reactive,shield_only,expert_shield]")
    envs = {u.row_name: u.policy_env for u in E.plan_units(E.prepare(cfg))}
    assert envs["oracle"] == envs["goal_seeking"] == envs["expert"] == {"render_depth": False}
    # the image or the shield's point cloud is read: behind the shield even the map-reading expert renders
    assert envs["reactive"] is None and envs["shield_only"] is None and envs["expert_shield"] is None
    # Rendering is observation only: the oracle flies the same trial with and without it.
    (spec,) = E.plan_units(E.prepare(tiny_cfg("configurations=[oracle]")))
    off = E.run_unit(spec)
    on = E.run_unit(dataclasses.replace(spec, policy_env=None))
    assert [t["outcome"] for t in off["trials"]] == [t["outcome"] for t in on["trials"]]
    assert [t["steps"] for t in off["trials"]] == [t["steps"] for t in on["trials"]]


def test_row_shield_overrides_change_that_rows_shield_only(tmp_path):
    """A row's shield_overrides replace the run's shield settings for that row: a shield that sees no point (a
    1 cm distance window) never acts, while the same controller behind the default shield does; a bad key or value
    names the row, and overrides without a shield are an error."""
    blind = ["rows.blind.controller=goal", "rows.blind.shield=true",
             "rows.blind.shield_overrides.point_filter=[0.0,0.01]"]  # fmt: skip
    cfg = tiny_cfg("configurations=[shield_only,blind]", *blind)
    specs = {s.row_name: s for s in E.plan_units(E.prepare(cfg))}
    trials = {n: E.run_unit(spec)["trials"] for n, spec in specs.items()}
    active = {n: sum(t["shield"]["active_steps"] for t in ts) for n, ts in trials.items()}
    assert active["shield_only"] > 0 and active["blind"] == 0
    # A shielded row's trajectory points carry the share of the steps since the previous point with the shield
    # acting: weighted by those steps they add up to the trial's own count of active steps.
    every = cfg.trajectory_every
    for ts in trials.values():
        for t in ts:
            tr = np.asarray(t["traj"])
            keep = [*range(0, t["steps"] + 1, every)] + ([t["steps"]] if t["steps"] % every else [])
            assert tr.shape == (len(keep), 6) and tr[0, 5] == 0.0 and np.all((tr[:, 5] >= 0) & (tr[:, 5] <= 1))
            acted = np.sum(tr[1:, 5] * np.diff(keep))
            assert acted == pytest.approx(t["shield"]["active_steps"], abs=5e-4 * every * len(keep))
    assert E.BUILTIN_ROWS["full_paper_shield"].shield_overrides["active_set_iterations"] == 0
    assert E.BUILTIN_ROWS["full_paper_shield"].shield_overrides["map_seconds"] == 0.0  # the paper keeps no map
    # The default shield keeps its local map (2 s, 0.2 m, 6 m); the row full_no_map flies Full without it.
    assert (ShieldConfig().map_seconds, ShieldConfig().map_voxel, ShieldConfig().map_radius) == (2.0, 0.2, 6.0)
    no_map = ShieldConfig(**E.BUILTIN_ROWS["full_no_map"].shield_overrides)
    no_map.validate()
    assert no_map.map_seconds == 0.0 and E.BUILTIN_ROWS["full_no_map"].policy == "full"
    # full_alone flies the same policy file as full, with no shield.
    alone, full = E.BUILTIN_ROWS["full_alone"], E.BUILTIN_ROWS["full"]
    assert (alone.policy, alone.controller, alone.shield, full.shield) == ("full", "policy", False, True)
    with pytest.raises(E.EvalError, match=r"rows\.blind\.shield_overrides: unknown key\(s\) \['alpha2'\]"):
        E.resolve_rows(tiny_cfg("configurations=[blind]", *blind, "rows.blind.shield_overrides.alpha2=1.0"))
    with pytest.raises(E.EvalError, match=r"rows\.blind\.shield_overrides\.lag_s"):
        E.resolve_rows(tiny_cfg("configurations=[blind]", *blind, "rows.blind.shield_overrides.lag_s=-1.0"))
    with pytest.raises(E.EvalError, match="has shield_overrides but no shield"):
        E.resolve_rows(tiny_cfg("configurations=[blind]", *blind, "rows.blind.shield=false"))


def test_scene_seed_of_the_config_survives_env_override_and_scenes_flags():
    """validation_benchmark's scene seed is part of its scene selection: replacing env_overrides (a common --set) or
    narrowing the scenes with --scenes keeps it, so a validation run never falls back to the test scenes."""
    import argparse

    path = os.path.join(ROOT, "configs", "eval", "validation_benchmark.yaml")
    cfg = E.load_eval_config(path, ["env_overrides=[episode.timeout_factor=1.5,render_depth=false]"])
    assert cfg.scenes.seed == 1150000
    assert E.nav_config(cfg, "benchmark", 15, 5.0, 1).scenes.seed == 1150000
    assert E.scene_seed(cfg) == 1150000
    args = argparse.Namespace(config=path, set=[], checkpoint=[], speeds=None, trials=None, scenes="benchmark:15",
                              configurations="expert", workers=None, seed=None)  # fmt: skip
    cfg2, _ = E.config_from_args(args)
    assert cfg2.scenes.indices == [15] and cfg2.scenes.seed == 1150000
    # the family's own scenes (the held-out ones) when no seed is given
    bench = E.load_eval_config(os.path.join(ROOT, "configs", "eval", "benchmark.yaml"))
    assert bench.scenes.seed is None and E.scene_seed(bench) is None


def test_scene_seed_set_twice_must_agree_and_an_error_names_both_keys():
    path = os.path.join(ROOT, "configs", "eval", "validation_benchmark.yaml")
    with pytest.raises(E.ConfigError, match=r"env_overrides.*scenes\.seed=7.*scenes\.seed \(1150000\)"):
        E.load_eval_config(path, ["env_overrides=[scenes.seed=7]"])
    same = E.load_eval_config(path, ["env_overrides=[episode.timeout_factor=3.0,scenes.seed=1150000]"])
    assert E.scene_seed(same) == 1150000
    # another draw of the same generator: set scenes.seed itself
    other = E.load_eval_config(path, ["scenes.seed=1160000"])
    assert E.nav_config(other, "benchmark", 3, 9.0, 1).scenes.seed == 1160000


def test_policy_with_a_memory_input_reads_its_groups_and_the_env_section_from_its_training_config(tmp_path):
    """A policy trained with ``memory`` after ``state`` is flown with the scene memory on and both groups joined."""
    torch = pytest.importorskip("torch")
    from tensordict import TensorDict

    from shield_nav.policies.export import export_policy
    from shield_nav.policies.models import DepthGRUModel

    torch.manual_seed(0)
    obs = TensorDict({"depth": torch.rand(2, 1, 60, 100), "state": torch.randn(2, 21), "memory": torch.rand(2, 8)}, [2])
    groups = {"actor": ["depth", "state", "memory"], "critic": ["critic"], "student": ["depth", "state"]}
    model = DepthGRUModel(obs, groups, "actor", 4, rnn_hidden_dim=16,
                          distribution_cfg={"class_name": "GaussianDistribution", "init_std": 0.5})  # fmt: skip
    export_policy(model, str(tmp_path / "ckpt" / "exported"))
    (tmp_path / "ckpt" / "params").mkdir()
    train_cfg = {"env": {"episode": {"target_speeds": [3.0]}, "scene_memory": {"enabled": True, "bins": 8}},
                 "runner": {"class_name": "OnPolicyRunner", "obs_groups": groups}}  # fmt: skip
    (tmp_path / "ckpt" / "params" / "config.yaml").write_text(yaml.safe_dump(train_cfg))
    pol = E.load_policy(tmp_path / "ckpt", "mem")
    assert pol.info.obs_dim == 29 and pol.info.state_groups == ("state", "memory")
    assert pol.info.train_env == {"scene_memory": {"enabled": True, "bins": 8}}
    a, b = np.arange(6.0).reshape(2, 3), np.full((2, 2), 9.0)
    np.testing.assert_array_equal(pol.state_of({"state": a, "memory": b, "depth": None}), np.hstack((a, b)))
    with pytest.raises(E.EvalError, match=r"\['memory'\]"):
        pol.state_of({"state": a})
    # A distillation run's policy reads its student set.
    train_cfg["runner"]["class_name"] = "DistillationRunner"
    (tmp_path / "ckpt" / "params" / "config.yaml").write_text(yaml.safe_dump(train_cfg))
    assert E.load_policy(tmp_path / "ckpt", "mem").info.state_groups == ("state",)
    # Through the harness (PPO layout again): the env gets the memory section and the policy flies a short trial.
    train_cfg["runner"]["class_name"] = "OnPolicyRunner"
    (tmp_path / "ckpt" / "params" / "config.yaml").write_text(yaml.safe_dump(train_cfg))
    cfg = tiny_cfg("configurations=[mem]", "rows.mem.label=Mem", "rows.mem.policy=mem",
                   f"checkpoints.mem={tmp_path / 'ckpt'}", "trials_per_scene=1", "speeds=[3.0]",
                   "env_overrides=[episode.timeout_factor=0.05]")  # fmt: skip
    E.evaluate(cfg, str(tmp_path / "out"), progress=False)
    (trial,) = json.loads((tmp_path / "out" / "trials.json").read_text())
    assert trial["steps"] > 0


def test_policy_with_a_clock_input_gets_the_clock_of_the_evaluations_own_time_limit(tmp_path):
    """A policy trained with ``clock`` is flown with ``episode.clock_input`` on and the eval's timeout_factor kept."""
    torch = pytest.importorskip("torch")
    from tensordict import TensorDict

    from shield_nav.policies.export import export_policy
    from shield_nav.policies.models import DepthGRUModel

    torch.manual_seed(0)
    obs = TensorDict({"depth": torch.rand(2, 1, 60, 100), "state": torch.randn(2, 21), "clock": torch.rand(2, 1)}, [2])
    groups = {"actor": ["depth", "state", "clock"], "critic": ["critic"]}
    model = DepthGRUModel(obs, groups, "actor", 4, rnn_hidden_dim=16,
                          distribution_cfg={"class_name": "GaussianDistribution", "init_std": 0.5})  # fmt: skip
    export_policy(model, str(tmp_path / "ckpt" / "exported"))
    (tmp_path / "ckpt" / "params").mkdir()
    train_cfg = {"env": {"episode": {"target_speeds": [3.0], "timeout_factor": 2.5, "clock_input": True,
                                     "deadline": "terminate"}},
                 "runner": {"class_name": "OnPolicyRunner", "obs_groups": groups}}  # fmt: skip
    (tmp_path / "ckpt" / "params" / "config.yaml").write_text(yaml.safe_dump(train_cfg))
    pol = E.load_policy(tmp_path / "ckpt", "clk")
    assert pol.info.obs_dim == 22 and pol.info.state_groups == ("state", "clock")
    assert pol.info.train_env == {"episode": {"clock_input": True}}  # only the input, not the training limit
    cfg = tiny_cfg("configurations=[clk]", "rows.clk.label=Clock", "rows.clk.policy=clk",
                   f"checkpoints.clk={tmp_path / 'ckpt'}", "trials_per_scene=1", "speeds=[3.0]",
                   "env_overrides=[episode.timeout_factor=0.05]")  # fmt: skip
    nav = E.nav_config(cfg, cfg.scenes.family, cfg.scene_indices[0], 3.0, 1, pol.info.train_env)
    assert nav.episode.clock_input and nav.episode.timeout_factor == 0.05 and nav.episode.deadline == "truncate"
    E.evaluate(cfg, str(tmp_path / "out"), progress=False)
    (trial,) = json.loads((tmp_path / "out" / "trials.json").read_text())
    assert trial["steps"] > 0
    # Without its clock section (a config that lost it) the harness refuses the policy by the group's name.
    train_cfg["env"]["episode"].pop("clock_input")
    (tmp_path / "ckpt" / "params" / "config.yaml").write_text(yaml.safe_dump(train_cfg))
    with pytest.raises(E.EvalError, match=r"\['clock'\].*episode\.clock_input"):
        E.evaluate(cfg, str(tmp_path / "out2"), progress=False)


def test_multi_hypothesis_policy_gives_its_candidates_in_score_order_and_flies_behind_the_choosing_shield(tmp_path):
    """``step_hypotheses`` against the eager model's own candidates and scores; the harness flies the option."""
    torch = pytest.importorskip("torch")
    from tensordict import TensorDict

    from shield_nav.policies.export import export_policy
    from shield_nav.policies.models import DepthGRUModel

    torch.manual_seed(0)
    obs = TensorDict({"depth": torch.rand(2, 1, 60, 100), "state": torch.randn(2, 21)}, [2])
    model = DepthGRUModel(obs, {"actor": ["depth", "state"]}, "actor", 4, rnn_hidden_dim=16, num_hypotheses=3,
                          distribution_cfg={"class_name": "GaussianDistribution", "init_std": 0.5})  # fmt: skip
    with torch.no_grad():  # spread the scores so the order is not decided by rounding
        model.mlp[0][-1].bias[-3:] = torch.tensor([0.0, 2.0, 1.0])
    paths = export_policy(model, str(tmp_path / "ckpt" / "exported"))
    jit = E.load_policy(paths["jit"], "mh")
    assert jit.num_hypotheses() == 3
    rng = np.random.default_rng(1)
    state, depth = rng.normal(size=(5, 21)).astype(np.float32), rng.uniform(size=(5, 1, 60, 100)).astype(np.float32)
    h = rng.normal(size=(1, 5, 16)).astype(np.float32)
    chosen, others, h1 = jit.step_hypotheses(state, depth, h)
    act, h2 = jit.step(state, depth, h)
    np.testing.assert_array_equal(chosen, act)
    np.testing.assert_array_equal(h1, h2)
    # Independently: the eager export's GRU output through the MLP core, candidates sorted by descending score.
    exp = model.as_onnx()
    with torch.no_grad():
        x = torch.cat([exp.obs_normalizer(torch.from_numpy(state)), exp.encoder(torch.from_numpy(depth))], dim=-1)
        y, _ = exp.gru(x.unsqueeze(0), torch.from_numpy(h))
        hyps, scores = exp.mlp[1].split(exp.mlp[0](y.squeeze(0)))
    order = np.argsort(-scores.numpy(), axis=1)
    ranked = np.take_along_axis(hyps.numpy(), order[:, :, None], axis=1)
    assert others.shape == (5, 2, 4)
    np.testing.assert_allclose(chosen, ranked[:, 0], atol=1e-6)
    np.testing.assert_allclose(others, ranked[:, 1:], atol=1e-6)
    # The ONNX export holds the selection inside its graph: the option says what it needs, naming it.
    with pytest.raises(E.EvalError, match="'hypotheses' option needs a multi-hypothesis actor's TorchScript"):
        E.load_policy(paths["onnx"], "mh").step_hypotheses(state, depth, h)
    # Through the harness: the Full row behind the choosing shield records how often it flew another candidate. The
    # checkpoint folder is read through its TorchScript export; a single-head actor is refused before any flight.
    single = export_fresh_policy(str(tmp_path / "single"))
    for bad in (single["jit"], str(tmp_path / "single")):
        cfg = tiny_cfg("configurations=[full]", f"checkpoints.full={bad}", "shield.hypotheses=first_clean")
        with pytest.raises(E.EvalError, match="shield.hypotheses other than 'top'"):
            E.evaluate(cfg, str(tmp_path / "refused"), progress=False)
    cfg = tiny_cfg("configurations=[full]", f"checkpoints.full={tmp_path / 'ckpt'}", "trials_per_scene=1", "speeds=[3]",
                   "shield.hypotheses=first_clean", "env_overrides=[episode.timeout_factor=0.05]")  # fmt: skip
    E.evaluate(cfg, str(tmp_path / "out"), progress=False)
    man = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert man["checkpoints"]["full"]["path"].endswith("policy.pt")
    (trial,) = json.loads((tmp_path / "out" / "trials.json").read_text())
    assert trial["steps"] > 0 and 0 <= trial["shield"]["switched_steps"] <= trial["steps"]
