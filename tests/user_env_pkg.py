"""A user's env module for the tests of ``--env MODULE:ATTR`` (``tests/test_user_env_cli.py``)."""

from __future__ import annotations

from tests.toy_envs import DictOnlyEnv

NOT_A_FACTORY = 3
"""An attribute that is not callable (``--env tests.user_env_pkg:NOT_A_FACTORY`` is refused)."""


def make_env(n_agents: int = 3, max_cycles: int = 5) -> DictOnlyEnv:
    """A plain PettingZoo ParallelEnv with its own graph (every agent sees everyone)."""
    return DictOnlyEnv(n_agents=n_agents, max_cycles=max_cycles)
