"""Orbax checkpoints of a whole :class:`mash.rl.mappo.TrainState`, with the config beside it as
JSON.

A checkpoint step holds two items: ``state`` (params, optimizer state, normalizer statistics, env
state, episode bookkeeping, rng, iteration; restored exactly, so training resumes bit-for-bit) and
``config`` (the :class:`mash.rl.config.TrainConfig` as JSON). Orbax writes each step into a
temporary directory and renames it when complete, so a crash mid-save leaves no step that
``all_steps`` would list. A step that is listed but does not restore (torn by a copy, a full disk, a
stray edit) is skipped with a one-line warning on stderr: :func:`restore_latest` returns the newest
step that restores, and raises :class:`CheckpointError` (one line) when steps exist but none
restores. Nothing is ever deleted here. Only the newest ``max_to_keep`` steps are kept by
:func:`make_manager`'s manager. A save the storage refuses (a full disk, a quota, a read-only file
system) raises :class:`StorageError`, one line; the steps already saved stay as they were (its
temporary directory is replaced by the next save of that step). Typed PRNG keys in the state are
stored as their raw data and re-wrapped on restore. Without a trainer (no template state),
:func:`restore_latest_flat` reads some top-level fields as saved, ``{key path: array}``, and
:func:`unflatten` nests them: how :mod:`mash.deploy.policy` loads one.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import sys
from typing import Any, Callable, Iterator, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from mash.errors import InputError, StorageError, storage_errno
from mash.rl.config import TrainConfig, config_from_dict, config_to_dict


class CheckpointError(InputError):
  """Checkpoint steps exist but none restores (one line, names the directory and the reason)."""


class Restored(NamedTuple):
  """A restored checkpoint.

  Attributes:
    step: the checkpoint step (the iteration it was saved at, by convention).
    state: the train state, with the structure, shapes and dtypes of the template.
    config: the config saved with it.
    skipped: newer steps that were tried first and did not restore (newest first).
  """

  step: int
  state: Any
  config: TrainConfig
  skipped: tuple[int, ...] = ()


def _is_empty(x: Any) -> bool:
  return hasattr(x, "shape") and math.prod(x.shape) == 0


def _to_flat(tree: Any) -> dict[str, Any]:
  """``{key path: leaf}`` without zero-size leaves (MJX keeps some, e.g. ``act`` of a model with no
  activations; Orbax refuses to save them and they carry no information). A flat dict also keeps
  the on-disk layout independent of how JAX flattens dataclass pytrees."""
  return {
      jax.tree_util.keystr(path): leaf
      for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]
      if not _is_empty(leaf)
  }


# What a policy needs; what learning needs (everything but the env states).
POLICY_FIELDS = ("params", "normalizer")
LEARNING_FIELDS = ("params", "opt_state", "normalizer", "episodes", "rng", "iteration")


def _in_fields(key: str, fields: Sequence[str] | None) -> bool:
  """Whether the flat key (``.params[...]...``) lies under one of the top-level ``fields``."""
  return fields is None or any(
      key == f".{f}" or key.startswith((f".{f}.", f".{f}[")) for f in fields)


def _from_flat(flat: dict[str, Any], template: Any, fields: Sequence[str] | None = None) -> Any:
  """Inverse of :func:`_to_flat`, zero-size leaves rebuilt from the template. With ``fields``,
  only the state's top-level fields of those names are read; every other leaf is zeros."""
  paths, treedef = jax.tree_util.tree_flatten_with_path(template)
  wanted = lambda key: _in_fields(key, fields)
  leaves = []
  for path, leaf in paths:
    key = jax.tree_util.keystr(path)
    if _is_empty(leaf) or not wanted(key):
      leaves.append(_zeros(leaf))
    elif key not in flat:
      raise KeyError(f"the checkpoint has no {key}")
    else:
      leaves.append(flat[key])
  return jax.tree.unflatten(treedef, leaves)


