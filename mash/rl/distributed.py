"""Several processes as one: joining them, the global device mesh, global arrays and collectives.

The trainer's mesh variant (:func:`mash.rl.trainer.make_trainer` with ``mesh``) splits the env
batch over a mesh of devices; this module supplies what changes when the mesh spans several
*processes* (several hosts, or several processes on one host):

- :func:`initialize` joins the processes (``jax.distributed.initialize``; Gloo collectives on CPU);
- :func:`global_mesh` is a 1-D mesh over all devices of all processes (``AxisType.Auto`` axes);
- :func:`to_global` turns a pytree every process built alike into global arrays;
- :func:`gather_to_host` brings metrics (replicated) or any global array back as numpy;
- :func:`barrier` and :func:`allgather_ints` are the host loop's two collectives.

Every process runs the same program (SPMD): the same calls, in the same order, with the same
arguments. Only **process 0** (:func:`is_primary`) should write run files (``progress.csv``,
``summary.json``, plots, TensorBoard); Orbax checkpoints are the exception, ``checkpoint.save`` and
``restore`` are collective and must be called by every process (each writes its own shards, Orbax's
primary process the metadata).

One process with several devices uses the same functions (no :func:`initialize` needed): on GPU/TPU
that is the usual setup. On CPU, one process with several forced host devices
(``--xla_force_host_platform_device_count``) runs the toy env, but a sharded MJX step deadlocks
there (see the project notes); use one process per CPU device instead.

Example (run once per process, ``i = 0 .. n-1``)::

    distributed.initialize('10.0.0.1:1234', num_processes=n, process_id=i)
    t = trainer.make_trainer(config, env, mesh=distributed.global_mesh())
    state = t.init()
    for _ in range(calls):
      state, metrics = t.train_epoch(state)
      metrics = t.to_host(metrics)                    # every process
      if distributed.is_primary():
        ...                                           # log, write files
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import NamedSharding


def _check_coordinator(coordinator: str) -> None:
  host, sep, port = str(coordinator).rpartition(":")
  if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
    raise ValueError(f"coordinator '{coordinator}' is not 'host:port' (e.g. '127.0.0.1:12355').")


def initialize(coordinator: str, num_processes: int, process_id: int,
               local_device_ids: int | list[int] | None = None, timeout_s: int = 300) -> None:
  """Joins this process to a multi-process JAX run. Call before any other JAX work.

  On CPU the cross-process collectives go through Gloo (``jax_cpu_collectives_implementation``);
  the setting only concerns the CPU client, so it is also set when the platform is not known yet.
  ``num_processes == 1`` does nothing (a plain single-process run), so callers may call this
  unconditionally. Calling it again once initialized does nothing. Before returning it runs one
  tiny collective over all devices, so that the communication context exists before the first
  (slow-to-compile) training call; a mesh over a subset of the devices would need its own.

  Args:
    coordinator: ``'host:port'`` of process 0, reachable from every process.
    num_processes: processes in the run.
    process_id: this process's index, ``0 <= process_id < num_processes``.
    local_device_ids: restrict this process to these local devices (e.g. one GPU per process).
    timeout_s: how long to wait for every process to join.

  Raises:
    ValueError: a malformed coordinator address or an out-of-range process count or id.
  """
  _check_coordinator(coordinator)
  if not isinstance(num_processes, int) or num_processes < 1:
    raise ValueError(f"num_processes must be an integer >= 1, got {num_processes!r}.")
  if not isinstance(process_id, int) or not 0 <= process_id < num_processes:
    raise ValueError(f"process_id must be an integer in [0, {num_processes - 1}], "
                     f"got {process_id!r}.")
  if num_processes == 1 or jax.distributed.is_initialized():
    return
  platforms = jax.config.jax_platforms
  if not platforms or "cpu" in platforms:
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
  jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                             process_id=process_id, local_device_ids=local_device_ids,
                             initialization_timeout=timeout_s)
  # The first collective over a set of devices sets up the communication context (Gloo on CPU),
  # and Gloo gives every process only 30 s to arrive: a first training call whose compile time
  # differs by more between processes would fail ("Gloo context initialization failed:
  # DEADLINE_EXCEEDED"). Set it up now, while the processes are in step (initialize is a barrier).
  # Later collectives wait for slow peers without that limit (measured: 45 s skew is fine).
  multihost_utils.sync_global_devices("mash.rl.distributed.initialize")


def is_primary() -> bool:
  """Whether this is process 0, the one that writes run files."""
  return jax.process_index() == 0


def global_mesh(axis_name: str = "devices", devices: list[Any] | None = None) -> jax.sharding.Mesh:
  """A 1-D mesh over every device of every process, ordered by process then device id.

  Each process's devices are contiguous along the axis, so process ``p`` of ``n`` (one device
  each) steps envs ``[p * B/n, (p + 1) * B/n)``, exactly the envs device ``p`` steps in a
  one-process run over ``n`` devices. The axis type is ``Auto`` (MJX's scatters fail under the
  ``Explicit`` default of ``jax.make_mesh``).

  Args:
    axis_name: the mesh axis the env batch is split over.
    devices: the devices to use (default: ``jax.devices()``, all of them).
  """
  devices = sorted(devices or jax.devices(), key=lambda d: (d.process_index, d.id))
  return jax.sharding.Mesh(np.array(devices), (axis_name,),
                           axis_types=(jax.sharding.AxisType.Auto,))


def _is_typed_key(x: Any) -> bool:
  return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _global_array(x: Any, sharding: NamedSharding, local: bool) -> jax.Array:
  """One leaf onto the global mesh (typed PRNG keys through their raw data)."""
  if _is_typed_key(x):
    data = _global_array(jax.random.key_data(x), sharding, local)
    return jax.random.wrap_key_data(data, impl=jax.random.key_impl(x))
  if local:
    host = np.asarray(jax.device_get(x))
    return jax.make_array_from_process_local_data(sharding, host)
  host = np.asarray(jax.device_get(x))
  # Each addressable device receives exactly its slice of the full array: no transfer of the
  # other processes' envs, and correct for any device order.
  return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


def to_global(tree: Any, shardings: Any, local: bool = False) -> Any:
  """Places a pytree on a mesh of every process's devices, leaf by leaf per ``shardings`` (a
  ``NamedSharding`` per leaf). Every process calls this with the same kind of input:

  - ``local=False`` (default): the FULL tree, built identically by every process (e.g. a fresh
    train state from the same key; cheap). Each process keeps its devices' slices and a copy of
    the replicated leaves.
  - ``local=True``: a process-local tree whose sharded leaves hold only this process's part
    (replicated leaves still in full), assembled with ``jax.make_array_from_process_local_data``.

  Returns:
    The tree as global ``jax.Array`` s.
  """
  return jax.tree.map(lambda x, s: _global_array(x, s, local), tree, shardings)


def _to_host(x: Any) -> Any:
  if not isinstance(x, jax.Array):
    return np.asarray(x)
  if _is_typed_key(x):
    x = jax.random.key_data(x)
  if x.is_fully_addressable:
    return np.asarray(jax.device_get(x))
  if x.is_fully_replicated:  # metrics, params: every process holds the whole value
    return np.asarray(x.addressable_shards[0].data)
  return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def gather_to_host(tree: Any) -> Any:
  """A pytree of (possibly global) arrays as numpy, on every process.

  Replicated arrays (metrics, parameters) are read from a local copy, with no communication;
  arrays sharded across processes (the env batch) are all-gathered, which is a collective:
  call this on every process with the same tree.
  """
  return jax.tree.map(_to_host, tree)


def barrier(name: str) -> None:
  """Waits until every process gets here (nothing in a one-process run)."""
  if jax.process_count() > 1:
    multihost_utils.sync_global_devices(name)


def allgather_ints(value: int) -> np.ndarray:
  """``value`` from every process, in process order (a collective; ``[value]`` in one process)."""
  if jax.process_count() == 1:
    return np.array([value])
  return np.asarray(multihost_utils.process_allgather(np.int32(value))).reshape(-1)
