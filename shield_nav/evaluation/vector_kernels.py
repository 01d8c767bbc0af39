"""Vector kernels of the fixed-order runtime: the convolutions and linear layers, most of a policy step's cost.

:mod:`shield_nav.evaluation.fixed_order` runs a policy through them. They are numba intrinsics that write LLVM
vector instructions: LANES neighbouring outputs (pixels of a convolution, outputs of a linear layer) are multiplied
and added side by side, each lane its own sum in the written order, the accumulators kept in registers. A vector
multiply or add rounds every lane as the scalar instruction does, and LLVM gets no fast-math flag, so nothing is
fused (no FMA) or reassociated: the bits are those of the scalar loops (:func:`conv_lane`; the tests' ordered sums
in Python) on every processor. Their cost: ``python -m shield_nav.bench network``, docs/evaluation.md ("Cost").
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

LANES = 8
"""Doubles per vector of the kernels below: each vector instruction rounds every lane on its own, as scalar code."""
TILE = 8
"""Output channels of a convolution one :func:`conv_tile` call computes (the linear layers tile by `_affine_kernel`)."""


def _vec_type() -> ir.VectorType:
    return ir.VectorType(ir.DoubleType(), LANES)


def _splat(builder: ir.IRBuilder, x: ir.Value) -> ir.Value:
    """``x`` in every lane of a vector."""
    vec = _vec_type()
    one = builder.insert_element(ir.Constant(vec, ir.Undefined), x, ir.Constant(ir.IntType(32), 0))
    return builder.shuffle_vector(
        one, ir.Constant(vec, ir.Undefined), ir.Constant(ir.VectorType(ir.IntType(32), LANES), [0] * LANES)
    )


def _operands(context: Any, builder: ir.IRBuilder, signature: Any, args: list) -> list:
    """An intrinsic's arguments in LLVM: arrays as numba's array structs (``.data``, ``.shape``), integers as intp."""
    out = []
    for t, v in zip(signature.args, args, strict=True):
        if isinstance(t, types.Array):
            out.append(context.make_array(t)(context, builder, v))
        else:
            out.append(context.cast(builder, v, t, types.intp))
    return out


def _c_arrays(*pairs: tuple[Any, int]) -> bool:
    """Whether each (numba type, ndim) pair is a C-contiguous float64 array of that many dimensions."""
    return all(isinstance(a, types.Array) and a.dtype == types.float64 and a.ndim == nd and a.layout == "C"
               for a, nd in pairs)  # fmt: skip


@intrinsic
def conv_tile(typingctx, src, off, w_t, b, out, src0, o0, dst0):  # noqa: ANN001, ANN201, ARG001 (numba's signature)
    """``out[o0 + t, dst0 + l] = b[o0 + t] + sum over j of w_t[j, o0 + t] src[src0 + off[j] + l]``, t < TILE, l < LANES.

    ``src`` is a flat float64 array, ``off`` (C_in k k) the offsets of a patch's values in the order of
    ``nn.Conv2d``'s weights, ``w_t`` (C_in k k, C_out) the weights transposed, ``out`` (C_out, pixels). Each lane's
    sum runs from ``j = 0`` up, one multiply and one add per term, as :func:`conv_lane` writes it; the lanes are
    LANES pixels side by side in a vector register. LLVM gets no fast-math flag, so nothing is fused (no FMA) or
    reassociated.
    """
    ints = isinstance(off, types.Array) and off.dtype == types.int64 and off.ndim == 1 and off.layout == "C"
    ints = ints and all(isinstance(v, types.Integer) for v in (src0, o0, dst0))
    if not (_c_arrays((src, 1), (w_t, 2), (b, 1), (out, 2)) and ints):
        return None
    sig = types.void(src, off, w_t, b, out, src0, o0, dst0)

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
        sa, fa, wa, ba, oa, src0_v, o0_v, dst0_v = _operands(context, builder, signature, args)
        vp = _vec_type().as_pointer()
        n_in = builder.extract_value(wa.shape, 0)
        n_out = builder.extract_value(wa.shape, 1)
        width = builder.extract_value(oa.shape, 1)
        base = builder.gep(sa.data, [src0_v])
        idx = [ir.Constant(n_in.type, t) for t in range(TILE)]
        accs = [cgutils.alloca_once(builder, _vec_type()) for _ in range(TILE)]
        for t in range(TILE):
            builder.store(_splat(builder, builder.load(builder.gep(ba.data, [builder.add(o0_v, idx[t])]))), accs[t])
        with cgutils.for_range(builder, n_in) as loop:
            j = loop.index
            at = builder.load(builder.gep(fa.data, [j]))
            v = builder.load(builder.bitcast(builder.gep(base, [at]), vp), align=8)
            wrow = builder.gep(wa.data, [builder.add(builder.mul(j, n_out), o0_v)])
            for t in range(TILE):
                wt = _splat(builder, builder.load(builder.gep(wrow, [idx[t]])))
                builder.store(builder.fadd(builder.load(accs[t]), builder.fmul(wt, v)), accs[t])
        for t in range(TILE):
            dst = builder.gep(oa.data, [builder.add(builder.mul(builder.add(o0_v, idx[t]), width), dst0_v)])
            builder.store(builder.load(accs[t]), builder.bitcast(dst, vp), align=8)
        return context.get_dummy_value()

    return sig, codegen


@numba.njit(cache=True)
def conv_lane(src: np.ndarray, off: np.ndarray, w_t: np.ndarray, b: np.ndarray, out: np.ndarray, src0: int, o: int,
               dst0: int) -> None:  # fmt: skip
    """Output channel ``o`` of :func:`conv_tile`'s LANES pixels, one pixel at a time: the same sums, the same bits."""
    for lane in range(LANES):
        acc = b[o]
        for j in range(off.shape[0]):
            acc += w_t[j, o] * src[src0 + off[j] + lane]
        out[o, dst0 + lane] = acc


