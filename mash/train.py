"""The MAPPO trainer: one jitted ``lax.scan`` over training iterations, plus its host loop.

``make_train(config, env)`` returns a :class:`Trainer` of pure functions:

- ``init(key) -> TrainState``: parameters, Adam state, observation statistics, a batch of
  ``num_envs`` reset environments, episode bookkeeping, the rng and the iteration counter;
- ``train_epoch(state) -> (state, metrics)``: ``iterations_per_call`` training iterations in one
  jitted call (state donated), each = a rollout of ``unroll_length`` steps over all envs, a normalizer
  update, per-agent GAE, and ``num_epochs x num_minibatches`` MAPPO steps; ``metrics`` holds one
  value per iteration (``[iterations_per_call]``).

The same functions serve ``jit(vmap(...))`` over seeds (:func:`make_seed_trainer`) and ``shard_map``
over an env-batch mesh axis (:func:`make_sharded_train_epoch`): when the trainer is built with an
``axis_name``, gradients, observation statistics, advantage statistics, episode statistics and logged
metrics are averaged over that axis, and each device draws its own random numbers. The MASH and
single-agent PPO runs differ only in the env's agent partition.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import PartitionSpec as P

from mash import losses
from mash import networks as nets
from mash import normalization
from mash.agents import AgentGroup, assemble_action
from mash.config import TrainConfig, derived

Metrics = dict[str, jax.Array]
ProgressFn = Callable[[int, Mapping[str, np.ndarray]], None]


@flax.struct.dataclass
class EpisodeStats:
  """Episode return/length bookkeeping (the env does not provide it).

  Attributes:
    running_return: ``[B]`` reward summed since each env's last reset.
    running_length: ``[B]`` steps since each env's last reset.
    last_return: ``[]`` mean return of the episodes completed in the last iteration that completed
      any (carried over otherwise; 0 before the first).
    last_length: ``[]`` the same for episode lengths.
  """

  running_return: jax.Array
  running_length: jax.Array
  last_return: jax.Array
  last_length: jax.Array


@flax.struct.dataclass
class TrainState:
  """Everything one training run carries between iterations (and checkpoints).

  Attributes:
    params: ``{'actors': {group: variables}, 'critic': variables}``.
    opt_state: optax state (gradient clip + Adam).
    normalizer: ``{group: RunningStats, 'critic': RunningStats}``.
    env_state: Brax env ``State`` batched over ``num_envs``.
    episodes: episode bookkeeping.
    rng: ``uint32[2]`` key (raw, so it can be checkpointed).
    iteration: ``[]`` int32 training iterations done.
  """

  params: nets.Params
  opt_state: optax.OptState
  normalizer: normalization.Normalizer
  env_state: Any
  episodes: EpisodeStats
  rng: jax.Array
  iteration: jax.Array


class Transition(NamedTuple):
  """One rollout step of all envs (stacked to ``[T, B, ...]`` by the scan).

  Attributes:
    obs: ``{group: [B, n_agents, obs_dim], 'critic': [B, C]}`` observations acted on.
    actions: ``{group: [B, n_agents, act_dim]}`` sampled actions.
    log_probs: ``[B, N]`` behaviour log-probs per agent.
    reward: ``[B]`` shared reward.
    done: ``[B]`` episode ended at this step.
    truncation: ``[B]`` ended by time-out.
    next_critic_obs: ``[B, C]`` critic obs of the state reached (terminal one when done).
    env_metrics: ``{name: [B]}`` the env's per-step metrics (``reward/<term>`` ...).
  """

  obs: Mapping[str, jax.Array]
  actions: Mapping[str, jax.Array]
  log_probs: jax.Array
  reward: jax.Array
  done: jax.Array
  truncation: jax.Array
  next_critic_obs: jax.Array
  env_metrics: Mapping[str, jax.Array]


class Trainer(NamedTuple):
  """A configured trainer.

  Attributes:
    config: the training config.
    env: the environment (``agent_groups``, ``reset``, ``step``, ...).
    networks: actor/critic apply functions.
    optimizer: the optax transformation.
    axis_name: mesh axis the update is averaged over, or ``None``.
    init: ``key -> TrainState`` (jitted).
    iteration: ``TrainState -> (TrainState, metrics)``: one training iteration (pure).
    train_epoch_fn: ``TrainState -> (TrainState, metrics [iterations_per_call])`` (pure, unjitted:
      for ``vmap`` / ``shard_map``).
    train_epoch: ``train_epoch_fn`` jitted with the state donated.
  """

  config: TrainConfig
  env: Any
  networks: nets.Networks
  optimizer: optax.GradientTransformation
  axis_name: str | None
  init: Callable[[jax.Array], TrainState]
  iteration: Callable[[TrainState], tuple[TrainState, Metrics]]
  train_epoch_fn: Callable[[TrainState], tuple[TrainState, Metrics]]
  train_epoch: Callable[[TrainState], tuple[TrainState, Metrics]]


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
  """Global-norm gradient clipping followed by Adam at a fixed learning rate."""
  return optax.chain(optax.clip_by_global_norm(config.max_grad_norm),
                     optax.adam(config.learning_rate))


def _obs_sizes(groups: tuple[AgentGroup, ...], critic_obs_size: int) -> dict[str, int]:
  return {**{g.name: g.obs_dim for g in groups}, 'critic': critic_obs_size}


def _device_key(key: jax.Array, axis_name: str | None) -> jax.Array:
  """A per-device key: ``key`` folded with the device index (0 without a mesh axis), so a
  one-device mesh reproduces the unsharded run exactly."""
  index = 0 if axis_name is None else jax.lax.axis_index(axis_name)
  return jax.random.fold_in(key, index)


def _mean(x: jax.Array, axis_name: str | None) -> jax.Array:
  m = jnp.mean(x)
  return m if axis_name is None else jax.lax.pmean(m, axis_name)


def _sum(x: jax.Array, axis_name: str | None) -> jax.Array:
  s = jnp.sum(x)
  return s if axis_name is None else jax.lax.psum(s, axis_name)


def make_train(config: TrainConfig, env: Any, axis_name: str | None = None) -> Trainer:
  """Builds the trainer for ``env``'s agent partition.

  Args:
    config: training config (sizes validated by :func:`mash.config.derived`).
    env: an env with ``agent_groups``, ``critic_obs_size``, unbatched ``reset(key)`` and
      ``step(state, action)``; see the module docstring of :mod:`mash.toy_env` for the contract.
    axis_name: when given, the functions must run inside ``shard_map`` over that mesh axis (the env
      batch split over devices) and average their updates over it.

  Returns:
    The :class:`Trainer`.
  """
  derived(config)
  groups = tuple(env.agent_groups)
  networks = nets.make_networks(groups, env.critic_obs_size, config)
  optimizer = make_optimizer(config)
  obs_sizes = _obs_sizes(groups, env.critic_obs_size)
  batch_reset = jax.vmap(env.reset)
  batch_step = jax.vmap(env.step)

  def init(key: jax.Array) -> TrainState:
    """Fresh parameters, optimizer and statistics, and ``num_envs`` reset environments."""
    param_key, env_key, rng = jax.random.split(key, 3)
    params = networks.init(param_key)
    env_state = batch_reset(jax.random.split(env_key, config.num_envs))
    zeros = jnp.zeros((config.num_envs,), jnp.float32)
    episodes = EpisodeStats(running_return=zeros, running_length=zeros,
                            last_return=jnp.zeros((), jnp.float32),
                            last_length=jnp.zeros((), jnp.float32))
    return TrainState(params=params, opt_state=optimizer.init(params),
                      normalizer=normalization.init_normalizer(obs_sizes), env_state=env_state,
                      episodes=episodes, rng=rng, iteration=jnp.zeros((), jnp.int32))

  def active_normalizer(normalizer: normalization.Normalizer) -> normalization.Normalizer | None:
    return normalizer if config.normalize_observations else None

  def rollout(params: nets.Params, normalizer: normalization.Normalizer | None, env_state: Any,
              episodes: EpisodeStats, key: jax.Array):
    """``unroll_length`` steps of all envs; returns the new env state, episode stats, the
    stacked transitions ``[T, B, ...]`` and this device's completed-episode sums."""

    def step(carry, step_key):
      env_state, ret, length, done_ret, done_len, done_count = carry
      obs = env_state.obs
      dists = networks.policy_apply(params, normalizer, obs)
      actions = nets.sample_actions(step_key, dists)
      log_probs = nets.per_agent(
          groups, {g.name: nets.gaussian_log_prob(dists[g.name], actions[g.name]) for g in groups})
      next_state = batch_step(env_state, assemble_action(groups, actions))
      done = next_state.done
      ret = ret + next_state.reward
      length = length + 1.0
      carry = (next_state, ret * (1.0 - done), length * (1.0 - done),
               done_ret + jnp.sum(ret * done), done_len + jnp.sum(length * done),
               done_count + jnp.sum(done))
      transition = Transition(
          obs=obs, actions=actions, log_probs=log_probs, reward=next_state.reward, done=done,
          truncation=next_state.info['truncation'],
          next_critic_obs=next_state.info['next_critic_obs'], env_metrics=next_state.metrics)
      return carry, transition

    zero = jnp.zeros((), jnp.float32)
    carry = (env_state, episodes.running_return, episodes.running_length, zero, zero, zero)
    carry, transitions = jax.lax.scan(step, carry,
                                      jax.random.split(key, config.unroll_length))
    env_state, ret, length, done_ret, done_len, done_count = carry
    return env_state, ret, length, (done_ret, done_len, done_count), transitions

  def minibatch_step(carry, batch: losses.LossBatch, normalizer):
    params, opt_state = carry
    grad_fn = jax.grad(losses.mappo_loss, has_aux=True)
    grads, metrics = grad_fn(params, normalizer, batch, networks, config, axis_name)
    if axis_name is not None:
      grads = jax.lax.pmean(grads, axis_name)
      metrics = jax.lax.pmean(metrics, axis_name)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return (optax.apply_updates(params, updates), opt_state), metrics

  def sgd(params, opt_state, normalizer, batch: losses.LossBatch, key: jax.Array):
    """``num_epochs`` shuffled passes of ``num_minibatches`` steps over the flat batch."""
    n = batch.advantages.shape[0]
    mb = n // config.num_minibatches

    def epoch(carry, epoch_key):
      perm = jax.random.permutation(epoch_key, n)
      shuffled = jax.tree.map(
          lambda x: x[perm].reshape((config.num_minibatches, mb) + x.shape[1:]), batch)
      return jax.lax.scan(lambda c, b: minibatch_step(c, b, normalizer), carry, shuffled)

    (params, opt_state), metrics = jax.lax.scan(epoch, (params, opt_state),
                                                jax.random.split(key, config.num_epochs))
    return params, opt_state, jax.tree.map(jnp.mean, metrics)

  def iteration(state: TrainState) -> tuple[TrainState, Metrics]:
    """One training iteration: rollout, statistics update, GAE, MAPPO epochs."""
    rng, rollout_key, sgd_key = jax.random.split(state.rng, 3)
    rollout_key = _device_key(rollout_key, axis_name)
    sgd_key = _device_key(sgd_key, axis_name)

    env_state, ret, length, (done_ret, done_len, done_count), tr = rollout(
        state.params, active_normalizer(state.normalizer), state.env_state, state.episodes,
        rollout_key)

    stats = state.normalizer
    if config.normalize_observations:
      stats = normalization.update_normalizer(stats, tr.obs, axis_name)
    normalizer = active_normalizer(stats)

    values = networks.value_apply(state.params, normalizer, tr.obs['critic'])
    next_values = networks.value_apply(state.params, normalizer, tr.next_critic_obs)
    advantages, returns = losses.compute_gae(tr.reward, values, next_values, tr.done,
                                             tr.truncation, config.gamma, config.gae_lambda)
    flat = lambda x: x.reshape((-1,) + x.shape[2:])
    batch = losses.LossBatch(obs=jax.tree.map(flat, tr.obs),
                             actions=jax.tree.map(flat, tr.actions),
                             log_probs=flat(tr.log_probs), values=flat(values),
                             advantages=flat(advantages), returns=flat(returns))
    params, opt_state, loss_metrics = sgd(state.params, state.opt_state, normalizer, batch,
                                          sgd_key)

    done_count = _sum(done_count, axis_name)
    any_done = done_count > 0
    denom = jnp.maximum(done_count, 1.0)
    episodes = EpisodeStats(
        running_return=ret, running_length=length,
        last_return=jnp.where(any_done, _sum(done_ret, axis_name) / denom,
                              state.episodes.last_return),
        last_length=jnp.where(any_done, _sum(done_len, axis_name) / denom,
                              state.episodes.last_length))
    metrics = {
        'episode_reward': episodes.last_return,
        'episode_length': episodes.last_length,
        'episodes_completed': done_count,
        'step_reward': _mean(tr.reward, axis_name),
        'done_rate': _mean(tr.done, axis_name),
        'value_mean': _mean(values, axis_name),
        'action_std': nets.mean_action_std(params),
        **{k: _mean(v, axis_name) for k, v in tr.env_metrics.items()},
        **loss_metrics,
    }
    new_state = TrainState(params=params, opt_state=opt_state, normalizer=stats,
                           env_state=env_state, episodes=episodes, rng=rng,
                           iteration=state.iteration + 1)
    return new_state, metrics

  def train_epoch_fn(state: TrainState) -> tuple[TrainState, Metrics]:
    """``iterations_per_call`` iterations; metrics stacked to ``[iterations_per_call]``."""
    return jax.lax.scan(lambda s, _: iteration(s), state, None,
                        length=config.iterations_per_call)

  return Trainer(config=config, env=env, networks=networks, optimizer=optimizer,
                 axis_name=axis_name, init=jax.jit(init), iteration=iteration,
                 train_epoch_fn=train_epoch_fn,
                 train_epoch=jax.jit(train_epoch_fn, donate_argnums=0))


