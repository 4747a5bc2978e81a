"""Sharded batches: the option checks here, and the sharded-vs-single-device comparisons on 4 simulated CPU
devices in a fresh pytest process (``tests/multidevice_cases.py``; the device count is fixed when JAX starts)."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import pytest

from scg_cli import main
from scg_jax import sharding
from scg_jax.config import load_config
from scg_jax.validation import FieldError

ROOT = Path(__file__).resolve().parents[1]


def test_four_simulated_devices_give_the_single_device_numbers():
    env = {
        **os.environ,
        "XLA_FLAGS": "--xla_force_host_platform_device_count=4",
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-x"]
    result = subprocess.run(
        [*command, str(ROOT / "tests" / "multidevice_cases.py")],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=500,
    )
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "10 passed" in result.stdout


@pytest.mark.parametrize("value", [0, -2, 1.5, "some", True])
def test_devices_option_names_the_field_and_the_allowed_values(value):
    with pytest.raises(FieldError, match=r"^devices: expected 'all' or a positive integer"):
        load_config({"env": {"system": "cartpole"}, "devices": value})


def test_devices_option_accepts_all_and_counts():
    assert load_config({"env": {"system": "cartpole"}, "devices": "all"}).devices == "all"
    assert load_config({"env": {"system": "cartpole"}}, ["devices=2"]).devices == 2
    assert load_config({"env": {"system": "cartpole"}}).devices is None


def test_one_device_means_no_mesh_and_more_than_there_are_is_refused():
    assert sharding.make_mesh(None) is None
    assert sharding.make_mesh(1) is None
    count = jax.device_count()
    with pytest.raises(FieldError, match=rf"devices: {count + 1} devices asked for but JAX sees {count}"):
        sharding.make_mesh(count + 1)


def test_cli_devices_flag_errors_name_the_flag(tmp_path, capsys):
    code = main(["rollout", "--system", "cartpole", "--devices", "0", "--out", str(tmp_path / "r")])
    assert code == 2
    assert "argument --devices: expected 'all' or a positive integer" in capsys.readouterr().err
