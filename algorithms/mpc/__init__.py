"""Model predictive control: a batched linear MPC in JAX (``linear``) and CasADi/IPOPT MPC (``nonlinear``)."""
