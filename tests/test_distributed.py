"""Multi-process training: two processes joined by ``jax.distributed`` equal one process over two
devices.

Three subprocesses of ``tests/distributed_worker.py`` run at once on 127.0.0.1: a pair of processes
with one CPU device each, joined into a global 2-device mesh (the multi-host path, Gloo
collectives), and one process with two forced CPU devices. Both train the toy env with the same
config and key through :func:`mash.rl.trainer.make_trainer` (with a mesh) for two jitted calls; the
pair also saves and restores its global state with Orbax, then trains again through
:func:`mash.runs.loop.train` (the CLI's loop) into a run directory, stopping after one call and
resuming. Every parameter, statistic and metric must agree: between the two processes of the pair
exactly (replicated values), and between the pair and the single process to float tolerance (only
the collective's implementation differs).
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from mash.rl import distributed

ROOT = Path(__file__).resolve().parent.parent
WORKER = ROOT / "tests" / "distributed_worker.py"
TIMEOUT_S = 240


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _env(devices: int) -> dict[str, str]:
  env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
  env.update(JAX_PLATFORMS="cpu",
             PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p))
  if devices > 1:
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
  return env


def _run_all(commands: list[tuple[list[str], dict[str, str]]], log_dir: Path,
             timeout_s: float = TIMEOUT_S) -> None:
  """Runs the commands concurrently; kills them all when one fails or the time is up."""
  procs, logs = [], []
  for i, (cmd, env) in enumerate(commands):
    log = open(log_dir / f"worker{i}.log", "w")
    logs.append(log)
    procs.append(subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT))
  deadline = time.monotonic() + timeout_s
  failure = None
  try:
    while any(p.poll() is None for p in procs):
      bad = [i for i, p in enumerate(procs) if p.poll() not in (None, 0)]
      if bad:
        failure = f"worker {bad[0]} exited with status {procs[bad[0]].returncode}"
        break
      if time.monotonic() > deadline:
        failure = f"timed out after {timeout_s:.0f} s"
        break
      time.sleep(0.2)
    else:
      bad = [i for i, p in enumerate(procs) if p.returncode != 0]
      if bad:
        failure = f"worker {bad[0]} exited with status {procs[bad[0]].returncode}"
  finally:
    for p in procs:
      if p.poll() is None:
        p.kill()
        p.wait()
    for log in logs:
      log.close()
  if failure:
    tails = "\n".join(f"--- worker{i} ---\n" + (log_dir / f"worker{i}.log").read_text()[-2000:]
                      for i in range(len(procs)))
    pytest.fail(f"{failure}\n{tails}")


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict[str, dict[str, np.ndarray]]:
  """``{'pair0', 'pair1', 'single'}``: each worker's saved arrays."""
  tmp = tmp_path_factory.mktemp("distributed")
  coordinator = f"127.0.0.1:{_free_port()}"
  pair = [([
      sys.executable,
      str(WORKER), "--out",
      str(tmp / "pair"), "--num-processes", "2", "--process-id",
      str(i), "--coordinator", coordinator, "--checkpoint",
      str(tmp / "checkpoints"), "--run",
      str(tmp / "run")
  ], _env(1)) for i in range(2)]
  single = ([sys.executable, str(WORKER), "--out", str(tmp / "single")], _env(2))
  _run_all(pair + [single], tmp)
  load = lambda p: dict(np.load(p))
  return {
      "pair0": load(tmp / "pair" / "result_p0.npz"), "pair1": load(tmp / "pair" / "result_p1.npz"),
      "single": load(tmp / "single" / "result_p0.npz"), "run_dir": tmp / "run"
  }


TRAINED = ("metrics", "params/", "normalizer/", "env_reward", "iteration")


def _trained_keys(r: dict[str, np.ndarray]) -> list[str]:
  return sorted(k for k in r if k.startswith(TRAINED))


def _workers(results) -> list[dict[str, np.ndarray]]:
  return [results[k] for k in ("pair0", "pair1", "single")]


def test_pair_ran_as_two_processes(results):
  assert int(results["pair0"]["process_count"]) == 2
  assert int(results["single"]["process_count"]) == 1
  assert bool(results["pair0"]["checkpoint_ok"]) and bool(results["pair1"]["checkpoint_ok"])
  # 2 calls x 2 iterations, normalizer merged over both devices:
  # 4 iterations x 32 envs x 16 steps x 2 leg agents = 4096 leg observations.
  for r in _workers(results):
    assert int(r["iteration"]) == 4
    np.testing.assert_allclose(r["normalizer/['legs'].count"], 4 * 32 * 16 * 2)
    assert r["env_reward"].shape == (32,)


def test_processes_of_the_pair_agree_exactly(results):
  a, b = results["pair0"], results["pair1"]
  assert _trained_keys(a) == _trained_keys(b)
  for k in _trained_keys(a):
    np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_two_processes_match_one_process_two_devices(results):
  pair, single = results["pair0"], results["single"]
  assert _trained_keys(pair) == _trained_keys(single)
  assert any(k.startswith("params/") for k in _trained_keys(pair))
  for k in _trained_keys(pair):
    np.testing.assert_allclose(pair[k], single[k], rtol=1e-5, atol=1e-6, err_msg=k)
  assert np.isfinite(pair["metrics1/['episode_reward']"]).all()


