"""Average several trained depth actors into one exported policy.

``python -m shield_nav.tools.ensemble RUN_OR_CKPT [RUN_OR_CKPT ...] --out DIR``

Each argument is a training checkpoint (``model_<it>.pt``), a run folder (its latest ``model_<it>.pt``) or a packaged
policy folder (``model.pt``). The members must share the observation layout and the env sections a policy is
evaluated with (``action``, ``camera``, ``vehicle``). ``DIR`` gets ``policy.onnx`` and TorchScript ``policy.pt``
with the single-policy signature ``(obs (B, S), depth (B, C, H, W), h_in (L, B, K Hd)) -> (actions (B, 4), h_out)``:
every member runs its own GRU on its slice of the hidden state, its mean action is clipped to the action box
``[-1, 1]`` (what the env would apply to it alone) and the K clipped actions are averaged. So ``eval.py``,
the shield and deployment take the ensemble as they take one policy (``--checkpoint full=DIR``). ``DIR`` also gets
``params/config.yaml`` (the first member's resolved config, for the env sections) and ``meta.json`` (members and
the sha256 of every file).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re

import torch
import torch.nn as nn

from envs.config import to_dict, to_yaml
from shield_nav.evaluation.policies import POLICY_ENV_SECTIONS, _sha256
from shield_nav.policies.export import ExportedDepthGRU, ExportedRecurrentPolicy, export_module

__all__ = ["ExportedEnsemble", "build_ensemble", "member_checkpoint"]


class ExportedEnsemble(ExportedRecurrentPolicy):
    """K exported depth actors as one: the mean of their clipped actions, the hidden states side by side.

    ``h_in`` is ``(L, B, K * Hd)``; member ``k`` reads and writes ``[..., k * Hd : (k + 1) * Hd]``. A zero ``h_in``
    starts every member from zeros, as a single policy starts.
    """

    def __init__(self, members: list[ExportedDepthGRU]) -> None:
        """Wrap ``members`` (at least two, one observation layout and one GRU shape)."""
        super().__init__()
        if len(members) < 2:
            raise ValueError(f"an ensemble needs at least two members, got {len(members)}")
        first = members[0]
        for k, m in enumerate(members[1:], start=1):
            if (m.obs_dim, list(m.depth_shape), m.num_layers, m.hidden_size) != (
                first.obs_dim, list(first.depth_shape), first.num_layers, first.hidden_size):  # fmt: skip
                raise ValueError(
                    f"member {k} has obs {m.obs_dim}, depth {list(m.depth_shape)}, GRU {m.num_layers} x "
                    f"{m.hidden_size}; member 0 has {first.obs_dim}, {list(first.depth_shape)}, "
                    f"{first.num_layers} x {first.hidden_size}"
                )
        self.members = nn.ModuleList(members)
        self.size = len(members)
        self.member_hidden = int(first.hidden_size)
        self.obs_dim = int(first.obs_dim)
        self.depth_shape = list(first.depth_shape)
        self.num_layers = int(first.num_layers)
        self.hidden_size = self.size * self.member_hidden
        self.input_names = list(first.input_names)
        self.output_names = list(first.output_names)

    def forward(self, obs: torch.Tensor, depth: torch.Tensor, h_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One step of every member; returns the mean clipped action and the members' next hidden states."""
        hd = self.member_hidden
        acts: list[torch.Tensor] = []
        outs: list[torch.Tensor] = []
        for k, member in enumerate(self.members):
            a, h = member(obs, depth, h_in[:, :, k * hd : (k + 1) * hd].contiguous())  # a GRU state of its own
            acts.append(torch.clamp(a, -1.0, 1.0))
            outs.append(h)
        return torch.stack(acts, dim=0).mean(dim=0), torch.cat(outs, dim=2)


def member_checkpoint(path: str) -> str:
    """The training checkpoint a member argument names: a file, a packaged ``model.pt`` or a run's latest."""
    if os.path.isfile(path):
        return path
    if not os.path.isdir(path):
        raise FileNotFoundError(f"ensemble member {path!r} does not exist")
    packaged = os.path.join(path, "model.pt")
    if os.path.isfile(packaged):
        return packaged
    its = [(int(m.group(1)), f) for f in glob.glob(os.path.join(path, "model_*.pt"))
           if (m := re.fullmatch(r"model_(\d+)\.pt", os.path.basename(f)))]  # fmt: skip
    if not its:
        raise FileNotFoundError(f"ensemble member {path!r} holds no model.pt or model_<it>.pt")
    return max(its)[1]


def build_ensemble(paths: list[str], out: str) -> str:
    """Export the ensemble of ``paths`` (see the module docstring) into ``out``; return ``out``."""
    from shield_nav.training.actor import actor_from_checkpoint

    files = [member_checkpoint(p) for p in paths]
    members, env_sections, cfgs = [], [], []
    for f in files:
        model, cfg, _ = actor_from_checkpoint(f)
        if model is None:
            raise ValueError(f"ensemble member {f!r} is a privileged teacher, not a depth actor")
        members.append(model.as_jit())
        env = to_dict(cfg.env)
        env_sections.append({k: env[k] for k in POLICY_ENV_SECTIONS})
        cfgs.append(cfg)
    for k, sec in enumerate(env_sections[1:], start=1):
        diff = sorted(key for key in POLICY_ENV_SECTIONS if sec[key] != env_sections[0][key])
        if diff:
            raise ValueError(
                f"ensemble member {files[k]!r} was trained with other env sections {diff} than {files[0]!r}"
            )
    ens = ExportedEnsemble(members)
    os.makedirs(os.path.join(out, "params"), exist_ok=True)
    with open(os.path.join(out, "params", "config.yaml"), "w", encoding="utf-8") as fh:
        fh.write(to_yaml(cfgs[0]))
    export_module(ens, out)
    names = sorted(f for f in os.listdir(out) if os.path.isfile(os.path.join(out, f)) and f != "meta.json")
    meta = {"kind": "ensemble", "members": [os.path.abspath(f) for f in files],
            "member_sha256": [_sha256(f) for f in files],
            "sha256": {f: _sha256(os.path.join(out, f)) for f in names}}  # fmt: skip
    with open(os.path.join(out, "meta.json"), "w", encoding="utf-8") as fh:
        json.dump(meta, fh, indent=2)
    return out


def main(argv: list[str] | None = None) -> None:
    """CLI entry point."""
    p = argparse.ArgumentParser(prog="python -m shield_nav.tools.ensemble", description=__doc__.splitlines()[0])
    p.add_argument("members", nargs="+", help="model_<it>.pt, a run folder or a packaged policy folder (2 or more)")
    p.add_argument("--out", required=True, help="folder for policy.onnx, policy.pt, params/ and meta.json")
    args = p.parse_args(argv)
    if len(args.members) < 2:
        p.error(f"an ensemble needs at least two members, got {len(args.members)}")
    try:
        print(f"ensemble of {len(args.members)} written to {build_ensemble(args.members, args.out)}")
    except (ValueError, FileNotFoundError) as err:
        p.exit(2, f"python -m shield_nav.tools.ensemble: error: {err}\n")


if __name__ == "__main__":
    main()
