"""How closely does a depth student imitate its expert, and how does it miss? Per-dimension imitation metrics.

``python -m shield_nav.tools.imitation checkpoints/student [--speed 3] [--level 8] [--family F] [--steps 400] [--json]``

flies the student's own policy on its training scene family (the DAgger state distribution; training seeds only,
no evaluation scene is touched) at one target speed and curriculum level. It labels every visited state with the
expert the checkpoint was distilled from (``runner.expert``), and reports, per action dimension (thrust, roll,
pitch, yaw):

* ``mse``: the behaviour-cloning error, and ``expert_var``, the variance of the labels. ``1 - mse / expert_var``
  is the share of the expert's action variance the student explains.
* ``corr``: the correlation between the two actions. ``std_ratio`` is the student's action std over the expert's;
  below 1, the student is more timid than its expert.
* For roll and yaw, where the expert turns hard (``|a| > 0.3``):
  * ``wrong_sign``: how often the student turns the other way;
  * ``weak``: how often it turns the same way by less than half;
  * ``wrong_sign_mse_share``: the share of that dimension's error that comes from the wrong-sign samples.

A large wrong-sign share means the student and its expert chose different sides around obstacles. Averaging the
two sides is the failure a multi-hypothesis head addresses (:mod:`shield_nav.algorithms.distillation`).

For a multi-hypothesis student (``actor.num_hypotheses`` K > 1) a ``selection`` section reads its candidate choice
(:func:`selection_metrics`): how often the flown (best-scored) candidate is the one nearest the expert's label
(``nearest_share``; 1/K is chance), the error of the flown candidate against the nearest one's (``chosen_mse``,
``nearest_mse``; their gap is what a perfect choice would gain), the median lead of the best score over the second
(``score_gap_median``, in logits), and how often the flown candidate changes from one 10 ms step to the next
(``switch_rate``), with the mean jump of the flown action on those steps and on the others.

With the planning expert the samples are also split by the expert's route
(:func:`shield_nav.tools.route_view.route_away`): steps where the route 3 m ahead lies more than 45 deg off the goal's
bearing (``away``: a way the goal's direction does not suggest, chosen by the map beyond the view) and the rest
(``toward``), each with the same metrics. ``--family`` flies another training family, e.g. the box fields of
``train_shapes_perlin`` (indices 16-23).
"""

from __future__ import annotations

from shield_nav.openmp import limit_spinning

if __name__ == "__main__":  # run as a tool: as train.py does, before torch and numba load libgomp
    limit_spinning()

import argparse
import json
import os

import numpy as np

from shield_nav.algorithms.expert import PlannerController
from shield_nav.tools.route_view import route_away

ACTION_NAMES = ("thrust", "roll", "pitch", "yaw")
HARD_TURN = 0.3
"""``|expert action| > HARD_TURN`` counts as a hard turn (normalised action units)."""


def gap_metrics(student: np.ndarray, expert: np.ndarray) -> dict:
    """Imitation metrics of student actions against expert labels, both ``(..., 4)`` (see the module docstring)."""
    s = np.asarray(student, dtype=np.float64).reshape(-1, 4)
    e = np.asarray(expert, dtype=np.float64).reshape(-1, 4)
    if s.shape != e.shape or len(s) < 2:
        raise ValueError(f"need matching (..., 4) arrays with >= 2 samples, got {student.shape} and {expert.shape}")
    if not (np.isfinite(s).all() and np.isfinite(e).all()):
        raise ValueError("student and expert actions must be finite")
    err = (s - e) ** 2
    out: dict = {"samples": len(s), "mse": float(err.mean()), "per_dim": {}}
    for k, name in enumerate(ACTION_NAMES):
        sd_s, sd_e = s[:, k].std(), e[:, k].std()
        row = {
            "mse": float(err[:, k].mean()),
            "expert_var": float(sd_e**2),
            "bias": float((s[:, k] - e[:, k]).mean()),
            "corr": float(np.corrcoef(s[:, k], e[:, k])[0, 1]) if sd_s > 0 and sd_e > 0 else float("nan"),
            "std_ratio": float(sd_s / sd_e) if sd_e > 0 else float("nan"),
        }
        if name in ("roll", "yaw"):
            hard = np.abs(e[:, k]) > HARD_TURN
            same = np.sign(s[:, k]) == np.sign(e[:, k])
            wrong = hard & ~same
            weak = hard & same & (np.abs(s[:, k]) < 0.5 * np.abs(e[:, k]))
            n_hard = max(int(hard.sum()), 1)
            row.update(
                hard_turn_share=float(hard.mean()),
                wrong_sign=float(wrong.sum() / n_hard),
                weak=float(weak.sum() / n_hard),
                wrong_sign_mse_share=float(err[wrong, k].sum() / max(err[:, k].sum(), 1e-12)),
            )
        out["per_dim"][name] = row
    return out


