"""The shield's point memory and local map (merge kernels), and its depth pre-filter (median windows)."""

from __future__ import annotations

import numba as nb
import numpy as np

from envs.camera.pointcloud import key_slots, voxel_keys


@nb.njit(cache=True, nogil=True)
def _append_remembered(ring: np.ndarray, out: np.ndarray, m: int) -> int:
    """Copy the filled rows of a point-memory ring (NaN x: empty) into ``out`` from row ``m``; return the new count."""
    for i in range(ring.shape[0]):
        x = ring[i, 0]
        if x == x:  # not NaN
            out[m, 0], out[m, 1], out[m, 2] = x, ring[i, 1], ring[i, 2]
            m += 1
    return m


@nb.njit(cache=True, nogil=True)
def _map_merge(img: np.ndarray, old: np.ndarray, old_st: np.ndarray, p: np.ndarray, r2: float, z_lo: float,
               z_hi: float, calls: int, max_age: int, voxel: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The local map's intake (``HOCBFShield._with_map``): the merged points (M, 3) and their call stamps (M,).

    Candidates: the image's points ``img`` within ``sqrt(r2)`` of ``p`` and inside [z_lo, z_hi] (stamped ``calls``),
    then the old map's points no older than ``max_age`` calls and within ``sqrt(r2)``, in that order. Of each
    ``voxel_keys`` cube the first candidate is kept (an image point before an old one: the newest wins), and the
    kept points come out in increasing key order: the set and order of ``np.unique(keys, return_index=True)``'s
    first indices, by ``key_slots``'s hash table and a sort of the kept keys only (the candidates repeat a cube
    several times).
    """
    n_img, n_old = img.shape[0], old.shape[0]
    cand = np.empty((n_img + n_old, 3))
    st = np.empty(n_img + n_old, dtype=np.int64)
    n = 0
    for i in range(n_img):
        dx, dy, dz = img[i, 0] - p[0], img[i, 1] - p[1], img[i, 2] - p[2]
        if dx * dx + dy * dy + dz * dz <= r2 and img[i, 2] >= z_lo and img[i, 2] <= z_hi:
            cand[n, 0], cand[n, 1], cand[n, 2] = img[i, 0], img[i, 1], img[i, 2]
            st[n] = calls
            n += 1
    for i in range(n_old):
        dx, dy, dz = old[i, 0] - p[0], old[i, 1] - p[1], old[i, 2] - p[2]
        if calls - old_st[i] <= max_age and dx * dx + dy * dy + dz * dz <= r2:
            cand[n, 0], cand[n, 1], cand[n, 2] = old[i, 0], old[i, 1], old[i, 2]
            st[n] = old_st[i]
            n += 1
    keys = voxel_keys(cand[:n], voxel)
    slots, m = key_slots(keys)
    first = np.empty(m, dtype=np.int64)  # each cube's first candidate: where its slot (numbered as first seen) appears
    seen = 0
    for i in range(n):
        if slots[i] == seen:
            first[seen] = i
            seen += 1
    order = np.argsort(keys[first])  # the kept keys are distinct: any sort gives np.unique's order
    out = np.empty((m, 3))
    out_st = np.empty(m, dtype=np.int64)
    for j in range(m):
        i = first[order[j]]
        out[j, 0], out[j, 1], out[j, 2] = cand[i, 0], cand[i, 1], cand[i, 2]
        out_st[j] = st[i]
    return out, out_st


# --------------------------------------------------------------------------------------------- depth pre-filter
DEPTH_FILTERS = ("none", "median_cross", "median_3x3")
"""Values of ``ShieldConfig.depth_filter``: the windows of :func:`_median_depth` (none: the image as it comes)."""


@nb.njit(cache=True, nogil=True)
def _median_depth(img: np.ndarray, out: np.ndarray, square: bool) -> None:
    """Median-filter a depth image (H, W) into ``out`` (H, W) over the valid pixels of each pixel's window.

    The window is the pixel with its 4 neighbours (``square`` False: a cross of 5, which keeps a one-pixel-wide
    vertical or horizontal line) or its 8 neighbours (True: 3 x 3). Valid pixels read z > 0 (a finite depth; pixels
    without a return read the far range and take part as far values, so a lone near outlier against the sky is
    removed). An invalid pixel (0 or NaN) stays as it is and is left out of its neighbours' windows; the median of
    an even count is the mean of the middle two. Window positions outside the image are left out.
    """
    h, w = img.shape
    buf = np.empty(9)
    for v in range(h):
        for u in range(w):
            z = img[v, u]
            if not (z > 0.0):  # invalid (0, negative or NaN): kept as is
                out[v, u] = z
                continue
            n = 0
            for dv in range(-1, 2):
                vv = v + dv
                if vv < 0 or vv >= h:
                    continue
                for du in range(-1, 2):
                    if not square and dv != 0 and du != 0:
                        continue
                    uu = u + du
                    if uu < 0 or uu >= w:
                        continue
                    x = img[vv, uu]
                    if x > 0.0:
                        buf[n] = x
                        n += 1
            for i in range(1, n):  # insertion sort of at most 9 values
                x = buf[i]
                j = i
                while j > 0 and buf[j - 1] > x:
                    buf[j] = buf[j - 1]
                    j -= 1
                buf[j] = x
            out[v, u] = buf[n // 2] if n % 2 == 1 else 0.5 * (buf[n // 2 - 1] + buf[n // 2])
