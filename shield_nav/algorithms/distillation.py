"""Multi-hypothesis DAgger: rsl-rl's ``Distillation`` with a winner-takes-all loss over ``K`` candidate actions.

Why: the oracle expert descends a geodesic field of the whole scene, so where it passes an obstacle on the left or
on the right can hang on geometry the depth camera does not see. A single-head student trained by MSE then learns
the *average* of the two, which points at the obstacle. Measured on the all-shapes student at 3 m/s
(docs/training.md, "Multi-hypothesis student"): when the expert rolls hard (|roll| > 0.3), the student rolls the
other way 22 % of the time, and those samples carry 46 % of its roll error.

The fix follows Loquercio et al. 2021 ("Learning high-speed flight in the wild", Science Robotics), who predict
several trajectories with a relaxed winner-takes-all loss. Here the student (``DepthGRUModel`` with
``num_hypotheses: K``) outputs ``K`` candidate actions and a score per candidate, and acts with the best-scored one.
Per sample, with ``e_k`` the loss of candidate ``k`` against the expert's action and ``k*`` its argmin:

``L = (1 - eps) e_{k*} + eps / (K - 1) sum_{k != k*} e_k  +  c * CE(scores, k*)``

The relaxed term (``wta_epsilon``) keeps the losing candidates near the data, so none of them is left unused. The
cross-entropy term (``selection_coef``) teaches the scores to pick the candidate the expert would agree with.
Everything else (rollout storage, truncated BPTT, hidden states, optimizer, checkpoints) is rsl-rl's own
``Distillation``; only its loss function is replaced. Use it as
``runner.algorithm.class_name: "shield_nav.algorithms.distillation:MultiHypothesisDistillation"``.

Both students can also anneal the learning rate (:class:`ScheduledDistillation`): rsl-rl's ``Distillation`` keeps
it constant, and with a constant 1e-3 the behaviour-cloning loss of a converged student stays as noisy as the
rollouts it is fitted on (docs/training.md, "Learning-rate schedule").
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from rsl_rl.algorithms import Distillation

__all__ = ["LR_SCHEDULES", "MultiHypothesisDistillation", "ScheduledDistillation", "scheduled_lr", "wta_loss"]

LR_SCHEDULES = ("constant", "cosine")
"""Learning-rate schedules of :class:`ScheduledDistillation`."""

ELEMENTWISE_LOSSES = {"mse": F.mse_loss, "huber": F.huber_loss}


def wta_loss(
    hypotheses: torch.Tensor,
    scores: torch.Tensor,
    target: torch.Tensor,
    epsilon: float,
    selection_coef: float,
    loss_type: str = "mse",
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Relaxed winner-takes-all loss plus score cross-entropy, averaged over samples.

    Args:
        hypotheses: Candidates ``(..., K, A)``.
        scores: Their scores ``(..., K)`` (logits).
        target: The expert's actions ``(..., A)``.
        epsilon: Share of the candidate loss spread over the ``K - 1`` losing candidates.
        selection_coef: Weight of the cross-entropy between the scores and the winning candidate.
        loss_type: Per-element loss, ``mse`` or ``huber``.

    Returns:
        The scalar loss and its parts: ``wta`` (the relaxed candidate loss), ``selection`` (the cross-entropy),
        ``chosen`` (the loss of the best-scored candidate, the action the student flies; comparable to a
        single-head student's loss) and ``accuracy`` (how often the best-scored candidate is the winner).
    """
    k = hypotheses.shape[-2]
    err = ELEMENTWISE_LOSSES[loss_type](hypotheses, target.unsqueeze(-2).expand_as(hypotheses), reduction="none")
    err = err.mean(-1).reshape(-1, k)  # (M, K)
    winner = err.argmin(-1)  # (M,)
    weights = torch.full_like(err, epsilon / (k - 1))
    weights.scatter_(1, winner.unsqueeze(1), 1.0 - epsilon)
    wta = (weights * err).sum(-1).mean()
    logits = scores.reshape(-1, k)
    selection = F.cross_entropy(logits, winner)
    picked = logits.argmax(-1)
    parts = {
        "wta": wta.detach(),
        "selection": selection.detach(),
        "chosen": err.gather(1, picked.unsqueeze(1)).mean().detach(),
        "accuracy": (picked == winner).float().mean(),
    }
    return wta + selection_coef * selection, parts


def scheduled_lr(update: int, lr: float, schedule: str, final: float, iterations: int) -> float:
    """Learning rate of the ``update``-th update (0-based).

    ``constant``: ``lr``. ``cosine``: from ``lr`` at update 0 to ``final`` at update ``N = iterations``, then
    ``final``: ``final + (lr - final) (1 + cos(pi u / N)) / 2``.
    """
    if schedule not in LR_SCHEDULES:
        raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {schedule!r}")
    if schedule == "constant":
        return lr
    u = min(max(update, 0), iterations)
    return final + (lr - final) * 0.5 * (1.0 + math.cos(math.pi * u / iterations))


