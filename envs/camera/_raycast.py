"""Numba kernels: exact ray casting of z-depth images against packed primitives.

Primitive packing (one row per primitive, world frame, float64 ``params`` of width ``PARAM_WIDTH``):

==========  ====  ============================================================
kind        code  params
==========  ====  ============================================================
sphere      0     centre (3), radius
cylinder    1     p0 (3), unit axis a (3), length L, radius  (flat caps)
capsule     2     p0 (3), unit axis a (3), length L, radius  (round caps)
box         3     centre (3), half extents (3), R box->world (9, row-major)
half-space  4     normal n (3), offset h: the solid is {x : n . x <= h}
==========  ====  ============================================================

``bsph`` (P, 4) holds a bounding sphere (centre, radius) of each primitive for frustum culling.

Per camera the algorithm is: cull primitives by bounding sphere against the view frustum and the far range;
project each survivor's bounding box (clipped to the half-space in front of the camera) to a pixel rectangle
and a lower bound ``zmin`` on its depth; sort survivors by ``zmin``; fill the depth buffer with the
half-spaces; then, front to back, intersect each survivor exactly with the rays of the pixels in its
rectangle whose current depth is larger than ``zmin``. All work happens in the camera frame, where the ray
of pixel (v, u) is ``t * (x_u, y_v, 1)`` from the origin, so the ray parameter ``t`` is the z-depth.

Solids are solid: if the optical centre lies inside any primitive, every ray hits at t = 0.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

SPHERE, CYLINDER, CAPSULE, BOX, HALFSPACE = 0, 1, 2, 3, 4
PARAM_WIDTH = 16
_EPS = 1e-12
_ZCLIP = 1e-6  # bounding boxes are clipped to z >= _ZCLIP before projection (metres)
_NJIT = {"cache": True, "fastmath": False, "nogil": True}


@nb.njit(**_NJIT)
def _perp_basis(a0: float, a1: float, a2: float) -> tuple:
    """Two unit vectors u, v with (a, u, v) orthonormal, for a unit vector a."""
    # Cross a with the world axis it is least aligned with.
    if abs(a0) < 0.6:
        u0, u1, u2 = 0.0, a2, -a1  # a x e_x
    elif abs(a1) < 0.6:
        u0, u1, u2 = -a2, 0.0, a0  # a x e_y
    else:
        u0, u1, u2 = a1, -a0, 0.0  # a x e_z
    n = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    u0, u1, u2 = u0 / n, u1 / n, u2 / n
    v0, v1, v2 = a1 * u2 - a2 * u1, a2 * u0 - a0 * u2, a0 * u1 - a1 * u0
    return u0, u1, u2, v0, v1, v2


@nb.njit(**_NJIT)
def _rect(corners: np.ndarray, fx: float, fy: float, cx: float, cy: float, W: int, H: int, out: np.ndarray) -> bool:
    """Pixel rectangle and depth lower bound of a box given by its 8 camera-frame ``corners``.

    Corner i has bits (i&1, i&2, i&4) of its box coordinates. Writes ``out = [u0, u1, v0, v1, zmin]`` and
    returns False if the box is off-screen.

    The box is clipped to z >= _ZCLIP: its kept corners plus the crossing points of its 12 edges with the
    plane z = _ZCLIP bound the clipped convex polytope, whose projection is the convex hull of theirs.
    """
    big = 1e7
    xmin, xmax, ymin, ymax, zmin = big, -big, big, -big, big
    any_pt = False
    for i in range(8):
        z = corners[i, 2]
        if z >= _ZCLIP:
            any_pt = True
            px, py = corners[i, 0] / z, corners[i, 1] / z
            xmin, xmax = min(xmin, px), max(xmax, px)
            ymin, ymax = min(ymin, py), max(ymax, py)
            zmin = min(zmin, z)
        for bit in (1, 2, 4):
            j = i | bit
            if j == i:
                continue
            zj = corners[j, 2]
            if (z >= _ZCLIP) != (zj >= _ZCLIP):
                s = (_ZCLIP - z) / (zj - z)  # edge point on the plane z = _ZCLIP
                px = (corners[i, 0] + s * (corners[j, 0] - corners[i, 0])) / _ZCLIP
                py = (corners[i, 1] + s * (corners[j, 1] - corners[i, 1])) / _ZCLIP
                xmin, xmax = min(xmin, px), max(xmax, px)
                ymin, ymax = min(ymin, py), max(ymax, py)
                zmin = _ZCLIP
    if not any_pt:
        return False
    # Pixel u is sampled at x_u = (u + 0.5 - cx) / fx, so x in [xmin, xmax] <=> u in [xmin*fx + cx - 0.5, ...].
    # One pixel of margin absorbs rounding.
    ulo = max(min(xmin * fx + cx - 0.5, big), -big)
    uhi = max(min(xmax * fx + cx - 0.5, big), -big)
    vlo = max(min(ymin * fy + cy - 0.5, big), -big)
    vhi = max(min(ymax * fy + cy - 0.5, big), -big)
    u0 = max(int(math.ceil(ulo)) - 1, 0)
    u1 = min(int(math.floor(uhi)) + 1, W - 1)
    v0 = max(int(math.ceil(vlo)) - 1, 0)
    v1 = min(int(math.floor(vhi)) + 1, H - 1)
    if u0 > u1 or v0 > v1:
        return False
    out[0], out[1], out[2], out[3], out[4] = u0, u1, v0, v1, zmin
    return True


@nb.njit(**_NJIT)
def _sphere_t(x: float, y: float, dd: float, q0: float, q1: float, q2: float, cc: float) -> float:
    """Entry depth of ray t*(x, y, 1) into the sphere at q with cc = |q|^2 - r^2 > 0 (origin outside); inf if none."""
    b = x * q0 + y * q1 + q2  # d . q; |t d - q|^2 = r^2  <=>  dd t^2 - 2 b t + cc = 0
    disc = b * b - dd * cc
    if disc < 0.0 or b <= 0.0:
        return np.inf
    return (b - math.sqrt(disc)) / dd


@nb.njit(**_NJIT)
def _render_camera(
    o: np.ndarray,
    Rc: np.ndarray,
    kinds: np.ndarray,
    params: np.ndarray,
    bsph: np.ndarray,
    start: int,
    stop: int,
    x_u: np.ndarray,
    y_v: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    zfar: float,
    zb: np.ndarray,
) -> None:
    """Fill ``zb`` (H, W) with the z-depth of the first hit (inf for none) for one camera at ``o``, ``Rc``."""
    H, W = zb.shape
    zb[:, :] = np.inf
    n = stop - start
    if n <= 0:
        return
    # Frustum side planes through the origin (camera frame), inward unit normals; culling by bounding sphere.
    xl, xr, yt, yb = x_u[0], x_u[W - 1], y_v[0], y_v[H - 1]
    nl = 1.0 / math.sqrt(1.0 + xl * xl)
    nr = 1.0 / math.sqrt(1.0 + xr * xr)
    nt = 1.0 / math.sqrt(1.0 + yt * yt)
    nbt = 1.0 / math.sqrt(1.0 + yb * yb)
    cam = np.empty((n, PARAM_WIDTH))  # primitive parameters transformed into the camera frame
    rects = np.empty((n, 5))
    order_key = np.empty(n)
    idx = np.empty(n, dtype=np.int64)
    corners = np.empty((8, 3))
    m = 0
    for k in range(start, stop):
        kind = kinds[k]
        p = params[k]
        if kind == HALFSPACE:
            # n . X_w <= h with X_w = o + Rc X_c  <=>  (Rc^T n) . X_c <= h - n . o
            c = cam[m]
            for j in range(3):
                c[j] = Rc[0, j] * p[0] + Rc[1, j] * p[1] + Rc[2, j] * p[2]
            c[3] = p[3] - (p[0] * o[0] + p[1] * o[1] + p[2] * o[2])
            if c[3] >= 0.0:  # origin inside the half-space solid
                zb[:, :] = 0.0
                return
            idx[m] = k
            order_key[m] = -1.0  # half-spaces first
            rects[m, 0], rects[m, 1], rects[m, 2], rects[m, 3], rects[m, 4] = 0, W - 1, 0, H - 1, 0.0
            m += 1
            continue
        # Bounding sphere in the camera frame: s = Rc^T (centre - o).
        dx, dy, dz = bsph[k, 0] - o[0], bsph[k, 1] - o[1], bsph[k, 2] - o[2]
        sx = Rc[0, 0] * dx + Rc[1, 0] * dy + Rc[2, 0] * dz
        sy = Rc[0, 1] * dx + Rc[1, 1] * dy + Rc[2, 1] * dz
        sz = Rc[0, 2] * dx + Rc[1, 2] * dy + Rc[2, 2] * dz
        r = bsph[k, 3]
        if sz + r < 0.0 or sz - r > zfar:
            continue
        if (sx - xl * sz) * nl < -r or (xr * sz - sx) * nr < -r:
            continue
        if (sy - yt * sz) * nt < -r or (yb * sz - sy) * nbt < -r:
            continue
        c = cam[m]
        # First point (sphere centre / p0 / box centre) in the camera frame.
        dx, dy, dz = p[0] - o[0], p[1] - o[1], p[2] - o[2]
        q0 = Rc[0, 0] * dx + Rc[1, 0] * dy + Rc[2, 0] * dz
        q1 = Rc[0, 1] * dx + Rc[1, 1] * dy + Rc[2, 1] * dz
        q2 = Rc[0, 2] * dx + Rc[1, 2] * dy + Rc[2, 2] * dz
        c[0], c[1], c[2] = q0, q1, q2
        if kind == SPHERE:
            rad = p[3]
            cc = q0 * q0 + q1 * q1 + q2 * q2 - rad * rad
            if cc <= 0.0:
                zb[:, :] = 0.0
                return
            c[3] = cc
            for i in range(8):
                corners[i, 0] = q0 + (rad if i & 1 else -rad)
                corners[i, 1] = q1 + (rad if i & 2 else -rad)
                corners[i, 2] = q2 + (rad if i & 4 else -rad)
        elif CYLINDER <= kind <= CAPSULE:
            a0 = Rc[0, 0] * p[3] + Rc[1, 0] * p[4] + Rc[2, 0] * p[5]
            a1 = Rc[0, 1] * p[3] + Rc[1, 1] * p[4] + Rc[2, 1] * p[5]
            a2 = Rc[0, 2] * p[3] + Rc[1, 2] * p[4] + Rc[2, 2] * p[5]
            length, rad = p[6], p[7]
            wa = -(q0 * a0 + q1 * a1 + q2 * a2)  # axial coordinate of the origin, w = o - p0 = -q
            ww = q0 * q0 + q1 * q1 + q2 * q2
            perp2 = ww - wa * wa  # squared distance of the origin from the axis line
            if kind == CYLINDER:
                inside = 0.0 <= wa <= length and perp2 < rad * rad
            else:
                sc = min(max(wa, 0.0), length)  # closest axis point to the origin
                inside = ww - 2.0 * sc * wa + sc * sc < rad * rad  # |w - sc a|^2 < r^2
            if inside:
                zb[:, :] = 0.0
                return
            c[3], c[4], c[5], c[6], c[7], c[8] = a0, a1, a2, length, rad, wa
            c[9] = perp2 - rad * rad
            if kind == CAPSULE:
                # second sphere centre q + L a, and cc terms for both end spheres
                c[10], c[11], c[12] = q0 + length * a0, q1 + length * a1, q2 + length * a2
                c[13] = ww - rad * rad
                c[14] = c[10] * c[10] + c[11] * c[11] + c[12] * c[12] - rad * rad
                lo, hi = -rad, length + rad
            else:
                lo, hi = 0.0, length
            u0, u1, u2, v0, v1, v2 = _perp_basis(a0, a1, a2)
            for i in range(8):
                s = hi if i & 1 else lo
                su = rad if i & 2 else -rad
                sv = rad if i & 4 else -rad
                corners[i, 0] = q0 + s * a0 + su * u0 + sv * v0
                corners[i, 1] = q1 + s * a1 + su * u1 + sv * v1
                corners[i, 2] = q2 + s * a2 + su * u2 + sv * v2
        else:  # BOX
            # B = Rc^T R_box: box axes in the camera frame (column j = box axis j).
            inside = True
            for j in range(3):
                b0 = Rc[0, 0] * p[6 + j] + Rc[1, 0] * p[9 + j] + Rc[2, 0] * p[12 + j]
                b1 = Rc[0, 1] * p[6 + j] + Rc[1, 1] * p[9 + j] + Rc[2, 1] * p[12 + j]
                b2 = Rc[0, 2] * p[6 + j] + Rc[1, 2] * p[9 + j] + Rc[2, 2] * p[12 + j]
                # ray in box coordinates: origin_j = -(b . q), direction_j = x b0 + y b1 + b2
                ol = -(b0 * q0 + b1 * q1 + b2 * q2)
                c[3 + 4 * j], c[4 + 4 * j], c[5 + 4 * j], c[6 + 4 * j] = b0, b1, b2, ol
                if abs(ol) > p[3 + j]:
                    inside = False
            if inside:
                zb[:, :] = 0.0
                return
            h0, h1, h2 = p[3], p[4], p[5]
            for i in range(8):
                s0 = h0 if i & 1 else -h0
                s1 = h1 if i & 2 else -h1
                s2 = h2 if i & 4 else -h2
                corners[i, 0] = q0 + s0 * c[3] + s1 * c[7] + s2 * c[11]
                corners[i, 1] = q1 + s0 * c[4] + s1 * c[8] + s2 * c[12]
                corners[i, 2] = q2 + s0 * c[5] + s1 * c[9] + s2 * c[13]
        if not _rect(corners, fx, fy, cx, cy, W, H, rects[m]):
            continue
        if rects[m, 4] > zfar:
            continue
        idx[m] = k
        order_key[m] = rects[m, 4]
        m += 1
    order = np.argsort(order_key[:m])
    for oi in range(m):
        j = order[oi]
        k = idx[j]
        kind = kinds[k]
        c = cam[j]
        u0, u1, v0, v1 = int(rects[j, 0]), int(rects[j, 1]), int(rects[j, 2]), int(rects[j, 3])
        zmin = rects[j, 4]
        if kind == HALFSPACE:
            # t (n . d) = h_c with h_c < 0: a hit in front needs n . d < 0.
            for v in range(H):
                y = y_v[v]
                for u in range(W):
                    nd = c[0] * x_u[u] + c[1] * y + c[2]
                    if nd < -_EPS:
                        t = c[3] / nd
                        if t < zb[v, u]:
                            zb[v, u] = t
            continue
        if kind == SPHERE:
            for v in range(v0, v1 + 1):
                y = y_v[v]
                for u in range(u0, u1 + 1):
                    if zb[v, u] <= zmin:
                        continue
                    x = x_u[u]
                    t = _sphere_t(x, y, x * x + y * y + 1.0, c[0], c[1], c[2], c[3])
                    if t < zb[v, u]:
                        zb[v, u] = t
        elif CYLINDER <= kind <= CAPSULE:
            q0, q1, q2, a0, a1, a2, length, wa, cc = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[8], c[9]
            capsule = kind == CAPSULE
            for v in range(v0, v1 + 1):
                y = y_v[v]
                for u in range(u0, u1 + 1):
                    if zb[v, u] <= zmin:
                        continue
                    x = x_u[u]
                    dd = x * x + y * y + 1.0
                    da = x * a0 + y * a1 + a2  # d . a
                    wd = -(x * q0 + y * q1 + q2)  # w . d with w = -q
                    # Infinite cylinder: |w + t d|^2 - (wa + t da)^2 = r^2
                    #   <=> qa t^2 + 2 qb t + cc = 0, qa = dd - da^2, qb = wd - wa da, cc = |w|^2 - wa^2 - r^2.
                    qa = dd - da * da
                    qb = wd - wa * da
                    if qa > _EPS * dd:
                        disc = qb * qb - qa * cc
                        if disc < 0.0:
                            continue
                        sq = math.sqrt(disc)
                        t1 = (-qb - sq) / qa
                        t2 = (-qb + sq) / qa
                    elif cc <= 0.0:
                        t1, t2 = -np.inf, np.inf  # ray parallel to the axis, within the radius
                    else:
                        continue
                    if t2 < 0.0:
                        continue
                    if not capsule:
                        # Clip to the slab 0 <= wa + t da <= L (flat caps).
                        if abs(da) > _EPS:
                            ta = -wa / da
                            tb = (length - wa) / da
                            if ta > tb:
                                ta, tb = tb, ta
                            t1 = max(t1, ta)
                            t2 = min(t2, tb)
                        elif wa < 0.0 or wa > length:
                            continue
                        if t1 <= t2 and t2 >= 0.0:
                            t = max(t1, 0.0)
                            if t < zb[v, u]:
                                zb[v, u] = t
                    else:
                        # Capsule: the side is hit where the ray enters the infinite cylinder within [0, L];
                        # otherwise the first hit (if any) is on the end sphere on that side (see module doc).
                        te = max(t1, 0.0)
                        s = wa + te * da
                        if 0.0 <= s <= length:
                            t = te
                        elif s < 0.0:
                            t = _sphere_t(x, y, dd, q0, q1, q2, c[13])
                        else:
                            t = _sphere_t(x, y, dd, c[10], c[11], c[12], c[14])
                        if t < zb[v, u]:
                            zb[v, u] = t
        else:  # BOX: slab test in box coordinates
            for v in range(v0, v1 + 1):
                y = y_v[v]
                for u in range(u0, u1 + 1):
                    if zb[v, u] <= zmin:
                        continue
                    x = x_u[u]
                    tin, tout = -np.inf, np.inf
                    hit = True
                    for ax in range(3):
                        dl = x * c[3 + 4 * ax] + y * c[4 + 4 * ax] + c[5 + 4 * ax]
                        ol = c[6 + 4 * ax]
                        h = params[k, 3 + ax]
                        if abs(dl) > _EPS:
                            ta = (-h - ol) / dl
                            tb = (h - ol) / dl
                            if ta > tb:
                                ta, tb = tb, ta
                            tin = max(tin, ta)
                            tout = min(tout, tb)
                            if tin > tout:
                                hit = False
                                break
                        elif abs(ol) > h:
                            hit = False
                            break
                    if hit and tout >= 0.0:
                        t = max(tin, 0.0)
                        if t < zb[v, u]:
                            zb[v, u] = t


@nb.njit(parallel=True, **_NJIT)
def render_batch(
    origins: np.ndarray,
    R_wc: np.ndarray,
    scene_ids: np.ndarray,
    offsets: np.ndarray,
    kinds: np.ndarray,
    params: np.ndarray,
    bsph: np.ndarray,
    x_u: np.ndarray,
    y_v: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    zmin_clip: float,
    zmax_clip: float,
    out: np.ndarray,
) -> None:
    """Render N cameras in parallel into ``out`` (N, H, W) float32, clamped to [zmin_clip, zmax_clip].

    Camera i sees the primitives ``offsets[scene_ids[i]] : offsets[scene_ids[i] + 1]``.
    """
    N, H, W = out.shape
    for i in nb.prange(N):
        zb = np.empty((H, W))
        sid = scene_ids[i]
        _render_camera(
            origins[i], R_wc[i], kinds, params, bsph, offsets[sid], offsets[sid + 1],
            x_u, y_v, fx, fy, cx, cy, zmax_clip, zb,
        )  # fmt: skip
        for v in range(H):
            for u in range(W):
                out[i, v, u] = min(max(zb[v, u], zmin_clip), zmax_clip)


@nb.njit(**_NJIT)
def render_batch_serial(
    origins: np.ndarray,
    R_wc: np.ndarray,
    scene_ids: np.ndarray,
    offsets: np.ndarray,
    kinds: np.ndarray,
    params: np.ndarray,
    bsph: np.ndarray,
    x_u: np.ndarray,
    y_v: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    zmin_clip: float,
    zmax_clip: float,
    out: np.ndarray,
) -> None:
    """``render_batch`` on the calling thread, for a few cameras (e.g. the shield's single image).

    Waking the thread pool costs more than it saves there, badly so when other processes load the cores.
    """
    N, H, W = out.shape
    zb = np.empty((H, W))
    for i in range(N):
        sid = scene_ids[i]
        _render_camera(
            origins[i], R_wc[i], kinds, params, bsph, offsets[sid], offsets[sid + 1],
            x_u, y_v, fx, fy, cx, cy, zmax_clip, zb,
        )  # fmt: skip
        for v in range(H):
            for u in range(W):
                out[i, v, u] = min(max(zb[v, u], zmin_clip), zmax_clip)
