"""What a second CPU device buys: the env step (and training) in one process vs two.

Measures the real MJX env's batched env step (PD, randomized model, observations, reward,
auto-reset; not training) in separate worker processes, launched by :func:`run_scaling`:

- ``one_process``: one process, one CPU device, ``B`` envs;
- ``two_process_mesh``: two processes joined by ``jax.distributed`` (Gloo) into a global 2-device
  mesh, each device stepping ``B/2`` envs under ``shard_map``, with one cross-process ``psum``
  per control step (a sync per step: more often than training synchronizes per env step);
- ``two_process_independent``: two unconnected processes, each stepping its own ``B/2`` envs at
  the same time (no collective): the upper bound of the mesh variant, so
  ``two_process_mesh / two_process_independent`` is the price of the collective;
- with ``train``: the MASH trainer on the real env, one process vs two processes over the
  global mesh (:func:`mash.rl.trainer.make_trainer` with a mesh), small batch.

Each worker (``python -m experiments.benchmark_devices --worker VARIANT ...``, which calls
:func:`run_worker`) compiles, warms up, waits until its peers are ready, then times ``repeats``
calls and keeps the best. The launcher sets each worker's ``JAX_PLATFORMS`` and drops
``XLA_FLAGS`` from its environment, so both are in place before the worker imports JAX.
:func:`write_report` writes the table as ``.json``, ``.md`` and a ``.png`` plot, with
``ratio_vs_one_process`` (total env steps/s over the one-process figure).

One process with two forced CPU devices is not measured: a sharded MJX step deadlocks there.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P
from matplotlib.figure import Figure

from mash import errors
from mash.rl import config as train_config
from mash.rl import distributed
from mash.rl import trainer as trainer_lib
from mash.sim import env as env_lib
from mash.sim import env_config

WORKER_MODULE = "experiments.benchmark_devices"  # run with --worker, it calls run_worker
WORKER_TIMEOUT_S = 600
REPO_ROOT = Path(__file__).resolve().parents[2]  # where WORKER_MODULE is importable
VARIANTS = (("one_process", 1), ("two_process_mesh", 2), ("two_process_independent", 2))
TRAIN_VARIANTS = (("train_one_process", 1), ("train_two_process", 2))
JOINED = ("two_process_mesh", "train_two_process")  # one global program over all workers


class WorkerFailed(errors.InputError):
  """A worker of a variant failed or timed out (its log is kept; the message says where)."""


@dataclasses.dataclass(frozen=True)
class ScalingConfig:
  """What the scaling benchmark measures.

  Attributes:
    batch: global env batch of the env-step variants (even).
    steps: control steps per timed call.
    repeats: timed calls per worker (the best is kept).
    task: the task whose env is stepped.
    train: also time MASH training, one process vs two.
    train_batch: global env batch of the training variants (a multiple of 4).
    platform: ``JAX_PLATFORMS`` of the workers.
  """

  batch: int = 256
  steps: int = 20
  repeats: int = 3
  task: str = "bipedal"
  train: bool = False
  train_batch: int = 256
  platform: str = "cpu"


@dataclasses.dataclass(frozen=True)
class Worker:
  """One worker process of a variant, as the launcher starts it.

  Attributes:
    variant: which measurement (a name of :data:`VARIANTS` or :data:`TRAIN_VARIANTS`).
    process_id: this worker's index among the variant's ``num_processes``.
    num_processes: workers of the variant.
    coordinator: ``'host:port'`` of process 0, for the variants joined by ``jax.distributed``.
    sync_dir: folder of the file barrier of the unconnected variants.
    result: the JSON file the worker writes its timing to.
  """

  variant: str
  process_id: int = 0
  num_processes: int = 1
  coordinator: str = "127.0.0.1:12355"
  sync_dir: str | None = None
  result: str | None = None


# --------------------------------------------------------------------------------------------------
# Worker side (runs in a subprocess).


def _wait_for_peers(sync_dir: str, process_id: int, num_processes: int, timeout_s: float = 600):
  """File barrier between workers that share no JAX runtime."""
  Path(sync_dir, f"ready_{process_id}").touch()
  deadline = time.monotonic() + timeout_s
  while not all(Path(sync_dir, f"ready_{i}").exists() for i in range(num_processes)):
    if time.monotonic() > deadline:
      raise TimeoutError("peers never became ready")
    time.sleep(0.05)


def _timed(fn: Callable, args: tuple, repeats: int, sync: Callable[[], None]) -> dict:
  """Compile + warm-up call, barrier, then the best of ``repeats`` calls (wall and CPU time)."""
  t0 = time.perf_counter()
  jax.block_until_ready(fn(*args))
  compile_s = time.perf_counter() - t0
  sync()
  best, cpu = float("inf"), 0.0
  for _ in range(repeats):
    c0, t0 = time.process_time(), time.perf_counter()
    jax.block_until_ready(fn(*args))
    dt = time.perf_counter() - t0
    if dt < best:
      best, cpu = dt, time.process_time() - c0
  return {"compile_s": compile_s, "run_s": best, "cpu_cores_used": cpu / best}


def _rollout_fn(env: env_lib.MashEnv, axis_name: str | None = None) -> Callable:
  """``rollout(state, actions [T, B, A]) -> total reward``: ``T`` batched env steps, with one
  ``psum`` of the reward over ``axis_name`` per control step when it is given."""

  def rollout(state, actions):

    def body(carry, a):
      s, total = carry
      s = jax.vmap(env.step)(s, a)
      r = jnp.sum(s.reward)
      if axis_name is not None:
        r = jax.lax.psum(r, axis_name)  # one cross-process sync per control step
      return (s, total + r), ()

    (s, total), _ = jax.lax.scan(body, (state, jnp.zeros(())), actions)
    return total

  return rollout


def _env_step_worker(config: ScalingConfig, worker: Worker) -> dict:
  """Times ``config.steps`` batched env steps of this process's envs (see the module docstring)."""
  env = env_lib.MashEnv(env_config.EnvConfig(task=config.task))
  n, pid = worker.num_processes, worker.process_id
  local_batch = config.batch // n
  keys = jax.random.split(jax.random.PRNGKey(0), config.batch)
  state = jax.jit(jax.vmap(env.reset))(keys[pid * local_batch:(pid + 1) * local_batch])
  actions = 0.1 * jax.random.normal(jax.random.fold_in(jax.random.PRNGKey(1), pid),
                                    (config.steps, local_batch, env.action_size))
  if worker.variant == "two_process_mesh":
    mesh = distributed.global_mesh("d")
    put = lambda x, spec: jax.make_array_from_process_local_data(NamedSharding(mesh, spec),
                                                                 np.asarray(x))
    state = jax.tree.map(lambda x: put(x, P("d")), state)
    actions = put(actions, P(None, "d"))
    fn = jax.jit(
        jax.shard_map(_rollout_fn(env, "d"), mesh=mesh, in_specs=(P("d"), P(None, "d")),
                      out_specs=P(), check_vma=False))
    sync = lambda: distributed.barrier("timed")
  else:
    fn = jax.jit(_rollout_fn(env))
    sync = lambda: _wait_for_peers(worker.sync_dir, pid, n)
  timing = _timed(fn, (state, actions), config.repeats, sync)
  return {
      **timing, "local_batch": local_batch, "substeps": env.n_substeps,
      "env_steps": local_batch * config.steps
  }


