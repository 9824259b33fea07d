"""RL-Zoo-style YAML configs: one file per env in ``sb3_hgrn/hyperparams``, with budgets and presets.

A config file holds (all sections optional except ``budgets``)::

    env_kwargs: {...}            # env constructor arguments shared by every budget
    default: {...}               # algorithm keyword arguments for every preset
    soft_hgrn: {...}             # ... for one preset only (any name of sb3_hgrn.presets.PRESETS)
    budgets:
      ci:                        # also cpu, paper
        description: "..."       # the sizes in words (shown in the Table 1 header)
        env_kwargs: {...}        # merged over the top-level env_kwargs
        n_envs: 1                # env copies stepped together while training
        eval_n_envs: 1           # env copies while evaluating (default: n_envs)
        total_timesteps: 2000    # agent-steps of training
        eval_episodes: 2         # team episodes of the final evaluation
        eval_epsilons: [0.3]     # extra evaluations with epsilon-random actions (the original's mode)
        paper: false             # true: make_model(..., paper=True) (the paper's network and schedule)
        default: {...}           # algorithm kwargs for every preset at this budget
        dgn: {...}               # ... for one preset at this budget

Algorithm keyword arguments are merged in that order (``policy_kwargs`` key by key): the preset,
top-level ``default``, top-level preset section, the budget's ``default``, the budget's preset
section, then ``--param`` overrides from the command line.

``train --config FILE [FILE ...]`` reads files of the same format in which every section is optional
(e.g. the ``best.yml`` that ``tune`` writes): their sections are merged over the packaged file's, one
file after the other, in the same order (so even a file's top-level preset section wins over the
packaged budget sections), and ``--param`` and ``--env-param`` still come last. Their budget fields
replace the packaged budget's.

An env of one's own is named ``MODULE:ATTR`` (:data:`ENV_SPEC_HELP`). It has no packaged file, so its
config files must give the budget's ``n_envs``, ``total_timesteps`` and ``eval_episodes``
(:data:`USER_ENV_CONFIG_EXAMPLE`).
"""

from __future__ import annotations

import ast
import importlib
import inspect
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from types import ModuleType
from typing import Any

import yaml

from sb3_hgrn.common.off_policy import check_model_arguments
from sb3_hgrn.common.vec_env import REGISTERED_ENVS
from sb3_hgrn.presets import PRESETS, merge
from sb3_hgrn.validation import is_flag, is_integer, is_number

BUDGETS = ("ci", "cpu", "paper")
"""Budgets every config file defines: toy sizes for tests, a 2-core CPU sweep, the paper's schedule."""

BUDGET_FIELDS = {
    "description", "env_kwargs", "n_envs", "eval_n_envs", "total_timesteps", "eval_episodes",
    "eval_epsilons", "paper", "keep_checkpoints",
}  # fmt: skip
KEEP_CHECKPOINTS = 3
"""Checkpoints a run keeps by default (the newest ones; ``0`` keeps all)."""
RANDOM_POLICY = "random"
"""Run name of the uniformly random policy (evaluated without training, as the tables' anchor)."""
RESERVED_PARAMS = {"policy", "env", "seed", "verbose", "tensorboard_log", "device", "_init_setup_model"}
"""Algorithm arguments the runner sets itself (``--seed``, ``--verbose``, ``--device``)."""


REQUIRED_BUDGET_FIELDS = ("n_envs", "total_timesteps", "eval_episodes")
"""Budget fields without a default: a packaged file has them, a user env's config file must give them."""
ENV_SPEC_HELP = "MODULE:ATTR, an importable module and its env factory (e.g. my_package.my_module:make_env)"
_ENV_SPEC = re.compile(r"(?P<module>[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*):(?P<attr>[A-Za-z_]\w*)", re.ASCII)
USER_ENV_CONFIG_EXAMPLE = """\
budgets:
  ci:
    n_envs: 1               # env copies stepped together while training
    total_timesteps: 2000   # agent-steps of training
    eval_episodes: 2        # team episodes of the final evaluation
    env_kwargs: {}          # arguments of the env factory (optional)"""
"""The smallest config file of a user env (one budget)."""


