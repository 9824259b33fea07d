"""Hyperparameter search of one preset on one env with Optuna (``sb3-hgrn tune``), in the RL Zoo's habit.

Every trial samples algorithm arguments from the preset's search space (``hyperparams/search_spaces.yml``
or a file of one's own), trains one run of the budget in memory with the study's seed, evaluates it
every ``eval_freq`` agent-steps (reporting the mean team return to the pruner, which may stop it early)
and at the end; the objective is the last evaluation's mean team return, maximised by a TPE sampler.
A trial whose training fails (:data:`TRIAL_ERRORS`: a diverged run's NaN logits, a failed check, ...)
is recorded as failed, its error logged with its number and kept in ``trials.csv``, and the study goes
on; a study whose every trial failed ends with :class:`AllTrialsFailed`.

A tune folder (``<folder>/<study name>/``) holds::

    study.db                    the study (the default storage: SQLite)
    best.yml                    the best trial's algorithm arguments as a config file for ``train --config``
    trials.csv                  one row per trial: number, state, value, agent-steps, start, duration,
                                error (of a failed trial), params
    optimization_history.png    value of every trial and the best so far (once a trial is complete)
    param_importances.png       Optuna's parameter importances (once two trials are complete)

The study lives in any Optuna storage (an SQLite file by default, a PostgreSQL or MySQL URL for workers
on several machines): a second ``tune`` with the same storage and study name joins it.
"""

from __future__ import annotations

import os
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from importlib import resources
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import optuna
import yaml
from optuna.distributions import (
    BaseDistribution,
    CategoricalDistribution,
    FloatDistribution,
    IntDistribution,
    distribution_to_json,
)
from optuna.trial import FrozenTrial, Trial, TrialState
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_hgrn.common.evaluation import evaluate_graph_policy
from sb3_hgrn.common.files import atomic_write, write_csv_atomically, write_text_atomically
from sb3_hgrn.common.policies import policy_parameters
from sb3_hgrn.experiments.config import (
    ConfigError,
    RunConfig,
    check_param_names,
    check_preset_name,
    env_folder_name,
    nest,
    resolve_config,
)
from sb3_hgrn.experiments.run_folder import config_differences
from sb3_hgrn.experiments.runs import EVAL_SEED_OFFSET, make_env, new_model
from sb3_hgrn.presets import PRESETS, merge
from sb3_hgrn.validation import is_flag, is_integer, is_number

SEARCH_SPACES_FILE = "search_spaces.yml"
STUDY_FILE = "study.db"
BEST_FILE = "best.yml"
TRIALS_FILE = "trials.csv"
HISTORY_PLOT = "optimization_history.png"
IMPORTANCES_PLOT = "param_importances.png"
PRUNERS = ("median", "halving", "none")
DISTRIBUTION_KEYS = {
    "uniform": ({"low", "high"}, {"step"}),
    "loguniform": ({"low", "high"}, set()),
    "int": ({"low", "high"}, {"step", "log"}),
    "categorical": ({"choices"}, set()),
}
"""Distribution type -> (required keys, optional keys) besides ``type``."""
OPEN_ATTEMPTS = 5
"""Tries at opening a storage whose tables another worker is creating at the same moment."""
OPEN_RETRY_PAUSE = 0.5
"""Seconds before the second try at opening a storage; the n-th waits n times as long."""
SETUP_ATTR = "sb3_hgrn_setup"
"""Study user attribute holding :meth:`TuneSetup.describe`: a worker joins only a study of its setup."""
ERROR_ATTR = "error"
"""Trial user attribute holding the error that failed the trial (:func:`describe_error`)."""
TRIAL_ERRORS = (ValueError, RuntimeError, ArithmeticError)
"""Errors that fail one trial (diverged training, NaN logits, arguments that do not fit together, out
of memory) while the study goes on; any other error stops the worker."""
ERROR_CHARS = 300
"""Longest error message kept with a trial."""


class AllTrialsFailed(RuntimeError):
    """Every trial of a study failed: none completed nor was pruned (the message says why the last one
    failed)."""


