"""``python -m experiments.benchmark [--quick]``: throughput of physics, env and training, in one process.

Prints one JSON object and writes it to ``benchmark.json``: bare ``mjx.step`` physics steps/s on the
env's own model and batch, the batched env step, full training (rollout + GAE + updates) for MASH,
our single-agent PPO and Brax's own PPO trainer on the same env, batch, rollout length and network
sizes, compile times, and peak memory. Because every figure comes from one process, their ratios
hold on a noisy machine.

``--stages env,mash,brax_ppo`` measures only the named stages (of ``STAGES``), for a bounded run
on a lent machine; ratios are given for the pairs measured.

``--impl warp`` runs the physics through MuJoCo Warp instead of MJX's JAX implementation (the
``impl`` field of the JSON says which; Warp's contact buffer is sized for the batch measured).

``--breakdown`` splits an iteration's time into the env rollout, the updates alone and the rest, for
MASH and PPO (``breakdown.json``). ``--sweep batch`` measures throughput against batch size and
writes ``benchmarks/scaling_batch.*``; ``--sweep physics`` measures each solver setting tried
(physics steps/s, standing drift).
"""

from __future__ import annotations

import dataclasses
import json
import resource
import sys
import time
from pathlib import Path

from experiments import common

STAGES = ("physics", "env", "mash", "ppo", "brax_ppo")
MAX_BATCH = 2**20  # envs; TrainConfig's own cap (mash.config.SIZE_CAPS)


def _device_kind() -> str:
  import jax
  return jax.devices()[0].device_kind


def _peak_rss_mb() -> float:
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _peak_device_mb() -> float | None:
  """Peak accelerator memory in use by this process (MB), where the backend reports it (GPU, TPU;
  not the CPU backend, whose arrays are in ``peak_rss_mb``)."""
  import jax
  stats = jax.devices()[0].memory_stats() or {}
  peak = stats.get("peak_bytes_in_use")
  return None if peak is None else peak / 2**20


def train_throughput(env, train_cfg, calls: int) -> tuple[float, float]:
  """(env steps/s of our training loop, compile seconds of one training call)."""
  import jax
  from mash import train as train_lib
  trainer = train_lib.make_train(train_cfg, env)
  state = trainer.init(jax.random.PRNGKey(0))
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


def brax_ppo_throughput(env_cfg, train_cfg, calls: int) -> tuple[float, float]:
  """Brax's PPO trainer on our env (same batch, unroll, epochs, minibatches, network sizes)."""
  import functools
  from brax.training.agents.ppo import networks as ppo_networks
  from brax.training.agents.ppo import train as ppo_train
  from mash import brax_compat
  brax_compat.patch_jax_for_brax()
  env = brax_compat.BraxView(env_cfg)
  per_epoch = train_cfg.num_envs * train_cfg.unroll_length * train_cfg.iterations_per_call
  stamps = []
  factory = functools.partial(
      ppo_networks.make_ppo_networks, policy_hidden_layer_sizes=train_cfg.actor_hidden,
      value_hidden_layer_sizes=train_cfg.critic_hidden, policy_obs_key="state",
      value_obs_key="privileged_state")
  # Brax runs num_evals - 1 training epochs of num_timesteps / (num_evals - 1) steps each and, with
  # run_evals off, calls progress_fn after each. The first epoch carries the compile; under JAX 0.10
  # Brax's pmapped epoch compiles once more on its second call (measured: the same program, 24 s at
  # a tiny batch), and from the third on it runs compiled. So time at least three epochs.
  num_evals = calls + 3
  t_start = time.perf_counter()
  ppo_train.train(
      environment=env, num_timesteps=per_epoch * (num_evals - 1), num_envs=train_cfg.num_envs,
      episode_length=1000, unroll_length=train_cfg.unroll_length,
      # Brax's batch_size counts trajectories of unroll_length per minibatch, not transitions.
      batch_size=train_cfg.num_envs // train_cfg.num_minibatches,
      num_minibatches=train_cfg.num_minibatches, num_updates_per_batch=train_cfg.num_epochs,
      learning_rate=train_cfg.learning_rate, entropy_cost=train_cfg.entropy_coef,
      discounting=train_cfg.gamma, gae_lambda=train_cfg.gae_lambda,
      normalize_observations=True, network_factory=factory, num_evals=num_evals,
      run_evals=False, progress_fn=lambda step, metrics: stamps.append(time.perf_counter()),
      seed=0)
  epochs = [b - a for a, b in zip(stamps[:-1], stamps[1:])]
  print(f"brax ppo: first epoch {stamps[0] - t_start:.1f} s, then {[round(e, 2) for e in epochs]}",
        file=sys.stderr, flush=True)
  steady = min(epochs[1:])
  return per_epoch / steady, (stamps[0] - t_start) - steady


