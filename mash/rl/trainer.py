"""The trainer: MAPPO (:mod:`mash.rl.mappo`) jitted and placed, in one of three variants.

:func:`make_trainer` returns one :class:`Trainer` whatever the variant:

- one seed on one device (the default);
- ``seeds`` independent seeds in one jitted ``vmap`` call on one device (seed ``i`` equals a
  one-seed run of ``config.seed + i``, :func:`seed_keys`);
- one seed with its env batch split over a ``mesh`` of devices (of one process or of several
  joined by :func:`mash.rl.distributed.initialize`) through ``jax.shard_map``: each device steps
  ``num_envs / mesh.size`` envs and draws its own random numbers, and the update is averaged over
  the mesh, so a run over ``n`` processes of one device each equals a one-process run over ``n``
  devices with the same config.

The host loop (:func:`mash.runs.loop.train`), checkpoint restores and resumes use only the
trainer's fields; nothing downstream asks which variant it has.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from mash.rl import distributed, mappo
from mash.rl import networks as nets
from mash.rl.config import TrainConfig, derived

# XLA options that halve CPU compile time at some run-time cost: for tests and smoke runs on CPU.
FAST_COMPILE_OPTIONS = {
    "xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True
}
AXIS = "devices"  # the mesh axis the env batch is split over


class Trainer(NamedTuple):
  """MAPPO ready to train: jitted, with its state placed on its device(s).

  Attributes:
    config: the training config.
    env: the environment.
    networks: actor/critic apply functions.
    mappo: the pure functions underneath (:class:`mash.rl.mappo.Mappo`), for nesting in other
      transformations and for timing parts alone.
    seeds: independent runs trained together (a leading state axis when > 1).
    devices: the devices the env batch is split over.
    key: the run's raw key(s) from ``config.seed``: ``[2]``, or ``[seeds, 2]``.
    init: ``(key=None, env_steps=None) -> TrainState``: a fresh state from ``key`` (default
      :attr:`key`; :func:`fold` makes others); ``env_steps`` is the envs' curriculum clock at
      their first episodes (``None``: a fresh run's). On a mesh, global arrays.
    state_shapes: ``() -> TrainState`` of ``jax.ShapeDtypeStruct`` without running ``init``: the
      checkpoint restore template (on a mesh with the global shardings, so that every process
      reads only its own shards).
    train_epoch: jitted ``state -> (state, metrics)`` (state donated); metrics
      ``[iterations_per_call]``, ``[seeds, iterations_per_call]`` when ``seeds > 1``.
    to_host: a pytree of the trainer's arrays as numpy (on a mesh a collective: every process
      calls it with the same tree).
  """

  config: TrainConfig
  env: mappo.MultiAgentEnv
  networks: nets.Networks
  mappo: mappo.Mappo
  seeds: int
  devices: int
  key: jax.Array
  init: Callable[..., mappo.TrainState]
  state_shapes: Callable[[], Any]
  train_epoch: Callable[[mappo.TrainState], tuple[mappo.TrainState, mappo.Metrics]]
  to_host: Callable[[Any], Any]


def seed_keys(seed: int, num_seeds: int) -> jax.Array:
  """``[num_seeds, 2]`` raw keys, seed ``i`` being ``PRNGKey(seed + i)`` (so seed ``i`` of a
  vmapped run equals a single run with ``TrainConfig.seed = seed + i``)."""
  return jnp.stack([jax.random.PRNGKey(seed + i) for i in range(num_seeds)])


def fold(trainer: Trainer, salt: int) -> jax.Array:
  """The trainer's key(s) with ``salt`` folded in (fresh env states for a resume from a
  checkpoint without them); ``salt`` 0 leaves them as they are."""
  if not salt:
    return trainer.key
  if trainer.seeds > 1:
    return jax.vmap(lambda k: jax.random.fold_in(k, salt))(trainer.key)
  return jax.random.fold_in(trainer.key, salt)


def make_trainer(config: TrainConfig, env: mappo.MultiAgentEnv, seeds: int = 1,
                 mesh: jax.sharding.Mesh | None = None,
                 compiler_options: Mapping[str, Any] | None = None) -> Trainer:
  """The :class:`Trainer` of ``config`` on ``env``: one seed on one device, ``seeds`` seeds
  vmapped on one device, or (with ``mesh``, one seed only) the env batch split over the mesh.

  Args:
    config: the training config (on a mesh ``num_envs`` is the global batch).
    env: the environment (every process of a mesh builds the same one).
    seeds: independent seeds trained in one call, from ``config.seed``.
    mesh: a 1-D mesh (:func:`mash.rl.distributed.global_mesh`) to split the env batch over.
    compiler_options: XLA options every jitted function is compiled with, e.g.
      :data:`FAST_COMPILE_OPTIONS` for tests on CPU.

  Raises:
    ValueError: several seeds on a mesh, or a batch that does not split into whole minibatches
      per device (:func:`mash.rl.config.derived`).
  """
  if mesh is not None and seeds != 1:
    raise ValueError(f"a mesh trains one seed; got seeds={seeds}")
  if mesh is not None:
    return _on_mesh(config, env, mesh, compiler_options)
  algo = mappo.make_mappo(config, env)
  if seeds > 1:
    return _many_seeds(algo, seeds, compiler_options)
  key = jax.random.PRNGKey(config.seed)
  init = jax.jit(algo.init, compiler_options=compiler_options)
  return Trainer(
      config=config, env=env, networks=algo.networks, mappo=algo, seeds=1, devices=1, key=key,
      init=lambda key_=None, env_steps=None: init(key if key_ is None else key_, env_steps),
      state_shapes=lambda: jax.eval_shape(algo.init, key), train_epoch=jax.jit(
          algo.train_epoch, donate_argnums=0,
          compiler_options=compiler_options), to_host=jax.device_get)


def _many_seeds(algo: mappo.Mappo, seeds: int,
                compiler_options: Mapping[str, Any] | None) -> Trainer:
  """``seeds`` seeds of ``algo`` in one vmapped call on one device."""
  keys = seed_keys(algo.config.seed, seeds)
  single_init = jax.jit(algo.init, compiler_options=compiler_options)

  def init(keys_: jax.Array | None = None, env_steps: jax.Array | int | None = None):
    # One single-seed init per key, stacked: reuses the single-seed program and makes seed i
    # bit-identical to a run started from keys[i].
    states = [single_init(k, env_steps) for k in (keys if keys_ is None else keys_)]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *states)

  epoch = jax.vmap(algo.train_epoch)
  return Trainer(
      config=algo.config, env=algo.env, networks=algo.networks, mappo=algo, seeds=seeds, devices=1,
      key=keys, init=init,
      state_shapes=lambda: jax.eval_shape(jax.vmap(algo.init, in_axes=(0, None)), keys, None),
      train_epoch=jax.jit(epoch, donate_argnums=0,
                          compiler_options=compiler_options), to_host=jax.device_get)


def state_partition_specs(axis_name: str = AXIS) -> mappo.TrainState:
  """``shard_map`` specs of a :class:`mash.rl.mappo.TrainState`: env batch and per-env episode
  sums split over ``axis_name``, everything else replicated."""
  batch = P(axis_name)
  return mappo.TrainState(
      params=P(), opt_state=P(), normalizer=P(), env_state=batch, episodes=mappo.EpisodeStats(
          running_return=batch, running_length=batch, last_return=P(), last_length=P(),
          running_paper_return=batch, last_paper_return=P()), rng=P(), iteration=P())


def state_shardings(mesh: jax.sharding.Mesh, state: Any, axis_name: str = AXIS) -> Any:
  """A ``NamedSharding`` per leaf of ``state`` per :func:`state_partition_specs`."""
  specs = state_partition_specs(axis_name)
  return jax.tree.map(lambda spec, sub: jax.tree.map(lambda _: NamedSharding(mesh, spec), sub),
                      specs, state, is_leaf=lambda x: isinstance(x, P))


def _on_mesh(config: TrainConfig, env: mappo.MultiAgentEnv, mesh: jax.sharding.Mesh,
             compiler_options: Mapping[str, Any] | None) -> Trainer:
  """One seed with its env batch split over ``mesh`` (every process calls this alike)."""
  derived(config, mesh.size)
  single = mappo.make_mappo(config, env)
  sharded = mappo.make_mappo(config, env, axis_name=AXIS)
  specs = state_partition_specs(AXIS)
  epoch = jax.shard_map(sharded.train_epoch, mesh=mesh, in_specs=(specs,), out_specs=(specs, P()),
                        check_vma=False)
  # Explicit output shardings: left to itself, jit returns zero-size leaves (MJX keeps some, e.g.
  # ``act`` [B, 0]) replicated rather than split, the next call sees a different input sharding
  # and compiles the whole epoch a second time.
  shardings = jax.tree.map(lambda spec: NamedSharding(mesh, spec), specs,
                           is_leaf=lambda x: isinstance(x, P))
  train_epoch = jax.jit(epoch, donate_argnums=0, compiler_options=compiler_options,
                        out_shardings=(shardings, NamedSharding(mesh, P())))
  key = jax.random.PRNGKey(config.seed)
  init_full = jax.jit(single.init, compiler_options=compiler_options)

  def init(key_: jax.Array | None = None, env_steps: jax.Array | int | None = None):
    # Every process builds the full state with the same key (cheap) and keeps its own slices.
    state = init_full(key if key_ is None else key_, env_steps)
    return distributed.to_global(state, state_shardings(mesh, state))

  def state_shapes():
    shapes = jax.eval_shape(single.init, key)
    return jax.tree.map(lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s), shapes,
                        state_shardings(mesh, shapes))

  return Trainer(config=config, env=env, networks=single.networks, mappo=sharded, seeds=1,
                 devices=mesh.size, key=key, init=init, state_shapes=state_shapes,
                 train_epoch=train_epoch, to_host=distributed.gather_to_host)
