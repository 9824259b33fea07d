"""SoftDQN: SB3's DQN with soft Q-learning targets and a temperature that tracks a target entropy."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3 import DQN
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule

from sb3_hgrn.common.single_agent import TEMPERATURE_SAVE_PARAMS, check_discrete_env, transitions
from sb3_hgrn.common.soft_math import (
    Q_LOSSES,
    boltzmann_entropy,
    bootstrapped,
    gradient_step,
    q_regression_loss,
    soft_q_next_value,
)
from sb3_hgrn.common.temperature import TemperatureLearner
from sb3_hgrn.common.tensorboard import AlgorithmNamedRuns
from sb3_hgrn.soft_dqn.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, SoftDQNPolicy


class SoftDQN(AlgorithmNamedRuns, TemperatureLearner, DQN):
    """Soft Q-learning for any Gymnasium env with a ``Discrete`` action space, used as SB3's ``DQN``.

    The policy is ``softmax(Q / alpha)``; the Q-network regresses (squared error by default) on
    ``r + gamma * (1 - terminated) * alpha * logsumexp(Q_target(o', .) / alpha)`` (with
    ``n_steps > 1``, SB3's n-step returns: the discounted sum of ``n_steps`` rewards and
    ``gamma ** n_steps``), and alpha is learned so that the batch's mean entropy of
    ``softmax(Q / alpha)`` tracks ``target_entropy_ratio * log(n_actions)`` (the same targets, losses
    and temperature controller as :class:`~sb3_hgrn.SoftHGRN`: :mod:`sb3_hgrn.common.soft_math`,
    :mod:`sb3_hgrn.common.temperature`). The Boltzmann policy explores, so epsilon-greedy
    exploration is off by default.

    All other arguments, units and behaviour are SB3's ``DQN``'s (``target_update_interval`` counts
    env steps; ``learning_starts`` steps of uniform random actions).

    :param target_entropy_ratio: the target entropy is ``target_entropy_ratio * log(n_actions)``.
    :param alpha_init: initial temperature, or ``"auto"``: 0.1 times the standard deviation of the
        rewards stored at the first gradient step (see :mod:`sb3_hgrn.common.temperature`).
    :param learn_alpha: learn the temperature (``False`` keeps ``alpha_init``).
    :param alpha_optimizer: ``"adam"`` or ``"sgd"`` for the temperature.
    :param alpha_learning_rate: learning rate of the temperature optimiser.
    :param alpha_max_step: one update moves alpha by at most this fraction of its value.
    :param q_loss: ``"mse"`` (squared error) or ``"huber"`` (SB3's DQN's loss).
    :param policy_kwargs: SB3's ``DQNPolicy`` options, plus ``alpha_log_space``.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: SoftDQNPolicy

    def __init__(
        self,
        policy: str | type[SoftDQNPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 32,
        tau: float = 1.0,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 4,
        gradient_steps: int = 1,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        target_update_interval: int = 10_000,
        target_entropy_ratio: float = 0.2,
        alpha_init: float | str = 0.1,
        learn_alpha: bool = True,
        alpha_optimizer: str = "adam",
        alpha_learning_rate: float = 1e-3,
        alpha_max_step: float = 0.01,
        q_loss: str = "mse",
        exploration_fraction: float = 0.1,
        exploration_initial_eps: float = 0.0,
        exploration_final_eps: float = 0.0,
        max_grad_norm: float = 10.0,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        self._set_temperature_options(
            target_entropy_ratio,
            alpha_init,
            learn_alpha,
            alpha_optimizer,
            alpha_learning_rate,
            alpha_max_step,
        )
        if q_loss not in Q_LOSSES:
            raise ValueError(f"q_loss must be one of {', '.join(map(repr, Q_LOSSES))}, got {q_loss!r}.")
        self.q_loss = q_loss
        super().__init__(
            policy,
            check_discrete_env(env, "SoftDQN", verbose),
            learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            target_update_interval=target_update_interval,
            exploration_fraction=exploration_fraction,
            exploration_initial_eps=exploration_initial_eps,
            exploration_final_eps=exploration_final_eps,
            max_grad_norm=max_grad_norm,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=_init_setup_model,
        )

    def _setup_model(self) -> None:
        super()._setup_model()
        self._setup_temperature()

    def train(self, gradient_steps: int, batch_size: int = 100) -> None:
        self._start_temperature()
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        losses, entropies, alpha_gradients = [], [], []
        for _ in range(gradient_steps):
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            batch = transitions(data, self.gamma)
            alpha = self.policy.temperature.per_agent(None)
            with th.no_grad():
                next_value = soft_q_next_value(self.q_net_target(data.next_observations), alpha)
                target_q = bootstrapped(batch.rewards, batch.discounts, batch.terminated, next_value)
            q_values = self.q_net(data.observations)
            loss = q_regression_loss(q_values, batch.actions, target_q, batch.mask, self.q_loss)
            gradient_step(self.policy.optimizer, loss, self.q_net, self.max_grad_norm)
            entropy, alpha_gradient = self._update_temperature(
                boltzmann_entropy(q_values.detach(), alpha), None, batch.mask
            )
            if alpha_gradient is not None:
                alpha_gradients.append(alpha_gradient)
            losses.append(loss.item())
            entropies.append(entropy)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/loss", float(np.mean(losses)))
        self._record_temperature(entropies, alpha_gradients)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, *TEMPERATURE_SAVE_PARAMS], variables
