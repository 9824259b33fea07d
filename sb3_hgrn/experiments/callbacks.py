"""Callbacks of the command-line runs: a Monitor-style CSV of team returns, atomic checkpoints."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import IO, Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback

from sb3_hgrn.common.files import save_atomically, save_model_atomically, write_text_atomically

TEAM_RETURNS_FILE = "team_returns.csv"


class TeamMonitorCallback(BaseCallback):
    """Write one ``r,l,t`` row per team episode of training, as SB3's ``Monitor`` does per episode.

    The file starts with ``#{json metadata}`` (``t_start``, ``env_id``, ``n_agents``, ``n_copies``)
    and the header ``r,l,t``: team return (all agents' rewards summed over the episode), length in
    env steps, and seconds since ``t_start``. Rows come from the ``team_episode`` info that the graph
    VecEnv puts in the slots of a copy whose episode ended. Every row is flushed at once.

    :param path: the CSV file; with ``append=True`` an existing file is continued (resumed runs).
    :param env_id: env name stored in the metadata line.
    """

    def __init__(self, path: str, env_id: str = "", append: bool = False, verbose: int = 0):
        super().__init__(verbose=verbose)
        self.path = path
        self.env_id = env_id
        self.append = append
        self.t_start = time.time()
        self.file: IO[str] | None = None
        self.n_episodes = 0

    def _init_callback(self) -> None:
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        continuing = self.append and os.path.exists(self.path) and os.path.getsize(self.path) > 0
        if continuing:
            with open(self.path, encoding="utf-8") as file:
                first = file.readline()
            if first.startswith("#"):
                self.t_start = float(json.loads(first[1:]).get("t_start", self.t_start))
        self.file = open(self.path, "a" if continuing else "w", encoding="utf-8")  # noqa: SIM115
        if not continuing:
            metadata = {
                "t_start": self.t_start,
                "env_id": self.env_id,
                "n_agents": int(self.training_env.n_agents),
                "n_copies": int(self.training_env.num_envs // self.training_env.n_agents),
            }
            self.file.write(f"#{json.dumps(metadata)}\nr,l,t\n")
            self.file.flush()

    def _on_step(self) -> bool:
        dones = np.asarray(self.locals["dones"], dtype=bool)
        infos: list[dict[str, Any]] = self.locals["infos"]
        n_agents = self.training_env.n_agents
        for first_slot in np.flatnonzero(dones[::n_agents]) * n_agents:
            team = infos[first_slot].get("team_episode")
            if team is None or self.file is None:
                continue
            elapsed = round(time.time() - self.t_start, 6)
            self.file.write(f"{round(float(team['r']), 6)},{int(team['l'])},{elapsed}\n")
            self.file.flush()
            self.n_episodes += 1
        return True

    def _on_training_end(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None


def rewind_team_returns(path: str | os.PathLike, agent_steps: int) -> int:
    """Drop the rows of a ``team_returns.csv`` logged after ``agent_steps`` (a resumed run's
    checkpoint), so the resumed run appends to the episodes its checkpoint has seen.

    A row's agent-steps are the env steps of all episodes up to it times the agent count (as the
    figures count them): exact when the env copies end their episodes together, otherwise a few rows
    of the last vec-steps may stay. A missing or unreadable file is left as it is.

    :return: the number of rows dropped (with a row cut short by a kill).
    """
    try:
        with open(path, encoding="utf-8") as file:
            lines = file.read().splitlines()
        n_agents = int(json.loads(lines[0][1:])["n_agents"])
    except (OSError, ValueError, IndexError, KeyError, TypeError):
        return 0
    lengths = []
    for line in lines[2:]:
        fields = line.split(",")
        if len(fields) != 3 or not fields[1].isdigit():  # a row cut short by a kill ends the table
            break
        lengths.append(int(fields[1]))
    kept = int(np.searchsorted(np.cumsum(lengths) * n_agents, agent_steps, side="right"))
    if kept < len(lines) - 2:
        write_text_atomically(path, "\n".join(lines[: 2 + kept]) + "\n")
    return len(lines) - 2 - kept


class AtomicCheckpointCallback(CheckpointCallback):
    """SB3's ``CheckpointCallback`` (``<save_path>/<name_prefix>_<agent-steps>_steps.zip`` every
    ``save_freq`` calls) whose files are written to a temporary file and renamed, so a process killed
    while saving leaves the previous checkpoints whole and no partial file.

    With ``save_replay_buffer`` the model's replay buffer goes beside each checkpoint, as
    ``<name_prefix>_replay_buffer_<agent-steps>_steps.pkl`` (see :func:`replay_buffer_path`), written
    before the zip: a checkpoint zip that exists has its buffer.

    :param save_freq: save a checkpoint every ``save_freq`` calls (vec-steps).
    :param save_path: folder of the checkpoints.
    :param name_prefix: start of the file names.
    :param save_replay_buffer: also save the replay buffer.
    """

    def __init__(
        self,
        save_freq: int,
        save_path: str,
        name_prefix: str = "rl_model",
        save_replay_buffer: bool = False,
        verbose: int = 0,
    ):
        super().__init__(
            save_freq,
            save_path,
            name_prefix=name_prefix,
            save_replay_buffer=save_replay_buffer,
            verbose=verbose,
        )

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            if self.save_replay_buffer and getattr(self.model, "replay_buffer", None) is not None:
                save_atomically(self.model.save_replay_buffer, self._checkpoint_path("replay_buffer_", "pkl"))
            path = self._checkpoint_path(extension="zip")
            save_model_atomically(self.model, path)
            if self.verbose >= 2:
                print(f"Saving model checkpoint to {path}")
        return True


def replay_buffer_path(checkpoint: str | os.PathLike) -> Path:
    """The replay buffer :class:`AtomicCheckpointCallback` saves beside ``checkpoint``
    (``<prefix>_<steps>_steps.zip`` -> ``<prefix>_replay_buffer_<steps>_steps.pkl``)."""
    checkpoint = Path(checkpoint)
    prefix, _, steps = checkpoint.stem.removesuffix("_steps").rpartition("_")
    return checkpoint.with_name(f"{prefix}_replay_buffer_{steps}_steps.pkl")
