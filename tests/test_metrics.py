"""Episode metrics against hand-computed values on a tiny synthetic rollout."""

import numpy as np
import pytest

from scg_jax.metrics import cvar, episode_metrics, summarize

# Three copies, four steps. Copy 0 runs to the time limit with three steps in violation (a failure, not a crash),
# copy 1 crashes out of bounds at step 1, copy 2 reaches its goal (terminated, not a failure) at step 2 without a
# violation. Steps past an episode's end hold junk that must not count.
REWARD = np.array([[-1.0, -2.0, 0.5], [-1.0, -4.0, 0.5], [-1.0, np.nan, 0.5], [-1.0, np.inf, 9.0]])
MSE = np.array([[1.0, 4.0, 0.0], [4.0, 16.0, 0.0], [9.0, np.nan, 3.0], [16.0, 1.0, 5.0]])
TERMINATED = np.array([[0, 0, 0], [0, 1, 0], [0, 0, 1], [0, 1, 0]], bool)
TRUNCATED = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0]], bool)
OUT = np.array([[0, 0, 0], [0, 1, 0], [0, 0, 0], [0, 1, 0]], bool)
COST = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [1.0, 1.0, 1.0]])


def test_per_copy_metrics_by_hand():
    m = episode_metrics(REWARD, TERMINATED, TRUNCATED, MSE, OUT, np.zeros_like(OUT), COST)
    np.testing.assert_array_equal(m["length"], [4, 2, 3])
    np.testing.assert_allclose(m["return"], [-4.0, -6.0, 1.5])
    np.testing.assert_allclose(m["rmse"], [np.sqrt(30 / 4), np.sqrt(20 / 2), np.sqrt(3 / 3)])
    np.testing.assert_array_equal(m["crashed"], [False, True, False])
    np.testing.assert_allclose(m["violation_steps"], [3.0, 1.0, 0.0])
    np.testing.assert_array_equal(m["failed"], [True, True, False])


def test_summary_by_hand():
    s = summarize(episode_metrics(REWARD, TERMINATED, TRUNCATED, MSE, OUT, np.zeros_like(OUT), COST))
    rmse = np.array([np.sqrt(7.5), np.sqrt(10.0), 1.0])
    assert s["num_envs"] == 3
    np.testing.assert_allclose([s["rmse_mean"], s["rmse_std"]], [rmse.mean(), rmse.std()])
    np.testing.assert_allclose([s["return_mean"], s["length_mean"], s["failure_rate"]], [-8.5 / 3, 3.0, 2 / 3])
    np.testing.assert_allclose([s["crash_rate"], s["violation_steps_mean"]], [1 / 3, 4 / 3])
    # The worst half of three episodes: all of the worst (sqrt 10) and half of the second worst (sqrt 7.5).
    np.testing.assert_allclose(s["worst_case_rmse_at_0.5"], (np.sqrt(10.0) + 0.5 * np.sqrt(7.5)) / 1.5)


@pytest.mark.parametrize(
    "values, alpha, expected",
    [
        ([1.0, 2.0, 3.0, 4.0], 0.5, 3.5),
        ([4.0, 1.0, 3.0, 2.0], 0.25, 4.0),
        ([1.0, 2.0, 3.0], 0.5, (3.0 + 0.5 * 2.0) / 1.5),
        ([1.0, 2.0, 3.0], 1.0, 2.0),
        ([2.5], 0.5, 2.5),
    ],
)
def test_cvar_by_hand(values, alpha, expected):
    np.testing.assert_allclose(cvar(values, alpha), expected)


def test_cvar_lies_between_mean_and_max():
    values = np.random.default_rng(0).gamma(2.0, size=101)
    for alpha in (0.1, 0.5, 0.9):
        assert values.mean() <= cvar(values, alpha) <= values.max()
    with pytest.raises(ValueError, match="alpha"):
        cvar(values, 0.0)


def test_mismatched_shapes_are_refused():
    with pytest.raises(ValueError, match=r"mse: expected shape \(4, 3\)"):
        episode_metrics(REWARD, TERMINATED, TRUNCATED, MSE[:2], OUT, np.zeros_like(OUT))