@numba.njit(cache=True)
def conv_block(src: np.ndarray, off: np.ndarray, w_t: np.ndarray, b: np.ndarray, out: np.ndarray, src0: int,
                dst0: int) -> None:  # fmt: skip
    """Every output channel of LANES pixels: TILE channels at a time, then the rest one by one."""
    n_out = w_t.shape[1]
    whole = n_out - n_out % TILE
    for o0 in range(0, whole, TILE):
        conv_tile(src, off, w_t, b, out, src0, o0, dst0)
    for o in range(whole, n_out):
        conv_lane(src, off, w_t, b, out, src0, o, dst0)


@numba.njit(cache=True)
def conv_direct(xp: np.ndarray, off: np.ndarray, w_t: np.ndarray, b: np.ndarray, out: np.ndarray, n_b: int,
                 plane: int, length: int) -> None:  # fmt: skip
    """A stride-1 convolution read in place from the zero-padded input ``xp`` (C, N, hp, wp), flat.

    Output (i, oy, ox) is ``out[:, i length + oy wp + ox]``: its patch starts at input ``i plane + oy wp + ox``
    (``plane = hp wp``), so LANES neighbouring outputs read LANES neighbouring inputs. The columns ``ox >= wo`` of
    each row, and the outputs past ``ho wp`` (``length`` rounds it up to whole vectors), are computed from the
    padding or the next row and dropped by the caller.
    """
    for i in range(n_b):
        for q in range(0, length, LANES):
            conv_block(xp, off, w_t, b, out, i * plane + q, i * length + q)


CHUNK = 256
"""Pixels whose patches a strided convolution gathers at a time (C_in k k x CHUNK doubles, within L2)."""


@numba.njit(cache=True)
def im2col(x: np.ndarray, k: int, stride: int, pad: int, ho: int, wo: int, p0: int, out: np.ndarray) -> None:
    """Patches of pixels ``p0 ..`` of ``x`` (C, N, H, W) as the columns of ``out`` (C k k, CHUNK).

    Pixel ``p = (i ho + oy) wo + ox``; row (c, ky, kx), the order of ``nn.Conv2d``'s weights; the zero padding, and
    the columns past the last pixel, are zeros.
    """
    c_in, n_b, h, wd = x.shape
    n = min(out.shape[1], n_b * ho * wo - p0)
    row = 0
    for c in range(c_in):
        for ky in range(k):
            for kx in range(k):
                dst = out[row]
                i, oy, ox = p0 // (ho * wo), p0 // wo % ho, p0 % wo
                q = 0
                while q < n:  # the rest of one output row at a time
                    seg = min(wo - ox, n - q)
                    iy = oy * stride - pad + ky
                    for t in range(seg):
                        ix = (ox + t) * stride - pad + kx
                        dst[q + t] = x[c, i, iy, ix] if 0 <= iy < h and 0 <= ix < wd else 0.0
                    q += seg
                    ox = 0
                    oy += 1
                    if oy == ho:
                        oy = 0
                        i += 1
                for q in range(n, out.shape[1]):
                    dst[q] = 0.0
                row += 1


@numba.njit(cache=True)
def conv_strided(x: np.ndarray, k: int, stride: int, pad: int, ho: int, wo: int, w_t: np.ndarray, b: np.ndarray,
                  out: np.ndarray) -> None:  # fmt: skip
    """A convolution of any stride through gathered patches: ``out`` (C_out, N ho wo rounded up to CHUNK)."""
    cols = np.empty((w_t.shape[0], CHUNK))
    flat = cols.reshape(-1)
    off = np.arange(w_t.shape[0]) * CHUNK
    for p0 in range(0, out.shape[1], CHUNK):
        im2col(x, k, stride, pad, ho, wo, p0, cols)
        for q in range(0, CHUNK, LANES):
            conv_block(flat, off, w_t, b, out, q, p0 + q)


