"""How a robot's controlled joints are split into agents, and how agent actions become one action.

An *agent group* is a set of agents that share one actor network (the two legs, the two arms).
Agents of a group are stacked on a leading axis: observations ``[n_agents, obs_dim]`` and actions
``[n_agents, act_dim]``. The environment's flat action vector (Brax's API) holds the controlled
joints in robot order; ``action_index`` says where each agent's action entries go in it.
"""

from __future__ import annotations

from typing import Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np


class AgentGroup(NamedTuple):
  """Agents that share one actor network.

  Attributes:
    name: group name, also the observation key (``'legs'``, ``'arms'``, ``'body'``).
    members: limb name of each agent, e.g. ``('left_leg', 'right_leg')``.
    obs_dim: observation size of one agent (one-hot id included when used).
    act_dim: action size of one agent.
    action_index: ``[n_agents][act_dim]`` positions of each agent's actions in the flat action.
  """

  name: str
  members: tuple[str, ...]
  obs_dim: int
  act_dim: int
  action_index: tuple[tuple[int, ...], ...]

  @property
  def n_agents(self) -> int:
    return len(self.members)


def total_agents(groups: Sequence[AgentGroup]) -> int:
  """Number of agents over all groups (the number of critic value heads)."""
  return sum(g.n_agents for g in groups)


def action_size(groups: Sequence[AgentGroup]) -> int:
  """Size of the flat action vector the groups fill."""
  return sum(g.n_agents * g.act_dim for g in groups)


def assemble_action(groups: Sequence[AgentGroup], actions: Mapping[str, jax.Array]) -> jax.Array:
  """Scatters per-group agent actions into the flat action vector.

  Args:
    groups: the agent groups.
    actions: ``{group.name: [..., n_agents, act_dim]}``.

  Returns:
    ``[..., action_size]`` flat action in robot joint order.
  """
  first = actions[groups[0].name]
  flat = jnp.zeros(first.shape[:-2] + (action_size(groups),), first.dtype)
  for g in groups:
    idx = np.asarray(g.action_index).reshape(-1)
    a = actions[g.name].reshape(first.shape[:-2] + (idx.size,))
    flat = flat.at[..., idx].set(a)
  return flat
