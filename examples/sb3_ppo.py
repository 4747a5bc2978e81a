"""Train stable-baselines3's PPO, with its default settings, on a registered scg-jax Gymnasium id.

    pip install -e ".[sb3]"           # stable-baselines3 and torch (PyPI's Linux torch brings CUDA libraries)
    python examples/sb3_ppo.py                               # scg_jax/CartPole-v0, 30k steps
    python examples/sb3_ppo.py --env-id scg_jax/Quadrotor2D-v0 --timesteps 100000

The ids default to normalised actions in [-1, 1] and the exponential reward ``exp(-c)`` in (0, 1] per step
with termination when the state leaves its failure bounds, so a longer episode is a larger return and PPO
learns to keep the pole up (or the quadrotor at its goal) without any setting changed. The script prints the
mean return and episode length of the untrained and of the trained policy over ``--eval-episodes`` episodes.
"""

from __future__ import annotations

import argparse

import gymnasium
import numpy as np

import scg_jax  # noqa: F401  (registers the scg_jax/... ids)


def evaluate(model, env, episodes: int, seed: int) -> tuple[float, float]:
    """Mean return and mean length of ``episodes`` deterministic episodes of ``model`` on ``env``."""
    returns, lengths = [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        done, total, length = False, 0.0, 0
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, _ = env.step(action)
            total, length, done = total + float(reward), length + 1, terminated or truncated
        returns.append(total)
        lengths.append(length)
    return float(np.mean(returns)), float(np.mean(lengths))


def train_and_evaluate(env_id: str = "scg_jax/CartPole-v0", timesteps: int = 30_000, seed: int = 0, eval_episodes=10):
    """Train PPO (stable-baselines3 defaults) for ``timesteps`` env steps; return the evaluations before and after
    as ``{"before": (mean return, mean length), "after": (...)}``."""
    from stable_baselines3 import PPO

    model = PPO("MlpPolicy", gymnasium.make(env_id), seed=seed, verbose=0)
    eval_env = gymnasium.make(env_id)
    before = evaluate(model, eval_env, eval_episodes, seed=10_000)
    model.learn(total_timesteps=timesteps)
    after = evaluate(model, eval_env, eval_episodes, seed=10_000)
    return {"before": before, "after": after}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env-id", default="scg_jax/CartPole-v0")
    parser.add_argument("--timesteps", type=int, default=30_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=10)
    args = parser.parse_args(argv)
    result = train_and_evaluate(args.env_id, args.timesteps, args.seed, args.eval_episodes)
    for name, (mean_return, mean_length) in result.items():
        print(f"{name:>6}: mean return {mean_return:8.2f}, mean episode length {mean_length:6.1f} steps")


if __name__ == "__main__":
    main()