def _train_worker(config: ScalingConfig, worker: Worker) -> dict:
  """Times MASH training calls on the real env: one process, or the global mesh of all of them."""
  env = env_lib.MashEnv(env_config.EnvConfig(task=config.task))
  cfg = dataclasses.replace(train_config.TrainConfig(), num_envs=config.train_batch,
                            unroll_length=16, iterations_per_call=1, num_epochs=2,
                            num_minibatches=2, actor_hidden=(64, 64), critic_hidden=(64, 64))
  mesh = distributed.global_mesh() if worker.num_processes > 1 else None
  trainer = trainer_lib.make_trainer(cfg, env, mesh=mesh)
  holder = {"state": trainer.init()}

  def call():  # the state is donated: thread it through
    holder["state"], metrics = trainer.train_epoch(holder["state"])
    return metrics

  timing = _timed(call, (), config.repeats, lambda: distributed.barrier("timed"))
  local_batch = config.train_batch // worker.num_processes
  return {
      **timing, "local_batch": local_batch, "substeps": env.n_substeps,
      "env_steps": local_batch * cfg.unroll_length * cfg.iterations_per_call
  }


def run_worker(config: ScalingConfig, worker: Worker) -> None:
  """One worker's measurement, written as JSON to ``worker.result``.

  Joins the variant's processes first where it is one global program (:data:`JOINED`); the
  process's ``JAX_PLATFORMS`` must already be set (the launcher sets it).
  """
  if worker.variant in JOINED:
    distributed.initialize(worker.coordinator, worker.num_processes, worker.process_id)
  t0 = time.perf_counter()
  if worker.variant.startswith("train"):
    result = _train_worker(config, worker)
  else:
    result = _env_step_worker(config, worker)
  result.update(process_id=worker.process_id, device=jax.devices()[0].device_kind,
                n_devices=jax.device_count(), total_s=time.perf_counter() - t0)
  Path(worker.result).write_text(json.dumps(result))


