"""Multi-process training: two processes joined by ``jax.distributed`` equal one process over two devices.

Three subprocesses of ``tests/distributed_worker.py`` run at once on 127.0.0.1: a pair of processes
with one CPU device each, joined into a global 2-device mesh (the multi-host path, Gloo
collectives), and one process with two forced CPU devices. Both train the toy env with the same
config and key through :func:`mash.distributed.make_distributed_trainer` for two jitted calls; the
pair also saves and restores its global state with Orbax. Every parameter, statistic and metric must
agree: between the two processes of the pair exactly (replicated values), and between the pair and
the single process to float tolerance (only the collective's implementation differs).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mash import distributed

ROOT = Path(__file__).resolve().parent.parent
WORKER = ROOT / 'tests' / 'distributed_worker.py'
TIMEOUT_S = 240


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(('127.0.0.1', 0))
    return s.getsockname()[1]


def _env(devices: int) -> dict[str, str]:
  env = {k: v for k, v in os.environ.items() if k != 'XLA_FLAGS'}
  env.update(JAX_PLATFORMS='cpu',
             PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get('PYTHONPATH')) if p))
  if devices > 1:
    env['XLA_FLAGS'] = f'--xla_force_host_platform_device_count={devices}'
  return env


def _run_all(commands: list[tuple[list[str], dict[str, str]]], log_dir: Path,
             timeout_s: float = TIMEOUT_S) -> None:
  """Runs the commands concurrently; kills them all when one fails or the time is up."""
  procs, logs = [], []
  for i, (cmd, env) in enumerate(commands):
    log = open(log_dir / f'worker{i}.log', 'w')
    logs.append(log)
    procs.append(subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT))
  deadline = time.monotonic() + timeout_s
  failure = None
  try:
    while any(p.poll() is None for p in procs):
      bad = [i for i, p in enumerate(procs) if p.poll() not in (None, 0)]
      if bad:
        failure = f'worker {bad[0]} exited with status {procs[bad[0]].returncode}'
        break
      if time.monotonic() > deadline:
        failure = f'timed out after {timeout_s:.0f} s'
        break
      time.sleep(0.2)
    else:
      bad = [i for i, p in enumerate(procs) if p.returncode != 0]
      if bad:
        failure = f'worker {bad[0]} exited with status {procs[bad[0]].returncode}'
  finally:
    for p in procs:
      if p.poll() is None:
        p.kill()
        p.wait()
    for log in logs:
      log.close()
  if failure:
    tails = '\n'.join(f'--- worker{i} ---\n' + (log_dir / f'worker{i}.log').read_text()[-2000:]
                      for i in range(len(procs)))
    pytest.fail(f'{failure}\n{tails}')


@pytest.fixture(scope='module')
def results(tmp_path_factory) -> dict[str, dict[str, np.ndarray]]:
  """``{'pair0', 'pair1', 'single'}``: each worker's saved arrays."""
  tmp = tmp_path_factory.mktemp('distributed')
  coordinator = f'127.0.0.1:{_free_port()}'
  pair = [([sys.executable, str(WORKER), '--out', str(tmp / 'pair'), '--num-processes', '2',
            '--process-id', str(i), '--coordinator', coordinator,
            '--checkpoint', str(tmp / 'checkpoints')], _env(1)) for i in range(2)]
  single = ([sys.executable, str(WORKER), '--out', str(tmp / 'single')], _env(2))
  _run_all(pair + [single], tmp)
  load = lambda p: dict(np.load(p))
  return {'pair0': load(tmp / 'pair' / 'result_p0.npz'),
          'pair1': load(tmp / 'pair' / 'result_p1.npz'),
          'single': load(tmp / 'single' / 'result_p0.npz')}


TRAINED = ('metrics', 'params/', 'normalizer/', 'env_reward', 'iteration')


def _trained_keys(r: dict[str, np.ndarray]) -> list[str]:
  return sorted(k for k in r if k.startswith(TRAINED))


def test_pair_ran_as_two_processes(results):
  assert int(results['pair0']['process_count']) == 2
  assert int(results['single']['process_count']) == 1
  assert bool(results['pair0']['checkpoint_ok']) and bool(results['pair1']['checkpoint_ok'])
  # 2 calls x 2 iterations, normalizer merged over both devices:
  # 4 iterations x 32 envs x 16 steps x 2 leg agents = 4096 leg observations.
  for r in results.values():
    assert int(r['iteration']) == 4
    np.testing.assert_allclose(r["normalizer/['legs'].count"], 4 * 32 * 16 * 2)
    assert r['env_reward'].shape == (32,)


def test_processes_of_the_pair_agree_exactly(results):
  a, b = results['pair0'], results['pair1']
  assert _trained_keys(a) == _trained_keys(b)
  for k in _trained_keys(a):
    np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_two_processes_match_one_process_two_devices(results):
  pair, single = results['pair0'], results['single']
  assert _trained_keys(pair) == _trained_keys(single)
  assert any(k.startswith('params/') for k in _trained_keys(pair))
  for k in _trained_keys(pair):
    np.testing.assert_allclose(pair[k], single[k], rtol=1e-5, atol=1e-6, err_msg=k)
  assert np.isfinite(pair["metrics1/['episode_reward']"]).all()


def test_initialize_rejects_bad_arguments():
  with pytest.raises(ValueError, match='coordinator'):
    distributed.initialize('localhost', 2, 0)
  with pytest.raises(ValueError, match='num_processes'):
    distributed.initialize('127.0.0.1:1234', 0, 0)
  with pytest.raises(ValueError, match='process_id'):
    distributed.initialize('127.0.0.1:1234', 2, 2)
