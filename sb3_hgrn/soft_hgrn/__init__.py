from sb3_hgrn.soft_hgrn.policies import SoftHGRNPolicy
from sb3_hgrn.soft_hgrn.soft_hgrn import SoftHGRN

__all__ = ["SoftHGRN", "SoftHGRNPolicy"]
