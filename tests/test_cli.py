"""The scg-jax command: outputs on disk, numbers in them, and clear errors."""

import json
import os

import numpy as np
import pytest

from scg_cli import main
from tests.rl_helpers import set_options


def _run(tmp_path, name, *args):
    out = tmp_path / name
    assert main(["rollout", *args, "--out", str(out)]) == 0
    data = np.load(out / "rollout.npz")
    metrics = json.loads((out / "metrics.json").read_text())
    assert (out / "rollout.png").stat().st_size > 10_000
    return data, metrics


def test_lqr_rollout_stabilises_the_cartpole_and_writes_consistent_files(tmp_path):
    data, metrics = _run(
        tmp_path, "lqr", "--system", "cartpole", "--policy", "linear", "--num-envs", "8", "--episode-len", "2"
    )
    assert data["x"].shape == (100, 8, 4) and data["x_ref"].shape == (101, 4) and data["u_ref"].shape == (100, 1)
    assert metrics["summary"]["failure_rate"] == 0.0
    assert np.abs(data["x_final"][:, 2]).max() < 0.05
    # The summary is the data's: recompute the RMSE from the saved per-step mse.
    np.testing.assert_allclose(metrics["per_copy"]["rmse"], np.sqrt(data["mse"].mean(axis=0)), rtol=1e-5)
    K = np.asarray(metrics["gain"])
    assert K.shape == (1, 4) and K[0, 2] < 0  # pushes the cart under a pole leaning towards +x
    import jax

    assert metrics["devices"] == [str(jax.devices()[0])]  # one device without --devices (several: multidevice_cases)


def test_zero_policy_lets_the_pole_fall(tmp_path):
    _, metrics = _run(tmp_path, "zero", "--system", "cartpole", "--policy", "zero", "--num-envs", "8")
    assert metrics["summary"]["failure_rate"] > 0.5
    assert metrics["summary"]["length_mean"] < 250


def test_lqr_tracks_the_circle_better_than_hovering(tmp_path):
    common = ["--system", "quadrotor_2d", "--task", "tracking", "--num-envs", "8", "--episode-len", "2"]
    _, lqr = _run(tmp_path, "lqr", *common, "--policy", "linear")
    _, hover = _run(tmp_path, "hover", *common, "--policy", "zero")
    assert lqr["summary"]["rmse_mean"] < 0.7 * hover["summary"]["rmse_mean"]


