"""Anchored PPO: rsl-rl's ``PPO`` with a penalty on drifting away from a frozen reference actor.

Why: PPO fine-tuning of a behaviour-cloned depth student collapsed twice here (docs/lab-log.md, "PPO fine-tuning of
the oracle-DAgger student"): once the actor was released from its critic warm-up, the return fell from 18 to 5 within
300 iterations, at learning rates 1e-4 and 3e-5 alike. The reward ranks the expert's behaviour well above crashing,
so the collapse is an optimisation problem: a young critic's noisy advantages push an actor that starts near a good
policy away from it faster than they improve it. The usual remedy (kickstarting, Schmitt et al. 2018; the KL to the
initial policy of KL-regularised fine-tuning) is to keep the fine-tuned actor close to where it started.

Objective, per mini-batch, with ``mu`` the actor's mean action and ``mu_ref`` the reference's on the same states:

``L = L_PPO + anchor_coef * mean((mu - mu_ref)^2)``

The reference is a frozen copy of the actor taken at the first rollout step (the warm-start weights of
``runner.actor_init``), saved in every checkpoint so that ``--resume`` keeps the same anchor. For two Gaussians with
the same std ``sigma`` the KL divergence is ``sum((mu - mu_ref)^2) / (2 sigma^2)``, so the term is the KL to the
reference up to a constant; it is written on the means so that its value reads like the distillation loss (same
units, ``Loss/anchor`` in tensorboard) and does not change when PPO moves the std.

How it plugs into rsl-rl without copying ``PPO.update``:

* ``act`` also runs the reference (its own GRU state, reset with the actor's) and stores its mean action in the
  rollout as an extra observation key, :data:`ANCHOR_KEY`. The rollout storage is built with that key, so rsl-rl's
  recurrent mini-batch generator splits and pads it exactly like the observations the actor reads.
* During ``update`` a forward hook on the actor's MLP head (whose output is the Gaussian's mean) passes the mean
  through :class:`_AnchorGradient`: the identity forward, and a backward that adds the gradient of the anchor term.
  Adding a term's gradient at the one tensor it depends on is the same as adding the term to the loss, so PPO's
  own loss, clipping, optimizer step and logging run unchanged. A test checks the resulting weights against a
  hand-written ``L_PPO + anchor`` step.

Use it as ``runner.algorithm.class_name: "shield_nav.algorithms.anchored:AnchoredPPO"`` with
``runner.algorithm.anchor_coef``.

**Kickstarting from the oracle** (``anchor_target: expert``). The reference can instead be the scripted oracle's
action on every visited state (the ``expert`` observation of oracle DAgger, ``runner.expert``): the term is then
DAgger's behaviour-cloning loss added to PPO's, which is kickstarting with the oracle as the teacher (Schmitt et al.
2018). A multi-hypothesis actor is held to the expert by the loss it was distilled with,
:func:`shield_nav.algorithms.distillation.wta_loss` over its candidates and scores, so that the term does not average
its candidates into one; a single head by ``mean((mu - a_expert)^2)``.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from rsl_rl.algorithms import PPO
from rsl_rl.storage import RolloutStorage
from rsl_rl.utils import unpad_trajectories
from tensordict import TensorDict
from torch import nn

from shield_nav.algorithms import ANCHOR_TARGETS

__all__ = ["ANCHOR_KEY", "ANCHOR_TARGETS", "AnchoredPPO", "anchor_loss"]

ANCHOR_KEY = "anchor_mean"
"""Rollout-storage key of the reference actor's mean action (never an observation group of a model)."""