def selection_metrics(cands: np.ndarray, scores: np.ndarray, expert: np.ndarray, dones: np.ndarray) -> dict:
    """How a multi-hypothesis student chooses among its candidates, over a closed-loop flight.

    Args:
        cands: Candidate actions ``(T, N, K, A)`` at each of ``T`` steps of ``N`` envs.
        scores: Their scores ``(T, N, K)``; the flown candidate is the best-scored one (the first on ties, as
            :class:`shield_nav.policies.models.HypothesisSelect`).
        expert: The expert's labels ``(T, N, A)``.
        dones: ``(T, N)``: env ``n``'s episode ended at step ``t`` (step ``t + 1`` starts a new one, so a change of
            candidate across it is not counted).

    Returns:
        ``nearest_share`` (the flown candidate has the smallest squared error to the label; ties count for it),
        ``chosen_mse`` / ``nearest_mse`` / ``uniform_mse`` (mean squared error per action value of the flown, the
        nearest, and a uniformly drawn candidate), ``score_gap_median`` and ``score_gap_below_0_5`` (the best score
        minus the second), ``switch_rate`` (steps whose flown candidate differs from the previous step's, over the
        steps that have a previous step in the same episode), ``jump_switch`` / ``jump_stay`` (mean Euclidean change
        of the flown action on those steps with / without a change; NaN where there are none) and ``share`` (how
        often each candidate is flown).
    """
    c = np.asarray(cands, dtype=np.float64)
    sc = np.asarray(scores, dtype=np.float64)
    e = np.asarray(expert, dtype=np.float64)
    d = np.asarray(dones, dtype=bool)
    if c.ndim != 4 or sc.shape != c.shape[:3] or e.shape != c.shape[:2] + c.shape[3:] or d.shape != c.shape[:2]:
        raise ValueError(f"need cands (T, N, K, A), scores (T, N, K), expert (T, N, A), dones (T, N); got "
                         f"{c.shape}, {sc.shape}, {e.shape}, {d.shape}")  # fmt: skip
    if c.shape[2] < 2:
        raise ValueError(f"selection metrics need K >= 2 candidates, got {c.shape[2]}")
    if not (np.isfinite(c).all() and np.isfinite(sc).all() and np.isfinite(e).all()):
        raise ValueError("candidates, scores and expert labels must be finite")
    k = c.shape[2]
    err = ((c - e[:, :, None, :]) ** 2).mean(axis=-1)  # (T, N, K)
    chosen = sc.argmax(axis=-1)  # (T, N)
    err_chosen = np.take_along_axis(err, chosen[..., None], axis=-1)[..., 0]
    top2 = np.sort(sc, axis=-1)[..., -2:]
    gap = top2[..., 1] - top2[..., 0]
    flown = np.take_along_axis(c, chosen[..., None, None], axis=2)[:, :, 0]  # (T, N, A)
    same_episode = ~d[:-1]  # step t + 1 continues step t's episode
    changed = (chosen[1:] != chosen[:-1]) & same_episode
    jump = np.linalg.norm(flown[1:] - flown[:-1], axis=-1)
    stay = same_episode & ~changed
    return {
        "samples": int(err_chosen.size),
        "candidates": k,
        "nearest_share": float((err_chosen <= err.min(axis=-1)).mean()),
        "chosen_mse": float(err_chosen.mean()),
        "nearest_mse": float(err.min(axis=-1).mean()),
        "uniform_mse": float(err.mean()),
        "score_gap_median": float(np.median(gap)),
        "score_gap_below_0_5": float((gap < 0.5).mean()),
        "switch_rate": float(changed.sum() / max(int(same_episode.sum()), 1)),
        "jump_switch": float(jump[changed].mean()) if changed.any() else float("nan"),
        "jump_stay": float(jump[stay].mean()) if stay.any() else float("nan"),
        "share": [float(v) for v in np.bincount(chosen.ravel(), minlength=k) / chosen.size],
    }