def _zeros(leaf: Any) -> jax.Array:
  """Zeros shaped like a template leaf, laid out as its sharding says when it has one (a global
  template of a multi-device run: every process makes the same array, and the next jitted call sees
  the layout it was compiled for)."""
  sharding = getattr(leaf, "sharding", None)
  if isinstance(sharding, jax.sharding.Sharding):
    host = np.zeros(leaf.shape, leaf.dtype)
    return jax.make_array_from_callback(leaf.shape, sharding, lambda index: host[index])
  return jnp.zeros(leaf.shape, leaf.dtype)


def make_manager(directory: str | os.PathLike,
                 max_to_keep: int | None = 5) -> ocp.CheckpointManager:
  """A checkpoint manager over ``directory`` (created if missing) keeping the last ``max_to_keep``
  steps (``None``: keep all)."""
  options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True)
  return ocp.CheckpointManager(os.path.abspath(os.fspath(directory)), options=options,
                               item_names=("state", "config"))


def save(manager: ocp.CheckpointManager, step: int, state: Any, config: TrainConfig,
         wait: bool = True, fields: Sequence[str] | None = None) -> bool:
  """Saves ``state`` (or only its top-level ``fields``, e.g. :data:`LEARNING_FIELDS`) and
  ``config`` as checkpoint ``step``.

  Args:
    manager: from :func:`make_manager`.
    step: checkpoint step (use the training iteration).
    state: the train state. Call this BEFORE donating ``state`` to the next ``train_epoch``.
    config: the training config, stored as JSON.
    wait: block until the checkpoint is complete on disk (default; the next jitted call donates
      the state's buffers, so an asynchronous save must not outlive them).

  Returns:
    Whether a checkpoint was saved (Orbax may skip a step already present).

  Raises:
    StorageError: the storage refused the write (one line; Orbax's own reports of it, tracebacks
      from several threads, are silenced). The step's temporary directory is left, never taken
      for a step; a later save of the step replaces it.
  """
  flat = {
      k: v for k, v in _to_flat(jax.tree.map(_key_to_data, state)).items() if _in_fields(k, fields)
  }
  try:
    with _quiet_absl(), _quiet_failed_writes():
      saved = manager.save(
          step, args=ocp.args.Composite(state=ocp.args.StandardSave(flat),
                                        config=ocp.args.JsonSave(config_to_dict(config))))
      if wait:
        manager.wait_until_finished()
  except Exception as e:  # noqa: BLE001 - only a refusing storage is turned into one line
    code = storage_errno(e)
    if code is None:
      raise
    raise StorageError(f"cannot write checkpoint step {step} in '{manager.directory}': "
                       f"{os.strerror(code)}") from None
  return saved


def restore(manager: ocp.CheckpointManager, step: int, template_state: Any,
            fields: Sequence[str] | None = None) -> Restored:
  """Restores checkpoint ``step`` into the structure of ``template_state`` (arrays or
  ``jax.ShapeDtypeStruct``s, e.g. ``jax.eval_shape(trainer.init, key)``).

  With ``fields`` (e.g. ``('params', 'normalizer')``: all a policy needs) only those top-level
  fields are read and the rest of the returned state is zeros, so a checkpoint stays usable for
  evaluation and export after the env state's layout changed.

  A template with shardings (:func:`mash.rl.distributed.global_state_shapes`) restores global
  arrays, each process reading its own shards (collective: every process calls this); a template
  without them restores onto this process's first device, whatever devices the checkpoint was saved
  from.
  """
  abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct,
                          jax.tree.map(_key_to_data_shape, template_state))
  # A leaf without a sharding in the template is read with the sharding it was saved with; when
  # that names devices this process does not have (a checkpoint of a multi-device or multi-process
  # run read by one process: evaluation, export), it lands on the first local device instead.
  target = ocp.args.StandardRestore(
      _to_flat(abstract) if fields is None else None,
      fallback_sharding=jax.sharding.SingleDeviceSharding(jax.local_devices()[0]))
  restored = manager.restore(step, args=ocp.args.Composite(state=target,
                                                           config=ocp.args.JsonRestore()))
  state = jax.tree.map(_match_commitment, _from_flat(restored["state"], abstract, fields),
                       template_state)
  state = jax.tree.map(_data_to_key, state, template_state)
  return Restored(step=step, state=state, config=config_from_dict(restored["config"]))


