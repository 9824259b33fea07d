"""Many-agent environments of sb3_hgrn, as PettingZoo-style modules (``module.parallel_env(**kwargs)``)."""

from sb3_hgrn.envs import surviving_v0

__all__ = ["surviving_v0"]
