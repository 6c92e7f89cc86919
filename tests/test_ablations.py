"""Ablation switches: each one resolves to a config, builds its env and networks, and does what it
says.

No MJX step is compiled here: only ``reset`` (no physics) and network applies.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mash.rl import networks
from mash.runs import experiment
from mash.sim import agents


@pytest.mark.parametrize("ablation", experiment.ABLATIONS)
def test_every_ablation_builds(ablation):
  """Config, env and networks of every ablation on armswing; action sizes add up."""
  cfg = experiment.make_config("armswing", "mash", "smoke", ablation=ablation)
  env = experiment.make_env(cfg)
  nets = networks.make_networks(env.agent_groups, env.critic_obs_size, cfg.train)
  params = nets.init(jax.random.PRNGKey(0))
  obs = {g.name: jnp.ones((g.n_agents, g.obs_dim)) for g in env.agent_groups}
  dists = nets.policy_apply(params, None, obs)
  values = nets.value_apply(params, None, jnp.ones((env.critic_obs_size,)))
  assert values.shape == (agents.total_agents(env.agent_groups),)
  assert sum(d.mean.size for d in dists.values()) == env.action_size
  expected = {"legs_only": 12}.get(ablation, 20)
  assert env.action_size == expected


def test_ablation_switches_change_what_they_name():
  make = lambda a: experiment.make_config("armswing", "mash", "smoke", ablation=a)
  assert make("no_sharing").train.share_actor is False
  assert make("single_value_head").train.shared_value_head is True
  assert make("local_critic").train.local_critic and make("local_critic").env.critic == "local"
  assert make("no_temporal_director").env.temporal_director is False
  assert make("no_agent_id").env.agent_id is False
  assert make("legs_only").env.task == "bipedal"
  per_limb = experiment.make_env(make("per_limb"))
  assert [g.name for g in per_limb.agent_groups
         ] == ["left_leg", "right_leg", "left_arm", "right_arm"]
  no_id = experiment.make_env(make("no_agent_id"))
  assert [g.obs_dim for g in no_id.agent_groups] == [30, 24]
  with pytest.raises(experiment.ConfigError):
    experiment.make_config("bipedal", "ppo", "smoke", ablation="no_sharing")


def test_local_critic_sees_only_its_agent():
  """IPPO critic: changing agent k's observation changes value k only; env stacks padded obs."""
  cfg = experiment.make_config("armswing", "mash", "smoke", ablation="local_critic")
  env = experiment.make_env(cfg)
  n, dim = 4, 32
  assert env.critic_obs_size == n * dim
  nets = networks.make_networks(env.agent_groups, env.critic_obs_size, cfg.train)
  params = nets.init(jax.random.PRNGKey(1))
  x = jax.random.normal(jax.random.PRNGKey(2), (n, dim))
  v0 = nets.value_apply(params, None, x.reshape(-1))
  for k in range(n):
    v1 = nets.value_apply(params, None, x.at[k].add(1.0).reshape(-1))
    changed = np.abs(np.asarray(v1 - v0)) > 1e-7
    assert changed[k] and changed.sum() == 1
  state = jax.jit(env.reset)(jax.random.PRNGKey(0))
  critic = np.asarray(state.obs["critic"]).reshape(n, dim)
  np.testing.assert_allclose(critic[:2], state.obs["legs"])
  np.testing.assert_allclose(critic[2:, :26], state.obs["arms"])
  np.testing.assert_array_equal(critic[2:, 26:], 0.0)
