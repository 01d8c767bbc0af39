"""A run: prepare, plan units, run them (workers, resume, SIGTERM), summarise, write the outputs."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import hashlib
import json
import multiprocessing as mp
import os
import platform
import signal
import subprocess
import sys
import threading
import time
import warnings
from typing import Any

import yaml

from envs.config import stored_config, to_dict
from shield_nav.algorithms.baselines import BASELINES
from shield_nav.evaluation.config import (
    EVAL_FORMAT_VERSION,
    POLICY_CONTROLLERS,
    EvalConfig,
    EvalError,
    resolve_rows,
    row_shield_config,
)
from shield_nav.evaluation.metrics import aggregate
from shield_nav.evaluation.outcomes import write_outcomes
from shield_nav.evaluation.policies import POLICY_FILES, PolicyInfo, check_layout, load_policy, load_teacher
from shield_nav.evaluation.report import _header_lines, csv_table, detail_table, latex_table, paper_table
from shield_nav.evaluation.rollout import (
    Prepared,
    UnitSpec,
    _worker_init,
    nav_config,
    run_unit,
    scene_seed,
    unit_key,
)
from shield_nav.jsonio import json_default, write_json
from shield_nav.provenance import (
    cpu_model,
    cpu_simd,
    format_differences,
    manifest_record,
    numpy_simd_targets,
    package_versions,
    version_differences,
)


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
            if needed[pname] == "teacher":
                pol = load_teacher(cfg.checkpoints[pname], pname)
            else:
                pol = load_policy(cfg.checkpoints[pname], pname, network=cfg.network)
            choosing = [rn for rn, r in rows.items() if r.policy == pname and r.controller == "policy" and r.shield
                        and row_shield_config(cfg.shield, r, rn).hypotheses != "top"]  # fmt: skip
            if choosing:
                pol = _hypotheses_policy(pol, cfg.checkpoints[pname], pname, choosing)
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
            sizes = {"state": STATE_DIM, "memory": nav.scene_memory.bins if nav.scene_memory.enabled else None,
                     "clock": 1 if nav.episode.clock_input else None}  # fmt: skip
            unknown = [g for g in pol.info.state_groups if sizes.get(g) is None]
            if unknown:
                raise EvalError(f"checkpoint {pname!r} ({pol.info.path}) reads groups {unknown} its "
                                f"env does not give (known: state; memory with scene_memory.enabled; clock with "
                                f"episode.clock_input)")  # fmt: skip
            check_layout(pol.info, sum(sizes[g] for g in pol.info.state_groups), (1, cam.height, cam.width))
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


def _hypotheses_policy(pol: Any, path: str, name: str, rows: list[str]) -> Any:
    """The TorchScript export of ``pol`` when rows fly it behind a shield that chooses among its hypotheses.

    An ONNX export holds the choice inside its graph, so a checkpoint folder is read through its ``policy.pt``
    instead; a policy without candidates to choose from is an error naming the option, before any flight.
    """
    if pol.info.kind == "onnx" and os.path.isdir(path):
        for rel in (f for f in POLICY_FILES if f.endswith(".pt")):
            if os.path.isfile(os.path.join(path, rel)):
                pol = load_policy(os.path.join(path, rel), name)
                break
    if pol.num_hypotheses() < 2:
        what = "an ONNX export (give its policy.pt)" if pol.info.kind == "onnx" else "a single-head actor"
        raise EvalError(f"rows {rows} fly checkpoint {name!r} behind shield.hypotheses other than 'top', which needs "
                        f"a multi-hypothesis actor's TorchScript export; {pol.info.path} is {what}")  # fmt: skip
    return pol


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
        elif pol is None and not row.shield and not getattr(BASELINES[row.controller], "reads_depth", True):
            env = {"render_depth": False}  # reads no image and no shield in the loop: skip the ray casting
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


def _plain(x: Any) -> Any:
    """``x`` as the manifest's JSON holds it."""
    return json.loads(json.dumps(x, sort_keys=True, default=json_default))


def _added_default_keys(old: Any, new: Any, default: Any, path: str = "") -> list[str] | None:
    """Keys that ``new`` has and ``old`` lacks, each at its default value; None when the two differ otherwise.

    A folder written before a config field existed resumes under a config that leaves that field at its default
    (new fields default to the behaviour before them); any other difference is another run.
    """
    if not (isinstance(old, dict) and isinstance(new, dict)):
        return [] if old == new else None
    if set(old) - set(new):
        return None
    added: list[str] = []
    for key, value in new.items():
        dflt = default.get(key) if isinstance(default, dict) else None
        if key not in old:
            if value != dflt:
                return None
            added.append(path + key)
            continue
        sub = _added_default_keys(old[key], value, dflt, f"{path}{key}.")
        if sub is None:
            return None
        added += sub
    return added


