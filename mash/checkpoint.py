"""Orbax checkpoints of a whole :class:`mash.train.TrainState`, with the config beside it as JSON.

A checkpoint step holds two items: ``state`` (params, optimizer state, normalizer statistics, env
state, episode bookkeeping, rng, iteration; restored exactly, so training resumes bit-for-bit) and
``config`` (the :class:`mash.config.TrainConfig` as JSON). Orbax writes each step into a temporary
directory and renames it when complete, so a crash mid-save leaves no step that ``latest_step`` would
return: :func:`restore_latest` always picks the newest complete step. Only the newest ``max_to_keep``
steps are kept. Typed PRNG keys in the state are stored as their raw data and re-wrapped on restore.
"""

from __future__ import annotations

import math
import os
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from mash.config import TrainConfig, config_from_dict, config_to_dict


class Restored(NamedTuple):
  """A restored checkpoint.

  Attributes:
    step: the checkpoint step (the iteration it was saved at, by convention).
    state: the train state, with the structure, shapes and dtypes of the template.
    config: the config saved with it.
  """

  step: int
  state: Any
  config: TrainConfig


def _is_empty(x: Any) -> bool:
  return hasattr(x, 'shape') and math.prod(x.shape) == 0


def _to_flat(tree: Any) -> dict[str, Any]:
  """``{key path: leaf}`` without zero-size leaves (MJX keeps some, e.g. ``act`` of a model with no
  activations; Orbax refuses to save them and they carry no information). A flat dict also keeps
  the on-disk layout independent of how JAX flattens dataclass pytrees."""
  return {jax.tree_util.keystr(path): leaf
          for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0] if not _is_empty(leaf)}


def _from_flat(flat: dict[str, Any], template: Any) -> Any:
  """Inverse of :func:`_to_flat`, zero-size leaves rebuilt from the template."""
  paths, treedef = jax.tree_util.tree_flatten_with_path(template)
  leaves = [jax.numpy.zeros(leaf.shape, leaf.dtype) if _is_empty(leaf)
            else flat[jax.tree_util.keystr(path)] for path, leaf in paths]
  return jax.tree.unflatten(treedef, leaves)


def make_manager(directory: str | os.PathLike, max_to_keep: int | None = 5) -> ocp.CheckpointManager:
  """A checkpoint manager over ``directory`` (created if missing) keeping the last ``max_to_keep``
  steps (``None``: keep all)."""
  options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True)
  return ocp.CheckpointManager(os.path.abspath(os.fspath(directory)), options=options,
                               item_names=('state', 'config'))


def save(manager: ocp.CheckpointManager, step: int, state: Any, config: TrainConfig,
         wait: bool = True) -> bool:
  """Saves ``state`` and ``config`` as checkpoint ``step``.

  Args:
    manager: from :func:`make_manager`.
    step: checkpoint step (use the training iteration).
    state: the train state. Call this BEFORE donating ``state`` to the next ``train_epoch``.
    config: the training config, stored as JSON.
    wait: block until the checkpoint is complete on disk (default; the next jitted call donates
      the state's buffers, so an asynchronous save must not outlive them).

  Returns:
    Whether a checkpoint was saved (Orbax may skip a step already present).
  """
  flat = _to_flat(jax.tree.map(_key_to_data, state))
  saved = manager.save(step, args=ocp.args.Composite(
      state=ocp.args.StandardSave(flat), config=ocp.args.JsonSave(config_to_dict(config))))
  if wait:
    manager.wait_until_finished()
  return saved


def restore(manager: ocp.CheckpointManager, step: int, template_state: Any) -> Restored:
  """Restores checkpoint ``step`` into the structure of ``template_state`` (arrays or
  ``jax.ShapeDtypeStruct``s, e.g. ``jax.eval_shape(trainer.init, key)``)."""
  abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct,
                          jax.tree.map(_key_to_data_shape, template_state))
  restored = manager.restore(step, args=ocp.args.Composite(
      state=ocp.args.StandardRestore(_to_flat(abstract)), config=ocp.args.JsonRestore()))
  state = jax.tree.map(_match_commitment, _from_flat(restored['state'], abstract), template_state)
  state = jax.tree.map(_data_to_key, state, template_state)
  return Restored(step=step, state=state, config=config_from_dict(restored['config']))


def _is_typed_key(x: Any) -> bool:
  return hasattr(x, 'dtype') and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _key_to_data(x: Any) -> Any:
  """Typed PRNG keys (``jax.random.key``) are stored as their raw ``uint32`` data."""
  return jax.random.key_data(x) if _is_typed_key(x) else x


def _key_to_data_shape(x: Any) -> Any:
  return jax.eval_shape(jax.random.key_data, x) if _is_typed_key(x) else x


def _data_to_key(restored: Any, template: Any) -> Any:
  if not _is_typed_key(template):
    return restored
  impl = (jax.random.key_impl(template) if isinstance(template, jax.Array)
          else getattr(template.dtype, '_impl', None))  # ShapeDtypeStruct template
  return jax.random.wrap_key_data(restored, impl=impl)


def _match_commitment(restored: jax.Array, template: Any) -> jax.Array:
  """Orbax returns device-committed arrays; a fresh ``init`` state is uncommitted, and jit caches the
  two separately (a resumed run would compile twice). Uncommit where the template is uncommitted."""
  committed = (getattr(template, 'committed', False) if isinstance(template, jax.Array)
               else getattr(template, 'sharding', None) is not None)
  return restored if committed else jnp.asarray(np.asarray(restored))


def restore_latest(directory: str | os.PathLike, template_state: Any) -> Restored | None:
  """Restores the newest complete checkpoint under ``directory``.

  Args:
    directory: a checkpoint directory written through :func:`make_manager` / :func:`save`.
    template_state: a train state (or its ``eval_shape``) giving structure, shapes and dtypes.

  Returns:
    The restored checkpoint, or ``None`` when ``directory`` holds no complete checkpoint.
  """
  if not os.path.isdir(directory):
    return None
  manager = make_manager(directory, max_to_keep=None)
  try:
    step = manager.latest_step()
    if step is None:
      return None
    return restore(manager, step, template_state)
  finally:
    manager.close()
