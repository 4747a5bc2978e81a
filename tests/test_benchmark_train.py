"""benchmarks/train.py's pure parts: the brax argument tables, the chunked race to the threshold, the table's ratios
and the page's sections. No learning run here (the script itself is the measurement)."""

import dataclasses
import importlib.util
import inspect
import re
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCHMARKS))  # the script imports benchmarks/machine.py by its plain name
    try:
        spec = importlib.util.spec_from_file_location("benchmark_train", BENCHMARKS / "train.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCHMARKS))
    return module


def _fields(config_class) -> set:
    return {field.name for field in dataclasses.fields(config_class)}


def test_brax_tables_map_fields_of_our_configs_to_arguments_of_brax_trainers(bench):
    from brax.training.agents.ppo import train as brax_ppo
    from brax.training.agents.sac import train as brax_sac

    from scg_algorithms.ppo import Config as PPOConfig
    from scg_algorithms.sac import Config as SACConfig

    for table, config_class, train in ((bench._BRAX_PPO, PPOConfig, brax_ppo.train),
                                       (bench._BRAX_SAC, SACConfig, brax_sac.train)):  # fmt: skip
        assert set(table.values()) <= _fields(config_class)
        assert set(table) <= set(inspect.signature(train).parameters)
    # SAC's table covers what the task asks to match (copies, batch, learning rate, discount, tau, replay size).
    assert {"num_envs", "batch_size", "learning_rate", "discounting", "tau", "max_replay_size"} <= set(bench._BRAX_SAC)


def test_brax_ppo_arguments_carry_our_values(bench):
    from brax.training.agents.ppo import train as brax_ppo

    from scg_algorithms.base import parse_options
    from scg_algorithms.ppo import Config

    options = {"num_envs": 64, "num_minibatches": 4, "vf_coef": 0.7, "normalize_advantages": False,
               "value_clip_eps": 0.2, "actor_hidden": [32, 16]}  # fmt: skip
    arguments = bench.brax_arguments("ppo", parse_options(Config, options, "training.ppo"))
    assert set(arguments) <= set(inspect.signature(brax_ppo.train).parameters)
    assert (arguments["batch_size"], arguments["vf_loss_coefficient"], arguments["normalize_advantage"]) == (
        16, 0.7, False,
    )  # fmt: skip
    assert arguments["clipping_epsilon_value"] == 0.2 and arguments["bootstrap_on_timeout"] is True
    assert arguments["network_factory"].keywords["policy_hidden_layer_sizes"] == (32, 16)
    # Our 0 (no value clip) is brax's None.
    assert bench.brax_arguments("ppo", parse_options(Config, {}, "training.ppo"))["clipping_epsilon_value"] is None


def test_brax_sac_arguments_carry_our_values(bench):
    from brax.training.agents.sac import train as brax_sac

    from scg_algorithms.base import parse_options
    from scg_algorithms.sac import Config

    options = {"num_envs": 32, "utd": 0.5, "batch_size": 128, "actor_lr": 3e-4, "critic_lr": 3e-4, "gamma": 0.97,
               "hidden_sizes": [32, 16]}  # fmt: skip
    config = parse_options(Config, options, "training.sac")
    arguments = bench.brax_arguments("sac", config)
    assert set(arguments) <= set(inspect.signature(brax_sac.train).parameters)
    assert (arguments["num_envs"], arguments["batch_size"], arguments["learning_rate"], arguments["discounting"]) == (
        32, 128, 3e-4, 0.97,
    )  # fmt: skip
    # 0.5 gradient steps per transition, brax's per step of the 32 copies: 16.
    assert arguments["grad_updates_per_step"] == 16
    assert arguments["network_factory"].keywords["hidden_layer_sizes"] == (32, 16)

    with pytest.raises(SystemExit, match=r"critic_lr \(0.001\) must equal training.sac.actor_lr \(0.0003\)"):
        bench.brax_arguments("sac", dataclasses.replace(config, critic_lr=1e-3))
    # 0.25 * 6 copies = 1.5 gradient steps per step of the copies (3 per iteration of 2 steps): not brax's integer.
    odd = parse_options(Config, {"num_envs": 6, "rollout_steps": 2, "utd": 0.25}, "training.sac")
    with pytest.raises(SystemExit, match=r"utd \* num_envs .* got 0.25 \* 6 = 1.5"):
        bench.brax_arguments("sac", odd)


class _FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def _race(bench, rmse_at, *, num_iterations=1000, warmup=0, max_s=1e9, chunk_s=1.25, compile_s=2.0):
    """The race on a fake learner: an iteration takes 0.125 s (the first chunk also ``compile_s``), an evaluation 5 s
    (not counted); the state is the iteration count and the RMSE ``rmse_at(iterations)``. Times are binary
    fractions, so the clock's sums are exact."""
    clock = _FakeClock()
    chunks = []

    def run_chunk(state, n):
        clock.now += 0.125 * n + (compile_s if not chunks else 0.0)
        chunks.append(n)
        return state + n

    def evaluate_state(state):
        clock.now += 5.0
        return {"rmse": rmse_at(state), "crash_rate": 0.0}

    result = bench.race_to_threshold(
        lambda: 0, run_chunk, evaluate_state, num_iterations=num_iterations, steps_per_iteration=64,
        warmup_iterations=warmup, threshold=0.1, max_s=max_s, chunk_s=chunk_s, clock=clock,
    )  # fmt: skip
    return result, chunks


def test_race_stops_at_the_threshold_with_evaluation_excluded(bench):
    # RMSE 1 / iterations: at most 0.1 from iteration 10 on.
    result, chunks = _race(bench, lambda it: 1.0 / it, chunk_s=0.625)
    # The first chunk takes 2.125 s with the compile, so the second is 1 again; then doubling, capped at chunk_s /
    # 0.125 s = 5 iterations: 1, 1, 2, 4, 5 reach 13 >= 10.
    assert chunks == [1, 1, 2, 4, 5]
    assert result["reached"] and result["env_steps"] == 13 * 64
    assert result["time_s"] == 2.0 + 0.125 * 13  # five evaluations of 5 s not counted
    assert [p["env_steps"] for p in result["curve"]] == [64, 128, 256, 512, 832]


def test_race_runs_the_warmup_in_one_chunk_and_gives_up_at_the_limits(bench):
    # Never reaches the threshold: the budget ends it (the last chunk shortened to fit), not reached.
    result, chunks = _race(bench, lambda it: 1.0, num_iterations=40, warmup=12, compile_s=0.0)
    assert chunks == [12, 10, 10, 8] and not result["reached"] and result["env_steps"] == 40 * 64
    # The time limit: stops at the first evaluation past max_s (2.125 s, 2.25 s, then 2.5 s > 2.3 s).
    result, chunks = _race(bench, lambda it: 1.0, max_s=2.3)
    assert chunks == [1, 1, 2] and not result["reached"]
    assert result["time_s"] == 2.5 and result["env_steps"] == 4 * 64


def test_ratio_rows_pair_each_learner_with_its_brax_rival(bench):
    def run(time_s, reached):
        return {"reached": reached, "time_s": time_s, "env_steps": 1000, "curve": []}

    ours = {"ppo": run(2.0, True), "sac": run(4.0, True), "ddpg": run(30.0, False), "td3": run(8.0, True)}
    ours["ddpg"]["curve"] = [{"rmse": 0.91}, {"rmse": 0.7912}, {"rmse": 0.83}]
    brax = {"ppo": run(10.0, True), "sac": run(20.0, False)}
    rows = {row["algo"]: row for row in bench.ttq_rows(ours, brax)}
    assert {algo: row["brax_algo"] for algo, row in rows.items()} == {
        "ppo": "ppo", "sac": "sac", "ddpg": "sac", "td3": "sac",
    }  # fmt: skip
    assert (rows["ppo"]["brax_over_ours"], rows["ppo"]["relation"]) == (5.0, "=")
    assert (rows["sac"]["brax_over_ours"], rows["sac"]["relation"]) == (5.0, ">=")  # brax stopped unreached at 20 s
    assert (rows["ddpg"]["brax_over_ours"], rows["ddpg"]["relation"]) == (None, "")
    cells = {cells[0]: cells for cells in bench.ttq_table_rows(list(rows.values()))}
    assert cells["td3"][-1] == ">= 2.50" and cells["ppo"][-1] == "5.00"
    assert cells["ddpg"][1:3] == ["0 / 1", "not reached (30.0; best RMSE 0.791)"]
    # Without brax's SAC (e.g. --no-brax), its rows have no rival time.
    (row,) = bench.ttq_rows({"sac": run(4.0, True)}, {})
    assert row["brax"] is None and row["brax_over_ours"] is None


def test_the_median_of_seeds_orders_unreached_runs_last_and_the_ratio_is_of_the_medians(bench):
    def run(time_s, reached):
        return {"reached": reached, "time_s": time_s, "env_steps": int(1000 * time_s), "curve": [{"rmse": 0.5}]}

    # An unreached seed that stopped early (its budget ended at 3 s) is still slower than one that reached at 9 s.
    ours = bench.median_run([run(4.0, True), run(3.0, False), run(9.0, True)])
    assert (ours["time_s"], ours["reached"], ours["env_steps"]) == (9.0, True, 9000) and len(ours["runs"]) == 3
    brax = bench.median_run([run(20.0, True), run(25.0, False), run(30.0, False)])  # most did not reach: a bound
    assert (brax["time_s"], brax["reached"]) == (25.0, False)
    assert bench.median_run([run(5.0, True), run(1.0, True), run(2.0, True), run(8.0, True)])["time_s"] == 5.0
    (row,) = bench.ttq_rows({"ppo": ours}, {"ppo": brax})
    assert row["brax_over_ours"] == 25.0 / 9.0 and row["relation"] == ">="
    (cells,) = bench.ttq_table_rows([row])
    assert cells[1:3] == ["2 / 3", "9.0"] and cells[5] == "1 / 3" and cells[-1] == ">= 2.78"
    assert bench.seed_times(ours) == "4.0, 3.0*, 9.0 s"
    record = {
        **bench.run_record("train"), "overrides": [],
        "time_to_threshold": {"threshold_rmse": 0.073, "rmse_factor": 1.5, "lqr_rmse": 0.0487, "max_crash_rate": 0.0,
                              "seeds": 3, "ours": {"ppo": ours}, "brax": {"ppo": brax}},
    }  # fmt: skip
    text = bench.section(record)
    assert "the median of seeds 0-2, ours and brax's alike" in text
    assert "- ppo per seed: 4.0, 3.0*, 9.0 s; brax PPO: 20.0, 25.0*, 30.0* s" in text


def test_page_sections_are_replaced_or_added_never_the_others(bench):
    old_format = "# Training speed\n\nMeasured once.\n\n| a |\n|---|\n| 1 |\n"
    page = bench.merge_section(old_format, "`configs/a.yaml`", "A1")
    page = bench.merge_section(page, "`configs/b.yaml`", "B1\n\n| x |")
    page = bench.merge_section(page, "`configs/a.yaml`", "A2")
    assert page == (
        f"# Training speed\n\nGenerated by `benchmarks/train.py`; do not edit by hand. {bench.PAGE_NOTE}\n\n"
        "## `configs/a.yaml`\n\nA2\n\n## `configs/b.yaml`\n\nB1\n\n| x |\n"
    )
    assert bench.merge_section(page, "`configs/b.yaml`", "B1\n\n| x |") == page  # same run again: same page


def test_a_rerun_with_a_warm_compilation_cache_writes_its_own_section(bench, tmp_path, monkeypatch):
    updates = {}
    monkeypatch.setattr(bench.jax.config, "update", lambda name, value: updates.__setitem__(name, value))
    folder = tmp_path / "cache"
    cold = bench.use_compile_cache(folder)
    assert cold == {"dir": str(folder), "entries_at_start": 0}
    assert updates == {"jax_compilation_cache_dir": str(folder), "jax_persistent_cache_min_compile_time_secs": 0.0}
    for name in ("a-cache", "b-cache"):
        (folder / name).write_bytes(b"x")
    warm = bench.use_compile_cache(folder)
    assert warm["entries_at_start"] == 2 and bench.use_compile_cache(None) is None
    config = Path("configs/cartpole_stabilization.yaml")
    assert bench.section_heading(config, None) == bench.section_heading(config, cold) == f"`{config.as_posix()}`"
    assert bench.section_heading(config, warm) == f"`{config.as_posix()}`, warm compilation cache"
    heading = bench.section_heading(config, None, Path("/tmp/own_starts.npy"))
    assert heading == f"`{config.as_posix()}`, starts `own_starts.npy`"
    record = {"overrides": [], "compile_cache": warm}
    monkeypatch.setattr(bench, "machine_line", lambda record: "Measured here.")
    assert "cache held 2 entries at the start, for ours and brax's alike" in bench.section(record)
    assert "cache held" not in bench.section({**record, "compile_cache": cold})


def test_sac_grid_points_parse_and_bad_ones_name_the_option(bench):
    import argparse

    assert bench.parse_grid_point("64:0.5") == {"num_envs": 64, "utd": 0.5}
    assert bench.parse_grid_point("16:2:128") == {"num_envs": 16, "utd": 2.0, "batch_size": 128}
    for bad in ("64", "64:x", "1:2:3:4", "64:0.5:1.5"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"--sac-grid: expected COPIES:UTD\[:BATCH\]"):
            bench.parse_grid_point(bad)


def test_sac_grid_section_ranks_by_seeds_reached_then_median_time(bench):
    def row(num_envs, runs):
        times = sorted(t for t, _ in runs)
        return {
            "num_envs": num_envs, "utd": 1.0, "batch_size": 256, "grad_steps_per_iteration": num_envs,
            "runs": [{"reached": r, "time_s": t, "env_steps": 20_000} for t, r in runs],
            "reached": sum(r for _, r in runs), "median_time_s": times[len(times) // 2],
        }  # fmt: skip

    record = {
        **bench.run_record("train"), "overrides": [],
        "sac_grid": {
            "rmse_factor": 1.5, "threshold_rmse": 0.073, "lqr_rmse": 0.0487, "seeds": 3, "max_seconds": 120.0,
            "total_env_steps": 150_000,
            "rows": [row(16, [(5.0, True), (30.0, False), (6.0, True)]),
                     row(64, [(9.0, True), (8.0, True), (10.0, True)]),
                     row(256, [(4.0, True), (50.0, False), (60.0, False)])],
        },
    }  # fmt: skip
    text = bench.grid_section(record)
    table = [line for line in text.splitlines() if line.startswith("| ") and line[2].isdigit()]
    # All three seeds first, then two of three (median 6 s), then one of three, whatever its fastest seed.
    assert [line.split(" | ")[0] for line in table] == ["| 64", "| 16", "| 256"]
    assert "| 3 / 3 | 9.0 |" in table[0] and "30.0* s (20 k)" in table[1]


def test_the_threshold_is_a_factor_of_lqrs_rmse_or_a_given_target_and_the_labels_say_which(bench, monkeypatch):
    class Fake:
        summary = {"rmse": 0.84, "crash_rate": 0.125}

    monkeypatch.setattr(bench, "make_lqr", lambda env, params: None)
    monkeypatch.setattr(bench, "evaluate", lambda *args, **kwargs: Fake())
    lqr = {"lqr_rmse": 0.84, "lqr_crash_rate": 0.125}
    relative = bench.lqr_threshold(None, None, None, 4, 1.5)
    assert relative == {**lqr, "threshold_rmse": pytest.approx(1.26), "rmse_factor": 1.5, "max_crash_rate": 0.0}
    assert bench.threshold_label(relative) == "1.5x LQR's RMSE (1.2600; LQR 0.8400), no crash"
    target = bench.lqr_threshold(None, None, None, 4, 1.5, target=bench.ORIGINAL_PPO_RMSE)
    assert target == {**lqr, "threshold_rmse": 0.619, "rmse_factor": None, "max_crash_rate": 0.125}
    assert bench.threshold_label(target) == "RMSE 0.619 with at most LQR's crash rate (0.8400, 12.5%)"
    record = {**bench.run_record("train"), "overrides": [], "time_to_threshold": {**target, "ours": {}, "brax": {}}}
    assert "Time to RMSE 0.619 with at most LQR's crash rate (0.8400, 12.5%): training" in bench.section(record)
    # A crash rate at the allowance meets the bar; above it, or an RMSE above the target, does not.
    assert bench._meets({"rmse": 0.6, "crash_rate": 0.125}, 0.619, 0.125)
    assert not bench._meets({"rmse": 0.6, "crash_rate": 0.15625}, 0.619, 0.125)
    assert not bench._meets({"rmse": 0.62, "crash_rate": 0.0}, 0.619, 0.125)
    assert not bench._meets({"rmse": 0.6, "crash_rate": 0.03125}, 0.619)  # the default bar: no crash
    with pytest.raises(SystemExit):
        bench.main(["--target-rmse", "-1"])


def _save_mlp(path, activation, layers):
    arrays = {}
    for i, (weight, bias) in enumerate(layers):
        arrays[f"weight_{i}"], arrays[f"bias_{i}"] = np.asarray(weight), np.asarray(bias)
    np.savez(path, activation=activation, **arrays)
    return path


def test_a_reference_policy_file_is_torchs_mlp_with_its_activation_and_a_linear_last_layer(bench, tmp_path):
    W0, b0 = np.array([[1.0, -2.0], [0.5, 1.0], [-1.0, 0.0]]), np.array([0.1, -3.0, 0.2])
    W1, b1 = np.array([[2.0, -1.0, 1.0]]), np.array([0.5])
    obs = np.array([0.3, 0.4])
    # Worked by hand: W0 obs + b0 = (-0.4, -2.45, -0.1); leaky_relu (slope 0.01) gives (-0.004, -0.0245, -0.001);
    # W1 h + b1 = -0.008 + 0.0245 - 0.001 + 0.5 = 0.5155. With tanh the same layers give tanh's values.
    name, policy = bench.load_reference_policy(_save_mlp(tmp_path / "orig.npz", "leaky_relu", [(W0, b0), (W1, b1)]))
    assert name == "orig"
    assert float(policy(obs)[0]) == pytest.approx(0.5155, abs=1e-6)
    _, policy = bench.load_reference_policy(_save_mlp(tmp_path / "tanh.npz", "tanh", [(W0, b0), (W1, b1)]))
    assert float(policy(obs)[0]) == pytest.approx(float((W1 @ np.tanh(W0 @ obs + b0))[0] + b1[0]), abs=1e-6)
    bad = {
        "activation must be one of": ("sigmoid", [(W0, b0), (W1, b1)]),
        "weight_1 takes 3 inputs, layer 0 gives 2": ("relu", [(W0[:2], b0[:2]), (W1, b1)]),
        "weight_0 must be (out, in) with bias_0 (out,)": ("relu", [(W0, b0[:2])]),
    }
    for message, (activation, layers) in bad.items():
        with pytest.raises(SystemExit, match=r"--target-policy: .*" + re.escape(message)):
            bench.load_reference_policy(_save_mlp(tmp_path / "bad.npz", activation, layers))
    with pytest.raises(SystemExit, match="--target-policy: .*the MLP has 2 inputs, the env's policy needs 4"):
        bench.load_reference_policy(tmp_path / "orig.npz", obs_size=4, action_size=1)
    with pytest.raises(SystemExit, match="--target-policy: .*the MLP has 1 outputs, the env's policy needs 2"):
        bench.load_reference_policy(tmp_path / "orig.npz", obs_size=2, action_size=2)
    with pytest.raises(SystemExit, match="--target-policy: cannot read"):
        bench.load_reference_policy(tmp_path / "missing.npz")
    with pytest.raises(SystemExit):
        bench.main(["--target-rmse", "0.6", "--target-policy", str(tmp_path / "orig.npz")])


def test_a_reference_policy_holding_lqrs_gain_sets_lqrs_rmse_as_the_bar(bench, tmp_path):
    from scg_jax.config import load_config, make_from_config

    env, params = make_from_config(load_config(ROOT / "configs" / "cartpole_stabilization.yaml"))
    K = np.asarray(bench.make_lqr(env, params).info["K"][0])
    goal, force_max = np.asarray(params.goal), float(params.physics.force_max)
    # One linear layer: the normalised action a = (u_eq - K (x - goal)) / force_max, u_eq = 0 on the cart-pole.
    lqr_file = _save_mlp(tmp_path / "lqr_gain.npz", "relu", [(-K / force_max, K @ goal / force_max)])
    weak_file = _save_mlp(tmp_path / "weak.npz", "relu", [(-0.5 * K / force_max, 0.5 * K @ goal / force_max)])
    bar = bench.policy_threshold(env, params, bench.jax.random.key(1), 4, [weak_file, lqr_file])
    assert bar["threshold_rmse"] == pytest.approx(bar["lqr_rmse"], rel=1e-4)
    assert bar["max_crash_rate"] == bar["lqr_crash_rate"] == 0.0
    assert [Path(score["policy"]).name for score in bar["reference_policies"]] == ["weak.npz", "lqr_gain.npz"]
    assert bar["reference_policies"][0]["rmse"] > bar["threshold_rmse"]  # the lowest RMSE is the bar
    label = bench.threshold_label(bar)
    assert label.startswith(f"RMSE {bar['threshold_rmse']:.4f} with at most 0.0% crashes (the best of 2 reference")
    record = {**bench.run_record("train"), "overrides": [], "time_to_threshold": {**bar, "ours": {}, "brax": {}}}
    assert f"- reference policy `lqr_gain.npz`: RMSE {bar['threshold_rmse']:.4f}, crash rate 0.0%" in bench.section(
        record
    )


def test_eval_starts_run_one_episode_from_each_given_state_whatever_the_key_draws(bench, tmp_path):
    from scg_jax.config import load_config, make_from_config

    env, params = make_from_config(load_config(ROOT / "configs" / "cartpole_stabilization.yaml"))
    starts = np.array([[0.1, 0.0, 0.05, 0.0], [-0.2, 0.1, -0.03, 0.2], [0.0, -0.3, 0.1, -0.1]], np.float32)
    batched, n, is_batched = bench.evaluation_params(env, params, starts)
    assert (n, is_batched) == (3, True) and bench.evaluation_params(env, params, 32)[1:] == (32, False)
    lqr = bench.make_lqr(env, params)
    runs = [bench.evaluate(env, batched, lqr, bench.jax.random.key(seed), n, batched_params=True, measure_time=False)
            for seed in (0, 1)]  # fmt: skip
    for run in runs:  # the key still draws the config's noise, not the start
        np.testing.assert_array_equal(np.asarray(run.trajectory["x"])[0], starts)
    assert bench._evaluate_controller(env, params, lqr, bench.jax.random.key(0), starts)["rmse"] == pytest.approx(
        float(np.mean(runs[0].per_episode["rmse"]))
    )
    for bad in (starts[:, :3], starts[:0], np.full((2, 4), np.nan)):
        with pytest.raises(SystemExit, match=r"--eval-starts: expected finite initial states of shape \(N, 4\)"):
            bench.evaluation_params(env, params, bad)
    record = {**bench.run_record("train"), "overrides": [], "eval_starts": str(tmp_path / "own_starts.npy")}
    record["time_to_threshold"] = {"lqr_rmse": 0.1, "threshold_rmse": 0.15, "rmse_factor": 1.5, "ours": {}, "brax": {}}
    assert "Every evaluation runs one episode from each start in `own_starts.npy`." in bench.section(record)
    np.save(tmp_path / "bad.npy", starts)
    with pytest.raises(SystemExit, match="--eval-starts: cannot read"):
        bench.main(["--eval-starts", str(tmp_path / "missing.npy"), "--no-split", "--algos", "ppo", "--batches", "8",
                    "--iterations", "1", "--repeats", "1", "--json", str(tmp_path / "t.json"),
                    "--markdown", str(tmp_path / "t.md"), "--ttq-algos", "ppo", "--no-brax"])  # fmt: skip
