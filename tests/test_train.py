"""End-to-end tests of mash.rl.mappo and mash.runs.checkpoint on the toy env (CPU, seconds)."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap

import chex
import jax
import numpy as np
import pytest

from mash.rl import mappo
from mash.rl import trainer as trainer_lib
from mash.rl.config import TrainConfig, derived
from mash.runs import checkpoint

from toy_env import make_toy_env


def assert_trees_close(a, b, rtol=1e-5, atol=1e-6):
  jax.tree.map(
      lambda x, y: np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol),
      a, b)


def test_derived_sizes_and_errors():
  d = derived(
      TrainConfig(num_envs=8, unroll_length=6, num_minibatches=4, num_epochs=5,
                  iterations_per_call=10, num_iterations=25))
  assert (d.batch_size, d.minibatch_size, d.updates_per_iteration, d.num_calls) == (48, 12, 20, 3)
  with pytest.raises(ValueError, match="num_minibatches"):
    derived(TrainConfig(num_envs=3, unroll_length=5, num_minibatches=4))
  with pytest.raises(ValueError, match="devices"):
    derived(TrainConfig(num_envs=6), num_devices=4)


def test_mash_learns_on_toy_env(learning_run, toy_config):
  m = learning_run["metrics"]
  n = toy_config.iterations_per_call * 6
  for key in ("episode_reward", "episode_length", "reward/tracking", "reward/alive",
              "reward/smoothness", "policy_loss", "value_loss", "entropy", "approx_kl",
              "clip_fraction"):
    chex.assert_shape(m[key], (n,))
    assert np.isfinite(m[key]).all(), key
  # The initial (std 1) policy falls within ~2 steps (episode reward ~1); zero actions would
  # already score ~23 and perfect tracking ~48 over the 40-step episode.
  first, last = m["episode_reward"][0], m["episode_reward"][-5:].mean()
  assert first < 5.0, first
  assert last > first + 10.0, (first, last)
  assert m["episode_length"][-5:].mean() > 3 * m["episode_length"][0]
  assert m["reward/tracking"][-5:].mean() > m["reward/tracking"][0] + 0.2


def test_vmapped_seeds_equal_single_seed_runs(mash_trainer, learning_run):
  seeds = trainer_lib.make_trainer(mash_trainer.config, mash_trainer.env, seeds=2,
                                   compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
  state = seeds.init()
  state, metrics = seeds.train_epoch(state)
  chex.assert_shape(metrics["episode_reward"], (2, mash_trainer.config.iterations_per_call))
  params = jax.device_get(state.params)
  # Seed 0: the first call of the learning run. Seed 1: a single run from PRNGKey(1).
  assert_trees_close(jax.tree.map(lambda x: x[0], params), learning_run["first_params"])
  single1, _ = mash_trainer.train_epoch(mash_trainer.init(jax.random.PRNGKey(1)))
  assert_trees_close(jax.tree.map(lambda x: x[1], params), single1.params)
  # ... and the two seeds really differ.
  assert not np.allclose(jax.tree.leaves(params)[0][0], jax.tree.leaves(params)[0][1])


def test_run_trainers_of_one_and_many_seeds_share_one_interface(mash_trainer):
  """The host loop's view of a trainer: the restore template matches a fresh state leaf for leaf,
  seed i of many is the one-seed run of seed + i, and a salt draws other keys."""
  config = dataclasses.replace(mash_trainer.config, seed=3)
  one = trainer_lib.make_trainer(config, mash_trainer.env,
                                 compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
  many = trainer_lib.make_trainer(config, mash_trainer.env, seeds=2,
                                  compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
  assert (one.seeds, one.devices, many.seeds, many.devices) == (1, 1, 2, 1)
  for run_trainer in (one, many):
    state = run_trainer.init()
    chex.assert_trees_all_equal_shapes_and_dtypes(
        jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), state),
        run_trainer.state_shapes())
  direct = jax.device_get(mash_trainer.init(jax.random.PRNGKey(3)).params)
  assert_trees_close(jax.device_get(one.init().params), direct)
  assert_trees_close(jax.tree.map(lambda x: x[0], jax.device_get(many.init().params)), direct)
  salted = jax.device_get(one.init(trainer_lib.fold(one, 4)).env_state.obs)
  assert not np.allclose(
      jax.tree.leaves(salted)[0],
      jax.tree.leaves(jax.device_get(one.init().env_state.obs))[0])


def test_checkpoint_round_trip_and_exact_resume(mash_trainer, toy_config, tmp_path):
  key = jax.random.PRNGKey(7)
  # A: two calls straight through.
  a, _ = mash_trainer.train_epoch(mash_trainer.init(key))
  a, _ = mash_trainer.train_epoch(a)
  # B: one call, save, restore into a fresh template, one more call.
  b, _ = mash_trainer.train_epoch(mash_trainer.init(key))
  manager = checkpoint.make_manager(tmp_path / "ckpt", max_to_keep=2)
  for step in (1, 2):  # older steps are garbage-collected
    checkpoint.save(manager, step, mash_trainer.init(jax.random.PRNGKey(step)), toy_config)
  checkpoint.save(manager, 5, b, toy_config)
  assert manager.all_steps() == [2, 5]
  manager.close()
  expected = jax.device_get(b)
  del b
  template = mash_trainer.state_shapes()
  restored = checkpoint.restore_latest(tmp_path / "ckpt", template)
  assert restored.step == 5 and restored.config == toy_config
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(restored.state), expected)
  b, _ = mash_trainer.train_epoch(restored.state)
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(b.params), jax.device_get(a.params))
  jax.tree.map(np.testing.assert_array_equal, jax.device_get(b.normalizer),
               jax.device_get(a.normalizer))
  assert int(b.iteration) == 2 * toy_config.iterations_per_call
  assert checkpoint.restore_latest(tmp_path / "missing", template) is None


def test_no_recompilation(mash_trainer, learning_run):
  # Runs after the learning run, the seed run and the resume from a restored checkpoint: every
  # call of the single-seed train_epoch went through one compiled program.
  assert mash_trainer.train_epoch._cache_size() == 1
  # And a further call neither traces nor compiles anything (public jax.monitoring events).
  events = []

  def listener(event, duration, **kwargs):
    if event.startswith("/jax/core/compile/"):
      events.append(event)

  jax.monitoring.register_event_duration_secs_listener(listener)
  try:
    state, _ = mash_trainer.train_epoch(learning_run["final_state"])
    jax.block_until_ready(state)
  finally:
    jax.monitoring.unregister_event_duration_listener(listener)
  assert events == []
  assert int(state.iteration) == 7 * mash_trainer.config.iterations_per_call


def test_ppo_partition_runs_through_same_code(toy_config):
  env = make_toy_env("legs", "ppo")
  trainer = trainer_lib.make_trainer(toy_config, env,
                                     compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
  assert [g.name for g in trainer.networks.groups] == ["body"]
  state, metrics = trainer.train_epoch(trainer.init(jax.random.PRNGKey(0)))
  chex.assert_tree_all_finite(metrics)
  chex.assert_shape(state.params["actors"]["body"]["params"]["log_std"], (env.action_size,))
  assert metrics["episode_reward"][-1] > metrics["episode_reward"][0]


def test_adaptive_learning_rate_rule():
  """rsl_rl's rule against hand values: / 1.5 above 2 x desired, x 1.5 below desired / 2 (not at
  0), unchanged between; clipped to [1e-5, 1e-2]."""
  rule = jax.jit(mappo.adapt_learning_rate, static_argnums=2)
  for lr, kl, expected in ((1e-3, 0.03, 1e-3 / 1.5), (1e-3, 0.004, 1.5e-3), (1e-3, 0.0, 1e-3),
                           (1e-3, 0.01, 1e-3), (1e-3, 0.02, 1e-3), (1.2e-5, 0.5, 1e-5), (8e-3, 1e-4,
                                                                                         1e-2)):
    np.testing.assert_allclose(rule(np.float32(lr), np.float32(kl), 0.01), expected, rtol=1e-6)


def test_adaptive_learning_rate_trains_checkpoints_and_logs(toy_config, mash_env, learning_run,
                                                            tmp_path):
  """Under ``adaptive_kl`` the rate lives in the optimizer state: it moves, stays in bounds, is
  logged per iteration and survives a checkpoint round trip; ``fixed`` logs the config's rate."""
  cfg = dataclasses.replace(toy_config, learning_rate_schedule="adaptive_kl")
  trainer = trainer_lib.make_trainer(cfg, mash_env,
                                     compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
  state = trainer.init(jax.random.PRNGKey(0))
  assert float(mappo.injected_learning_rate(state.opt_state)) == pytest.approx(3e-3)
  state, metrics = trainer.train_epoch(state)
  lr = float(mappo.injected_learning_rate(state.opt_state))
  assert lr != pytest.approx(3e-3) and 1e-5 <= lr <= 1e-2
  chex.assert_shape(metrics["learning_rate"], (cfg.iterations_per_call,))
  assert np.all((metrics["learning_rate"] >= 1e-5) & (metrics["learning_rate"] <= 1e-2))
  manager = checkpoint.make_manager(tmp_path / "ckpt", max_to_keep=1)
  checkpoint.save(manager, 1, state, cfg)
  manager.close()
  restored = checkpoint.restore_latest(tmp_path / "ckpt", trainer.state_shapes())
  assert float(mappo.injected_learning_rate(restored.state.opt_state)) == lr
  np.testing.assert_allclose(learning_run["metrics"]["learning_rate"], toy_config.learning_rate)
  with pytest.raises(ValueError, match="learning_rate_schedule 'cosine' is unknown"):
    derived(dataclasses.replace(cfg, learning_rate_schedule="cosine"))


def test_linear_learning_rate_decays_to_zero_at_the_last_iteration(toy_config, mash_env):
  """``linear``: iteration i's 16 minibatch steps (4 epochs x 4) use the rates
  3e-3 * (1 - step / 160) of its steps 16 i .. 16 i + 15 (10 iterations), logged as their mean;
  the rate is in the optimizer state, so a resume goes on from it; 0 after the last step."""
  cfg = dataclasses.replace(toy_config, learning_rate_schedule="linear", num_iterations=10)
  trainer = trainer_lib.make_trainer(cfg, mash_env,
                                     compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
  state, first = trainer.train_epoch(trainer.init(jax.random.PRNGKey(0)))
  state, second = trainer.train_epoch(state)
  logged = np.concatenate([first["learning_rate"], second["learning_rate"]])
  expected = [3e-3 * (1.0 - (16 * i + 7.5) / 160) for i in range(10)]
  np.testing.assert_allclose(logged, expected, rtol=1e-5)
  assert float(mappo.injected_learning_rate(state.opt_state)) == pytest.approx(
      3e-3 / 160, rel=1e-4)  # the last step's
  assert float(mappo.linear_learning_rate(cfg)(160)) == 0.0


def test_sharded_one_device_matches_unsharded(mash_trainer):
  mesh = jax.make_mesh((1,), ("devices",), axis_types=(jax.sharding.AxisType.Auto,))
  sharded = trainer_lib.make_trainer(mash_trainer.config, mash_trainer.env, mesh=mesh,
                                     compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
  key = jax.random.PRNGKey(11)
  out, metrics = sharded.train_epoch(sharded.init(key))
  ref, ref_metrics = mash_trainer.train_epoch(mash_trainer.init(key))
  assert_trees_close(out.params, ref.params, rtol=1e-4, atol=1e-5)
  np.testing.assert_allclose(metrics["episode_reward"], ref_metrics["episode_reward"], rtol=1e-4)


TWO_DEVICE_SCRIPT = textwrap.dedent("""
    import jax, numpy as np
    from jax.sharding import PartitionSpec as P
    from mash.rl import trainer as trainer_lib
    from mash.rl.config import TrainConfig
    from toy_env import make_toy_env
    assert jax.device_count() == 2, jax.devices()
    config = TrainConfig(num_envs=16, unroll_length=8, iterations_per_call=2, num_epochs=2,
                         num_minibatches=2, actor_hidden=(16,), critic_hidden=(16,))
    mesh = jax.make_mesh((2,), ('devices',), axis_types=(jax.sharding.AxisType.Auto,))
    trainer = trainer_lib.make_trainer(config, make_toy_env('legs', 'mash'), mesh=mesh,
                                       compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
    state, metrics = trainer.train_epoch(trainer.init())
    assert state.env_state.reward.sharding.spec == P('devices')
    assert int(state.iteration) == 2
    # Replicated outputs hold each device's own result: they agree only if the update was
    # averaged over devices.
    for leaf in jax.tree.leaves((state.params, state.opt_state, state.normalizer, state.rng)):
      shards = [np.asarray(s.data) for s in leaf.addressable_shards]
      assert len(shards) == 2
      np.testing.assert_array_equal(shards[0], shards[1])
    # Statistics merged over both devices: 2 iterations x 16 envs x 8 steps x 2 leg agents.
    np.testing.assert_allclose(state.normalizer['legs'].count, 2 * 16 * 8 * 2)
    assert np.isfinite(np.asarray(metrics['episode_reward'])).all()
    print('OK')
""")


def test_two_devices_sharded_training_in_subprocess():
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  env = dict(
      os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", PYTHONPATH=os.pathsep.join([
          root, os.path.join(root, "tests"),
          os.environ.get("PYTHONPATH", "")
      ]), JAX_PLATFORMS="cpu")
  result = subprocess.run([sys.executable, "-c", TWO_DEVICE_SCRIPT], env=env, cwd=root,
                          capture_output=True, text=True, timeout=300)
  assert result.returncode == 0 and "OK" in result.stdout, result.stdout + result.stderr[-3000:]


def test_paper_episode_reward_is_the_episode_reward_without_a_paper_metric(learning_run):
  """The toy env reports no ``paper_reward``: the paper-weight episode return is then the trained
  one, iteration by iteration (the MJX env's curricula make them differ; test_env checks its
  ``paper_reward`` against the reward where no curriculum is on)."""
  m = learning_run["metrics"]
  np.testing.assert_allclose(m["paper_episode_reward"], m["episode_reward"], rtol=1e-6)
  assert np.any(m["episode_reward"] != 0)


def test_the_first_update_step_sees_the_rollout_policy(toy_config, mash_env):
  """Seam between rollout and update: with one epoch of one minibatch, the only gradient step
  sees exactly the policy that acted (ratio 1: approx KL 0, nothing clipped), because the update
  normalizes observations with the statistics the rollout used, not the ones updated from it.
  (Normalizing with the updated statistics makes the KL ~3e-3 here.)"""
  cfg = dataclasses.replace(toy_config, num_epochs=1, num_minibatches=1, iterations_per_call=2)
  trainer = trainer_lib.make_trainer(cfg, mash_env,
                                     compiler_options=trainer_lib.FAST_COMPILE_OPTIONS)
  _, metrics = trainer.train_epoch(trainer.init(jax.random.PRNGKey(0)))
  np.testing.assert_allclose(metrics["approx_kl"], 0.0, atol=1e-7)
  np.testing.assert_array_equal(metrics["clip_fraction"], 0.0)
