"""``scg-jax train``: a folder holding a run, --resume / --overwrite, Ctrl-C, progress in a log, extending a run."""

import io
import json
import re
import shlex
import sys
import time

import numpy as np
import pytest

import scg_algorithms.rl.training as training
from scg_algorithms.progress import Progress
from scg_cli import main
from tests.rl_helpers import set_options

# 1-s episodes; 2 iterations of 16 copies x 16 steps (512 env steps).
_ENV = ["--config", "configs/cartpole_stabilization.yaml", "--set", "env.episode_len_sec=1"]
_TINY_PPO = set_options(
    "training.ppo", total_env_steps=512, num_envs=16, rollout_length=16, num_minibatches=2, lr_decay="false"
)


def _fake_run(folder, algo="ppo"):
    folder.mkdir()
    (folder / "checkpoint.json").write_text(json.dumps({"algo": algo, "iteration": 1}))
    (folder / "progress.csv").write_text("iteration\n1\n")


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    return err[-1]


def test_a_folder_holding_a_run_is_refused_naming_the_flags(tmp_path, capsys):
    out = tmp_path / "run"
    _fake_run(out)
    before = (out / "checkpoint.json").read_text()
    assert main(["train", *_ENV, *_TINY_PPO, "--algo", "ppo", "--out", str(out)]) == 2
    message = _error(capsys)
    assert message.startswith("scg-jax train: error: argument --out: ")
    assert "already holds a training run (checkpoint.json, progress.csv); pass --resume to continue it or " in message
    assert message.endswith("--overwrite to replace it")
    assert (out / "checkpoint.json").read_text() == before


def test_resume_of_another_algorithms_run_says_so_plainly(tmp_path, capsys):
    out = tmp_path / "run"
    _fake_run(out, algo="ppo")
    assert main(["train", "--system", "cartpole", "--algo", "sac", "--out", str(out), "--resume"]) == 2
    assert "argument --resume: " in (message := _error(capsys))
    assert "holds a ppo run, not sac; resume it with --algo ppo" in message


def test_resume_on_a_folder_without_a_run_refuses_naming_resume_and_the_folder(tmp_path, capsys):
    """A typo in --out with --resume must not start a whole new run in the new folder."""
    missing, empty = tmp_path / "typo", tmp_path / "empty"
    empty.mkdir()
    for out, what in ((missing, "does not exist"), (empty, "holds no run to resume (no checkpoint.json)")):
        assert main(["train", "--system", "cartpole", "--algo", "ppo", "--out", str(out), "--resume"]) == 2
        captured = capsys.readouterr()
        assert captured.out == "" and captured.err.splitlines() == [
            f"scg-jax train: error: argument --resume: {out} {what}; check --out, or leave out --resume to start a "
            "new run there"
        ]
    assert not missing.exists() and not any(empty.iterdir())


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--resume", "--overwrite"], "argument --overwrite: not allowed with argument --resume"),
        (["--checkpoint-interval", "0"], "argument --checkpoint-interval: expected a positive number of seconds"),
        (["--progress-interval", "soon"], "argument --progress-interval: expected a positive number of seconds"),
    ],
)
def test_bad_train_flags_exit_2_with_one_line(tmp_path, capsys, flags, message):
    out = tmp_path / "run"
    assert main(["train", "--system", "cartpole", "--algo", "ppo", "--out", str(out), *flags]) == 2
    assert message in _error(capsys)
    assert not out.exists()


