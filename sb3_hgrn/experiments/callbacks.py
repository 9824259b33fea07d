"""Callbacks of the command-line runs: a Monitor-style CSV of team returns, atomic checkpoints."""

from __future__ import annotations

import functools
import json
import os
import pickle
import re
import time
import warnings
from pathlib import Path
from typing import IO, Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback

from sb3_hgrn.common.files import save_atomically, save_model_atomically, write_text_atomically
from sb3_hgrn.common.vec_env import UnpicklableEnvError
from sb3_hgrn.validation import is_integer

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


def rewind_team_returns(path: str | os.PathLike, n_episodes: int) -> int:
    """Keep the first ``n_episodes`` rows of a ``team_returns.csv``: those of the team episodes a
    resumed run's checkpoint has seen (its model's episode count), so the resumed run appends to
    exactly them. The rows logged after the checkpoint go, as does a row cut short by a kill and
    anything after it. A missing or unreadable file is left as it is.

    :return: the number of rows dropped (with a row cut short by a kill).
    """
    try:
        with open(path, encoding="utf-8") as file:
            lines = file.read().splitlines()
    except OSError:
        return 0
    if len(lines) < 2 or not lines[0].startswith("#"):
        return 0
    whole = 0
    for line in lines[2:]:
        fields = line.split(",")
        if len(fields) != 3 or not fields[1].isdigit():  # a row cut short by a kill ends the table
            break
        whole += 1
    kept = min(n_episodes, whole)
    if kept < len(lines) - 2:
        write_text_atomically(path, "\n".join(lines[: 2 + kept]) + "\n")
    return len(lines) - 2 - kept


class AtomicCheckpointCallback(CheckpointCallback):
    """SB3's ``CheckpointCallback`` (``<save_path>/<name_prefix>_<agent-steps>_steps.zip`` every
    ``save_freq`` vec-steps) whose files are written to a temporary file and renamed, so a process
    killed while saving leaves the previous checkpoints whole and no partial file, and whose
    checkpoints hold what an exact resume needs.

    A checkpoint falls due when the vec-steps since the run's start (``num_timesteps`` over the slot
    count, so a resumed run keeps the schedule) reach a multiple of ``save_freq``. It is written at
    the end of the collection round it falls in (``train_freq`` vec-steps), once ``learn`` has
    trained on that round: at the start of the next round or at the end of training. There the
    model, its replay buffer and the env agree (inside a round SB3 runs the callbacks before it
    stores the last vec-step), and the file names carry the agent-steps done by then.

    Beside each zip go, with ``save_replay_buffer``, the replay buffer
    (``<name_prefix>_replay_buffer_<agent-steps>_steps.pkl``) and always the model's
    :meth:`~sb3_hgrn.common.off_policy.GraphOffPolicyAlgorithm.get_training_state` as a pickle
    (``<name_prefix>_training_state_<agent-steps>_steps.pkl``; see :func:`checkpoint_companion`),
    both written before the zip: a checkpoint zip that exists has them. An env that cannot be pickled
    (e.g. Pursuit's MAgent) gets no training state, with one warning.

    Only the newest ``keep`` checkpoints stay: once a checkpoint's zip is written, the files of the
    checkpoints older than it but its ``keep - 1`` predecessors are removed (each zip before its
    companions, so a zip that exists still has them). The checkpoint just written and any newer ones
    are never removed, so the one a resumed run would load stays; neither are files of other names.

    :param save_freq: a checkpoint every ``save_freq`` vec-steps.
    :param save_path: folder of the checkpoints.
    :param name_prefix: start of the file names.
    :param save_replay_buffer: also save the replay buffer.
    :param keep: checkpoints kept, the newest ones (``0``: all).
    """

    def __init__(
        self,
        save_freq: int,
        save_path: str,
        name_prefix: str = "rl_model",
        save_replay_buffer: bool = False,
        keep: int = 0,
        verbose: int = 0,
    ):
        if not is_integer(keep) or keep < 0:
            raise ValueError(f"keep must be a whole number >= 0 (checkpoints kept, 0: all), got {keep!r}.")
        super().__init__(
            save_freq,
            save_path,
            name_prefix=name_prefix,
            save_replay_buffer=save_replay_buffer,
            verbose=verbose,
        )
        self.due = False
        self.saves_training_state = True
        self.keep = keep

    def _on_step(self) -> bool:
        if self.num_timesteps % (self.save_freq * self.training_env.num_envs) == 0:
            self.due = True
        return True

    def _on_rollout_start(self) -> None:
        if self.due:
            self._save()

    def _on_training_end(self) -> None:
        if self.due:
            self._save()

    def _save(self) -> None:
        """Write the replay buffer (with ``save_replay_buffer``), the training state, then the zip."""
        self.due = False
        self.num_timesteps = self.model.num_timesteps
        path = self._checkpoint_path(extension="zip")
        if self.save_replay_buffer and getattr(self.model, "replay_buffer", None) is not None:
            save_atomically(self.model.save_replay_buffer, checkpoint_companion(path, "replay_buffer"))
        if self.saves_training_state:
            self._save_training_state(checkpoint_companion(path, "training_state"))
        save_model_atomically(self.model, path)
        if self.verbose >= 2:
            print(f"Saving model checkpoint to {path}")
        if self.keep:
            remove_old_checkpoints(Path(self.save_path), self.name_prefix, self.num_timesteps, self.keep)

    def _save_training_state(self, path: Path) -> None:
        """Pickle the model's training state to ``path``; warn once and stop when the env cannot be."""
        try:
            state = self.model.get_training_state()
        except UnpicklableEnvError as error:
            warnings.warn(
                f"The checkpoints of this run hold no training state, so a resumed run restarts its "
                f"episodes: {error}",
                stacklevel=2,
            )
            self.saves_training_state = False
            return
        save_atomically(functools.partial(pickle.dump, state, protocol=pickle.HIGHEST_PROTOCOL), path)


