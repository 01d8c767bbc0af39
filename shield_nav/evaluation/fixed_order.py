"""The exported depth actor run in a fixed order of floating-point operations (``network: fixed_order``).

onnxruntime and torch pick their convolution and matrix kernels by the processor's vector extensions, and each kernel
sums its products in its own order: the same policy file gives actions that differ in the last bits from one
processor kind to another, and closed-loop flight grows such differences into other trajectories (13-16 of 100
trials end otherwise when only the network's kernels change; docs/evaluation.md, "Reproducing a table"). This module
runs the same weights (read from a training checkpoint ``model*.pt`` through
:func:`shield_nav.training.actor.actor_from_checkpoint`, which needs no TorchScript and is what a packaged folder is
read through, or from the TorchScript export ``policy.pt``) with loops compiled by numba without ``fastmath``: every
sum runs in one written order in float64, no operation is fused or reassociated, and the exponential is this module's
own polynomial (libm's may differ between its FMA and non-FMA variants). So the actions are the same bits on every
processor numba compiles for; the test suite checks that a baseline x86-64 build (``NUMBA_CPU_NAME=generic``) gives
the host build's bits.

The convolutions and linear layers, most of the cost, run as explicit LLVM vector instructions (numba intrinsics
that multiply and add LANES neighbouring outputs at once, each lane its own sum in the written order, their
accumulators kept in registers): a vector multiply or add rounds every lane as the scalar instruction would, so
the bits are those of the scalar loops (:mod:`shield_nav.evaluation.vector_kernels`).

The layers are those of :class:`shield_nav.policies.models.DepthGRUModel` exports: the state normaliser, the convolution
stack (``Conv2d``, ``ReLU``, ``MaxPool2d(2)``), ``Flatten -> Linear -> ReLU``, a GRU (any number of layers, PyTorch's
gate equations), the MLP head (``Linear`` with ``ELU`` / ``ReLU`` / ``Tanh``) and the multi-hypothesis selection.
Anything else is refused by name when the file is loaded.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from shield_nav.evaluation.vector_kernels import CHUNK, LANES, affine, conv_direct, conv_strided

_LN2_HI = 6.93147180369123816490e-01  # ln 2 split so that k * _LN2_HI is exact for |k| < 2^20 (fdlibm's split)
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e00
# 1 / j! for j = 0..13: the Taylor series of exp on |r| <= ln(2) / 2 to below 1e-17 relative.
_EXP_COEFFS = np.array([1.0 / math.factorial(j) for j in range(14)])


@numba.njit(cache=True)
def fixed_exp(x: float) -> float:
    """``exp(x)`` in float64 from additions and multiplications only (relative error about 2e-16).

    ``x = k ln 2 + r`` with integer ``k`` and ``|r| <= ln(2) / 2`` (Cody-Waite reduction), ``exp(r)`` by its Taylor
    series to degree 13 in Horner form, then the exact scaling by ``2^k``.
    """
    if x != x:
        return x
    if x > 709.0:
        return np.inf
    if x < -745.0:
        return 0.0
    k = math.floor(x * _INV_LN2 + 0.5)
    r = (x - k * _LN2_HI) - k * _LN2_LO
    p = _EXP_COEFFS[13]
    for j in range(12, -1, -1):
        p = p * r + _EXP_COEFFS[j]
    return math.ldexp(p, int(k))


@numba.njit(cache=True)
def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + fixed_exp(-x))


@numba.njit(cache=True)
def _tanh(x: float) -> float:
    if x > 20.0:
        return 1.0
    if x < -20.0:
        return -1.0
    e = fixed_exp(2.0 * x)
    return (e - 1.0) / (e + 1.0)


@numba.njit(cache=True)
def _crop(raw: np.ndarray, pitch: int, length: int, relu: bool, out: np.ndarray) -> None:
    """``out[o, i, y, x] = raw[o, i length + y pitch + x]``, through ``ReLU`` if ``relu``.

    The ReLU keeps NaN and gives +0 for -0, as numpy's vector ``maximum(v, 0)`` does.
    """
    c, n_b, ho, wo = out.shape
    for o in range(c):
        for i in range(n_b):
            for y in range(ho):
                base = i * length + y * pitch
                for x in range(wo):
                    v = raw[o, base + x]
                    out[o, i, y, x] = v if not relu or v > 0.0 or v != v else 0.0


class _Workspace:
    """Arrays the layers reuse from one call to the next, one set per thread.

    Each is kept under a key that names every size its contents depend on; a policy flies one batch size per unit,
    so few are made.
    """

    def __init__(self) -> None:
        self._local = threading.local()

    def get(self, key: tuple, make: Callable[[], np.ndarray]) -> np.ndarray:
        """The array under ``key``, made by ``make()`` the first time."""
        store = self._local.__dict__.setdefault("arrays", {})
        if key not in store:
            store[key] = make()
        return store[key]

    def empty(self, key: tuple, shape: tuple[int, ...]) -> np.ndarray:
        """An array of ``shape`` that every call overwrites whole (its contents carry nothing over)."""
        return self.get((*key, shape), lambda: np.empty(shape))


def _convolve(x: np.ndarray, c: _Conv, work: _Workspace, layer: int) -> np.ndarray:
    """``nn.Conv2d`` of ``x`` (C, N, H, W) with ``c``'s weights, and its ReLU: (C_out, N, ho, wo).

    Each output's sum runs in the order of the weights (c, ky, kx). The result is ``work``'s array: it holds until
    the next call for this layer.
    """
    n_in, n_b, h, wd = x.shape
    k, s, pad = c.kernel, c.stride, c.pad
    ho, wo = (h + 2 * pad - k) // s + 1, (wd + 2 * pad - k) // s + 1
    n_out = c.w_t.shape[1]
    if s != 1:
        raw = work.empty(("raw", layer), (n_out, -(-n_b * ho * wo // CHUNK) * CHUNK))
        conv_strided(x, k, s, pad, ho, wo, c.w_t, c.b, raw)
        pitch, length = wo, ho * wo
    else:
        hp, wp = h + 2 * pad, wd + 2 * pad
        plane = hp * wp
        length = -(-ho * wp // LANES) * LANES  # the outputs of one image, rows of wp, in whole vectors
        # zeros once: only the image's part is written again, so the padding stays zero; room for the last
        # vector's reads past the last row
        xp = work.get(("padded", layer, x.shape), lambda: np.zeros(n_in * n_b * plane + LANES + k))
        xp[: n_in * n_b * plane].reshape(n_in, n_b, hp, wp)[:, :, pad : pad + h, pad : pad + wd] = x

        def offsets() -> np.ndarray:  # each patch value's place relative to the patch's first, in the weights' order
            cc, ky, kx = np.meshgrid(np.arange(n_in), np.arange(k), np.arange(k), indexing="ij")
            return np.ascontiguousarray((cc * (n_b * plane) + ky * wp + kx).reshape(-1), dtype=np.int64)

        off = work.get(("offsets", layer, x.shape), offsets)
        raw = work.empty(("raw", layer), (n_out, n_b * length))
        conv_direct(xp, off, c.w_t, c.b, raw, n_b, plane, length)
        pitch = wp
    out = work.empty(("out", layer), (n_out, n_b, ho, wo))
    _crop(raw, pitch, length, c.relu, out)
    return out


@numba.njit(cache=True)
def _max_pool2(x: np.ndarray, out: np.ndarray) -> None:
    """2 x 2 max pooling, stride 2, no padding, of ``x`` (C, N, H, W) (odd sizes floored, as ``nn.MaxPool2d(2)``)."""
    c, n_b, ho, wo = out.shape
    for o in range(c):
        for i in range(n_b):
            for y in range(ho):
                for xx in range(wo):
                    a = x[o, i, 2 * y, 2 * xx]
                    for v in (x[o, i, 2 * y, 2 * xx + 1], x[o, i, 2 * y + 1, 2 * xx], x[o, i, 2 * y + 1, 2 * xx + 1]):
                        if v > a or v != v:
                            a = v
                    out[o, i, y, xx] = a


@numba.njit(cache=True)
def _activate(y: np.ndarray, act: int) -> None:
    """In place: act 1 ReLU, 2 ELU, 3 tanh (0: none)."""
    n_b, n = y.shape
    for i in range(n_b):
        for o in range(n):
            v = y[i, o]
            if act == 1:
                y[i, o] = v if v > 0.0 else 0.0
            elif act == 2:
                y[i, o] = v if v > 0.0 else fixed_exp(v) - 1.0
            elif act == 3:
                y[i, o] = _tanh(v)


@numba.njit(cache=True)
def _gru_gates(gi: np.ndarray, gh: np.ndarray, h: np.ndarray, out: np.ndarray) -> None:
    """PyTorch's GRU update from the input and hidden projections (gates ordered r, z, n)."""
    n_b, hd = h.shape
    for i in range(n_b):
        for j in range(hd):
            r = _sigmoid(gi[i, j] + gh[i, j])
            z = _sigmoid(gi[i, hd + j] + gh[i, hd + j])
            nn = _tanh(gi[i, 2 * hd + j] + r * gh[i, 2 * hd + j])
            out[i, j] = (1.0 - z) * nn + z * h[i, j]


