"""Throughput of physics, env and training in one process: the figures ``experiments.benchmark``
prints.

:func:`run_benchmark` measures bare ``mjx.step`` physics steps/s on the env's own model and batch,
the batched env step, and full training (rollout + GAE + updates) for MASH, our single-agent PPO and
Brax's own PPO trainer on the same env, batch, rollout length and network sizes, with compile times
and peak memory. Every figure comes from one process, so their ratios hold on a noisy machine.
:func:`breakdown` splits an iteration's time into the env rollout, the updates alone and the rest.
The sweeps over batch size and solver settings live in :mod:`mash.bench.sweeps`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import resource
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
from brax.training.agents.ppo import networks as ppo_networks
from brax.training.agents.ppo import train as ppo_train

from mash.bench import brax_compat, throughput
from mash.rl import config as train_config
from mash.rl import losses, mappo, normalization
from mash.rl import trainer as trainer_lib
from mash.sim import env as env_lib
from mash.sim import env_config
from mash.sim import model as model_lib

STAGES = ("physics", "env", "mash", "ppo", "brax_ppo")
BENCH_HIDDEN = (256, 128, 64)  # actor and critic hidden layers of every benchmarked trainer


def device_kind() -> str:
  """The first device's kind, e.g. ``'cpu'`` or ``'NVIDIA H100 80GB HBM3'``."""
  return jax.devices()[0].device_kind


def now() -> str:
  """The local time as the benchmark files record it."""
  return time.strftime("%Y-%m-%d %H:%M:%S")


def _peak_rss_mb() -> float:
  """Peak resident memory of this process (MB)."""
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _peak_device_mb() -> float | None:
  """Peak accelerator memory in use by this process (MB), where the backend reports it (GPU, TPU;
  not the CPU backend, whose arrays are in ``peak_rss_mb``)."""
  stats = jax.devices()[0].memory_stats() or {}
  peak = stats.get("peak_bytes_in_use")
  return None if peak is None else peak / 2**20


def bench_train_config(batch: int, unroll: int, iterations: int) -> train_config.TrainConfig:
  """The default training config at ``batch`` envs, ``unroll`` steps per rollout, ``iterations``
  per training call, with the benchmark's network sizes (:data:`BENCH_HIDDEN`)."""
  return dataclasses.replace(train_config.TrainConfig(), num_envs=batch, unroll_length=unroll,
                             iterations_per_call=iterations, actor_hidden=BENCH_HIDDEN,
                             critic_hidden=BENCH_HIDDEN)


def bench_env_config(task: str, impl: str, batch: int, robot: str = "booster_t1",
                     **fields) -> env_config.EnvConfig:
  """The benchmarked env's config: ``robot``, physics through ``impl``, Warp's contacts sized for
  ``batch``; ``fields`` are further ``EnvConfig`` fields (e.g. ``partition``)."""
  physics = model_lib.PhysicsConfig(impl=impl, warp_max_envs=batch)
  return env_config.EnvConfig(task=task, robot=robot, physics=physics, **fields)


def train_throughput(env: env_lib.MashEnv, train_cfg: train_config.TrainConfig,
                     calls: int) -> tuple[float, float]:
  """Times our training loop: a first (compiling) call, then the best of ``calls`` calls.

  Returns:
    (env steps/s of training, compile seconds of one training call).
  """
  trainer = trainer_lib.make_trainer(train_cfg, env)
  state = trainer.init()
  t0 = time.perf_counter()
  state, m = trainer.train_epoch(state)
  jax.block_until_ready(m)
  first = time.perf_counter() - t0
  best = float("inf")
  for _ in range(calls):
    t0 = time.perf_counter()
    state, m = trainer.train_epoch(state)
    jax.block_until_ready(m)
    best = min(best, time.perf_counter() - t0)
  steps = train_cfg.num_envs * train_cfg.unroll_length * train_cfg.iterations_per_call
  return steps / best, first - best


