"""Tests of mash.rl.networks and mash.rl.normalization: shapes, parameter sharing, value heads,
statistics."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mash.rl import networks as nets
from mash.rl import normalization
from mash.rl.config import TrainConfig
from mash.rl.trainer import FAST_COMPILE_OPTIONS
from mash.sim.agents import assemble_action

from toy_env import make_toy_env

SMALL = dict(actor_hidden=(16, 16), critic_hidden=(16,))


@pytest.fixture(scope="module")
def env():
  return make_toy_env("legs_arms", "mash")


def jit(f):
  """Jitted with fast-compile options: one small compile instead of many eager op compiles."""
  return jax.jit(f, compiler_options=FAST_COMPILE_OPTIONS)


@pytest.fixture(scope="module")
def obs(env):
  """A batch of 3 toy observations ``{group: [3, n, d], 'critic': [3, C]}``."""
  states = jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(3), 3))
  return states.obs


class Built:
  """Networks with jitted apply functions, and their initial params."""

  def __init__(self, env, **kw):
    config = TrainConfig(**SMALL, **kw)
    self.networks = nets.make_networks(env.agent_groups, env.critic_obs_size, config)
    self.params = jit(self.networks.init)(jax.random.PRNGKey(0))
    self.policy = jit(self.networks.policy_apply)
    self.value = jit(self.networks.value_apply)


@pytest.fixture(scope="module")
def shared(env):
  return Built(env, init_log_std=-0.7)


@pytest.fixture(scope="module")
def per_agent(env):
  return Built(env, share_actor=False)


def test_shapes_and_log_std(env, obs, shared):
  dists = shared.policy(shared.params, None, obs)
  chex.assert_shape(dists["legs"].mean, (3, 2, 2))
  chex.assert_shape(dists["arms"].mean, (3, 2, 1))
  chex.assert_shape(dists["legs"].log_std, (2,))  # one log-std per group, state independent
  np.testing.assert_allclose(dists["legs"].log_std, -0.7)
  chex.assert_shape(shared.value(shared.params, None, obs["critic"]), (3, 4))
  assert shared.networks.n_value_heads == 4
  # The shared actor has no agent axis in its parameters: one set for both legs.
  kernel = shared.params["actors"]["legs"]["params"]["MLP_0"]["Dense_0"]["kernel"]
  chex.assert_shape(kernel, (env.agent_groups[0].obs_dim, 16))


def test_shared_actor_swapping_agents_swaps_outputs(obs, shared):
  # Scale the weights up so that output differences are far above float noise.
  params = jax.tree.map(lambda x: x * 30.0, shared.params)
  swapped = dict(obs, legs=obs["legs"][:, ::-1])  # swap whole rows: one-hot ids and other obs
  out = shared.policy(params, None, obs)["legs"].mean
  out_swapped = shared.policy(params, None, swapped)["legs"].mean
  np.testing.assert_allclose(out_swapped, out[:, ::-1], rtol=1e-5, atol=1e-6)
  # The id is an input: changing only the one-hot id of agent 0 changes its action.
  relabelled = obs["legs"].at[:, 0, -2:].set(jnp.array([0.0, 1.0]))
  out_relabelled = shared.policy(params, None, dict(obs, legs=relabelled))["legs"].mean
  assert np.abs(out_relabelled[:, 0] - out[:, 0]).max() > 1e-4


def test_shared_actor_applied_per_agent_equals_one_stacked_application(obs, shared):
  # policy_apply runs the shared actor once per agent (for the CPU runtime's concurrency): the
  # result must be the module applied to the stacked [batch, n_agents, obs_dim] in one call.
  params = jax.tree.map(lambda x: x * 30.0, shared.params)
  actor = nets.GroupActor(act_dim=2, hidden_sizes=SMALL["actor_hidden"])
  stacked, _ = jit(actor.apply)(params["actors"]["legs"], obs["legs"])
  np.testing.assert_allclose(
      shared.policy(params, None, obs)["legs"].mean, stacked, rtol=1e-5, atol=1e-6)


def test_elu_matches_jax_elu_in_value_and_gradient():
  x = jnp.array([-80.0, -5.0, -1.0, -1e-3, -1e-7, 0.0, 1e-7, 1e-3, 1.0, 5.0, 80.0])
  value_and_grad = lambda f: jit(jax.vmap(jax.value_and_grad(f)))(x)
  ours, ours_grad = value_and_grad(nets.elu)
  ref, ref_grad = value_and_grad(jax.nn.elu)
  np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-7)
  np.testing.assert_allclose(ours_grad, ref_grad, rtol=1e-6, atol=1e-12)
  np.testing.assert_allclose(np.asarray(ours_grad)[[5, -1]], [1.0, 1.0])  # 1 at 0 and at large x
  np.testing.assert_allclose(ours[0], -1.0)


def test_per_agent_actors_have_distinct_params(obs, per_agent):
  actor = per_agent.params["actors"]["legs"]
  for leaf in jax.tree.leaves(actor):
    assert leaf.shape[0] == 2  # leading agent axis
  kernel = actor["params"]["VmapGroupActor_0"]["MLP_0"]["Dense_0"]["kernel"]
  assert np.abs(kernel[0] - kernel[1]).max() > 1e-3
  params = jax.tree.map(lambda x: x * 30.0, per_agent.params)
  dists = per_agent.policy(params, None, obs)
  chex.assert_shape(dists["legs"].mean, (3, 2, 2))
  chex.assert_shape(dists["legs"].log_std, (2, 2))  # per agent
  # Identical rows given to the two agents now give different actions (different networks).
  same = dict(obs, legs=jnp.repeat(obs["legs"][:, :1], 2, axis=1))
  mean = per_agent.policy(params, None, same)["legs"].mean
  assert np.abs(mean[:, 0] - mean[:, 1]).max() > 1e-4


def test_shared_value_head_broadcasts(env, obs):
  config = TrainConfig(**SMALL, shared_value_head=True)
  networks = nets.make_networks(env.agent_groups, env.critic_obs_size, config)
  assert networks.n_value_heads == 1
  values = jit(lambda k, x: networks.value_apply(networks.init(k), None, x))(jax.random.PRNGKey(0),
                                                                             obs["critic"])
  chex.assert_shape(values, (3, 4))
  np.testing.assert_array_equal(values[:, 0:1] * np.ones((1, 4)), values)


def test_gaussian_log_prob_and_entropy():
  dist = nets.GaussianParams(mean=jnp.array([[0.0, 1.0]]), log_std=jnp.log(jnp.array([1.0, 2.0])))
  x = jnp.array([[1.0, 0.0]])
  # log N(1; 0, 1) + log N(0; 1, 2) = (-0.5 - 0.9189385) + (-0.125 - ln 2 - 0.9189385)
  expected = -0.5 - 0.9189385 - 0.125 - np.log(2.0) - 0.9189385
  np.testing.assert_allclose(nets.gaussian_log_prob(dist, x[None])[0], [expected], rtol=1e-6)
  # entropy = sum_d (0.5 + 0.5 ln 2 pi + log std) = 2 * 1.4189385 + ln 2
  np.testing.assert_allclose(nets.gaussian_entropy(dist), [2 * 1.4189385 + np.log(2.0)], rtol=1e-6)


def test_deterministic_policy_fn_assembles_means(env, obs, shared):
  action = jit(nets.make_policy_fn(shared.networks))(shared.params, None, obs)
  dists = shared.policy(shared.params, None, obs)
  expected = assemble_action(env.agent_groups, {k: d.mean for k, d in dists.items()})
  chex.assert_shape(action, (3, env.action_size))
  np.testing.assert_allclose(action, expected, rtol=1e-6)


def test_running_stats_merge_matches_numpy():
  rng = np.random.default_rng(0)
  data = rng.normal(3.0, 2.0, size=(50, 4)).astype(np.float32)
  stats = normalization.init_stats(4)
  x = jnp.asarray(data[:3])
  # Before any data normalization is the identity (mean 0, var 1), up to the clip.
  np.testing.assert_allclose(jit(normalization.normalize)(stats, x, 100.0), x)
  for chunk in (data[:7], data[7:30].reshape(23, 1, 4), data[30:]):  # leading axes are samples
    stats = jit(normalization.update_stats)(stats, jnp.asarray(chunk))
  np.testing.assert_allclose(stats.count, 50)
  np.testing.assert_allclose(stats.mean, data.mean(0), rtol=1e-5)
  np.testing.assert_allclose(stats.var, data.var(0), rtol=1e-4)
  z = jit(normalization.normalize)(stats, jnp.asarray(data), 10.0)
  np.testing.assert_allclose(z.mean(0), 0.0, atol=1e-4)
  np.testing.assert_allclose(z.std(0), 1.0, atol=1e-3)


def test_normalizer_streams_and_normalized_apply(env, obs, shared):
  norm = normalization.init_normalizer({"legs": 8, "arms": 6, "critic": env.critic_obs_size})
  norm = jit(normalization.update_normalizer)(norm, obs)
  np.testing.assert_allclose(norm["legs"].count, 6)  # 3 samples x 2 agents
  np.testing.assert_allclose(norm["critic"].count, 3)
  values = shared.value(shared.params, norm, obs["critic"])
  chex.assert_tree_all_finite(values)