def restore_flat(manager: ocp.CheckpointManager, step: int, fields: Sequence[str]) -> Restored:
  """Restores the top-level ``fields`` of checkpoint ``step`` without a template (no trainer):
  ``state`` is ``{key path: array}``, the on-disk layout of :func:`save` (see :func:`unflatten`),
  as saved: with a leading seed axis for a multi-seed run. Arrays are uncommitted, on this process's
  first device. KeyError when a field holds nothing in the checkpoint."""
  target = ocp.args.StandardRestore(
      None, fallback_sharding=jax.sharding.SingleDeviceSharding(jax.local_devices()[0]))
  restored = manager.restore(step, args=ocp.args.Composite(state=target,
                                                           config=ocp.args.JsonRestore()))
  flat = {
      k: jnp.asarray(np.asarray(v)) for k, v in restored["state"].items() if _in_fields(k, fields)
  }
  for field in fields:
    if not any(_in_fields(k, (field,)) for k in flat):
      raise KeyError(f"the checkpoint has no .{field}")
  return Restored(step=step, state=flat, config=config_from_dict(restored["config"]))


_KEY_PART = re.compile(r"\.([A-Za-z_]\w*)|\['((?:[^'\\]|\\.)*)'\]")


def unflatten(flat: dict[str, Any]) -> dict[str, Any]:
  """Nested dicts from :func:`_to_flat`'s ``{key path: leaf}`` without a template: dict keys and
  dataclass fields both become dict entries (``.normalizer['legs'].mean`` ->
  ``{'normalizer': {'legs': {'mean': leaf}}}``). ValueError for a path with other parts (sequence
  indices), which the policy fields do not have."""
  tree: dict[str, Any] = {}
  for key, leaf in flat.items():
    parts, end = [], 0
    for match in _KEY_PART.finditer(key):
      if match.start() != end:
        break
      parts.append(match.group(1) if match.group(1) is not None else match.group(2))
      end = match.end()
    if end != len(key) or not parts:
      raise ValueError(f"checkpoint key {key!r} is not a path of dict keys and fields")
    node = tree
    for part in parts[:-1]:
      node = node.setdefault(part, {})
    node[parts[-1]] = leaf
  return tree


def _is_typed_key(x: Any) -> bool:
  return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _key_to_data(x: Any) -> Any:
  """Typed PRNG keys (``jax.random.key``) are stored as their raw ``uint32`` data."""
  return jax.random.key_data(x) if _is_typed_key(x) else x


def _key_to_data_shape(x: Any) -> Any:
  return jax.eval_shape(jax.random.key_data, x) if _is_typed_key(x) else x


def _data_to_key(restored: Any, template: Any) -> Any:
  if not _is_typed_key(template):
    return restored
  impl = (jax.random.key_impl(template) if isinstance(template, jax.Array) else getattr(
      template.dtype, "_impl", None))  # ShapeDtypeStruct template
  return jax.random.wrap_key_data(restored, impl=impl)


def _match_commitment(restored: jax.Array, template: Any) -> jax.Array:
  """Orbax returns device-committed arrays; a fresh ``init`` state is uncommitted, and jit caches
  the two separately (a resumed run would compile twice). Uncommit where the template is
  uncommitted."""
  committed = (getattr(template, "committed", False) if isinstance(template, jax.Array) else
               getattr(template, "sharding", None) is not None)
  return restored if committed else jnp.asarray(np.asarray(restored))


def _one_line(error: BaseException, limit: int = 160) -> str:
  """``Type: first line of the message``, at most ``limit`` characters."""
  lines = str(error).strip().splitlines()
  text = f"{type(error).__name__}: {lines[0] if lines else ''}".rstrip(": ")
  return text if len(text) <= limit else text[:limit - 3] + "..."


@contextlib.contextmanager
def _quiet_absl() -> Iterator[None]:
  """Silences absl's log lines (Orbax logs every metadata file it cannot parse) while we try steps
  and report failures ourselves, one line each."""
  logger = logging.getLogger("absl")
  level = logger.level
  logger.setLevel(logging.CRITICAL)
  try:
    yield
  finally:
    logger.setLevel(level)


