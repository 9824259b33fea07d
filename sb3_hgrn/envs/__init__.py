"""The env side of sb3_hgrn: many-agent environments as PettingZoo-style modules
(``module.parallel_env(**kwargs)``) and what they are built from.

- :mod:`~sb3_hgrn.envs.base`: :class:`~sb3_hgrn.envs.base.GraphParallelEnv`, the ``ParallelEnv``
  with an array API that every env here subclasses;
- :mod:`~sb3_hgrn.envs.graph`: communication graphs of agents on grid cells;
- :mod:`~sb3_hgrn.envs.position_graph` and :mod:`~sb3_hgrn.envs.wrappers`: graphs from agent
  positions (:class:`~sb3_hgrn.envs.wrappers.GraphFromPositions`) for any PettingZoo env, and
  :class:`~sb3_hgrn.envs.wrappers.DrivenAgents`, which lets one team of it learn, and
  :class:`~sb3_hgrn.envs.wrappers.TeamFigures`, which reports its episodes' figures;
- :mod:`~sb3_hgrn.envs.driven_sides`: what drives the agents that do not learn (random, scripted or
  a model);
- :mod:`~sb3_hgrn.envs.rendering`: the pygame window of ``render_mode="human"``.

It needs numpy, gymnasium and PettingZoo (scipy for graphs from positions, pygame to show a window)
and imports no torch, no Stable-Baselines3 and nothing of the learner side (``tests/test_layout.py``
checks this). ``pursuit_v0`` needs MAgent2 (installed with the ``extra`` dependencies) when an env is
built.
"""

from sb3_hgrn.envs import ctc_v0, pursuit_v0, surviving_v0, uav_mbs_v0

__all__ = ["ctc_v0", "pursuit_v0", "surviving_v0", "uav_mbs_v0"]
