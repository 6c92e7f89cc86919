"""A view of the MASH env that Brax's own training code accepts (for the benchmark's Brax PPO).

Brax's PPO wants ``obs = {'state': [D], 'privileged_state': [C]}`` and does time-outs and
auto-resets with its own wrappers, so the view uses the single-agent (``ppo``) partition,
turns our auto-reset and time-out off, and flattens the observation. It exists to compare
throughput on the same physics; our trainer uses ``MashEnv`` directly.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from brax.envs import base as brax_base

from mash.sim import env as env_lib
from mash.sim import env_config


def _device_put_replicated(tree, devices):
  """One copy of every leaf per device, stacked on a new leading axis, laid out as ``jax.pmap``
  lays out its outputs, with strong dtypes (so Brax's pmapped training epoch compiles once): what
  ``jax.device_put_replicated`` did before JAX 0.10 removed it."""

  def stack(x):
    x = jnp.asarray(x)
    # A named dtype drops weak typing: the epoch returns strong types, and a weak leaf going in
    # would make its second call compile again.
    return jnp.stack([jnp.asarray(x, dtype=x.dtype)] * len(devices))

  stacked = jax.tree.map(stack, tree)
  return jax.pmap(lambda t: t, devices=devices)(stacked)


def patch_jax_for_brax() -> None:
  """Brax 0.14.2's trainers (the latest release) still call ``jax.device_put_replicated``, which
  JAX 0.10 removed; puts back an equivalent when it is missing. Does nothing on older JAX."""
  try:
    jax.device_put_replicated  # noqa: B018 (raises AttributeError once removed)
  except AttributeError:
    jax.device_put_replicated = _device_put_replicated


class BraxView(brax_base.Env):
  """``MashEnv`` (single-agent partition) with Brax's observation dict and no inner auto-reset."""

  def __init__(self, config: env_config.EnvConfig):
    config = dataclasses.replace(config, partition="ppo", auto_reset=False, episode_length=2**30)
    self.env = env_lib.MashEnv(config)

  def _obs(self, obs):
    return {"state": obs["body"][0], "privileged_state": obs["critic"]}

  def reset(self, rng: jax.Array) -> brax_base.State:
    s = self.env.reset(rng)
    return s.replace(obs=self._obs(s.obs))

  def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
    inner = state.replace(
        obs={"body": state.obs["state"][None], "critic": state.obs["privileged_state"]})
    s = self.env.step(inner, action)
    return s.replace(obs=self._obs(s.obs))

  @property
  def observation_size(self):
    return {
        "state": (self.env.agent_groups[0].obs_dim,), "privileged_state": (self.env.critic_obs_size,
                                                                          )
    }

  @property
  def action_size(self) -> int:
    return self.env.action_size

  @property
  def backend(self) -> str:
    return "mjx"
