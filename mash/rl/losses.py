"""MAPPO losses: per-agent GAE and the clipped multi-agent surrogate of the MASH paper.

Shapes: ``T`` unroll steps, ``B`` environments, ``M`` samples of a minibatch (``M = T*B/k``),
``N`` agents over all groups (groups in order, members in order).

The paper's objective (its eq. "MAPPO") sums one clipped PPO surrogate per agent,
``L = sum_i E_t[min(r_t^i A_t^i, clip(r_t^i, 1-eps, 1+eps) A_t^i)]``, where ``r_t^i`` is agent
``i``'s own probability ratio (its Gaussian log-prob summed over its action dims) and ``A_t^i`` its
advantage from its own value head. Conventions fixed here:

- policy loss: summed over agents (the paper's equation), mean over samples;
- entropy: summed over agents (the entropy of the joint policy, so it means the same thing for MASH
  and the single-agent baseline), mean over samples;
- approx_kl: summed over agents (the KL of the joint policy), mean over samples;
- value loss: clipped squared error (rsl_rl form, no 1/2), MEAN over agents and samples, so its
  scale does not depend on the number of agents and ``value_loss_coef`` means the same for any
  partition;
- advantages: normalized per agent over the minibatch (over all devices when ``axis_name`` is
  given);
- sample weights (``LossBatch.weights``, 0 for transitions into a blown-up physics state): a
  weight-0 sample has zero advantage, is left out of the advantage statistics and of every mean.
"""

from __future__ import annotations

from typing import Mapping, NamedTuple

import jax
import jax.numpy as jnp

from mash.rl import networks as nets
from mash.rl import normalization
from mash.rl.config import TrainConfig


class LossBatch(NamedTuple):
  """A minibatch of rollout samples, flattened over time and environments.

  Attributes:
    obs: ``{group: [M, n_agents, obs_dim], 'critic': [M, C]}`` raw (unnormalized) observations.
    actions: ``{group: [M, n_agents, act_dim]}`` sampled actions.
    log_probs: ``[M, N]`` log-prob of each agent's action under the behaviour policy.
    values: ``[M, N]`` value estimates at collection (after the normalizer update).
    advantages: ``[M, N]`` GAE advantages (not normalized).
    returns: ``[M, N]`` value targets (advantages + values).
    weights: ``[M]`` sample weights (1 valid, 0 masked out), or ``None`` for all ones.
  """

  obs: Mapping[str, jax.Array]
  actions: Mapping[str, jax.Array]
  log_probs: jax.Array
  values: jax.Array
  advantages: jax.Array
  returns: jax.Array
  weights: jax.Array | None = None


