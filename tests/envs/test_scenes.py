"""Scene model and families: determinism, serialisation, MuJoCo/trimesh conversion, seed split, bad input."""

import json
import math

import mujoco
import numpy as np
import pytest

from envs.scenes import (
    EVAL_SEEDS,
    FAMILIES,
    TRAIN_SEEDS,
    Box,
    Cylinder,
    MovingObstacle,
    Scene,
    Sphere,
    is_training_family,
    make_scene,
)
from envs.scenes import composites as C
from envs.scenes.families import _perlin_passable
from envs.scenes.sdf import primitive_sdf, union_sdf


def test_family_sizes_match_the_paper():
    assert {k: f.size for k, f in FAMILIES.items()} == {
        "train": 16, "train_shapes": 16, "ablation": 8, "benchmark": 16, "dynamic": 4, "forest": 4, "traps": 8,
        "train_traps": 16, "train_shapes_perlin": 24,
    }  # fmt: skip


def test_make_scene_is_deterministic_and_index_dependent():
    a, b = make_scene("ablation", 2), make_scene("ablation", 2)
    assert a == b and a.digest() == b.digest()
    # A fresh generation (bypassing the cache) gives the same content.
    from envs.scenes.families import _make_scene_cached

    assert _make_scene_cached.__wrapped__("ablation", 2, a.seed).digest() == a.digest()
    assert make_scene("ablation", 3).digest() != a.digest()
    assert make_scene("ablation", 2, seed=a.seed + 1).digest() != a.digest()


def test_json_round_trip(tmp_path):
    s = make_scene("dynamic", 1)
    assert Scene.from_dict(json.loads(json.dumps(s.to_dict()))) == s
    s.save(tmp_path / "s.json")
    assert Scene.load(tmp_path / "s.json").digest() == s.digest()


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_every_family_compiles_in_mujoco_and_trimesh(family):
    fam = FAMILIES[family]
    for index in (0, fam.size - 1):
        s = make_scene(family, index)
        assert s.family == family and s.index == index
        model = mujoco.MjModel.from_xml_string(s.to_mjcf())
        assert model.ngeom == len(s.primitives) + int(s.floor) + int(s.ceiling) + len(s.moving)
        assert model.nmocap == len(s.moving)
        mesh_scene = s.to_trimesh()
        assert len(mesh_scene.geometry) == len(s.primitives) + len(s.moving)
        lo, hi = mesh_scene.bounds
        assert np.all(lo >= np.array(s.bounds_lo) - 1e-6) and np.all(hi <= np.array(s.bounds_hi) + 1e-6)


def test_difficulty_rises_with_index_in_train():
    counts = [len(make_scene("train", i).primitives) for i in range(16)]
    assert counts[-1] > 4 * counts[0]
    assert np.all(np.diff(counts[::3]) > 0)


def test_train_uses_only_trees_and_cylinders():
    kinds = {p.kind for i in (0, 15) for p in make_scene("train", i).primitives}
    assert kinds <= {"cylinder", "capsule", "sphere"}  # trunks, cylinders; canopies are capsules/spheres


def test_train_shapes_has_every_kind_and_the_train_density_ramp():
    scenes = [make_scene("train_shapes", i) for i in range(16)]
    counts = [len(s.primitives) for s in scenes]
    assert counts[-1] > 4 * counts[0] and np.all(np.diff(counts[::3]) > 0)
    top = scenes[-1].primitives
    assert {p.kind for p in top} == {"cylinder", "capsule", "box", "sphere"}
    # Thin poles (r < 0.08 m) and inclined segments, which the paper's training family never has.
    assert any(p.kind in ("cylinder", "capsule") and p.radius < 0.08 for p in top)
    axes = [np.subtract(p.p1, p.p0) for p in top if p.kind == "cylinder"]
    assert any(0.2 < abs(a[2]) / np.linalg.norm(a) < 0.99 for a in axes)
    # U-traps (round(-1 + 5u)) from level 5 and dead ends (round(-0.5 + 2.5u)) from level 8, three 0.2 m thick
    # walls each (half-thickness exactly 0.1; free-standing walls draw theirs from U(0.08, 0.15)):
    # level 4 (u = 0.27): 0 + 0; level 5 (u = 0.33): 1 + 0; level 8 (u = 0.53): 2 + 1; level 15: 4 + 2.
    for i, traps in ((4, 0), (5, 1), (8, 3), (15, 6)):
        trap_walls = [p for p in scenes[i].primitives if p.kind == "box" and min(p.half[:2]) == 0.1]
        assert len(trap_walls) == 3 * traps


