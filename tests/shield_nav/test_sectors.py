"""The shield's direction sectors: the fast form gives the definition's integer on every direction tried, boundary
directions included, and the definition on hand-computed directions."""

import math

import numba as nb
import numpy as np
import pytest

from shield_nav.safety.sectors import AZ_MARGIN, _atan2, elevation_bounds, exact_sector, sector


@nb.njit(cache=False)
def _mismatches(r, n_az, n_el, bounds):
    bad = 0
    for i in range(r.shape[0]):
        rx, ry, rz = r[i, 0], r[i, 1], r[i, 2]
        d = math.sqrt(rx * rx + ry * ry + rz * rz)
        if sector(rx, ry, rz, d, n_az, n_el, bounds) != exact_sector(rx, ry, rz, d, n_az, n_el):
            bad += 1
    return bad


def _boundary_directions(n_az, n_el):
    """Offsets r = p - o whose direction o - p lies on, or 1e-16 .. 1e-3 rad beside, each sector boundary."""
    eps = np.concatenate(([0.0], np.geomspace(1e-16, 1e-3, 25), -np.geomspace(1e-16, 1e-3, 25)))
    out = []
    for k in range(n_az + 1):
        phi = 2.0 * math.pi * k / n_az - math.pi
        for e in eps:
            for z in (-1.0, 0.0, 0.4):
                out.append((-math.cos(phi + e), -math.sin(phi + e), z))
    for k in range(n_el + 1):
        th = k * math.pi / n_el - 0.5 * math.pi
        for e in eps:
            s = math.sin(th + e)
            h = math.sqrt(max(0.0, 1.0 - s * s))
            for phi in np.linspace(-math.pi, math.pi, 7):
                out.append((-h * math.cos(phi), -h * math.sin(phi), -s))
    out += [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (-0.0, 0.0, 1.0), (1.0, -0.0, 0.0), (-1.0, -0.0, 0.0), (-1.0, 0.0, 0.0)]
    return np.array(out)


@pytest.mark.parametrize(("n_az", "n_el"), [(12, 3), (1, 1), (16, 4), (5, 2)])
def test_the_fast_sector_is_the_definitions_integer(n_az, n_el):
    rng = np.random.default_rng(n_az * 10 + n_el)
    bounds = elevation_bounds(n_el)
    gauss = rng.normal(size=(300_000, 3))
    scaled = rng.normal(size=(100_000, 3)) * 10.0 ** rng.uniform(-6, 2, size=(100_000, 1))
    edges = _boundary_directions(n_az, n_el)
    assert _mismatches(gauss, n_az, n_el, bounds) == 0
    assert _mismatches(scaled, n_az, n_el, bounds) == 0
    assert _mismatches(edges, n_az, n_el, bounds) == 0


def test_the_sector_definition_by_hand():
    """12 azimuth x 3 elevation sectors; the direction is o - p = -r. Azimuth 0 points along -x, counter-clockwise."""
    cases = {
        (-1.0, 0.0, 0.0): 1 * 12 + 6,  # ahead along +x, level: atan2(0, 1) = 0 -> az pi -> sector 6; middle band
        (1.0, 1e-3, 0.0): 1 * 12 + 0,  # along -x, just below the -x axis: atan2(-1e-3, -1) ~ -pi -> sector 0
        (0.0, -1.0, 0.0): 1 * 12 + 9,  # along +y: atan2(1, 0) = pi / 2 -> az 3 pi / 2 -> sector 9
        (0.0, 0.0, -1.0): 2 * 12 + 0,  # straight up: asin(1) + pi / 2 = pi -> the top band; atan2(-0., -0.) = -pi
        (-1.0, 0.0, 1.0): 0 * 12 + 6,  # 45 degrees down: asin(-0.707) + pi / 2 = pi / 4 < pi / 3 -> the bottom band
    }
    bounds = elevation_bounds(3)
    for (rx, ry, rz), want in cases.items():
        d = math.sqrt(rx * rx + ry * ry + rz * rz)
        assert exact_sector(rx, ry, rz, d, 12, 3) == want
        assert sector(rx, ry, rz, d, 12, 3, bounds) == want
    np.testing.assert_allclose(bounds, [-0.5, 0.5], atol=1e-15)


def test_the_azimuth_polynomial_stays_far_inside_its_margin():
    g = np.linspace(-1.0, 1.0, 1201)
    err = max(abs(_atan2(float(y), float(x)) - math.atan2(y, x)) for x in g for y in g if (x, y) != (0.0, 0.0))
    assert err < 3e-7 and 30 * err <= AZ_MARGIN


def test_the_compiled_selection_is_its_source(monkeypatch):
    """The row selection as compiled (possibly read from numba's on-disk cache) against its Python source run line by
    line, on a random cloud, with and without the lagged rows. ``_select`` inlines ``sectors.sector`` from another
    file, and numba's cache keys a kernel on its own file only: after an edit of sectors.py a stale cached
    ``_select`` would fail here (clear the ``__pycache__`` folders' ``*.nbi`` / ``*.nbc`` files)."""
    import shield_nav.safety.shield as sh
    from shield_nav.safety.rows import _select

    rng = np.random.default_rng(3)
    pts = rng.uniform(-4.0, 4.0, size=(600, 3)) + np.array([3.0, 0.0, 1.5])
    p, v, a = np.array([0.0, 0.0, 1.5]), np.array([4.0, 0.5, 0.0]), np.array([1.0, -2.0, 0.5])
    for lagged in (None, (p + 0.04 * v, v + 0.04 * a)):
        compiled = sh.HOCBFShield().constraints(pts, p, v, a, lagged)
        monkeypatch.setattr(sh, "_select", _select.py_func)
        source = sh.HOCBFShield().constraints(pts, p, v, a, lagged)
        monkeypatch.undo()
        assert len(compiled[0]) > 1
        for x, y in zip(compiled, source, strict=True):
            assert np.array_equal(x, y)
