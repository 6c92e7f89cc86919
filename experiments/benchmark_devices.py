"""``python -m experiments.benchmark_devices [--batch 256] [--steps 20]``: what a second CPU device buys.

Measures the real MJX env's batched env step (PD, randomized model, observations, reward, auto-reset;
not training) in separate worker processes, launched by this script:

- ``one_process``: one process, one CPU device, ``B`` envs;
- ``two_process_mesh``: two processes joined by ``jax.distributed`` (Gloo) into a global 2-device
  mesh, each device stepping ``B/2`` envs under ``shard_map``, with one cross-process ``psum``
  per control step (a sync per step: more often than training synchronizes per env step);
- ``two_process_independent``: two unconnected processes, each stepping its own ``B/2`` envs at
  the same time (no collective): the upper bound of the mesh variant, so
  ``two_process_mesh / two_process_independent`` is the price of the collective;
- with ``--train``: the MASH trainer on the real env, one process vs two processes over the
  global mesh (:func:`mash.distributed.make_distributed_trainer`), small batch.

Each worker compiles, warms up, waits until its peers are ready, then times ``--repeats`` calls and
keeps the best. Prints the table as JSON and writes ``benchmarks/scaling_devices.json`` and ``.md``
with ``ratio_vs_one_process`` (total env steps/s over the one-process figure): what the second core
buys. The machine may be shared, so quote the ratios, not the absolute figures (the load average
at the start is recorded).

One process with two forced CPU devices is not measured: a sharded MJX step deadlocks there.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from experiments import common

WORKER_TIMEOUT_S = 600
PLATFORMS = ('cpu', 'gpu', 'cuda', 'rocm', 'tpu')  # JAX_PLATFORMS values for the workers
# Sanity caps: TrainConfig's own on the envs; steps x batch x action floats fit in memory.
MAX_BATCH, MAX_STEPS, MAX_REPEATS = 2**20, 100_000, 1000


# --------------------------------------------------------------------------------------------------
# Worker side (runs in a subprocess).


def _wait_for_peers(sync_dir: str, process_id: int, num_processes: int, timeout_s: float = 600):
  """File barrier between workers that share no JAX runtime."""
  Path(sync_dir, f'ready_{process_id}').touch()
  deadline = time.monotonic() + timeout_s
  while not all(Path(sync_dir, f'ready_{i}').exists() for i in range(num_processes)):
    if time.monotonic() > deadline:
      raise TimeoutError('peers never became ready')
    time.sleep(0.05)


def _timed(fn, args, repeats: int, sync) -> dict:
  """Compile + warm-up call, barrier, then the best of ``repeats`` calls (wall and CPU time)."""
  import jax
  t0 = time.perf_counter()
  jax.block_until_ready(fn(*args))
  compile_s = time.perf_counter() - t0
  sync()
  best, cpu = float('inf'), 0.0
  for _ in range(repeats):
    c0, t0 = time.process_time(), time.perf_counter()
    jax.block_until_ready(fn(*args))
    dt = time.perf_counter() - t0
    if dt < best:
      best, cpu = dt, time.process_time() - c0
  return {'compile_s': compile_s, 'run_s': best, 'cpu_cores_used': cpu / best}


def _env_step_worker(args) -> dict:
  """Times ``args.steps`` batched env steps of this process's envs (see the module docstring)."""
  import jax
  import jax.numpy as jnp
  import numpy as np
  from jax.sharding import NamedSharding, PartitionSpec as P
  from mash import distributed
  from mash import env as env_lib

  env = env_lib.MashEnv(env_lib.EnvConfig(task=args.task))
  n, pid = args.num_processes, args.process_id
  local_batch = args.batch // n
  keys = jax.random.split(jax.random.PRNGKey(0), args.batch)[pid * local_batch:(pid + 1) * local_batch]
  state = jax.jit(jax.vmap(env.reset))(keys)
  actions = 0.1 * jax.random.normal(jax.random.fold_in(jax.random.PRNGKey(1), pid),
                                    (args.steps, local_batch, env.action_size))

  def rollout(state, actions, axis_name=None):
    def body(carry, a):
      s, total = carry
      s = jax.vmap(env.step)(s, a)
      r = jnp.sum(s.reward)
      if axis_name is not None:
        r = jax.lax.psum(r, axis_name)  # one cross-process sync per control step
      return (s, total + r), ()
    (s, total), _ = jax.lax.scan(body, (state, jnp.zeros(())), actions)
    return total

  if args.variant == 'two_process_mesh':
    mesh = distributed.global_mesh('d')
    put = lambda x, spec: jax.make_array_from_process_local_data(NamedSharding(mesh, spec),
                                                                 np.asarray(x))
    state = jax.tree.map(lambda x: put(x, P('d')), state)
    actions = put(actions, P(None, 'd'))
    fn = jax.jit(jax.shard_map(lambda s, a: rollout(s, a, 'd'), mesh=mesh,
                               in_specs=(P('d'), P(None, 'd')), out_specs=P(), check_vma=False))
    from jax.experimental import multihost_utils
    sync = lambda: multihost_utils.sync_global_devices('timed')
  else:
    fn = jax.jit(rollout)
    sync = lambda: _wait_for_peers(args.sync_dir, pid, n)
  timing = _timed(fn, (state, actions), args.repeats, sync)
  return {**timing, 'local_batch': local_batch, 'substeps': env.n_substeps,
          'env_steps': local_batch * args.steps}