# --- search spaces --------------------------------------------------------------------------------


def parse_distribution(name: str, spec: Any, where: str) -> BaseDistribution:
    """The Optuna distribution of one search-space entry (see ``hyperparams/search_spaces.yml``).

    :param name: the (dotted) parameter name, for messages.
    :param spec: ``{type: uniform|loguniform|int|categorical, ...}``.
    :param where: the file and section, for messages.
    """
    if not isinstance(spec, dict) or "type" not in spec:
        raise ConfigError(f"{where}: {name} must be a mapping with a type ({', '.join(DISTRIBUTION_KEYS)}).")
    kind = spec["type"]
    if kind not in DISTRIBUTION_KEYS:
        raise ConfigError(
            f"{where}: {name} has an unknown distribution type {kind!r}; expected "
            f"{', '.join(DISTRIBUTION_KEYS)}."
        )
    required, optional = DISTRIBUTION_KEYS[kind]
    keys = set(spec) - {"type"}
    if required - keys or keys - required - optional:
        raise ConfigError(
            f"{where}: {name} ({kind}) takes {', '.join(sorted(required))}"
            + (f" and optionally {', '.join(sorted(optional))}" if optional else "")
            + f"; got {', '.join(sorted(keys)) or 'nothing'}."
        )
    try:
        if kind == "categorical":
            choices = spec["choices"]
            if not isinstance(choices, list) or not choices:
                raise ValueError("choices must be a non-empty list")
            if any(
                choice is not None and not isinstance(choice, bool | int | float | str) for choice in choices
            ):
                raise ValueError("choices must be numbers, strings, booleans or null")
            return CategoricalDistribution(choices)
        if not all(is_number(spec[key]) for key in keys if key != "log"):
            raise ValueError(f"{', '.join(sorted(keys - {'log'}))} must be numbers")
        if kind == "int":
            if not all(is_integer(spec[key]) for key in keys if key != "log"):
                raise ValueError("low, high and step must be integers")
            if not is_flag(spec.get("log", False)):
                raise ValueError("log must be true or false")
            return IntDistribution(
                spec["low"], spec["high"], log=spec.get("log", False), step=spec.get("step", 1)
            )
        return FloatDistribution(
            float(spec["low"]), float(spec["high"]), log=kind == "loguniform", step=spec.get("step")
        )
    except ValueError as error:
        raise ConfigError(f"{where}: bad distribution for {name}: {str(error).rstrip('.')}.") from error


def load_search_space(preset: str, path: str | os.PathLike | None = None) -> dict[str, BaseDistribution]:
    """The search space of ``preset``: its section of ``path`` (default: the packaged
    ``hyperparams/search_spaces.yml``), checked against the arguments of the preset's class.

    :return: dotted parameter name -> Optuna distribution, in the file's order.
    """
    check_preset_name(preset)
    if path is None:
        where = f"hyperparams/{SEARCH_SPACES_FILE}"
        text = (resources.files("sb3_hgrn") / "hyperparams" / SEARCH_SPACES_FILE).read_text(encoding="utf-8")
    else:
        where = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as error:
            raise ConfigError(f"Cannot read the search space {path}: {error.strerror}.") from error
    try:
        spaces = yaml.safe_load(text) or {}
    except yaml.YAMLError as error:
        raise ConfigError(f"The search space {where} is not valid YAML: {error}") from error
    if not isinstance(spaces, dict):
        raise ConfigError(f"The search space {where} must be a mapping of preset names.")
    if preset not in spaces:
        raise ConfigError(
            f"{where} has no search space for preset {preset!r} "
            f"(it has: {', '.join(map(str, spaces)) or 'none'}); give one with --search-space FILE."
        )
    section = spaces[preset]
    where = f"{where} section {preset}"
    if not isinstance(section, dict) or not section:
        raise ConfigError(f"{where} must be a non-empty mapping of parameter names to distributions.")
    space = {str(name): parse_distribution(str(name), spec, where) for name, spec in section.items()}
    check_search_space(preset, space, where)
    return space


