"""Actor and critic networks of MASH, the Gaussian policy math, and their pure apply functions.

- :class:`GroupActor`: one MLP (ELU) shared by all agents of a group; maps ONE agent's observation
  ``[obs_dim]`` to its action mean ``[act_dim]``, with a state-independent learned log-std per
  group. With ``share_actor=False`` (ablation) the module is vmapped over the group's agents with
  separate parameters (:class:`PerAgentActor`).
- :class:`CentralCritic`: one MLP on the privileged critic observation with one value head per agent
  (or a single head broadcast to all agents when ``shared_value_head``).
- :func:`make_networks` builds both and returns pure ``init`` / ``policy_apply`` / ``value_apply``
  functions over a params dict ``{'actors': {group: variables}, 'critic': variables}``.

Agent order everywhere (value heads, per-agent log-probs): groups in order, members in order.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import flax.linen as nn
import flax.traverse_util
import jax
import jax.numpy as jnp
import numpy as np

from mash.rl import normalization
from mash.rl.config import TrainConfig
from mash.sim.agents import AgentGroup, assemble_action, total_agents

Params = dict[str, Any]
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


class GaussianParams(NamedTuple):
  """Diagonal Gaussian policy of a group.

  Attributes:
    mean: ``[..., n_agents, act_dim]``.
    log_std: ``[act_dim]`` (shared actor) or ``[n_agents, act_dim]`` (per-agent actors);
      broadcasts against ``mean``.
  """

  mean: jax.Array
  log_std: jax.Array


@jax.custom_jvp
def elu(x: jax.Array) -> jax.Array:
  """ELU (alpha 1): ``jax.nn.elu``'s values and gradient to float rounding (absolute error below
  1e-7), computed more cheaply on XLA's CPU backend (measured on 2 CPU cores: the MASH update 7 %
  faster from ``exp(x) - 1`` in place of ``expm1``, 4 % more from the derivative below)."""
  negative = jnp.where(x > 0, 0.0, x)  # keeps the unused branch finite
  return jnp.where(x > 0, x, jnp.exp(negative) - 1.0)


@elu.defjvp
def _elu_jvp(primals: tuple[jax.Array], tangents: tuple[jax.Array]) -> tuple[jax.Array, jax.Array]:
  # The derivative from the output alone (1 where y > 0, else exp(x) = y + 1), so the backward
  # pass reads y, which the next layer keeps anyway, and no exp is kept or recomputed for it.
  (x,), (dx,) = primals, tangents
  y = elu(x)
  return y, jnp.where(y > 0, dx, dx * (y + 1.0))


class MLP(nn.Module):
  """ELU multilayer perceptron with a linear output layer.

  Attributes:
    hidden_sizes: widths of the hidden layers.
    out_size: output width.
    out_scale: scale of the output layer's initial weights (small for the actor's mean, so the
      initial policy is centred on the default pose).
  """

  hidden_sizes: Sequence[int]
  out_size: int
  out_scale: float = 1.0

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    for width in self.hidden_sizes:
      x = elu(nn.Dense(width)(x))
    init = nn.initializers.variance_scaling(self.out_scale, "fan_in", "truncated_normal")
    return nn.Dense(self.out_size, kernel_init=init)(x)


class GroupActor(nn.Module):
  """Actor of one agent group: one agent's observation to its action distribution.

  Attributes:
    act_dim: action size of one agent.
    hidden_sizes: MLP hidden widths.
    init_log_std: initial log-std of every action dimension.
  """

  act_dim: int
  hidden_sizes: Sequence[int] = (512, 256, 128)
  init_log_std: float = 0.0

  @nn.compact
  def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``obs [..., obs_dim]`` -> ``(mean [..., act_dim], log_std [act_dim])``."""
    mean = MLP(self.hidden_sizes, self.act_dim, out_scale=0.01)(obs)
    log_std = self.param("log_std", nn.initializers.constant(self.init_log_std), (self.act_dim,))
    return mean, log_std


