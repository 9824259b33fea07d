"""Team-return evaluation of graph policies, and a callback that runs it during training."""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback, EventCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_hgrn.common.checks import check_rewards
from sb3_hgrn.common.off_policy import check_graph_env


class RandomGraphPolicy:
    """Uniformly random actions for every slot of a graph VecEnv, within each agent's own group's
    actions (the baseline the examples and benchmarks compare with). It is called as a model is,
    ``actions, state = policy.predict(obs)``, so it goes wherever a model goes in an evaluation::

        env = make_graph_vec_env("surviving_v0", n_envs=2, seed=0)
        policy = RandomGraphPolicy(env, seed=0)
        actions, _ = policy.predict(env.reset())  # (env.num_envs,) int64
        mean_return, std_return = evaluate_graph_policy(policy, env, n_eval_episodes=2)

    :param env: the graph VecEnv it acts in (its ``action_space.n`` actions; with several agent
        groups the padded count of the largest group).
    :param seed: seed of its own random generator (``None``: fresh entropy); the env's seed is
        separate.
    """

    def __init__(self, env: VecEnv, seed: int | None = None):
        self.n_actions = int(env.action_space.n)
        self.rng = np.random.default_rng(seed)

    def predict(
        self,
        observation: dict[str, np.ndarray],
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, Any]:
        """Random actions, with the same signature as a model's ``predict``.

        :param observation: a graph VecEnv's observation dict: ``"obs"`` ``(n_slots, *obs_shape)``
            (only its length is read) and, on envs with several agent groups, ``"action_mask"``
            ``(n_slots, n_actions)`` whose ones are the first actions of each slot (its group's).
        :param state: returned unchanged (the policy has no recurrent state).
        :param episode_start: ignored ``(n_slots,)``.
        :param deterministic: ignored: the actions are random either way.
        :return: ``(actions, state)``: ``actions`` ``(n_slots,)`` int64, each drawn uniformly from
            ``0 .. n_actions - 1``, or from the slot's ``action_mask.sum()`` valid actions.
        """
        mask = observation.get("action_mask")
        high = self.n_actions if mask is None else mask.sum(axis=1)
        return self.rng.integers(0, high, size=len(observation["obs"])), state