class ScheduledDistillation(Distillation):
    """rsl-rl ``Distillation`` with a learning-rate schedule and optional dataset aggregation (replay).

    **Schedule** (:func:`scheduled_lr`): the update count is saved in the checkpoint (``num_updates``), so a resumed
    run continues the schedule; a warm start (``runner.student_init``) starts it afresh. The runner logs the rate as
    ``Loss/learning_rate``.

    **Aggregation**: rsl-rl's DAgger fits each rollout once and drops it. With ``replay_rollouts = M > 0`` the last
    ``M`` rollouts (observations, expert labels, dones and the student's hidden state at their start) are kept, and
    each update also fits ``replay_passes`` of them drawn at random, closer to DAgger's aggregated dataset (Ross et
    al. 2011). A replayed rollout starts from its recorded hidden state (computed by the student of its time, as
    R2D2's stored-state replay) and is fitted with the same truncated BPTT. Its loss is logged as ``Loss/replay``.
    The buffer is not checkpointed: a resumed run refills it.

    Use it as ``runner.algorithm.class_name: "shield_nav.algorithms.distillation:ScheduledDistillation"``.
    """

    def __init__(
        self,
        student: torch.nn.Module,
        teacher: torch.nn.Module,
        storage: object,
        learning_rate: float = 1e-3,
        lr_schedule: str = "constant",
        lr_final: float = 1e-5,
        lr_schedule_iterations: int = 1000,
        replay_rollouts: int = 0,
        replay_passes: int = 0,
        seed: int = 0,
        **kwargs: object,
    ) -> None:
        """Build rsl-rl's ``Distillation`` and record the schedule and the replay settings.

        Args:
            student: The student model.
            teacher: The teacher model.
            storage: rsl-rl rollout storage.
            learning_rate: Rate at the first update (rsl-rl's key).
            lr_schedule: ``constant`` (rsl-rl's behaviour) or ``cosine``.
            lr_final: Rate after ``lr_schedule_iterations`` updates (cosine only), > 0 and <= ``learning_rate``.
            lr_schedule_iterations: Updates (= iterations) the cosine takes, >= 1.
            replay_rollouts: Past rollouts kept for replay, >= 0 (0: rsl-rl's behaviour).
            replay_passes: Past rollouts fitted per update, in [0, ``replay_rollouts``]; 0 without replay.
            seed: Seed of the draw of replayed rollouts.
            **kwargs: Passed to ``Distillation``.
        """
        if lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {lr_schedule!r}")
        if lr_schedule != "constant" and not 0.0 < lr_final <= learning_rate:
            raise ValueError(f"lr_final must be in (0, learning_rate = {learning_rate}], got {lr_final}")
        if lr_schedule_iterations < 1:
            raise ValueError(f"lr_schedule_iterations must be >= 1, got {lr_schedule_iterations}")
        if (
            replay_rollouts < 0
            or not 0 <= replay_passes <= replay_rollouts
            or (replay_rollouts > 0) != (replay_passes > 0)
        ):
            raise ValueError(
                "need replay_rollouts >= 0 and 0 <= replay_passes <= replay_rollouts, both 0 or both > 0; got "
                f"replay_rollouts={replay_rollouts}, replay_passes={replay_passes}"
            )
        super().__init__(student, teacher, storage, learning_rate=learning_rate, **kwargs)
        self.lr_schedule = lr_schedule
        self.lr_initial = float(learning_rate)
        self.lr_final = float(lr_final)
        self.lr_schedule_iterations = int(lr_schedule_iterations)
        self.replay_rollouts = int(replay_rollouts)
        self.replay_passes = int(replay_passes)
        self.replay_buffer: list[dict] = []
        """The kept rollouts, oldest first: ``observations`` (T, N), ``labels`` (T, N, A), ``dones`` (T, N, 1) and
        ``hidden`` (the student's hidden state at the rollout's start, or ``None`` for zeros)."""
        self._replay_gen = torch.Generator().manual_seed(int(seed))
        self._replaying = False

    def update(self) -> dict[str, float]:
        """Set this update's rate, run rsl-rl's update on the new rollout, then fit ``replay_passes`` kept ones."""
        self.learning_rate = scheduled_lr(
            self.num_updates, self.lr_initial, self.lr_schedule, self.lr_final, self.lr_schedule_iterations
        )
        for group in self.optimizer.param_groups:
            group["lr"] = self.learning_rate
        if not self.replay_rollouts:
            return super().update()
        new = {
            "observations": self.storage.observations.clone(),
            "labels": self.storage.privileged_actions.clone(),
            "dones": self.storage.dones.clone(),
            "hidden": _clone_hidden(self.last_hidden_states[0]),
        }
        past = self.replay_buffer
        picks = torch.randperm(len(past), generator=self._replay_gen)[: self.replay_passes].tolist() if past else []
        out = super().update()
        h_after = _clone_hidden(self.student.get_hidden_state())  # the live rollout continues from here
        losses = [self._fit_rollout(past[i]) for i in picks]
        self.student.reset(hidden_state=h_after)
        self.replay_buffer = (past + [new])[-self.replay_rollouts :]
        if losses:
            out["replay"] = sum(losses) / len(losses)
        return out

    def _fit_rollout(self, rollout: dict) -> float:
        """One pass of truncated-BPTT behaviour cloning over a kept rollout; its mean loss."""
        self._replaying = True
        try:
            self.student.reset(hidden_state=_clone_hidden(rollout["hidden"]))
            self.student.detach_hidden_state()
            obs, labels, dones = rollout["observations"], rollout["labels"], rollout["dones"]
            loss, total, cnt = 0, 0.0, 0
            for t in range(labels.shape[0]):
                step_loss = self.loss_fn(self.student(obs[t]), labels[t])
                loss = loss + step_loss
                total += step_loss.item()
                cnt += 1
                if cnt % self.gradient_length == 0 or t == labels.shape[0] - 1:
                    self.optimizer.zero_grad()
                    loss.backward()
                    if self.is_multi_gpu:
                        self.reduce_parameters()
                    if self.max_grad_norm:
                        torch.nn.utils.clip_grad_norm_(self.student.parameters(), self.max_grad_norm)
                    self.optimizer.step()
                    self.student.detach_hidden_state()
                    loss = 0
                self.student.reset(dones[t].view(-1))
                self.student.detach_hidden_state(dones[t].view(-1))
            return total / max(cnt, 1)
        finally:
            self._replaying = False

    def save(self) -> dict:
        """rsl-rl's checkpoint dict plus the update count (the schedule's position)."""
        out = super().save()
        out["num_updates"] = self.num_updates
        return out

    def load(self, loaded_dict: dict, load_cfg: dict | None, strict: bool) -> bool:
        """rsl-rl's load; a resumed run (``iteration`` loaded) also continues the schedule."""
        load_iteration = super().load(loaded_dict, load_cfg, strict)
        if load_iteration:
            self.num_updates = int(loaded_dict.get("num_updates", 0))
        return load_iteration


