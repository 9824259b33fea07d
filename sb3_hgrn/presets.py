"""The paper's algorithms, ablations and baselines as named configurations of SoftHGRN and SACHGRN.

``make_model("dgn", env)`` builds the DGN baseline, ``make_model("sac_hgrn-R", env, paper=True)`` the
SAC-HGRN ablation without GRU at the paper's network size and schedule. Keyword overrides replace
preset values (``policy_kwargs`` is merged key by key).
"""

from __future__ import annotations

from typing import Any

from stable_baselines3.common.type_aliases import GymEnv

from sb3_hgrn.common.hgrn import PAPER_SIZE
from sb3_hgrn.common.off_policy import GraphOffPolicyAlgorithm, check_graph_env
from sb3_hgrn.sac_hgrn import SACHGRN
from sb3_hgrn.soft_hgrn import SoftHGRN

NO_COMMUNICATION = {"communication": "none"}
NO_MEMORY = {"recurrent": False}
OWN_GROUP = {"communication": "gat"}  # homogeneous attention: each agent group attends within itself

BASELINE_Q = dict(stochastic=False, reward_scale=1.0)
"""The Q-learning baselines: greedy, hard-max targets on the env's own rewards (no scaling)."""

PAPER_ACTOR_CRITIC = dict(behaviour_policy="actor", critic_target="actor", reward_scale=1.0)
"""SACHGRN as the paper runs it: the actor collects and is deployed, and the critics bootstrap on its
policy, on the env's own rewards (the library's SACHGRN defaults collect, deploy and bootstrap with
the critic's Boltzmann policy on scaled rewards)."""

PRESETS: dict[str, tuple[type[GraphOffPolicyAlgorithm], dict[str, Any]]] = {
    # baselines
    "dqn": (SoftHGRN, dict(BASELINE_Q, policy_kwargs={**NO_COMMUNICATION, **NO_MEMORY})),
    "commnet": (SoftHGRN, dict(BASELINE_Q, policy_kwargs={"communication": "mean", **NO_MEMORY})),
    "dgn": (SoftHGRN, dict(BASELINE_Q, policy_kwargs={**OWN_GROUP, **NO_MEMORY})),
    "hgn": (SoftHGRN, dict(BASELINE_Q, policy_kwargs=dict(NO_MEMORY))),
    "maac": (
        SACHGRN,
        dict(
            PAPER_ACTOR_CRITIC,
            learn_alpha=False,
            exploration_initial_eps=0.0,
            exploration_final_eps=0.0,
            policy_kwargs=dict(actor_kwargs={**NO_COMMUNICATION, **NO_MEMORY}, critic_kwargs=dict(NO_MEMORY)),
        ),
    ),
    # the paper's methods and their ablations
    "soft_hgrn": (SoftHGRN, {}),
    "soft_hgrn-G": (SoftHGRN, dict(policy_kwargs=dict(NO_COMMUNICATION))),
    "soft_hgrn-R": (SoftHGRN, dict(policy_kwargs=dict(NO_MEMORY))),
    "soft_hgrn-S": (SoftHGRN, dict(stochastic=False)),
    "sac_hgrn": (SACHGRN, {}),
    "sac_hgrn-G": (SACHGRN, dict(policy_kwargs=dict(NO_COMMUNICATION))),
    "sac_hgrn-R": (SACHGRN, dict(policy_kwargs=dict(NO_MEMORY))),
    "sac_hgrn-S": (SACHGRN, dict(stochastic=False)),
    # homogeneous-attention twins of the paper's methods (they differ only with several agent groups)
    "soft_dgrn": (SoftHGRN, dict(policy_kwargs=dict(OWN_GROUP))),
    "sac_dgrn": (SACHGRN, dict(policy_kwargs=dict(OWN_GROUP))),
}

HGAT_TWINS = {"dgn": "hgn", "soft_dgrn": "soft_hgrn", "sac_dgrn": "sac_hgrn"}
"""Homogeneous-attention preset -> its HGAT original."""

TABLE1 = (
    "dqn", "commnet", "maac", "dgn",
    "soft_hgrn", "soft_hgrn-G", "soft_hgrn-R", "soft_hgrn-S",
    "sac_hgrn", "sac_hgrn-G", "sac_hgrn-R", "sac_hgrn-S",
)  # fmt: skip
"""The rows of the paper's Table 1, in its order."""

PAPER_SCHEDULE: dict[str, Any] = dict(
    learning_rate=1e-3,
    batch_size=128,
    train_freq=25,  # 20 gradient steps per 500-step episode
    gradient_steps=1,
    gamma=0.95,
    target_update_interval=5,
    learning_starts=0,
    alpha_learning_rate=1e-3,  # the paper's temperature rule: at most 1 % of alpha per update
    alpha_max_step=0.01,
    reward_scale=1.0,
)
"""The paper's schedule, on unscaled rewards; the buffer holds 50,000 joint transitions (``make_model``
scales it)."""

PAPER_BUFFER_TRANSITIONS = 50_000
PAPER_EXPLORATION = dict(exploration_initial_eps=0.9, exploration_final_eps=0.3, exploration_fraction=0.5)
"""Epsilon-random actions per agent from 0.9 down to 0.3, for every method (the original holds 0.9 for
1,000 episodes, then decays exponentially to 0.3; here the decay is linear over half of training)."""


def merge(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """``base`` updated with ``overrides``; ``policy_kwargs`` and its nested dicts merge key by key."""
    merged = dict(base)
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def preset_kwargs(
    name: str, paper: bool = False, n_envs: int = 1
) -> tuple[type[GraphOffPolicyAlgorithm], dict]:
    """Algorithm class and keyword arguments of preset ``name``.

    :param paper: use the paper's network size (hidden 256, 4 heads of 256) and schedule.
    :param n_envs: slots of the env (for the paper's buffer of 50,000 joint transitions).
    """
    if name not in PRESETS:
        raise ValueError(f"Unknown preset {name!r}; available: {', '.join(PRESETS)}.")
    algorithm, kwargs = PRESETS[name]
    if paper:
        paper_kwargs = dict(
            PAPER_SCHEDULE,
            buffer_size=PAPER_BUFFER_TRANSITIONS * n_envs,
            tau=1.0 if algorithm is SoftHGRN else 0.01,
            policy_kwargs=dict(PAPER_SIZE),
            **(PAPER_ACTOR_CRITIC if algorithm is SACHGRN else {}),
        )
        # every method explores as the original: over a preset's own exploration (maac's none)
        kwargs = merge(merge(paper_kwargs, kwargs), PAPER_EXPLORATION)
    return algorithm, kwargs


def make_model(
    name: str, env: GymEnv | str, paper: bool = False, **overrides: Any
) -> GraphOffPolicyAlgorithm:
    """Build preset ``name`` (see :data:`PRESETS`) on ``env``; ``overrides`` replace preset values."""
    env = check_graph_env(env)
    algorithm, kwargs = preset_kwargs(name, paper=paper, n_envs=env.num_envs)
    return algorithm("GraphPolicy", env, **merge(kwargs, overrides))