def brax_ppo_throughput(env_cfg: env_config.EnvConfig, train_cfg: train_config.TrainConfig,
                        calls: int) -> tuple[float, float]:
  """Brax's PPO trainer on our env (same batch, unroll, epochs, minibatches, network sizes).

  Returns:
    (env steps/s of Brax's steady training epochs, compile seconds of its first epoch).
  """
  brax_compat.patch_jax_for_brax()
  env = brax_compat.BraxView(env_cfg)
  per_epoch = train_cfg.num_envs * train_cfg.unroll_length * train_cfg.iterations_per_call
  stamps = []
  factory = functools.partial(ppo_networks.make_ppo_networks,
                              policy_hidden_layer_sizes=train_cfg.actor_hidden,
                              value_hidden_layer_sizes=train_cfg.critic_hidden,
                              policy_obs_key="state", value_obs_key="privileged_state")
  # Brax runs num_evals - 1 training epochs of num_timesteps / (num_evals - 1) steps each and, with
  # run_evals off, calls progress_fn after each. The first epoch carries the compile; under JAX 0.10
  # Brax's pmapped epoch compiles once more on its second call (measured: the same program, 24 s at
  # a tiny batch), and from the third on it runs compiled. So time at least three epochs.
  num_evals = calls + 3
  t_start = time.perf_counter()
  ppo_train.train(
      environment=env,
      num_timesteps=per_epoch * (num_evals - 1),
      num_envs=train_cfg.num_envs,
      episode_length=1000,
      unroll_length=train_cfg.unroll_length,
      # Brax's batch_size counts trajectories of unroll_length per minibatch, not transitions.
      batch_size=train_cfg.num_envs // train_cfg.num_minibatches,
      num_minibatches=train_cfg.num_minibatches,
      num_updates_per_batch=train_cfg.num_epochs,
      learning_rate=train_cfg.learning_rate,
      entropy_cost=train_cfg.entropy_coef,
      discounting=train_cfg.gamma,
      gae_lambda=train_cfg.gae_lambda,
      normalize_observations=True,
      network_factory=factory,
      num_evals=num_evals,
      run_evals=False,
      progress_fn=lambda step, metrics: stamps.append(time.perf_counter()),
      seed=0)
  epochs = [b - a for a, b in zip(stamps[:-1], stamps[1:])]
  print(f"brax ppo: first epoch {stamps[0] - t_start:.1f} s, then {[round(e, 2) for e in epochs]}",
        file=sys.stderr, flush=True)
  steady = min(epochs[1:])
  return per_epoch / steady, (stamps[0] - t_start) - steady


def _synthetic_batch(groups, n: int, critic_obs_size: int) -> losses.LossBatch:
  """A random ``LossBatch`` of ``n`` transitions shaped as the groups' (values and returns zero)."""
  n_agents = sum(g.n_agents for g in groups)
  keys = iter(jax.random.split(jax.random.PRNGKey(0), 2 * len(groups) + 3))
  normal = lambda shape: jax.random.normal(next(keys), shape)
  obs = {g.name: normal((n, g.n_agents, g.obs_dim)) for g in groups}
  obs["critic"] = normal((n, critic_obs_size))
  return losses.LossBatch(obs=obs, actions={
      g.name: normal((n, g.n_agents, g.act_dim)) for g in groups
  }, log_probs=jnp.zeros((n, n_agents)), values=jnp.zeros((n, n_agents)), advantages=normal(
      (n, n_agents)), returns=jnp.zeros((n, n_agents)), weights=jnp.ones((n,)))


