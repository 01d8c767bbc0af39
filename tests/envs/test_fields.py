"""Fields: ESDF against analytic distances, geodesic on known shapes, lookups, caching, bad input."""

import math

import numpy as np
import pytest

from envs.fields import FieldStack, Grid, SceneFields, build_fields
from envs.scenes import Box, Capsule, Cylinder, Scene, Sphere
from envs.scenes import composites as C
from envs.scenes.sdf import union_sdf

RES = 0.1
SMALL = {"bounds_lo": (0.0, -3.0, 0.0), "bounds_hi": (6.0, 3.0, 3.0), "floor": False}


def _nodes(fields):
    g = fields.grid
    return g.points(tuple(slice(0, n) for n in g.shape)).reshape(*g.shape, 3)


@pytest.mark.parametrize(
    "prim",
    [
        Sphere((3.0, 0.1, 1.5), 0.8),
        Cylinder((2.5, -1.0, 0.4), (3.6, 1.2, 2.5), 0.3),  # inclined
        Box((3.0, 0.0, 1.4), (1.0, 0.4, 0.6), C.yaw_quat(0.5)),
        Capsule((3.03, 0.02, 0.3), (3.03, 0.02, 2.6), 0.03),  # thin pole, thinner than a voxel
    ],
    ids=["sphere", "inclined-cylinder", "rotated-box", "thin-pole"],
)
def test_esdf_within_one_voxel_of_analytic(tmp_path, prim):
    f = build_fields(Scene(primitives=(prim,), **SMALL), RES, cache_dir=tmp_path)
    truth = union_sdf([prim], _nodes(f).reshape(-1, 3)).reshape(f.shape)
    err = np.abs(f.esdf - truth)
    assert err.max() <= RES
    # Within the exact band (3 voxels) the values are the analytic ones (float32 rounding only).
    band = truth <= 3 * RES
    assert err[band].max() < 1e-5


def test_esdf_includes_floor_and_ceiling_as_half_spaces(tmp_path):
    f = build_fields(Scene(bounds_lo=(0, -2, 0), bounds_hi=(4, 2, 3), ceiling=True), RES, cache_dir=tmp_path)
    z = f.grid.axis(2)
    np.testing.assert_allclose(f.esdf[20, 20, :], np.minimum(z, 3.0 - z), atol=1e-6)


def test_esdf_gradient_points_away_from_a_sphere(tmp_path):
    f = build_fields(Scene(primitives=(Sphere((3.0, 0.0, 1.5), 0.5),), **SMALL), RES, cache_dir=tmp_path)
    c = np.array([3.0, 0.0, 1.5])
    near = np.array([[3.63, 0.21, 1.61], [2.6, -0.4, 1.2]])  # inside the exact band (d < 0.3 m)
    far = np.array([[4.23, 0.37, 1.61], [1.9, -0.8, 1.2]])  # far field (d ~ 0.8 m)
    for pts, atol in ((near, 0.03), (far, 0.15)):
        g = f.stack().esdf_grad(np.zeros(2, int), pts)
        expected = (pts - c) / np.linalg.norm(pts - c, axis=1, keepdims=True)
        np.testing.assert_allclose(g, expected, atol=atol)


def _linear_fields(shape=(5, 4, 3), origin=(1.0, 2.0, 0.0), res=0.5):
    # Fields that are affine in position: trilinear interpolation must reproduce them exactly.
    g = Grid(origin, res, shape)
    p = g.points(tuple(slice(0, n) for n in shape)).reshape(*shape, 3)
    esdf = (0.3 * p[..., 0] - 0.2 * p[..., 1] + 0.5 * p[..., 2]).astype(np.float32)
    phi = (10.0 - p[..., 0]).astype(np.float32)
    grad = np.broadcast_to(np.array([0.3, -0.2, 0.5], np.float32), (*shape, 3)).copy()
    return SceneFields(origin, res, shape, 0.2, esdf, grad, phi, 100.0)