def seed_keys(seed: int, num_seeds: int) -> jax.Array:
  """``[num_seeds, 2]`` raw keys, seed ``i`` being ``PRNGKey(seed + i)`` (so seed ``i`` of a
  vmapped run equals a single run with ``TrainConfig.seed = seed + i``)."""
  return jnp.stack([jax.random.PRNGKey(seed + i) for i in range(num_seeds)])


def make_seed_trainer(trainer: Trainer) -> Trainer:
  """The same trainer over a leading seed axis: ``init(keys [S, 2])`` and ``train_epoch`` train
  ``S`` independent runs in one jitted call (metrics ``[S, iterations_per_call]``)."""
  if trainer.axis_name is not None:
    raise ValueError('make_seed_trainer expects a trainer built without axis_name.')
  epoch_fn = jax.vmap(trainer.train_epoch_fn)
  return trainer._replace(init=jax.jit(jax.vmap(trainer.init)),
                          iteration=jax.vmap(trainer.iteration), train_epoch_fn=epoch_fn,
                          train_epoch=jax.jit(epoch_fn, donate_argnums=0))


def state_partition_specs(axis_name: str = 'devices') -> TrainState:
  """``shard_map`` specs of a :class:`TrainState`: env batch and per-env episode sums split over
  ``axis_name``, everything else replicated."""
  batch = P(axis_name)
  return TrainState(params=P(), opt_state=P(), normalizer=P(), env_state=batch,
                    episodes=EpisodeStats(running_return=batch, running_length=batch,
                                          last_return=P(), last_length=P()),
                    rng=P(), iteration=P())


