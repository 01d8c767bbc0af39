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
``runner.algorithm.class_name: "shield_nav.distillation:MultiHypothesisDistillation"``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from rsl_rl.algorithms import Distillation

__all__ = ["MultiHypothesisDistillation", "wta_loss"]

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


class MultiHypothesisDistillation(Distillation):
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
            teacher: The teacher (e.g. ``shield_nav.models:ExpertTeacher``).
            storage: rsl-rl rollout storage.
            wta_epsilon: Relaxation of the winner-takes-all loss, in [0, 1).
            selection_coef: Weight of the score cross-entropy, >= 0.
            loss_type: Per-element loss of each candidate, ``mse`` or ``huber``.
            **kwargs: Passed to ``Distillation``.
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
