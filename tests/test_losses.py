"""Tests of mash.rl.losses: GAE against a plain loop and hand cases, the MAPPO loss against hand
arithmetic."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mash.rl import losses
from mash.rl.config import TrainConfig


def gae_loop(rewards, values, next_values, dones, truncs, gamma, lam):
  """Reference GAE: a plain Python loop over time, envs and agents."""
  T, B, N = values.shape
  adv = np.zeros((T, B, N))
  for b in range(B):
    for i in range(N):
      running = 0.0
      for t in reversed(range(T)):
        bootstrap = 1.0 - dones[t, b] + truncs[t, b]
        delta = rewards[t, b] + gamma * bootstrap * next_values[t, b, i] - values[t, b, i]
        running = delta + gamma * lam * (1.0 - dones[t, b]) * running
        adv[t, b, i] = running
  return adv, adv + values


def test_gae_matches_python_loop():
  rng = np.random.default_rng(0)
  T, B, N = 9, 3, 4
  rewards = rng.normal(size=(T, B))
  values = rng.normal(size=(T, B, N))
  next_values = rng.normal(size=(T, B, N))
  dones = (rng.random((T, B)) < 0.3).astype(np.float64)
  truncs = dones * (rng.random((T, B)) < 0.5)  # some ends are time-outs, some falls
  assert dones.sum() > 2 and truncs.sum() > 0 and (dones - truncs).sum() > 0
  adv, ret = jax.jit(losses.compute_gae, static_argnums=(5, 6))(
      *(jnp.asarray(x, jnp.float32) for x in (rewards, values, next_values, dones, truncs)), 0.97,
      0.9)
  ref_adv, ref_ret = gae_loop(rewards, values, next_values, dones, truncs, 0.97, 0.9)
  chex.assert_shape(adv, (T, B, N))
  np.testing.assert_allclose(adv, ref_adv, rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(ret, ref_ret, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    "truncated, expected_adv",
    [
        # gamma = lam = 0.5, r = 1, V = [1, 2, 3], V(s') = [2, 10, 4], episode ends at t=1.
        # delta_2 = 1 + 0.5*4 - 3 = 0                          -> A_2 = 0
        # time-out at t=1: delta_1 = 1 + 0.5*10 - 2 = 4 (bootstrap), A_1 = 4 + 0 (cut) = 4
        #                  delta_0 = 1 + 0.5*2 - 1 = 1,           A_0 = 1 + 0.25*4 = 2
        (1.0, [2.0, 4.0, 0.0]),
        # fall at t=1:     delta_1 = 1 + 0 - 2 = -1,              A_1 = -1
        #                                                         A_0 = 1 + 0.25*(-1) = 0.75
        (0.0, [0.75, -1.0, 0.0]),
    ])
def test_gae_hand_cases(truncated, expected_adv):
  rewards = jnp.ones((3, 1))
  values = jnp.array([1.0, 2.0, 3.0]).reshape(3, 1, 1)
  next_values = jnp.array([2.0, 10.0, 4.0]).reshape(3, 1, 1)
  dones = jnp.array([0.0, 1.0, 0.0]).reshape(3, 1)
  truncs = jnp.array([0.0, truncated, 0.0]).reshape(3, 1)
  adv, ret = losses.compute_gae(rewards, values, next_values, dones, truncs, 0.5, 0.5)
  np.testing.assert_allclose(adv[:, 0, 0], expected_adv, atol=1e-6)
  np.testing.assert_allclose(ret[:, 0, 0], np.array(expected_adv) + [1.0, 2.0, 3.0], atol=1e-6)


def test_mappo_loss_terms_hand_computed():
  """2 samples x 2 agents, eps = 0.2, value clip 0.2, c_v = 0.5, c_e = 0.01."""
  config = TrainConfig(clip_epsilon=0.2, value_clip=0.2, value_loss_coef=0.5, entropy_coef=0.01)
  ratios = np.array([[1.5, 0.7], [0.9, 1.1]])  # [M=2, N=2]: column = agent
  old_log_probs = jnp.array([[-1.0, -2.0], [0.5, 0.0]])
  log_probs = old_log_probs + jnp.log(ratios)
  advantages = jnp.array([[1.0, -1.0], [-2.0, 3.0]])
  old_values = jnp.array([[0.0, 2.0], [1.0, 0.0]])
  values = jnp.array([[0.5, 2.1], [0.9, -0.5]])
  returns = jnp.array([[1.0, 2.0], [1.0, 1.0]])
  entropy = jnp.array([1.0, 2.0])
  loss, m = losses.mappo_loss_terms(log_probs, old_log_probs, advantages, values, old_values,
                                    returns, entropy, config)
  # agent 0: min(1.5*1, 1.2*1) = 1.2 ; min(0.9*-2, 0.9*-2) = -1.8   -> mean -0.3
  # agent 1: min(0.7*-1, 0.8*-1) = -0.8 ; min(1.1*3, 1.1*3) = 3.3   -> mean 1.25
  # policy loss = -(-0.3 + 1.25) = -0.95 (summed over agents)
  np.testing.assert_allclose(m["policy_loss"], -0.95, atol=1e-5)
  # value errors: a0s0 max((.5-1)^2, (0.2-1)^2) = .64 ; a0s1 (.9-1)^2 = .01 ;
  # a1s0 (2.1-2)^2 = .01 ; a1s1 max((-.5-1)^2, (-.2-1)^2) = 2.25   -> mean 2.91/4 = 0.7275
  np.testing.assert_allclose(m["value_loss"], 0.7275, atol=1e-5)
  np.testing.assert_allclose(m["entropy"], 3.0, atol=1e-6)  # summed over agents
  # |r-1| > 0.2 for r = 1.5 and 0.7 -> 2 of 4
  np.testing.assert_allclose(m["clip_fraction"], 0.5)
  # k3 KL (r-1) - ln r: a0 (0.094535 + 0.005361)/2, a1 (0.056675 + 0.004690)/2 -> sum 0.0806305
  np.testing.assert_allclose(m["approx_kl"], 0.0806305, atol=1e-5)
  # loss = -0.95 + 0.5*0.7275 - 0.01*3 = -0.61625
  np.testing.assert_allclose(loss, -0.61625, atol=1e-5)


def test_value_clip_disabled():
  config = TrainConfig(value_clip=0.0, value_loss_coef=1.0, entropy_coef=0.0)
  z = jnp.zeros((2, 1))
  values = jnp.array([[0.5], [3.0]])
  _, m = losses.mappo_loss_terms(z, z, z, values, z, jnp.ones((2, 1)), jnp.zeros((1,)), config)
  np.testing.assert_allclose(m["value_loss"], (0.25 + 4.0) / 2)  # plain squared error


def test_normalize_advantages_per_agent():
  adv = jnp.array([[1.0, 10.0], [3.0, 30.0], [5.0, 50.0]])
  out = losses.normalize_advantages(adv)
  np.testing.assert_allclose(out.mean(axis=0), 0.0, atol=1e-6)
  np.testing.assert_allclose(out.std(axis=0), 1.0, atol=1e-5)
  np.testing.assert_allclose(out[:, 0], out[:, 1], atol=1e-6)  # same shape, independent scale
