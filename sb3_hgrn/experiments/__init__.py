"""Experiment runner behind the ``sb3-hgrn`` command line: YAML configs, run folders, the sweeps.

- :mod:`sb3_hgrn.experiments.config`: load ``sb3_hgrn/hyperparams/<env>.yml`` and resolve one run's
  configuration (budget, preset overrides, ``--param`` / ``--env-param``).
- :mod:`sb3_hgrn.experiments.run_folder`: a run folder's files, how a run starts in it (fresh,
  resumed, evaluated or refused) and finding a saved run's model and configuration.
- :mod:`sb3_hgrn.experiments.runs`: train one run into its folder, load and evaluate saved runs.
- :mod:`sb3_hgrn.experiments.trust`: what a saved run's ``config.yml`` may make the loader import.
- :mod:`sb3_hgrn.experiments.policy_evaluation`: evaluation wrappers (epsilon-random actions, action
  counts) and the team-return figures of an evaluation.
- :mod:`sb3_hgrn.experiments.render`: one episode of a saved run as a GIF.
- :mod:`sb3_hgrn.experiments.table1`: the paper's Table 1 sweep, resumable, and its tables.
- :mod:`sb3_hgrn.experiments.figures`: the paper's figures (CTC curves, alpha, transfer, p_alpha).
- :mod:`sb3_hgrn.experiments.sweep`: grids of presets, seeds and argument values on one env.
- :mod:`sb3_hgrn.experiments.jobs`: the sweeps' runs as ``sb3-hgrn train`` processes, a few at a time.
- :mod:`sb3_hgrn.experiments.cells`: the figures and text of a results table's cells.
- :mod:`sb3_hgrn.experiments.backends`: where the sweeps' runs execute (local processes, Ray tasks).
"""

from sb3_hgrn.experiments.config import ConfigError, RunConfig, load_hyperparams, resolve_config

__all__ = ["ConfigError", "RunConfig", "load_hyperparams", "resolve_config"]
