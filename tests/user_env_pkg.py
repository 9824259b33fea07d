"""A user's env module for the tests of ``--env MODULE:ATTR`` (``tests/test_user_env_cli.py``)."""

from __future__ import annotations

from typing import Any

from sb3_hgrn import DrivenAgents
from sb3_hgrn.envs.driven_sides import controller_paths
from tests.toy_envs import DictOnlyEnv

NOT_A_FACTORY = 3
"""An attribute that is not callable (``--env tests.user_env_pkg:NOT_A_FACTORY`` is refused)."""


def make_env(n_agents: int = 3, max_cycles: int = 5) -> DictOnlyEnv:
    """A plain PettingZoo ParallelEnv with its own graph (every agent sees everyone)."""
    return DictOnlyEnv(n_agents=n_agents, max_cycles=max_cycles)


def make_driven_env(controller: Any = "random", n_agents: int = 6, max_cycles: int = 5) -> DrivenAgents:
    """The first half of :class:`DictOnlyEnv`'s agents learn; ``controller`` drives the others."""
    learners = [f"a{i}" for i in range(n_agents // 2)]
    return DrivenAgents(
        DictOnlyEnv(n_agents=n_agents, max_cycles=max_cycles), learners, controller=controller
    )


def model_paths(env_kwargs: dict[str, Any]) -> dict[str, str]:
    """``make_driven_env``'s controller given as a saved model's path: loaded on the learner side."""
    return controller_paths(env_kwargs, {"controller": ("random",)})
