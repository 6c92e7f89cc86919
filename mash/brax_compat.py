"""A view of the MASH env that Brax's own training code accepts (for the benchmark's Brax PPO).

Brax's PPO wants ``obs = {'state': [D], 'privileged_state': [C]}`` and does time-outs and
auto-resets with its own wrappers, so the view uses the single-agent (``ppo``) partition,
turns our auto-reset and time-out off, and flattens the observation. It exists to compare
throughput on the same physics; our trainer uses ``MashEnv`` directly.
"""

from __future__ import annotations

import dataclasses

import jax
from brax.envs import base as brax_base

from mash import env as env_lib


class BraxView(brax_base.Env):
  """``MashEnv`` (single-agent partition) with Brax's observation dict and no inner auto-reset."""

  def __init__(self, config: env_lib.EnvConfig):
    config = dataclasses.replace(config, partition="ppo", auto_reset=False,
                                 episode_length=2**30)
    self.env = env_lib.MashEnv(config)

  def _obs(self, obs):
    return {"state": obs["body"][0], "privileged_state": obs["critic"]}

  def reset(self, rng: jax.Array) -> brax_base.State:
    s = self.env.reset(rng)
    return s.replace(obs=self._obs(s.obs))

  def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
    inner = state.replace(obs={"body": state.obs["state"][None], "critic": state.obs["privileged_state"]})
    s = self.env.step(inner, action)
    return s.replace(obs=self._obs(s.obs))

  @property
  def observation_size(self):
    return {"state": (self.env.agent_groups[0].obs_dim,),
            "privileged_state": (self.env.critic_obs_size,)}

  @property
  def action_size(self) -> int:
    return self.env.action_size

  @property
  def backend(self) -> str:
    return "mjx"
