"""DiscreteSAC: soft actor-critic for discrete actions, with a temperature that tracks a target entropy."""

from __future__ import annotations

from functools import partial
from typing import Any, ClassVar

import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule

from sb3_hgrn.common.files import check_policy_settings
from sb3_hgrn.common.single_agent import TEMPERATURE_SAVE_PARAMS, check_discrete_env, transitions
from sb3_hgrn.common.soft_actor_critic import (
    SACFigures,
    SoftActorCritic,
    check_critic_target,
    resolve_actor_steps,
    with_behaviour_policy,
)
from sb3_hgrn.common.soft_math import (
    ACTOR_LOSSES,
    ALPHA_ENTROPIES,
    bootstrapped,
    critic_minimum,
)
from sb3_hgrn.common.tensorboard import AlgorithmNamedRuns
from sb3_hgrn.discrete_sac.policies import CnnPolicy, DiscreteSACPolicy, MlpPolicy, MultiInputPolicy


class DiscreteSAC(AlgorithmNamedRuns, SoftActorCritic, OffPolicyAlgorithm):
    """Soft actor-critic for any Gymnasium env with a ``Discrete`` action space, used as SB3's ``SAC``.

    The critics regress (squared error) on the exact soft expectation over actions,
    ``r + gamma * (1 - terminated) * sum_a pi(a|o') (min_i Q_target_i(o', a) - alpha log pi(a|o'))``
    (with ``n_steps > 1``, SB3's n-step returns). The actor then moves toward the Boltzmann policy
    ``softmax(min_i Q_i(o, .) / alpha)`` by ``actor_loss`` (``"boltzmann"``: ``KL(softmax(Q / alpha) ||
    pi)``; ``"standard"``: the usual discrete-SAC loss ``sum_a pi(a) (alpha log pi(a) - Q(a))``;
    ``"policy_gradient"``), and alpha steps toward ``target_entropy_ratio * log(n_actions)`` on the
    entropy that ``alpha_entropy`` names. These are the targets, losses and temperature controller of
    :class:`~sb3_hgrn.SACHGRN` (:mod:`sb3_hgrn.common.soft_math`, :mod:`sb3_hgrn.common.temperature`).

    Units as SB3's ``SAC``: ``target_update_interval`` counts gradient steps and the critic targets
    follow with Polyak coefficient ``tau``; ``learning_starts`` steps of uniform random actions.

    :param actor_loss: ``"boltzmann"``, ``"standard"`` or ``"policy_gradient"``.
    :param alpha_entropy: ``"boltzmann"`` (the entropy of ``softmax(Q / alpha)``, the policy the actor
        is trained toward) or ``"actor"`` (the actor's own).
    :param behaviour_policy: the policy that collects and that ``predict`` acts with: ``"actor"``, or
        ``"critic"``, the first critic's Boltzmann policy ``softmax(Q / alpha)`` (the policy every
        actor loss moves the actor toward; the actor still gives the targets' soft values), as
        :class:`~sb3_hgrn.SACHGRN`'s option of that name.
    :param critic_target: ``"actor"`` (the targets above) or ``"boltzmann"``: the soft expectation
        over ``softmax(min_i Q_target_i(o', .) / alpha)`` instead of the actor's policy, which is the
        soft value ``alpha * logsumexp(min_i Q_target_i(o', .) / alpha)``, as :class:`~sb3_hgrn.SACHGRN`'s
        option of that name.
    :param actor_steps: actor gradient steps per critic step; 0 never trains the actor, where
        nothing reads it (``behaviour_policy="critic"``, ``critic_target="boltzmann"`` and
        ``alpha_entropy="boltzmann"``); ``"auto"`` (the default) is 0 there and 1 otherwise, as
        :class:`~sb3_hgrn.SACHGRN`'s option of that name.
    :param target_entropy_ratio: the target entropy is ``target_entropy_ratio * log(n_actions)``.
    :param alpha_init: initial temperature, or ``"auto"``: 0.1 times the standard deviation of the
        rewards stored at the first gradient step (see :mod:`sb3_hgrn.common.temperature`).
    :param learn_alpha: learn the temperature (``False`` keeps ``alpha_init``).
    :param alpha_optimizer: ``"adam"`` or ``"sgd"`` for the temperature.
    :param alpha_learning_rate: learning rate of the temperature optimiser.
    :param alpha_max_step: one update moves alpha by at most this fraction of its value.
    :param max_grad_norm: gradient-norm clip of the actor and of the critics.
    :param policy_kwargs: SB3's ``DQNPolicy`` options for every network, plus ``n_critics`` and
        ``alpha_log_space``.
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: DiscreteSACPolicy
    stochastic = True  # the stochastic variant only (the graph algorithms also have a greedy one)

    def __init__(
        self,
        policy: str | type[DiscreteSACPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        target_update_interval: int = 1,
        actor_loss: str = "boltzmann",
        alpha_entropy: str = "boltzmann",
        behaviour_policy: str = "actor",
        critic_target: str = "actor",
        actor_steps: int | str = "auto",
        target_entropy_ratio: float = 0.2,
        alpha_init: float | str = 0.1,
        learn_alpha: bool = True,
        alpha_optimizer: str = "adam",
        alpha_learning_rate: float = 1e-3,
        alpha_max_step: float = 0.01,
        max_grad_norm: float = 10.0,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        if actor_loss not in ACTOR_LOSSES:
            raise ValueError(f"actor_loss must be one of {ACTOR_LOSSES}, got {actor_loss!r}.")
        if alpha_entropy not in ALPHA_ENTROPIES:
            raise ValueError(f"alpha_entropy must be one of {ALPHA_ENTROPIES}, got {alpha_entropy!r}.")
        policy_kwargs = with_behaviour_policy(policy_kwargs, behaviour_policy, "DiscreteSAC")
        check_critic_target(critic_target)
        actor_steps = resolve_actor_steps(actor_steps, behaviour_policy, critic_target, alpha_entropy)
        super().__init__(
            policy,
            check_discrete_env(env, "DiscreteSAC", verbose),
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
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            sde_support=False,
            support_multi_env=True,
            supported_action_spaces=(spaces.Discrete,),
        )
        self.target_update_interval = target_update_interval
        self.actor_loss = actor_loss
        self.alpha_entropy = alpha_entropy
        self.behaviour_policy = behaviour_policy
        self.critic_target = critic_target
        self.actor_steps = actor_steps
        self._set_temperature_options(
            target_entropy_ratio,
            alpha_init,
            learn_alpha,
            alpha_optimizer,
            alpha_learning_rate,
            alpha_max_step,
        )
        self.max_grad_norm = max_grad_norm
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        super()._setup_model()
        self._setup_temperature()

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        self._start_temperature()
        policy = self.policy
        policy.set_training_mode(True)
        self._update_learning_rate([policy.actor_optimizer, policy.critic_optimizer])
        figures = SACFigures()
        for _ in range(gradient_steps):
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            batch = transitions(data, self.gamma)
            alpha = policy.temperature.per_agent(None)
            with th.no_grad():
                next_q = critic_minimum([target(data.next_observations) for target in policy.critic_targets])
                next_value = self._next_value(next_q, partial(policy.actor, data.next_observations), alpha)
                target_q = bootstrapped(batch.rewards, batch.discounts, batch.terminated, next_value)
            self._sac_step(
                [critic(data.observations) for critic in policy.critics],
                batch.actions,
                target_q,
                partial(policy.actor, data.observations),
                alpha,
                None,
                batch.mask,
                figures,
            )
        self._record_sac(figures)

    @classmethod
    def load(cls, *args: Any, **kwargs: Any) -> DiscreteSAC:
        """SB3's ``load``, refusing (a ``ValueError``) a ``behaviour_policy`` other than the saved
        policy's (the policy is built with it, so a new one would not change how it acts) and
        options that read an actor trained with ``actor_steps=0``."""
        model = super().load(*args, **kwargs)
        check_policy_settings(model, ["behaviour_policy"])
        model._resolve_loaded_actor_steps()
        return model

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", "policy.actor_optimizer", "policy.critic_optimizer", *TEMPERATURE_SAVE_PARAMS], []
