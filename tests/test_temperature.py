import math

import pytest
import torch as th

from sb3_hgrn.common.temperature import (
    EntropyTemperature,
    TemperatureController,
    categorical_entropy,
    target_entropy,
)


def test_target_entropy_and_categorical_entropy():
    assert target_entropy(0.3, 5) == pytest.approx(0.3 * math.log(5))
    with pytest.raises(ValueError, match="target_entropy_ratio"):
        target_entropy(1.5, 5)
    uniform = th.zeros(4)
    assert categorical_entropy(uniform).item() == pytest.approx(math.log(4))
    logits = th.tensor([math.log(0.75), math.log(0.25)])
    assert categorical_entropy(logits).item() == pytest.approx(
        -(0.75 * math.log(0.75) + 0.25 * math.log(0.25))
    )


@pytest.mark.parametrize("log_space", [False, True])
@pytest.mark.parametrize("optimizer", ["adam", "sgd"])
def test_alpha_falls_above_target_and_rises_below(optimizer, log_space):
    for entropy, direction in ((1.0, -1), (0.1, +1)):
        temperature = EntropyTemperature(0.5, log_space=log_space)
        controller = TemperatureController(temperature, target=0.5, optimizer=optimizer, learning_rate=0.1)
        before = temperature.alpha.item()
        for _ in range(5):
            controller.update(th.tensor(entropy))
        assert (temperature.alpha.item() - before) * direction > 0


def test_sgd_step_is_clipped_to_one_percent_of_alpha():
    temperature = EntropyTemperature(2.0)
    controller = TemperatureController(temperature, target=0.0, optimizer="sgd", learning_rate=1.0)
    gradient = controller.update(th.tensor(3.0))
    assert gradient == pytest.approx(3.0)  # d/d alpha of alpha * (H - H*)
    assert temperature.alpha.item() == pytest.approx(2.0 - 0.01 * 2.0)


def test_alpha_stays_above_its_floor():
    temperature = EntropyTemperature(1e-5)
    controller = TemperatureController(
        temperature, target=0.0, optimizer="sgd", learning_rate=10.0, max_grad_ratio=1e9
    )
    controller.update(th.tensor(5.0))
    assert temperature.alpha.item() == pytest.approx(1e-5)


def test_bad_temperature_arguments():
    with pytest.raises(ValueError, match="initial_alpha"):
        EntropyTemperature(0.0)
    with pytest.raises(ValueError, match="alpha_optimizer"):
        TemperatureController(EntropyTemperature(), 0.1, optimizer="rmsprop")
