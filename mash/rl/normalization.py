"""Running observation normalization: mean and variance with counts, as pure functions.

One :class:`RunningStats` per observation stream (each agent group's stream and the critic's), kept
in the train state as ``{stream_name: RunningStats}``. Statistics are merged from whole rollout
batches with the parallel (Chan et al.) update, so the result does not depend on how the batch is
split, and across devices by summing counts, sums and squared deviations over an optional mesh axis.
"""

from __future__ import annotations

from typing import Mapping

import flax.struct
import jax
import jax.numpy as jnp

VAR_FLOOR = 1e-4  # variances below this (constant features) are floored: std >= 1e-2.


@flax.struct.dataclass
class RunningStats:
  """Running moments of one observation stream.

  Attributes:
    count: ``[]`` number of vectors merged so far (float32).
    mean: ``[dim]`` running mean.
    m2: ``[dim]`` running sum of squared deviations from the mean (variance = m2 / count).
  """

  count: jax.Array
  mean: jax.Array
  m2: jax.Array

  @property
  def var(self) -> jax.Array:
    """``[dim]`` population variance; 1 before any data (so normalization starts as identity)."""
    return jnp.where(self.count > 0, self.m2 / jnp.maximum(self.count, 1.0), 1.0)

  @property
  def std(self) -> jax.Array:
    """``[dim]`` standard deviation, floored at ``sqrt(VAR_FLOOR)``."""
    return jnp.sqrt(jnp.maximum(self.var, VAR_FLOOR))


Normalizer = dict[str, RunningStats]


def init_stats(dim: int) -> RunningStats:
  """Empty statistics for a ``dim``-sized stream."""
  return RunningStats(count=jnp.zeros((), jnp.float32), mean=jnp.zeros((dim,), jnp.float32),
                      m2=jnp.zeros((dim,), jnp.float32))


def update_stats(stats: RunningStats, batch: jax.Array,
                 axis_name: str | None = None) -> RunningStats:
  """Merges a batch of observations into the statistics.

  Args:
    stats: current statistics of a ``dim`` stream.
    batch: ``[..., dim]`` observations; all leading axes are samples.
    axis_name: if given, the batch is this device's share and the statistics of all devices on the
      mesh axis are merged (every device returns the same result).

  Returns:
    Updated statistics.
  """
  x = batch.reshape(-1, batch.shape[-1]).astype(jnp.float32)
  n_b = jnp.asarray(x.shape[0], jnp.float32)
  sum_b = x.sum(axis=0)
  if axis_name is not None:
    n_b = jax.lax.psum(n_b, axis_name)
    sum_b = jax.lax.psum(sum_b, axis_name)
  mean_b = sum_b / n_b
  m2_b = jnp.square(x - mean_b).sum(axis=0)
  if axis_name is not None:
    m2_b = jax.lax.psum(m2_b, axis_name)
  total = stats.count + n_b
  delta = mean_b - stats.mean
  mean = stats.mean + delta * (n_b / total)
  m2 = stats.m2 + m2_b + jnp.square(delta) * (stats.count * n_b / total)
  return RunningStats(count=total, mean=mean, m2=m2)


def normalize(stats: RunningStats, x: jax.Array, clip: float) -> jax.Array:
  """``[..., dim] -> [..., dim]``: ``clip((x - mean) / std, -clip, clip)``."""
  return jnp.clip((x - stats.mean) / stats.std, -clip, clip)


def init_normalizer(sizes: Mapping[str, int]) -> Normalizer:
  """Empty statistics for each stream, e.g. ``{'legs': 32, 'arms': 26, 'critic': 106}``."""
  return {name: init_stats(dim) for name, dim in sizes.items()}


def update_normalizer(normalizer: Normalizer, obs: Mapping[str, jax.Array],
                      axis_name: str | None = None) -> Normalizer:
  """Updates every stream of ``normalizer`` from ``obs[stream]`` (``[..., dim]``); see
  :func:`update_stats`."""
  return {name: update_stats(stats, obs[name], axis_name) for name, stats in normalizer.items()}