def update_seconds(env: env_lib.MashEnv, train_cfg: train_config.TrainConfig,
                   calls: int = 3) -> float:
  """Seconds of one iteration's updates (``num_epochs x num_minibatches`` MAPPO steps) run alone
  on a synthetic batch of the iteration's shapes: the floor the updates put under an iteration,
  whatever the loop around them does."""
  algo = mappo.make_mappo(train_cfg, env)
  groups = algo.networks.groups
  batch = _synthetic_batch(groups, train_cfg.num_envs * train_cfg.unroll_length,
                           env.critic_obs_size)
  normalizer = normalization.init_normalizer(
      {**{g.name: g.obs_dim for g in groups}, "critic": env.critic_obs_size})
  params = algo.networks.init(jax.random.PRNGKey(1))
  opt = mappo.OptimizerState(params, algo.optimizer.init(params))
  update = jax.jit(lambda o, b, k: algo.update(o, normalizer, b, k)[0].params)
  return throughput.time_call(update, opt, batch, jax.random.PRNGKey(2), repeats=calls).run_s


def train_breakdown(env: env_lib.MashEnv, train_cfg: train_config.TrainConfig,
                    calls: int = 2) -> dict:
  """Where a training iteration's time goes, in seconds per iteration: the env rollout alone (random
  actions), the updates alone (:func:`update_seconds`), and the whole training call; the rest is
  the networks in the rollout, GAE and bookkeeping. ``train_vs_env_ceiling`` is the train/env
  ratio the updates allow even with no other cost."""
  sps_env, _ = throughput.env_steps(env, train_cfg.num_envs, train_cfg.unroll_length, repeats=calls)
  steps = train_cfg.num_envs * train_cfg.unroll_length
  t_env = steps / sps_env
  t_all = steps / train_throughput(env, train_cfg, calls)[0]
  t_updates = update_seconds(env, train_cfg)
  return {
      "env_rollout_s": t_env, "updates_alone_s": t_updates, "rest_s": t_all - t_env - t_updates,
      "iteration_s": t_all, "train_vs_env": t_env / t_all,
      "train_vs_env_ceiling": t_env / (t_env + t_updates), "epochs": train_cfg.num_epochs,
      "minibatches": train_cfg.num_minibatches
  }


def breakdown(task: str, batch: int | None, impl: str, robot: str, out: Path) -> dict:
  """:func:`train_breakdown` of a MASH and a PPO iteration at ``batch`` envs (default 256), with
  the ratio of their updates alone; written to ``out`` as JSON and returned."""
  batch = batch or 256
  cfg = bench_train_config(batch, unroll=24, iterations=2)
  result = {"batch": batch, "device": device_kind(), "impl": impl, "date": now()}
  for partition in ("mash", "ppo"):
    print(f"breakdown: {partition}", file=sys.stderr, flush=True)
    env = env_lib.MashEnv(bench_env_config(task, impl, batch, robot, partition=partition))
    result[partition] = train_breakdown(env, cfg)
  result["updates_alone_mash_vs_ppo"] = (result["mash"]["updates_alone_s"] /
                                         result["ppo"]["updates_alone_s"])
  out.write_text(json.dumps(result, indent=2))
  return result


def ratios(result: dict) -> dict:
  """``env_vs_physics``, ``mash_train_vs_env``, ``mash_vs_ppo``, ``mash_vs_brax_ppo``: those whose
  two figures were measured."""
  tr = result.get("train_env_steps_per_s", {})
  figures = {
      "physics": result.get("physics_steps_per_s"),
      "env_physics": result.get("env_physics_equivalent_per_s"),
      "env": result.get("env_steps_per_s"), **tr
  }
  pairs = {
      "env_vs_physics": ("env_physics", "physics"), "mash_train_vs_env": ("mash", "env"),
      "mash_vs_ppo": ("mash", "ppo"), "mash_vs_brax_ppo": ("mash", "brax_ppo")
  }
  return {
      name: figures[a] / figures[b]
      for name, (a, b) in pairs.items()
      if figures.get(a) is not None and figures.get(b) is not None
  }


class _Progress:
  """Announces each measured stage (``[i/n] ...`` on stderr) and rewrites the result file."""

  def __init__(self, result: dict, todo: list[str], out: Path | None):
    self.result, self.todo, self.out = result, todo, out

  def start(self, stage: str, what: str) -> None:
    """Prints ``[i/n] what`` for ``stage``."""
    print(f"[{self.todo.index(stage) + 1}/{len(self.todo)}] {what}", file=sys.stderr, flush=True)

  def save(self) -> None:
    """Records peak memory so far and, with an output file, rewrites the JSON."""
    self.result["peak_rss_mb"] = _peak_rss_mb()
    self.result["peak_device_mb"] = _peak_device_mb()
    if self.out is not None:
      self.out.write_text(json.dumps(self.result, indent=2))