def test_ctrl_c_prints_the_checkpoint_and_the_resume_command(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"

    def interrupted(learner, env, params, key, out_dir, **options):
        assert options["checkpoint_seconds"] == 5.0 and isinstance(options["progress"], Progress)
        raise training.TrainingInterrupted(out_dir, 1, 2, out_dir / "checkpoint.msgpack")

    monkeypatch.setattr(training, "run_training", interrupted)
    args = ["train", *_ENV, *_TINY_PPO, "--algo", "ppo", "--out", str(out), "--seed", "3"]
    assert main([*args, "--checkpoint-interval", "5", "--progress-interval", "2"]) == 130
    printed = capsys.readouterr()
    assert "Traceback" not in printed.err
    assert f"interrupted: iteration 1/2 saved in {out / 'checkpoint.msgpack'}" in " ".join(printed.out.split())
    command = printed.out.strip().splitlines()[-1]
    words = shlex.split(command)
    assert words[:2] == ["scg-jax", "train"] and "--resume" in words
    assert words[words.index("--out") + 1] == str(out) and words[words.index("--seed") + 1] == "3"
    assert words[words.index("--checkpoint-interval") + 1] == "5.0"
    assert "training.ppo.num_envs=16" in words and "--overwrite" not in words


def test_ctrl_c_before_the_first_checkpoint_gives_the_command_that_starts_again(tmp_path, capsys, monkeypatch):
    """Nothing to resume (and --resume would be refused): the command starts the run again, with --overwrite when the
    interrupted attempt left files that would otherwise be refused."""
    out = tmp_path / "run"

    def interrupted(learner, env, params, key, out_dir, **options):
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "progress.csv").write_text("iteration\n")  # the header the first attempt wrote
        raise training.TrainingInterrupted(out_dir, 0, 2, None)

    monkeypatch.setattr(training, "run_training", interrupted)
    assert main(["train", *_ENV, *_TINY_PPO, "--algo", "ppo", "--out", str(out)]) == 130
    printed = capsys.readouterr()
    assert "interrupted before the first iteration completed; nothing saved. Start again with:" in printed.out
    words = shlex.split(printed.out.strip().splitlines()[-1])
    assert words[:2] == ["scg-jax", "train"] and "--resume" not in words and "--overwrite" in words


class _StampedStdout(io.StringIO):
    """A piped stdout (not a terminal) that notes when each line was written."""

    def __init__(self):
        super().__init__()
        self.stamps: list[float] = []

    def write(self, text):
        self.stamps += [time.monotonic()] * text.count("\n")
        return super().write(text)