class ConfigError(ValueError):
    """A config file or a command-line override that cannot be used (the message says why)."""


def is_env_spec(env: str) -> bool:
    """Whether ``env`` names an env of one's own (``MODULE:ATTR``) rather than a registered one."""
    return ":" in env


def check_env_name(env: str) -> None:
    """Raise :class:`ConfigError` unless ``env`` is a registered env or a well-formed ``MODULE:ATTR``
    (which is not imported here)."""
    if is_env_spec(env):
        if _ENV_SPEC.fullmatch(env) is None:
            raise ConfigError(
                f"Malformed env {env!r}: expected {ENV_SPEC_HELP}, with a dotted module path, one colon "
                "and a Python name after it."
            )
    elif env not in REGISTERED_ENVS:
        raise ConfigError(
            f"Unknown env {env!r}; available: {', '.join(REGISTERED_ENVS)}, or {ENV_SPEC_HELP}."
        )


def env_folder_name(env: str) -> str:
    """The folder name of ``env`` in run folders and study names: a registered name itself, a
    ``MODULE:ATTR`` as ``MODULE-ATTR`` (``my_package.my_module-make_env``; no registered name and no
    Python name holds a ``-``, so distinct envs get distinct folders)."""
    check_env_name(env)
    return env.replace(":", "-")


def load_env_factory(env: str) -> ModuleType | Callable[..., Any]:
    """Import the env ``MODULE:ATTR`` and return its attribute: a callable building a PettingZoo
    ``ParallelEnv`` or AEC env (e.g. a ``parallel_env`` function) or a module with ``parallel_env()``.

    Importing a module runs its code: call this only for an env the user named.
    """
    check_env_name(env)
    match = _ENV_SPEC.fullmatch(env)
    if match is None:
        raise ConfigError(f"{env!r} is a registered env name, not {ENV_SPEC_HELP}.")
    module_name, attr = match["module"], match["attr"]
    try:
        module = importlib.import_module(module_name)
    except Exception as error:  # the user's module may raise anything while it is imported
        raise ConfigError(
            f"Cannot import module {module_name!r} of the env {env!r}: {type(error).__name__}: {error}. "
            "It must be importable (installed, or on PYTHONPATH)."
        ) from error
    if not hasattr(module, attr):
        raise ConfigError(f"Module {module_name!r} has no attribute {attr!r} (the env {env!r}).")
    factory = getattr(module, attr)
    if isinstance(factory, ModuleType):
        if not callable(getattr(factory, "parallel_env", None)):
            raise ConfigError(
                f"{module_name}.{attr} (the env {env!r}) is a module without parallel_env(); name a "
                "callable that returns a PettingZoo ParallelEnv or AEC env."
            )
        return factory
    if not callable(factory):
        raise ConfigError(
            f"{module_name}.{attr} (the env {env!r}) is a {type(factory).__name__}, not callable; name a "
            "callable that returns a PettingZoo ParallelEnv or AEC env."
        )
    return factory


def check_preset_name(preset: str) -> None:
    """Raise :class:`ConfigError` unless ``preset`` names one of :data:`sb3_hgrn.presets.PRESETS`."""
    if preset not in PRESETS:
        raise ConfigError(f"Unknown preset {preset!r}; available: {', '.join(PRESETS)}.")


def check_budget_name(budget: str) -> None:
    """Raise :class:`ConfigError` unless ``budget`` is one of :data:`BUDGETS`."""
    if budget not in BUDGETS:
        raise ConfigError(f"Unknown budget {budget!r}; available: {', '.join(BUDGETS)}.")


def load_hyperparams(env: str) -> dict[str, Any]:
    """Read and check ``sb3_hgrn/hyperparams/<env>.yml``."""
    check_env_name(env)
    if is_env_spec(env):
        raise ConfigError(f"The env {env!r} is not a registered one and has no packaged config file.")
    text = (resources.files("sb3_hgrn") / "hyperparams" / f"{env}.yml").read_text(encoding="utf-8")
    config = yaml.safe_load(text) or {}
    _check_config(config, packaged_config_name(env), complete=True)
    return config


