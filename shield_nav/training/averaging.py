"""Uniform weight averaging of the actor over a run's last iterations (``runner.average_iterations``).

Why: a PPO stage at a fixed learning rate ends at one point of a noisy path, and checkpoints a few dozen iterations
apart can fly quite differently. Averaging the weights along the end of the path (stochastic weight averaging,
Izmailov et al. 2018, "Averaging Weights Leads to Wider Optima and Better Generalization"; in deep RL, Nikishin et
al. 2018) is the standard remedy; what it measured here is in docs/training.md, "Weight averaging".

Every floating-point tensor of the actor's ``state_dict`` is averaged, the observation normaliser's mean and
variance included (its std is then ``sqrt(var)``, as rsl-rl's ``EmpiricalNormalization`` computes it); integer
buffers (the normaliser's count) are the last iteration's. The mean is kept in float64 and updated in place,
``m += (x - m) / n``, so a resumed run continues it exactly.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["WeightAverage"]

_STD, _VAR = "obs_normalizer._std", "obs_normalizer._var"


class WeightAverage:
    """The running uniform mean of a module's floating-point ``state_dict`` entries over iterations ``[first, last]``.

    Args:
        first: The first iteration averaged (``max_iterations - average_iterations``).
        last: The last iteration averaged (``max_iterations - 1``).
    """

    def __init__(self, first: int, last: int) -> None:
        if not 0 <= first <= last:
            raise ValueError(f"WeightAverage: need 0 <= first <= last, got first={first}, last={last}")
        self.first, self.last = int(first), int(last)
        self.iterations: list[int] = []
        self.mean: dict[str, torch.Tensor] = {}

    @property
    def count(self) -> int:
        """How many iterations the mean holds."""
        return len(self.iterations)

    @property
    def complete(self) -> bool:
        """Whether every iteration of ``[first, last]`` has been added."""
        return self.iterations == list(range(self.first, self.last + 1))

    def add(self, module: nn.Module, it: int) -> bool:
        """Add ``module``'s weights after iteration ``it`` if it lies in the window; return whether it was added."""
        if not self.first <= it <= self.last or it in self.iterations:
            return False
        if self.iterations and it != self.iterations[-1] + 1:
            raise RuntimeError(f"WeightAverage: iteration {it} follows {self.iterations[-1]}: an iteration is missing")
        if not self.iterations and it != self.first:
            raise RuntimeError(f"WeightAverage: the average starts at iteration {self.first}, got {it} first")
        n = self.count + 1
        for k, v in module.state_dict().items():
            if not v.is_floating_point():
                continue
            x = v.detach().to("cpu", torch.float64)
            if not torch.isfinite(x).all():
                raise FloatingPointError(f"WeightAverage: the actor's {k!r} is not finite at iteration {it}")
            if k not in self.mean:
                self.mean[k] = x.clone()
            else:
                self.mean[k] += (x - self.mean[k]) / n
        self.iterations.append(int(it))
        return True

    def averaged_state_dict(self, module: nn.Module) -> dict[str, torch.Tensor]:
        """``module``'s state dict with every floating-point entry replaced by its mean (std from the mean var)."""
        if not self.count:
            raise RuntimeError("WeightAverage: nothing averaged yet")
        out = {}
        for k, v in module.state_dict().items():
            out[k] = self.mean[k].to(v.device, v.dtype) if k in self.mean else v.clone()
        if _STD in out and _VAR in out:
            out[_STD] = torch.sqrt(out[_VAR])
        return out

    def state(self) -> dict:
        """What a checkpoint stores (``infos["weight_average"]``) for ``--resume`` to continue the mean."""
        return {"first": self.first, "last": self.last, "count": self.count, "iterations": list(self.iterations),
                "mean": {k: v.clone() for k, v in self.mean.items()}}  # fmt: skip

    @classmethod
    def from_state(cls, state: dict, first: int, last: int) -> WeightAverage:
        """Restore a stored mean; a stored window other than ``[first, last]`` is an error (the config changed)."""
        if (state["first"], state["last"]) != (first, last):
            raise ValueError(f"WeightAverage: the checkpoint averages iterations [{state['first']}, {state['last']}], "
                             f"this run's config [{first}, {last}] (runner.average_iterations or max_iterations "
                             f"changed since)")  # fmt: skip
        avg = cls(first, last)
        avg.iterations = [int(i) for i in state["iterations"]]
        avg.mean = {k: v.to(torch.float64).clone() for k, v in state["mean"].items()}
        return avg