def evaluate_team_episodes(
    model: BaseAlgorithm, env: VecEnv, n_eval_episodes: int = 10, deterministic: bool = False
) -> list[dict[str, Any]]:
    """Run ``n_eval_episodes`` team episodes and return the figures of each.

    A team episode is one episode of one env copy. Episodes are spread evenly over the copies, every
    copy keeps stepping until all are counted, and the recurrent state is reset exactly at each
    copy's episode starts.

    :param model: a trained graph model, or anything with its
        ``predict(obs, state, episode_start, deterministic)`` (e.g. :class:`RandomGraphPolicy`).
    :param env: a graph VecEnv (:func:`sb3_hgrn.make_graph_vec_env`); it is reset first.
    :param n_eval_episodes: number of team episodes.
    :param deterministic: greedy actions instead of sampled ones.
    :raises ValueError: on a NaN or infinite reward, naming the agent and the step.
    :return: each episode's ``info["team_episode"]`` dict, in the order the episodes ended: the team
        return ``r`` (the sum of all agents' rewards over all its steps), the length ``l``, the env's
        team figures after the last step (those of sb3_hgrn's envs, or of an env's ``team_info()``
        such as :class:`~sb3_hgrn.envs.wrappers.TeamFigures`), the final observation and terminations.
    """
    env = check_graph_env(env)
    n_agents = env.n_agents
    if n_eval_episodes < 1:
        raise ValueError(f"n_eval_episodes must be >= 1, got {n_eval_episodes}.")
    n_copies = env.num_envs // n_agents
    targets = np.array([(n_eval_episodes + copy) // n_copies for copy in range(n_copies)])
    counts = np.zeros(n_copies, dtype=int)
    episodes: list[dict[str, Any]] = []
    observations = env.reset()
    state = None
    episode_starts = np.ones(env.num_envs, dtype=bool)
    step = 0
    while (counts < targets).any():
        actions, state = model.predict(
            observations, state=state, episode_start=episode_starts, deterministic=deterministic
        )
        observations, rewards, dones, infos = env.step(actions)
        step += 1
        check_rewards(np.asarray(rewards), n_agents, f"at step {step} of the evaluation")
        episode_starts = np.asarray(dones, dtype=bool)
        for copy in np.flatnonzero(episode_starts[::n_agents]):
            if counts[copy] < targets[copy]:
                episodes.append(infos[copy * n_agents]["team_episode"])
                counts[copy] += 1
    return episodes


def evaluate_graph_policy(
    model: BaseAlgorithm,
    env: VecEnv,
    n_eval_episodes: int = 10,
    deterministic: bool = False,
    return_episode_rewards: bool = False,
) -> tuple[float, float] | tuple[list[float], list[int]]:
    """Run ``n_eval_episodes`` team episodes and report their team returns.

    A team episode is one episode of one env copy; its return is the sum of all agents' rewards
    over all its steps (see :func:`evaluate_team_episodes`, which also returns the env's figures).

    :param model: a trained graph model, or anything with its
        ``predict(obs, state, episode_start, deterministic)`` (e.g. :class:`RandomGraphPolicy`).
    :param env: a graph VecEnv (:func:`sb3_hgrn.make_graph_vec_env`); it is reset first.
    :param n_eval_episodes: number of team episodes.
    :param deterministic: greedy actions instead of sampled ones.
    :param return_episode_rewards: return the per-episode lists instead of mean and std.
    :raises ValueError: on a NaN or infinite reward, naming the agent and the step.
    :return: ``(mean, std)`` of team returns, or ``(returns, lengths)``.
    """
    episodes = evaluate_team_episodes(model, env, n_eval_episodes, deterministic)
    returns = [float(episode["r"]) for episode in episodes]
    if return_episode_rewards:
        return returns, [int(episode["l"]) for episode in episodes]
    return float(np.mean(returns)), float(np.std(returns))


class GraphEvalCallback(EventCallback):
    """Evaluate team returns every ``eval_freq`` vec-steps; keep the best model.

    Logs ``eval/mean_team_reward``, ``eval/std_team_reward`` and ``eval/mean_ep_length``; with
    ``best_model_save_path`` saves ``best_model.zip`` on each new best; with ``log_path`` writes
    ``evaluations.npz`` (``timesteps``, ``results``, ``ep_lengths``) as SB3's ``EvalCallback``.

    :param eval_env: a graph VecEnv (separate from the training env).
    :param callback_on_new_best: callback triggered on a new best mean team return.
    :param n_eval_episodes: team episodes per evaluation.
    :param eval_freq: vec-steps between evaluations.
    """

    def __init__(
        self,
        eval_env: VecEnv,
        callback_on_new_best: BaseCallback | None = None,
        n_eval_episodes: int = 5,
        eval_freq: int = 10_000,
        log_path: str | None = None,
        best_model_save_path: str | None = None,
        deterministic: bool = False,
        verbose: int = 1,
    ):
        super().__init__(callback_on_new_best, verbose=verbose)
        self.eval_env = eval_env
        self.n_eval_episodes = n_eval_episodes
        self.eval_freq = eval_freq
        self.log_path = log_path
        self.best_model_save_path = best_model_save_path
        self.deterministic = deterministic
        self.best_mean_reward = -np.inf
        self.last_mean_reward = -np.inf
        self.evaluations_timesteps: list[int] = []
        self.evaluations_results: list[list[float]] = []
        self.evaluations_length: list[list[int]] = []

    def _init_callback(self) -> None:
        for path in (self.best_model_save_path, self.log_path):
            if path is not None:
                os.makedirs(path, exist_ok=True)

    def _on_step(self) -> bool:
        if self.eval_freq <= 0 or self.n_calls % self.eval_freq != 0:
            return True
        returns, lengths = evaluate_graph_policy(
            self.model, self.eval_env, self.n_eval_episodes, self.deterministic, return_episode_rewards=True
        )
        mean_return, std_return = float(np.mean(returns)), float(np.std(returns))
        self.last_mean_reward = mean_return
        if self.log_path is not None:
            self.evaluations_timesteps.append(self.num_timesteps)
            self.evaluations_results.append(returns)
            self.evaluations_length.append(lengths)
            np.savez(
                os.path.join(self.log_path, "evaluations"),
                timesteps=self.evaluations_timesteps,
                results=self.evaluations_results,
                ep_lengths=self.evaluations_length,
            )
        if self.verbose >= 1:
            acting = getattr(getattr(self.model, "policy", None), "deployed_label", None)
            print(
                f"Eval num_timesteps={self.num_timesteps}, team return={mean_return:.2f} +/- {std_return:.2f}"
                + ("" if acting is None else f" (acting: {acting})")
            )
        self.logger.record("eval/mean_team_reward", mean_return)
        self.logger.record("eval/std_team_reward", std_return)
        self.logger.record("eval/mean_ep_length", float(np.mean(lengths)))
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(self.num_timesteps)
        if mean_return > self.best_mean_reward:
            self.best_mean_reward = mean_return
            if self.best_model_save_path is not None:
                self.model.save(os.path.join(self.best_model_save_path, "best_model"))
            if self.callback is not None:
                return self.callback.on_step()
        return True

    def update_child_locals(self, locals_: dict[str, Any]) -> None:
        if self.callback is not None:
            self.callback.update_locals(locals_)