def packaged_config_name(env: str) -> str:
    """How messages name the packaged config file of the registered env ``env``."""
    return f"hyperparams/{env}.yml"


def read_yaml_file(path: str | os.PathLike, what: str = "config file") -> Any:
    """The YAML contents of ``path``; a :class:`ConfigError` naming ``what`` and the file when it
    cannot be read or is not YAML."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as error:
        raise ConfigError(f"Cannot read the {what} {path}: {error.strerror}.") from error
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ConfigError(f"The {what} {path} is not valid YAML: {error}") from error


def load_config_file(path: str | os.PathLike) -> dict[str, Any]:
    """Read and check a config file of one's own (``train --config``): the format of the packaged
    files, with every section optional."""
    config = read_yaml_file(path)
    config = {} if config is None else config
    _check_config(config, str(path), complete=False)
    return config


def _check_config(config: Any, where: str, complete: bool) -> None:
    """Check the sections of a config file; a ``complete`` one (a packaged file) defines every budget,
    each with ``n_envs``, ``total_timesteps`` and ``eval_episodes``."""
    _check_sections(config, {"env_kwargs", "budgets"}, where)
    budgets = config.get("budgets") or {}
    if not isinstance(budgets, dict):
        raise ConfigError(f"{where}: budgets must be a mapping of budgets, got {type(budgets).__name__}.")
    for budget in BUDGETS if complete else ():
        if budget not in budgets:
            raise ConfigError(f"{where} has no budget {budget!r}.")
    for budget, section in budgets.items():
        check_budget_name(budget)
        section = {} if section is None else section
        _check_sections(section, BUDGET_FIELDS, f"{where} budget {budget}")
        _check_budget_values(section, f"{where} budget {budget}", complete)
        if "keep_checkpoints" in section:
            check_keep_checkpoints(section["keep_checkpoints"], f"{where} budget {budget}: keep_checkpoints")


def _check_budget_values(section: dict[str, Any], where: str, complete: bool) -> None:
    """Raise :class:`ConfigError` naming ``where``, the field and its value unless the counts of a budget
    section are positive integers (those of :data:`REQUIRED_BUDGET_FIELDS` given when ``complete``),
    ``paper`` is true or false and ``eval_epsilons`` a list of numbers in [0, 1]."""
    for key in (*REQUIRED_BUDGET_FIELDS, "eval_n_envs"):
        given = key in section or (complete and key in REQUIRED_BUDGET_FIELDS)
        if given and not (is_integer(section.get(key)) and section[key] >= 1):
            raise ConfigError(f"{where}: {key} must be a positive integer, got {section.get(key)!r}.")
    if not is_flag(section.get("paper", False)):
        raise ConfigError(f"{where}: paper must be true or false, got {section['paper']!r}.")
    epsilons = section.get("eval_epsilons") or []
    if not isinstance(epsilons, list) or not all(is_number(eps) and 0 <= eps <= 1 for eps in epsilons):
        raise ConfigError(f"{where}: eval_epsilons must be a list of numbers in [0, 1], got {epsilons!r}.")


def check_keep_checkpoints(value: Any, name: str) -> int:
    """``value`` as a count of checkpoints to keep, or :class:`ConfigError` naming ``name``."""
    if not is_integer(value) or value < 0:
        raise ConfigError(
            f"{name} must be a whole number >= 0 (the newest checkpoints kept, 0: all), got {value!r}."
        )
    return value


def _check_sections(section: Any, fields: set[str], where: str) -> None:
    """Check that ``section`` is a mapping of ``fields``, ``default`` and preset names only."""
    if not isinstance(section, dict):
        raise ConfigError(f"{where} must be a mapping, got {type(section).__name__}.")
    for key, value in section.items():
        if key in fields:
            continue
        if key != "default" and key not in PRESETS:
            raise ConfigError(
                f"{where}: unknown key {key!r} "
                f"(expected {', '.join(sorted(fields))}, default or a preset name)."
            )
        if value is not None and not isinstance(value, dict):
            raise ConfigError(f"{where}: section {key!r} must be a mapping of algorithm arguments.")


def parse_value(text: str) -> Any:
    """A command-line value: a Python or YAML literal (``3``, ``1e-3``, ``true``, ``[1, 2]``,
    ``{hidden_dim: 32}``), else the string itself."""
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        pass
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def parse_assignments(items: list[str] | None, option: str = "--param") -> dict[str, Any]:
    """Parse ``key=value`` items into a (nested) dict of values.

    ``["lr=1e-3", "policy_kwargs.hidden_dim=32"]`` gives
    ``{"lr": 0.001, "policy_kwargs": {"hidden_dim": 32}}``: a dotted key sets a value in a nested mapping.
    """
    result: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        path = key.strip().split(".")
        if not sep or not all(part.strip() for part in path):
            raise ConfigError(
                f"Malformed {option} {item!r}: expected key=value (e.g. {option} batch_size=64)."
            )
        result = merge(result, nest(".".join(part.strip() for part in path), parse_value(text.strip())))
    return result


def nest(key: str, value: Any) -> dict[str, Any]:
    """``{key: value}``, a dotted ``key`` giving nested mappings: ``nest("a.b", 1) == {"a": {"b": 1}}``."""
    parts = key.split(".")
    for part in reversed(parts[1:]):
        value = {part: value}
    return {parts[0]: value}


@dataclass
class RunConfig:
    """Everything that defines one training run (written to the run folder as ``config.yml``)."""

    env: str
    preset: str
    budget: str
    seed: int
    env_kwargs: dict[str, Any]
    n_envs: int
    eval_n_envs: int
    total_timesteps: int
    eval_episodes: int
    eval_epsilons: list[float]
    paper: bool
    hyperparams: dict[str, Any]
    """Algorithm keyword arguments from the config file and ``--param`` (over the preset's own)."""
    description: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    """Figures added when the run is set up (algorithm class, resolved kwargs, agent count, version)."""
    keep_checkpoints: int = KEEP_CHECKPOINTS
    """Checkpoints kept (the newest ones; ``0``: all); not part of what the run computes."""

    def to_dict(self) -> dict[str, Any]:
        """Plain data for ``config.yml``."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RunConfig:
        """Read back :meth:`to_dict` (unknown keys are kept in ``extra``)."""
        names = {f.name for f in cls.__dataclass_fields__.values()}
        known = {key: value for key, value in data.items() if key in names}
        extra = {key: value for key, value in data.items() if key not in names}
        known["extra"] = {**known.get("extra", {}), **extra}
        return cls(**known)


def check_params(preset: str, params: dict[str, Any], where: str = "", section: str = "") -> None:
    """Raise :class:`ConfigError` for algorithm arguments that preset's class does not take (see
    :func:`check_param_names`), and for numbers, flags and ``policy_kwargs`` of a wrong type (see
    :func:`~sb3_hgrn.common.off_policy.check_model_arguments`).

    :param where: the config file ``params`` come from, named first in the message (none: they come
        from the command line, ``--param``).
    :param section: the section of that file that holds them (``default``, ``budgets.ci.soft_hgrn``),
        put before the argument's name.
    """
    algorithm = PRESETS[preset][0]
    context = f"{algorithm.__name__} (preset {preset!r})"
    check_param_names(preset, params, f"{where}: {section}: {context}" if where else context)
    try:
        check_model_arguments(algorithm, params, f"{section}." if section else "")
    except TypeError as error:
        if where:
            raise ConfigError(
                f"{where}: {str(error).removesuffix('.')} ({algorithm.__name__}, preset {preset!r})."
            ) from error
        raise ConfigError(f"{context}: {error}") from error


def check_param_names(preset: str, params: dict[str, Any], where: str = "") -> None:
    """Raise :class:`ConfigError` for algorithm arguments that preset's class does not take or that the
    runner sets itself.

    :param where: where ``params`` come from, named first in the message (default: the algorithm).
    """
    algorithm = PRESETS[preset][0]
    where = where or f"{algorithm.__name__} (preset {preset!r})"
    accepted = set(inspect.signature(algorithm.__init__).parameters) - {"self"}
    for key in params:
        if key in RESERVED_PARAMS:
            raise ConfigError(
                f"{where}: {key!r} is set by the runner, not by --param or a config file (use the "
                "command's own option)."
            )
        if key not in accepted:
            raise ConfigError(
                f"{where} takes no argument {key!r}; "
                f"its arguments: {', '.join(sorted(accepted - RESERVED_PARAMS))}."
            )


def resolve_config(
    env: str,
    preset: str,
    budget: str = "cpu",
    seed: int = 0,
    timesteps: int | None = None,
    params: dict[str, Any] | None = None,
    env_params: dict[str, Any] | None = None,
    config_file: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
    keep_checkpoints: int | None = None,
) -> RunConfig:
    """The configuration of one run of ``preset`` on ``env`` at ``budget``.

    :param timesteps: agent-steps of training instead of the budget's ``total_timesteps``.
    :param keep_checkpoints: checkpoints to keep instead of the budget's ``keep_checkpoints``
        (default :data:`KEEP_CHECKPOINTS`; ``0``: all).
    :param params: algorithm keyword arguments over the config files' (``--param``).
    :param env_params: env keyword arguments over the config files' (``--env-param``).
    :param config_file: config files of one's own merged over the packaged one, in order (``--config``,
        see :func:`load_config_file`); a user env (``MODULE:ATTR``) has no packaged file, so they must
        give the budget's :data:`REQUIRED_BUDGET_FIELDS`.
    """
    check_env_name(env)
    check_preset_name(preset)
    check_budget_name(budget)
    named_configs = _load_configs(env, budget, config_file)
    hyperparams: dict[str, Any] = {}
    for where, config in named_configs:
        for section, layer in _param_layers(config, preset, budget):
            check_params(preset, layer, where, section)
            hyperparams = merge(hyperparams, layer)
    check_params(preset, params or {})
    hyperparams = merge(hyperparams, params or {})
    if timesteps is not None and timesteps < 1:
        raise ConfigError(f"--timesteps must be a positive number of agent-steps, got {timesteps}.")
    configs = [config for _, config in named_configs]
    config = _budget_config(configs, env, preset, budget, seed, timesteps, hyperparams, env_params)
    if keep_checkpoints is not None:
        config.keep_checkpoints = check_keep_checkpoints(keep_checkpoints, "--keep-checkpoints")
    return config


def random_policy_config(
    env: str,
    budget: str = "cpu",
    seed: int = 0,
    config_file: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
) -> RunConfig:
    """The evaluation settings of ``budget`` for the uniformly random policy (preset ``"random"``):
    no training and no algorithm arguments; the anchor row of the Table 1 sweep. ``config_file``: as
    :func:`budget_settings` (a ``MODULE:ATTR`` env needs one with its budget)."""
    check_env_name(env)
    check_budget_name(budget)
    configs = [config for _, config in _load_configs(env, budget, config_file)]
    return _budget_config(configs, env, RANDOM_POLICY, budget, seed, 0, {}, None)


def budget_settings(
    env: str, budget: str, config_file: str | os.PathLike | Sequence[str | os.PathLike] | None = None
) -> dict[str, Any]:
    """The fields of ``budget`` (``description``, ``n_envs``, ``total_timesteps``, ...) that ``env``'s
    packaged config file and ``config_file`` (see :func:`resolve_config`) give, later files winning."""
    check_env_name(env)
    check_budget_name(budget)
    configs = [config for _, config in _load_configs(env, budget, config_file)]
    return _merged_budget(configs, budget)[0]


def _load_configs(
    env: str, budget: str, config_file: str | os.PathLike | Sequence[str | os.PathLike] | None
) -> list[tuple[str, dict[str, Any]]]:
    """The config files of a run of ``env`` at ``budget``, each as ``(its path, its content)``: the
    packaged one of a registered env, then ``config_file``'s; those of a user env must give the
    budget's :data:`REQUIRED_BUDGET_FIELDS`."""
    configs = [(str(path), load_config_file(path)) for path in _config_paths(config_file)]
    if is_env_spec(env):
        _check_user_env_budget(env, budget, [config for _, config in configs])
        return configs
    return [(packaged_config_name(env), load_hyperparams(env)), *configs]