def _train_worker(args) -> dict:
  """Times MASH training calls on the real env: one process, or the global mesh of all of them."""
  import jax
  from mash import config as train_config
  from mash import distributed
  from mash import env as env_lib
  from mash import train as train_lib

  env = env_lib.MashEnv(env_lib.EnvConfig(task=args.task))
  cfg = dataclasses.replace(train_config.TrainConfig(), num_envs=args.train_batch, unroll_length=16,
                            iterations_per_call=1, num_epochs=2, num_minibatches=2,
                            actor_hidden=(64, 64), critic_hidden=(64, 64))
  key = jax.random.PRNGKey(0)
  if args.num_processes == 1:
    trainer = train_lib.make_train(cfg, env)
    state, epoch = trainer.init(key), trainer.train_epoch
    sync = lambda: None
  else:
    from jax.experimental import multihost_utils
    dt = distributed.make_distributed_trainer(cfg, env, distributed.global_mesh())
    state, epoch = dt.init(key), dt.train_epoch
    sync = lambda: multihost_utils.sync_global_devices('timed')
  holder = {'state': state}

  def call():  # the state is donated: thread it through
    holder['state'], metrics = epoch(holder['state'])
    return metrics

  timing = _timed(call, (), args.repeats, sync)
  local_batch = args.train_batch // args.num_processes
  return {**timing, 'local_batch': local_batch, 'substeps': env.n_substeps,
          'env_steps': local_batch * cfg.unroll_length * cfg.iterations_per_call}


def worker_main(args) -> None:
  os.environ.setdefault('JAX_PLATFORMS', args.platform)
  from mash import distributed
  if args.variant in ('two_process_mesh', 'train_two_process'):
    distributed.initialize(args.coordinator, args.num_processes, args.process_id)
  import jax
  t0 = time.perf_counter()
  if args.variant.startswith('train'):
    result = _train_worker(args)
  else:
    result = _env_step_worker(args)
  result.update(process_id=args.process_id, device=jax.devices()[0].device_kind,
                n_devices=jax.device_count(), total_s=time.perf_counter() - t0)
  Path(args.result).write_text(json.dumps(result))


# --------------------------------------------------------------------------------------------------
# Launcher side.


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(('127.0.0.1', 0))
    return s.getsockname()[1]


def _launch(variant: str, num_processes: int, args, tmp: Path) -> list[dict]:
  """Runs one variant's workers concurrently; returns each worker's result."""
  sync_dir = tmp / variant
  sync_dir.mkdir()
  coordinator = f'127.0.0.1:{_free_port()}'
  env = {k: v for k, v in os.environ.items() if k != 'XLA_FLAGS'}
  env['JAX_PLATFORMS'] = args.platform
  root = str(Path(__file__).resolve().parent.parent)
  env['PYTHONPATH'] = os.pathsep.join(p for p in (root, os.environ.get('PYTHONPATH')) if p)
  procs = []
  for i in range(num_processes):
    cmd = [sys.executable, '-m', 'experiments.benchmark_devices', '--worker', variant,
           '--process-id', str(i), '--num-processes', str(num_processes),
           '--coordinator', coordinator, '--sync-dir', str(sync_dir),
           '--result', str(sync_dir / f'result_{i}.json'), '--batch', str(args.batch),
           '--steps', str(args.steps), '--repeats', str(args.repeats), '--task', args.task,
           '--train-batch', str(args.train_batch), '--platform', args.platform]
    log = open(sync_dir / f'worker_{i}.log', 'w')
    procs.append((subprocess.Popen(cmd, env=env, cwd=root, stdout=log, stderr=subprocess.STDOUT),
                  log))
  deadline = time.monotonic() + WORKER_TIMEOUT_S
  failed = None
  try:
    while any(p.poll() is None for p, _ in procs):
      if any(p.poll() not in (None, 0) for p, _ in procs):
        failed = 'a worker failed'
        break
      if time.monotonic() > deadline:
        failed = f'timed out after {WORKER_TIMEOUT_S} s'
        break
      time.sleep(0.5)
  finally:
    for p, log in procs:
      if p.poll() is None:
        p.kill()
        p.wait()
      log.close()
  if failed or any(p.returncode for p, _ in procs):
    raise common.UserError(f"variant '{variant}': {failed or 'a worker failed'}; worker logs in "
                           f"{sync_dir}")
  return [json.loads((sync_dir / f'result_{i}.json').read_text()) for i in range(num_processes)]