def test_config_and_set_overrides_reach_the_env(tmp_path):
    data, metrics = _run(
        tmp_path,
        "cfg",
        "--config",
        "configs/paper_cartpole_lqr_mpc.yaml",
        "--set",
        "env.episode_len_sec=2",
        "--set",
        "env.constraints=[{type: abs_bound, on: input, bound: 0.01}]",
        "--num-envs",
        "4",
    )
    assert metrics["env"]["ctrl_freq"] == 15 and data["x"].shape[0] == 30
    # The resolved config is stored and rebuilds the same env (constraint included).
    import scg_jax

    env, params = scg_jax.make_from_config(scg_jax.load_config(str(data["config"])))
    assert env.ctrl_freq == 15 and env.num_steps == 30 and len(env.constraint_specs) == 1
    np.testing.assert_allclose(np.asarray(params.constraints[0].b), [0.01, 0.01])
    assert metrics["overrides"][0] == "env.episode_len_sec=2"
    # An LQR force bounded by 1 cN cannot hold; every copy violates the input constraint at some step.
    assert np.all(np.asarray(metrics["per_copy"]["violation_steps"]) > 0)
    # Rows u - b and -b - u: the larger is |u| - b.
    np.testing.assert_allclose(data["constraint_values"].max(axis=-1), np.abs(data["u"][..., 0]) - 0.01, atol=1e-6)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--system", "cartpole", "--task", "tracking", "--offset", "1,2,3"], "argument --offset: expected 2"),
        (["--system", "pendulum"], "argument --system: invalid choice: 'pendulum'"),
        (["--task", "tracking"], "argument --system: required unless --config is given"),
        (["--system", "cartpole", "--policy", "linear", "--gain", "1,2"], "argument --gain: cartpole needs nu x nx"),
        (
            ["--system", "cartpole", "--ctrl-freq", "15"],
            "argument --physics-freq: env.physics_freq: must be a multiple of ctrl_freq",
        ),
        (["--system", "cartpole", "--set", "env.trajectry.shape=circle"], "env.trajectry"),
    ],
)
def test_bad_input_exits_2_naming_the_option(tmp_path, capsys, args, message):
    assert main(["rollout", *args, "--out", str(tmp_path / "bad")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


# ----------------------------------------------------------------------------------------------- eval, compare
_EVAL_ENV = ["--config", "configs/cartpole_stabilization.yaml", "--set", "env.episode_len_sec=1", "--episodes", "4"]


def test_eval_writes_the_paper_metrics_consistent_with_the_data(tmp_path):
    out = tmp_path / "eval" / "lqr.json"
    assert main(["eval", *_EVAL_ENV, "--controller", "lqr", "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    for key in ("rmse", "rmse_std", "worst_case_rmse_at_0.5", "failure_rate", "constraint_violation_steps"):
        assert isinstance(record[key], float)
    # exponential reward (the config's): each step earns exp(-c) in (0, 1]
    assert 0 < record["return"] <= record["length"] == 50 and record["controller"] == "lqr"
    data = np.load(out.with_suffix(".npz"))
    rmse = np.sqrt(data["mse"].mean(axis=0))
    np.testing.assert_allclose(record["per_episode"]["rmse"], rmse, rtol=1e-5)
    np.testing.assert_allclose(record["rmse"], rmse.mean(), rtol=1e-5)
    assert record["worst_case_rmse_at_0.5"] >= record["rmse"]
    assert data["x"].shape == (50, 4, 4) and data["u"].shape == (50, 4, 1)
    np.testing.assert_allclose(data["x_high"], [2.4, np.inf, np.pi / 2, np.inf], rtol=1e-6)
    assert out.with_suffix(".png").stat().st_size > 10_000


def test_compare_evaluates_every_controller_on_the_same_episodes(tmp_path, capsys):
    out = tmp_path / "compare.json"
    args = ["compare", *_EVAL_ENV, "--controllers", "lqr", "--prior-scale", "1.5", "--out", str(out)]
    assert main(args) == 0
    record = json.loads(out.read_text())
    assert list(record["controllers"]) == ["lqr"] and record["prior_scale"] == 1.5
    assert "worst-case rmse" in capsys.readouterr().out
    # The prior reaches the controller: a heavier model gives other gains than the true one.
    true_out = tmp_path / "true.json"
    assert main(["compare", *_EVAL_ENV, "--controllers", "lqr", "--out", str(true_out)]) == 0
    true_record = json.loads(true_out.read_text())
    K_true = np.asarray(true_record["controllers"]["lqr"]["controller_info"]["K"])
    K_heavy = np.asarray(record["controllers"]["lqr"]["controller_info"]["K"])
    assert K_true.shape == K_heavy.shape == (1, 1, 4) and not np.allclose(K_true, K_heavy, rtol=1e-3)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["eval", "--controller", "pd"], "argument --controller: 'pd' is neither a controller name (pid, lqr"),
        (["eval", "--controller", "lqr", "--prior-scale", "0"], "argument --prior-scale: must be a positive number"),
        (["eval", "--controller", "lqr", "--set", "controllers.lqr.mode=near"], "controllers.lqr.mode: unknown value"),
        (["compare", "--controllers", "lqr,lqr"], "argument --controllers: a controller is listed twice"),
    ],
)
def test_eval_and_compare_refuse_bad_input(tmp_path, capsys, args, message):
    out = tmp_path / "bad.json"
    assert main([*args, "--system", "cartpole", "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


# ----------------------------------------------------------------------------------------------- train
_TINY_PPO = set_options("training.ppo", total_env_steps=1024, num_envs=16, rollout_length=16, num_minibatches=2)


def test_train_writes_a_policy_that_eval_and_compare_run(tmp_path, capsys):
    out = tmp_path / "ppo"
    args = ["train", *_EVAL_ENV[:4], *_TINY_PPO, "--algo", "ppo", "--out", str(out), "--eval-episodes", "4"]
    assert main(args) == 0
    for name in ("policy.msgpack", "policy.json", "checkpoint.msgpack", "progress.csv", "learning_curve.png"):
        assert (out / name).stat().st_size > 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["algo"] == "ppo" and metrics["hyperparameters"]["total_env_steps"] == 1024
    assert metrics["training"]["env_steps"] == 1024  # 4 iterations of 16 copies x 16 steps
    rows = (out / "progress.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 4
    assert metrics["evaluation"]["num_episodes"] == 4
    # The saved policy is a controller: scg-jax eval runs it and writes the same metric keys as for LQR.
    record_path = tmp_path / "eval.json"
    assert main(["eval", *_EVAL_ENV, "--controller", str(out), "--out", str(record_path)]) == 0
    record = json.loads(record_path.read_text())
    assert record["controller"] == "ppo" and record["length"] <= 50 and np.isfinite(record["rmse"])
    # (Same seed, same policy bytes: tests/test_train_run.py and tests/test_rl_common.py, on the library that runs it.)
    assert main(["compare", *_EVAL_ENV, "--controllers", f"lqr,{out}"]) == 0
    assert "ppo" in capsys.readouterr().out


def test_train_refuses_bad_hyperparameters(tmp_path, capsys):
    out = tmp_path / "bad"
    args = ["train", "--system", "cartpole", "--algo", "ppo", "--set", "training.ppo.gama=0.9", "--out", str(out)]
    assert main(args) == 2
    assert "training.ppo.gama: unknown key" in capsys.readouterr().err
    assert not out.exists()


# ----------------------------------------------------------------------------------------------- --gain convention
def test_gain_convention_the_default_lqr_gain_passed_explicitly_stabilises(tmp_path):
    """--gain K means u = u_ref - K (x - x_ref): the default gain, copied from metrics.json into --gain (negative
    values right after the flag, as a user types them), gives the same, stable rollout."""
    common = ["--system", "cartpole", "--num-envs", "16"]
    _, default = _run(tmp_path, "default", *common)
    K = np.asarray(default["gain"])
    np.testing.assert_allclose(K, [[-2.781, -5.150, -43.88, -11.58]], rtol=2e-3)  # the help text's example
    _, explicit = _run(tmp_path, "explicit", *common, "--gain", ",".join(str(float(k)) for k in K.ravel()))
    assert explicit["summary"]["failure_rate"] == default["summary"]["failure_rate"] == 0.0
    np.testing.assert_allclose(explicit["per_copy"]["rmse"], default["per_copy"]["rmse"], rtol=1e-6)
    # The opposite sign on the cart terms (a gain for u = u_ref + K e on x) drops most poles.
    _, flipped = _run(tmp_path, "flipped", *common, "--gain", "1,2,-30,-5")
    assert flipped["summary"]["failure_rate"] > 0.5


def test_gain_help_states_the_sign_convention(capsys):
    assert main(["rollout", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "u = u_ref - K (x - x_ref) (note the minus sign)" in text
    assert "--gain -2.8,-5.2,-43.9,-11.6" in text


# ----------------------------------------------------------------------------------------------- --out checks
@pytest.fixture
def no_work(monkeypatch):
    """Fail the test if a command starts computing: the output location must be refused before."""
    import importlib

    import scg_algorithms.evaluation

    def refuse(*args, **kwargs):
        raise AssertionError("the command started computing before checking --out")

    # scg_jax.rollout is also the name of a function in scg_jax, so fetch the module itself.
    monkeypatch.setattr(importlib.import_module("scg_jax.rollout"), "make_rollout", refuse)
    monkeypatch.setattr(scg_algorithms.evaluation, "evaluate", refuse)


def _bad_out(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    return err[-1]


def test_out_with_a_file_in_the_way_exits_2_before_any_work(tmp_path, capsys, no_work):
    blocker = tmp_path / "blocker"
    blocker.write_text("not a folder")
    line = _bad_out(capsys, ["rollout", "--system", "cartpole", "--out", str(blocker / "run")])
    assert line == (
        f"scg-jax rollout: error: argument --out: cannot write results to '{blocker / 'run'}': '{blocker}' is a "
        "file, not a folder"
    )
    line = _bad_out(capsys, ["eval", "--system", "cartpole", "--controller", "lqr", "--out", str(blocker / "e.json")])
    assert line.endswith(
        f"argument --out: cannot write results to '{blocker / 'e.json'}': '{blocker}' is a file, not a folder"
    )
    line = _bad_out(
        capsys, ["compare", "--system", "cartpole", "--controllers", "lqr", "--out", str(blocker / "c.json")]
    )
    assert "argument --out: cannot write results to" in line and "is a file, not a folder" in line
    folder = tmp_path / "taken.json"
    folder.mkdir()
    line = _bad_out(capsys, ["eval", "--system", "cartpole", "--controller", "lqr", "--out", str(folder)])
    assert line.endswith(f"argument --out: cannot write results to '{folder}': it is a folder, expected a file name")
    assert blocker.read_text() == "not a folder" and not any(folder.iterdir())


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into read-only folders")
def test_out_in_a_read_only_folder_exits_2_before_any_work(tmp_path, capsys, no_work):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        line = _bad_out(capsys, ["rollout", "--system", "cartpole", "--out", str(locked / "a" / "b")])
    finally:
        locked.chmod(0o700)
    assert line.endswith(
        f"cannot write results to '{locked / 'a' / 'b'}': '{locked}' is not writable (Permission denied)"
    )
    assert not any(locked.iterdir())


def test_check_output_dir_accepts_missing_parents_and_creates_nothing(tmp_path):
    from scg_jax.files import check_output_dir, check_output_file

    target = tmp_path / "a" / "b" / "c"
    assert check_output_dir(target) == target and not (tmp_path / "a").exists()
    assert check_output_file(target / "m.json") == target / "m.json" and not (tmp_path / "a").exists()
    assert list(tmp_path.iterdir()) == []  # the write probe is removed


def test_missing_out_parents_are_created_when_results_are_written(tmp_path):
    out = tmp_path / "new" / "nested" / "eval.json"
    assert main(["eval", *_EVAL_ENV, "--controller", "lqr", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["controller"] == "lqr"


def test_check_output_dir_refuses_a_folder_it_cannot_write(tmp_path, monkeypatch):
    """The write probe is the test (os.access ignores read-only mounts and says yes to root); simulate its refusal
    so this runs as root too."""
    import tempfile

    from scg_jax.files import check_output_dir

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(ValueError) as err:
        check_output_dir(tmp_path / "a" / "b")
    assert str(err.value) == (
        f"cannot write results to '{tmp_path / 'a' / 'b'}': '{tmp_path}' is not writable (Permission denied)"
    )