def measure(ckpt: str, speed: float = 3.0, level: int = 8, steps: int = 400, num_envs: int = 32, seed: int = 0,
            family: str | None = None) -> dict:  # fmt: skip
    """Fly the student of ``ckpt`` ``steps`` steps in ``num_envs`` envs of its training family: :func:`gap_metrics`.

    ``family``: another training family to fly instead (``level`` is then that family's scene index, at its default
    seed), e.g. ``train_shapes_perlin`` for box fields a student never trained on.
    """
    import torch

    from shield_nav.training import make_env
    from shield_nav.training.actor import actor_from_checkpoint

    path = os.path.join(ckpt, "model.pt") if os.path.isdir(ckpt) else ckpt
    model, cfg, meta = actor_from_checkpoint(path)
    if model is None:
        raise ValueError(f"{path}: not a depth student")
    if not cfg.runner.expert.kind:
        raise ValueError(f"{path}: the checkpoint was not distilled from a scripted expert (runner.expert.kind)")
    if family is not None:
        from envs.scenes import FAMILIES
        from envs.scenes.families import is_training_family

        if family not in FAMILIES or not is_training_family(family):
            train = sorted(f for f in FAMILIES if is_training_family(f))
            raise ValueError(f"--family must be a training family ({', '.join(train)}), got {family!r}")
        cfg.env.scenes.family, cfg.env.scenes.seed = family, None
        cfg.env.scenes.indices = list(range(FAMILIES[family].size))
    if not 0 <= level < len(cfg.env.scenes.indices):
        raise ValueError(f"level must be in [0, {len(cfg.env.scenes.indices)}), got {level}")
    scene = cfg.env.scenes.indices[level]
    cfg.env.num_envs = num_envs
    cfg.env.episode.target_speeds = [float(speed)]
    cfg.env.episode.speed_range = []
    cfg.env.seed = seed  # starts, goals and randomization
    # The env holds this one scene, so every episode flies it whether or not the checkpoint trained with the
    # curriculum (without it, setting the level alone left resets to sample the whole list).
    cfg.env.scenes.indices = [scene]
    env = make_env(cfg)
    env.set_curriculum_levels([0] * num_envs)
    obs = env.get_observations()
    planner = getattr(env.expert, "controller", None)
    planner = planner if isinstance(planner, PlannerController) else None
    student, expert, away = [], [], []
    multi = getattr(model, "num_hypotheses", 1) > 1
    cands, scores, ended = [], [], []
    with torch.no_grad():
        for _ in range(steps):
            act = model(obs)
            student.append(act.numpy().copy())
            expert.append(obs["expert"].numpy().copy())
            if multi:  # the head's candidates and scores of this forward pass (DepthGRUModel keeps them)
                cands.append(model.last_hypotheses.numpy().copy())
                scores.append(model.last_scores.numpy().copy())
            if planner is not None:  # the route the label was computed on (the expert ran on this observation)
                away.append(route_away(planner.last["path"], env.env.goal_buf - env.env.local_pos))
            obs, _, dones, _ = env.step(act)
            model.reset(dones)
            ended.append(dones.numpy().astype(bool))
    out = gap_metrics(np.array(student), np.array(expert))
    if multi:
        out["selection"] = selection_metrics(np.array(cands), np.array(scores), np.array(expert), np.array(ended))
    if planner is not None:
        # Split by where the expert's route goes: more than 45 deg off the goal's bearing 3 m along (a way the goal's
        # direction does not suggest, chosen by the map beyond the view) or not.
        s, e, a = np.concatenate(student), np.concatenate(expert), np.concatenate(away)
        out["away_share"] = float(a.mean())
        out["split"] = {k: gap_metrics(s[m], e[m]) for k, m in (("away", a), ("toward", ~a)) if m.sum() >= 2}
    out.update(
        checkpoint=path,
        iteration=meta["iter"],
        speed=speed,
        level=level,
        steps=steps,
        num_envs=num_envs,
        scene=f"{cfg.env.scenes.family}/{scene}",
    )
    return out