def compute_gae(rewards: jax.Array, values: jax.Array, next_values: jax.Array, dones: jax.Array,
                truncations: jax.Array, gamma: float, lam: float,
                valid: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
  """Generalized advantage estimation for every agent's value head, by a reverse ``lax.scan``.

  ``delta_t = r_t + gamma * (1 - done_t + trunc_t) * V(s'_t) - V(s_t)`` (bootstrap at time-outs, not
  at falls) and ``A_t = delta_t + gamma * lam * (1 - done_t) * A_{t+1}`` (the recursion is cut at
  every episode end), with ``A_T = 0`` after the last step. Where ``valid_t = 0`` (a step into a
  blown-up physics state) ``delta_t = 0`` whatever ``r_t`` and ``V(s'_t)`` hold, NaN included, so
  ``A_t = 0``, the return is ``V(s_t)`` and the episode counts as cut at ``s_t`` (bootstrapped by
  the step before, not penalized as a fall).

  Args:
    rewards: ``[T, B]`` shared reward (or ``[T, B, N]``).
    values: ``[T, B, N]`` ``V(s_t)``.
    next_values: ``[T, B, N]`` ``V(s'_t)`` of the state reached by step t (the terminal state,
      before the auto-reset, when the episode ended).
    dones: ``[T, B]`` 1.0 where the episode ended at step t (fall or time-out).
    truncations: ``[T, B]`` 1.0 where it ended by time-out only.
    gamma: discount.
    lam: GAE lambda.
    valid: ``[T, B]`` 1.0 for usable steps, 0.0 for masked ones (``None``: all usable).

  Returns:
    ``(advantages, returns)``, each ``[T, B, N]``; ``returns = advantages + values``.
  """
  if rewards.ndim == values.ndim - 1:
    rewards = rewards[..., None]
  rewards = jnp.broadcast_to(rewards, values.shape)
  done = dones[..., None].astype(values.dtype)
  bootstrap = 1.0 - done + truncations[..., None].astype(values.dtype)
  deltas = rewards + gamma * bootstrap * next_values - values
  if valid is not None:
    deltas = jnp.where(valid[..., None] > 0, deltas, 0.0)
  carry_mask = gamma * lam * (1.0 - done)

  def backward(next_adv: jax.Array, x: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
    delta, mask = x
    adv = delta + mask * next_adv
    return adv, adv

  _, advantages = jax.lax.scan(backward, jnp.zeros_like(values[0]), (deltas, carry_mask),
                               reverse=True)
  return advantages, advantages + values


def normalize_advantages(advantages: jax.Array, axis_name: str | None = None,
                         weights: jax.Array | None = None) -> jax.Array:
  """``[M, N] -> [M, N]``: zero mean, unit std per agent over the minibatch (and devices).

  With ``weights [M]`` (0 or 1), the statistics are those of the weight-1 samples and the
  weight-0 samples come out as exactly 0.
  """
  if weights is not None:
    w = weights[:, None].astype(advantages.dtype)
    advantages = jnp.where(w > 0, advantages, 0.0)
    count, total = jnp.sum(w), jnp.sum(w * advantages, axis=0)
    if axis_name is not None:
      count, total = jax.lax.psum((count, total), axis_name)
    mean = total / jnp.maximum(count, 1.0)
    square = jnp.sum(w * jnp.square(advantages - mean), axis=0)
    if axis_name is not None:
      square = jax.lax.psum(square, axis_name)
    std = jnp.sqrt(square / jnp.maximum(count, 1.0))
    return jnp.where(w > 0, (advantages - mean) / (std + 1e-8), 0.0)
  mean = jnp.mean(advantages, axis=0)
  if axis_name is not None:
    mean = jax.lax.pmean(mean, axis_name)
  var = jnp.mean(jnp.square(advantages - mean), axis=0)
  if axis_name is not None:
    var = jax.lax.pmean(var, axis_name)
  return (advantages - mean) / (jnp.sqrt(var) + 1e-8)


def mappo_loss_terms(log_probs: jax.Array, old_log_probs: jax.Array, advantages: jax.Array,
                     values: jax.Array, old_values: jax.Array, returns: jax.Array,
                     entropy: jax.Array, config: TrainConfig,
                     weights: jax.Array | None = None) -> tuple[jax.Array, dict[str, jax.Array]]:
  """The MAPPO loss from per-agent quantities (no networks; advantages used as given).

  Args:
    log_probs: ``[M, N]`` log-probs under the current policy.
    old_log_probs: ``[M, N]`` log-probs under the behaviour policy.
    advantages: ``[M, N]`` advantages (already normalized if wanted).
    values: ``[M, N]`` current value predictions.
    old_values: ``[M, N]`` value predictions at collection.
    returns: ``[M, N]`` value targets.
    entropy: ``[M, N]`` (or ``[N]``) entropy of each agent's current policy.
    config: uses ``clip_epsilon``, ``value_clip``, ``value_loss_coef``, ``entropy_coef``.
    weights: ``[M]`` sample weights: every mean over samples becomes ``sum(w x) / sum(w)``
      (``None``: plain means).

  Returns:
    ``(loss, metrics)``, ``loss = policy_loss + value_loss_coef * value_loss - entropy_coef *
    entropy``; metrics: ``policy_loss``, ``value_loss``, ``entropy``, ``approx_kl``,
    ``clip_fraction`` (scalars).
  """
  eps = config.clip_epsilon

  def sample_mean(x: jax.Array) -> jax.Array:
    """``[M, N] -> [N]``: (weighted) mean over samples."""
    if weights is None:
      return jnp.mean(x, axis=0)
    w = weights[:, None].astype(x.dtype)
    return jnp.sum(w * x, axis=0) / jnp.maximum(jnp.sum(w), 1.0)

  log_ratio = log_probs - old_log_probs
  ratio = jnp.exp(log_ratio)
  surrogate = jnp.minimum(ratio * advantages, jnp.clip(ratio, 1.0 - eps, 1.0 + eps) * advantages)
  policy_loss = -jnp.sum(sample_mean(surrogate))

  value_error = jnp.square(values - returns)
  if config.value_clip > 0:
    clipped = old_values + jnp.clip(values - old_values, -config.value_clip, config.value_clip)
    value_error = jnp.maximum(value_error, jnp.square(clipped - returns))
  value_loss = jnp.mean(sample_mean(value_error))

  entropy = jnp.sum(sample_mean(jnp.broadcast_to(entropy, log_probs.shape)))
  loss = policy_loss + config.value_loss_coef * value_loss - config.entropy_coef * entropy
  metrics = {
      "policy_loss": policy_loss,
      "value_loss": value_loss,
      "entropy": entropy,
      "approx_kl": jnp.sum(sample_mean((ratio - 1.0) - log_ratio)),
      "clip_fraction": jnp.mean(sample_mean((jnp.abs(ratio - 1.0) > eps).astype(jnp.float32))),
  }
  return loss, metrics


def mappo_loss(params: nets.Params, normalizer: normalization.Normalizer | None, batch: LossBatch,
               networks: nets.Networks, config: TrainConfig,
               axis_name: str | None = None) -> tuple[jax.Array, dict[str, jax.Array]]:
  """MAPPO loss of a minibatch under ``params``.

  Args:
    params: actor and critic parameters.
    normalizer: observation statistics (fixed during the update), or ``None``.
    batch: the minibatch, ``M`` samples.
    networks: the apply functions.
    config: loss coefficients; ``normalize_advantages``.
    axis_name: mesh axis over which advantage statistics are averaged, or ``None``.

  Returns:
    ``(loss, metrics)`` as in :func:`mappo_loss_terms`.
  """
  dists = networks.policy_apply(params, normalizer, batch.obs)
  groups = networks.groups
  # yapf: disable
  log_probs = nets.per_agent(
      groups,
      {g.name: nets.gaussian_log_prob(dists[g.name], batch.actions[g.name]) for g in groups})
  # yapf: enable
  entropy = nets.per_agent(groups, {g.name: nets.gaussian_entropy(dists[g.name]) for g in groups})
  values = networks.value_apply(params, normalizer, batch.obs["critic"])
  advantages = batch.advantages
  if config.normalize_advantages:
    advantages = normalize_advantages(advantages, axis_name, batch.weights)
  elif batch.weights is not None:
    advantages = jnp.where(batch.weights[:, None] > 0, advantages, 0.0)
  return mappo_loss_terms(log_probs, batch.log_probs, advantages, values, batch.values,
                          batch.returns, entropy, config, batch.weights)
