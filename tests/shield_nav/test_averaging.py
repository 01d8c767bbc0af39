"""Weight averaging of the actor over a run's last iterations (``runner.average_iterations``), by hand."""

import math

import pytest
import torch
from torch import nn

from shield_nav.training.averaging import WeightAverage


class _Tiny(nn.Module):
    """A linear layer plus the buffers of rsl-rl's observation normaliser (float mean/var/std, integer count)."""

    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(2, 1)
        self.obs_normalizer = nn.Module()
        self.obs_normalizer.register_buffer("_mean", torch.zeros(2))
        self.obs_normalizer.register_buffer("_var", torch.ones(2))
        self.obs_normalizer.register_buffer("_std", torch.ones(2))
        self.obs_normalizer.register_buffer("count", torch.tensor(0))

    def set(self, w, var, count):
        with torch.no_grad():
            self.lin.weight.fill_(w)
            self.lin.bias.fill_(-w)
            self.obs_normalizer._var.fill_(var)
            self.obs_normalizer._std.fill_(math.sqrt(var))
            self.obs_normalizer.count.fill_(count)


def test_mean_of_the_window_by_hand():
    m, avg = _Tiny(), WeightAverage(first=3, last=5)
    for it, (w, var) in enumerate([(10.0, 4.0), (7.0, 4.0), (5.0, 4.0), (1.0, 1.0), (2.0, 9.0), (6.0, 2.0)]):
        m.set(w, var, count=100 + it)
        assert avg.add(m, it) == (3 <= it <= 5)  # iterations 0-2 lie before the window
    assert avg.complete and avg.iterations == [3, 4, 5] and avg.count == 3
    sd = avg.averaged_state_dict(m)
    assert sd["lin.weight"].tolist() == [[3.0, 3.0]]  # (1 + 2 + 6) / 3
    assert sd["lin.bias"].tolist() == [-3.0]
    assert sd["obs_normalizer._var"].tolist() == [4.0, 4.0]  # (1 + 9 + 2) / 3
    assert sd["obs_normalizer._std"].tolist() == [2.0, 2.0]  # sqrt of the mean var, not the mean std (1.80)
    assert sd["obs_normalizer.count"].item() == 105 and sd["lin.weight"].dtype == torch.float32  # the last, as is
    m.load_state_dict(sd)  # loads into the module it came from
    assert m.lin.weight.tolist() == [[3.0, 3.0]]


def test_stored_state_resumes_the_same_mean_and_checks_the_window():
    m, avg = _Tiny(), WeightAverage(first=0, last=2)
    m.set(1.0, 1.0, 1)
    avg.add(m, 0)
    resumed = WeightAverage.from_state(avg.state(), first=0, last=2)
    for it, w in [(1, 2.0), (2, 6.0)]:
        m.set(w, 1.0, 1)
        resumed.add(m, it)
    assert resumed.complete and resumed.averaged_state_dict(m)["lin.weight"].tolist() == [[3.0, 3.0]]
    with pytest.raises(ValueError, match=r"averages iterations \[0, 2\].*\[1, 3\]"):
        WeightAverage.from_state(avg.state(), first=1, last=3)


def test_a_missing_iteration_or_a_non_finite_weight_is_an_error():
    m, avg = _Tiny(), WeightAverage(first=0, last=3)
    with pytest.raises(RuntimeError, match="starts at iteration 0"):
        avg.add(m, 1)
    avg.add(m, 0)
    with pytest.raises(RuntimeError, match="iteration 2 follows 0"):
        avg.add(m, 2)
    m.set(float("nan"), 1.0, 1)
    with pytest.raises(FloatingPointError, match="lin.weight"):
        avg.add(m, 1)
    with pytest.raises(ValueError, match="first <= last"):
        WeightAverage(first=3, last=2)
