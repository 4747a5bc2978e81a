"""GP-MPC (Hewing, Kabzan & Zeilinger 2020): MPC on a prior model plus a Gaussian-process model of its error,
with state and input constraints tightened from the GP's variance propagated along the horizon.

``tightening``: the chance-constraint quantile, the covariance propagation and the per-stage offsets.
"""
