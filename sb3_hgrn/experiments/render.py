"""Rendering one episode of a saved run as a GIF."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from sb3_hgrn.experiments.config import ConfigError
from sb3_hgrn.experiments.runs import load_run


def render_run(
    path: str | os.PathLike,
    out: str | os.PathLike,
    steps: int | None = None,
    fps: float = 10.0,
    deterministic: bool = False,
    env: str | None = None,
    seed: int | None = None,
    trust_config: bool = False,
    trust_pickle: bool = False,
    **env_kwargs: Any,
) -> int:
    """Run one episode of copy 0 with ``render_mode="rgb_array"`` and write the frames as a GIF.

    :param steps: stop after this many steps (default: the whole episode).
    :param trust_config: see :func:`load_run`.
    :param trust_pickle: see :func:`load_run`.
    :return: the number of frames written.
    """
    from PIL import Image

    model, vec_env, _ = load_run(
        path,
        env=env,
        n_envs=1,
        seed=seed,
        device="cpu",
        render_mode="rgb_array",
        trust_config=trust_config,
        trust_pickle=trust_pickle,
        **env_kwargs,
    )
    try:
        observations = vec_env.reset()
        frames = [vec_env.render()]
        state, starts = None, np.ones(vec_env.num_envs, dtype=bool)
        step = 0
        while steps is None or step < steps:
            actions, state = model.predict(
                observations, state=state, episode_start=starts, deterministic=deterministic
            )
            observations, _, dones, _ = vec_env.step(actions)
            step += 1
            if dones[0]:  # the copy has already reset: its next frame would show a new episode
                break
            frames.append(vec_env.render())
    finally:
        vec_env.close()
    frames = [frame for frame in frames if frame is not None]
    if not frames:
        raise ConfigError(f"{vec_env} rendered no frames.")
    images = [Image.fromarray(np.asarray(frame, dtype=np.uint8)) for frame in frames]
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    images[0].save(out, save_all=True, append_images=images[1:], duration=max(1, round(1000 / fps)), loop=0)
    return len(images)
