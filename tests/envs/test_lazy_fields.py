"""Lazy fields: a lazy stack and lazy goal anchors give the eager values, build only what is used, share the cache."""

import numpy as np
import pytest

from envs.fields import FieldStack, build_fields, geodesic_field, region_mask, scene_field_stack
from envs.fields.anchors import GoalAnchorFields
from envs.fields.geodesic import nearest_traversable
from envs.navigation import NavigationEnv
from envs.scenes import Box, Scene, Sphere

RES = 0.25
BOUNDS = {"bounds_lo": (0.0, -6.0, 0.0), "bounds_hi": (12.0, 6.0, 3.0)}


def _scenes():
    return [
        Scene(**BOUNDS),
        Scene(primitives=(Sphere((6.0, 0.0, 1.5), 1.5),), **BOUNDS),
        Scene(primitives=(Box((6.0, 2.0, 1.5), (0.5, 3.0, 1.5)),), **BOUNDS),
    ]


def _points(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 3, n), rng.uniform((0.0, -6.0, 0.0), (12.0, 6.0, 3.0), (n, 3))


def test_lazy_stack_builds_only_queried_scenes_and_matches_the_eager_stack(tmp_path):
    scenes = _scenes()
    eager = FieldStack([build_fields(s, RES, cache_dir=tmp_path) for s in scenes])
    lazy = scene_field_stack(scenes, RES, cache_dir=tmp_path)
    assert not lazy.ready.any()  # nothing built at construction
    pts = np.array([[3.0, 0.0, 1.5], [6.0, 4.0, 1.0]])
    lazy.query(np.array([2, 2]), pts)
    np.testing.assert_array_equal(lazy.ready, [False, False, True])
    ids, pts = _points(500)
    for got, want in zip(lazy.query(ids, pts), eager.query(ids, pts), strict=True):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(lazy.ready, [True, True, True])
    np.testing.assert_array_equal(lazy.phi_unreachable, eager.phi_unreachable)
    # The SceneFields handed out reads the stack's own arrays (one copy in memory), with the eager values.
    f = lazy.scene_fields(1)
    np.testing.assert_array_equal(f.esdf, build_fields(scenes[1], RES, cache_dir=tmp_path).esdf)
    assert np.shares_memory(f.esdf, lazy._esdf)


def test_lazy_stack_rejects_a_build_on_the_wrong_grid_and_bad_ids(tmp_path):
    scenes = _scenes()
    wrong = FieldStack.lazy([build_fields(s, RES, cache_dir=tmp_path).grid for s in scenes],
                            lambda s: build_fields(scenes[s], 0.5, cache_dir=tmp_path))  # fmt: skip
    with pytest.raises(ValueError, match="scene 0: fields of shape"):
        wrong.esdf(np.array([0]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="scene id must lie in 0..2"):
        scene_field_stack(scenes, RES, cache_dir=tmp_path).scene_fields(3)


def test_shared_nearest_traversable_gives_the_same_geodesic_field(tmp_path):
    f = build_fields(_scenes()[2], RES, cache_dir=tmp_path)
    trav = f.esdf > f.vehicle_radius
    goal = region_mask(f.grid, ((11.0, -1.0, 1.0), (12.0, 1.0, 2.0)))
    own = geodesic_field(trav, goal, RES, 20.0)
    shared = geodesic_field(trav, goal, RES, 20.0, fill=nearest_traversable(trav, RES))
    np.testing.assert_array_equal(own[0], shared[0])
    assert own[1] == shared[1]


def test_lazy_anchors_build_only_what_is_drawn_and_match_the_eager_fields(tmp_path):
    scenes = _scenes()
    eager = GoalAnchorFields(scenes, [build_fields(s, RES, cache_dir=tmp_path) for s in scenes], 3,
                             cache_dir=tmp_path / "eager")  # fmt: skip
    stack = scene_field_stack(scenes, RES, cache_dir=tmp_path)
    lazy = GoalAnchorFields(scenes, stack, 3, cache_dir=tmp_path / "lazy", lazy=True)
    assert not lazy._ready.any() and not stack.ready.any()
    pts = np.array([[2.0, 0.0, 1.5], [4.0, -3.0, 1.0]])
    got = lazy.geodesic(np.array([1, 1]), np.array([2, 2]), pts)
    np.testing.assert_array_equal(np.flatnonzero(lazy._ready), [1 * 3 + 2])  # one (scene, anchor) field built
    np.testing.assert_array_equal(stack.ready, [False, True, False])
    np.testing.assert_array_equal(got, eager.geodesic(np.array([1, 1]), np.array([2, 2]), pts))
    ids, p = _points(300, seed=1)
    k = np.random.default_rng(2).integers(0, 3, 300)
    np.testing.assert_array_equal(lazy.geodesic(ids, k, p), eager.geodesic(ids, k, p))
    np.testing.assert_array_equal(lazy.valid, eager.valid)
    # One file per anchor: a new lazy instance reads them instead of solving again.
    files = sorted(p.name for p in (tmp_path / "lazy").glob("anchor_*.npz"))
    assert len(files) == 9
    again = GoalAnchorFields(scenes, scene_field_stack(scenes, RES, cache_dir=tmp_path), 3,
                             cache_dir=tmp_path / "lazy", lazy=True)  # fmt: skip
    again._save = None  # a solve would try to save: a cache hit never does
    np.testing.assert_array_equal(again.geodesic(ids, k, p), eager.geodesic(ids, k, p))


def test_lazy_anchors_read_the_one_file_per_scene_cache_of_earlier_versions(tmp_path):
    import hashlib

    scenes = _scenes()[:1]
    stack = scene_field_stack(scenes, RES, cache_dir=tmp_path)
    lazy = GoalAnchorFields(scenes, stack, 3, cache_dir=tmp_path, lazy=True)
    legacy = f"{lazy._key(0)}|3|0.5|{lazy.anchors[0].tolist()}"
    marker = np.arange(3 * int(np.prod(stack.shape[0])), dtype=np.float32).reshape(3, *stack.shape[0])
    np.savez(tmp_path / f"anchors_{hashlib.sha256(legacy.encode()).hexdigest()[:40]}.npz", phi=marker,
             valid=np.ones(3, bool))  # fmt: skip
    lazy.geodesic(np.array([0]), np.array([1]), np.array([[1.0, 0.0, 1.5]]))
    assert lazy._ready.all()  # all three read from the one file
    np.testing.assert_array_equal(lazy._phi.reshape(3, -1), marker.reshape(3, -1))


def test_a_new_env_builds_fields_only_for_the_scenes_it_resets_into(tmp_path, monkeypatch):
    monkeypatch.setenv("SHIELD_NAV_CACHE", str(tmp_path))  # cold cache
    env = NavigationEnv(num_envs=3, **{"scenes.indices": [0, 1, 2, 3]})
    assert not env.field_stack.ready.any() and not env.anchor_fields._ready.any()
    env.reset(seed=0, options={"scene_ids": [2, 2, 2]})
    np.testing.assert_array_equal(env.field_stack.ready, [False, False, True, False])
    built = np.flatnonzero(env.anchor_fields._ready)
    assert set(built // env.anchor_fields.count) == {2}
    assert set(built % env.anchor_fields.count) == set(env.anchor_buf.tolist())
