"""The reproduction (``scg_experiments``, ``scg-jax reproduce``) at the tiny profile: its files, its report and the
claims that hold even at a tiny budget (LQR with the 150 % prior is worse than LQR; RMSE rises with input noise)."""

from __future__ import annotations

import csv
import json
import os

import jax
import numpy as np
import pytest

import scg_cli
import scg_jax
from scg_algorithms.rl.policy import load_policy
from scg_experiments import RESULTS, common, constraint_satisfaction, reproduce, robustness, throughput


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """LQR-only results of the tiny profile, run once for the module."""
    out = tmp_path_factory.mktemp("reproduce")
    sections = reproduce(["control_performance", "robustness", "throughput"], out, "tiny", 1)
    return out, {s.name: s for s in sections}


def test_each_result_writes_data_png_and_its_report_section(tiny):
    """Each section's data and figure, and a report whose claims count is the sum over the sections' claims."""
    out, sections = tiny
    counts = {}
    for name, section in sections.items():
        pngs = [f for f in section.files if f.endswith(".png")]
        assert pngs and any(f.endswith((".csv", ".json")) for f in section.files), name
        assert all((out / name / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for f in pngs)  # whole PNGs
        saved = json.loads((out / name / "section.json").read_text())
        assert saved["wall_s"] == pytest.approx(section.wall_s) and section.wall_s > 0
        assert [c["verdict"] for c in saved["claims"]] == [c.verdict for c in section.claims]
        for c in section.claims:
            counts[c.verdict] = counts.get(c.verdict, 0) + 1
    report = (out / "report.md").read_text()
    assert "Claims: " + ", ".join(f"{n} {v}" for v, n in sorted(counts.items())) + "\n" in report
    assert sum(counts.values()) == sum(len(s.claims) for s in sections.values()) >= 3
    for section in sections.values():
        assert f"## {section.title}" in report and f"wall time {section.wall_s:.1f} s" in report
    assert not list(out.rglob("*.tmp*"))  # every file written whole (atomically)


def test_lqr_with_the_150_percent_prior_is_worse_than_lqr(tiny):
    out, sections = tiny
    scores = {r["method"]: float(r["rmse"]) for r in _rows(out / "control_performance" / "scores.csv")}
    assert scores["lqr_150"] > scores["lqr"] > 0
    (verdict,) = [c for c in sections["control_performance"].claims if "150% prior is worse" in c.text]
    assert verdict.verdict == common.HOLDS and f"{scores['lqr_150']:.4f}" in verdict.measured


def test_noise_sweep_rmse_rises_with_sigma_in_one_evaluation(tiny):
    out, sections = tiny
    rows = _rows(out / "robustness" / "robustness.csv")
    noise = {float(r["value"]): float(r["lqr"]) for r in rows if r["sweep"] == "input_noise_std"}
    lengths = {float(r["value"]): float(r["lqr"]) for r in rows if r["sweep"] == "pole_length"}
    assert sorted(noise) == list(robustness.NOISE_STDS) and sorted(lengths) == list(robustness.POLE_LENGTHS)
    assert noise[4.0] > noise[1.0] > noise[0.0]
    assert lengths[3.0] > 10 * lengths[0.5]  # the nominal-model LQR loses a 6x longer pole
    assert sections["robustness"].claims[0].verdict == common.HOLDS
    # Methods left out of the tiny profile are reported as not run there, never as holding or failing.
    assert all(c.verdict == common.NOT_MEASURED for c in sections["robustness"].claims[1:])


def test_throughput_rows_and_ratio_to_the_original(tiny):
    out, _ = tiny
    rows = _rows(out / "throughput" / "throughput.csv")
    assert [int(r["copies"]) for r in rows] == [1, 16]
    for r in rows:
        assert float(r["steps_per_s"]) > 0
        assert float(r["x_original"]) == pytest.approx(float(r["steps_per_s"]) / 2100.0)


def test_a_missing_method_is_reported_as_not_available():
    lengths = {"lqr": np.ones(9), "ppo": np.ones(9)}
    noise = {"lqr": np.linspace(0.1, 1, 6), "ppo": np.linspace(0.1, 1, 6)}
    claims = robustness.claims(lengths, noise, {"rap", "ppo_dr"}, "quick")
    rap = next(c for c in claims if c.text.startswith("RAP is more robust to input noise"))
    assert rap.verdict == common.UNAVAILABLE and rap.measured == "method rap not available in this build"
    lqr = next(c for c in claims if c.text.startswith("LQR is no less resilient"))
    assert lqr.verdict == common.HOLDS  # equal curves: within 1.2x


def test_availability_follows_the_registry():
    """Every registered learner is part of this build (tests/test_train_run.py: the registry drives the list)."""
    from scg_algorithms.learners import LEARNERS

    assert common.train_algorithms() == tuple(LEARNERS)
    assert common.learner_available("ppo") and not common.learner_available("no_such_learner")
    assert common.safety_filter("no_such_filter") is None
    assert common.safety_filter("learned_cbf") == "scg_algorithms.safety_filters.learned_cbf:make_learned_cbf"


def test_cli_rejects_unknown_results_and_profiles(tmp_path, capsys):
    assert scg_cli.main(["reproduce", "no_such_result", "--out", str(tmp_path)]) == 2
    assert "allowed values are " + ", ".join(RESULTS) in capsys.readouterr().err
    assert scg_cli.main(["reproduce", "--profile", "huge", "--out", str(tmp_path)]) == 2
    assert not list(tmp_path.iterdir())
    with pytest.raises(ValueError, match="seeds: must be a positive integer"):
        reproduce(["throughput"], tmp_path, "tiny", 0)


def test_config_hash_names_what_determines_a_cached_artefact():
    assert common.config_hash("ppo", "env: a", 0, 10) == common.config_hash("ppo", "env: a", 0, 10)
    assert len({common.config_hash("ppo", "env: a", s, 10) for s in range(3)}) == 3
    assert common.config_hash("ppo", "env: a", 0, 10) != common.config_hash("ppo", "env: a", 0, 11)


@pytest.mark.slow
def test_learning_and_constraint_results_at_the_tiny_budget_and_the_cache(tmp_path):
    """A tiny PPO learning curve (cached: a rerun evaluates nothing new) and the impossible tracking of the linear
    MPC with the 150 % prior, which leaves the box as in the original."""
    (learning, constraint) = reproduce(["learning_efficiency", "constraint_satisfaction"], tmp_path, "tiny", 1)
    rows = _rows(tmp_path / "learning_efficiency" / "learning_curves.csv")
    assert [int(r["env_steps"]) for r in rows] == [1024, 2048]
    assert [float(r["data_seconds"]) for r in rows] == pytest.approx([1024 * 0.02, 2048 * 0.02])
    (curve_file,) = list((tmp_path / "cache").glob("ppo-curve-*/curve.json"))
    cached = curve_file.stat().st_mtime_ns
    reproduce(["learning_efficiency"], tmp_path, "tiny", 1)
    assert curve_file.stat().st_mtime_ns == cached
    assert json.loads(curve_file.read_text())["rows"][0]["rmse"] == pytest.approx(float(rows[0]["rmse"]))

    box = next(c for c in constraint.claims if c.text.endswith("linear MPC with the 150% prior violates the box"))
    assert box.verdict == common.HOLDS
    paths = json.loads((tmp_path / "constraint_satisfaction" / "impossible_paths.json").read_text())
    path = np.asarray(paths["linear_mpc"])
    assert path.shape == (51, 2) and (path[:, 1].max() > 0.9 or np.abs(path[:, 0]).max() > 0.4)


# Budgets of one iteration of 256 env steps (16 copies x 16 steps) for the methods merged after the results were
# written, so their training, loading as a controller and evaluation run inside the results. CI trains one method
# of each family (RAP, whose population covers RARL's code; PPO-Lagrangian's learning curve and the learned CBF's
# loop, which cover the constraint result's code for safety-layer PPO too) in about a minute of CPU per test;
# SCG_EXPERIMENT_METHODS=1 adds RARL and safety-layer PPO (its curve and the impossible task), about 3.5 min more.
SMALL = ["num_envs=16", "rollout_length=16", "num_minibatches=2", "num_epochs=1"]
SAFE_PPO_SMALL = ["constraint_epochs=1", "constraint_steps_per_epoch=256", "constraint_eval_steps=256"]
EVERY_METHOD = os.environ.get("SCG_EXPERIMENT_METHODS") == "1"


def _small(algo, *extra):
    return [f"training.{algo}.{kv}" for kv in (*SMALL, *extra)]


def test_every_merged_method_builds_its_learner_from_the_results_configs():
    """The configs the results train RARL, RAP, PPO^DR, safety-layer PPO and PPO-Lagrangian with are accepted by
    those learners (options, adversary channel, constraint rows), without training anything."""
    from scg_algorithms.base import parse_options
    from scg_algorithms.rl.policy import algorithm_module

    def learner(algo, cfg):
        env, _ = scg_jax.make_from_config(cfg)
        config = parse_options(algorithm_module(algo, "Config"), cfg.training.get(algo), f"training.{algo}")
        return algorithm_module(algo, "make_learner")(config, env), env

    base = scg_jax.load_config(common.CONFIG_DIR / "cartpole.yaml").to_dict()
    for method, (algo, channel) in {"rarl": ("rarl", "dynamics"), "rap": ("rap", "action")}.items():
        name, cfg = robustness.method_config(method)
        built, env = learner(name, cfg)
        assert name == algo and env.adversary_channel == channel and float(cfg.env.adversary.scale) == 0.1
        assert cfg.to_dict()["env"] == {**base["env"], "adversary": cfg.to_dict()["env"]["adversary"]}
        assert built.steps_per_iteration == 512 * 32
    assert robustness.method_config("rap")[1].training["rap"]["num_adversaries"] == 2
    name, cfg = robustness.method_config("ppo_dr", ["training.ppo.num_envs=16"])
    assert name == "ppo" and cfg.env.physics_randomization["pole_half_length"].low == pytest.approx(0.1)
    assert cfg.training["ppo"]["num_envs"] == 16 and learner("ppo", cfg)[0].steps_per_iteration == 16 * 32
    cfg = scg_jax.load_config(common.CONFIG_DIR / "cartpole_constraint.yaml")
    assert learner("safe_ppo", cfg)[0].config.constraint_slack == (0.05, 0.07, 0.05, 0.07)
    assert learner("ppo_lagrangian", cfg)[0].config.cost_limit == pytest.approx(0.01)
    assert learner("safe_ppo", scg_jax.load_config(common.CONFIG_DIR / "quadrotor_impossible.yaml"))[0]


@pytest.mark.slow
def test_robust_methods_train_load_and_sweep_inside_the_result(tmp_path, monkeypatch):
    """RAP (and RARL) trained by train_run on the result's plant with its own adversaries, loaded as controllers (on
    the env without an adversary input) and swept: the result's RMSE per grid value is the harness's on the saved
    policy, and the cached run holds its budget and adversary."""
    steps = {"rap": 256, **({"rarl": 256} if EVERY_METHOD else {})}
    overrides = {m: _small(m) for m in steps}
    monkeypatch.setitem(robustness.PROFILES, "tiny", {"episodes": 1, "rl_steps": steps, "gp_mpc": None,
                                                      "overrides": overrides})  # fmt: skip
    (section,) = reproduce(["robustness"], tmp_path, "tiny", 1)
    rows = _rows(tmp_path / "robustness" / "robustness.csv")
    assert set(rows[0]) == {"sweep", "value", "lqr", *steps}
    _, env, params = common.load("cartpole", robustness.EVAL)
    for algo, channel in (("rap", "action"), ("rarl", "dynamics"))[: len(steps)]:
        (run,) = [p for p in (tmp_path / "cache").glob(f"{algo}-*") if p.is_dir()]
        metrics = json.loads((run / "metrics.json").read_text())
        assert metrics["algo"] == algo and metrics["training"]["env_steps"] == 256
        assert metrics["evaluation"]["num_episodes"] == 2
        adversary = scg_jax.load_config(run / "config.yaml").env.adversary
        assert (adversary.channel, adversary.scale) == (channel, pytest.approx(0.1))
        by_length, by_noise = robustness.sweep(env, params, load_policy(run, env, params), jax.random.key(6161), 1)
        np.testing.assert_allclose([float(r[algo]) for r in rows], [*by_length, *by_noise], rtol=1e-5)
        assert np.all(np.isfinite(by_length)) and np.all(by_noise > 0)
    assert all("failed" not in c.measured for c in section.claims) and not section.notes[:-1]


@pytest.mark.slow
def test_safe_rl_methods_and_learned_cbf_run_inside_the_constraint_result(tmp_path, monkeypatch):
    """PPO-Lagrangian's (and safety-layer PPO's) learning curve and the learned CBF's loop inside the constraint
    result, each at a budget of one iteration or episode: the curve's point is at 256 env steps, 5.12 s of data
    (50 Hz); the CBF's data is its copies' steps (8 x 250 steps of 0.02 s per episode); every one is measured."""
    safe_ppo = {"safe_ppo": [256]} if EVERY_METHOD else {}
    budget = {
        "episodes": 1,
        "rl_points": {"ppo_lagrangian": [256], **safe_ppo},
        "gp_mpc": None,
        "impossible": ["safe_ppo"] if EVERY_METHOD else [],
        "impossible_rl_steps": 256,
        "overrides": {"safe_ppo": _small("safe_ppo", *SAFE_PPO_SMALL), "ppo_lagrangian": _small("ppo_lagrangian")},
        "cbf": {"num_episodes": 1, "num_copies": 8, "train_iterations": 2, "batch_size": 32, "eval_episodes": 4},
    }
    monkeypatch.setitem(constraint_satisfaction.PROFILES, "tiny", budget)
    (section,) = reproduce(["constraint_satisfaction"], tmp_path, "tiny", 1)
    rows = _rows(tmp_path / "constraint_satisfaction" / "violations.csv")
    curves = [r for r in rows if r["method"] != "learned_cbf"]
    assert sorted(r["method"] for r in curves) == sorted(budget["rl_points"])
    for r in curves:
        assert int(r["env_steps"]) == 256 and float(r["data_seconds"]) == pytest.approx(256 * 0.02)
        fraction, failure = float(r["violation_fraction"]), float(r["failure_rate"])
        assert 0.0 <= fraction <= 1.0 and failure == (1.0 if fraction > 0 else 0.0)  # one episode
    cbf = [r for r in rows if r["method"] == "learned_cbf"]
    assert [float(r["data_seconds"]) for r in cbf] == pytest.approx([0.0, 8 * 250 * 0.02])
    assert all(0.0 <= float(r["violation_fraction"]) <= 1.0 for r in cbf)
    (note,) = [n for n in section.notes if n.startswith("learned_cbf: ")]
    assert "after 1 blending episodes, certifying the 150%-prior LQR: violation fraction " in note
    if EVERY_METHOD:
        paths = json.loads((tmp_path / "constraint_satisfaction" / "impossible_paths.json").read_text())
        outside = constraint_satisfaction.outside(np.asarray(paths["safe_ppo"]))
        (claim,) = [c for c in section.claims if c.text.startswith("Impossible tracking: safety-layer PPO")]
        assert claim.measured == f"{outside} of 51 points outside"
        assert claim.verdict == (common.HOLDS if outside > 0 else common.FAILS)
    assert not any("failed" in n for n in section.notes)


def test_a_failing_method_or_result_is_reported_and_the_report_written_whole(tmp_path, monkeypatch):
    """A method whose training raises makes its claims "not measured" with the error while the other methods run;
    a result that raises still gets its section, and the report is written with every section."""

    def broken(ctx, algo, *args, **kwargs):
        raise RuntimeError(f"{algo} exploded")

    monkeypatch.setattr(common, "train_policy", broken)
    # The sweep itself is covered above; here each controller's sweep is a rising curve, so the LQR claim holds.
    monkeypatch.setattr(robustness, "sweep", lambda *args: (np.linspace(0.1, 1, 9), np.linspace(0.1, 1, 6)))
    monkeypatch.setitem(robustness.PROFILES, "tiny", {"episodes": 1, "rl_steps": {"rap": 256}, "gp_mpc": None})

    def raises(ctx):
        raise ValueError("no throughput today\nsecond line")

    monkeypatch.setattr(throughput, "run", raises)
    sections = reproduce(["robustness", "throughput"], tmp_path, "tiny", 1)
    rob = sections[0]
    assert rob.claims[0].verdict == common.HOLDS  # LQR still measured
    rap = next(c for c in rob.claims if c.text.startswith("RAP is more robust to input noise"))
    assert rap.verdict == common.NOT_MEASURED and rap.measured == "not measured: rap failed: RuntimeError: rap exploded"
    assert sections[1].claims[0].verdict == common.NOT_MEASURED
    assert sections[1].claims[0].measured == "not measured: ValueError: no throughput today"
    report = (tmp_path / "report.md").read_text()
    assert "rap failed: RuntimeError: rap exploded" in report and "## " + throughput.TITLE in report
    assert not list(tmp_path.rglob("*.tmp*"))
