"""2D Perlin (gradient) noise and its conversion into box obstacles.

Classic Perlin construction: random unit gradients on an integer lattice; at a point, dot each of the four
surrounding corners' gradient with the offset from that corner, and blend the four values with the quintic
fade ``f(t) = 6t^5 - 15t^4 + 10t^3`` (zero first and second derivative at lattice lines). Octaves add
copies at double frequency and half amplitude (fractal noise).
"""

from __future__ import annotations

import numpy as np


def _fade(t: np.ndarray) -> np.ndarray:
    # Quintic fade 6t^5 - 15t^4 + 10t^3 (Perlin 2002), in Horner form.
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def perlin2d(rng: np.random.Generator, xs: np.ndarray, ys: np.ndarray, scale: float, octaves: int = 2) -> np.ndarray:
    """Fractal Perlin noise on the grid ``xs`` x ``ys`` (metres), feature size ``scale`` metres.

    Args:
        rng: Source of the lattice gradients.
        xs: Sample x coordinates (nx,).
        ys: Sample y coordinates (ny,).
        scale: Lattice spacing of the first octave (m).
        octaves: Number of octaves (each at twice the frequency and half the amplitude).

    Returns:
        Noise values (nx, ny), roughly in [-1, 1].
    """
    out = np.zeros((len(xs), len(ys)))
    amp = 1.0
    for o in range(octaves):
        freq = (2.0**o) / scale
        u = (xs - xs.min()) * freq
        v = (ys - ys.min()) * freq
        gx, gy = int(np.floor(u.max())) + 2, int(np.floor(v.max())) + 2
        ang = rng.uniform(0.0, 2.0 * np.pi, size=(gx, gy))
        grad = np.stack([np.cos(ang), np.sin(ang)], axis=-1)  # (gx, gy, 2) unit gradients
        i0 = np.floor(u).astype(int)[:, None]
        j0 = np.floor(v).astype(int)[None, :]
        fu = (u - np.floor(u))[:, None]
        fv = (v - np.floor(v))[None, :]

        # Corner value: lattice gradient . offset of the point from that corner, shape (nx, ny).
        c = {}
        for di in (0, 1):
            for dj in (0, 1):
                g = grad[i0 + di, j0 + dj]  # (nx, ny, 2)
                c[di, dj] = g[..., 0] * (fu - di) + g[..., 1] * (fv - dj)
        su, sv = _fade(fu), _fade(fv)
        n0 = c[0, 0] * (1 - su) + c[1, 0] * su
        n1 = c[0, 1] * (1 - su) + c[1, 1] * su
        out += amp * (n0 * (1 - sv) + n1 * sv)
        amp *= 0.5
    return out


def merge_cells(occ: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Greedy rectangle cover of a boolean grid: ``(i0, j0, i1, j1)`` half-open cell ranges.

    Scans cells in order; from each uncovered occupied cell grows a run along axis 0, then extends the run
    along axis 1 while the whole run stays occupied and uncovered. Exact cover, far fewer boxes than cells.
    """
    occ = occ.copy()
    rects = []
    nx, ny = occ.shape
    for j in range(ny):
        for i in range(nx):
            if not occ[i, j]:
                continue
            i1 = i
            while i1 < nx and occ[i1, j]:
                i1 += 1
            j1 = j + 1
            while j1 < ny and np.all(occ[i:i1, j1]):
                j1 += 1
            occ[i:i1, j:j1] = False
            rects.append((i, j, i1, j1))
    return rects
