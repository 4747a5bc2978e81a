"""Shared reinforcement-learning infrastructure for the JAX learners (``algorithms.ppo``, ``algorithms.sac``).

- ``envs``: ``make_train_env(env, num_envs) -> TrainEnv``, N auto-resetting copies that take normalised actions in
  [-1, 1] and keep the final observation of a finished episode (for bootstrapping at a time limit), plus per-copy
  episode statistics (return, cost, RMSE) for learning curves.
- ``normalization``: running observation mean/variance (parallel Welford) and ``normalize``.
- ``networks``: the ``MLP`` flax module.
- ``checkpoint``: atomic save/load of any pytree with JSON metadata.
- ``training``: the ``Learner`` description and the host driver ``run_training`` (progress bar, CSV, checkpoints,
  resume, final policy, learning-curve plot).
- ``policy``: ``load_policy(directory, env, params)``, a saved policy as an ``algorithms.base.JaxController``.
"""
