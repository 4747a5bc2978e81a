"""What a new user meets first: one-line usage errors that name the right option, ``--version``, and error wording."""

import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

from scg_cli import main

CONFIG = "configs/cartpole_stabilization.yaml"
OUT = "{tmp}/e.json"


def _one_line_error(capsys, argv) -> str:
    """Run ``argv``: exit 2, nothing on stdout, exactly one line on stderr (returned)."""
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    return lines[0]


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        ([], "scg-jax: error: the following arguments are required: COMMAND (see scg-jax --help)"),
        (
            ["eval", "--system", "cartpole"],
            "scg-jax eval: error: the following arguments are required: --controller, --out (see scg-jax eval --help)",
        ),
        (
            ["eval", "--system", "cartpole", "--controller", "lqr", "--out", "{tmp}/e.json", "--bogus", "1"],
            "scg-jax eval: error: unrecognized arguments: --bogus 1 (see scg-jax eval --help)",
        ),
        (
            ["train", "--system", "cartpole", "--algo", "ppq", "--out", "{tmp}/run"],
            "scg-jax train: error: argument --algo: invalid choice: 'ppq' (choose from ",
        ),
        (
            ["eval", "--config", CONFIG, "--controller", "lqr", "--set", "env.ctrl_freq=fifty", "--out", OUT],
            "scg-jax eval: error: argument --set: env.ctrl_freq: expected an integer, got 'fifty' (set by override "
            "'env.ctrl_freq=fifty')",
        ),
        (
            ["compare", "--system", "cartpole", "--controllers", "lqr,lqrr"],
            "scg-jax compare: error: argument --controllers: 'lqrr' is neither a controller name (pid, lqr, ",
        ),
        (
            ["reproduce", "control_performanc", "--out", "{tmp}/rep"],
            "scg-jax reproduce: error: argument NAME: unknown value 'control_performanc'; allowed values are ",
        ),
    ],
)
def test_a_usage_error_is_one_line_naming_the_option(tmp_path, capsys, argv, expected):
    line = _one_line_error(capsys, [word.format(tmp=tmp_path) for word in argv])
    assert line.startswith(expected)
    assert not any(tmp_path.iterdir())  # nothing written
    if "lqr,lqrr" in argv:
        assert line.endswith("(did you mean 'lqr'?)")
    if "reproduce" in argv:
        assert line.endswith("(did you mean 'control_performance'?)")


def test_the_flag_is_named_unless_an_override_set_the_value(tmp_path, capsys):
    """The flag of an option is named when the flag (or the config) gave the bad value, --set when an override did."""
    out = str(tmp_path / "e.json")
    line = _one_line_error(capsys, ["eval", "--system", "cartpole", "--ctrl-freq", "15", "--controller", "lqr",
                                    "--out", out])  # fmt: skip
    assert line.startswith("scg-jax eval: error: argument --physics-freq: env.physics_freq: must be a multiple of")
    line = _one_line_error(capsys, ["eval", "--system", "cartpole", "--set", "env.trajectory.shape=cirle",
                                    "--controller", "lqr", "--out", out])  # fmt: skip
    assert line.startswith("scg-jax eval: error: argument --set: env.trajectory.shape: unknown value 'cirle'")


def test_an_output_folder_that_takes_no_files_says_so(tmp_path, capsys, monkeypatch):
    """Not "not writable (No such file or directory)" (what /proc gave): a permission error is "not writable", any
    other failure to create a file there is named as such, with the system's reason."""
    import tempfile

    def refuse(*args, **kwargs):
        raise FileNotFoundError(2, "No such file or directory")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    line = _one_line_error(capsys, ["eval", "--system", "cartpole", "--controller", "lqr",
                                    "--out", str(tmp_path / "e.json")])  # fmt: skip
    assert line == (
        f"scg-jax eval: error: argument --out: cannot write results to '{tmp_path / 'e.json'}': '{tmp_path}' takes "
        "no new files (No such file or directory)"
    )


def test_distributed_without_a_coordinator_says_how_to_give_one(tmp_path, capsys, monkeypatch):
    import scg_jax.sharding

    def jax_refuses(*args, **kwargs):
        raise ValueError("coordinator_address should be defined.")  # jax.distributed.initialize's own words

    monkeypatch.setattr(scg_jax.sharding, "initialize_distributed", jax_refuses)
    monkeypatch.delenv("JAX_COORDINATOR_ADDRESS", raising=False)
    line = _one_line_error(capsys, ["eval", "--system", "cartpole", "--controller", "lqr", "--distributed",
                                    "--out", str(tmp_path / "e.json")])  # fmt: skip
    assert line.startswith("scg-jax eval: error: argument --distributed: found no cluster to join")
    assert "pass --coordinator HOST:PORT --num-processes N --process-id I" in line
    assert "coordinator_address" not in line


def test_version_is_the_installed_distributions(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out == f"scg-jax {version('scg-jax')}\n"
    # As a user types it: the installed entry point.
    result = subprocess.run(
        [str(Path(sys.prefix) / "bin" / "scg-jax"), "--version"], capture_output=True, text=True, timeout=300
    )
    assert (result.returncode, result.stdout, result.stderr) == (0, f"scg-jax {version('scg-jax')}\n", "")


def test_help_lists_every_subcommand_and_every_learner(capsys):
    from scg_algorithms.learners import LEARNERS

    assert main(["--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for name in ("rollout", "eval", "compare", "train", "sweep", "reproduce"):
        assert f" {name} " in text
    assert main(["train", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert all(f"{name} (" in text for name in LEARNERS), text
