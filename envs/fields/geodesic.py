"""Geodesic navigation field Phi_g: shortest-path distance to the goal region through inflated free space.

Paper, "Model-based Reward Shaping": Phi_g is a Dijkstra cost map; the navigation reward is
``lambda * clamp(Phi(p_{t-1}) - Phi(p_t), -C, C)``.

**Graph.** Nodes are the grid nodes whose ESDF exceeds the vehicle radius (free space inflated by the vehicle).
Edges join a node to the offsets of a *stencil*, weighted by their Euclidean length:

* ``"26"``: the 26 neighbours (lengths res, sqrt(2) res, sqrt(3) res). Worst-case metric error for a straight
  free path: 8.2 % (a path at 22.5 deg to the axes is approximated by axis + diagonal steps:
  (1 + sqrt 2) / (2 cos 22.5deg) ... = 1.082).
* ``"extended"`` (default): all offsets with ``|dx|, |dy| <= 2``, ``|dz| <= 1`` and gcd 1 (66 edges; adds the
  horizontal "knight" moves (2, 1, 0) and their 3D variants). Horizontal directions are then 26.6 deg apart at
  most, so the worst-case error of a straight horizontal path is ``1 / cos(13.3 deg) - 1 ~= 2.7 %``.

An edge is usable only if both end nodes and every node its segment passes between (all nodes whose
coordinates are the floor or ceil of half the offset, the "no corner cutting" rule) are traversable.

**Solver.** A binary-heap Dijkstra compiled with numba over the implicit grid graph (no edge list in memory),
multi-source from every traversable node inside the goal region (Phi = 0 there). On a one-layer grid (nz = 1, the
camera maps of ``shield_nav.safety.escape``) the edges that leave the layer are dropped before the search: they are
never usable there, so the relaxations are the same, in the same order, for a third of the edge checks.

**Outside the graph.** Reachable nodes keep their Dijkstra distance. Traversable nodes that cannot reach the goal
(sealed pockets) get ``phi_unreachable = max(reachable Phi) + |bounds diagonal|``, a finite penalty larger than
any reachable value. Non-traversable nodes (inside obstacles or within the vehicle radius of one) get the value
of their nearest traversable node plus the straight distance to it, capped at ``phi_unreachable``, so the
field stays continuous-ish where a vehicle grazes an obstacle and is never inf or NaN.
"""

from __future__ import annotations

import math
from itertools import product

import numba
import numpy as np
from scipy import ndimage

STENCILS = ("26", "extended")


