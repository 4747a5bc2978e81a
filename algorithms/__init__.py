"""Controllers and learning algorithms built on ``scg_jax`` environments (LQR gains so far)."""
