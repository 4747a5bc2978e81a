"""The rollout/eval plot: what is drawn on each panel and what the legend lists (artists, not pixels)."""

import numpy as np
import pytest

from scg_jax.plotting import plot_rollout

T, N = 50, 4


def _data(**extra):
    """Two states: ``a`` creeps to 0.05 (far from its +-2.4 bounds), ``b`` climbs to 1.9 (near its bound 2.0)."""
    x = np.zeros((T, N, 2))
    x[:, :, 0] = np.linspace(0.0, 0.05, T)[:, None]
    x[:, :, 1] = np.linspace(0.0, 1.9, T)[:, None]
    truncated = np.zeros((T, N), bool)
    truncated[-1] = True
    data = {
        "t": 0.02 * np.arange(T),
        "dt": 0.02,
        "x": x,
        "x_final": x[-1],
        "x_ref": np.zeros((T + 1, 2)),
        "terminated": np.zeros((T, N), bool),
        "truncated": truncated,
        "state_names": np.array(["a", "b"]),
    }
    data.update(extra)
    return data


def _red_lines(ax) -> list[float]:
    return sorted(float(line.get_ydata()[0]) for line in ax.lines if line.get_color() == "red")


def _legend(fig) -> list[str]:
    return [text.get_text() for text in fig.legends[0].get_texts()]


def test_bounds_far_from_the_data_are_named_not_drawn(tmp_path):
    data = _data(x_low=np.array([-2.4, -np.inf]), x_high=np.array([2.4, 2.0]))
    fig = plot_rollout(data, tmp_path / "p.png")
    a, b = fig.axes[:2]
    assert _red_lines(a) == [] and a.get_title() == "a (bounds -2.4, 2.4 off scale)"
    assert _red_lines(b) == [2.0] and b.get_title() == "b"
    lo, hi = a.get_ylim()
    assert hi - lo < 0.1  # the traces fill the panel, not squashed by a bound 50 times their range away
    assert _legend(fig) == ["reference", "constraint bound"]  # nobody terminated early: no marker entry
    assert (tmp_path / "p.png").stat().st_size > 10_000


def test_legend_lists_only_what_is_drawn(tmp_path):
    fig = plot_rollout(_data(), tmp_path / "none.png")  # no bounds, no early termination
    assert _legend(fig) == ["reference"]
    assert all(_red_lines(ax) == [] for ax in fig.axes[:2])
    assert "constraint" not in fig.get_suptitle() and "terminated" not in fig.get_suptitle()

    data = _data(x_low=np.array([-2.4, -5.0]), x_high=np.array([2.4, 5.0]))
    data["terminated"][29, 1] = True  # copy 1 ends at step 30
    fig = plot_rollout(data, tmp_path / "early.png")
    assert _legend(fig) == ["reference", "terminated early"]  # both bounds are off scale: no bound entry
    markers = [line for line in fig.axes[0].lines if line.get_marker() == "x"]
    assert len(markers) == 1 and float(markers[0].get_xdata()[0]) == pytest.approx(30 * 0.02)


def test_input_bounds_follow_the_same_rule(tmp_path):
    u = np.repeat(np.linspace(0.0, 0.5, T)[:, None, None], N, axis=1)
    fig = plot_rollout(_data(u=u, u_low=np.array([-0.4]), u_high=np.array([10.0])), tmp_path / "u.png")
    ax = fig.axes[2]
    assert ax.get_title() == "u0 (applied) (bound 10 off scale)"
    assert _red_lines(ax) == [-0.4]
    assert _legend(fig) == ["reference", "constraint bound"]
    # A held input (constant) shows bounds within 10% of its size.
    held = np.full((T, N, 1), 0.5)
    fig = plot_rollout(_data(u=held, u_low=np.array([0.46]), u_high=np.array([0.6])), tmp_path / "held.png")
    assert _red_lines(fig.axes[2]) == [0.46] and fig.axes[2].get_title() == "u0 (applied) (bound 0.6 off scale)"
