"""sb3_hgrn models that drive the agents of an env that do not learn, such as Pursuit's prey or
predators or the other team of :class:`~sb3_hgrn.envs.wrappers.DrivenAgents`.

The envs of :mod:`sb3_hgrn.envs` import no torch and load no model: they take any object with SB3's
``predict``. :class:`ModelController` is the one to hand them: it loads a saved model, fits a graph
policy to the agents it drives and seeds the model's sampling from the env, so that a seeded episode
repeats exactly. :func:`resolve_model_paths` turns the saved models' paths of an env's
``env_kwargs`` into such controllers; :func:`sb3_hgrn.make_graph_vec_env` calls it.
"""

from __future__ import annotations

import contextlib
import importlib
import inspect
import os
from collections.abc import Callable, Iterator
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th

from sb3_hgrn.common.files import ModelFileError, check_model_file, describe_saved_model, saved_policy_module
from sb3_hgrn.common.policies import GraphPolicy

MODEL_CLASSES = {"sb3_hgrn.soft_hgrn": "SoftHGRN", "sb3_hgrn.sac_hgrn": "SACHGRN"}
"""sb3_hgrn algorithms by the package of the policy class recorded in a saved zip."""


def load_controller(
    path: str | os.PathLike, model_class: type | None = None, trust_pickle: bool = False
) -> Any:
    """Load a saved sb3_hgrn model on the CPU, without running code from the file unless
    ``trust_pickle`` (see ``GraphOffPolicyAlgorithm.load``).

    :param path: the ``.zip`` written by ``model.save`` (the suffix may be left out, as in SB3).
    :param model_class: class whose ``load`` reads it; ``None`` picks ``SoftHGRN`` or ``SACHGRN``
        from the policy class recorded in the zip.
    :raises ValueError: when there is no file at ``path`` (nor at ``path.zip``), the file is damaged,
        needs ``trust_pickle`` or was not saved by an sb3_hgrn algorithm; the message names the file.
    """
    try:
        file = check_model_file(path)
    except FileNotFoundError as error:
        raise ValueError(str(error)) from error
    if model_class is None:
        policy_module = saved_policy_module(file)
        package = policy_module.rpartition(".")[0]
        if package not in MODEL_CLASSES:
            raise ModelFileError(
                f"{file} is not an sb3_hgrn model: it was saved by {describe_saved_model(file)}."
            )
        model_class = getattr(importlib.import_module(package), MODEL_CLASSES[package])
    return model_class.load(file, device="cpu", trust_pickle=trust_pickle)


class ModelController:
    """A model driving the agents of one side of an env, seeded by the env.

    It has the ``predict`` of SB3 and the two optional methods the envs call on a model controller:
    :meth:`bind`, once, with the side it drives, and :meth:`seed`, before every ``predict``.

    :param model: a model with SB3's ``predict`` (e.g. a ``SoftHGRN``), or the path of a saved
        sb3_hgrn model, loaded with :func:`load_controller`.
    :param model_class: the class that loads a path (``None``: read from the zip).
    :param trust_pickle: load a path that needs full unpickling (which can run code); see
        :func:`load_controller`.
    """

    def __init__(self, model: Any, model_class: type | None = None, trust_pickle: bool = False) -> None:
        if isinstance(model, str | os.PathLike):
            model = load_controller(model, model_class, trust_pickle)
        elif not callable(getattr(model, "predict", None)):
            raise TypeError(
                f"ModelController takes a model with predict() or a saved model's path, got "
                f"{type(model).__name__}."
            )
        self.model = model
        self._seed: int | None = None

    @property
    def observation_space(self) -> gym.spaces.Space | None:
        """The model's observation space (``None`` if it has none)."""
        return getattr(self.model, "observation_space", None)

    def bind(self, observation_space: gym.spaces.Box, n_agents: int) -> None:
        """Fit the model to the side it drives: ``n_agents`` agents observing ``observation_space``.

        A graph policy's ``n_agents`` is set to ``n_agents`` (all of them form one graph).

        :raises ValueError: when the model takes observations of another shape.
        """
        space = self.observation_space
        if isinstance(space, gym.spaces.Dict) and space["obs"].shape != observation_space.shape:
            raise ValueError(
                f"The controller takes observations of shape {space['obs'].shape}, but the "
                f"{n_agents} agents it is to drive observe shape {observation_space.shape}: was it "
                "trained on that side?"
            )
        policy = getattr(self.model, "policy", self.model)
        if isinstance(policy, GraphPolicy):
            policy.n_agents = n_agents

    def seed(self, seed: int) -> None:
        """Make the next :meth:`predict` sample from a torch CPU generator seeded with ``seed``.

        A model on a GPU samples from the unseeded CUDA generator.
        """
        self._seed = int(seed)

    def predict(
        self,
        observation: dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """The model's ``predict``, under the seed given to :meth:`seed` since the last call, if any;
        the caller's torch RNG state is left as it was.

        :param observation: ``{"obs": (n_agents, *obs_shape), "neighbors": (n_agents, K)}``.
        :return: actions ``(n_agents,)`` and the model's new recurrent state.
        """
        seed, self._seed = self._seed, None
        with contextlib.nullcontext() if seed is None else _torch_seeded(seed):
            return self.model.predict(
                observation, state=state, episode_start=episode_start, deterministic=deterministic
            )


@contextlib.contextmanager
def _torch_seeded(seed: int) -> Iterator[None]:
    """Torch's CPU generator seeded with ``seed`` inside the block, and as it was before after it."""
    # th.manual_seed is 100x slower than seeding the CPU generator alone.
    with th.random.fork_rng(devices=[]):
        th.default_generator.manual_seed(seed)
        yield


def resolve_model_paths(env_fn: Callable[..., Any], env_kwargs: dict[str, Any]) -> dict[str, Any]:
    """``env_kwargs`` with every saved model's path its env names loaded as a :class:`ModelController`.

    Which arguments name saved models the module defining ``env_fn`` says with
    ``model_paths(env_kwargs) -> {argument: path}`` (as :mod:`sb3_hgrn.envs.pursuit_v0` does, and a
    module of one's own can with :func:`sb3_hgrn.envs.driven_sides.controller_paths`); for other envs
    ``env_kwargs`` is returned as it is. The models are loaded without running code from their files
    (a file that needs full unpickling is refused; pass a ``ModelController(path, trust_pickle=True)``
    in ``env_kwargs`` instead of its path to load one you trust).

    :raises ValueError: naming the argument whose path holds no saved model.
    """
    model_paths = getattr(inspect.getmodule(env_fn), "model_paths", None)
    if model_paths is None:
        return env_kwargs
    resolved = dict(env_kwargs)
    for name, path in model_paths(env_kwargs).items():
        try:
            resolved[name] = ModelController(path)
        except ValueError as error:
            raise ValueError(f"{name}={path!r}: {error}") from error
    return resolved