VARIANTS = (('one_process', 1), ('two_process_mesh', 2), ('two_process_independent', 2))
TRAIN_VARIANTS = (('train_one_process', 1), ('train_two_process', 2))


JOINED = ('two_process_mesh', 'train_two_process')  # one global program over all workers


def _row(variant: str, workers: list[dict]) -> dict:
  """Total env steps/s of a variant: one global program runs at the pace of its slowest worker;
  independent processes add up."""
  if variant in JOINED:
    total = sum(w['env_steps'] for w in workers) / max(w['run_s'] for w in workers)
  else:
    total = sum(w['env_steps'] / w['run_s'] for w in workers)
  return {'variant': variant, 'processes': len(workers),
          'envs_per_process': workers[0]['local_batch'],
          'env_steps_per_s': total, 'physics_steps_per_s': total * workers[0]['substeps'],
          'cpu_cores_used': sum(w['cpu_cores_used'] for w in workers),
          'compile_s': max(w['compile_s'] for w in workers)}


def run(args) -> dict:
  import multiprocessing
  rows = []
  load_at_start = os.getloadavg()[0]
  variants = VARIANTS + (TRAIN_VARIANTS if args.train else ())
  tmp = Path(tempfile.mkdtemp(prefix='bench_devices_'))  # worker logs; kept if a worker fails
  for i, (variant, n) in enumerate(variants):
    print(f'[{i + 1}/{len(variants)}] {variant} ({n} process{"es" if n > 1 else ""})',
          file=sys.stderr, flush=True)
    workers = _launch(variant, n, args, tmp)
    rows.append({**_row(variant, workers), 'load_average': round(os.getloadavg()[0], 2)})
    print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
  shutil.rmtree(tmp, ignore_errors=True)
  by = {r['variant']: r for r in rows}
  for r in rows:
    base = by['train_one_process' if r['variant'].startswith('train') else 'one_process']
    r['ratio_vs_one_process'] = r['env_steps_per_s'] / base['env_steps_per_s']
  summary = {
      'second_core_buys': by['two_process_mesh']['ratio_vs_one_process'],
      'second_core_buys_without_collective': by['two_process_independent']['ratio_vs_one_process'],
      'collective_cost': 1.0 - (by['two_process_mesh']['env_steps_per_s']
                                / by['two_process_independent']['env_steps_per_s']),
  }
  if 'train_two_process' in by:
    summary['second_core_buys_training'] = by['train_two_process']['ratio_vs_one_process']
  return {'batch': args.batch, 'steps': args.steps, 'repeats': args.repeats, 'task': args.task,
          'platform': args.platform, 'cpu_count': multiprocessing.cpu_count(),
          'load_average_at_start': load_at_start,
          'train_batch': args.train_batch if args.train else None,
          'date': time.strftime('%Y-%m-%d %H:%M:%S'), 'summary': summary, 'rows': rows}


def _write(result: dict, stem: Path) -> None:
  stem.parent.mkdir(parents=True, exist_ok=True)
  stem.with_suffix('.json').write_text(json.dumps(result, indent=2))
  cols = ('variant', 'processes', 'envs_per_process', 'env_steps_per_s', 'physics_steps_per_s',
          'cpu_cores_used', 'compile_s', 'ratio_vs_one_process')
  fmt = lambda v: f'{v:,.3g}' if isinstance(v, float) else str(v)
  s = result['summary']
  lines = [
      f"# What a second CPU device buys (batch {result['batch']}, {result['steps']} control steps, "
      f"task {result['task']})", '',
      f"`python -m experiments.benchmark_devices --batch {result['batch']} --steps "
      f"{result['steps']}`, {result['date']}, {result['cpu_count']} CPUs, load average "
      f"{result['load_average_at_start']:.1f} at the start (shared machine: quote ratios).", '',
      '| ' + ' | '.join(cols) + ' |', '|' + '---|' * len(cols)]
  lines += ['| ' + ' | '.join(fmt(r[c]) for c in cols) + ' |' for r in result['rows']]
  lines += ['', f"Two processes on the global 2-device mesh step **{s['second_core_buys']:.2f}x** "
            f"the envs/s of one process (without the per-step collective: "
            f"{s['second_core_buys_without_collective']:.2f}x; the collective costs "
            f"{100 * s['collective_cost']:.0f} %)."]
  if 'second_core_buys_training' in s:
    lines.append(f"MASH training (batch {result['train_batch']}): "
                 f"{s['second_core_buys_training']:.2f}x.")
  stem.with_suffix('.md').write_text('\n'.join(lines) + '\n')
  _plot(result['rows'], stem.with_suffix('.png'))