def _affine_kernel(rows: int, vectors: int) -> Any:
    """An intrinsic ``(x, w_t, b, out, i0, o0)`` computing ``rows`` rows by ``vectors`` vectors of a linear layer.

    For ``i`` in ``i0 .. i0 + rows`` and ``o`` in ``o0 .. o0 + vectors LANES``, ``out[i, o] = b[o] + sum over j of
    x[i, j] w_t[j, o]``. ``w_t`` (inputs, outputs), ``b`` and ``out``'s rows hold whole vectors (outputs padded with
    zeros to a multiple of LANES by :func:`_t`); each sum runs from the first input to the last, one multiply and one
    add per term, as a scalar loop would; ``rows`` rows share each load of the weights.
    """

    @intrinsic
    def kernel(typingctx, x, w_t, b, out, i0, o0):  # noqa: ANN001, ANN202, ARG001 (numba's intrinsic signature)
        if not (_c_arrays((x, 2), (w_t, 2), (b, 1), (out, 2)) and isinstance(i0, types.Integer)
                and isinstance(o0, types.Integer)):  # fmt: skip
            return None
        sig = types.void(x, w_t, b, out, i0, o0)

        def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
            xa, wa, ba, oa, i0_v, o0_v = _operands(context, builder, signature, args)
            vp = _vec_type().as_pointer()
            n_in = builder.extract_value(xa.shape, 1)
            n_out = builder.extract_value(wa.shape, 1)
            width = builder.extract_value(oa.shape, 1)
            offs = [ir.Constant(n_in.type, LANES * t) for t in range(vectors)]
            accs = [[cgutils.alloca_once(builder, _vec_type()) for _ in range(vectors)] for _ in range(rows)]
            for t in range(vectors):
                bias = builder.load(builder.bitcast(builder.gep(ba.data, [builder.add(o0_v, offs[t])]), vp), align=8)
                for r in range(rows):
                    builder.store(bias, accs[r][t])
            xrows = [builder.gep(xa.data, [builder.mul(builder.add(i0_v, ir.Constant(n_in.type, r)), n_in)])
                     for r in range(rows)]  # fmt: skip
            with cgutils.for_range(builder, n_in) as loop:
                j = loop.index
                wrow = builder.gep(wa.data, [builder.add(builder.mul(j, n_out), o0_v)])
                ws = [builder.load(builder.bitcast(builder.gep(wrow, [offs[t]]), vp), align=8) for t in range(vectors)]
                for r in range(rows):
                    xs = _splat(builder, builder.load(builder.gep(xrows[r], [j])))
                    for t in range(vectors):
                        builder.store(builder.fadd(builder.load(accs[r][t]), builder.fmul(xs, ws[t])), accs[r][t])
            for r in range(rows):
                orow = builder.gep(oa.data, [builder.add(builder.mul(builder.add(i0_v, ir.Constant(n_in.type, r)),
                                                                     width), o0_v)])  # fmt: skip
                for t in range(vectors):
                    builder.store(builder.load(accs[r][t]), builder.bitcast(builder.gep(orow, [offs[t]]), vp), align=8)
            return context.get_dummy_value()

        return sig, codegen

    return kernel


_affine_4x4 = _affine_kernel(4, 4)
_affine_4x1 = _affine_kernel(4, 1)
_affine_1x4 = _affine_kernel(1, 4)
_affine_1x1 = _affine_kernel(1, 1)


@numba.njit(cache=True)
def affine(x: np.ndarray, w_t: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out[n] = b + sum over j of x[n, j] w_t[j]``, each output's sum from the first input to the last.

    ``w_t`` is the weight transposed (inputs, outputs), its outputs padded to whole vectors (:func:`_t`), as are
    ``b`` and ``out``'s rows. Tiles of 4 rows by 4 vectors of outputs, then the rest of the outputs one vector at a
    time, then the last rows one at a time: every tile gives the scalar loop's bits.
    """
    n_b = x.shape[0]
    n_out = w_t.shape[1]
    four = n_out - n_out % (4 * LANES)
    rows4 = n_b - n_b % 4
    for i in range(0, rows4, 4):
        for o0 in range(0, four, 4 * LANES):
            _affine_4x4(x, w_t, b, out, i, o0)
        for o0 in range(four, n_out, LANES):
            _affine_4x1(x, w_t, b, out, i, o0)
    for i in range(rows4, n_b):
        for o0 in range(0, four, 4 * LANES):
            _affine_1x4(x, w_t, b, out, i, o0)
        for o0 in range(four, n_out, LANES):
            _affine_1x1(x, w_t, b, out, i, o0)