def _measure_env(env: env_lib.MashEnv, batch: int, steps: int, progress: _Progress) -> None:
  """The ``physics`` and ``env`` stages (those in ``progress.todo``), into ``progress.result``."""
  result = progress.result
  if "physics" in progress.todo:
    progress.start("physics", f"bare mjx.step, batch {batch}")
    result["physics_steps_per_s"], _ = throughput.bare_physics(env, batch, steps)
    progress.save()
  if "env" in progress.todo:
    progress.start("env", f"env step, batch {batch}")
    env_sps, _ = throughput.env_steps(env, batch, steps)
    result["env_steps_per_s"] = env_sps
    result["env_physics_equivalent_per_s"] = env_sps * env.n_substeps
    progress.save()


def _measure_training(env_cfg: env_config.EnvConfig, train_cfg: train_config.TrainConfig,
                      progress: _Progress) -> None:
  """The training stages (``mash``, ``ppo``, ``brax_ppo`` of ``progress.todo``): env steps/s and
  compile seconds, into ``progress.result``."""
  result = progress.result
  result["unroll_length"] = train_cfg.unroll_length
  result["network"] = {"actor": train_cfg.actor_hidden, "critic": train_cfg.critic_hidden}
  tr = result["train_env_steps_per_s"] = {}
  result["compile_s"] = {}
  for name in ("mash", "ppo"):
    if name in progress.todo:
      progress.start(name, f"training: {name}")
      e = env_lib.MashEnv(dataclasses.replace(env_cfg, partition=name))
      tr[name], result["compile_s"][name] = train_throughput(e, train_cfg, calls=2)
      progress.save()
  if "brax_ppo" in progress.todo:
    progress.start("brax_ppo", "training: brax_ppo")
    tr["brax_ppo"], result["compile_s"]["brax_ppo"] = brax_ppo_throughput(
        env_cfg, train_cfg, calls=2)


def run_benchmark(quick: bool, batch: int | None, task: str, out: Path | None = None,
                  stages: tuple[str, ...] = STAGES, impl: str = "jax",
                  robot: str = "booster_t1") -> dict:
  """The figures of ``stages`` (default: all) at one batch, the physics run by MJX's ``impl``.

  Args:
    quick: a smaller default batch (256, else 1024) and fewer steps and iterations per call.
    batch: envs stepped at once (``None`` or 0: the default).
    task: the task whose env is measured.
    out: with it, the JSON is rewritten after every stage (``complete`` false until the last), so
      a run stopped early keeps what it measured.
    stages: which of :data:`STAGES` to measure.
    impl: MJX's implementation of the physics, ``'jax'`` or ``'warp'``.
    robot: a shipped robot's name or a robot file.

  Returns:
    The result object (``ratios`` for the pairs measured, ``complete`` true).
  """
  batch = batch or (256 if quick else 1024)
  env_cfg = bench_env_config(task, impl, batch, robot)
  env = env_lib.MashEnv(env_cfg)
  result = {
      "device": device_kind(), "backend": jax.default_backend(), "robot": env.spec.name,
      "n_devices": jax.device_count(), "impl": impl, "batch": batch, "substeps": env.n_substeps,
      "task": task, "quick": quick, "date": now(), "stages": list(stages), "complete": False
  }
  progress = _Progress(result, [s for s in STAGES if s in stages], out)
  _measure_env(env, batch, 20 if quick else 50, progress)
  train_cfg = bench_train_config(batch, unroll=24, iterations=2 if quick else 4)
  _measure_training(env_cfg, train_cfg, progress)
  result["ratios"] = ratios(result)
  result["complete"] = True
  progress.save()
  return result
