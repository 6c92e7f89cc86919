"""Shared, session-scoped fixtures: each trainer program is compiled once for the whole test run.

The learner tests (``test_losses``, ``test_networks``, ``test_train``) use the tiny toy env
(:mod:`toy_env`) and tiny networks so that every jitted program compiles in seconds on CPU.

JAX's persistent compilation cache is on for the whole session, in ``.jax_cache/`` at the repository
root (git-ignored; a ``JAX_COMPILATION_CACHE_DIR`` set by the caller wins). The settings are also
put in the environment, so every subprocess and notebook kernel a test starts shares the cache: a
CLI run of the smoke preset loads the program the ``smoke_run`` fixture compiled (measured on 2 busy
CPU cores: ~210 s cold, ~40 s from the cache, most of it tracing and lowering). Entries are keyed by
the program, the compile options and the JAX version, so stale ones are never used, only kept:
delete ``.jax_cache/`` to reclaim the space.

Every program of the session, and of the subprocesses and kernels it starts, is compiled at XLA's
backend optimization level 0 (appended to the caller's ``XLA_FLAGS``, which win where they set the
same flag): compiling MJX dominates the suite, and level 0 compiled ``test_env.py`` in 157 s instead
of 260 s and ``test_brax.py`` in 76 s instead of 121 s (fresh caches, 2 busy CPU cores). The tests
compare runs of the same session with each other, never with a curve recorded outside it, so the
level changes no verdict; the recipes' own runs keep XLA's defaults.

The suite runs in two worker processes (pytest-xdist,
``-n 2 --dist loadgroup --no-loadscope-reorder`` in ``pyproject.toml``): compiling is
single-threaded, so two workers keep both cores busy. Tests are grouped so that the smoke trainer,
the costliest fixture, is compiled once per worker at most: the tests that train with it or change
its run form one group, sent first to one worker; each other file is a group of its own, handed to
whichever worker is free, in file order. The files whose tests only read the smoke run
(``SMOKE_READERS``) go last, when the trainer is in the persistent cache, so that a second worker
builds the run from the cache rather than compiling it again.
"""

from __future__ import annotations

import os
from pathlib import Path

if "--xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
  os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                             " --xla_backend_optimization_level=0").strip()

import jax  # noqa: E402  (after XLA_FLAGS: the backend reads them when it starts)
import numpy as np
import pytest

from mash.rl import trainer as trainer_lib
from mash.rl.config import TrainConfig

from toy_env import make_toy_env

SMOKE_READERS = frozenset({"test_notebooks", "test_seams", "test_sim2sim", "test_tracking"})
TOY_CALLS = 6  # jitted calls of the learning run (x iterations_per_call iterations).

REPO = Path(__file__).resolve().parents[1]
JAX_CACHE_DIR = os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(REPO / ".jax_cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "-1")
jax.config.update("jax_compilation_cache_dir", JAX_CACHE_DIR)
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))
jax.config.update("jax_persistent_cache_min_entry_size_bytes",
                  int(os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"]))


@pytest.fixture(scope="session")
def toy_config() -> TrainConfig:
  """A config small enough to compile and train in seconds: 32 envs x 16 steps = 512 steps/iter."""
  return TrainConfig(num_envs=32, unroll_length=16, iterations_per_call=5, num_epochs=4,
                     num_minibatches=4, learning_rate=3e-3, actor_hidden=(32, 32),
                     critic_hidden=(32, 32), seed=0)


@pytest.fixture(scope="session")
def mash_env():
  """Toy env, 2 legs + 2 arms, MASH partition (two agent groups)."""
  return make_toy_env("legs_arms", "mash")


@pytest.fixture(scope="session")
def mash_trainer(toy_config, mash_env) -> trainer_lib.Trainer:
  return trainer_lib.make_trainer(toy_config, mash_env,
                                  compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)


@pytest.fixture(scope="session")
def learning_run(mash_trainer):
  """Trains seed 0 for ``TOY_CALLS`` calls; returns the metrics of every call (numpy, stacked to
  ``[TOY_CALLS * iterations_per_call]``) and the params after the first call."""
  state = mash_trainer.init()
  history, first_params = [], None
  for call in range(TOY_CALLS):
    state, metrics = mash_trainer.train_epoch(state)
    history.append(jax.device_get(metrics))
    if call == 0:
      first_params = jax.device_get(state.params)
  metrics = {k: np.concatenate([m[k] for m in history]) for k in history[0]}
  return {"metrics": metrics, "first_params": first_params, "final_state": state}


@pytest.fixture(scope="session")
def smoke_config():
  """The ``smoke`` preset of bipedal MASH."""
  from mash.runs import experiment
  return experiment.make_config("bipedal", "mash", "smoke")


@pytest.fixture(scope="session")
def smoke_trainer(smoke_config):
  """The trainer of ``smoke_config``: its programs compile once and serve every in-process run."""
  from mash.runs import loop as runs
  return runs.build_trainer(smoke_config)


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory, smoke_config, smoke_trainer):
  """A real MJX training run of the ``smoke`` preset (bipedal MASH), trained once per session.

  Returns the run directory (``config.json``, ``progress.csv``, ``checkpoints/``, ...).
  """
  from mash.runs import loop as runs
  out = tmp_path_factory.mktemp("runs") / "smoke_bipedal_mash"
  runs.train(smoke_config, out, show_progress=False, trainer=smoke_trainer)
  return out


@pytest.fixture
def evaluated_smoke_run(smoke_run):
  """``smoke_run`` with an evaluation in ``eval/``: the one a test wrote there, else a tiny one
  (3 episodes of 1 s)."""
  if not (smoke_run / "eval" / "metrics.json").exists():
    from mash.analysis import evaluation
    from mash.analysis.reports import evaluate_run
    evaluate_run(str(smoke_run), evaluation.EvalConfig(num_episodes=3, episode_s=1.0))
  return smoke_run


@pytest.fixture
def skip_for_missing_gl():
  """A function that skips the calling test because no headless OpenGL library could render;
  its argument says what failed. These are system libraries, not Python packages, so the message
  names them."""

  def skip(reason: str) -> None:
    pytest.skip(f"no headless OpenGL to render with: {reason} (a system library, not a Python "
                "package: on Debian, apt install libegl1 libgl1-mesa-dri, or libosmesa6)")

  return skip


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(items):
  """Groups and orders the tests for the two workers (see the module docstring)."""

  def rank(item):
    if item.path.stem in SMOKE_READERS:
      return 2
    return 0 if "smoke_trainer" in getattr(item, "fixturenames", ()) else 1

  for item in items:
    item.add_marker(pytest.mark.xdist_group("smoke" if rank(item) == 0 else item.path.stem))
  items.sort(key=rank)  # stable: the order within a file is kept
