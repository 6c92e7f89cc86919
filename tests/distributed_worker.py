"""Worker process of ``tests/test_distributed.py``: trains the toy env on a global 2-device mesh.

``python tests/distributed_worker.py --out DIR --num-processes N --process-id I --coordinator H:P``

With ``N = 2`` the two processes (one CPU device each) join through ``jax.distributed``; with
``N = 1`` the process must see two CPU devices itself
(``XLA_FLAGS=--xla_force_host_platform_device_count=2``). Either way the same sharded program trains
the same config from the same key for ``--calls`` jitted calls, and each process writes
``DIR/result_p{I}.npz``: parameters, normalizer statistics, the metrics of every call and the global
env batch's last rewards, keyed by pytree path.
With ``--checkpoint`` it also saves the final global state with Orbax (every process) and restores
it into a globally sharded template, checking the round trip. With ``--run DIR`` it then trains the
same config from the same key through :func:`mash.runs.loop.train` (the CLI's loop) into ``DIR``:
one call, stopped by ``max_calls``, then ``resume=True`` to the end (``num_iterations = 2 * calls``
iterations in all), and checks that a second non-resume ``train`` into ``DIR`` is refused by every
process.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# The config the test compares: 32 envs split over 2 devices, 16 x 16 = 256 transitions per device.
CONFIG = dict(num_envs=32, unroll_length=16, iterations_per_call=2, num_epochs=2, num_minibatches=4,
              learning_rate=3e-3, actor_hidden=(32, 32), critic_hidden=(32, 32), seed=0)


def _flat(prefix: str, tree) -> dict:
  import jax
  return {
      prefix + jax.tree_util.keystr(path): leaf
      for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]
  }


def _log(args, t_start: float, what: str) -> None:
  print(f"[process {args.process_id}] {time.perf_counter() - t_start:6.1f} s  {what}", flush=True)


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument("--out", required=True)
  parser.add_argument("--num-processes", type=int, default=1)
  parser.add_argument("--process-id", type=int, default=0)
  parser.add_argument("--coordinator", default="127.0.0.1:12355")
  parser.add_argument("--calls", type=int, default=2)
  parser.add_argument("--checkpoint", default=None)
  parser.add_argument("--run", default=None)
  args = parser.parse_args()
  t_start = time.perf_counter()

  from mash.rl import distributed
  distributed.initialize(args.coordinator, args.num_processes, args.process_id)
  _log(args, t_start, "initialized")

  import jax
  import numpy as np
  from jax.sharding import PartitionSpec as P

  from mash.rl import trainer as trainer_lib
  from mash.rl.config import TrainConfig

  from toy_env import make_toy_env

  assert jax.process_count() == args.num_processes, jax.process_count()
  assert jax.device_count() == 2, jax.devices()
  config = TrainConfig(**CONFIG)
  mesh = distributed.global_mesh()
  dt = trainer_lib.make_trainer(config, make_toy_env("legs_arms", "mash"), mesh=mesh,
                                compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
  _log(args, t_start, "built trainer")
  state = dt.init()
  _log(args, t_start, "init")
  assert state.env_state.reward.sharding.spec == P("devices")
  assert len(state.env_state.reward.addressable_shards) == 2 // args.num_processes
  results = {}
  for call in range(args.calls):
    state, metrics = dt.train_epoch(state)
    results.update(_flat(f"metrics{call}/", distributed.gather_to_host(metrics)))
    _log(args, t_start, f"call {call}")
  results.update(_flat("params/", distributed.gather_to_host(state.params)))
  results.update(_flat("normalizer/", distributed.gather_to_host(state.normalizer)))
  results["env_reward"] = distributed.gather_to_host(state.env_state.reward)
  results["iteration"] = distributed.gather_to_host(state.iteration)

  if args.checkpoint:
    from mash.runs import checkpoint
    expected = distributed.gather_to_host(state)
    manager = checkpoint.make_manager(args.checkpoint)
    checkpoint.save(manager, int(results["iteration"]), state, config)
    manager.close()
    template = dt.state_shapes()
    restored = checkpoint.restore_latest(args.checkpoint, template)
    assert restored.state.env_state.reward.sharding.spec == P("devices")
    jax.tree.map(np.testing.assert_array_equal, distributed.gather_to_host(restored.state),
                 expected)
    state, _ = dt.train_epoch(restored.state)  # the restored state trains (same program)
    results["checkpoint_ok"] = np.array(True)
    _log(args, t_start, "checkpoint round trip")

  if args.run:
    import dataclasses

    from mash.runs import experiment
    from mash.runs import loop as runs
    cfg = experiment.ExperimentConfig(
        preset="smoke", checkpoint_every=1,
        train=dataclasses.replace(config, num_iterations=config.iterations_per_call * args.calls))
    first = runs.train(cfg, args.run, show_progress=False, max_calls=1, trainer=dt)
    _log(args, t_start, f'runs.train: {first["iterations"]} iterations')
    resumed = runs.train(cfg, args.run, resume=True, show_progress=False, trainer=dt)
    _log(args, t_start, f'runs.train resumed: {resumed["iterations"]} iterations')
    try:
      runs.train(cfg, args.run, show_progress=False, trainer=dt)
      refused = ""
    except runs.RunError as e:
      refused = str(e)
    results.update(run_first_iterations=np.array(first["iterations"]), run_iterations=np.array(
        resumed["iterations"]), run_devices=np.array(resumed["devices"]), run_processes=np.array(
            resumed["processes"]), run_final_reward=np.array(resumed["final_episode_reward"]),
                   run_refused=np.array(refused))

  results["process_count"] = np.array(jax.process_count())
  results["wall_s"] = np.array(time.perf_counter() - t_start)
  os.makedirs(args.out, exist_ok=True)
  np.savez(os.path.join(args.out, f"result_p{args.process_id}.npz"), **results)
  print(
      f"OK process {args.process_id}/{args.num_processes} in {time.perf_counter() - t_start:.1f} s",
      flush=True)


if __name__ == "__main__":
  main()
