"""The paper's Table 1 (Ye et al., AAAI 2022) as data: team return, mean +- std over 3 runs of 2,000
test episodes each."""

from __future__ import annotations

TABLE1_ENVS = ("uav_mbs_v0", "surviving_v0", "pursuit_v0")
"""The columns of Table 1, in its order."""

ENV_TITLES = {"uav_mbs_v0": "UAV-MBS", "surviving_v0": "Surviving", "pursuit_v0": "Pursuit", "ctc_v0": "CTC"}

PRESET_TITLES = {
    "dqn": "DQN", "commnet": "CommNet", "maac": "MAAC", "dgn": "DGN",
    "soft_hgrn": "Soft-HGRN", "soft_hgrn-G": "Soft-HGRN -G", "soft_hgrn-R": "Soft-HGRN -R",
    "soft_hgrn-S": "Soft-HGRN -S", "sac_hgrn": "SAC-HGRN", "sac_hgrn-G": "SAC-HGRN -G",
    "sac_hgrn-R": "SAC-HGRN -R", "sac_hgrn-S": "SAC-HGRN -S", "random": "Random",
    "hgn": "HGN", "soft_dgrn": "Soft-DGRN", "sac_dgrn": "SAC-DGRN",
}  # fmt: skip

PAPER_TABLE1: dict[str, dict[str, tuple[float, float]]] = {
    # preset: {env: (mean, std)}          UAV-MBS          Surviving          Pursuit
    "dqn": {"uav_mbs_v0": (2314, 177), "surviving_v0": (-7453, 74), "pursuit_v0": (5007, 150)},
    "commnet": {"uav_mbs_v0": (2377, 116), "surviving_v0": (-7511, 82), "pursuit_v0": (5222, 60)},
    "maac": {"uav_mbs_v0": (3435, 88), "surviving_v0": (-10, 46), "pursuit_v0": (5927, 91)},
    "dgn": {"uav_mbs_v0": (2808, 109), "surviving_v0": (-286, 67), "pursuit_v0": (4552, 50)},
    "soft_hgrn": {"uav_mbs_v0": (4051, 75), "surviving_v0": (194, 41), "pursuit_v0": (6840, 20)},
    "soft_hgrn-G": {"uav_mbs_v0": (3751, 59), "surviving_v0": (-118, 90), "pursuit_v0": (7138, 96)},
    "soft_hgrn-R": {"uav_mbs_v0": (2935, 134), "surviving_v0": (-26, 61), "pursuit_v0": (5649, 166)},
    "soft_hgrn-S": {"uav_mbs_v0": (3925, 46), "surviving_v0": (-89, 35), "pursuit_v0": (5570, 30)},
    "sac_hgrn": {"uav_mbs_v0": (4072, 77), "surviving_v0": (325, 48), "pursuit_v0": (7033, 55)},
    "sac_hgrn-G": {"uav_mbs_v0": (3580, 75), "surviving_v0": (-36, 63), "pursuit_v0": (7183, 77)},
    "sac_hgrn-R": {"uav_mbs_v0": (3052, 22), "surviving_v0": (141, 13), "pursuit_v0": (5797, 36)},
    "sac_hgrn-S": {"uav_mbs_v0": (3723, 82), "surviving_v0": (-376, 27), "pursuit_v0": (-76, 1)},
}
"""Table 1 of the paper, keyed by sb3_hgrn preset and env name."""

PAPER_EVAL_EPISODES = 2000
PAPER_SEEDS = 3
PAPER_SIZES = {
    "uav_mbs_v0": "20 UAVs, 120 users in 3 clusters, 100-step episodes, 100,000 training episodes",
    "surviving_v0": "100 agents, 32 x 32 map, 8 resource points, 500-step episodes, 20,000 training episodes",
    "pursuit_v0": "25 predators against 50 prey, 45 x 45 map, 500-step episodes (budget not stated)",
}
"""The paper's env sizes and schedules, as the Table 1 header states them."""