def update_seconds(env, train_cfg, calls: int = 3) -> float:
  """Seconds of one iteration's updates (``num_epochs x num_minibatches`` MAPPO steps) run alone
  on a synthetic batch of the iteration's shapes: the floor the updates put under an iteration,
  whatever the loop around them does."""
  import jax
  import jax.numpy as jnp
  from mash import losses
  from mash import normalization
  from mash import throughput
  from mash import train as train_lib
  trainer = train_lib.make_train(train_cfg, env)
  groups = trainer.networks.groups
  n = train_cfg.num_envs * train_cfg.unroll_length
  n_agents = sum(g.n_agents for g in groups)
  keys = iter(jax.random.split(jax.random.PRNGKey(0), 2 * len(groups) + 3))
  normal = lambda shape: jax.random.normal(next(keys), shape)
  obs = {g.name: normal((n, g.n_agents, g.obs_dim)) for g in groups}
  obs["critic"] = normal((n, env.critic_obs_size))
  batch = losses.LossBatch(
      obs=obs, actions={g.name: normal((n, g.n_agents, g.act_dim)) for g in groups},
      log_probs=jnp.zeros((n, n_agents)), values=jnp.zeros((n, n_agents)),
      advantages=normal((n, n_agents)), returns=jnp.zeros((n, n_agents)), weights=jnp.ones((n,)))
  normalizer = normalization.init_normalizer(
      {**{g.name: g.obs_dim for g in groups}, "critic": env.critic_obs_size})
  params = trainer.networks.init(jax.random.PRNGKey(1))
  opt = train_lib.OptimizerState(params, trainer.optimizer.init(params))
  update = jax.jit(lambda o, b, k: trainer.update(o, normalizer, b, k)[0].params)
  return throughput.time_call(update, opt, batch, jax.random.PRNGKey(2), repeats=calls).run_s


def train_breakdown(env, train_cfg, calls: int = 2) -> dict:
  """Where a training iteration's time goes, in seconds per iteration: the env rollout alone (random
  actions), the updates alone (:func:`update_seconds`), and the whole training call; the rest is
  the networks in the rollout, GAE and bookkeeping. ``train_vs_env_ceiling`` is the train/env
  ratio the updates allow even with no other cost."""
  from mash import throughput
  sps_env, _ = throughput.env_steps(env, train_cfg.num_envs, train_cfg.unroll_length,
                                    repeats=calls)
  steps = train_cfg.num_envs * train_cfg.unroll_length
  t_env = steps / sps_env
  t_all = steps / train_throughput(env, train_cfg, calls)[0]
  t_updates = update_seconds(env, train_cfg)
  return {"env_rollout_s": t_env, "updates_alone_s": t_updates,
          "rest_s": t_all - t_env - t_updates, "iteration_s": t_all,
          "train_vs_env": t_env / t_all, "train_vs_env_ceiling": t_env / (t_env + t_updates),
          "epochs": train_cfg.num_epochs, "minibatches": train_cfg.num_minibatches}


def _env_config(task: str, impl: str, batch: int, robot: str = "booster_t1", **fields):
  """The benchmarked env's config: ``robot``, physics through ``impl``, Warp's contacts sized for
  ``batch``."""
  from mash import env as env_lib
  from mash import robots
  physics = robots.PhysicsConfig(impl=impl, warp_max_envs=batch)
  return env_lib.EnvConfig(task=task, robot=robot, physics=physics, **fields)