def policy_arguments(preset: str) -> set[str]:
    """The ``policy_kwargs`` the preset's policy class takes (its own and those of its graph bases)."""
    return set(policy_parameters(PRESETS[preset][0].policy_aliases["GraphPolicy"]))


def check_search_space(preset: str, space: dict[str, BaseDistribution], where: str) -> None:
    """Raise :class:`ConfigError` for a parameter the preset's class (or, for ``policy_kwargs.NAME``,
    its policy) does not take."""
    nested: dict[str, Any] = {}
    for name in space:
        if not all(name.split(".")):
            raise ConfigError(f"{where}: malformed parameter name {name!r}.")
        nested = merge(nested, nest(name, None))
    try:
        check_param_names(preset, nested)
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from error
    accepted = policy_arguments(preset)
    for name in nested.get("policy_kwargs") or {}:
        if name not in accepted:
            raise ConfigError(
                f"{where}: the policy of preset {preset!r} takes no argument {name!r} "
                f"(policy_kwargs.{name}); its arguments: {', '.join(sorted(accepted))}."
            )


def suggest(trial: Trial, space: dict[str, BaseDistribution]) -> dict[str, Any]:
    """Sample every parameter of ``space`` in ``trial``; dotted names become nested mappings."""
    sampled: dict[str, Any] = {}
    for name, distribution in space.items():
        if isinstance(distribution, CategoricalDistribution):
            value = trial.suggest_categorical(name, distribution.choices)
        elif isinstance(distribution, IntDistribution):
            value = trial.suggest_int(
                name, distribution.low, distribution.high, step=distribution.step, log=distribution.log
            )
        else:
            value = trial.suggest_float(
                name, distribution.low, distribution.high, step=distribution.step, log=distribution.log
            )
        sampled = merge(sampled, nest(name, value))
    return sampled


# --- trials ---------------------------------------------------------------------------------------


class TrialEvalCallback(BaseCallback):
    """Evaluate the mean team return every ``eval_freq`` agent-steps, report it to the Optuna trial
    (at the agent-step count) and stop training when the trial's pruner says so.

    :param trial: the trial being trained.
    :param eval_env: a graph VecEnv apart from the training env.
    :param eval_freq: agent-steps between evaluations.
    :param n_eval_episodes: team episodes per evaluation.
    """

    def __init__(
        self, trial: Trial, eval_env: VecEnv, eval_freq: int, n_eval_episodes: int, verbose: int = 0
    ):
        super().__init__(verbose=verbose)
        self.trial = trial
        self.eval_env = eval_env
        self.eval_freq = eval_freq
        self.n_eval_episodes = n_eval_episodes
        self.last_mean_return: float | None = None
        self.last_evaluated_at = 0
        self.pruned = False

    def _on_step(self) -> bool:
        if self.num_timesteps < self.last_evaluated_at + self.eval_freq:
            return True
        self.evaluate()
        self.pruned = self.trial.should_prune()
        return not self.pruned

    def evaluate(self) -> float:
        """Evaluate now and report the mean team return to the trial; returns it."""
        mean_return, _ = evaluate_graph_policy(self.model, self.eval_env, self.n_eval_episodes)
        self.trial.report(mean_return, self.num_timesteps)
        self.last_mean_return, self.last_evaluated_at = mean_return, self.num_timesteps
        if self.verbose:
            print(
                f"trial {self.trial.number}: team return {mean_return:.2f} "
                f"after {self.num_timesteps} agent-steps"
            )
        return mean_return