CHECKPOINT_KINDS = ("replay_buffer", "training_state")
"""The companions saved beside a checkpoint zip (see :func:`checkpoint_companion`)."""


def remove_old_checkpoints(folder: Path, prefix: str, newest: int, keep: int) -> list[int]:
    """Remove the checkpoints in ``folder`` older than the one of ``newest`` agent-steps but the
    ``keep - 1`` next older ones: each zip first, then its companions (and companions whose zip is
    gone, left by a kill). Checkpoints of ``newest`` agent-steps or more are kept.

    :return: the agent-steps of the checkpoints removed, newest first.
    """
    kinds = "|".join(CHECKPOINT_KINDS)
    pattern = re.compile(rf"{re.escape(prefix)}_(?:(?:{kinds})_)?(\d+)_steps\.(?:zip|pkl)")
    steps: dict[int, list[Path]] = {}
    for path in folder.iterdir():
        match = pattern.fullmatch(path.name)
        if match:
            steps.setdefault(int(match.group(1)), []).append(path)
    older = sorted((step for step in steps if step < newest), reverse=True)
    removed = older[keep - 1 :]
    for step in removed:
        for path in sorted(steps[step], key=lambda path: path.suffix != ".zip"):  # the zip first
            path.unlink(missing_ok=True)
    return removed


def checkpoint_companion(checkpoint: str | os.PathLike, kind: str) -> Path:
    """The file of ``kind`` (``"replay_buffer"`` or ``"training_state"``) that
    :class:`AtomicCheckpointCallback` saves beside ``checkpoint``
    (``<prefix>_<steps>_steps.zip`` -> ``<prefix>_<kind>_<steps>_steps.pkl``)."""
    checkpoint = Path(checkpoint)
    prefix, _, steps = checkpoint.stem.removesuffix("_steps").rpartition("_")
    return checkpoint.with_name(f"{prefix}_{kind}_{steps}_steps.pkl")
