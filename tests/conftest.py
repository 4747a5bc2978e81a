"""Shared fixtures. Tests that need float64 wrap their body in ``with jax.enable_x64(True):``.

One JAX persistent compilation cache serves the whole test run: the pytest process creates it in a temporary
folder and hands it on through ``JAX_COMPILATION_CACHE_DIR`` to the xdist workers and to every CLI subprocess a
test starts, so a computation compiled once (the same env step, rollout or training loop, built afresh by another
test or process) is loaded instead of compiled again. It is removed when the run ends. A run started with
``JAX_COMPILATION_CACHE_DIR`` already set uses that folder and keeps it.

Most tests run a compiled program for a fraction of a second after compiling it for several, so XLA compiles them
with most optimisations off (``jax_disable_most_optimizations``: LLVM's backend optimisation level 0, the same HLO
program): about 30% less compile time, the same operations (rounded in another order). A test whose outcome that
rounding can steer (a learning test at a small budget) is marked ``optimized``. The setting is chosen per test,
before its fixtures are built, and applies to what is compiled from then on: an executable that the process already
holds (a jitted function called again with the same shapes) runs as it was compiled, so an ``optimized`` test builds
the programs it depends on itself. The persistent cache keys its entries by the setting, and the CLI subprocesses a
test starts inherit it through ``JAX_DISABLE_MOST_OPTIMIZATIONS``.
XLA's CPU backend also emits the tests' fused loops with its older LLVM emitters (``XLA_FLAGS`` gets
``--xla_cpu_use_fusion_emitters=false`` here, before JAX starts its backend, for every worker and subprocess): at
optimisation level 0 they compile in about half the CPU time of the default MLIR emitters (a PPO training program:
3.7 s against 8.1 s), and run as fast. It is a process-wide flag, so an ``optimized`` test keeps it.
``SCG_TEST_OPTIMIZE=1`` compiles every test fully optimised with XLA's default emitters, as users' programs are.
"""

import os
import shutil
import tempfile

_LEGACY_EMITTERS = "--xla_cpu_use_fusion_emitters=false"
if os.environ.get("SCG_TEST_OPTIMIZE") != "1" and "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_LEGACY_EMITTERS}".strip()

import jax  # noqa: E402  (after XLA_FLAGS: the backend reads them once, when it starts)
import pytest  # noqa: E402

import scg_jax  # noqa: E402

SYSTEM_NAMES = tuple(scg_jax.SYSTEMS)
_CACHE_ENV = "JAX_COMPILATION_CACHE_DIR"
# Compilations shorter than this are not stored: loading them would cost about what compiling them does.
_MIN_COMPILE_SECONDS = "0.2"


def pytest_configure(config):
    if not hasattr(config, "workerinput") and _CACHE_ENV not in os.environ:  # the controlling process, once
        config._scg_compile_cache = tempfile.mkdtemp(prefix="scg-jax-test-compile-cache-")
        os.environ[_CACHE_ENV] = config._scg_compile_cache
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", _MIN_COMPILE_SECONDS)
    # jax read its environment when this module imported it: set the options it read as well.
    jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE_ENV])
    jax.config.update(
        "jax_persistent_cache_min_compile_time_secs", float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])
    )


def _fast_compile(item) -> bool:
    return os.environ.get("SCG_TEST_OPTIMIZE") != "1" and item.get_closest_marker("optimized") is None


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    fast = _fast_compile(item)
    jax.config.update("jax_disable_most_optimizations", fast)
    os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1" if fast else "0"


def pytest_unconfigure(config):
    folder = getattr(config, "_scg_compile_cache", None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="session")
def envs():
    """One stabilization env per system, built once for the session (jitted functions cache per env)."""
    return {name: scg_jax.make(name) for name in SYSTEM_NAMES}


@pytest.fixture(scope="session")
def jitted_step(envs):
    """A jitted ``step`` per system, so tests reuse one compilation."""
    return {name: jax.jit(env.step) for name, env in envs.items()}
