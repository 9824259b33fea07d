"""SAC-HGRN: discrete soft actor-critic on graphs with a temperature that tracks a target entropy."""

from __future__ import annotations

from functools import partial
from typing import Any, ClassVar

import torch as th
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, Schedule

from sb3_hgrn.common.attention import GraphBatch
from sb3_hgrn.common.buffers import GraphSamples
from sb3_hgrn.common.off_policy import GraphOffPolicyAlgorithm, check_added_arguments, unroll
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
    critic_minimum,
)
from sb3_hgrn.sac_hgrn.policies import SACHGRNPolicy


class SACHGRN(SoftActorCritic, GraphOffPolicyAlgorithm):
    """SAC-HGRN (discrete soft actor-critic with HGRN actor and critics, Ye et al., AAAI 2022).

    Critic target: ``r + gamma * (1 - terminated) * sum_a pi(a|o') (Q_target(o', a) - alpha log pi(a|o'))``
    with ``Q_target`` the minimum over critics when there are several and ``pi`` the Boltzmann policy
    ``softmax(Q_target(o', .) / alpha)`` (``critic_target="boltzmann"``, so the sum is the soft value
    ``alpha * logsumexp(Q_target(o', .) / alpha)``) or the actor's (``"actor"``, the paper's); with
    ``n_steps > 1`` the discounted sum of ``n_steps`` rewards and ``gamma ** n_steps``, as in
    SoftHGRN. Every actor loss has the same minimiser, the Boltzmann policy ``softmax(Q(o, .) / alpha)``:

    - ``"boltzmann"`` (default): ``KL(softmax(Q(o, .) / alpha) || pi(.|o))``, whose gradient on the
      logits is ``pi - softmax(Q / alpha)`` (see :func:`boltzmann_divergence`);
    - ``"standard"`` (discrete SAC): ``sum_a pi(a|o) (alpha log pi(a|o) - Q(o, a))``, i.e.
      ``KL(pi || softmax(Q / alpha))`` up to a constant; its gradient on an action's logit is
      proportional to that action's probability, so an action the actor dropped early (a costly tag,
      a last-step choice) is hardly ever taken up again (docs/results.md);
    - ``"policy_gradient"`` (the paper's form): ``-log pi(a|o) (Q(o, a) - alpha log pi(a|o))`` for
      ``a`` sampled from the policy.

    Losses and entropies are means over the agents alive at their step (see
    :class:`~sb3_hgrn.common.vec_env.GraphVecEnv` for agents that die).

    Each gradient step updates the critics, then the actor (``actor_steps`` times; not at all by
    default where nothing reads it), then alpha (toward ``target_entropy_ratio * log|A|`` on the
    entropy of the critic's Boltzmann policy ``softmax(Q / alpha)``, the policy the actor is trained
    toward; or on the actor's own entropy, as in the paper, with ``alpha_entropy="actor"``). Where
    the actor trains, its entropy is logged as ``train/actor_entropy``. With ``stochastic=False`` (``-S``) the
    actor acts greedily with epsilon-greedy exploration, the target follows the greedy action and the
    actor moves toward the greedy action of the critic (``"boltzmann"``: cross-entropy to it; the
    other losses maximise ``sum_a pi(a|o) Q(o, a)``).

    Units and the shared options: see :class:`~sb3_hgrn.soft_hgrn.SoftHGRN`. Critic targets are
    copied every ``target_update_interval`` gradient steps (``tau=1.0``); the original's
    ``tau=0.01`` (used by ``presets.make_model(..., paper=True)``) left the critic behind a nearly
    frozen target at CPU budgets (docs/results.md).

    Defaults (``reward_scale="auto"``, ``alpha_learning_rate=1e-2``, ``alpha_max_step=0.05``,
    collecting with 30 % uniform random actions per agent and with the critic's policy) are
    SoftHGRN's, and the critics bootstrap on their own Boltzmann policy; both were chosen on a suite
    of eight envs (docs/results_defaults.md, "SAC-HGRN's defaults"). ``make_model(..., paper=True)``
    and the ``maac`` preset keep the paper's.

    :param actor_loss: ``"boltzmann"``, ``"standard"`` or ``"policy_gradient"``.
    :param alpha_entropy: the entropy alpha steers toward the target: ``"boltzmann"`` (that of the
        critic's Boltzmann policy ``softmax(Q / alpha)``, which every actor loss moves the actor
        toward; as in SoftHGRN) or ``"actor"`` (the actor's, as in the paper). An actor that lags
        its critic keeps its entropy above the target whatever alpha does, so steering by it drives
        alpha to its floor (docs/results.md, "Temperature").
    :param behaviour_policy: the policy the agents act with while collecting: ``"critic"`` (the
        default), the first critic's Boltzmann policy ``softmax(Q / alpha)``, the policy every actor
        loss moves the actor toward, or ``"actor"`` (as in the paper). The actor and the critics learn
        the same way either way (off-policy). ``predict`` and every evaluation act with the same
        policy as collecting (with ``average_tau``, that of the network's average), so that the saved
        model is the policy its training returns describe. The actor lags its critic (its entropy
        stays 0.4 to 2 nats above the Boltzmann policy's on the suite of docs/results_defaults.md);
        collecting with it scored 542 against 1,670 on UAV-MBS there. Models saved before this
        option existed load with ``"actor"``, as they trained; so do those saved before
        ``alpha_entropy`` for that option.
    :param critic_target: the policy the critics' targets average over at the next observations:
        ``"boltzmann"`` (the default: ``softmax(min_i Q_target_i / alpha)``, whose soft expectation
        is the soft value of soft Q-learning, taken of the target critics' minimum) or ``"actor"``
        (discrete SAC's exact soft expectation over the actor's policy, as in the paper). The actor
        lags its critic, so with ``"actor"`` the critics value a more random policy than the one
        that collects: on MAgent2 battle they valued attacks so little that the saved models
        scored 8 against 59 with ``"boltzmann"`` (docs/results_defaults.md). Models saved before
        this option existed load with ``"actor"``, as they trained.
    :param actor_steps: actor gradient steps on each batch, after its one critic step: more let the
        actor keep up with a critic that moves fast (docs/results.md). 0 never runs the actor in
        training or collection, which is only allowed when nothing reads it
        (``behaviour_policy="critic"``, ``critic_target="boltzmann"`` and
        ``alpha_entropy="boltzmann"``): the critics, alpha and the deployed policy then train exactly
        as with 1, in about two thirds of the update time, and the saved actor is untrained.
        ``"auto"`` (the default) is 0 where nothing reads the actor, as at the defaults, and 1 where
        something does (docs/usage.md). Models saved before this option existed load with 1.
    :param policy_kwargs: network options for both networks, plus ``n_critics``, ``actor_kwargs``,
        ``critic_kwargs`` (options of one network only), ``tempered_actor`` and ``average_tau`` (a
        Polyak-averaged actor that ``predict`` acts with).
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"GraphPolicy": SACHGRNPolicy}
    policy: SACHGRNPolicy
    defaults_before_saved: ClassVar[dict[str, Any]] = {
        **GraphOffPolicyAlgorithm.defaults_before_saved,
        "alpha_entropy": "actor",
        "behaviour_policy": "actor",
        "critic_target": "actor",
        "actor_steps": 1,
    }
    policy_settings: ClassVar[tuple[str, ...]] = (
        *GraphOffPolicyAlgorithm.policy_settings,
        "behaviour_policy",
    )

    def __init__(
        self,
        policy: str | type[SACHGRNPolicy],
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
        actor_loss: str = "boltzmann",
        alpha_entropy: str = "boltzmann",
        behaviour_policy: str = "critic",
        critic_target: str = "boltzmann",
        actor_steps: int | str = "auto",
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
        check_added_arguments(SACHGRN, locals())
        if actor_loss not in ACTOR_LOSSES:
            raise ValueError(f"actor_loss must be one of {ACTOR_LOSSES}, got {actor_loss!r}.")
        if alpha_entropy not in ALPHA_ENTROPIES:
            raise ValueError(f"alpha_entropy must be one of {ALPHA_ENTROPIES}, got {alpha_entropy!r}.")
        policy_kwargs = with_behaviour_policy(policy_kwargs, behaviour_policy, "SACHGRN")
        check_critic_target(critic_target)
        actor_steps = resolve_actor_steps(actor_steps, behaviour_policy, critic_target, alpha_entropy)
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
        self.actor_loss = actor_loss
        self.alpha_entropy = alpha_entropy
        self.behaviour_policy = behaviour_policy
        self.critic_target = critic_target
        self.actor_steps = actor_steps
        if _init_setup_model:
            self._setup_model()

    def _optimizer_names(self) -> list[str]:
        return ["policy.actor_optimizer", "policy.critic_optimizer"]

    def _behaviour_act(self, obs: dict[str, th.Tensor], hidden: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        if self.behaviour_policy == "critic":  # the actor's state is only stored for its training
            return self.policy.critic_act(obs, hidden, runs_actor=self.actor_steps > 0)
        return super()._behaviour_act(obs, hidden)

    @classmethod
    def load(cls, *args: Any, **kwargs: Any) -> SACHGRN:
        """:meth:`GraphOffPolicyAlgorithm.load`, also refusing (a ``ValueError``) options that read an
        actor trained with ``actor_steps=0``."""
        model = super().load(*args, **kwargs)
        model._resolve_loaded_actor_steps()
        return model

    def _after_actor_steps(self) -> None:
        self.policy.update_average()

    def _actor_logits(
        self, batch: GraphSamples, graph: GraphBatch, state: th.Tensor, starts: list[th.Tensor]
    ) -> th.Tensor:
        """The actor's logits ``(steps * batch, n_agents, n_actions)`` along runs of consecutive
        samples (``batch``, step-major, and every step's ``starts``) from its stored state ``state``
        (see :func:`~sb3_hgrn.common.off_policy.unroll`)."""
        outputs = unroll(self.policy.actor, batch.observations, graph, state, starts)
        return self.policy.logits(outputs, batch.groups)

    def _next_actor_logits(self, batch: GraphSamples, graph: Any, state: th.Tensor) -> th.Tensor:
        """The actor's logits ``(batch, n_agents, n_actions)`` at ``batch``'s next observations, from
        its state ``state`` there."""
        return self.policy.actor_logits(batch.next_observations, graph, state, batch.groups)[0]

    def train(self, gradient_steps: int, batch_size: int = 32) -> None:
        self._start_training()
        policy = self.policy
        policy.set_training_mode(True)
        self._update_learning_rate([policy.actor_optimizer, policy.critic_optimizer])
        figures = SACFigures()
        for _ in range(gradient_steps):
            batch, steps = self._sample_runs(batch_size)
            actor_state, *critic_states = policy.split_state(steps[0].hidden)
            next_actor_state, *next_critic_states = policy.split_state(batch.next_hidden)
            alpha = policy.temperature.per_agent(batch.groups)
            graph = policy.graph_batch(batch.neighbors, batch.groups)  # every step's, actor and critics
            starts = [step.starts for step in steps]
            with th.no_grad():
                next_graph = policy.graph_batch(batch.next_neighbors, batch.groups)
                next_q = critic_minimum(
                    [
                        target(batch.next_observations, next_graph, state)[0]
                        for target, state in zip(policy.critic_targets, next_critic_states, strict=True)
                    ]
                )
                next_value = self._next_value(
                    next_q,
                    partial(self._next_actor_logits, batch, next_graph, next_actor_state),
                    alpha,
                )
                target_q = batch.bootstrapped(next_value)

            q_values = [
                unroll(critic, batch.observations, graph, state, starts)
                for critic, state in zip(policy.critics, critic_states, strict=True)
            ]
            self._sac_step(
                q_values,
                batch.actions.unsqueeze(-1),
                target_q,
                partial(self._actor_logits, batch, graph, actor_state, starts),
                alpha,
                batch.groups,
                batch.alive,
                figures,
            )
        self._record_sac(figures)