@dataclass
class TuneSetup:
    """What every trial of a study shares: the run it trains (but for the sampled arguments) and how
    it is evaluated.

    :param params: algorithm arguments fixed for every trial (``--param``).
    :param env_params: env arguments over the config's (``--env-param``).
    :param timesteps: agent-steps of training per trial (``None``: the budget's).
    :param eval_freq: agent-steps between evaluations (``None``: a fifth of the training).
    :param eval_episodes: team episodes per evaluation.
    :param config: config files of one's own (``--config``; a user env ``MODULE:ATTR`` needs one).
    """

    env: str
    preset: str
    budget: str
    seed: int
    search_space: dict[str, BaseDistribution]
    params: dict[str, Any] = field(default_factory=dict)
    env_params: dict[str, Any] = field(default_factory=dict)
    timesteps: int | None = None
    eval_freq: int | None = None
    eval_episodes: int = 4
    config: list[str] = field(default_factory=list)

    def __post_init__(self):
        for name in self.search_space:
            if _has_key(self.params, name):
                raise ConfigError(f"{name} is both searched and fixed by --param; drop one of them.")
        self.run_config({})  # bad names or values of the env, preset, budget or --param fail here
        if self.eval_episodes < 1:
            raise ConfigError(f"--eval-episodes must be a positive integer, got {self.eval_episodes}.")
        if self.eval_freq is not None and self.eval_freq < 1:
            raise ConfigError(f"--eval-freq must be a positive number of agent-steps, got {self.eval_freq}.")

    def run_config(self, sampled: dict[str, Any]) -> RunConfig:
        """The configuration of a trial with the ``sampled`` algorithm arguments."""
        return resolve_config(
            self.env,
            self.preset,
            self.budget,
            self.seed,
            self.timesteps,
            params=merge(self.params, sampled),
            env_params=self.env_params,
            config_file=self.config,
        )

    def default_study_name(self) -> str:
        """``<env>_<preset>_<budget>``, ``<env>`` as in run folders (:func:`env_folder_name`)."""
        return f"{env_folder_name(self.env)}_{self.preset}_{self.budget}"

    def evaluation_interval(self, total_timesteps: int) -> int:
        """Agent-steps between evaluations of a trial training ``total_timesteps``."""
        return self.eval_freq if self.eval_freq is not None else max(1, total_timesteps // 5)

    def describe(self) -> dict[str, Any]:
        """Plain data of the setup (stored in the study; the search space as Optuna's JSON; no
        ``config`` when there is none, as before it existed)."""
        data = asdict(self)
        if not self.config:
            del data["config"]
        data["search_space"] = {name: distribution_to_json(d) for name, d in self.search_space.items()}
        return data

    def best_config(self, trial: FrozenTrial) -> dict[str, Any]:
        """A config file (``train --config``) of ``trial``: its sampled and the fixed algorithm arguments
        in the preset's section, and the ``--env-param`` values as ``env_kwargs``."""
        params = dict(self.params)
        for name, value in trial.params.items():
            params = merge(params, nest(name, value))
        config: dict[str, Any] = {"env_kwargs": dict(self.env_params)} if self.env_params else {}
        config[self.preset] = params
        return config


def _has_key(params: dict[str, Any], dotted: str) -> bool:
    """Whether the nested mapping ``params`` sets the dotted key ``dotted``."""
    head, _, rest = dotted.partition(".")
    if head not in params:
        return False
    return not rest or (isinstance(params[head], dict) and _has_key(params[head], rest))


class Objective:
    """The objective of a study: trains one trial of ``setup`` and returns its last mean team return.

    :param device: torch device of the trials.
    :param verbose: 1: print every evaluation.
    """

    def __init__(self, setup: TuneSetup, device: str = "auto", verbose: int = 0):
        self.setup = setup
        self.device = device
        self.verbose = verbose

    def __call__(self, trial: Trial) -> float:
        """Train and evaluate ``trial``; an error of :data:`TRIAL_ERRORS` is recorded with the trial
        (:data:`ERROR_ATTR`) before it fails it."""
        try:
            return self.train(trial)
        except TRIAL_ERRORS as error:
            trial.set_user_attr(ERROR_ATTR, describe_error(error))
            raise

    def train(self, trial: Trial) -> float:
        """The body of :meth:`__call__`: the trial's last mean team return."""
        config = self.setup.run_config(suggest(trial, self.setup.search_space))
        env = make_env(config, config.n_envs, config.seed)
        eval_env = make_env(config, config.eval_n_envs, config.seed + EVAL_SEED_OFFSET)
        try:
            model = new_model(config, env, verbose=0, tensorboard_log=None, device=self.device)
            callback = TrialEvalCallback(
                trial,
                eval_env,
                self.setup.evaluation_interval(config.total_timesteps),
                self.setup.eval_episodes,
                verbose=self.verbose,
            )
            model.learn(config.total_timesteps, callback=callback)
            trial.set_user_attr("agent_steps", int(model.num_timesteps))
            if callback.pruned:
                raise optuna.TrialPruned(f"pruned after {model.num_timesteps} agent-steps")
            if callback.last_evaluated_at != model.num_timesteps:
                callback.evaluate()
        finally:
            env.close()
            eval_env.close()
        return float(callback.last_mean_return)


def describe_error(error: BaseException) -> str:
    """``Type: first line of the message``, at most :data:`ERROR_CHARS` characters (a NaN check's
    message goes on with the whole tensor)."""
    lines = str(error).strip().splitlines()
    text = f"{type(error).__name__}: {lines[0] if lines else ''}"
    return text if len(text) <= ERROR_CHARS else text[: ERROR_CHARS - 3] + "..."


# --- studies --------------------------------------------------------------------------------------


def make_pruner(name: str, n_startup_trials: int = 5, n_warmup_steps: int = 0) -> optuna.pruners.BasePruner:
    """The pruner ``median`` (Optuna's median rule), ``halving`` (successive halving) or ``none``.

    :param n_startup_trials: trials completed before the median pruner prunes.
    :param n_warmup_steps: agent-steps of a trial before the median pruner may prune it.
    """
    if n_warmup_steps < 0:
        raise ConfigError(f"--n-warmup-steps must be >= 0 agent-steps, got {n_warmup_steps}.")
    if name == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=n_startup_trials, n_warmup_steps=n_warmup_steps)
    if name == "halving":
        return optuna.pruners.SuccessiveHalvingPruner()
    if name == "none":
        return optuna.pruners.NopPruner()
    raise ConfigError(f"Unknown pruner {name!r}; available: {', '.join(PRUNERS)}.")


