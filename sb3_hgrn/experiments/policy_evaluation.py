"""Evaluating a graph policy: wrappers that change or count its actions, and the team-return
figures of an evaluation."""

from __future__ import annotations

from typing import Any

import numpy as np

from sb3_hgrn.common.evaluation import RandomGraphPolicy, evaluate_graph_policy
from sb3_hgrn.common.vec_env import GraphVecEnv


class PolicyWrapper:
    """Anything with a graph model's ``predict``, whose actions :meth:`adjust` sees (and may change).

    :param model: anything with a graph model's ``predict``.
    """

    def __init__(self, model: Any):
        self.model = model

    def predict(
        self,
        observation: dict[str, np.ndarray],
        state: Any = None,
        episode_start: Any = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, Any]:
        """The wrapped model's actions ``(n_slots,)`` after :meth:`adjust`, and its state."""
        actions, state = self.model.predict(
            observation, state=state, episode_start=episode_start, deterministic=deterministic
        )
        return self.adjust(observation, np.asarray(actions)), state

    def adjust(self, observation: dict[str, np.ndarray], actions: np.ndarray) -> np.ndarray:
        """The actions to return instead of the model's ``actions`` ``(n_slots,)``."""
        raise NotImplementedError


class EpsilonRandomPolicy(PolicyWrapper):
    """A model whose action is replaced, per agent with probability ``epsilon``, by a uniformly random
    valid action (within ``obs["action_mask"]`` when present): the original code's evaluation mode.

    :param model: anything with a graph model's ``predict``.
    :param epsilon: probability of a random action per agent and step.
    """

    def __init__(self, model: Any, epsilon: float, seed: int | None = None):
        if not 0.0 <= epsilon <= 1.0:
            raise ValueError(f"epsilon must lie in [0, 1], got {epsilon}.")
        super().__init__(model)
        self.epsilon = epsilon
        self.n_actions = int(model.action_space.n)
        self.rng = np.random.default_rng(seed)

    def adjust(self, observation: dict[str, np.ndarray], actions: np.ndarray) -> np.ndarray:
        """Each action replaced by a random valid one with probability ``epsilon``."""
        n_slots = len(observation["obs"])
        mask = observation.get("action_mask")
        valid = (
            np.ones((n_slots, self.n_actions), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        )
        random_actions = np.argmax(self.rng.random(valid.shape) * valid, axis=1)  # uniform among valid
        explore = self.rng.random(n_slots) < self.epsilon
        return np.where(explore, random_actions, actions)


class ActionCounter(PolicyWrapper):
    """A model whose actions are counted, per action index.

    :param model: anything with a graph model's ``predict``.
    :param n_actions: size of the (padded) action space.
    """

    def __init__(self, model: Any, n_actions: int):
        super().__init__(model)
        self.counts = np.zeros(n_actions, dtype=np.int64)

    def adjust(self, observation: dict[str, np.ndarray], actions: np.ndarray) -> np.ndarray:
        """The actions unchanged, counted."""
        self.counts += np.bincount(actions.ravel(), minlength=len(self.counts))
        return actions

    def frequencies(self) -> list[float]:
        """Fraction of all counted agent-steps that took each action (zeros before any step)."""
        return (self.counts / max(1, int(self.counts.sum()))).tolist()


def action_rule(model: Any, deterministic: bool) -> str:
    """How ``model.predict(..., deterministic=deterministic)`` picks its actions, before any
    :class:`PolicyWrapper` (such as :class:`EpsilonRandomPolicy`) changes them: ``"uniform random"``
    for a :class:`RandomGraphPolicy`, ``"greedy"`` with ``deterministic`` or for a graph model with
    ``stochastic=False`` (the DQN-style presets and the ``-S`` variants), ``"sampled"`` for a
    stochastic graph model, else ``"predict(deterministic=False)"`` (a model this cannot tell)."""
    while isinstance(model, PolicyWrapper):
        model = model.model
    if isinstance(model, RandomGraphPolicy):
        return "uniform random"
    stochastic = getattr(getattr(model, "policy", None), "stochastic", None)
    if deterministic or stochastic is False:
        return "greedy"
    return "sampled" if stochastic else "predict(deterministic=False)"


def deployed_label(model: Any) -> str | None:
    """The network a graph model acts with, in words (see
    :attr:`~sb3_hgrn.common.policies.GraphPolicy.deployed_label`), under any :class:`PolicyWrapper`;
    ``None`` for a policy without networks (such as :class:`RandomGraphPolicy`)."""
    while isinstance(model, PolicyWrapper):
        model = model.model
    return getattr(getattr(model, "policy", None), "deployed_label", None)


def evaluate_model(model: Any, env: GraphVecEnv, n_episodes: int, deterministic: bool) -> dict[str, Any]:
    """Team-return figures of ``n_episodes`` episodes: mean, std, per-episode returns and lengths, the
    fraction of agent-steps that took each action (over every step the evaluation ran), the action
    rule used (``actions``, see :func:`action_rule`; ``deterministic`` says whether it is greedy), the
    network that acted (``network``, see :func:`deployed_label`) and the probability ``epsilon`` of a
    random action mixed in."""
    counter = ActionCounter(model, int(env.action_space.n))
    returns, lengths = evaluate_graph_policy(
        counter, env, n_eval_episodes=n_episodes, deterministic=deterministic, return_episode_rewards=True
    )
    rule = action_rule(model, deterministic)
    return {
        "mean": float(np.mean(returns)),
        "std": float(np.std(returns)),
        "returns": [float(r) for r in returns],
        "lengths": [int(n) for n in lengths],
        "n_episodes": len(returns),
        "actions": rule,
        "deterministic": rule == "greedy",
        "network": deployed_label(model),
        "epsilon": float(getattr(model, "epsilon", 0.0)),
        "action_frequencies": counter.frequencies(),
    }
