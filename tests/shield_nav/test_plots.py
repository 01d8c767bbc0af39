"""Trajectory figures of a finished eval output (shield_nav/evaluation/plots.py): what is drawn, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from PIL import Image

from envs.config import to_dict
from shield_nav.evaluation.config import load_eval_config
from shield_nav.evaluation.plots import main, trajectory_figures


def image_size(path):
    """(width, height) of a PNG, the file closed again."""
    with Image.open(path) as im:
        return im.size


def _folder(tmp_path):
    """An output folder of the default eval config with two units of ablation scene 0 (3 and 5 m/s), by hand."""
    cfg = load_eval_config()
    tmp_path.mkdir()
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    (tmp_path / "units").mkdir()
    k = np.arange(50)[:, None]
    straight = np.hstack([5.0 + 0.3 * k, np.full_like(k, 0.0), np.full_like(k, 1.5), np.full_like(k, 3.0)])
    for speed in (3.0, 5.0):
        goal = [25.0, 0.0, 1.5]
        unit = {"row": "full", "family": "ablation", "scene": 0, "speed": speed,
                "summary": {"success_rate": 0.5, "n": 2},
                "trials": [{"outcome": "success", "goal": goal, "traj": straight.tolist()},
                           {"outcome": "collision", "goal": goal, "traj": straight[:20].tolist()}]}  # fmt: skip
        (tmp_path / "units" / f"full__ablation-00__v{speed:g}.json").write_text(json.dumps(unit))
    (tmp_path / "summary.json").write_text(json.dumps({"rows": {"full": {"label": "Full"}}}))
    return tmp_path


def test_one_figure_per_scene_with_a_panel_per_unit_and_the_cli(tmp_path, capsys):
    out = _folder(tmp_path / "run")
    one = trajectory_figures(str(out), [0], speeds=[3.0], dest=str(tmp_path / "a"))
    assert one == [str(tmp_path / "a" / "trajectories_ablation-00_v3.png")]
    both = trajectory_figures(str(out), [0], dest=str(tmp_path / "b"))
    assert both == [str(tmp_path / "b" / "trajectories_ablation-00_v3_v5.png")]
    h1, h2 = image_size(one[0])[1], image_size(both[0])[1]
    assert 1.8 * h1 < h2 < 2.2 * h1  # two panels stacked, each as tall as the one-panel figure's
    main([str(out), "--scenes", "0", "--rows", "full"])
    assert capsys.readouterr().out.strip() == str(out / "figures" / "trajectories_ablation-00_v3_v5.png")
    assert (out / "figures" / "trajectories_ablation-00_v3_v5.png").stat().st_size > 10_000


def test_what_was_not_flown_is_named(tmp_path):
    out = _folder(tmp_path / "run")
    with pytest.raises(ValueError, match=r"scene\(s\) \[4\] not flown there; flown: \[0\]"):
        trajectory_figures(str(out), [4])
    with pytest.raises(ValueError, match=r"speed\(s\) \[7.0\]"):
        trajectory_figures(str(out), [0], speeds=[7.0])
    with pytest.raises(ValueError, match=r"row\(s\) \['expert'\]"):
        trajectory_figures(str(out), [0], rows=["expert"])
    (out / "units" / "full__ablation-00__v5.json").rename(out / "units" / "full__ablation-01__v5.json")
    unit = json.loads((out / "units" / "full__ablation-01__v5.json").read_text())
    (out / "units" / "full__ablation-01__v5.json").write_text(json.dumps({**unit, "scene": 1}))
    with pytest.raises(ValueError, match=r"scene 0 was not flown at speeds \[5.0\]"):
        trajectory_figures(str(out), [0], speeds=[5.0])  # 5 m/s was flown, but in scene 1 only
    with pytest.raises(FileNotFoundError, match="config.yaml"):
        trajectory_figures(str(tmp_path), [0])
    with pytest.raises(SystemExit):
        main([str(out), "--scenes", "a"])


def test_two_folders_stack_their_panels_and_name_a_shared_row_by_folder(tmp_path, monkeypatch):
    a, b = _folder(tmp_path / "a"), _folder(tmp_path / "b")
    one = trajectory_figures(str(a), [0], speeds=[3.0], dest=str(tmp_path / "one"))
    two = trajectory_figures([str(a), str(b)], [0], speeds=[3.0], dest=str(tmp_path / "two"))
    h1, h2 = image_size(one[0])[1], image_size(two[0])[1]
    assert 1.8 * h1 < h2 < 2.2 * h1  # a panel from each folder
    import shield_nav.evaluation.plots as plots

    drawn = []
    monkeypatch.setattr(plots, "plot_trajectories", lambda scene, fields, units, *a, **k: drawn.append(units))
    trajectory_figures([str(a), str(b)], [0], speeds=[3.0, 5.0], dest=str(tmp_path / "three"))
    # Folder order first, then row and speed; row 'full' was flown in both, so each label names its folder.
    assert [u["label"] for u in drawn[0]] == ["Full (a)", "Full (a)", "Full (b)", "Full (b)"]
    assert [u["speed"] for u in drawn[0]] == [3.0, 5.0, 3.0, 5.0]


def test_folders_that_flew_another_scene_cannot_share_a_figure(tmp_path):
    a, b = _folder(tmp_path / "a"), _folder(tmp_path / "b")
    cfg = yaml.safe_load((b / "config.yaml").read_text())
    cfg["scenes"]["seed"] = 1_234_567  # the same index drawn from another (validation) generator seed
    (b / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    with pytest.raises(ValueError, match="flew another scene as ablation 0"):
        trajectory_figures([str(a), str(b)], [0])


def test_xlim_draws_part_of_the_scene_and_bad_limits_are_named(tmp_path):
    out = _folder(tmp_path / "run")
    whole = trajectory_figures(str(out), [0], speeds=[3.0], dest=str(tmp_path / "w"))
    part = trajectory_figures(str(out), [0], speeds=[3.0], dest=str(tmp_path / "p"), xlim=(0.0, 20.0))
    (w1, h1), (w2, h2) = image_size(whole[0]), image_size(part[0])
    assert w1 == w2 and h2 > 1.5 * h1  # a third of the scene's 64 m drawn as wide: taller
    for bad in ((5.0, 5.0), (0.0, float("nan")), (1.0,)):
        with pytest.raises(ValueError, match="xlim"):
            trajectory_figures(str(out), [0], xlim=bad)
    with pytest.raises(SystemExit):
        main([str(out), "--scenes", "0", "--xlim", "0,a"])
    with pytest.raises(SystemExit):
        main([str(out), "--scenes", "0", "--xlim", "9,3"])