def run_benchmark(quick: bool, batch: int | None, task: str, out: Path | None = None,
                  stages: tuple[str, ...] = STAGES, impl: str = "jax",
                  robot: str = "booster_t1") -> dict:
  """The figures of ``stages`` (default: all) at one batch, the physics run by MJX's ``impl``
  ('jax' or 'warp'). With ``out``, the JSON is rewritten after every stage (``complete`` false
  until the last), so a run stopped early keeps what it measured."""
  import jax
  from mash import config as train_config
  from mash import env as env_lib
  from mash import throughput
  batch = batch or (256 if quick else 1024)
  unroll = 24
  iters = 2 if quick else 4
  env_cfg = _env_config(task, impl, batch, robot)
  env = env_lib.MashEnv(env_cfg)
  result = {"device": _device_kind(), "backend": jax.default_backend(), "robot": env.spec.name,
            "n_devices": jax.device_count(), "impl": impl, "batch": batch,
            "substeps": env.n_substeps, "task": task, "quick": quick,
            "date": time.strftime("%Y-%m-%d %H:%M:%S"), "stages": list(stages),
            "complete": False}
  todo = [s for s in STAGES if s in stages]
  label = lambda name: f"[{todo.index(name) + 1}/{len(todo)}]"

  def save():
    result["peak_rss_mb"] = _peak_rss_mb()
    result["peak_device_mb"] = _peak_device_mb()
    if out is not None:
      out.write_text(json.dumps(result, indent=2))

  steps = 20 if quick else 50
  if "physics" in todo:
    print(f"{label('physics')} bare mjx.step, batch {batch}", file=sys.stderr, flush=True)
    result["physics_steps_per_s"], _ = throughput.bare_physics(env, batch, steps)
    save()
  if "env" in todo:
    print(f"{label('env')} env step, batch {batch}", file=sys.stderr, flush=True)
    env_sps, _ = throughput.env_steps(env, batch, steps)
    result["env_steps_per_s"] = env_sps
    result["env_physics_equivalent_per_s"] = env_sps * env.n_substeps
    save()
  train_cfg = dataclasses.replace(
      train_config.TrainConfig(), num_envs=batch, unroll_length=unroll, iterations_per_call=iters,
      actor_hidden=(256, 128, 64), critic_hidden=(256, 128, 64))
  result["unroll_length"] = unroll
  result["network"] = {"actor": train_cfg.actor_hidden, "critic": train_cfg.critic_hidden}
  tr = result["train_env_steps_per_s"] = {}
  result["compile_s"] = {}
  for name in ("mash", "ppo"):
    if name in todo:
      print(f"{label(name)} training: {name}", file=sys.stderr, flush=True)
      e = env_lib.MashEnv(dataclasses.replace(env_cfg, partition=name))
      tr[name], result["compile_s"][name] = train_throughput(e, train_cfg, calls=2)
      save()
  if "brax_ppo" in todo:
    print(f"{label('brax_ppo')} training: brax_ppo", file=sys.stderr, flush=True)
    tr["brax_ppo"], result["compile_s"]["brax_ppo"] = brax_ppo_throughput(env_cfg, train_cfg,
                                                                          calls=2)
  result["ratios"] = _ratios(result)
  result["complete"] = True
  save()
  return result


def _ratios(result: dict) -> dict:
  """``env_vs_physics``, ``mash_train_vs_env``, ``mash_vs_ppo``, ``mash_vs_brax_ppo``: those whose
  two figures were measured."""
  tr = result.get("train_env_steps_per_s", {})
  figures = {"physics": result.get("physics_steps_per_s"),
             "env_physics": result.get("env_physics_equivalent_per_s"),
             "env": result.get("env_steps_per_s"), **tr}
  pairs = {"env_vs_physics": ("env_physics", "physics"), "mash_train_vs_env": ("mash", "env"),
           "mash_vs_ppo": ("mash", "ppo"), "mash_vs_brax_ppo": ("mash", "brax_ppo")}
  return {name: figures[a] / figures[b] for name, (a, b) in pairs.items()
          if figures.get(a) is not None and figures.get(b) is not None}


