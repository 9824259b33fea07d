"""Many-agent environments of sb3_hgrn, as PettingZoo-style modules (``module.parallel_env(**kwargs)``).

``pursuit_v0`` needs MAgent2 (installed with the ``extra`` dependencies) when an env is built.
"""

from sb3_hgrn.envs import ctc_v0, pursuit_v0, surviving_v0, uav_mbs_v0

__all__ = ["ctc_v0", "pursuit_v0", "surviving_v0", "uav_mbs_v0"]