def test_run_directory_of_two_processes(results):
  """``runs.train`` over the pair: one call, stopped, then resumed to the end. Process 0 wrote the
  run files; the progress equals the metrics of the pair's direct training (same program, same
  key: bit for bit, so the resume restored the global state exactly); a second non-resume run
  into the directory is refused by both processes; one process restores the policy."""
  import json

  from mash.rl import trainer as trainer_lib
  from mash.runs import loop as runs

  from toy_env import make_toy_env

  run, pair = results["run_dir"], [results["pair0"], results["pair1"]]
  for r in pair:
    assert int(r["run_first_iterations"]) == 2 and int(r["run_iterations"]) == 4
    assert int(r["run_devices"]) == 2 and int(r["run_processes"]) == 2
    assert "already holds a run" in str(r["run_refused"]) or "refused" in str(r["run_refused"])
  for name in ("config.json", "progress.csv", "summary.json", "reward_curve.png"):
    assert (run / name).is_file(), name
  assert sorted(p.name for p in (run / "checkpoints").iterdir() if p.name.isdigit()) == ["2", "4"]
  summary = json.loads((run / "summary.json").read_text())
  assert summary["devices"] == 2 and summary["processes"] == 2 and summary["iterations"] == 4
  progress = runs.read_progress(run)
  np.testing.assert_array_equal(progress["iteration"], [1, 2, 3, 4])
  direct = np.concatenate([pair[0][f"metrics{c}/['episode_reward']"] for c in range(2)])
  np.testing.assert_array_equal(progress["episode_reward"], direct.astype(np.float64))
  assert float(pair[1]["run_final_reward"]) == progress["episode_reward"][-1]

  # One process (no mesh) reads the policy the two processes saved, as evaluate/export do.
  cfg = runs.load_config(run)
  trainer = trainer_lib.make_trainer(cfg.train, make_toy_env("legs_arms", "mash"))
  restored = runs.restore_run(run, trainer, fields=("params", "normalizer"))
  assert restored.step == 4
  flat = {
      "params/" + jax.tree_util.keystr(p): np.asarray(x)
      for p, x in jax.tree_util.tree_flatten_with_path(restored.state.params)[0]
  }
  assert flat and all(k in pair[0] for k in flat)
  for k, v in flat.items():
    np.testing.assert_array_equal(v, pair[0][k], err_msg=k)


def test_initialize_rejects_bad_arguments():
  with pytest.raises(ValueError, match="coordinator"):
    distributed.initialize("localhost", 2, 0)
  with pytest.raises(ValueError, match="num_processes"):
    distributed.initialize("127.0.0.1:1234", 0, 0)
  with pytest.raises(ValueError, match="process_id"):
    distributed.initialize("127.0.0.1:1234", 2, 2)


@pytest.mark.parametrize("flags, env, words", [
    (dict(num_processes="2"), {}, "needs --coordinator"),
    (dict(num_processes="2", coordinator="127.0.0.1:1234"), {}, "needs --process-id"),
    (dict(num_processes="two"), {}, "--num-processes must be an integer, got 'two'"),
    (dict(num_processes="0"), {}, "--num-processes must be >= 1"),
    (dict(num_processes="2", coordinator="127.0.0.1:1234",
          process_id="2"), {}, "--process-id must be in 0 .. 1"),
    (dict(process_id="1"), {}, "--process-id 1 needs --num-processes 2 or more"),
    (dict(num_processes="2", coordinator="localhost", process_id="0"), {}, "'localhost' is not"),
    ({}, {"MASH_NUM_PROCESSES": "x"}, "MASH_NUM_PROCESSES must be an integer, got 'x'"),
    ({}, {"MASH_NUM_PROCESSES": "3", "MASH_COORDINATOR": "127.0.0.1:1"}, "needs --process-id"),
])
def test_cli_process_flags_reject_bad_values(flags, env, words, monkeypatch):
  """The training CLI's --coordinator/--num-processes/--process-id (or MASH_* variables): every
  mistake is one UserError (one line, exit 2) before anything joins or runs."""
  import argparse

  from mash.cli import UserError
  from mash.runs import launch
  for name in launch.DISTRIBUTED_ENV.values():
    monkeypatch.delenv(name, raising=False)
  for name, value in env.items():
    monkeypatch.setenv(name, value)
  args = argparse.Namespace(
      **{"coordinator": None, "num_processes": None, "process_id": None, **flags})
  with pytest.raises(UserError, match=re.escape(words)):
    launch.join_processes(args)


def test_cli_one_process_by_default(monkeypatch):
  import argparse

  from mash.runs import launch
  for name in launch.DISTRIBUTED_ENV.values():
    monkeypatch.delenv(name, raising=False)
  assert launch.join_processes(
      argparse.Namespace(coordinator=None, num_processes=None, process_id=None)) is True
  assert launch.join_processes(
      argparse.Namespace(coordinator="127.0.0.1:1", num_processes="1", process_id="0")) is True