def _plot(rows: list[dict], path: Path) -> None:
  """Bars of env steps/s per variant, env step and training side by side, each labelled with its
  ratio to one process."""
  import matplotlib
  matplotlib.use('Agg')
  import matplotlib.pyplot as plt
  fig, ax = plt.subplots(figsize=(6.5, 3.5))
  names = [r['variant'].replace('_', ' ') for r in rows]
  colors = ['tab:green' if r['variant'].startswith('train') else 'tab:blue' for r in rows]
  bars = ax.bar(range(len(rows)), [r['env_steps_per_s'] for r in rows], color=colors)
  for bar, r in zip(bars, rows):
    ax.annotate(f"{r['ratio_vs_one_process']:.2f}x", (bar.get_x() + bar.get_width() / 2,
                bar.get_height()), ha='center', va='bottom', fontsize=8)
  ax.set_xticks(range(len(rows)), names, rotation=20, ha='right', fontsize=8)
  ax.set_ylabel('env steps / s')
  ax.set_title('one process vs two joined by jax.distributed (blue: env step, green: MASH training)',
               fontsize=8)
  ax.grid(axis='y', alpha=0.3)
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def main(argv=None) -> None:
  p = common.Parser(prog='python -m experiments.benchmark_devices',
                    description=__doc__.splitlines()[0])
  p.add_argument('--batch', type=int, default=256, help='global env batch (even)')
  p.add_argument('--steps', type=int, default=20, help='control steps per timed call')
  p.add_argument('--repeats', type=int, default=3, help='timed calls (best kept)')
  p.add_argument('--task', default='bipedal')
  p.add_argument('--train', action='store_true', help='also time MASH training, 1 vs 2 processes')
  p.add_argument('--train-batch', type=int, default=256, help='global env batch of --train')
  p.add_argument('--platform', default='cpu', help='JAX platform of the workers')
  p.add_argument('--out', default='benchmarks/scaling_devices', help='output stem (.json, .md, .png)')
  # Worker-side arguments (set by the launcher).
  hidden = argparse.SUPPRESS
  p.add_argument('--worker', default=None, help=hidden)
  p.add_argument('--process-id', type=int, default=0, help=hidden)
  p.add_argument('--num-processes', type=int, default=1, help=hidden)
  p.add_argument('--coordinator', default='127.0.0.1:12355', help=hidden)
  p.add_argument('--sync-dir', default=None, help=hidden)
  p.add_argument('--result', default=None, help=hidden)
  args = p.parse_args(argv)
  if args.worker is not None:
    args.variant = args.worker
    worker_main(args)
    return
  with common.user_errors():
    common.check_path(args.out, '--out')
    if args.batch < 2 or args.batch % 2 or args.batch > MAX_BATCH:
      raise common.UserError(f'--batch must be an even number in [2, {MAX_BATCH}], got '
                             f'{args.batch}')
    if not (1 <= args.steps <= MAX_STEPS and 1 <= args.repeats <= MAX_REPEATS):
      raise common.UserError(f'--steps must be in [1, {MAX_STEPS}] and --repeats in [1, '
                             f'{MAX_REPEATS}], got {args.steps} and {args.repeats}')
    if args.train and (args.train_batch < 4 or args.train_batch % 4
                       or args.train_batch > MAX_BATCH):
      raise common.UserError(f'--train-batch must be a multiple of 4 in [4, {MAX_BATCH}], got '
                             f'{args.train_batch}')
    common.check_task(args.task)
    if args.platform not in PLATFORMS:
      raise common.UserError(f"--platform '{args.platform}' is unknown; expected one of "
                             f"{', '.join(PLATFORMS)}")
    common.check_writable_file(Path(args.out).with_suffix('.json'), '--out')
    result = run(args)
    _write(result, Path(args.out))
    print(json.dumps(result, indent=2))


if __name__ == '__main__':
  main()
