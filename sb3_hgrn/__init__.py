"""sb3_hgrn: graph-recurrent many-agent reinforcement learning for Stable-Baselines3,
and the same soft algorithms for single-agent envs (SoftDQN, DiscreteSAC).

The public names are imported when first used (PEP 562), so that importing the env side,
:mod:`sb3_hgrn.envs`, does not import torch.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_MODULES = {
    "AgentViewCNN": "sb3_hgrn.common.torch_layers",
    "DiscreteSAC": "sb3_hgrn.discrete_sac",
    "DrivenAgents": "sb3_hgrn.envs.wrappers",
    "GraphEvalCallback": "sb3_hgrn.common.evaluation",
    "GraphFromPositions": "sb3_hgrn.envs.wrappers",
    "GraphVecEnv": "sb3_hgrn.common.vec_env",
    "ModelController": "sb3_hgrn.common.saved_controllers",
    "RandomGraphPolicy": "sb3_hgrn.common.evaluation",
    "SACHGRN": "sb3_hgrn.sac_hgrn",
    "SoftDQN": "sb3_hgrn.soft_dqn",
    "SoftHGRN": "sb3_hgrn.soft_hgrn",
    "TeamFigures": "sb3_hgrn.envs.wrappers",
    "evaluate_graph_policy": "sb3_hgrn.common.evaluation",
    "evaluate_team_episodes": "sb3_hgrn.common.evaluation",
    "make_graph_vec_env": "sb3_hgrn.common.vec_env",
}
"""The module that defines each public name."""

__all__ = [
    "AgentViewCNN",
    "DiscreteSAC",
    "DrivenAgents",
    "GraphEvalCallback",
    "GraphFromPositions",
    "GraphVecEnv",
    "ModelController",
    "RandomGraphPolicy",
    "SACHGRN",
    "SoftDQN",
    "SoftHGRN",
    "TeamFigures",
    "__version__",
    "evaluate_graph_policy",
    "evaluate_team_episodes",
    "make_graph_vec_env",
]


def __getattr__(name: str) -> Any:
    """Import a public name from its module on first use (later uses find it in the module)."""
    module = _MODULES.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