def _drops_closed_loop(hook: Callable[[Any], None]) -> Callable[[Any], None]:
  """``sys.unraisablehook`` ``hook`` but silent on ``RuntimeError('Event loop is closed')``."""

  def drop(unraisable) -> None:
    error = unraisable.exc_value
    if not (isinstance(error, RuntimeError) and str(error) == "Event loop is closed"):
      hook(unraisable)

  drop.drops_closed_loop = True
  return drop


@contextlib.contextmanager
def _quiet_failed_writes() -> Iterator[None]:
  """When an Orbax save fails, its writes still in flight (TensorStore's threads) finish into the
  event loop the failure closed, and Python prints each as ``Exception ignored ... Event loop is
  closed`` with a traceback, during the save or just after it. Those reports (only those) are
  dropped during a save, and for the rest of the process after one that failed."""
  previous = sys.unraisablehook
  if not getattr(previous, "drops_closed_loop", False):
    sys.unraisablehook = _drops_closed_loop(previous)
  yield  # on an exception: the filter stays, for the stragglers
  sys.unraisablehook = previous


def restore_latest(directory: str | os.PathLike, template_state: Any,
                   fields: Sequence[str] | None = None, step: int | None = None) -> Restored | None:
  """Restores the newest checkpoint under ``directory`` that restores (or the one of ``step``).

  Steps are tried newest first; one that fails (torn files, a template that does not match) is
  reported on stderr as ``warning: ...`` and the next older one is tried. Nothing is deleted.

  Args:
    directory: a checkpoint directory written through :func:`make_manager` / :func:`save`.
    template_state: a train state (or its ``eval_shape``) giving structure, shapes and dtypes.
    fields: restore only these top-level fields (see :func:`restore`).
    step: restore this step only (no fallback to older ones); CheckpointError naming the steps
      there are when it is not one of them.

  Returns:
    The restored checkpoint (``skipped`` lists the newer steps that failed), or ``None`` when
    ``directory`` holds no complete checkpoint.

  Raises:
    CheckpointError: checkpoint steps exist but none of them restores.
  """
  return _restore_newest(
      directory, step,
      lambda manager, candidate: restore(manager, candidate, template_state, fields))


def restore_latest_flat(directory: str | os.PathLike, fields: Sequence[str],
                        step: int | None = None) -> Restored | None:
  """:func:`restore_latest` without a template (no trainer): the newest step whose ``fields``
  restore, as :func:`restore_flat` returns them; the same fallback, warnings and errors."""
  return _restore_newest(directory, step,
                         lambda manager, candidate: restore_flat(manager, candidate, fields))


def _restore_newest(
    directory: str | os.PathLike, step: int | None,
    restore_step: Callable[[ocp.CheckpointManager, int], Restored]) -> Restored | None:
  """``restore_step`` on the newest step that restores (or on ``step`` alone); see
  :func:`restore_latest`."""
  if not os.path.isdir(directory):
    return None
  with _quiet_absl():
    manager = make_manager(directory, max_to_keep=None)
    try:
      steps = sorted(manager.all_steps(), reverse=True)
      if step is not None:
        if step not in steps:
          raise CheckpointError(f"no checkpoint of step {step} in '{directory}' (there are "
                                f"steps {', '.join(map(str, sorted(steps))) or 'none'})")
        steps = [step]
      first_error = None
      for i, candidate in enumerate(steps):
        try:
          return restore_step(manager, candidate)._replace(skipped=tuple(steps[:i]))
        except Exception as e:  # noqa: BLE001 - whatever the cause, this step is unusable
          first_error = first_error or _one_line(e)
          if i + 1 < len(steps):  # when none restores, the CheckpointError alone says it all
            print(
                f"warning: checkpoint step {candidate} in '{directory}' does not restore "
                f"({_one_line(e)}); trying step {steps[i + 1]}", file=sys.stderr, flush=True)
    finally:
      manager.close()
  if steps:
    raise CheckpointError(f"no checkpoint in '{directory}' restores (steps "
                          f"{', '.join(map(str, steps))} tried; step {steps[0]}: {first_error})")
  return None
