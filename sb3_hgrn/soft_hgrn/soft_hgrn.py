"""Soft-HGRN: soft Q-learning on graphs with a temperature that tracks a target action entropy."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from stable_baselines3.common.utils import polyak_update

from sb3_hgrn.common.off_policy import GraphOffPolicyAlgorithm, check_added_arguments, unroll
from sb3_hgrn.common.soft_math import (
    boltzmann_entropy,
    gradient_step,
    q_regression_loss,
    soft_q_next_value,
)
from sb3_hgrn.soft_hgrn.policies import SoftHGRNPolicy


class SoftHGRN(GraphOffPolicyAlgorithm):
    """Soft-HGRN (soft Q-learning with HGRN, Ye et al., AAAI 2022).

    The policy is ``softmax(Q / alpha)``; the critic regresses on
    ``r + gamma * (1 - terminated) * alpha * logsumexp(Q_target(o', .) / alpha)`` (with
    ``n_steps > 1``, the discounted sum of ``n_steps`` rewards and ``gamma ** n_steps``) and alpha is
    learned so that the mean action entropy tracks ``target_entropy_ratio * log(n_actions)``.
    Losses and entropies are means over the agents alive at their step (see
    :class:`~sb3_hgrn.common.vec_env.GraphVecEnv` for agents that die).
    With ``stochastic=False`` it is the deterministic ``-S`` variant: greedy actions, hard-max
    targets and epsilon-greedy exploration.

    Units as in SB3 (see :class:`~sb3_hgrn.common.off_policy.GraphOffPolicyAlgorithm`): timesteps,
    ``learning_starts`` and ``buffer_size`` count agent-steps, ``train_freq`` vec-steps,
    ``batch_size`` graphs, ``target_update_interval`` gradient steps.

    :param policy: ``"GraphPolicy"`` or a :class:`SoftHGRNPolicy` subclass.
    :param env: graph VecEnv from :func:`sb3_hgrn.make_graph_vec_env` (or a registered env name).
    :param learning_rate: Adam learning rate of the Q-network (float or schedule).
    :param buffer_size: replay capacity in agent-transitions.
    :param learning_starts: agent-steps of uniform random actions before learning starts.
    :param batch_size: graphs per gradient step.
    :param tau: target update coefficient (1.0 = hard copy).
    :param gamma: discount factor.
    :param reward_scale: factor of the rewards in the Q targets (the envs' rewards, logs and
        evaluations are untouched), or ``"auto"``: at the first gradient step, one over the root mean
        square of the discounted returns in the replay buffer where that is above 1, else 1, so the
        Q-values are of order one at most whatever the env's reward units (logged as
        ``train/reward_scale``; resumed models keep it).
    :param n_steps: rewards summed per target before bootstrapping (n-step returns, as SB3's
        ``n_steps``; they stop at episode ends).
    :param sequence_length: steps per replayed run: a batch of ``batch_size`` graphs is
        ``batch_size // sequence_length`` runs of consecutive steps, along which the Q-network's
        recurrent state is carried and its gradients flow back through time (1: single steps from
        their stored states).
    :param train_freq: train every ``train_freq`` vec-steps.
    :param gradient_steps: gradient steps per training round.
    :param target_update_interval: gradient steps between target updates.
    :param target_entropy_ratio: ``p_alpha``; the target entropy is ``p_alpha * log(n_actions)``.
    :param alpha_init: initial temperature, or ``"auto"``: 0.1 times the standard deviation of the
        rewards stored at the first gradient step (see :mod:`sb3_hgrn.common.temperature`).
    :param learn_alpha: learn the temperature (``False`` keeps ``alpha_init``).
    :param alpha_optimizer: ``"adam"`` or ``"sgd"`` for the temperature.
    :param alpha_learning_rate: learning rate of the temperature optimiser.
    :param alpha_max_step: one update moves alpha by at most this fraction of its value.
    :param stochastic: ``False`` gives the deterministic ``-S`` variant.
    :param exploration_fraction: fraction of training over which epsilon decays.
    :param exploration_initial_eps: initial probability of a uniform random action per agent
        (``None``: 0.3 for the stochastic policy, 1 for ``stochastic=False``).
    :param exploration_final_eps: final epsilon (``None``: 0.3 stochastic, 0.05 deterministic).
    :param max_grad_norm: gradient-norm clip of the Q-network.
    :param hidden_dtype: storage dtype of recurrent states in the replay buffer.
    :param policy_kwargs: network options (``hidden_dim``, ``n_heads``, ``head_dim``,
        ``communication``, ``recurrent``, ``alpha_log_space``, ``average_tau`` for a Polyak-averaged
        Q-network that ``predict`` acts with, optimiser).
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"GraphPolicy": SoftHGRNPolicy}
    policy: SoftHGRNPolicy

    def __init__(
        self,
        policy: str | type[SoftHGRNPolicy],
        env: GymEnv | str | None,
        learning_rate: float | Schedule = 1e-3,
        buffer_size: int = 1_000_000,
        learning_starts: int = 10_000,
        batch_size: int = 32,
        tau: float = 1.0,
        gamma: float = 0.95,
        reward_scale: float | str = "auto",
        n_steps: int = 1,
        sequence_length: int = 1,
        train_freq: int | tuple[int, str] = 4,
        gradient_steps: int = 1,
        target_update_interval: int = 5,
        target_entropy_ratio: float = 0.2,
        alpha_init: float | str = 0.1,
        learn_alpha: bool = True,
        alpha_optimizer: str = "adam",
        alpha_learning_rate: float = 1e-2,
        alpha_max_step: float = 0.05,
        stochastic: bool = True,
        exploration_fraction: float = 0.1,
        exploration_initial_eps: float | None = None,
        exploration_final_eps: float | None = None,
        max_grad_norm: float = 10.0,
        hidden_dtype: str = "float16",
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        check_added_arguments(SoftHGRN, locals())
        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            reward_scale=reward_scale,
            n_steps=n_steps,
            sequence_length=sequence_length,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            target_update_interval=target_update_interval,
            target_entropy_ratio=target_entropy_ratio,
            alpha_init=alpha_init,
            learn_alpha=learn_alpha,
            alpha_optimizer=alpha_optimizer,
            alpha_learning_rate=alpha_learning_rate,
            alpha_max_step=alpha_max_step,
            stochastic=stochastic,
            exploration_fraction=exploration_fraction,
            exploration_initial_eps=exploration_initial_eps,
            exploration_final_eps=exploration_final_eps,
            max_grad_norm=max_grad_norm,
            hidden_dtype=hidden_dtype,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            seed=seed,
            device=device,
        )
        if _init_setup_model:
            self._setup_model()

    def _next_value(self, next_q: th.Tensor, alpha: th.Tensor) -> th.Tensor:
        """State value ``(batch, n_agents)`` of the next observations from target Q-values
        ``(batch, n_agents, n_actions)``: the soft value, or the hard max for ``stochastic=False``."""
        return soft_q_next_value(next_q, alpha, self.stochastic)

    def train(self, gradient_steps: int, batch_size: int = 32) -> None:
        self._start_training()
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        q_net, q_net_target = self.policy.q_net, self.policy.q_net_target
        losses, entropies, alpha_gradients = [], [], []
        for _ in range(gradient_steps):
            batch, steps = self._sample_runs(batch_size)
            alpha = self.policy.temperature.per_agent(batch.groups)
            with th.no_grad():
                next_graph = self.policy.graph_batch(batch.next_neighbors, batch.groups)
                next_q, _ = q_net_target(batch.next_observations, next_graph, batch.next_hidden)
                target_q = batch.bootstrapped(self._next_value(next_q, alpha))
            graph = self.policy.graph_batch(batch.neighbors, batch.groups)  # every step's graphs
            q_values = unroll(
                q_net, batch.observations, graph, steps[0].hidden, [step.starts for step in steps]
            )
            loss = q_regression_loss(q_values, batch.actions.unsqueeze(-1), target_q, batch.alive)
            gradient_step(self.policy.optimizer, loss, q_net, self.max_grad_norm)
            self.policy.update_average()

            entropy, alpha_gradient = self._update_temperature(
                boltzmann_entropy(q_values.detach(), alpha), batch.groups, batch.alive
            )
            if alpha_gradient is not None:
                alpha_gradients.append(alpha_gradient)
            losses.append(loss.item())
            entropies.append(entropy)
            self._n_updates += 1
            if self._n_updates % self.target_update_interval == 0:
                polyak_update(q_net.parameters(), q_net_target.parameters(), self.tau)

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/q_loss", float(np.mean(losses)))
        self._record_temperature(entropies, alpha_gradients)