# --------------------------------------------------------------------------------------------------
# Launcher side.


def _free_port() -> int:
  """A TCP port free on this machine now."""
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _worker_env(config: ScalingConfig) -> dict[str, str]:
  """The workers' environment: this one without ``XLA_FLAGS``, with ``JAX_PLATFORMS`` set to the
  config's platform and the repository on ``PYTHONPATH``."""
  env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
  env["JAX_PLATFORMS"] = config.platform
  env["PYTHONPATH"] = os.pathsep.join(
      p for p in (str(REPO_ROOT), os.environ.get("PYTHONPATH")) if p)
  return env


def _worker_command(config: ScalingConfig, worker: Worker) -> list[str]:
  """The command line that runs ``worker`` (:data:`WORKER_MODULE` with its hidden flags)."""
  return [
      sys.executable, "-m", WORKER_MODULE, "--worker", worker.variant, "--process-id",
      str(worker.process_id), "--num-processes",
      str(worker.num_processes), "--coordinator", worker.coordinator, "--sync-dir", worker.sync_dir,
      "--result", worker.result, "--batch",
      str(config.batch), "--steps",
      str(config.steps), "--repeats",
      str(config.repeats), "--task", config.task, "--train-batch",
      str(config.train_batch), "--platform", config.platform
  ]


def _wait(procs: list[subprocess.Popen]) -> str | None:
  """Waits for every worker; ``None`` once all exited, else why it stopped waiting."""
  deadline = time.monotonic() + WORKER_TIMEOUT_S
  while any(p.poll() is None for p in procs):
    if any(p.poll() not in (None, 0) for p in procs):
      return "a worker failed"
    if time.monotonic() > deadline:
      return f"timed out after {WORKER_TIMEOUT_S} s"
    time.sleep(0.5)
  return None


def _launch(variant: str, num_processes: int, config: ScalingConfig, tmp: Path) -> list[dict]:
  """Runs one variant's workers concurrently; returns each worker's result.

  Raises:
    WorkerFailed: a worker failed or they ran past :data:`WORKER_TIMEOUT_S`.
  """
  sync_dir = tmp / variant
  sync_dir.mkdir()
  coordinator = f"127.0.0.1:{_free_port()}"
  env = _worker_env(config)
  procs, logs = [], []
  try:
    for i in range(num_processes):
      worker = Worker(variant, i, num_processes, coordinator, str(sync_dir),
                      str(sync_dir / f"result_{i}.json"))
      logs.append(open(sync_dir / f"worker_{i}.log", "w"))
      procs.append(
          subprocess.Popen(_worker_command(config, worker), env=env, cwd=REPO_ROOT, stdout=logs[-1],
                           stderr=subprocess.STDOUT))
    failed = _wait(procs)
  finally:
    for p in procs:
      if p.poll() is None:
        p.kill()
        p.wait()
    for log in logs:
      log.close()
  if failed or any(p.returncode for p in procs):
    raise WorkerFailed(f"variant '{variant}': {failed or 'a worker failed'}; worker logs in "
                       f"{sync_dir}")
  return [json.loads((sync_dir / f"result_{i}.json").read_text()) for i in range(num_processes)]


def _row(variant: str, workers: list[dict]) -> dict:
  """Total env steps/s of a variant: one global program runs at the pace of its slowest worker;
  independent processes add up."""
  if variant in JOINED:
    total = sum(w["env_steps"] for w in workers) / max(w["run_s"] for w in workers)
  else:
    total = sum(w["env_steps"] / w["run_s"] for w in workers)
  return {
      "variant": variant, "processes": len(workers), "envs_per_process": workers[0]["local_batch"],
      "env_steps_per_s": total, "physics_steps_per_s": total * workers[0]["substeps"],
      "cpu_cores_used": sum(w["cpu_cores_used"] for w in workers
                           ), "compile_s": max(w["compile_s"] for w in workers)
  }


def _summary(rows: list[dict]) -> dict:
  """Sets each row's ``ratio_vs_one_process``; returns what the second core buys."""
  by = {r["variant"]: r for r in rows}
  for r in rows:
    base = by["train_one_process" if r["variant"].startswith("train") else "one_process"]
    r["ratio_vs_one_process"] = r["env_steps_per_s"] / base["env_steps_per_s"]
  summary = {
      "second_core_buys":
          by["two_process_mesh"]["ratio_vs_one_process"],
      "second_core_buys_without_collective":
          by["two_process_independent"]["ratio_vs_one_process"],
      "collective_cost":
          1.0 - (by["two_process_mesh"]["env_steps_per_s"] /
                 by["two_process_independent"]["env_steps_per_s"]),
  }
  if "train_two_process" in by:
    summary["second_core_buys_training"] = by["train_two_process"]["ratio_vs_one_process"]
  return summary