def default_storage(folder: str | os.PathLike) -> str:
    """``sqlite:///<folder>/study.db`` (an absolute path, so workers in any directory share it)."""
    return f"sqlite:///{(Path(folder) / STUDY_FILE).resolve()}"


def hide_password(url: str) -> str:
    """``url`` with its password (if any) replaced by ``***``, for messages."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        return make_url(url).render_as_string(hide_password=True)
    except ArgumentError:
        return url


def open_storage(url: str) -> optuna.storages.RDBStorage:
    """The Optuna storage at ``url`` (any SQLAlchemy URL Optuna takes). Running trials send a heartbeat,
    so a later worker marks those of a killed one as failed; SQLite waits up to a minute for a lock.

    Workers that open a new database at the same moment each create Optuna's tables, and all but one
    fail on the tables the first one made; those try again, up to ``OPEN_ATTEMPTS`` times in all, and
    then find the tables there."""
    try:
        for attempt in range(1, OPEN_ATTEMPTS):
            try:
                return _rdb_storage(url)
            except Exception as error:
                if not _lost_table_race(error):
                    raise
                time.sleep(OPEN_RETRY_PAUSE * attempt)
        return _rdb_storage(url)
    except ImportError as error:  # Optuna's, raised from SQLAlchemy's import of the database driver
        raise ConfigError(
            f"Cannot open the Optuna storage {hide_password(url)}: {missing_driver(url, error)}"
        ) from error
    except Exception as error:  # SQLAlchemy's errors differ by database: name the URL and pass its message
        raise ConfigError(f"Cannot open the Optuna storage {hide_password(url)}: {error}") from error


def _lost_table_race(error: Exception) -> bool:
    """Whether ``error`` may come from creating Optuna's tables while another worker creates them: an
    integrity or programming error (PostgreSQL's duplicate type or key), or MySQL's "table already
    exists" (error 1050, an operational error there). Any other fault is raised at once."""
    from sqlalchemy.exc import IntegrityError, OperationalError, ProgrammingError

    if isinstance(error, (IntegrityError, ProgrammingError)):
        return True
    return isinstance(error, OperationalError) and "already exists" in str(error.orig)


def _rdb_storage(url: str) -> optuna.storages.RDBStorage:
    """One try of :func:`open_storage`."""
    connect_args = {"timeout": 60} if url.startswith("sqlite") else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)  # the heartbeat's
        return optuna.storages.RDBStorage(
            url, engine_kwargs={"connect_args": connect_args}, heartbeat_interval=60, grace_period=180
        )


