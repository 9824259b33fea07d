import pytest
import torch as th
from torch import nn

from sb3_hgrn.common.averaging import PolyakWeight, polyak_average


def test_plain_mean_of_the_first_iterates_then_an_exponential_average():
    network = nn.Linear(1, 1, bias=False)
    average = polyak_average(network, tau=0.25)
    expected = None
    for step, value in enumerate([4.0, 8.0, 0.0, 12.0, 20.0, 4.0]):
        with th.no_grad():
            network.weight.fill_(value)
        average.update_parameters(network)
        if step < 4:  # 1 / tau = 4 iterates: their mean
            expected = sum([4.0, 8.0, 0.0, 12.0][: step + 1]) / (step + 1)
        else:
            expected = 0.75 * expected + 0.25 * value
        assert average.module.weight.item() == pytest.approx(expected)
    assert not average.module.weight.requires_grad


def test_rejects_a_weight_outside_zero_one():
    for tau in (0.0, 1.5, -0.1):
        with pytest.raises(ValueError, match="tau"):
            PolyakWeight(tau)