def _clone_hidden(h: object) -> object:
    """A detached copy of a hidden state (a tensor, a tuple of tensors or ``None``)."""
    if h is None:
        return None
    if isinstance(h, torch.Tensor):
        return h.detach().clone()
    return tuple(_clone_hidden(x) for x in h)


class MultiHypothesisDistillation(ScheduledDistillation):
    """rsl-rl ``Distillation`` whose behaviour loss is :func:`wta_loss` over the student's candidates.

    The student must be a ``DepthGRUModel`` with ``num_hypotheses >= 2``. ``update()`` returns rsl-rl's
    ``behavior`` loss (the full loss above) plus ``chosen``, ``wta``, ``selection`` and ``accuracy``, averaged over
    the update; the runner logs each as ``Loss/<name>``.
    """

    def __init__(
        self,
        student: torch.nn.Module,
        teacher: torch.nn.Module,
        storage: object,
        wta_epsilon: float = 0.05,
        selection_coef: float = 0.1,
        loss_type: str = "mse",
        **kwargs: object,
    ) -> None:
        """Build rsl-rl's ``Distillation``, then replace its loss function.

        Args:
            student: The multi-hypothesis student.
            teacher: The teacher (e.g. ``shield_nav.policies.models:ExpertTeacher``).
            storage: rsl-rl rollout storage.
            wta_epsilon: Relaxation of the winner-takes-all loss, in [0, 1).
            selection_coef: Weight of the score cross-entropy, >= 0.
            loss_type: Per-element loss of each candidate, ``mse`` or ``huber``.
            **kwargs: Passed to :class:`ScheduledDistillation` (the learning-rate schedule) and ``Distillation``.
        """
        k = int(getattr(student, "num_hypotheses", 1))
        if k < 2:
            raise ValueError(f"MultiHypothesisDistillation needs a student with num_hypotheses >= 2, got {k}")
        if not 0.0 <= wta_epsilon < 1.0:
            raise ValueError(f"wta_epsilon must be in [0, 1), got {wta_epsilon}")
        if selection_coef < 0.0:
            raise ValueError(f"selection_coef must be >= 0, got {selection_coef}")
        super().__init__(student, teacher, storage, loss_type=loss_type, **kwargs)
        self.wta_epsilon = float(wta_epsilon)
        self.selection_coef = float(selection_coef)
        self.element_loss = loss_type
        self.loss_fn = self._loss
        self._parts: dict[str, float] = {}
        self._count = 0

    def _loss(self, actions: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """``loss_fn(student_actions, teacher_actions)`` as ``Distillation.update`` calls it."""
        student = self._raw_student
        loss, parts = wta_loss(
            student.last_hypotheses, student.last_scores, target, self.wta_epsilon, self.selection_coef,
            self.element_loss,
        )  # fmt: skip
        if not self._replaying:  # the logged parts describe the new rollout; replay is logged as Loss/replay
            for name, value in parts.items():
                self._parts[name] = self._parts.get(name, 0.0) + float(value)
            self._count += 1
        return loss

    def update(self) -> dict[str, float]:
        """rsl-rl's update; the loss parts are added to its loss dict."""
        self._parts, self._count = {}, 0
        out = super().update()
        out.update({name: total / max(self._count, 1) for name, total in self._parts.items()})
        return out