def open_output(prep: Prepared, out_dir: str, argv: list[str] | None = None) -> None:
    """Create (or check, for resume) the output folder and its manifest: git revision, configs, checkpoint hashes."""
    os.makedirs(os.path.join(out_dir, "units"), exist_ok=True)
    ident = _identity(prep)
    digest = hashlib.sha256(json.dumps(ident, sort_keys=True, default=str).encode()).hexdigest()
    arithmetic = {"cpu_simd": cpu_simd(), "packages": package_versions(),  # what the flights' arithmetic ran on
                  "openblas_coretype": os.environ.get("OPENBLAS_CORETYPE"),
                  "numpy_simd": numpy_simd_targets()}  # fmt: skip
    man_path = os.path.join(out_dir, "manifest.json")
    if os.path.exists(man_path):
        with open(man_path) as f:
            old = json.load(f)
        added = None
        if old.get("identity_sha256") != digest and old.get("checkpoint_sha256") == ident["checkpoint_sha256"]:
            was = old.get("config")
            meant = _plain(stored_config(EvalConfig, was)) if isinstance(was, dict) else was  # as it ran
            added = _added_default_keys(meant, _plain(ident["config"]), _plain(to_dict(EvalConfig())))
            if added is not None:
                added += _added_default_keys(was, meant, meant) or []  # keys read with their earlier values
                print(f"[eval] resuming {out_dir!r}, written before these config keys existed (each at its "
                      f"default now, or at the value it had before): {', '.join(sorted(added))}",
                      file=sys.stderr)  # fmt: skip
        if old.get("identity_sha256") != digest and added is None:
            was_network = (
                stored_config(EvalConfig, old["config"]).get("network") if isinstance(old.get("config"), dict) else None
            )
            hint = (f" It was flown with network: {was_network}; add --set network={was_network} to resume it."
                    if was_network is not None and was_network != prep.cfg.network else "")  # fmt: skip
            raise EvalError(
                f"{out_dir!r} holds results of a different run (config, seed or checkpoints differ); resume needs "
                f"the same command. Use another --out or delete the folder.{hint}"
            )
        was_git, now_git = old.get("git") or {}, _git_info()
        if (was_git.get("rev"), was_git.get("diff_sha256", "")) != (now_git["rev"], now_git["diff_sha256"]):
            print(f"[eval] resuming {out_dir!r} with other code than its first units were flown with (git "
                  f"{str(was_git.get('rev'))[:12]}{' + diff' if was_git.get('dirty') else ''} then, "
                  f"{now_git['rev'][:12]}{' + diff' if now_git['dirty'] else ''} now): if the change moves flights, "
                  "the table mixes the two; the manifest keeps the first revision", file=sys.stderr)  # fmt: skip
        changed = version_differences(manifest_record(old), manifest_record(arithmetic))
        if changed:
            print(f"[eval] resuming {out_dir!r} with other package versions (or SIMD extensions) than its first units "
                  f"were flown with ({format_differences(changed)}): the units flown from now on may differ trial by "
                  "trial from what the first environment would have flown (docs/evaluation.md, 'Reproducing a table')",
                  file=sys.stderr)  # fmt: skip
        return
    manifest = {
        "format": EVAL_FORMAT_VERSION,
        "identity_sha256": digest,
        "created": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": argv if argv is not None else sys.argv,
        "git": _git_info(),
        "python": platform.python_version(),
        "machine": f"{platform.machine()} {os.cpu_count()} cpus",
        "cpu": cpu_model(),
        **arithmetic,
        "checkpoints": {k: dataclasses.asdict(v) for k, v in prep.policies.items()},
        "missing_rows": prep.missing,
        **ident,
    }
    write_json(man_path, manifest)
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
        write_json(os.path.join(unit_dir, res["key"] + ".json"), res)
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
        "scene_seed": scene_seed(prep.cfg),
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


def write_outputs(prep: Prepared, out_dir: str, units: list[UnitSpec]) -> dict:
    """Tables (md, csv, tex), trials.json, outcomes.csv.gz, summary.json and figures from the unit files on disk."""
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
    write_json(os.path.join(out_dir, "trials.json"), trials)
    write_outcomes(out_dir, results)
    write_json(os.path.join(out_dir, "summary.json"), summary)
    summary["markdown"] = md
    summary["paper_table"] = paper_table(prep, summary)
    summary["header"] = header
    if prep.cfg.plots and results:
        from shield_nav.evaluation import plots

        try:
            plots.write_figures(prep, summary, results, os.path.join(out_dir, "figures"))
        except Exception as err:  # a figure must never cost the tables
            print(f"WARNING: figures failed: {type(err).__name__}: {err}", flush=True)
    return summary