ACTIVATIONS = {"ReLU": 1, "ELU": 2, "Tanh": 3}
"""MLP activations the fixed-order actor runs (code passed to ``_activate``)."""


@dataclass
class _Conv:
    w_t: np.ndarray
    """Weights transposed (C_in * k * k, C_out), rows ordered (c, ky, kx)."""
    b: np.ndarray
    kernel: int
    stride: int
    pad: int
    relu: bool
    pool: bool


def _f64(t: Any) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)


def _kind(layer: Any) -> str:
    """A layer's class name: a TorchScript module keeps it as ``original_name``, an eager one is its type."""
    name = getattr(layer, "original_name", None)
    return name if isinstance(name, str) else type(layer).__name__


def _children(module: Any) -> list[tuple[str, Any]]:
    """A module's children in order, repeats included.

    ``named_children`` yields a module shared by two slots once, and rsl-rl's MLP shares one activation module
    between its layers.
    """
    return list(module._modules.items())


@dataclass
class _Linear:
    """A Linear layer in the layout :func:`affine` reads."""

    w_t: np.ndarray
    """The weight transposed (inputs, outputs), float64, its outputs padded with zero columns to whole vectors."""
    b: np.ndarray
    """The bias, padded with zeros as ``w_t``'s columns."""
    n_out: int
    """Outputs before the padding."""

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """``x (N, inputs) -> (N, n_out)``: a view of a padded, C-contiguous result."""
        out = np.empty((x.shape[0], self.w_t.shape[1]))
        affine(np.ascontiguousarray(x), self.w_t, self.b, out)
        return out[:, : self.n_out]