def stencil(kind: str = "extended") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Edge offsets of a stencil and what each edge must keep free.

    Returns:
        offsets (K, 3) int64, lengths (K,) float64 in voxels, intermediates (K, 8, 3) int64 (offsets of nodes
        that must be traversable besides the end points, padded), n_intermediate (K,) int64.
    """
    if kind not in STENCILS:
        raise ValueError(f"unknown geodesic stencil {kind!r}; expected one of {STENCILS}")
    reach_xy = 1 if kind == "26" else 2
    offs = []
    for d in product(range(-reach_xy, reach_xy + 1), range(-reach_xy, reach_xy + 1), (-1, 0, 1)):
        if d == (0, 0, 0) or math.gcd(math.gcd(abs(d[0]), abs(d[1])), abs(d[2])) != 1:
            continue
        offs.append(d)
    K = len(offs)
    inter = np.zeros((K, 8, 3), dtype=np.int64)
    n_inter = np.zeros(K, dtype=np.int64)
    for e, d in enumerate(offs):
        # Nodes the segment 0 -> d passes between at its midpoint: each coordinate floor or ceil of d/2.
        choices = [sorted({math.floor(c / 2), math.ceil(c / 2)}) for c in d]
        cells = [c for c in product(*choices) if c != (0, 0, 0) and c != d]
        n_inter[e] = len(cells)
        for m, c in enumerate(cells):
            inter[e, m] = c
    offsets = np.array(offs, dtype=np.int64)
    lengths = np.linalg.norm(offsets.astype(float), axis=1)
    return offsets, lengths, inter, n_inter


@numba.njit(cache=True)
def _heap_push(keys: np.ndarray, vals: np.ndarray, size: int, key: float, val: int) -> None:
    # Sift up: parent of slot i is (i - 1) // 2.
    i = size
    while i > 0:
        p = (i - 1) >> 1
        if keys[p] <= key:
            break
        keys[i] = keys[p]
        vals[i] = vals[p]
        i = p
    keys[i] = key
    vals[i] = val


@numba.njit(cache=True)
def _heap_pop(keys: np.ndarray, vals: np.ndarray, size: int) -> tuple[float, int]:
    # Remove the root; move the last element down: children of slot i are 2i+1, 2i+2.
    top_k, top_v = keys[0], vals[0]
    size -= 1
    key, val = keys[size], vals[size]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and keys[c + 1] < keys[c]:
            c += 1
        if keys[c] >= key:
            break
        keys[i] = keys[c]
        vals[i] = vals[c]
        i = c
    if size > 0:
        keys[i] = key
        vals[i] = val
    return top_k, top_v


@numba.njit(cache=True, nogil=True)  # nogil: goals on one grid are solved on parallel threads
def _dijkstra(
    trav: np.ndarray,
    nx: int,
    ny: int,
    nz: int,
    sources: np.ndarray,
    offsets: np.ndarray,
    lengths: np.ndarray,
    inter: np.ndarray,
    n_inter: np.ndarray,
    dist: np.ndarray,
    cost: np.ndarray,
) -> int:
    """Multi-source Dijkstra on the implicit grid graph; fills ``dist`` (flat, inf = unreached). Returns pops.

    ``cost`` (flat, or empty for none): per-node cost factor; an edge then weighs its length times the mean of its
    end nodes' factors.
    """
    weighted = cost.shape[0] > 0
    sy, sx = nz, ny * nz  # flat index = i * sx + j * sy + k
    cap = max(1024, 2 * sources.shape[0])
    keys = np.empty(cap, dtype=np.float64)
    vals = np.empty(cap, dtype=np.int64)
    size = 0
    for s in sources:
        dist[s] = 0.0
        if size == cap:
            cap *= 2
            keys = np.concatenate((keys, np.empty(cap - keys.shape[0])))
            vals = np.concatenate((vals, np.empty(cap - vals.shape[0], dtype=np.int64)))
        _heap_push(keys, vals, size, 0.0, s)
        size += 1
    pops = 0
    K = offsets.shape[0]
    while size > 0:
        d, u = _heap_pop(keys, vals, size)
        size -= 1
        if d > dist[u]:
            continue  # stale entry (lazy deletion)
        pops += 1
        i = u // sx
        j = (u - i * sx) // sy
        k = u - i * sx - j * sy
        for e in range(K):
            a = i + offsets[e, 0]
            b = j + offsets[e, 1]
            c = k + offsets[e, 2]
            if a < 0 or a >= nx or b < 0 or b >= ny or c < 0 or c >= nz:
                continue
            v = a * sx + b * sy + c
            nd = d + lengths[e] * (0.5 * (cost[u] + cost[v])) if weighted else d + lengths[e]
            if nd >= dist[v] or not trav[v]:
                continue
            ok = True
            for m in range(n_inter[e]):
                w = (i + inter[e, m, 0]) * sx + (j + inter[e, m, 1]) * sy + (k + inter[e, m, 2])
                if not trav[w]:
                    ok = False
                    break
            if not ok:
                continue
            dist[v] = nd
            if size == cap:
                cap *= 2
                keys = np.concatenate((keys, np.empty(cap - keys.shape[0])))
                vals = np.concatenate((vals, np.empty(cap - vals.shape[0], dtype=np.int64)))
            _heap_push(keys, vals, size, nd, v)
            size += 1
    return pops


def geodesic_field(
    traversable: np.ndarray,
    goal_mask: np.ndarray,
    res: float,
    diag: float,
    stencil_kind: str = "extended",
    fill: tuple[np.ndarray, np.ndarray] | None = None,
    cost: np.ndarray | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Phi (nx, ny, nz) float32 in metres, its unreachable value, and the reachable mask.

    Args:
        traversable: Nodes the vehicle's centre may occupy (ESDF > vehicle radius), bool (nx, ny, nz).
        goal_mask: Nodes inside the goal region, bool (nx, ny, nz).
        res: Node spacing (m).
        diag: Length (m) of the scene's bounds diagonal (the unreachable margin).
        stencil_kind: ``"26"`` or ``"extended"`` (see the module docstring).
        fill: ``nearest_traversable(traversable, res)`` when the caller already has it (it depends on
            ``traversable`` only, so several goals on one grid share it); computed here otherwise.
        cost: Per-node cost factor >= 1 (nx, ny, nz), or None: an edge then weighs its length times the mean of
            its end nodes' factors, so Phi is a weighted path length (>= the distance) rather than metres.

    Raises:
        ValueError: If no goal node is traversable (goal region fully blocked), or a bad ``cost``.
    """
    sources = np.flatnonzero((traversable & goal_mask).reshape(-1))
    if sources.size == 0:
        raise ValueError("goal region is fully blocked: none of its grid nodes is traversable")
    offsets, lengths, inter, n_inter = stencil(stencil_kind)
    nx, ny, nz = traversable.shape
    if nz == 1:  # a 2D grid: the edges that leave the layer are never usable, so drop them (the same relaxations,
        flat = offsets[:, 2] == 0  # in the same order, a third of the work)
        offsets, lengths, inter, n_inter = offsets[flat], lengths[flat], inter[flat], n_inter[flat]
    trav_flat = np.ascontiguousarray(traversable.reshape(-1))
    dist = np.full(trav_flat.shape[0], np.inf)
    if cost is None:
        cost_flat = np.zeros(0)
    else:
        cost_flat = np.ascontiguousarray(cost, dtype=np.float64).reshape(-1)
        if cost_flat.shape != trav_flat.shape or not np.isfinite(cost_flat).all() or (cost_flat < 1.0).any():
            raise ValueError(f"cost must be a finite array >= 1 of the grid's shape {traversable.shape}")
    _dijkstra(trav_flat, nx, ny, nz, sources.astype(np.int64), offsets, lengths, inter, n_inter, dist, cost_flat)
    dist = dist.reshape(traversable.shape) * res
    reachable = np.isfinite(dist)
    phi_unreachable = float(dist[reachable].max()) + float(diag)
    phi = np.where(reachable, dist, phi_unreachable)
    if not traversable.all():
        # Non-traversable nodes: value of the nearest traversable node plus the straight distance to it.
        gap, idx = fill if fill is not None else nearest_traversable(traversable, res)
        filled = phi[idx[0], idx[1], idx[2]] + gap
        phi = np.where(traversable, phi, np.minimum(filled, phi_unreachable))
    return phi.astype(np.float32), phi_unreachable, reachable


def nearest_traversable(traversable: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m) from every node to the nearest traversable node and that node's index (3, nx, ny, nz)."""
    return ndimage.distance_transform_edt(~traversable, sampling=res, return_indices=True)
