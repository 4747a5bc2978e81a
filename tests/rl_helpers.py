"""Helpers shared by the PPO and SAC tests."""

from algorithms.rl.training import run_training


def run_training_capturing_policy(learner, env, params, key, out_dir):
    """``run_training`` (no progress, no CSV) that also returns the policy parameters it saved.

    Returns:
        ``(policy_params, result)``: what ``learner.policy_params`` gave for the final runner state, and
        ``run_training``'s summary.
    """
    captured = []

    def policy_params(runner_state):
        captured.append(learner.policy_params(runner_state))
        return captured[-1]

    result = run_training(
        learner._replace(policy_params=policy_params), env, params, key, out_dir, progress=False, csv=False
    )
    return captured[-1], result
