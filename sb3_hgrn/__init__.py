"""sb3_hgrn: graph-recurrent many-agent reinforcement learning for Stable-Baselines3."""

from sb3_hgrn.common.evaluation import GraphEvalCallback, RandomGraphPolicy, evaluate_graph_policy
from sb3_hgrn.common.torch_layers import AgentViewCNN
from sb3_hgrn.common.vec_env import GraphVecEnv, make_graph_vec_env
from sb3_hgrn.envs.wrappers import GraphFromPositions
from sb3_hgrn.sac_hgrn import SACHGRN
from sb3_hgrn.soft_hgrn import SoftHGRN

__version__ = "0.1.0"

__all__ = [
    "AgentViewCNN",
    "GraphEvalCallback",
    "GraphFromPositions",
    "GraphVecEnv",
    "RandomGraphPolicy",
    "SACHGRN",
    "SoftHGRN",
    "__version__",
    "evaluate_graph_policy",
    "make_graph_vec_env",
]