def format_table(res: dict) -> str:
    """Markdown table of :func:`gap_metrics` output."""
    lines = ["| action | MSE | expert var | explained | corr | std ratio | hard turns | wrong sign | weak |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for name, r in res["per_dim"].items():
        expl = 1.0 - r["mse"] / r["expert_var"] if r["expert_var"] > 0 else float("nan")
        extra = [f"{100 * r[k]:.0f} %" for k in ("hard_turn_share", "wrong_sign", "weak")] if "weak" in r else [""] * 3
        lines.append(f"| {name} | {r['mse']:.4f} | {r['expert_var']:.4f} | {100 * expl:.0f} % | {r['corr']:.2f} | "
                     f"{r['std_ratio']:.2f} | " + " | ".join(extra) + " |")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point."""
    ap = argparse.ArgumentParser(prog="python -m shield_nav.tools.imitation", description=__doc__.split("\n")[0])
    ap.add_argument("checkpoint", help="checkpoint folder (checkpoints/<name>) or model_*.pt of a DAgger student")
    ap.add_argument("--speed", type=float, default=3.0, help="target speed [m/s] (default 3)")
    ap.add_argument("--level", type=int, default=8, help="curriculum level = training scene index (default 8)")
    ap.add_argument("--steps", type=int, default=400, help="policy steps of 10 ms (default 400)")
    ap.add_argument("--num-envs", type=int, default=32, help="parallel envs (default 32)")
    ap.add_argument(
        "--family",
        default=None,
        help="fly this training family instead of the checkpoint's (--level = its scene index)",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true", help="print one JSON line instead of a table")
    args = ap.parse_args(argv)
    if not (os.path.isfile(args.checkpoint) or os.path.isfile(os.path.join(args.checkpoint, "model.pt"))):
        ap.error(f"no checkpoint at {args.checkpoint!r} (a checkpoints/<name> folder or a model_*.pt)")
    if args.steps < 2 or args.num_envs < 1 or args.speed <= 0:
        ap.error(f"need --steps >= 2, --num-envs >= 1 and --speed > 0, got {args.steps}, {args.num_envs}, {args.speed}")
    try:
        res = measure(args.checkpoint, args.speed, args.level, args.steps, args.num_envs, args.seed, args.family)
    except ValueError as err:
        ap.error(str(err))
    if args.json:
        print(json.dumps(res))
    else:
        print(f"{res['checkpoint']} (iteration {res['iteration']}), {res['speed']:g} m/s, level {res['level']} "
              f"({res['scene']}), {res['samples']} samples: MSE {res['mse']:.4f}")  # fmt: skip
        print(format_table(res))
        for key, sub in res.get("split", {}).items():
            share = res["away_share"] if key == "away" else 1.0 - res["away_share"]
            where = "away from" if key == "away" else "toward"
            print(f"\nsteps where the expert's route turns {where} the goal ({100 * share:.0f} % of samples, "
                  f"{sub['samples']}): MSE {sub['mse']:.4f}")  # fmt: skip
            print(format_table(sub))
        sel = res.get("selection")
        if sel is not None:
            print(f"\ncandidate choice ({sel['candidates']} candidates): the flown one is the nearest to the label on "
                  f"{100 * sel['nearest_share']:.0f} % of samples (chance {100 / sel['candidates']:.0f} %); MSE flown "
                  f"{sel['chosen_mse']:.4f}, nearest {sel['nearest_mse']:.4f}, uniform pick {sel['uniform_mse']:.4f}; "
                  f"best score leads the second by {sel['score_gap_median']:.2f} (median, logits); the flown "
                  f"candidate changes on {100 * sel['switch_rate']:.1f} % of steps, the action then jumping "
                  f"{sel['jump_switch']:.2f} (otherwise {sel['jump_stay']:.2f})")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