def _t(weight: Any, bias: Any) -> _Linear:
    """A Linear layer's weight (outputs, inputs) and bias, read as a :class:`_Linear`."""
    w = _f64(weight)
    n_out, n_in = w.shape
    width = -(-n_out // LANES) * LANES
    w_t = np.zeros((n_in, width))
    w_t[:, :n_out] = w.T
    b = np.zeros(width)
    b[:n_out] = _f64(bias)
    return _Linear(w_t, b, n_out)


class FixedOrderActor:
    """The layers of a ``DepthGRUModel`` export, run by :mod:`numba` loops in one fixed order.

    The export is the TorchScript file's module (``torch.jit.load``) or the eager
    :class:`~shield_nav.policies.export.ExportedDepthGRU` of a training checkpoint (what ``load_policy`` builds for a
    ``model*.pt``); both hold the same parameters, so both give the same bits.

    ``forward(state (N, S), depth (N, C, H, W), h (L, N, Hd)) -> (head (N, K * (A + 1)) or (N, A), h_out)``,
    float64 throughout; :meth:`act` adds the hypothesis selection (the best-scored candidate, the first on ties, as
    ``HypothesisSelect``).
    """

    def __init__(self, module: Any, file: str) -> None:
        """Read the weights of an export ``module`` (TorchScript or eager); ``file`` names it in errors."""
        self.file = file
        self._work = _Workspace()

        def refuse(what: str) -> None:
            raise ValueError(f"network 'fixed_order': {file!r} has {what}, which the fixed-order runtime does not run "
                             "(it runs the DepthGRUModel export: normaliser, Conv2d/ReLU/MaxPool2d(2), Flatten-Linear-"
                             "ReLU, GRU, Linear/ELU/ReLU/Tanh, HypothesisSelect); use network 'export'")  # fmt: skip

        for attr in ("obs_normalizer", "encoder", "gru", "mlp", "deterministic_output"):
            if not hasattr(module, attr):
                refuse(f"no {attr!r} submodule")
        norm = module.obs_normalizer
        if _kind(norm) == "EmpiricalNormalization":
            self.norm = (_f64(norm._mean).reshape(-1), _f64(norm._std).reshape(-1), float(norm.eps))
        elif _kind(norm) == "Identity":
            self.norm = None
        else:
            refuse(f"a state normaliser {_kind(norm)!r}")
        if _kind(module.deterministic_output) != "_IdentityDeterministicOutput":
            refuse(f"an output transform {_kind(module.deterministic_output)!r}")
        self.convs: list[_Conv] = []
        for name, layer in _children(module.encoder.conv):
            kind = _kind(layer)
            if kind == "Conv2d":
                if tuple(layer.dilation) != (1, 1) or layer.groups != 1 or layer.padding_mode != "zeros":
                    refuse(f"a dilated, grouped or non-zero-padded convolution (encoder.conv.{name})")
                st, pd = tuple(layer.stride), tuple(layer.padding)
                if st[0] != st[1] or pd[0] != pd[1] or layer.kernel_size[0] != layer.kernel_size[1]:
                    refuse(f"a non-square convolution (encoder.conv.{name})")
                w = _f64(layer.weight)
                b = _f64(layer.bias) if layer.bias is not None else np.zeros(w.shape[0])
                self.convs.append(_Conv(np.ascontiguousarray(w.reshape(w.shape[0], -1).T), b, int(w.shape[2]),
                                        int(st[0]), int(pd[0]), False, False))  # fmt: skip
            elif kind == "ReLU" and self.convs and not self.convs[-1].pool:
                self.convs[-1].relu = True
            elif kind == "MaxPool2d" and self.convs and layer.kernel_size == 2 and layer.stride == 2 \
                    and layer.padding == 0 and not layer.ceil_mode:  # fmt: skip
                self.convs[-1].pool = True
            else:
                refuse(f"a layer {kind!r} at encoder.conv.{name}")
        proj = [_kind(c) for _, c in _children(module.encoder.proj)]
        if proj != ["Flatten", "Linear", "ReLU"]:
            refuse(f"an encoder projection {proj}")
        lin = getattr(module.encoder.proj, "1")
        self.proj = _t(lin.weight, lin.bias)
        self.num_layers, self.hidden_size = int(module.num_layers), int(module.hidden_size)
        self.gru = []
        for k in range(self.num_layers):
            g = module.gru
            self.gru.append((_t(getattr(g, f"weight_ih_l{k}"), getattr(g, f"bias_ih_l{k}")),
                             _t(getattr(g, f"weight_hh_l{k}"), getattr(g, f"bias_hh_l{k}"))))  # fmt: skip
        heads = dict(_children(module.mlp))
        core = heads.get("0") if "0" in heads and _kind(heads["0"]) == "MLP" else module.mlp
        self.mlp: list[tuple[_Linear, int]] = []
        for name, layer in _children(core):
            kind = _kind(layer)
            if kind == "Linear":
                self.mlp.append((_t(layer.weight, layer.bias), 0))
            elif kind in ACTIVATIONS and self.mlp and self.mlp[-1][1] == 0:
                self.mlp[-1] = (self.mlp[-1][0], ACTIVATIONS[kind])
            else:
                refuse(f"a head layer {kind!r} ({name})")
        select = heads.get("1") if core is not module.mlp else None
        if select is not None and _kind(select) != "HypothesisSelect":
            refuse(f"a head selection {_kind(select)!r}")
        self.num_hypotheses = int(select.num_hypotheses) if select is not None else 1
        self.action_dim = int(select.action_dim) if select is not None else self.mlp[-1][0].n_out
        if select is not None and self.mlp[-1][0].n_out != self.num_hypotheses * (self.action_dim + 1):
            refuse(f"a head of {self.mlp[-1][0].n_out} outputs for {self.num_hypotheses} hypotheses")

    def forward(self, state: np.ndarray, depth: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The head's raw outputs (N, K (A + 1)) and the new hidden state (L, N, Hd), both float64."""
        x = np.ascontiguousarray(state, dtype=np.float64)
        if self.norm is not None:
            mean, std, eps = self.norm
            x = (x - mean) / (std + eps)  # elementwise: one rounding per value on every processor
        img = np.ascontiguousarray(np.asarray(depth, dtype=np.float64).transpose(1, 0, 2, 3))  # (C, N, H, W)
        for layer, c in enumerate(self.convs):
            out = _convolve(img, c, self._work, layer)
            if c.pool:
                c_o, n_o, h_o, w_o = out.shape
                pooled = self._work.empty(("pooled", layer), (c_o, n_o, h_o // 2, w_o // 2))
                _max_pool2(out, pooled)
                out = pooled
            img = out
        img = np.ascontiguousarray(img.transpose(1, 0, 2, 3))  # (N, C, H, W): flattened in nn.Flatten's order
        feat = self.proj(img.reshape(img.shape[0], -1))
        _activate(feat, 1)
        y = np.concatenate((x, feat), axis=1)
        h_in = np.ascontiguousarray(h, dtype=np.float64)
        h_out = np.empty_like(h_in)
        for k, (ih, hh) in enumerate(self.gru):
            _gru_gates(ih(y), hh(h_in[k]), h_in[k], h_out[k])
            y = h_out[k]
        for layer, act in self.mlp:
            y = layer(y)
            if act:
                _activate(y, act)
        return np.ascontiguousarray(y), h_out

    def candidates(self, head: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(actions (N, K, A), scores (N, K))`` of a multi-hypothesis head (K = 1: the head is the action)."""
        k, a = self.num_hypotheses, self.action_dim
        if k == 1 and head.shape[1] == a:
            return head[:, None, :], np.zeros((len(head), 1))
        return head[:, : k * a].reshape(-1, k, a), head[:, k * a :]

    def act(self, state: np.ndarray, depth: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The chosen actions (N, A) (the best-scored hypothesis, the first on ties) and the new hidden state."""
        head, h_out = self.forward(state, depth, h)
        cands, scores = self.candidates(head)
        best = np.argmax(scores, axis=1)  # the first maximum, as torch.argmax on these finite scores
        return cands[np.arange(len(cands)), best], h_out