def sweep_batch(batches: list[int], task: str, stem: Path | None = None,
                impl: str = "jax", robot: str = "booster_t1") -> list[dict]:
  """Physics, env and MASH training throughput per batch size (one process), through MJX's
  ``impl``.

  With ``stem``, the table is rewritten after every batch (a run stopped early keeps its rows)."""
  from mash import config as train_config
  from mash import env as env_lib
  from mash import throughput
  env = env_lib.MashEnv(_env_config(task, impl, max(batches), robot))
  rows = []
  for b in batches:
    print(f"batch {b}", file=sys.stderr, flush=True)
    phys, _ = throughput.bare_physics(env, b, 10, repeats=1)
    envs, _ = throughput.env_steps(env, b, 10, repeats=1)
    cfg = dataclasses.replace(train_config.TrainConfig(), num_envs=b, unroll_length=16,
                              iterations_per_call=1, actor_hidden=(256, 128, 64),
                              critic_hidden=(256, 128, 64))
    train_sps, _ = train_throughput(env, cfg, calls=1)
    rows.append({"batch": b, "physics_steps_per_s": phys, "env_steps_per_s": envs,
                 "train_env_steps_per_s": train_sps, "device": _device_kind(), "impl": impl})
    if stem is not None:
      _write_table(rows, stem, "batch")
  return rows


def sweep_physics(task: str, robot: str = "booster_t1") -> list[dict]:
  """Each solver setting: MJX physics steps/s (batch 256) and standing drift over 10 s (MuJoCo C,
  same model and options, PD at the default pose, zero action)."""
  import mujoco
  import numpy as np
  from mash import env as env_lib
  from mash import robots
  from mash import throughput
  settings = [(0.005, 1), (0.005, 3), (0.004, 1), (0.002, 3)]
  rows = []
  for sim_dt, iterations in settings:
    print(f"sim_dt {sim_dt}, iterations {iterations}", file=sys.stderr, flush=True)
    physics = robots.PhysicsConfig(sim_dt=sim_dt, iterations=iterations)
    env = env_lib.MashEnv(env_lib.EnvConfig(task=task, robot=robot, physics=physics))
    phys, _ = throughput.bare_physics(env, 256, 10, repeats=1)
    lay, m, addr = env.layout, env.mj_model, env.joint_addresses()
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    q0, kp, kd, lim = lay.default_pose, lay.kp, lay.kd, lay.torque_limit
    start = d.qpos[:3].copy()
    for _ in range(int(10.0 / sim_dt)):
      d.ctrl[addr.actuator] = np.clip(kp * (q0 - d.qpos[addr.qpos]) - kd * d.qvel[addr.dof],
                                      -lim, lim)
      mujoco.mj_step(m, d)
    rows.append({"sim_dt": sim_dt, "iterations": iterations, "substeps": env.n_substeps,
                 "physics_steps_per_s": phys, "control_steps_per_s": phys / env.n_substeps,
                 "standing_drift_xy_m": float(np.linalg.norm(d.qpos[:2] - start[:2])),
                 "standing_height_change_m": float(d.qpos[2] - start[2]),
                 "upright_after_10s": bool(d.qpos[2] > 0.6)})
  return rows


def _write_table(rows: list[dict], stem: Path, x: str) -> None:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  stem.parent.mkdir(parents=True, exist_ok=True)
  stem.with_suffix(".json").write_text(json.dumps(rows, indent=2))
  keys = [k for k in rows[0] if k != x and isinstance(rows[0][k], (int, float))]
  lines = ["| " + " | ".join([x] + keys) + " |", "|" + "---|" * (len(keys) + 1)]
  for r in rows:
    lines.append("| " + " | ".join([str(r[x])] + [f"{r[k]:,.3g}" if isinstance(r[k], float)
                                                    else str(r[k]) for k in keys]) + " |")
  stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
  if x == "batch":
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for k in ("physics_steps_per_s", "env_steps_per_s", "train_env_steps_per_s"):
      ax.plot([r[x] for r in rows], [r[k] for r in rows], "o-", label=k)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("batch (envs)")
    ax.set_ylabel("steps / s")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(stem.with_suffix(".png"), dpi=120)
    plt.close(fig)


def _check_impl(impl: str, sweep: str | None) -> None:
  """``--impl``: a known MJX implementation, installed; the physics sweep measures MJX's JAX one
  only (its drift figures come from MuJoCo C)."""
  from mash import robots
  try:
    robots.check_physics(robots.PhysicsConfig(impl=impl))
  except ValueError as e:
    raise common.UserError(f"--{e}") from None
  if impl != "jax" and sweep == "physics":
    raise common.UserError("--sweep physics measures the jax implementation only; drop --impl")


