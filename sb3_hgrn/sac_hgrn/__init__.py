from sb3_hgrn.sac_hgrn.policies import SACHGRNPolicy
from sb3_hgrn.sac_hgrn.sac_hgrn import SACHGRN

__all__ = ["SACHGRN", "SACHGRNPolicy"]
