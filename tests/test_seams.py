"""Tests where the pieces meet (issue 27, item 6): each fails when its seam is broken.

- ``mappo_loss`` with real networks: agent ``k``'s advantage column must weigh agent ``k``'s own
  log-prob (the group and member the env's agent order names), and value column ``k`` must meet
  return column ``k``. Checked by making only agent ``k``'s advantage (or return error) non-zero
  and comparing the loss gradient with the gradient of that one agent's term written out.
- Gradient averaging over devices: ``train.loss_gradients`` on two devices, each holding half of a
  minibatch, must equal one device's gradient on the whole minibatch (a ``psum`` in place of the
  ``pmean`` doubles it; Adam's scale invariance would hide that from a comparison of parameters).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mash import losses
from mash import networks as nets
from mash import train
from mash.config import TrainConfig
from mash.toy_env import make_toy_env

ROOT = Path(__file__).resolve().parents[1]
M = 6  # samples in the minibatch


def _agent_order(groups) -> list[tuple[str, int]]:
  """``(group, member)`` of each agent column: groups in order, members in order (the env's)."""
  return [(g.name, i) for g in groups for i in range(g.n_agents)]


@pytest.fixture(scope="module")
def setup():
  """Toy legs + arms (MASH partition: two groups of two agents), small networks, one minibatch."""
  env = make_toy_env("legs_arms", "mash")
  config = TrainConfig(actor_hidden=(16,), critic_hidden=(16,), init_log_std=-0.5,
                       normalize_advantages=False, clip_epsilon=1e6, value_clip=0.0,
                       entropy_coef=0.0)
  networks = nets.make_networks(env.agent_groups, env.critic_obs_size, config)
  params = networks.init(jax.random.PRNGKey(0))
  obs = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), M)).obs
  keys = iter(jax.random.split(jax.random.PRNGKey(2), 8))
  actions = {g.name: jax.random.normal(next(keys), (M, g.n_agents, g.act_dim))
             for g in env.agent_groups}
  dists = networks.policy_apply(params, None, obs)
  log_probs = nets.per_agent(env.agent_groups, {
      g.name: nets.gaussian_log_prob(dists[g.name], actions[g.name]) for g in env.agent_groups})
  values = networks.value_apply(params, None, obs["critic"])
  return dict(env=env, config=config, networks=networks, params=params, obs=obs,
              actions=actions, log_probs=log_probs, values=values)


def _grad(fn, params):
  return jax.jit(jax.grad(fn))(params)


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_advantage_k_weighs_agent_k_log_prob(setup, k):
  """Advantage 1 for agent ``k`` only, ratio 1 (old log-probs = current): the policy-loss gradient
  is ``-grad mean log pi(a_k | o_k)`` of agent k's own row of its group's actor."""
  s = setup
  n = s["log_probs"].shape[-1]
  advantages = jnp.zeros((M, n)).at[:, k].set(1.0)
  batch = losses.LossBatch(obs=s["obs"], actions=s["actions"], log_probs=s["log_probs"],
                           values=s["values"], advantages=advantages, returns=s["values"])
  config = s["config"]
  got = _grad(lambda p: losses.mappo_loss(p, None, batch, s["networks"], config)[0], s["params"])

  group, member = _agent_order(s["env"].agent_groups)[k]

  def own_term(p):
    dist = s["networks"].policy_apply(p, None, s["obs"])[group]
    return -jnp.mean(nets.gaussian_log_prob(dist, s["actions"][group])[:, member])

  want = _grad(own_term, s["params"])
  chex.assert_trees_all_close(got, want, atol=1e-6, rtol=1e-5)
  # The check can tell agents apart: another agent's term has another gradient.
  other_group, other_member = _agent_order(s["env"].agent_groups)[(k + 1) % n]
  other = _grad(lambda p: -jnp.mean(nets.gaussian_log_prob(
      s["networks"].policy_apply(p, None, s["obs"])[other_group],
      s["actions"][other_group])[:, other_member]), s["params"])
  diff = jax.tree.map(lambda a, b: float(jnp.max(jnp.abs(a - b))), want, other)
  assert max(jax.tree.leaves(diff)) > 1e-3


@pytest.mark.parametrize("k", [0, 3])
def test_return_k_trains_value_head_k(setup, k):
  """Returns off by 1 for agent ``k`` only (zero advantages): the critic gradient is that of
  ``mean((V_k - R_k)^2) / N``, value head k alone (the value loss is a mean over agents)."""
  s = setup
  n = s["values"].shape[-1]
  returns = s["values"].at[:, k].add(1.0)
  batch = losses.LossBatch(obs=s["obs"], actions=s["actions"], log_probs=s["log_probs"],
                           values=s["values"], advantages=jnp.zeros((M, n)), returns=returns)
  got = _grad(lambda p: losses.mappo_loss(p, None, batch, s["networks"], s["config"])[0],
              s["params"])

  def own_term(p):
    v = s["networks"].value_apply(p, None, s["obs"]["critic"])[:, k]
    return jnp.mean(jnp.square(v - returns[:, k])) / n

  chex.assert_trees_all_close(got, _grad(own_term, s["params"]), atol=1e-6, rtol=1e-5)


TWO_DEVICE_GRADIENTS = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import PartitionSpec as P
    from mash import losses, networks as nets, train
    from mash.config import TrainConfig
    from mash.toy_env import make_toy_env
    assert jax.device_count() == 2, jax.devices()
    env = make_toy_env('legs_arms', 'mash')
    config = TrainConfig(actor_hidden=(16,), critic_hidden=(16,))  # advantages normalized
    networks = nets.make_networks(env.agent_groups, env.critic_obs_size, config)
    params = networks.init(jax.random.PRNGKey(0))
    m = 8
    obs = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), m)).obs
    k = iter(jax.random.split(jax.random.PRNGKey(2), 8))
    n = sum(g.n_agents for g in env.agent_groups)
    actions = {g.name: jax.random.normal(next(k), (m, g.n_agents, g.act_dim))
               for g in env.agent_groups}
    values = networks.value_apply(params, None, obs['critic'])
    batch = losses.LossBatch(
        obs=obs, actions=actions, log_probs=-jax.random.uniform(next(k), (m, n)) - 3.0,
        values=values, advantages=jax.random.normal(next(k), (m, n)),
        returns=values + jax.random.normal(next(k), (m, n)))
    one, one_metrics = jax.jit(lambda b: train.loss_gradients(params, None, b, networks, config))(batch)
    mesh = jax.make_mesh((2,), ('devices',), axis_types=(jax.sharding.AxisType.Auto,))
    two, two_metrics = jax.jit(jax.shard_map(
        lambda b: train.loss_gradients(params, None, b, networks, config, 'devices'),
        mesh=mesh, in_specs=(P('devices'),), out_specs=P(), check_vma=False))(batch)
    for a, b in zip(jax.tree.leaves((one, one_metrics)), jax.tree.leaves((two, two_metrics))):
      np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=2e-5, atol=1e-6)
    assert max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves(one)) > 1e-3
    print('OK')
""")


def test_two_devices_average_gradients_to_the_whole_minibatch():
  env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
             PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
             JAX_PLATFORMS="cpu")
  result = subprocess.run([sys.executable, "-c", TWO_DEVICE_GRADIENTS], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
  assert result.returncode == 0 and "OK" in result.stdout, result.stdout + result.stderr[-3000:]
