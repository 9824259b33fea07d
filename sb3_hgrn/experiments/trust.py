"""Trust checks of a saved run's ``config.yml``: what it may make the loader import or unpickle."""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Collection
from pathlib import Path

from sb3_hgrn.common.files import model_file_path
from sb3_hgrn.experiments.config import (
    ConfigError,
    RunConfig,
    is_env_spec,
    load_env_factory,
)
from sb3_hgrn.experiments.run_folder import CONFIG_FILE


def check_stored_model_paths(
    config: RunConfig, folder: Path, given: Collection[str] = (), trust_config: bool = False
) -> None:
    """Raise :class:`ConfigError` when the ``config.yml`` of the run in ``folder`` makes its env load
    a saved model (e.g. a Pursuit controller) from outside the folder.

    Loading a model zip unpickles it and so can run code: a run's ``config.yml`` may only point to
    models inside its own folder, unless ``trust_config``. Env arguments in ``given`` (passed by the
    user, over the stored ones) are not checked. Which env arguments name models the env module says
    with ``model_paths(env_kwargs) -> {argument: path}`` (a registered env's module, or the module that
    defines a user env ``MODULE:ATTR``, imported here: call this after :func:`check_stored_env`).
    """
    if trust_config:
        return
    if is_env_spec(config.env):
        env_module = inspect.getmodule(load_env_factory(config.env))
    else:
        env_module = importlib.import_module(f"sb3_hgrn.envs.{config.env}")
    model_paths = getattr(env_module, "model_paths", None)
    if model_paths is None:
        return
    inside = folder.resolve()
    for name, value in model_paths(config.env_kwargs).items():
        if name not in given and not model_file_path(value).resolve().is_relative_to(inside):
            raise ConfigError(
                f"{folder / CONFIG_FILE} sets {name}={value!r}, a model outside the run folder. Loading a "
                "model file can run code, so a run's config may only name models inside its own folder. "
                f"If you trust this config, pass --trust-config (trust_config=True), or give the model "
                f"yourself with --env-param {name}=PATH."
            )


def check_stored_env(config: RunConfig, folder: Path, given: str | None, trust_config: bool = False) -> None:
    """Raise :class:`ConfigError` when the ``config.yml`` of the run in ``folder`` names a user env
    (``MODULE:ATTR``) that the user did not name too.

    Building a user env imports its module, which runs its code: a run's ``config.yml`` may name one
    only if the user gives the same with ``given`` (``--env``), or with ``trust_config``.
    """
    if trust_config or not is_env_spec(config.env) or given == config.env:
        return
    raise ConfigError(
        f"{folder / CONFIG_FILE} names the env {config.env!r}, code of its own that would be imported "
        "and run. A run's config may name such an env only if you name it too: pass "
        f"--env {config.env} (env={config.env!r}) if that is your env, or --trust-config "
        "(trust_config=True) if you trust this config."
    )
