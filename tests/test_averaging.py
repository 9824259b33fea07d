import pytest
import torch as th
from torch import nn

from sb3_hgrn.common.averaging import PolyakWeight, polyak_average


def test_the_weight_falls_with_the_updates_until_it_reaches_tau():
    """The first iterate is copied; the n-th later one weighs ``max(tau, 1 / (1 + n / 10))``: the
    average covers about the last tenth of the updates, then the last ``1 / tau``."""
    network = nn.Linear(1, 1, bias=False)
    average = polyak_average(network, tau=0.25)
    values = [4.0, 8.0, 0.0, 12.0, 20.0, 4.0] + [float(v) for v in range(40)]
    expected = values[0]
    for n, value in enumerate(values):
        with th.no_grad():
            network.weight.fill_(value)
        average.update_parameters(network)
        weight = max(0.25, 1.0 / (1.0 + n / 10))
        expected = value if n == 0 else (1 - weight) * expected + weight * value
        assert average.module.weight.item() == pytest.approx(expected)
    assert not average.module.weight.requires_grad


def test_rejects_a_weight_outside_zero_one():
    for tau in (0.0, 1.5, -0.1):
        with pytest.raises(ValueError, match="tau"):
            PolyakWeight(tau)
    with pytest.raises(ValueError, match="window"):
        PolyakWeight(0.1, window=0.0)


def averaged_pair(tau: float) -> tuple[nn.Module, th.optim.swa_utils.AveragedModel, nn.Module]:
    """A small network with a buffer, torch's own ``AveragedModel`` of :class:`PolyakWeight` (the
    earlier implementation) and :func:`polyak_average` of it."""
    th.manual_seed(0)
    network = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4), nn.Linear(4, 2))
    reference = th.optim.swa_utils.AveragedModel(network, multi_avg_fn=PolyakWeight(tau))
    return network, reference, polyak_average(network, tau)


def train_step(network: nn.Module, step: int) -> None:
    """Move every weight and buffer of ``network`` as a gradient step (and a forward pass) would;
    every third step shrinks the weights a million times (where blending an average into them with
    weight 1 is not an exact copy)."""
    with th.no_grad():
        for param in network.parameters():
            param.mul_(1e-6 if step % 3 == 0 else 1.0).add_(th.randn_like(param) * 10.0 ** (step % 3 - 9))
    network.train(True)
    network(th.randn(5, 3))


def assert_same_average(want: nn.Module, got: nn.Module) -> None:
    for (name, expected), actual in zip(want.state_dict().items(), got.state_dict().values(), strict=True):
        assert th.equal(actual, expected), name


def test_the_average_is_bitwise_that_of_torchs_averaged_model():
    network, reference, average = averaged_pair(tau=0.25)
    for step in range(8):
        train_step(network, step)
        reference.update_parameters(network)
        average.update_parameters(network)
        assert_same_average(reference, average)


def test_an_update_never_reads_a_tensor_on_the_host(monkeypatch):
    """No ``bool``, ``int``, ``float`` or ``.item()`` of a tensor (each waits for the device)."""
    network, _, average = averaged_pair(tau=0.5)

    def host_read(*args):
        raise AssertionError("the update read a tensor on the host")

    for step in range(4):
        train_step(network, step)
        with monkeypatch.context() as patch:
            for name in ("__bool__", "__int__", "__float__", "__index__", "item", "tolist"):
                patch.setattr(th.Tensor, name, host_read)
            average.update_parameters(network)
    assert average.n_averaged.item() == 4


@pytest.mark.parametrize("updates_before_saving", [0, 3])
def test_a_loaded_average_goes_on_as_the_saved_one(updates_before_saving):
    network, reference, average = averaged_pair(tau=0.25)
    for step in range(updates_before_saving):
        train_step(network, step)
        reference.update_parameters(network)
        average.update_parameters(network)
    loaded = polyak_average(network, 0.25)
    loaded.update_parameters(network)  # its own count is 1 now; loading sets the saved one
    loaded.load_state_dict(average.state_dict())
    for step in range(updates_before_saving, updates_before_saving + 3):
        train_step(network, step)
        reference.update_parameters(network)
        loaded.update_parameters(network)
        assert_same_average(reference, loaded)


def assert_close_average(want: nn.Module, got: nn.Module) -> None:
    for (name, expected), actual in zip(want.state_dict().items(), got.state_dict().values(), strict=True):
        assert th.allclose(actual.double(), expected.double(), atol=1e-6), name


def test_the_listed_tensors_follow_the_network_given_and_its_loaded_weights():
    """The tensor lists are kept between updates: a state dict loaded into the network counts, and
    another network given is listed afresh (its weights, not the first network's, are averaged)."""
    network, reference, average = averaged_pair(tau=1.0)  # weight 1: the average copies the network
    average.update_parameters(network)
    other = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4), nn.Linear(4, 2))
    network.load_state_dict(other.state_dict())
    average.update_parameters(network)
    assert_close_average(network, average.module)
    train_step(other, 1)
    average.update_parameters(other)
    assert_close_average(other, average.module)
    with pytest.raises(ValueError, match="different tensors"):
        average.update_parameters(nn.Linear(3, 4))
