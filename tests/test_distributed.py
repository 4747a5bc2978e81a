"""Two-process ``jax.distributed`` evaluation, rollout and training on this machine (loopback coordinator, gloo
collectives).

Two ``scg-jax eval --distributed`` (or ``train --distributed``) processes with 2 simulated CPU devices each form one
4-device mesh; each steps the copies on its own devices, and process 0 alone writes the result, with the metrics of
all copies.
"""

import argparse
import csv
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from flax import serialization
from jax.sharding import Mesh

import scg_jax
from scg_algorithms.evaluation import evaluate
from scg_algorithms.lqr import make_lqr
from scg_algorithms.ppo import make_learner
from scg_algorithms.rl.training import RUN_FILES, run_training
from scg_cli import main, scale
from scg_cli.common import UsageError
from scg_jax.sharding import BATCH_AXIS
from tests.rl_helpers import set_options, tiny_ppo

ROOT = Path(__file__).resolve().parents[1]
EPISODES = 8


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _launch(out: Path, port: int, process_id: int) -> subprocess.Popen:
    arguments = [
        "eval", "--system", "cartpole", "--controller", "lqr", "--episodes", str(EPISODES), "--episode-len", "1",
        "--seed", "3", "--out", str(out),
    ]  # fmt: skip
    return _launch_process(arguments, port, process_id)


