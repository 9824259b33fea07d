from sb3_hgrn.soft_dqn.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, SoftDQNPolicy
from sb3_hgrn.soft_dqn.soft_dqn import SoftDQN

__all__ = ["CnnPolicy", "MlpPolicy", "MultiInputPolicy", "SoftDQN", "SoftDQNPolicy"]
