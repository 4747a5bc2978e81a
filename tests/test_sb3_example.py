"""examples/sb3_ppo.py: stable-baselines3's PPO with default settings learns on a registered id.

Runs only where stable-baselines3 is installed (``pip install -e ".[sb3]"``); skipped otherwise.
"""

import importlib.util
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3")

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "sb3_ppo.py"


def _example():
    spec = importlib.util.spec_from_file_location("sb3_ppo", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_default_ppo_improves_its_return_on_the_cartpole_id():
    # Untrained, the pole falls within about a second (~50 of 250 steps). With the exponential reward a longer
    # episode is a larger return; the test asks for a doubling of both, well short of the full 250 steps.
    result = _example().train_and_evaluate("scg_jax/CartPole-v0", timesteps=30_000, seed=0, eval_episodes=10)
    (return_before, length_before), (return_after, length_after) = result["before"], result["after"]
    print("sb3 PPO on scg_jax/CartPole-v0:", result)
    assert return_after > 2.0 * return_before and length_after > 2.0 * length_before
