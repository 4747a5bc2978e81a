"""A two-process ``jax.distributed`` evaluation on this machine (loopback coordinator, gloo collectives).

Two ``scg-jax eval --distributed`` processes with 2 simulated CPU devices each form one 4-device mesh; each steps
the copies on its own devices, and process 0 alone writes the result, with the metrics of all copies.
"""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import scg_jax
from scg_algorithms.evaluation import evaluate
from scg_algorithms.lqr import make_lqr

ROOT = Path(__file__).resolve().parents[1]
EPISODES = 8


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _launch(out: Path, port: int, process_id: int) -> subprocess.Popen:
    env = {
        **os.environ,
        "SCG_JAX_LOCAL_DEVICES": "2",
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.pop("XLA_FLAGS", None)
    command = [
        sys.executable, "-m", "scg_cli", "eval", "--system", "cartpole", "--controller", "lqr",
        "--episodes", str(EPISODES), "--episode-len", "1", "--seed", "3", "--out", str(out),
        "--distributed", "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(process_id),
    ]  # fmt: skip
    return subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


@pytest.fixture(scope="module")
def two_process_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("distributed")
    out = folder / "eval.json"
    port = _free_port()
    processes = [_launch(out, port, i) for i in range(2)]
    outputs = []
    try:
        for process in processes:
            outputs.append(process.communicate(timeout=240)[0])
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
    return folder, out, [p.returncode for p in processes], outputs


def test_two_processes_complete_one_evaluation_and_write_one_result(two_process_run):
    folder, out, codes, outputs = two_process_run
    assert codes == [0, 0], "\n".join(outputs)
    assert sorted(p.name for p in folder.iterdir()) == ["eval.json", "eval.npz", "eval.png"]
    assert "wrote" in outputs[0] and "wrote" not in outputs[1]  # only process 0 writes


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