def _param_layers(config: dict[str, Any], preset: str, budget: str) -> list[tuple[str, dict[str, Any]]]:
    """The sections of a config file that hold ``preset``'s algorithm arguments at ``budget``, each as
    ``(its path in the file, its arguments)``, in the order they are merged."""
    section = _budget_section(config, budget)
    layers = [
        ("default", config.get("default")),
        (preset, config.get(preset)),
        (f"budgets.{budget}.default", section.get("default")),
        (f"budgets.{budget}.{preset}", section.get(preset)),
    ]
    return [(path, layer) for path, layer in layers if layer]


def _config_paths(
    config_file: str | os.PathLike | Sequence[str | os.PathLike] | None,
) -> list[str | os.PathLike]:
    """``config_file`` as a list of paths (one path, several, or none)."""
    if config_file is None:
        return []
    if isinstance(config_file, str | os.PathLike):
        return [config_file]
    return list(config_file)


def _check_user_env_budget(env: str, budget: str, configs: list[dict[str, Any]]) -> None:
    """Raise :class:`ConfigError` unless the config files of the user env ``env`` give ``budget``'s
    :data:`REQUIRED_BUDGET_FIELDS`."""
    given = {key for config in configs for key in _budget_section(config, budget)}
    missing = [key for key in REQUIRED_BUDGET_FIELDS if key not in given]
    if missing:
        where = "its --config file" if configs else "--config FILE (it has none)"
        raise ConfigError(
            f"The env {env!r} has no packaged config file, so {where} must give the budget "
            f"{budget!r} with {', '.join(REQUIRED_BUDGET_FIELDS)}; missing: {', '.join(missing)}. "
            f"A minimal config file (docs/cli.md, 'Your own env'):\n"
            + USER_ENV_CONFIG_EXAMPLE.replace("ci:", f"{budget}:", 1)
        )