def _launch_process(arguments: list[str], port: int, process_id: int) -> subprocess.Popen:
    """``scg-jax ARGUMENTS --distributed`` as process ``process_id`` of 2, each with 2 simulated CPU devices."""
    env = {
        **os.environ,
        "SCG_JAX_LOCAL_DEVICES": "2",
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    # A simulated device count in XLA_FLAGS would fight SCG_JAX_LOCAL_DEVICES; the test run's other flags stay.
    env["XLA_FLAGS"] = " ".join(flag for flag in env.get("XLA_FLAGS", "").split() if "device_count" not in flag)
    command = [
        sys.executable, "-m", "scg_cli", *arguments,
        "--distributed", "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(process_id),
    ]  # fmt: skip
    return subprocess.Popen(command, env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _run_both(launch, meanwhile=None) -> tuple[list[int], list[str]]:
    """Start processes 0 and 1 (``launch(port, process_id)``), call ``meanwhile()`` while they run, and wait for
    both; their exit codes and outputs."""
    port = _free_port()
    processes = [launch(port, i) for i in range(2)]
    outputs = []
    try:
        if meanwhile is not None:
            meanwhile()
        for process in processes:
            outputs.append(process.communicate(timeout=240)[0])
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
    return [p.returncode for p in processes], outputs


def _distributed_and_single(folder: Path, arguments: list[str]):
    """``scg-jax ARGUMENTS --out folder/run --distributed`` in two processes, and ``--out folder/single`` in this
    process meanwhile (compiling dominates all three): ``(run, single, exit codes, outputs)``."""
    out, single = folder / "run", folder / "single"
    single_code = []
    codes, outputs = _run_both(
        lambda port, i: _launch_process([*arguments, "--out", str(out)], port, i),
        meanwhile=lambda: single_code.append(main([*arguments, "--out", str(single)])),
    )
    assert single_code == [0]
    return out, single, codes, outputs


@pytest.fixture(scope="module")
def two_process_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("distributed")
    out = folder / "eval.json"
    codes, outputs = _run_both(lambda port, i: _launch(out, port, i))
    return folder, out, codes, outputs


def test_two_processes_complete_one_evaluation_and_write_one_result(two_process_run):
    """Process 0 alone writes and reports; its trajectories hold every copy's 50 steps, whose rewards sum to the
    returns in the JSON, and its table shows the JSON's RMSE."""
    folder, out, codes, outputs = two_process_run
    assert codes == [0, 0], "\n".join(outputs)
    assert sorted(p.name for p in folder.iterdir()) == ["eval.json", "eval.npz", "eval.png"]
    assert "wrote" in outputs[0] and "wrote" not in outputs[1]  # only process 0 writes
    record = json.loads(out.read_text())
    with np.load(folder / "eval.npz") as data:
        assert data["reward"].shape == (50, EPISODES) and record["per_episode"]["length"] == [50] * EPISODES
        np.testing.assert_allclose(data["reward"].sum(axis=0), record["per_episode"]["return"], rtol=1e-5)
    assert f"{record['rmse']:.4f}" in outputs[0] and f"{record['rmse']:.4f}" not in outputs[1]


def test_the_result_holds_every_copy_and_equals_a_single_process_run(two_process_run):
    _, out, codes, _ = two_process_run
    assert codes == [0, 0]
    record = json.loads(out.read_text())
    assert record["num_episodes"] == EPISODES
    assert len(record["per_episode"]["return"]) == EPISODES
    env = scg_jax.make("cartpole", episode_len_sec=1.0)
    params = env.default_params
    single = evaluate(env, params, make_lqr(env, params), jax.random.key(3), EPISODES, measure_time=False)
    np.testing.assert_allclose(record["per_episode"]["return"], single.per_episode["return"], rtol=1e-5)
    np.testing.assert_allclose(record["rmse"], single.summary["rmse"], rtol=1e-5)


# ------------------------------------------------------------------------------------------------ rollout
_ROLLOUT = [
    "rollout", "--system", "cartpole", "--policy", "random", "--num-envs", "8", "--episode-len", "1", "--seed", "3",
]  # fmt: skip


@pytest.fixture(scope="module")
def two_process_rollout(tmp_path_factory):
    """``scg-jax rollout --distributed`` in two processes (4 devices), and the same rollout in this process."""
    return _distributed_and_single(tmp_path_factory.mktemp("distributed_rollout"), _ROLLOUT)


def test_a_two_process_rollout_writes_every_copy_once_and_equals_one_process(two_process_rollout):
    out, single, codes, outputs = two_process_rollout
    assert codes == [0, 0], "\n".join(outputs)
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "rollout.npz", "rollout.png"]
    assert "wrote" in outputs[0] and "wrote" not in outputs[1]  # only process 0 writes
    # Random inputs: every copy's own noise, the same whichever device steps it (layout-independent keys).
    with np.load(out / "rollout.npz") as sharded, np.load(single / "rollout.npz") as reference:
        assert sharded["x"].shape == reference["x"].shape == (50, 8, 4)
        for name in ("x", "x_final", "u", "reward"):
            np.testing.assert_allclose(sharded[name], reference[name], rtol=1e-5, atol=1e-6, err_msg=name)
        assert np.ptp(sharded["u"][:, :, 0], axis=1).max() > 0  # the copies really differ
    record = json.loads((out / "metrics.json").read_text())
    assert len(record["per_copy"]["return"]) == 8


# ------------------------------------------------------------------------------------------------ training
# 3 PPO iterations of 8 copies x 8 steps on 0.2-s (10-step) cart-pole episodes, so episodes end during training;
# tiny networks: compiling dominates the time.
_TRAIN = [
    "train", "--algo", "ppo", "--config", "configs/cartpole_stabilization.yaml", "--set", "env.episode_len_sec=0.2",
    *set_options(
        "training.ppo", total_env_steps=192, num_envs=8, rollout_length=8, num_epochs=1, num_minibatches=2,
        actor_hidden="[8]", critic_hidden="[8]",
    ),
    "--eval-episodes", "4", "--seed", "5",
]  # fmt: skip


@pytest.fixture(scope="module")
def two_process_training(tmp_path_factory):
    """``scg-jax train --distributed`` in two processes (4 devices), and the same run in this process (1 device)."""
    return _distributed_and_single(tmp_path_factory.mktemp("distributed_train"), _TRAIN)


def _progress(folder: Path) -> dict[str, np.ndarray]:
    with (folder / "progress.csv").open(newline="") as file:
        rows = list(csv.DictReader(file))
    return {name: np.array([float(row[name]) for row in rows]) for name in rows[0]}


def test_two_processes_train_one_run_and_only_process_0_writes(two_process_training):
    out, _, codes, outputs = two_process_training
    assert codes == [0, 0], "\n".join(outputs)
    assert sorted(p.name for p in out.iterdir()) == sorted(RUN_FILES)  # one set of files, no stray temporaries
    assert "ppo: iteration 3/3" in outputs[0] and "wrote" in outputs[0]
    assert "iteration" not in outputs[1] and "wrote" not in outputs[1]  # process 1 neither reports nor writes
    assert json.loads((out / "checkpoint.json").read_text())["iteration"] == 3


def test_two_process_training_equals_a_single_process_run(two_process_training):
    out, single, codes, _ = two_process_training
    assert codes == [0, 0]
    got, want = _progress(out), _progress(single)
    assert got.keys() == want.keys()
    np.testing.assert_array_equal(got["iteration"], [1, 2, 3])
    np.testing.assert_array_equal(got["env_steps"], want["env_steps"])
    assert np.all(np.isfinite(got["episode_return"][1:]))  # episodes ended: their metrics are compared too
    for name in got.keys() - {"wall_time_s"}:  # the gradients are all-reduced over the 4 devices of 2 processes
        np.testing.assert_allclose(got[name], want[name], rtol=1e-4, atol=1e-6, err_msg=name)
    policy, reference = (serialization.msgpack_restore((f / "policy.msgpack").read_bytes()) for f in (out, single))
    assert policy.keys() == reference.keys()
    for name in policy:
        np.testing.assert_allclose(policy[name], reference[name], rtol=1e-4, atol=1e-6, err_msg=name)
    evaluation, reference = (json.loads((f / "metrics.json").read_text())["evaluation"] for f in (out, single))
    np.testing.assert_allclose(evaluation["per_episode"]["return"], reference["per_episode"]["return"], rtol=1e-4)


def test_a_multi_process_mesh_must_hold_every_process_devices(monkeypatch, tmp_path):
    # As seen from a process of a 2-process job with 4 devices in all: a mesh of 1 device leaves a process out.
    monkeypatch.setattr(jax, "process_count", lambda: 2)
    monkeypatch.setattr(jax, "device_count", lambda: 4)
    args = argparse.Namespace(devices="1")
    with pytest.raises(UsageError, match=r"--devices: a --distributed job spans the 4 devices of its 2 processes"):
        scale.make_mesh(args, None)
    env = scg_jax.make("cartpole", episode_len_sec=0.2)
    learner = make_learner(tiny_ppo(total_env_steps=128, num_epochs=1, num_minibatches=1), env)
    one_device = Mesh(np.asarray(jax.local_devices()[:1]), (BATCH_AXIS,))
    with pytest.raises(ValueError, match=r"mesh: a run over 2 processes needs a mesh over all 4 devices"):
        run_training(learner, env, env.default_params, jax.random.key(0), tmp_path, progress=False, mesh=one_device)
    assert not any(tmp_path.iterdir())  # refused before writing anything