def run_scaling(config: ScalingConfig) -> dict:
  """Runs every variant's workers in turn (progress on stderr) and returns the result object.

  Raises:
    WorkerFailed: a worker failed (its logs are kept in a temporary folder the message names).
  """
  rows = []
  load_at_start = os.getloadavg()[0]
  variants = VARIANTS + (TRAIN_VARIANTS if config.train else ())
  tmp = Path(tempfile.mkdtemp(prefix="bench_devices_"))  # worker logs; kept if a worker fails
  for i, (variant, n) in enumerate(variants):
    print(f"[{i + 1}/{len(variants)}] {variant} ({n} process{'es' if n > 1 else ''})",
          file=sys.stderr, flush=True)
    workers = _launch(variant, n, config, tmp)
    rows.append({**_row(variant, workers), "load_average": round(os.getloadavg()[0], 2)})
    print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
  shutil.rmtree(tmp, ignore_errors=True)
  summary = _summary(rows)
  return {
      "batch": config.batch, "steps": config.steps, "repeats": config.repeats, "task": config.task,
      "platform": config.platform, "cpu_count": multiprocessing.cpu_count(),
      "load_average_at_start": load_at_start,
      "train_batch": config.train_batch if config.train else None,
      "date": time.strftime("%Y-%m-%d %H:%M:%S"), "summary": summary, "rows": rows
  }


def write_report(result: dict, stem: Path) -> None:
  """Writes :func:`run_scaling`'s ``result`` to ``stem.json``, a markdown table with the summary
  to ``stem.md`` and the bar plot to ``stem.png``."""
  stem.parent.mkdir(parents=True, exist_ok=True)
  stem.with_suffix(".json").write_text(json.dumps(result, indent=2))
  cols = ("variant", "processes", "envs_per_process", "env_steps_per_s", "physics_steps_per_s",
          "cpu_cores_used", "compile_s", "ratio_vs_one_process")
  fmt = lambda v: f"{v:,.3g}" if isinstance(v, float) else str(v)
  s = result["summary"]
  lines = [
      f"# What a second CPU device buys (batch {result['batch']}, {result['steps']} control steps, "
      f"task {result['task']})", "",
      f"`python -m {WORKER_MODULE} --batch {result['batch']} --steps "
      f"{result['steps']}`, {result['date']}, {result['cpu_count']} CPUs, load average "
      f"{result['load_average_at_start']:.1f} at the start (shared machine: quote ratios).", "",
      "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)
  ]
  lines += ["| " + " | ".join(fmt(r[c]) for c in cols) + " |" for r in result["rows"]]
  lines += [
      "", f"Two processes on the global 2-device mesh step **{s['second_core_buys']:.2f}x** "
      f"the envs/s of one process (without the per-step collective: "
      f"{s['second_core_buys_without_collective']:.2f}x; the collective costs "
      f"{100 * s['collective_cost']:.0f} %)."
  ]
  if "second_core_buys_training" in s:
    lines.append(f"MASH training (batch {result['train_batch']}): "
                 f"{s['second_core_buys_training']:.2f}x.")
  stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
  _plot(result["rows"], stem.with_suffix(".png"))


def _plot(rows: list[dict], path: Path) -> None:
  """Bars of env steps/s per variant, env step and training side by side, each labelled with its
  ratio to one process."""
  fig = Figure(figsize=(6.5, 3.5))
  ax = fig.subplots()
  names = [r["variant"].replace("_", " ") for r in rows]
  colors = ["tab:green" if r["variant"].startswith("train") else "tab:blue" for r in rows]
  bars = ax.bar(range(len(rows)), [r["env_steps_per_s"] for r in rows], color=colors)
  for bar, r in zip(bars, rows):
    ax.annotate(f"{r['ratio_vs_one_process']:.2f}x",
                (bar.get_x() + bar.get_width() / 2, bar.get_height()), ha="center", va="bottom",
                fontsize=8)
  ax.set_xticks(range(len(rows)), names, rotation=20, ha="right", fontsize=8)
  ax.set_ylabel("env steps / s")
  ax.set_title(
      "one process vs two joined by jax.distributed (blue: env step, "
      "green: MASH training)", fontsize=8)
  ax.grid(axis="y", alpha=0.3)
  fig.tight_layout()
  fig.savefig(path, dpi=120)