def _budget_section(config: dict[str, Any], budget: str) -> dict[str, Any]:
    """The ``budget`` section of a config file (empty if it has none)."""
    return (config.get("budgets") or {}).get(budget) or {}


def _merged_budget(configs: list[dict[str, Any]], budget: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The budget fields of ``budget`` and the env arguments (top-level, then the budget's) of
    ``configs``, each merged over the ones before."""
    section: dict[str, Any] = {}
    env_kwargs: dict[str, Any] = {}
    for config in configs:
        budget_section = _budget_section(config, budget)
        section.update({key: value for key, value in budget_section.items() if key in BUDGET_FIELDS})
        env_kwargs = merge(env_kwargs, config.get("env_kwargs") or {})
        env_kwargs = merge(env_kwargs, budget_section.get("env_kwargs") or {})
    return section, env_kwargs


def _budget_config(
    configs: list[dict[str, Any]],
    env: str,
    preset: str,
    budget: str,
    seed: int,
    total_timesteps: int | None,
    hyperparams: dict[str, Any],
    env_params: dict[str, Any] | None,
) -> RunConfig:
    """A :class:`RunConfig` with the env sizes and evaluation settings of the ``budget`` sections of
    ``env``'s config files ``configs`` (the packaged one first, each merged over the ones before).

    :param total_timesteps: agent-steps of training (``None``: the budget's ``total_timesteps``).
    """
    section, env_kwargs = _merged_budget(configs, budget)
    env_kwargs = merge(env_kwargs, env_params or {})
    if total_timesteps is None:
        total_timesteps = section["total_timesteps"]
    return RunConfig(
        env=env,
        preset=preset,
        budget=budget,
        seed=int(seed),
        env_kwargs=env_kwargs,
        n_envs=int(section["n_envs"]),
        eval_n_envs=int(section.get("eval_n_envs", section["n_envs"])),
        total_timesteps=int(total_timesteps),
        eval_episodes=int(section["eval_episodes"]),
        eval_epsilons=[float(eps) for eps in section.get("eval_epsilons") or []],
        paper=bool(section.get("paper", False)),
        hyperparams=hyperparams,
        description=str(section.get("description", "")),
        keep_checkpoints=int(section.get("keep_checkpoints", KEEP_CHECKPOINTS)),
    )