def main(argv=None) -> None:
  p = common.Parser(prog="python -m experiments.benchmark", description=__doc__.splitlines()[0])
  p.add_argument("--quick", action="store_true", help="smaller batch and fewer repeats (< 15 min CPU)")
  p.add_argument("--batch", type=int, default=None)
  p.add_argument("--task", default="bipedal")
  p.add_argument("--out", default=None,
                 help="JSON file (default benchmark.json, or breakdown.json with --breakdown)")
  p.add_argument("--sweep", default=None, help="batch | physics")
  p.add_argument("--breakdown", action="store_true",
                 help="time the env rollout, the updates and the rest of a MASH and a PPO iteration")
  p.add_argument("--batches", default="64,256,1024,4096")
  p.add_argument("--stages", default=",".join(STAGES),
                 help=f"comma-separated subset of {','.join(STAGES)} (default: all)")
  p.add_argument("--dir", default="benchmarks", help="where --sweep writes its table and plot")
  p.add_argument("--robot", default="booster_t1", metavar="NAME|FILE.toml",
                 help="a shipped robot (booster_t1, unitree_g1) or a robot file")
  p.add_argument("--impl", default="jax",
                 help="MJX implementation of the physics: jax (default) or warp (MuJoCo Warp)")
  args = p.parse_args(argv)
  with common.user_errors():
    common.check_paths({"--out": args.out, "--dir": args.dir})
    _check_impl(args.impl, args.sweep)
    from mash import env as env_lib
    try:
      env_lib.check_config(env_lib.EnvConfig(robot=args.robot))
    except ValueError as e:
      raise common.UserError(f"--robot: {e}") from None
    common.check_task(args.task)
    if args.batch is not None and not 0 <= args.batch <= MAX_BATCH:
      raise common.UserError(f"--batch must be a number of envs in [1, {MAX_BATCH}] (0: the "
                             f"default), got {args.batch}")
    if args.sweep in ("batch", "physics"):
      common.check_writable_dir(args.dir, "--dir")
    else:
      common.check_writable_file(
          args.out or ("breakdown.json" if args.breakdown else "benchmark.json"), "--out")
    if args.sweep == "batch":
      try:
        batches = [int(b) for b in args.batches.split(",")]
      except ValueError:
        batches = []
      if not batches or not all(1 <= b <= MAX_BATCH for b in batches):
        raise common.UserError(f"--batches '{args.batches}': expected comma-separated numbers of "
                               f"envs in [1, {MAX_BATCH}], e.g. 64,256,1024")
      rows = sweep_batch(batches, args.task, Path(args.dir) / "scaling_batch", args.impl,
                         args.robot)
      print(json.dumps(rows, indent=2))
      return
    if args.sweep == "physics":
      rows = sweep_physics(args.task, args.robot)
      _write_table(rows, Path(args.dir) / "physics_settings", "sim_dt")
      print(json.dumps(rows, indent=2))
      return
    if args.breakdown:
      from mash import config as train_config
      from mash import env as env_lib
      batch = args.batch or 256
      cfg = dataclasses.replace(train_config.TrainConfig(), num_envs=batch, unroll_length=24,
                                iterations_per_call=2, actor_hidden=(256, 128, 64),
                                critic_hidden=(256, 128, 64))
      result = {"batch": batch, "device": _device_kind(), "impl": args.impl,
                "date": time.strftime("%Y-%m-%d %H:%M:%S")}
      for partition in ("mash", "ppo"):
        print(f"breakdown: {partition}", file=sys.stderr, flush=True)
        env = env_lib.MashEnv(_env_config(args.task, args.impl, batch, args.robot,
                                          partition=partition))
        result[partition] = train_breakdown(env, cfg)
      result["updates_alone_mash_vs_ppo"] = (result["mash"]["updates_alone_s"]
                                             / result["ppo"]["updates_alone_s"])
      Path(args.out or "breakdown.json").write_text(json.dumps(result, indent=2))
      print(json.dumps(result, indent=2))
      return
    if args.sweep is not None:
      raise common.UserError(f"--sweep '{args.sweep}' is unknown; expected batch or physics")
    stages = tuple(args.stages.split(","))
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
      raise common.UserError(f"--stages '{args.stages}': expected a comma-separated subset of "
                             f"{','.join(STAGES)}")
    result = run_benchmark(args.quick, args.batch, args.task, Path(args.out or "benchmark.json"),
                           stages, args.impl, args.robot)
    print(json.dumps(result))


if __name__ == "__main__":
  main()
