"""Exports of the actor.

Its deployable module (:class:`ExportedDepthGRU`), written as TorchScript and ONNX files checked against the eager
model.
"""

from __future__ import annotations

import copy
import logging
import os
import warnings
from typing import TYPE_CHECKING

import torch
import torch.nn as nn

if TYPE_CHECKING:  # the model builds its exports from this module
    from shield_nav.policies.models import DepthGRUModel


class ExportedRecurrentPolicy(nn.Module):
    """What every exported actor shares: an explicit hidden state ``(L, B, hidden_size)`` and one env's dummy inputs.

    A subclass sets ``obs_dim``, ``depth_shape``, ``num_layers``, ``hidden_size``, ``input_names`` and
    ``output_names`` and defines ``forward(obs, depth, h_in) -> (actions, h_out)``.
    """

    @torch.jit.export
    def initial_state(self, batch_size: int) -> torch.Tensor:
        """Zero hidden state ``(L, batch_size, hidden_size)``."""
        return torch.zeros(self.num_layers, batch_size, self.hidden_size)

    @torch.jit.export
    def reset(self) -> None:
        """No-op (the state is an explicit input); kept because rsl-rl's exported policies have it."""
        pass

    @torch.jit.unused
    def get_dummy_inputs(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Inputs for ONNX tracing: one env."""
        return (
            torch.zeros(1, self.obs_dim),
            torch.zeros(1, *self.depth_shape),
            torch.zeros(self.num_layers, 1, self.hidden_size),
        )


class ExportedDepthGRU(ExportedRecurrentPolicy):
    """Deterministic, stateless export of a :class:`DepthGRUModel` (TorchScript and ONNX).

    ``forward(obs (B, S), depth (B, C, H, W), h_in (L, B, Hd)) -> (actions (B, A), h_out (L, B, Hd))``: the state
    normaliser is frozen, the action is the distribution mean. The caller owns the hidden state: start from zeros
    (``initial_state(B)``) and zero the rows of envs whose episode ended, as the training rollout does.
    """

    def __init__(self, model: DepthGRUModel, verbose: bool = False) -> None:
        """Copy the parts of ``model`` (on the CPU) needed for inference."""
        super().__init__()
        self.verbose = verbose
        self.obs_normalizer = copy.deepcopy(model.obs_normalizer).cpu()
        self.encoder = copy.deepcopy(model.encoder).cpu()
        self.gru = copy.deepcopy(model.rnn.rnn).cpu()  # the bare nn.GRU, no stored state
        self.mlp = copy.deepcopy(model.mlp).cpu()
        if model.distribution is not None:
            self.deterministic_output = model.distribution.as_deterministic_output_module()
        else:
            self.deterministic_output = nn.Identity()
        self.obs_dim = int(model.obs_dim)
        self.depth_shape = list(model.depth_shape)
        self.num_layers = int(self.gru.num_layers)
        self.hidden_size = int(self.gru.hidden_size)
        self.input_names = ["obs", model.depth_group, "h_in"]
        """ONNX input names (rsl-rl's exporter reads them)."""
        self.output_names = ["actions", "h_out"]
        """ONNX output names."""

    def forward(self, obs: torch.Tensor, depth: torch.Tensor, h_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One policy step for a batch of B envs; returns the actions and the next hidden state."""
        x = torch.cat([self.obs_normalizer(obs), self.encoder(depth)], dim=-1)  # (B, S + F)
        y, h_out = self.gru(x.unsqueeze(0), h_in)  # (1, B, Hd), (L, B, Hd)
        return self.deterministic_output(self.mlp(y.squeeze(0))), h_out


def export_policy(
    model: DepthGRUModel, out_dir: str, jit_name: str = "policy.pt", onnx_name: str = "policy.onnx"
) -> dict[str, str]:
    """Write TorchScript and ONNX exports of ``model`` with a dynamic batch dimension; return their paths.

    The ONNX graph has inputs ``obs (B, S)``, ``<depth group> (B, C, H, W)``, ``h_in (L, B, Hd)`` and outputs
    ``actions (B, A)``, ``h_out (L, B, Hd)`` (opset 18, the ``torch.export``-based exporter, a dynamic batch).
    """
    return export_module(model.as_onnx(verbose=False), out_dir, jit_name, onnx_name)


def export_module(
    exp: nn.Module, out_dir: str, jit_name: str = "policy.pt", onnx_name: str = "policy.onnx"
) -> dict[str, str]:
    """Write the TorchScript and ONNX files of an export module; return their paths.

    ``exp``: ``forward(obs, depth, h_in) -> (actions, h_out)`` with ``input_names``, ``output_names`` and
    ``get_dummy_inputs``, e.g. :class:`ExportedDepthGRU` or :class:`shield_nav.tools.ensemble.ExportedEnsemble`.
    """
    os.makedirs(out_dir, exist_ok=True)
    jit_path = os.path.join(out_dir, jit_name)
    onnx_path = os.path.join(out_dir, onnx_name)
    exp.eval()
    torch.jit.script(exp).save(jit_path)
    # torch.export specialises a dimension of size 1, so the example batch has two rows; the batch is dynamic.
    obs, depth, h_in = exp.get_dummy_inputs()
    example = (obs.repeat(2, 1), depth.repeat(2, 1, 1, 1), h_in.repeat(1, 2, 1))
    batch = torch.export.Dim("batch", min=1, max=65536)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=FutureWarning)  # torch.export's notices about its own internals
        warnings.filterwarnings("ignore", message=r".*axis name: batch will not be used.*")  # one Dim for three inputs
        warnings.filterwarnings("ignore", message=r".*_flat_weights.*were assigned during export.*")  # nn.GRU's
        registration = logging.getLogger("torch.onnx._internal.exporter._registration")
        level = registration.level
        registration.setLevel(logging.ERROR)  # it names the torchvision ops it skips; no policy uses them
        try:
            torch.onnx.export(
                exp,
                example,
                onnx_path,
                input_names=exp.input_names,
                output_names=exp.output_names,
                dynamic_shapes=({0: batch}, {0: batch}, {1: batch}),
                opset_version=18,
                dynamo=True,
                verbose=False,
            )
        finally:
            registration.setLevel(level)
    return {"jit": jit_path, "onnx": onnx_path}
