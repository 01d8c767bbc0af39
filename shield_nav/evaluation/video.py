"""Videos of flights: re-fly a pinned trial and record it."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from shield_nav.evaluation.rollout import Prepared, _run_batch, nav_config, sample_trial, trial_seed
from shield_nav.evaluation.run import plan_units


def record_videos(prep: Prepared, out_dir: str, fps: int = 25, size: tuple[int, int] = (360, 640)) -> list[str]:
    """Re-fly trial 0 of the first scene at the top speed for every row and record it (issue #8, "watching a flight").

    A chase view from MuJoCo's offscreen renderer (``MUJOCO_GL=egl`` on a machine without a display) with the
    sensor depth image inset, the speed and the shield's activity written on each frame, saved as MP4 (imageio +
    imageio-ffmpeg) or, without them, as an animated GIF. If MuJoCo cannot render here, the fallback is an animated
    top-down plot of the same trial over the ESDF; the message says which one was written. The re-flown trial is
    the one in the tables (same seed, same pinned start and goal; the flight is deterministic).
    """
    from envs.navigation import NavigationEnv
    from shield_nav.evaluation import plots

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
