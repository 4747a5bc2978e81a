"""Hyperparameter search (``scg-jax tune``): Optuna studies of a learner's or an MPC's options, stored in a folder.

- ``tune(algo, config, out_dir, trials=N, population=P, ...) -> TuneResult``: run or continue a study
  (``scg_algorithms.tune.study``: TPE sampler, median pruner, SQLite storage, ``best.yaml``, ``trials.csv``, a plot).
- ``objective_value(per_episode, metric, alpha)``: the CVaR objective of one trial's evaluation.
- ``SEARCH_SPACES``, ``Param``: what is searched, as data (``scg_algorithms.tune.spaces``).
- ``population``: P settings of a JAX learner trained as one vmapped program with the hyperparameters traced.
"""

from scg_algorithms.tune.spaces import SEARCH_SPACES, Param
from scg_algorithms.tune.study import (
    BEST_FILE,
    OBJECTIVES,
    PLOT_FILE,
    STUDY_FILE,
    TRIALS_FILE,
    TuneInterrupted,
    TuneResult,
    objective_value,
    tunable_methods,
    tune,
)

__all__ = [
    "BEST_FILE",
    "OBJECTIVES",
    "PLOT_FILE",
    "SEARCH_SPACES",
    "STUDY_FILE",
    "TRIALS_FILE",
    "Param",
    "TuneInterrupted",
    "TuneResult",
    "objective_value",
    "tunable_methods",
    "tune",
]
