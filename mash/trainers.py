"""The one trainer interface the host loop (:func:`mash.runs.train`) drives.

A run trains in one of three ways, and each is wrapped here, once, into a :class:`RunTrainer`:

- one seed on one device (:func:`one_seed`, over :func:`mash.train.make_train`);
- several seeds vmapped in one jitted call on one device (:func:`many_seeds`, over
  :func:`mash.train.make_seed_trainer`);
- one seed with its env batch split over a mesh of every device of every process
  (:func:`on_mesh`, over :func:`mash.distributed.make_distributed_trainer`).

The host loop, checkpoint restores and resumes ask a :class:`RunTrainer` for a fresh state, a
restore template, an epoch and host copies of its arrays; nothing downstream asks which kind it
has. :func:`build` picks the kind from a config and the devices there are.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax

from mash import distributed
from mash import experiment
from mash import train as train_lib


class RunTrainer(NamedTuple):
  """A trainer as the host loop sees it.

  Attributes:
    init: ``(salt=0, env_steps=None) -> TrainState``: a fresh state from the run's seed(s); a
      non-zero ``salt`` is folded into every key (fresh env states for a resume from a checkpoint
      without them); ``env_steps`` is the envs' curriculum clock at their first episodes
      (``None``: a fresh run's).
    state_shapes: ``() -> TrainState`` of ``jax.ShapeDtypeStruct``, without running ``init``: the
      checkpoint restore template (on a mesh with the global shardings, so that every process
      reads only its own shards).
    train_epoch: jitted ``state -> (state, metrics)`` (state donated); metrics
      ``[iterations_per_call]``, ``[seeds, iterations_per_call]`` when ``seeds > 1``.
    to_host: a pytree of the trainer's arrays as numpy (on a mesh a collective: every process
      calls it with the same tree).
    seeds: the independent runs trained together (a leading state axis when > 1).
    devices: the devices the env batch is split over.
    trainer: the single-seed :class:`mash.train.Trainer` underneath (env, networks, config).
  """

  init: Callable[..., train_lib.TrainState]
  state_shapes: Callable[[], Any]
  train_epoch: Callable[[train_lib.TrainState], tuple[train_lib.TrainState, train_lib.Metrics]]
  to_host: Callable[[Any], Any]
  seeds: int
  devices: int
  trainer: train_lib.Trainer


def _fold(key: jax.Array, salt: int) -> jax.Array:
  return jax.random.fold_in(key, salt) if salt else key


def one_seed(trainer: train_lib.Trainer, seed: int) -> RunTrainer:
  """Seed ``seed`` of ``trainer`` on one device."""
  key = jax.random.PRNGKey(seed)
  return RunTrainer(
      init=lambda salt=0, env_steps=None: trainer.init(_fold(key, salt), env_steps),
      state_shapes=lambda: jax.eval_shape(trainer.init, key),
      train_epoch=trainer.train_epoch, to_host=jax.device_get, seeds=1, devices=1,
      trainer=trainer)


def many_seeds(trainer: train_lib.Trainer, seed: int, seeds: int) -> RunTrainer:
  """Seeds ``seed .. seed + seeds - 1`` of ``trainer`` in one vmapped call on one device (seed
  ``i`` equals a one-seed run with ``seed + i``: :func:`mash.train.seed_keys`)."""
  vmapped = train_lib.make_seed_trainer(trainer)
  keys = train_lib.seed_keys(seed, seeds)
  return RunTrainer(
      init=lambda salt=0, env_steps=None: vmapped.init(
          jax.vmap(lambda k: _fold(k, salt))(keys), env_steps),
      state_shapes=lambda: jax.eval_shape(vmapped.init, keys),
      train_epoch=vmapped.train_epoch, to_host=jax.device_get, seeds=seeds, devices=1,
      trainer=trainer)


def on_mesh(trainer: distributed.DistributedTrainer, seed: int) -> RunTrainer:
  """Seed ``seed`` of a :class:`mash.distributed.DistributedTrainer`, its env batch split over
  its mesh."""
  key = jax.random.PRNGKey(seed)
  return RunTrainer(
      init=lambda salt=0, env_steps=None: trainer.init(_fold(key, salt), env_steps),
      state_shapes=lambda: distributed.global_state_shapes(trainer.trainer, trainer.mesh, key),
      train_epoch=trainer.train_epoch, to_host=distributed.gather_to_host, seeds=1,
      devices=trainer.mesh.size, trainer=trainer.trainer)


def uses_mesh(cfg: experiment.ExperimentConfig) -> bool:
  """Whether :func:`build` trains ``cfg`` on the global mesh: a one-seed run where there are
  several devices (several seeds train on one device)."""
  return jax.device_count() > 1 and cfg.seeds == 1


def build(cfg: experiment.ExperimentConfig) -> RunTrainer:
  """The :class:`RunTrainer` of a config: on the global mesh (:func:`mash.distributed.global_mesh`)
  when :func:`uses_mesh`, else on one device, seed-vmapped when ``cfg.seeds > 1``."""
  env = experiment.make_env(cfg)
  if uses_mesh(cfg):
    mesh = distributed.global_mesh()
    return on_mesh(distributed.make_distributed_trainer(cfg.train, env, mesh), cfg.train.seed)
  trainer = train_lib.make_train(cfg.train, env)
  if cfg.seeds > 1:
    return many_seeds(trainer, cfg.train.seed, cfg.seeds)
  return one_seed(trainer, cfg.train.seed)