def shard_train_state(state: TrainState, mesh: jax.sharding.Mesh,
                      axis_name: str = 'devices') -> TrainState:
  """Places an (unsharded) train state on ``mesh`` according to :func:`state_partition_specs`."""
  specs = state_partition_specs(axis_name)
  shardings = jax.tree.map(lambda spec, sub: jax.tree.map(
      lambda _: jax.sharding.NamedSharding(mesh, spec), sub), specs, state,
                           is_leaf=lambda x: isinstance(x, P))
  return jax.device_put(state, shardings)


def make_sharded_train_epoch(trainer: Trainer, mesh: jax.sharding.Mesh,
                             axis_name: str = 'devices',
                             check_vma: bool = True) -> Callable[[TrainState], tuple[TrainState, Metrics]]:
  """``train_epoch`` with the env batch split over ``mesh``'s ``axis_name`` via ``jax.shard_map``.

  Each device steps ``num_envs / n_devices`` envs and draws its own random numbers; gradients,
  normalizer statistics, advantage statistics and metrics are averaged over the axis, so the
  parameters stay replicated. Make the mesh with ``axis_types=(jax.sharding.AxisType.Auto,)``;
  place the state with :func:`shard_train_state`.

  Args:
    trainer: a trainer from :func:`make_train` (its config and env are reused).
    mesh: a 1-D device mesh.
    axis_name: the mesh axis to split the env batch over.
    check_vma: let ``shard_map`` verify that replicated outputs are the same on every device.

  Returns:
    The jitted ``state -> (state, metrics)`` (state donated).

  Raises:
    ValueError: the env batch does not split evenly into whole minibatches per device.
  """
  derived(trainer.config, mesh.shape[axis_name])
  inner = make_train(trainer.config, trainer.env, axis_name=axis_name)
  specs = state_partition_specs(axis_name)
  fn = jax.shard_map(inner.train_epoch_fn, mesh=mesh, in_specs=(specs,), out_specs=(specs, P()),
                     check_vma=check_vma)
  return jax.jit(fn, donate_argnums=0)


def run(trainer: Trainer, state: TrainState, num_calls: int,
        progress_fn: ProgressFn | None = None,
        train_epoch: Callable[[TrainState], tuple[TrainState, Metrics]] | None = None
        ) -> TrainState:
  """Host loop: ``num_calls`` jitted calls, ``progress_fn(iteration, metrics)`` after each.

  Args:
    trainer: the trainer.
    state: the initial state (donated to the first call: do not reuse it).
    num_calls: jitted calls to make.
    progress_fn: called with the iteration count reached and the call's metrics as numpy arrays
      (``[iterations_per_call]``, or ``[S, iterations_per_call]`` for seed trainers).
    train_epoch: overrides ``trainer.train_epoch`` (e.g. the sharded one).

  Returns:
    The final state.
  """
  epoch = train_epoch or trainer.train_epoch
  for _ in range(num_calls):
    state, metrics = epoch(state)
    if progress_fn is not None:
      metrics = jax.device_get(metrics)
      iteration = int(np.asarray(jax.device_get(state.iteration)).reshape(-1)[0])
      progress_fn(iteration, metrics)
  return state
