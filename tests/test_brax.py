"""Brax's own PPO trainer (``brax.training.agents.ppo``) runs on the MASH env through its Brax view.

One tiny epoch: Brax's wrappers (episode limit, auto-reset, vmap) around ``BraxView``, its rollout,
GAE and updates, compiled once. The benchmark uses the same path to compare throughput.
"""

from __future__ import annotations

import functools

import jax
import numpy as np

from mash.bench import brax_compat
from mash.sim import env_config


def test_brax_ppo_trains_on_the_env():
  from brax.training.agents.ppo import networks as ppo_networks
  from brax.training.agents.ppo import train as ppo_train

  brax_compat.patch_jax_for_brax()
  env = brax_compat.BraxView(env_config.EnvConfig(task="bipedal"))
  obs_size = env.observation_size
  assert obs_size == {"state": (50,), "privileged_state": (106,)}
  assert env.action_size == 12

  steps = []
  factory = functools.partial(ppo_networks.make_ppo_networks, policy_hidden_layer_sizes=(16,),
                              value_hidden_layer_sizes=(16,), policy_obs_key="state",
                              value_obs_key="privileged_state")
  make_policy, params, _ = ppo_train.train(
      environment=env, num_timesteps=4 * 4, num_envs=4, episode_length=50, unroll_length=4,
      batch_size=2, num_minibatches=2, num_updates_per_batch=1, normalize_observations=True,
      network_factory=factory, num_evals=2, run_evals=False, seed=0,
      progress_fn=lambda step, metrics: steps.append((step, metrics)))

  assert steps and steps[-1][0] >= 16  # Brax counted the env steps it took
  leaves = jax.tree.leaves(params)
  assert leaves and all(np.isfinite(np.asarray(x)).all() for x in leaves)
  metrics = steps[-1][1]
  assert np.isfinite(metrics["training/total_loss"]) and metrics["training/v_loss"] > 0
  # The trained policy acts on the view's observation.
  state = jax.jit(env.reset)(jax.random.PRNGKey(1))
  action, _ = make_policy(params, deterministic=True)(jax.tree.map(lambda x: x[None], state.obs),
                                                      jax.random.PRNGKey(2))
  assert action.shape == (1, 12) and np.all(np.abs(np.asarray(action)) <= 1.0)
