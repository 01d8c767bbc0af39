"""The direction sector of a point around the vehicle, as the shield's row selection bins its points.

``_select`` (:mod:`shield_nav.safety.rows`) keeps the tightest point of each azimuth / elevation sector of the
direction o - p. Its sector is defined by :func:`exact_sector`: ``atan2`` and ``asin`` of the direction, scaled and
truncated. Those two calls are costly beside the rest of a point's work (docs/shield.md, "Cost"); :func:`sector`
gives the same integer without them for all but a vanishing share of points:

- elevation: ``asin`` is increasing, so the sector is how many of the boundaries' sines ``-cos(k pi / n_el)`` the
  clamped ``-r_z / d`` reaches; a value within ``X_MARGIN`` of a boundary goes to :func:`exact_sector`;
- azimuth: ``atan2`` by an odd polynomial on [0, 1] after the usual octant reduction (error below ``3e-7`` rad,
  checked by the tests on a dense grid); an angle within ``AZ_MARGIN`` (30 x that) of a sector boundary, and a
  direction with no horizontal part, goes to :func:`exact_sector`.

Away from the boundaries the floating-point rounding of the exact formula (a few ulps) cannot move the truncation,
so both give one integer; the tests compare them on millions of directions, boundary ones included, and a flight
through the shield repeats trial for trial.

``_select`` inlines :func:`sector`, and numba's on-disk cache keys a kernel on its own file: after editing this
module remove the cached kernels (``shield_nav/safety/__pycache__/*.nb?``), or the cached ``_select`` keeps the old
code (``tests/shield_nav/test_sectors.py`` checks the compiled selection against its source).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

ATAN_COEFFS = (
    0.9999966346192147,
    -0.3331830260567584,
    0.19813210704816323,
    -0.13247511695098893,
    0.07981099678077015,
    -0.033725753083081886,
    0.006842562354743771,
)
"""``atan(a) ~ a (c0 + c1 a^2 + ... + c6 a^12)`` on [0, 1] (least squares on Chebyshev nodes; error below 3e-7)."""

AZ_MARGIN = 1e-5
"""Radians: an azimuth the polynomial puts this close to a sector boundary is binned by ``atan2`` itself."""

X_MARGIN = 1e-9
"""An elevation sine this close to a boundary's is binned by ``asin`` itself."""


@nb.njit(cache=True, nogil=True, inline="always")
def exact_sector(rx: float, ry: float, rz: float, d: float, n_az: int, n_el: int) -> int:
    """The sector ``ie n_az + ia`` of the direction ``-(rx, ry, rz)`` (length ``d``): the definition."""
    two_pi = 2.0 * math.pi
    az = math.atan2(-ry, -rx) + math.pi  # direction o - p, in [0, 2 pi]
    el = math.asin(min(1.0, max(-1.0, -rz / max(d, 1e-12)))) + 0.5 * math.pi  # [0, pi]
    ia = min(int(az / two_pi * n_az), n_az - 1)
    ie = min(int(el / math.pi * n_el), n_el - 1)
    return ie * n_az + ia


@nb.njit(cache=True, nogil=True)
def elevation_bounds(n_el: int) -> np.ndarray:
    """The sines ``-cos(k pi / n_el)``, k = 1 .. n_el - 1, at which :func:`exact_sector`'s elevation index steps."""
    out = np.empty(max(n_el - 1, 0))
    for k in range(1, n_el):
        out[k - 1] = -math.cos(k * math.pi / n_el)
    return out


@nb.njit(cache=True, nogil=True, inline="always")
def _atan2(y: float, x: float) -> float:
    """``atan2(y, x)`` to within 3e-7 rad for (x, y) != (0, 0): the polynomial on the octant's ratio."""
    ax, ay = abs(x), abs(y)
    a = min(ax, ay) / max(ax, ay)
    z = a * a
    c = ATAN_COEFFS
    t = a * (c[0] + z * (c[1] + z * (c[2] + z * (c[3] + z * (c[4] + z * (c[5] + z * c[6]))))))
    if ay > ax:
        t = 0.5 * math.pi - t
    if x < 0.0:
        t = math.pi - t
    return -t if y < 0.0 else t


@nb.njit(cache=True, nogil=True, inline="always")
def sector(rx: float, ry: float, rz: float, d: float, n_az: int, n_el: int, el_bounds: np.ndarray) -> int:
    """:func:`exact_sector`'s integer, mostly without ``atan2`` and ``asin`` (bounds: :func:`elevation_bounds`)."""
    x = min(1.0, max(-1.0, -rz / max(d, 1e-12)))
    ie = 0
    for k in range(el_bounds.shape[0]):
        gap = x - el_bounds[k]
        if abs(gap) <= X_MARGIN:
            return exact_sector(rx, ry, rz, d, n_az, n_el)
        if gap > 0.0:
            ie += 1
    if max(abs(rx), abs(ry)) == 0.0:
        return exact_sector(rx, ry, rz, d, n_az, n_el)
    width = 2.0 * math.pi / n_az
    v = (_atan2(-ry, -rx) + math.pi) / width  # sectors from the direction -x, counter-clockwise
    ia = int(math.floor(v))
    if min(v - ia, ia + 1 - v) * width <= AZ_MARGIN or ia < 0 or ia >= n_az:
        return exact_sector(rx, ry, rz, d, n_az, n_el)
    return min(ie, n_el - 1) * n_az + ia