def test_trilinear_lookup_is_exact_for_affine_fields_and_clamps_outside():
    f0 = _linear_fields()
    f1 = _linear_fields(shape=(3, 3, 3), origin=(0.0, 0.0, 0.0), res=1.0)
    stack = FieldStack([f0, f1])
    pts = np.array([[1.7, 2.9, 0.33], [1.7, 1.9, 0.33], [0.4, 1.2, 1.9]])
    ids = np.array([0, 1, 1])
    d, g, phi = stack.query(ids, pts)
    np.testing.assert_allclose(d, 0.3 * pts[:, 0] - 0.2 * pts[:, 1] + 0.5 * pts[:, 2], atol=1e-6)
    np.testing.assert_allclose(phi, 10.0 - pts[:, 0], atol=1e-6)
    np.testing.assert_allclose(g, [[0.3, -0.2, 0.5]] * 3, atol=1e-6)
    # Outside: f0's box is x in [1, 3], y in [2, 3.5], z in [0, 1]. A point 3 m beyond x=3 and 4 m above z=1
    # is 5 m outside: ESDF at the clamped point (3, 3, 1) minus 5, Phi there plus 5.
    d, g, phi = stack.query(np.array([0]), np.array([[6.0, 3.0, 5.0]]))
    np.testing.assert_allclose(d, [0.3 * 3 - 0.2 * 3 + 0.5 * 1 - 5.0], atol=1e-6)
    np.testing.assert_allclose(phi, [10.0 - 3.0 + 5.0], atol=1e-6)


