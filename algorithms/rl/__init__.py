"""Shared reinforcement-learning infrastructure for the JAX learners (``scg_algorithms.ppo``, ``scg_algorithms.sac``).

- ``envs``: ``make_train_env(env, num_envs) -> TrainEnv``, N auto-resetting copies that take normalised actions in
  [-1, 1] and keep the final observation of a finished episode (for bootstrapping at a time limit), plus per-copy
  episode statistics (return, cost, RMSE) for learning curves.
- ``collector``: ``collect(train_env, params, state, act, key, num_steps)``, the one data collector of every learner
  (scan over the batched env, episode statistics, observation normaliser; transitions with ``cost``, ``next_obs``,
  chosen ``info`` entries, the act function's extras, an optional adversary input and optional per-copy labels).
- ``config``: the option declarations learners share (``learner_option``, ``hidden_sizes_option``), parsed with
  ``scg_algorithms.base.parse_options`` like every method's options.
- ``learner``: ``make_train(learner)``, the whole run of any ``Learner`` as one pure function (jit, vmap over seeds).
- ``counter``: ``Count``, an exact step counter past 2^31 without x64 (two uint32 words).
- ``distributions``: the Gaussian and tanh-Gaussian log-densities, entropy and sampler.
- ``normalization``: running observation mean/variance (parallel Welford) and ``normalize``.
- ``networks``: ``MLP``, ``value_network`` (critics, cost critics), SAC's ``TanhGaussianActor``, ``QNetwork``,
  ``twin_q``.
- ``checkpoint``: atomic save/load of any pytree with JSON metadata.
- ``training``: the ``Learner`` description and the host driver ``run_training`` (progress bar or log lines, CSV,
  checkpoints, resume/extend/overwrite, save on Ctrl-C, final policy, learning-curve plot).
- ``policy``: ``load_policy(directory, env, params)``, a saved policy as an ``scg_algorithms.base.JaxController``.
"""