def missing_driver(url: str, error: ImportError) -> str:
    """What to install when the Python driver of the database at ``url`` does not import (``error``:
    Optuna's, whose cause is the driver's own ``ImportError``)."""
    cause = error.__cause__ or error
    if url.startswith("postgresql"):
        return (
            f"the PostgreSQL driver is not installed ({cause}); pip install 'sb3_hgrn[postgres]' "
            "installs psycopg 3, the driver of postgresql+psycopg:// URLs."
        )
    if url.startswith(("mysql", "mariadb")):
        return (
            f"the MySQL driver is not installed ({cause}); pip install 'sb3_hgrn[mysql]' "
            "installs PyMySQL, the driver of mysql+pymysql:// URLs."
        )
    return f"the database driver the URL names is not installed ({cause}); install it with pip."


def open_study(
    setup: TuneSetup,
    storage: str,
    study_name: str,
    sampler: optuna.samplers.BaseSampler | None = None,
    pruner: optuna.pruners.BasePruner | None = None,
) -> optuna.Study:
    """Create the study ``study_name`` in ``storage``, or join it if it exists: a study is joined only
    when it was created with the same setup (env, preset, budget, seed, search space, fixed arguments,
    training length and evaluation), else :class:`ConfigError` names what differs."""
    study = optuna.create_study(
        storage=open_storage(storage),
        study_name=study_name,
        sampler=sampler,
        pruner=pruner,
        direction="maximize",
        load_if_exists=True,
    )
    current = setup.describe()
    stored = study.user_attrs.get(SETUP_ATTR)
    if stored is None:
        study.set_user_attr(SETUP_ATTR, current)
    elif differences := config_differences(stored, current):
        raise ConfigError(
            f"The study {study_name!r} in {hide_password(storage)} was created for another setup "
            f"({', '.join(differences)} differ); use another --study-name or the study's own options."
        )
    return study


def _optimize(
    setup: TuneSetup,
    storage: str,
    study_name: str,
    pruner: optuna.pruners.BasePruner,
    n_trials: int,
    sampler_seed: int,
    n_startup_trials: int,
    threads: int,
    device: str,
    verbose: int,
) -> None:
    """Run ``n_trials`` trials of the study in this process (also the entry of a worker process); a
    trial failing with an error of :data:`TRIAL_ERRORS` is recorded as failed and logged by Optuna
    with its number and the error, and the next trial starts."""
    import torch

    torch.set_num_threads(threads)
    _set_optuna_verbosity(verbose)
    sampler = optuna.samplers.TPESampler(n_startup_trials=n_startup_trials, seed=sampler_seed)
    study = open_study(setup, storage, study_name, sampler, pruner)
    study.optimize(Objective(setup, device=device, verbose=verbose), n_trials=n_trials, catch=TRIAL_ERRORS)


def _set_optuna_verbosity(verbose: int) -> None:
    """Optuna's log of every trial with ``verbose``, else only its warnings."""
    optuna.logging.set_verbosity(optuna.logging.INFO if verbose else optuna.logging.WARNING)