def test_ablation_scenes_contain_u_traps_and_dead_ends():
    for i in range(8):
        boxes = [p for p in make_scene("ablation", i).primitives if p.kind == "box"]
        # Only U-traps/dead ends make boxes here: at least (2 + i//3) traps + (1 + i//4) dead ends, 3 walls each.
        assert len(boxes) >= 3 * ((2 + i // 3) + (1 + i // 4))


def test_traps_block_the_straight_route_with_cups_facing_the_start():
    """``traps``: >= 8 cups (three 0.2 m walls each, the only boxes), closed end downstream, and most straight
    start-to-goal lines run into a cup's back wall (checked with the walls' own SDF along 61 lines per scene)."""
    ys = np.linspace(-15.0, 15.0, 61)
    xs = np.arange(0.0, 64.0, 0.05)
    for i in range(8):
        scene = make_scene("traps", i)
        boxes = [p for p in scene.primitives if p.kind == "box"]
        assert len(boxes) % 3 == 0 and len(boxes) >= 3 * 8
        assert all(min(b.half[:2]) == pytest.approx(0.1) for b in boxes)
        # Wall triples in u_trap order: back, left, right; the back wall is downstream of the side walls.
        backs = [boxes[k] for k in range(0, len(boxes), 3)]
        for k in range(0, len(boxes), 3):
            assert boxes[k].center[0] > max(boxes[k + 1].center[0], boxes[k + 2].center[0])
        blocked = 0
        for y in ys:
            pts = np.stack([xs, np.full_like(xs, y), np.full_like(xs, 1.5)], axis=1)
            blocked += any((primitive_sdf(b, pts) < 0).any() for b in backs)
        assert blocked / len(ys) >= 0.6, (i, blocked)


def test_benchmark_has_12_geometric_and_4_perlin_scenes():
    for i in range(16):
        kinds = {p.kind for p in make_scene("benchmark", i).primitives}
        if i >= 12:
            assert kinds == {"box"}
        else:
            assert {"cylinder", "box"} <= kinds


def test_train_shapes_perlin_is_the_all_shapes_levels_then_perlin_fields():
    # Indices 0-15 come from the all-shapes generator (its own random stream: the same kinds and counts as
    # train_shapes at that level), 16-23 are fields of box columns whose occupancy rises with the index.
    for i in (0, 9, 15):
        mixed, shapes = make_scene("train_shapes_perlin", i), make_scene("train_shapes", i)
        assert mixed.digest() != shapes.digest()
        assert abs(len(mixed.primitives) - len(shapes.primitives)) <= 0.1 * len(shapes.primitives) + 2
    fields = [make_scene("train_shapes_perlin", i) for i in range(16, 24)]
    assert all({p.kind for p in s.primitives} == {"box"} for s in fields)
    volume = [sum(8 * np.prod(p.half) for p in s.primitives) for s in fields]
    assert volume[-1] > volume[0]
    with pytest.raises(ValueError, match="seed range"):
        make_scene("train_shapes_perlin", 16, seed=EVAL_SEEDS.start)


def test_train_and_eval_seeds_are_disjoint_and_enforced():
    assert set(TRAIN_SEEDS).isdisjoint(range(EVAL_SEEDS.start, EVAL_SEEDS.stop))
    training = {"train", "train_shapes", "train_traps", "train_shapes_perlin"}
    for name, fam in FAMILIES.items():
        allowed = TRAIN_SEEDS if name in training else EVAL_SEEDS
        assert fam.default_seed in allowed and (fam.split == "train") == (name in training)
        assert is_training_family(name) == (name in training)
    with pytest.raises(ValueError, match="seed range"):
        make_scene("train", 0, seed=EVAL_SEEDS.start)
    with pytest.raises(ValueError, match="seed range"):
        make_scene("benchmark", 0, seed=0)
    with pytest.raises(ValueError, match="seed range"):
        make_scene("train_shapes", 0, seed=EVAL_SEEDS.start)
    with pytest.raises(ValueError, match="seed range"):
        make_scene("train_traps", 0, seed=EVAL_SEEDS.start)
    train = {make_scene(f, i).digest() for f in ("train", "train_shapes", "train_traps") for i in range(16)}
    assert len(train) == 48
    evals = {make_scene(f, i).digest() for f in ("ablation", "benchmark", "traps") for i in range(FAMILIES[f].size)}
    assert train.isdisjoint(evals)


def test_bad_family_and_index_name_the_problem():
    with pytest.raises(ValueError, match="unknown scene family 'nope'"):
        make_scene("nope", 0)
    with pytest.raises(ValueError, match="index 8 out of range.*ablation"):
        make_scene("ablation", 8)
    with pytest.raises(ValueError, match="index -1 out of range"):
        make_scene("train", -1)


def test_bad_scene_files_name_the_problem(tmp_path):
    d = Scene(primitives=(Sphere((10, 0, 1), 0.5),)).to_dict()
    d["primitives"][0]["radius"] = -0.5
    with pytest.raises(ValueError, match=r"primitive 0: sphere.radius must be a positive"):
        Scene.from_dict(d)
    d["primitives"][0].update(radius=0.5, center=[70.0, 0.0, 1.0])
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(d))
    with pytest.raises(ValueError, match=r"bad.json.*primitive 0 \(sphere\) lies outside the scene bounds"):
        Scene.load(path)
    d["primitives"] = []
    d["colour"] = "red"
    with pytest.raises(ValueError, match="unknown scene key"):
        Scene.from_dict(d)


def test_moving_positions_bounce_hand_computed():
    # x bounds 0..10, radius 1: the axis stays in [1, 9] (span 8). Start x=2, vx=3 m/s.
    # t=1: 5. t=3: 2+9=11 -> reflected off 9: 7. t=6: reaches 9 at 7/3 s, back at 1 at 5 s, then 3 m: 4.
    mob = MovingObstacle(Cylinder((2, 0, 0), (2, 0, 2), 1.0), (3.0, 0.0))
    s = Scene(bounds_lo=(0, -5, 0), bounds_hi=(10, 5, 2), moving=(mob,))
    xs = s.moving_positions(np.array([0.0, 1.0, 3.0, 6.0]))[:, 0, 0]
    np.testing.assert_allclose(xs, [2, 5, 7, 4])
    assert s.moving_positions(1.0).shape == (1, 3)
    np.testing.assert_allclose(s.moving_positions(1.0)[0], [5, 0, 0])


def test_mjcf_offset_translates_geoms():
    s = Scene(bounds_lo=(0, -2, 0), bounds_hi=(4, 2, 3), primitives=(Box((2, 0, 1), (0.5, 0.5, 0.5)),))
    m = mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{s.to_mjcf_geoms(offset=(100, 0, 0))}</worldbody></mujoco>")
    np.testing.assert_allclose(m.geom("obs0").pos, [102, 0, 1])
    np.testing.assert_allclose(m.geom("floor").pos, [102, 0, -0.05])


def test_analytic_sdf_hand_values():
    pts = np.array([[3.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 4.0]])
    # Vertical cylinder r=1 from z=0 to 2: side distance 2, inside depth min(1, 1) = -1, above the cap 2.
    np.testing.assert_allclose(primitive_sdf(Cylinder((0, 0, 0), (0, 0, 2), 1.0), pts), [2.0, -1.0, 2.0])
    # Rotated box (45 deg about z), half extents 1: the point (3, 0) is 3 - sqrt(2) from the corner.
    b = Box((0, 0, 1), (1, 1, 1), C.yaw_quat(math.pi / 4))
    np.testing.assert_allclose(primitive_sdf(b, pts[:1]), [3.0 - math.sqrt(2.0)])
    assert union_sdf([], pts).tolist() == [math.inf] * 3


def test_u_trap_is_a_cup_open_towards_the_start():
    prims, _ = C.u_trap(10.0, 0.0, 2.0, 3.0, 0.0, 0.0, 3.0)
    inside = np.array([10.0, 0.0, 1.5])

    def blocked(direction):
        ts = np.linspace(0, 5, 501)[:, None]
        return bool((union_sdf(prims, inside + ts * np.asarray(direction)) <= 0).any())

    assert blocked([1, 0, 0]) and blocked([0, 1, 0]) and blocked([0, -1, 0])
    assert not blocked([-1, 0, 0])


def test_perlin_passability_check():
    occ = np.zeros((10, 10), dtype=bool)
    occ[5, :] = True  # a full wall across y
    assert not _perlin_passable(occ)
    occ[5, 4:6] = False  # a 1 m gap: clearance 0.5 m > 0.35
    assert _perlin_passable(occ)
    occ[5, 5] = True  # 0.5 m gap: clearance 0.25 m, too narrow
    assert not _perlin_passable(occ)


def test_bottleneck_clearance_by_hand():
    """Two routes from x = 0 to x = 9 on a 1 m grid: one through a node of ESDF 0.8, one through 0.5; the widest
    route's clearance is 0.8 (to the bisection's tolerance), and 0 when no route is free."""
    from envs.scenes.stats import bottleneck_clearance

    esdf = np.full((10, 5, 1), -1.0)
    esdf[:, 1] = 2.0  # route A along y = 1
    esdf[5, 1] = 0.8  # its narrowest node
    esdf[:, 3] = 2.0  # route B along y = 3
    esdf[5, 3] = 0.5
    start = np.zeros_like(esdf, dtype=bool)
    goal = np.zeros_like(start)
    start[0], goal[9] = True, True
    r = bottleneck_clearance(esdf, start, goal, 1.0)
    assert 0.7 <= r <= 0.8
    esdf[5, 1] = esdf[5, 3] = -0.5  # both routes cut
    assert bottleneck_clearance(esdf, start, goal, 1.0) == 0.0


def test_stats_command_reads_the_scene_seed(capsys):
    """``python -m envs.scenes stats --seed S`` tabulates the scene drawn at seed S (validation draws), the same row
    as scene_stats on make_scene(..., seed=S); without --seed, the family's own (held-out) scene."""
    from envs.fields import build_fields
    from envs.scenes.__main__ import main
    from envs.scenes.stats import scene_stats

    def row(*extra):
        assert main(["stats", "--family", "ablation", "--indices", "0", "--resolution", "0.4", "--json", *extra]) == 0
        return json.loads(capsys.readouterr().out.strip().splitlines()[-1])[0]

    seeded, held_out = row("--seed", "1160000"), row()
    for seed, got in ((1160000, seeded), (None, held_out)):
        scene = make_scene("ablation", 0, seed=seed)
        assert got == pytest.approx(scene_stats(scene, build_fields(scene, 0.4, 0.2)), nan_ok=True)
    assert seeded["occupied_%"] != held_out["occupied_%"]