def test_train_logs_progress_lines_and_extends_a_finished_run(tmp_path, capsys, monkeypatch):
    """Piped output (not a terminal) gets plain progress lines, at least one every --progress-interval seconds from the
    command's first line to its table: set-up (env, learner, init), compilation, iterations, evaluation and writing
    (a line may come a little late on a loaded machine, hence the slack); --resume with a raised budget continues the
    run (that it ends where a run of that budget in one go ends is tests/test_rl_common.py's, on the same driver), and
    resuming a finished run says that nothing was trained."""
    out = tmp_path / "run"
    # In process, the progress thread shares the interpreter with the compiler: in a CI run (2 loaded cores) one gap
    # during PPO's compilation took 2.25 s, so the slack is 3 s (the other gaps there: 0.15-0.28 s).
    interval, slack = 0.25, 3.0
    common = ["train", *_ENV, "--algo", "ppo", "--eval-episodes", "2", "--progress-interval", str(interval)]
    stdout = _StampedStdout()
    with monkeypatch.context() as patch:
        patch.setattr(sys, "stdout", stdout)
        assert main([*common, *_TINY_PPO, "--out", str(out)]) == 0
    texts = stdout.getvalue().splitlines()
    table = next(i for i, text in enumerate(texts) if not re.match(r"^[^:]+: .*elapsed \d+:\d\d", text))
    # The first line comes from the set-up or, when the set-up takes less than an interval (the init compiles on a
    # worker thread beside the training loop), from the compilation.
    assert texts[0].startswith(("train ppo: elapsed 0:0", "compiling ppo: elapsed 0:0")) and table > 3
    assert any(t.startswith("compiling ppo") for t in texts) and any(t.startswith("evaluating ppo") for t in texts)
    gaps = np.diff(stdout.stamps[:table])
    assert gaps.max() <= interval + slack, list(zip(gaps, texts[1:table], strict=True))
    lines = [line for line in texts if line.startswith("ppo: iteration")]
    assert lines and lines[-1].startswith("ppo: iteration 2/2 (100.0%), 512 env steps, ")
    # Twice the budget: resumed at iteration 2, on to 4.
    longer = [*_TINY_PPO, "--set", "training.ppo.total_env_steps=1024"]
    assert main([*common, *longer, "--out", str(out), "--resume"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["training"]["resumed_from_iteration"] == 2 and metrics["training"]["env_steps"] == 1024
    assert len((out / "progress.csv").read_text().splitlines()) == 1 + 4  # header, iterations 1-4
    assert "resumed at iteration 2: 1,024 env steps in all" in capsys.readouterr().out
    # The same budget again: nothing to train, and the output says so (not "1,024 env steps in 1.7 s").
    before = (out / "checkpoint.msgpack").read_bytes()
    assert main([*common, *longer, "--out", str(out), "--resume"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert f"nothing to train: the run in {out} was already complete at iteration 4; it was evaluated again" in text
    assert "ppo, already trained: 1,024 env steps, none this time" in text
    assert (out / "checkpoint.msgpack").read_bytes() == before
    # Another setting than the budget is named.
    other = [*longer, "--set", "training.ppo.learning_rate=0.0003"]
    assert main([*common, *other, "--out", str(out), "--resume"]) == 2
    message = _error(capsys)
    assert "argument --resume: " in message and "learning_rate: 0.001 in the checkpoint, 0.0003 now" in message
    # So is another env.
    assert main([*common, *longer, "--set", "env.ctrl_freq=25", "--out", str(out), "--resume"]) == 2
    message = _error(capsys)
    assert "was trained on another env: env.ctrl_freq: 50 in the checkpoint, 25 now." in message


# GP-MPC on 2-s cart-pole episodes at 10 Hz: one round of 2 episodes, a small GP, a short horizon.
_TINY_GP_MPC = [
    "--set", "env.ctrl_freq=10", "--set", "env.episode_len_sec=2", "--set", "env.disturbances={}",
    "--set", "controllers.gp_mpc={horizon: 8, rounds: 1, train_episodes: 2, eval_episodes: 2, num_inducing: 10, "
    "gp_iterations: 10, max_fit_points: 40}",
]  # fmt: skip


@pytest.mark.slow
def test_train_gp_mpc_writes_a_run_that_eval_uses(tmp_path, capsys):
    """One round of 2 episodes of 20 steps (4 s of data); the final evaluation in metrics.json (key(seed + 1)) is what
    scg-jax eval --seed 1 measures on the saved GP, episode by episode."""
    out = tmp_path / "gp"
    argv = ["train", "--algo", "gp_mpc", *_ENV, *_TINY_GP_MPC, "--prior-scale", "1.5", "--eval-episodes", "2"]
    assert main([*argv, "--out", str(out)]) == 0
    assert "wrote " + f"{out}/gp_mpc.json, gp_mpc.npz, learning_curve.csv, learning_curve.png, metrics.json" in (
        capsys.readouterr().out
    )
    record = json.loads((out / "metrics.json").read_text())
    assert record["algo"] == "gp_mpc" and record["prior_scale"] == 1.5 and record["options"]["rounds"] == 1
    history = record["history"]
    assert [h["round"] for h in history] == [0, 1] and [h["transitions"] for h in history] == [0, 40]
    assert [h["data_seconds"] for h in history] == [0.0, 4.0]
    curve = (out / "learning_curve.csv").read_text().splitlines()
    assert [float(line.split(",")[3]) for line in curve[1:]] == pytest.approx([h["rmse"] for h in history])
    assert main(["eval", *_ENV, *_TINY_GP_MPC, "--controller", str(out), "--episodes", "2", "--seed", "1",
                 "--out", str(tmp_path / "eval.json")]) == 0  # fmt: skip
    evaluated = json.loads((tmp_path / "eval.json").read_text())
    assert evaluated["controller"] == "gp_mpc"
    final = record["evaluation"]
    np.testing.assert_allclose(evaluated["per_episode"]["rmse"], final["per_episode"]["rmse"], rtol=1e-6)
    assert evaluated["rmse"] == pytest.approx(final["rmse"], rel=1e-6) and np.isfinite(final["rmse"])
    capsys.readouterr()
    assert main([*argv, "--out", str(out)]) == 2
    assert "already holds a run; pass --overwrite to replace it" in _error(capsys)
    assert main([*argv, "--out", str(out), "--resume"]) == 2
    assert "a gp_mpc run is not resumable" in _error(capsys)
    assert main(["eval", *_ENV, "--controller", str(out), "--prior-scale", "2", "--out", str(tmp_path / "e.json")]) == 2
    assert "learned its GP on a prior of scale 1.5" in _error(capsys)


def test_train_gp_mpc_refuses_a_folder_of_another_algorithm_and_ppo_a_prior_scale(tmp_path, capsys):
    out = tmp_path / "run"
    _fake_run(out)
    assert main(["train", "--algo", "gp_mpc", *_ENV, "--out", str(out)]) == 2
    assert "already holds a training run of another algorithm (checkpoint.json, progress.csv)" in _error(capsys)
    assert main(["train", "--algo", "ppo", *_ENV, "--prior-scale", "1.5", "--out", str(tmp_path / "p")]) == 2
    assert "only gp_mpc and learned_cbf learn on a prior model; ppo has none" in _error(capsys)