def run_study(
    setup: TuneSetup,
    folder: str | os.PathLike,
    n_trials: int,
    n_jobs: int = 1,
    storage: str | None = None,
    study_name: str | None = None,
    pruner: optuna.pruners.BasePruner | None = None,
    n_startup_trials: int = 5,
    sampler_seed: int | None = None,
    threads: int = 1,
    device: str = "auto",
    verbose: int = 0,
) -> optuna.Study:
    """Run ``n_trials`` more trials of the study of ``setup``, then write the tune folder's results
    (:func:`write_results`); returns the study. Failed trials are recorded and the others go on, but
    when every trial of the study has failed it raises :class:`AllTrialsFailed` (after writing the
    results).

    :param folder: the tune folder (results, and the default SQLite storage ``study.db``).
    :param n_jobs: worker processes, each running its share of the trials with ``threads`` torch
        threads and a TPE sampler seeded ``sampler_seed + worker``.
    :param storage: an Optuna storage URL (default :func:`default_storage` of ``folder``).
    :param study_name: default ``<env>_<preset>_<budget>``.
    :param pruner: default the median pruner of :func:`make_pruner`.
    :param n_startup_trials: random trials before TPE samples from its model.
    :param sampler_seed: default ``setup.seed``; commands that share a study from several machines
        should each have their own, spaced by at least ``n_jobs``, or their random startup
        trials repeat one another.
    """
    if n_trials < 1 or n_jobs < 1 or threads < 1:
        raise ConfigError(
            f"n_trials, n_jobs and threads must be positive, got {n_trials}, {n_jobs}, {threads}."
        )
    _set_optuna_verbosity(verbose)
    folder = Path(folder)
    if storage is None:
        folder.mkdir(parents=True, exist_ok=True)
        storage = default_storage(folder)
    study_name = study_name or setup.default_study_name()
    pruner = pruner if pruner is not None else make_pruner("median", n_startup_trials)
    open_study(setup, storage, study_name)  # created (or checked) before any worker joins it
    folder.mkdir(parents=True, exist_ok=True)
    shares = [n_trials // n_jobs + (worker < n_trials % n_jobs) for worker in range(n_jobs)]
    jobs = [
        (
            setup,
            storage,
            study_name,
            pruner,
            share,
            (setup.seed if sampler_seed is None else sampler_seed) + worker,
            n_startup_trials,
            threads,
            device,
            verbose,
        )
        for worker, share in enumerate(shares)
        if share
    ]
    if len(jobs) == 1:
        _optimize(*jobs[0])
    else:
        with ProcessPoolExecutor(len(jobs), mp_context=get_context("spawn")) as pool:
            for future in [pool.submit(_optimize, *job) for job in jobs]:
                future.result()
    study = optuna.load_study(study_name=study_name, storage=open_storage(storage))
    write_results(study, setup, folder)
    check_some_trial_ran(study, folder)
    return study


def check_some_trial_ran(study: optuna.Study, folder: str | os.PathLike) -> None:
    """Raise :class:`AllTrialsFailed` when the study has failed trials and none that completed or was
    pruned, naming the error of its last failed trial."""
    trials = study.get_trials(deepcopy=False)
    failed = [trial for trial in trials if trial.state == TrialState.FAIL]
    if not failed or any(trial.state in (TrialState.COMPLETE, TrialState.PRUNED) for trial in trials):
        return
    last = failed[-1]
    error = last.user_attrs.get(ERROR_ATTR, "its error is in the log above")
    raise AllTrialsFailed(
        f"Every trial of the study {study.study_name!r} failed ({len(failed)} of {len(trials)}); the last, "
        f"trial {last.number} with {last.params}: {error}. See {Path(folder) / TRIALS_FILE}."
    )


# --- results --------------------------------------------------------------------------------------


def write_results(study: optuna.Study, setup: TuneSetup, folder: str | os.PathLike) -> list[Path]:
    """Write ``trials.csv``, and with complete trials ``best.yml`` and the plots, into ``folder``
    (each file atomically); returns the files written."""
    folder = Path(folder)
    trials = study.get_trials(deepcopy=False)
    write_trials_csv(trials, list(setup.search_space), folder / TRIALS_FILE)
    written = [folder / TRIALS_FILE]
    complete = [trial for trial in trials if trial.state == TrialState.COMPLETE]
    if complete:
        write_best_config(study, setup, folder / BEST_FILE)
        written.append(folder / BEST_FILE)
        written += write_plots(study, folder, importances=len(complete) >= 2)
    return written


def write_trials_csv(trials: list[FrozenTrial], names: list[str], path: Path) -> None:
    """One row per trial: ``number``, ``state``, ``value`` (last mean team return), ``agent_steps``
    trained, ``last_step`` (agent-steps of the last evaluation), ``datetime_start``, ``duration_s``,
    ``error`` (:func:`describe_error` of a failed trial) and ``params_<name>`` per searched parameter."""
    rows = []
    for trial in trials:
        duration = (
            None
            if trial.datetime_complete is None or trial.datetime_start is None
            else round((trial.datetime_complete - trial.datetime_start).total_seconds(), 2)
        )
        row = {
            "number": trial.number,
            "state": trial.state.name,
            "value": trial.value,
            "agent_steps": trial.user_attrs.get("agent_steps"),
            "last_step": trial.last_step,
            "datetime_start": None if trial.datetime_start is None else trial.datetime_start.isoformat(),
            "duration_s": duration,
            "error": trial.user_attrs.get(ERROR_ATTR),
        }
        rows.append(row | {f"params_{name}": trial.params.get(name) for name in names})
    write_csv_atomically(path, rows)


def write_best_config(study: optuna.Study, setup: TuneSetup, path: Path) -> None:
    """``best.yml``: :meth:`TuneSetup.best_config` of the best trial, after comment lines saying where
    it comes from and how to train with it."""
    trial = study.best_trial
    steps = f" --timesteps {setup.timesteps}" if setup.timesteps else ""
    header = (
        f"# Best trial {trial.number} of the Optuna study {study.study_name!r}: mean team return "
        f"{trial.value:.4g} after {trial.user_attrs.get('agent_steps')} agent-steps\n"
        f"# ({setup.preset} on {setup.env}, budget {setup.budget}, seed {setup.seed}; "
        f"{time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}). Train with it:\n"
        f"#   sb3-hgrn train --env {setup.env} --preset {setup.preset} --budget {setup.budget}{steps} "
        f"--config {' '.join([*setup.config, str(path)])}\n"
    )
    write_text_atomically(path, header + yaml.safe_dump(setup.best_config(trial), sort_keys=False))


def write_plots(study: optuna.Study, folder: Path, importances: bool) -> list[Path]:
    """Optuna's optimization history and (with ``importances``) parameter importances as PNG files, drawn
    with matplotlib; returns the files written (none when matplotlib is not installed)."""
    try:
        import matplotlib.pyplot as plt
        from optuna.visualization import matplotlib as plots
    except ImportError:
        warnings.warn(
            "matplotlib is not installed: no plots of the study (pip install matplotlib).", stacklevel=2
        )
        return []
    drawers = [(HISTORY_PLOT, plots.plot_optimization_history)]
    if importances:
        drawers.append((IMPORTANCES_PLOT, plots.plot_param_importances))
    written = []
    for name, draw in drawers:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            axes = draw(study)
        figure = axes.figure
        try:
            with atomic_write(folder / name, "wb") as file:
                figure.savefig(file, format="png", dpi=110, bbox_inches="tight")
        finally:
            plt.close(figure)
        written.append(folder / name)
    return written


def summary(study: optuna.Study, folder: str | os.PathLike) -> str:
    """Lines for the terminal: the study's trials by state, its best trial and the tune folder."""
    trials = study.get_trials(deepcopy=False)
    counts = {state: sum(trial.state == state for trial in trials) for state in TrialState}
    states = ", ".join(f"{count} {state.name.lower()}" for state, count in counts.items() if count)
    lines = [f"study {study.study_name!r}: {len(trials)} trials ({states})"]
    if counts[TrialState.COMPLETE]:
        best = study.best_trial
        lines.append(f"best trial {best.number}: mean team return {best.value:.4g} with {best.params}")
        lines.append(f"train with it: sb3-hgrn train ... --config {Path(folder) / BEST_FILE}")
    lines.append(f"results in {folder}")
    return "\n".join(lines)