class PerAgentActor(nn.Module):
  """Ablation (``share_actor=False``): a :class:`GroupActor` per agent, separate parameters.

  Attributes:
    n_agents: agents in the group.
    act_dim, hidden_sizes, init_log_std: as in :class:`GroupActor`.
  """

  n_agents: int
  act_dim: int
  hidden_sizes: Sequence[int] = (512, 256, 128)
  init_log_std: float = 0.0

  @nn.compact
  def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``obs [..., n_agents, obs_dim]`` ->
    ``(mean [..., n_agents, act_dim], log_std [n_agents, act_dim])``."""
    actors = nn.vmap(GroupActor, in_axes=0, out_axes=0, variable_axes={"params": 0},
                     split_rngs={"params": True}, axis_size=self.n_agents)
    mean, log_std = actors(self.act_dim, self.hidden_sizes,
                           self.init_log_std)(jnp.moveaxis(obs, -2, 0))
    return jnp.moveaxis(mean, 0, -2), log_std


class CentralCritic(nn.Module):
  """Centralized critic: privileged global observation to one value per head.

  Attributes:
    n_heads: number of value heads (total agents, or 1 for the shared-head ablation).
    hidden_sizes: MLP hidden widths.
  """

  n_heads: int
  hidden_sizes: Sequence[int] = (512, 256, 128)

  @nn.compact
  def __call__(self, critic_obs: jax.Array) -> jax.Array:
    """``[..., critic_obs_size] -> [..., n_heads]``."""
    return MLP(self.hidden_sizes, self.n_heads)(critic_obs)


class LocalCritic(nn.Module):
  """Ablation (IPPO): each agent's own critic on its own observation only.

  Attributes:
    n_agents: agents (value heads).
    hidden_sizes: MLP hidden widths (separate parameters per agent).
  """

  n_agents: int
  hidden_sizes: Sequence[int] = (512, 256, 128)

  @nn.compact
  def __call__(self, critic_obs: jax.Array) -> jax.Array:
    """``[..., n_agents * obs_dim]`` (each agent's padded observation) -> ``[..., n_agents]``."""
    x = critic_obs.reshape(critic_obs.shape[:-1] + (self.n_agents, -1))
    critics = nn.vmap(MLP, in_axes=0, out_axes=0, variable_axes={"params": 0},
                      split_rngs={"params": True}, axis_size=self.n_agents)
    values = critics(self.hidden_sizes, 1)(jnp.moveaxis(x, -2, 0))
    return jnp.moveaxis(values[..., 0], 0, -1)


class Networks(NamedTuple):
  """The networks of one agent partition, as pure functions.

  Attributes:
    groups: the agent groups.
    n_value_heads: critic outputs (``total_agents`` or 1).
    init: ``key -> params``.
    policy_apply: ``(params, normalizer, obs) -> {group: GaussianParams}``.
    value_apply: ``(params, normalizer, critic_obs [..., C]) -> values [..., total_agents]``.
  """

  groups: tuple[AgentGroup, ...]
  n_value_heads: int
  init: Callable[[jax.Array], Params]
  policy_apply: Callable[..., dict[str, GaussianParams]]
  value_apply: Callable[..., jax.Array]


def make_networks(groups: Sequence[AgentGroup], critic_obs_size: int,
                  config: TrainConfig) -> Networks:
  """Builds the actors (one per group) and the centralized critic.

  Args:
    groups: the agent groups (their ``obs_dim`` / ``act_dim`` size the actors).
    critic_obs_size: size of the critic observation.
    config: uses ``actor_hidden``, ``critic_hidden``, ``init_log_std``, ``share_actor``,
      ``shared_value_head``, ``obs_clip``.

  Returns:
    :class:`Networks`. ``normalizer`` arguments of the apply functions are
    ``{group.name: RunningStats, 'critic': RunningStats}`` or ``None`` (no normalization).
  """
  groups = tuple(groups)
  n_agents = total_agents(groups)
  n_heads = 1 if config.shared_value_head else n_agents

  def actor_module(g: AgentGroup) -> nn.Module:
    if config.share_actor:
      return GroupActor(g.act_dim, tuple(config.actor_hidden), config.init_log_std)
    return PerAgentActor(g.n_agents, g.act_dim, tuple(config.actor_hidden), config.init_log_std)

  actors = {g.name: actor_module(g) for g in groups}
  if config.local_critic:
    if critic_obs_size % n_agents:
      raise ValueError(f'local_critic: critic_obs_size {critic_obs_size} is not n_agents '
                       f'({n_agents}) x an observation size; build the env with critic="local"')
    critic = LocalCritic(n_agents, tuple(config.critic_hidden))
    n_heads = n_agents
  else:
    critic = CentralCritic(n_heads, tuple(config.critic_hidden))

  def maybe_normalize(normalizer: normalization.Normalizer | None, name: str,
                      x: jax.Array) -> jax.Array:
    if normalizer is None:
      return x
    return normalization.normalize(normalizer[name], x, config.obs_clip)

  def init(key: jax.Array) -> Params:
    keys = jax.random.split(key, len(groups) + 1)
    actor_params = {
        g.name: actors[g.name].init(k, jnp.zeros((g.n_agents, g.obs_dim), jnp.float32))
        for g, k in zip(groups, keys[:-1])
    }
    critic_params = critic.init(keys[-1], jnp.zeros((critic_obs_size,), jnp.float32))
    return {"actors": actor_params, "critic": critic_params}

  def policy_apply(params: Params, normalizer: normalization.Normalizer | None,
                   obs: Mapping[str, jax.Array]) -> dict[str, GaussianParams]:
    """``obs {group: [..., n_agents, obs_dim]}`` -> ``{group: GaussianParams}``."""
    out = {}
    for g in groups:
      x = maybe_normalize(normalizer, g.name, obs[g.name])
      if config.share_actor:
        # One application per agent, not one over the stacked [..., n_agents, obs_dim]: the same
        # parameters and results, but independent matrix chains, which XLA's CPU runtime runs
        # concurrently with each other and with the critic (measured on 2 CPU cores: the MASH
        # update 8 % faster; single-agent PPO's, with its one agent, 9 %).
        per_agent = [
            actors[g.name].apply(params["actors"][g.name], x[..., i, :]) for i in range(g.n_agents)
        ]
        mean = jnp.stack([m for m, _ in per_agent], axis=-2)
        log_std = per_agent[0][1]
      else:
        mean, log_std = actors[g.name].apply(params["actors"][g.name], x)
      out[g.name] = GaussianParams(mean=mean, log_std=log_std)
    return out

  def value_apply(params: Params, normalizer: normalization.Normalizer | None,
                  critic_obs: jax.Array) -> jax.Array:
    """``critic_obs [..., C]`` -> ``[..., total_agents]`` (single head broadcast when shared)."""
    x = maybe_normalize(normalizer, "critic", critic_obs)
    values = critic.apply(params["critic"], x)
    return jnp.broadcast_to(values, values.shape[:-1] + (n_agents,))

  return Networks(groups=groups, n_value_heads=n_heads, init=init, policy_apply=policy_apply,
                  value_apply=value_apply)


def gaussian_log_prob(dist: GaussianParams, actions: jax.Array) -> jax.Array:
  """Log-density of ``actions [..., n_agents, act_dim]``, summed over each agent's action dims.

  Returns:
    ``[..., n_agents]``.
  """
  z = (actions - dist.mean) * jnp.exp(-dist.log_std)
  return jnp.sum(-0.5 * jnp.square(z) - dist.log_std - _LOG_SQRT_2PI, axis=-1)


def gaussian_entropy(dist: GaussianParams) -> jax.Array:
  """Entropy of each agent's Gaussian, ``[..., n_agents]`` (same shape as the mean less act_dim)."""
  log_std = jnp.broadcast_to(dist.log_std, dist.mean.shape)
  return jnp.sum(log_std + 0.5 + _LOG_SQRT_2PI, axis=-1)


def sample_actions(key: jax.Array, dists: Mapping[str, GaussianParams]) -> dict[str, jax.Array]:
  """Samples ``{group: [..., n_agents, act_dim]}`` from each group's Gaussian.

  One normal draw covers all groups (split afterwards); all groups must share the batch shape.
  """
  items = list(dists.items())
  batch_shape = items[0][1].mean.shape[:-2]
  sizes = [d.mean.shape[-2] * d.mean.shape[-1] for _, d in items]
  noise = jax.random.normal(key, batch_shape + (sum(sizes),), items[0][1].mean.dtype)
  chunks = jnp.split(noise, np.cumsum(sizes)[:-1], axis=-1)
  return {
      name: d.mean + jnp.exp(d.log_std) * z.reshape(d.mean.shape)
      for (name, d), z in zip(items, chunks)
  }


def per_agent(groups: Sequence[AgentGroup], values: Mapping[str, jax.Array]) -> jax.Array:
  """Concatenates per-group ``{group: [..., n_agents_g]}`` into ``[..., total_agents]`` (agent
  order)."""
  return jnp.concatenate([values[g.name] for g in groups], axis=-1)


def make_policy_fn(networks: Networks, deterministic: bool = True) -> Callable[..., jax.Array]:
  """Policy for rollouts outside training (evaluation, sim-to-sim, export).

  Returns:
    ``policy(params, normalizer, obs, key) -> flat action [..., action_size]``: the mean action when
    ``deterministic``, else a sample (``key`` unused when deterministic).
  """

  def policy(params: Params, normalizer: normalization.Normalizer | None,
             obs: Mapping[str, jax.Array], key: jax.Array | None = None) -> jax.Array:
    dists = networks.policy_apply(params, normalizer, obs)
    if deterministic:
      actions = {name: d.mean for name, d in dists.items()}
    else:
      actions = sample_actions(key, dists)
    return assemble_action(networks.groups, actions)

  return policy


def mean_action_std(params: Params) -> jax.Array:
  """``[]`` mean of ``exp(log_std)`` over every actor's action dims (and agents, if not shared)."""
  flat = flax.traverse_util.flatten_dict(params["actors"])
  stds = [jnp.exp(v).reshape(-1) for k, v in flat.items() if k[-1] == "log_std"]
  return jnp.mean(jnp.concatenate(stds))