def test_lookup_rejects_bad_input():
    stack = FieldStack([_linear_fields()])
    with pytest.raises(ValueError, match="scene_ids must lie in 0..0"):
        stack.esdf(np.array([1]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="finite; row 1"):
        stack.esdf(np.array([0, 0]), np.array([[0, 0, 0], [np.nan, 0, 0]]))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        stack.esdf(np.array([0]), np.zeros((2, 3)))


# Thin 2D-like scenes (0.4 m tall, no floor) for geodesics with known Euclidean shortest paths.
FLAT = {"bounds_lo": (0.0, -6.0, 0.0), "bounds_hi": (12.0, 6.0, 0.4), "floor": False}


def _true_wall_gap(p):
    # Wall x in [5.95, 6.15] (faces 0.2 m apart) blocking y in [-6, 1.95] and [3.05, 6]; gap y in [1.95, 3.05].
    # From p below the gap the taut string wraps the gap's lower corners (5.95, 1.95) and (6.15, 1.95), then
    # runs straight in +x to the goal face x = 11.
    c0, c1 = np.array([5.95, 1.95]), np.array([6.15, 1.95])
    return np.linalg.norm(p - c0) + np.linalg.norm(c1 - c0) + (11.0 - c1[0])


def _true_u_trap(p):
    # U open towards -x: back wall x in [8.05, 8.25], y in [-2.25, 2.25]; side walls y in [1.95, 2.25] and
    # [-2.25, -1.95], x in [4.95, 8.25]. From p inside, wrap (4.95, 1.95), (4.95, 2.25), (8.25, 2.25), then +x
    # (or the mirror image below y = 0, whichever is shorter).
    def via_top(q):
        pts = [q, np.array([4.95, 1.95]), np.array([4.95, 2.25]), np.array([8.25, 2.25])]
        return sum(np.linalg.norm(b - a) for a, b in zip(pts[:-1], pts[1:], strict=True)) + (11.0 - 8.25)

    return min(via_top(p), via_top(p * [1.0, -1.0]))


WALL = (Box((6.05, -2.025, 0.2), (0.1, 3.975, 0.2)), Box((6.05, 4.525, 0.2), (0.1, 1.475, 0.2)))
U = (
    Box((8.15, 0.0, 0.2), (0.1, 2.25, 0.2)),
    Box((6.6, 2.1, 0.2), (1.65, 0.15, 0.2)),
    Box((6.6, -2.1, 0.2), (1.65, 0.15, 0.2)),
)


@pytest.mark.parametrize(
    ("prims", "truth", "points"),
    [
        (WALL, _true_wall_gap, [[2.0, -3.0], [3.0, -5.0], [4.5, 0.0], [1.0, 1.0]]),
        (U, _true_u_trap, [[7.0, 0.0], [6.0, -1.0], [7.5, 1.5]]),
    ],
    ids=["wall-with-gap", "u-trap"],
)
@pytest.mark.parametrize(("stencil", "tol"), [("extended", 0.03), ("26", 0.085)])
def test_geodesic_matches_euclidean_shortest_paths(tmp_path, prims, truth, points, stencil, tol):
    scene = Scene(primitives=prims, **FLAT)
    f = build_fields(scene, RES, vehicle_radius=0.0, cache_dir=tmp_path, stencil=stencil)
    for xy in points:
        p = np.array([xy[0], xy[1], 0.2])
        true = truth(np.array(xy))
        got = f.stack().geodesic(np.zeros(1, int), p[None])[0]
        # Grid paths pass one node off the corners (nodes on a surface are not free): allow 2 voxels.
        assert abs(got - true) <= tol * true + 2 * RES, (xy, got, true)
        assert got >= true - 2 * RES  # a grid path is never much shorter than the true shortest path
        assert got > 11.0 - xy[0] + 0.05  # longer than the straight flight: the obstacle is in the way


def test_unreachable_pocket_gets_finite_penalty_and_goal_is_zero(tmp_path):
    # A closed box (4 walls) around (3, 0): its inside cannot reach the goal.
    walls = (
        Box((2.0, 0.0, 0.2), (0.1, 1.1, 0.2)), Box((4.0, 0.0, 0.2), (0.1, 1.1, 0.2)),
        Box((3.0, 1.0, 0.2), (1.1, 0.1, 0.2)), Box((3.0, -1.0, 0.2), (1.1, 0.1, 0.2)),
    )  # fmt: skip
    f = build_fields(Scene(primitives=walls, **FLAT), RES, vehicle_radius=0.0, cache_dir=tmp_path)
    assert np.isfinite(f.phi).all() and np.isfinite(f.esdf).all() and np.isfinite(f.grad).all()
    phi = f.stack().geodesic(np.zeros(3, int), np.array([[3.0, 0.0, 0.2], [11.5, 0.0, 0.2], [1.0, 4.0, 0.2]]))
    assert phi[0] == pytest.approx(f.phi_unreachable)
    assert phi[1] == pytest.approx(0.0)
    assert phi[2] == pytest.approx(10.0, abs=0.05)  # straight line to the goal face x = 11
    assert f.phi.max() <= f.phi_unreachable
    assert f.info["start_reachable_fraction"] == 1.0


def test_vehicle_radius_closes_narrow_gaps(tmp_path):
    # The gap is 1.1 m wide: open for a 0.2 m vehicle, closed for a 0.6 m one.
    scene = Scene(primitives=WALL, **FLAT)
    p = np.array([[2.0, -3.0, 0.2]])
    small = build_fields(scene, RES, vehicle_radius=0.2, cache_dir=tmp_path).stack().geodesic(np.zeros(1, int), p)
    big = build_fields(scene, RES, vehicle_radius=0.6, cache_dir=tmp_path)
    assert small[0] < 20.0
    assert big.stack().geodesic(np.zeros(1, int), p)[0] == pytest.approx(big.phi_unreachable)


def test_bad_input_names_the_problem(tmp_path):
    scene = Scene(**FLAT)
    with pytest.raises(ValueError, match="vehicle_radius must be a non-negative"):
        build_fields(scene, RES, vehicle_radius=-0.1, cache_dir=tmp_path)
    with pytest.raises(ValueError, match="resolution must be a positive"):
        build_fields(scene, 0.0, cache_dir=tmp_path)
    blocker = Box((11.5, 0.0, 0.2), (0.5, 6.0, 0.2))  # fills the goal region
    with pytest.raises(ValueError, match="goal region .* is fully blocked"):
        build_fields(Scene(primitives=(blocker,), **FLAT), RES, cache_dir=tmp_path)


def test_cache_round_trip_and_keying(tmp_path, monkeypatch):
    scene = Scene(primitives=WALL, **FLAT)
    monkeypatch.setenv("SHIELD_NAV_CACHE", str(tmp_path / "env"))
    a = build_fields(scene, RES)
    assert not a.info["cache_hit"] and len(list((tmp_path / "env").glob("*.npz"))) == 1
    b = build_fields(scene, RES)
    assert b.info["cache_hit"]
    np.testing.assert_array_equal(a.esdf, b.esdf)
    np.testing.assert_array_equal(a.phi, b.phi)
    np.testing.assert_array_equal(a.grad, b.grad)
    assert b.phi_unreachable == a.phi_unreachable
    build_fields(scene, RES, vehicle_radius=0.3)  # another radius: another file
    build_fields(scene, 0.2)  # another resolution: another file
    assert len(list((tmp_path / "env").glob("*.npz"))) == 3
    c = build_fields(scene, RES, use_cache=False)
    assert not c.info["cache_hit"]


def test_grid_covers_bounds():
    g = Grid.for_scene(Scene(), 0.1)
    assert g.shape == (641, 321, 31)
    assert math.isclose(g.axis(0)[-1], 64.0, abs_tol=1e-9)


def test_goal_anchor_fields_lead_to_their_own_anchor():
    from envs.fields.anchors import GoalAnchorFields, anchor_points

    scene = Scene()  # empty 64 x 32 x 3 m scene with a floor
    f = build_fields(scene, resolution=0.25, vehicle_radius=0.2, use_cache=False)
    anchors = GoalAnchorFields([scene], [f], 3, cache_dir=None)
    np.testing.assert_allclose(anchor_points(scene, 3)[:, 1], [-14.5, 0.0, 14.5])
    ids = np.zeros(3, dtype=np.int64)
    # Free space: Phi to anchor k is the straight distance to its goal box (x >= 63, |y - y_k| <= 0.5, |z - z_c|
    # <= 0.5), within the stencil's error (+3 %) and one grid cell.
    p = np.array([[10.0, 0.0, 1.5], [10.0, 0.0, 1.5], [60.0, 14.5, 1.5]])
    phi = anchors.geodesic(ids, np.array([0, 1, 2]), p)
    exact = np.array([np.hypot(53.0, 14.0), 53.0, 3.0])
    assert np.all(phi >= exact - 0.3) and np.all(phi <= exact * 1.03 + 0.3)
    # Moving towards anchor 0's side lowers Phi_0 and raises Phi_2.
    q = p[:1] + np.array([[0.0, -1.0, 0.0]])
    assert anchors.geodesic(ids[:1], [0], q)[0] < phi[0]
    assert anchors.geodesic(ids[:1], [2], q)[0] > anchors.geodesic(ids[:1], [2], p[:1])[0]
    np.testing.assert_array_equal(anchors.nearest(ids[:1], np.array([[63.5, 13.0, 1.0]])), [2])


def test_weighted_geodesic_by_hand():
    """A 1-D corridor of 5 nodes (res 0.5 m), goal at node 0: unit costs give the distances; costs c give edge
    weights len * (c_u + c_v) / 2, summed by hand; bad costs are refused."""
    from envs.fields.geodesic import geodesic_field

    trav = np.ones((5, 1, 1), dtype=bool)
    goal = np.zeros_like(trav)
    goal[0] = True
    phi, _, reach = geodesic_field(trav, goal, 0.5, 10.0, "26")
    np.testing.assert_allclose(phi[:, 0, 0], [0.0, 0.5, 1.0, 1.5, 2.0])
    cost = np.array([1.0, 3.0, 1.0, 1.0, 5.0]).reshape(5, 1, 1)
    phi_w, _, _ = geodesic_field(trav, goal, 0.5, 10.0, "26", cost=cost)
    # edges: 0-1 0.5 * 2 = 1.0; 1-2 0.5 * 2 = 1.0; 2-3 0.5 * 1 = 0.5; 3-4 0.5 * 3 = 1.5
    np.testing.assert_allclose(phi_w[:, 0, 0], [0.0, 1.0, 2.0, 2.5, 4.0])
    assert reach.all()
    # Two routes round a wall: the costlier short one loses to the cheap long one.
    trav = np.ones((3, 3, 1), dtype=bool)
    trav[1, 1] = False  # centre blocked
    goal = np.zeros_like(trav)
    goal[2, 1] = True
    cost = np.ones((3, 3, 1))
    cost[:, 0] = 10.0  # the y = 0 side is expensive
    # From (0, 1) every diagonal cuts the blocked centre's corner (not allowed), so both routes take 4 unit steps:
    # round the cheap y = 2 side 4 x 1 = 4; round the y = 0 side 5.5 + 10 + 10 + 5.5 = 31.
    phi_w, _, _ = geodesic_field(trav, goal, 1.0, 10.0, "26", cost=cost)
    np.testing.assert_allclose(phi_w[0, 1, 0], 4.0, rtol=1e-6)
    np.testing.assert_allclose(phi_w[0, 0, 0], 4.0 + 5.5, rtol=1e-6)  # step to (0, 1), then the cheap side
    cost = cost[:, ::-1].copy()  # now the y = 2 side is the expensive one: the route flips, the value does not
    phi_w, _, _ = geodesic_field(trav, goal, 1.0, 10.0, "26", cost=cost)
    np.testing.assert_allclose(phi_w[0, 1, 0], 4.0, rtol=1e-6)
    np.testing.assert_allclose(phi_w[0, 2, 0], 4.0 + 5.5, rtol=1e-6)
    for bad in (np.zeros((3, 3, 1)), np.full((3, 3, 1), np.nan), np.ones((2, 2, 1))):
        with pytest.raises(ValueError, match="cost"):
            geodesic_field(trav, goal, 1.0, 10.0, "26", cost=bad)


def test_clearance_cost_anchor_fields_are_keyed_apart_and_weigh_narrow_space(tmp_path):
    from envs.fields.anchors import GoalAnchorFields

    scene = Scene()
    f = build_fields(scene, resolution=0.25, vehicle_radius=0.2, use_cache=False)
    plain = GoalAnchorFields([scene], [f], 1, cache_dir=tmp_path)
    weighted = GoalAnchorFields([scene], [f], 1, cache_dir=tmp_path, clearance_cost=(0.6, 4.0))
    assert plain._file(0, 0) != weighted._file(0, 0)
    ids, k = np.zeros(2, dtype=np.int64), np.zeros(2, dtype=np.int64)
    # Mid-height, far from floor and ceiling (ESDF 1.5 m > 0.6 m): no cost, the same Phi.
    p = np.array([[20.0, 0.0, 1.5], [20.0, 0.0, 0.3]])
    a, b = plain.geodesic(ids, k, p), weighted.geodesic(ids, k, p)
    assert abs(a[0] - b[0]) < 1e-6
    # 0.3 m above the floor the path to the goal (which lies at mid-height) crosses costly nodes: Phi grows.
    assert b[1] > a[1] + 0.1
    with pytest.raises(ValueError, match="clearance_cost"):
        GoalAnchorFields([scene], [f], 1, cache_dir=tmp_path, clearance_cost=(0.0, 1.0))


def test_height_cost_anchor_fields_charge_height_above_the_reference_by_hand(tmp_path):
    """Empty default scene, goal box at z 1.0-2.0, cost 1 + 2 max(0, z - 1) per metre (the expert's ``high_*``).

    At z = 1.0 the straight way costs 1 per metre: Phi as without the cost. From z = 2.5 any way crosses the band
    z 2.0-2.5 (at least 0.5 m where the cost is >= 3): Phi >= the plain one + 2 x 1.0 x 0.5; descending straight
    down to z = 1.0 first costs 1.5 + 2 x 1.5^2 / 2 (linear cost: the edges' mean of end nodes is exact), a bound
    above."""
    from envs.fields.anchors import GoalAnchorFields

    scene = Scene()
    f = build_fields(scene, resolution=0.25, vehicle_radius=0.2, use_cache=False)
    plain = GoalAnchorFields([scene], [f], 1, cache_dir=tmp_path)
    high = GoalAnchorFields([scene], [f], 1, cache_dir=tmp_path, height_cost=(1.0, 2.0))
    assert plain._file(0, 0) != high._file(0, 0)
    assert np.asarray(scene.bounds_lo)[2] == 0.0 and plain.anchors[0, 0, 2] == 1.5
    ids, k = np.zeros(2, dtype=np.int64), np.zeros(2, dtype=np.int64)
    p = np.array([[20.0, 0.0, 1.0], [20.0, 0.0, 2.5]])
    a, b = plain.geodesic(ids, k, p), high.geodesic(ids, k, p)
    assert abs(a[0] - b[0]) < 1e-5
    assert a[1] + 1.0 - 1e-5 <= b[1] <= b[0] + 1.5 + 2.25 + 1e-5
    with pytest.raises(ValueError, match="height_cost"):
        GoalAnchorFields([scene], [f], 1, cache_dir=tmp_path, height_cost=(1.0, -1.0))


def test_a_one_layer_geodesic_field_is_scipys_dijkstra_on_the_explicit_graph():
    """A 2D grid (nz = 1, the camera map's) takes the kernel's in-layer edges only: its field equals scipy's
    Dijkstra on an edge list built here from the rule in the module docstring (every |dx|, |dy| <= 2 offset of gcd 1,
    its Euclidean length; usable only with both ends and the nodes its midpoint falls between traversable)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    from envs.fields.geodesic import geodesic_field

    rng = np.random.default_rng(7)
    nx, ny, res = 23, 17, 0.2
    trav = rng.random((nx, ny)) > 0.25
    goal = np.zeros((nx, ny), dtype=bool)
    goal[18:, 6:11] = True
    trav[18:, 6:11] = True
    rows, cols, w = [], [], []
    for dx in range(-2, 3):
        for dy in range(-2, 3):
            if (dx, dy) == (0, 0) or math.gcd(abs(dx), abs(dy)) != 1:
                continue
            between = {
                (math.floor(dx / 2), math.floor(dy / 2)),
                (math.ceil(dx / 2), math.ceil(dy / 2)),
                (math.floor(dx / 2), math.ceil(dy / 2)),
                (math.ceil(dx / 2), math.floor(dy / 2)),
            }
            between -= {(0, 0), (dx, dy)}
            for i in range(nx):
                for j in range(ny):
                    a, b = i + dx, j + dy
                    if not (0 <= a < nx and 0 <= b < ny and trav[i, j] and trav[a, b]):
                        continue
                    if all(trav[i + p, j + q] for p, q in between):
                        rows.append(i * ny + j)
                        cols.append(a * ny + b)
                        w.append(res * math.hypot(dx, dy))
    graph = coo_matrix((w, (rows, cols)), shape=(nx * ny, nx * ny)).tocsr()
    want = dijkstra(graph, indices=np.flatnonzero(goal.ravel()), min_only=True).reshape(nx, ny)
    phi, phi_unreachable, reach = geodesic_field(trav[..., None], goal[..., None], res, 10.0)
    np.testing.assert_array_equal(reach[..., 0], np.isfinite(want) & trav)
    np.testing.assert_allclose(phi[..., 0][reach[..., 0]], want[reach[..., 0]], rtol=1e-6)
    pocket = trav & ~reach[..., 0]  # sealed-off traversable nodes: the finite penalty
    assert pocket.sum() > 0 and (phi[..., 0][pocket] == np.float32(phi_unreachable)).all()