def anchor_loss(mean: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between the actor's and the reference's mean actions, over samples and dimensions."""
    return (mean - reference).pow(2).mean()


class _AnchorGradient(torch.autograd.Function):
    """Identity in the forward pass; the backward adds ``coef * d anchor_loss(x, reference) / dx``."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, reference: torch.Tensor, coef: float) -> torch.Tensor:
        ctx.save_for_backward(x, reference)
        ctx.coef = coef
        return x.view_as(x)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        x, reference = ctx.saved_tensors
        return grad + ctx.coef * 2.0 * (x - reference) / x.numel(), None, None


class _AddGradient(torch.autograd.Function):
    """Identity in the forward pass; the backward adds a precomputed gradient ``g`` (the same shape as ``x``)."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(g)
        return x.view_as(x)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        (g,) = ctx.saved_tensors
        return grad + g, None


class AnchoredPPO(PPO):
    """rsl-rl's ``PPO`` plus ``anchor_coef`` times a distance to a reference actor or expert.

    The reference is the frozen starting actor (``mean((mu - mu_ref)^2)``) or the scripted expert (DAgger's loss,
    kickstarting).

    The actor must output the Gaussian's mean from its ``mlp`` head (rsl-rl's ``GaussianDistribution`` with a
    state-independent std; ``DepthGRUModel`` single- or multi-hypothesis). ``anchor_coef = 0`` is plain PPO.
    """

    def __init__(self, actor: nn.Module, critic: nn.Module, storage: RolloutStorage, anchor_coef: float = 1.0,
                 anchor_target: str = "actor_init", wta_epsilon: float = 0.05, selection_coef: float = 0.1,
                 **kwargs: Any) -> None:  # fmt: skip
        """Build rsl-rl's ``PPO`` (``kwargs``) with the anchor term.

        Args:
            actor: The actor (rsl-rl ``PPO``).
            critic: The critic (rsl-rl ``PPO``).
            storage: The rollout storage, with :data:`ANCHOR_KEY` (built by :meth:`construct_algorithm`).
            anchor_coef: Weight of the anchor term (0: plain PPO).
            anchor_target: ``actor_init`` (a frozen copy of the starting actor) or ``expert`` (the ``expert``
                observation, kickstarting).
            wta_epsilon: ``anchor_target: expert`` with a multi-hypothesis actor only: the relaxation of
                :func:`shield_nav.algorithms.distillation.wta_loss`, as in its distillation.
            selection_coef: Likewise, the weight of its score cross-entropy.
            **kwargs: rsl-rl ``PPO``'s other arguments.
        """
        if not anchor_coef >= 0.0:  # also rejects NaN
            raise ValueError(f"AnchoredPPO: anchor_coef must be >= 0, got {anchor_coef}")
        if anchor_target not in ANCHOR_TARGETS:
            raise ValueError(f"AnchoredPPO: anchor_target must be one of {ANCHOR_TARGETS}, got {anchor_target!r}")
        super().__init__(actor, critic, storage, **kwargs)
        self.anchor_coef = float(anchor_coef)
        self.anchor_target = anchor_target
        self.wta_epsilon = float(wta_epsilon)
        self.selection_coef = float(selection_coef)
        self._multi = anchor_target == "expert" and int(getattr(self._raw_actor, "num_hypotheses", 1)) > 1
        self.anchor: nn.Module | None = None
        """The frozen reference actor (taken at the first ``act`` or restored by ``load``)."""
        self._reference: torch.Tensor | None = None  # the current mini-batch's reference means (update only)
        self._anchor_sum = 0.0
        self._anchor_count = 0

    @staticmethod
    def construct_algorithm(obs: TensorDict, env: Any, cfg: dict, device: str) -> AnchoredPPO:
        """rsl-rl's construction, then a rollout storage that also holds the reference's mean actions."""
        alg = PPO.construct_algorithm(obs, env, cfg, device)
        extended = obs.clone()
        extended[ANCHOR_KEY] = torch.zeros(obs.batch_size[0], env.num_actions, device=obs.device)
        alg.storage = RolloutStorage("rl", env.num_envs, cfg["num_steps_per_env"], extended, [env.num_actions],
                                     device)  # fmt: skip
        return alg  # type: ignore[return-value]

    # ------------------------------------------------------------------------------------------------ reference

    def set_anchor(self) -> None:
        """Freeze a copy of the actor as it is now (weights, normaliser, GRU state) as the reference."""
        with torch.inference_mode(False):  # act() runs under inference mode; the copy must stay loadable
            anchor = copy.deepcopy(self._raw_actor)
        anchor.eval()
        for p in anchor.parameters():
            p.requires_grad_(False)
        self.anchor = anchor

    def act(self, obs: TensorDict) -> torch.Tensor:
        """PPO's ``act``; the reference's mean action on the same observation is stored with the transition."""
        if self.anchor_target == "expert":
            if "expert" not in obs:
                raise KeyError("AnchoredPPO(anchor_target='expert') needs the 'expert' observation: set runner.expert")
            reference = obs["expert"].float()
        elif self.anchor is None:
            self.set_anchor()
        actions = super().act(obs)
        if self.anchor_target == "actor_init":
            with torch.no_grad():
                reference = self.anchor(obs)  # deterministic output: the mean
        stored = obs.clone(recurse=False)
        stored[ANCHOR_KEY] = reference
        self.transition.observations = stored
        return actions

    def process_env_step(self, obs: TensorDict, rewards: torch.Tensor, dones: torch.Tensor,
                         extras: dict[str, torch.Tensor]) -> None:  # fmt: skip
        """PPO's ``process_env_step``; the reference's GRU state is reset with the actor's."""
        super().process_env_step(obs, rewards, dones, extras)
        if self.anchor is not None and self.anchor_target == "actor_init":
            self.anchor.reset(dones)

    # ------------------------------------------------------------------------------------------------ update

    def _capture_reference(self, module: nn.Module, args: tuple, kwargs: dict) -> None:
        """Forward pre-hook on the actor: the reference means of this mini-batch, aligned with the actor's output."""
        obs, masks = args[0], kwargs.get("masks")
        reference = obs[ANCHOR_KEY]
        self._reference = reference if masks is None else unpad_trajectories(reference, masks)

    def _anchor_head(self, module: nn.Module, args: tuple, output: torch.Tensor) -> torch.Tensor:
        """Forward hook on the actor's MLP head (the Gaussian's mean): attach the anchor term's gradient."""
        reference = self._reference
        if reference is None or reference.shape != output.shape:
            raise RuntimeError(f"AnchoredPPO: reference means {None if reference is None else tuple(reference.shape)} "
                               f"do not match the actor's mean {tuple(output.shape)}")  # fmt: skip
        self._anchor_sum += float(anchor_loss(output.detach(), reference))
        self._anchor_count += 1
        return _AnchorGradient.apply(output, reference, self.anchor_coef)

    def _anchor_candidates(self, module: nn.Module, args: tuple, output: torch.Tensor) -> torch.Tensor:
        """Forward hook on a multi-hypothesis actor's raw head: attach the WTA loss's gradient towards the expert.

        The raw head's output holds the candidates and their scores, before the selection.
        """
        from shield_nav.algorithms.distillation import wta_loss

        reference = self._reference
        select = self._raw_actor.mlp[1]
        with torch.enable_grad():
            raw = output.detach().requires_grad_(True)
            hypotheses, scores = select.split(raw)
            if reference is None or reference.shape != hypotheses.shape[:-2] + hypotheses.shape[-1:]:
                got = None if reference is None else tuple(reference.shape)
                raise RuntimeError(f"AnchoredPPO: expert actions {got} do not match the actor's candidates "
                                   f"{tuple(hypotheses.shape)}")  # fmt: skip
            loss, _ = wta_loss(hypotheses, scores, reference, self.wta_epsilon, self.selection_coef)
            (g,) = torch.autograd.grad(loss, raw)
        self._anchor_sum += float(loss.detach())
        self._anchor_count += 1
        return _AddGradient.apply(output, self.anchor_coef * g)

    def update(self) -> dict[str, float]:
        """PPO's update with the anchor term in every mini-batch; the loss dict gains ``anchor`` (its mean)."""
        self._anchor_sum, self._anchor_count = 0.0, 0
        hooks = [self._raw_actor.register_forward_pre_hook(self._capture_reference, with_kwargs=True)]
        if self._multi:
            hooks.append(self._raw_actor.mlp[0].register_forward_hook(self._anchor_candidates))
        else:
            head = getattr(self._raw_actor, "mean_head", self._raw_actor.mlp)
            hooks.append(head.register_forward_hook(self._anchor_head))
        try:
            losses = super().update()
        finally:
            for h in hooks:
                h.remove()
            self._reference = None
        losses["anchor"] = self._anchor_sum / max(self._anchor_count, 1)
        return losses

    # ------------------------------------------------------------------------------------------------ checkpoints

    def save(self) -> dict:
        """PPO's checkpoint plus the reference actor, so that a resumed run keeps the same anchor."""
        saved = super().save()
        if self.anchor is not None:
            saved["anchor_state_dict"] = self.anchor.state_dict()
        return saved

    def load(self, loaded_dict: dict, load_cfg: dict | None, strict: bool) -> bool:
        """PPO's load; a checkpoint of an anchored run also restores its reference."""
        out = super().load(loaded_dict, load_cfg, strict)
        if "anchor_state_dict" in loaded_dict:
            self.set_anchor()
            self.anchor.load_state_dict(loaded_dict["anchor_state_dict"], strict=strict)
        return out
