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
single-agent PPO runs differ only in the env's agent partition. A step into a blown-up physics state
(NaN/inf) is masked out of GAE and the loss and counted in the per-iteration metric ``nan_resets``.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, NamedTuple, Protocol

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
from mash.config import MAX_LEARNING_RATE, MIN_LEARNING_RATE, TrainConfig, derived

Metrics = dict[str, jax.Array]

# XLA options that halve CPU compile time at some run-time cost: for tests and smoke runs on CPU.
FAST_COMPILE_OPTIONS = {'xla_backend_optimization_level': 0,
                        'xla_llvm_disable_expensive_passes': True}
ProgressFn = Callable[[int, Mapping[str, np.ndarray]], None]


class MultiAgentEnv(Protocol):
  """The environment contract the trainer relies on (the MJX env and :mod:`mash.toy_env` meet it).

  ``reset`` and ``step`` are unbatched (the trainer vmaps them) and return a Brax
  ``brax.envs.base.State`` with:

  - ``obs``: ``{group.name: [n_agents, obs_dim] for each group, 'critic': [critic_obs_size]}``;
  - ``reward``: ``[]`` shared reward; ``done``: ``[]`` 1.0 when the episode ended at this step
    (fall or time-out);
  - ``info['truncation']``: ``[]`` 1.0 when it ended by time-out only (the value is bootstrapped);
  - ``info['next_critic_obs']``: ``[critic_obs_size]`` critic obs of the state reached, before the
    automatic reset (equal to ``obs['critic']`` when not done);
  - ``info['nan_reset']`` (optional): ``[]`` 1.0 when the step blew up (NaN/inf state) and the env
    was reset; such a step must also be ``done`` and carry finite ``reward``/``obs``. The trainer
    masks it out of GAE and the loss (as it does any step whose reward or ``next_critic_obs`` is
    not finite) and logs the count as ``nan_resets``;
  - ``metrics``: ``{name: []}`` scalars (``reward/<term>`` ...), logged as per-iteration means.
  """

  agent_groups: tuple[AgentGroup, ...]
  action_size: int
  critic_obs_size: int

  def reset(self, key: jax.Array) -> Any:
    """A fresh episode. Envs with curricula may take a second argument, the slot's control-step
    count so far (the trainer passes it only when asked to: ``init(key, env_steps)``)."""
    ...

  def step(self, state: Any, action: jax.Array) -> Any:
    """``action``: ``[action_size]`` flat action (see :func:`mash.agents.assemble_action`)."""
    ...


@flax.struct.dataclass
class EpisodeStats:
  """Episode return/length bookkeeping (the env does not provide it).

  Attributes:
    running_return: ``[B]`` reward summed since each env's last reset.
    running_length: ``[B]`` steps since each env's last reset.
    last_return: ``[]`` mean return of the episodes completed in the last iteration that completed
      any (carried over otherwise; 0 before the first).
    last_length: ``[]`` the same for episode lengths.
    running_paper_return: ``[B]``, last_paper_return: ``[]``: the same for the env's
      ``metrics['paper_reward']``, the reward under the paper's weights whatever the curricula
      apply (the trained reward for an env without it), so curves of runs with different
      curricula compare.
  """

  running_return: jax.Array
  running_length: jax.Array
  last_return: jax.Array
  last_length: jax.Array
  running_paper_return: jax.Array
  last_paper_return: jax.Array


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
    nan_reset: ``[B]`` 1.0 where the step blew up (non-finite state, reward or critic obs): masked
      out of GAE and the loss.
  """

  obs: Mapping[str, jax.Array]
  actions: Mapping[str, jax.Array]
  log_probs: jax.Array
  reward: jax.Array
  done: jax.Array
  truncation: jax.Array
  next_critic_obs: jax.Array
  env_metrics: Mapping[str, jax.Array]
  nan_reset: jax.Array


class RolloutCarry(NamedTuple):
  """Loop state of the rollout scan.

  Attributes:
    env_state: batched env state.
    episode_return: ``[B]`` reward summed since each env's last reset.
    episode_length: ``[B]`` steps since each env's last reset.
    episode_paper_return: ``[B]`` paper-weight reward summed since each env's last reset.
    done_return: ``[]`` sum of the returns of episodes completed in this rollout (this device).
    done_length: ``[]`` sum of their lengths.
    done_paper_return: ``[]`` sum of their paper-weight returns.
    done_count: ``[]`` number of episodes completed.
  """

  env_state: Any
  episode_return: jax.Array
  episode_length: jax.Array
  episode_paper_return: jax.Array
  done_return: jax.Array
  done_length: jax.Array
  done_paper_return: jax.Array
  done_count: jax.Array


class OptimizerState(NamedTuple):
  """Loop state of the SGD scans: parameters and optax state."""

  params: nets.Params
  opt_state: optax.OptState


class Trainer(NamedTuple):
  """A configured trainer.

  Attributes:
    config: the training config.
    env: the environment (``agent_groups``, ``reset``, ``step``, ...).
    networks: actor/critic apply functions.
    optimizer: the optax transformation.
    axis_name: mesh axis the update is averaged over, or ``None``.
    compiler_options: XLA options every jitted function is compiled with (``None``: defaults).
    init_fn: ``(key, env_steps=None) -> TrainState`` (pure, unjitted: for nesting in other
      transformations).
    init: ``init_fn`` jitted.
    iteration: ``TrainState -> (TrainState, metrics)``: one training iteration (pure).
    update: ``(OptimizerState, normalizer, flat LossBatch [T*B, ...], key) -> (OptimizerState,
      metrics)``: the ``num_epochs x num_minibatches`` MAPPO steps of one iteration (pure; the
      benchmark times it alone).
    train_epoch_fn: ``TrainState -> (TrainState, metrics [iterations_per_call])`` (pure, unjitted:
      for ``vmap`` / ``shard_map``).
    train_epoch: ``train_epoch_fn`` jitted with the state donated.
  """

  config: TrainConfig
  env: MultiAgentEnv
  networks: nets.Networks
  optimizer: optax.GradientTransformation
  axis_name: str | None
  compiler_options: Mapping[str, Any] | None
  init_fn: Callable[..., TrainState]
  init: Callable[..., TrainState]
  iteration: Callable[[TrainState], tuple[TrainState, Metrics]]
  update: Callable[..., tuple[OptimizerState, Metrics]]
  train_epoch_fn: Callable[[TrainState], tuple[TrainState, Metrics]]
  train_epoch: Callable[[TrainState], tuple[TrainState, Metrics]]


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
  """Global-norm gradient clipping followed by Adam.

  Under ``learning_rate_schedule='adaptive_kl'`` or ``'linear'`` the rate lives in the optimizer
  state (``optax.inject_hyperparams``; read and set with ``optax.tree_utils.tree_get/tree_set``
  under the name ``learning_rate``), so it is checkpointed and resumed with it. The update runs on all
  parameters raveled into one vector (``optax.flatten``): the same math, but a handful of fused
  kernels instead of a few per parameter array, which shortens compilation.
  """
  if config.learning_rate_schedule == 'adaptive_kl':
    adam = optax.inject_hyperparams(optax.adam)(learning_rate=config.learning_rate)
  elif config.learning_rate_schedule == 'linear':
    adam = optax.inject_hyperparams(optax.adam)(learning_rate=linear_learning_rate(config))
  else:
    adam = optax.adam(config.learning_rate)
  return optax.flatten(optax.chain(optax.clip_by_global_norm(config.max_grad_norm), adam))


def linear_learning_rate(config: TrainConfig) -> optax.Schedule:
  """``learning_rate`` decaying linearly to 0 at the last minibatch step of ``num_iterations``
  (PureJaxRL's and CleanRL's ``anneal_lr``): ``step -> []``."""
  return optax.linear_schedule(config.learning_rate, 0.0, config.num_iterations *
                               config.num_epochs * config.num_minibatches)


def injected_learning_rate(opt_state: optax.OptState) -> jax.Array:
  """``[]`` the rate in the optimizer state under ``'adaptive_kl'`` or ``'linear'`` (for
  ``'linear'``, the last step's; the schedule's own step counter sits in the state under the
  same name, hence the filter)."""
  return optax.tree_utils.tree_get(opt_state, 'learning_rate',
                                   filtering=lambda _, value: hasattr(value, 'dtype'))


def adapt_learning_rate(learning_rate: jax.Array, kl: jax.Array,
                        desired_kl: float) -> jax.Array:
  """rsl_rl's adaptive rule: ``[] -> []``, the rate / 1.5 when ``kl > 2 desired_kl``, x 1.5 when
  ``0 < kl < desired_kl / 2``, else unchanged; clipped to [MIN_LEARNING_RATE, MAX_LEARNING_RATE]."""
  lower = jnp.maximum(learning_rate / 1.5, MIN_LEARNING_RATE)
  higher = jnp.minimum(learning_rate * 1.5, MAX_LEARNING_RATE)
  return jnp.where(kl > 2.0 * desired_kl, lower,
                   jnp.where((kl < 0.5 * desired_kl) & (kl > 0.0), higher, learning_rate))


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


def loss_gradients(params: nets.Params, normalizer: normalization.Normalizer | None,
                   batch: losses.LossBatch, networks: nets.Networks, config: TrainConfig,
                   axis_name: str | None = None) -> tuple[nets.Params, Metrics]:
  """Gradient of the MAPPO loss (:func:`mash.losses.mappo_loss`) on this device's part of a
  minibatch, and the loss metrics; with ``axis_name`` both are averaged over the devices, so
  equal parts on D devices give the gradient of the whole minibatch on one device.

  Returns:
    ``(grads, metrics)``: grads with the structure of ``params``; metrics as ``mappo_loss``'s.
  """
  grads, metrics = jax.grad(losses.mappo_loss, has_aux=True)(params, normalizer, batch, networks,
                                                             config, axis_name)
  if axis_name is not None:
    grads = jax.lax.pmean(grads, axis_name)
    metrics = jax.lax.pmean(metrics, axis_name)
  return grads, metrics


def _screen_blowups(state: Any) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Reward ``[B]``, ``next_critic_obs`` ``[B, ...]`` and the blow-up mask ``[B]`` of a batched step.

  A step is a blow-up when the env says so (``info['nan_reset']``) or when its reward or terminal
  critic observation is not finite; its reward and critic observation are zeroed so that no NaN
  reaches GAE (``0 * NaN`` is NaN).
  """
  reward, next_critic_obs = state.reward, state.info['next_critic_obs']
  flagged = state.info.get('nan_reset', jnp.zeros_like(reward)) > 0
  obs_finite = jnp.all(jnp.isfinite(next_critic_obs.reshape(reward.shape + (-1,))), axis=-1)
  blown = flagged | ~jnp.isfinite(reward) | ~obs_finite
  mask = blown.reshape(blown.shape + (1,) * (next_critic_obs.ndim - blown.ndim))
  return (jnp.where(blown, 0.0, reward), jnp.where(mask, 0.0, next_critic_obs),
          blown.astype(jnp.float32))


def make_train(config: TrainConfig, env: MultiAgentEnv, axis_name: str | None = None,
               compiler_options: Mapping[str, Any] | None = None) -> Trainer:
  """Builds the trainer for ``env``'s agent partition.

  Args:
    config: training config (sizes validated by :func:`mash.config.derived`).
    env: a :class:`MultiAgentEnv`.
    axis_name: when given, the functions must run inside ``shard_map`` over that mesh axis (the env
      batch split over devices) and average their updates over it.
    compiler_options: XLA compiler options for the jitted ``init`` / ``train_epoch``, e.g.
      :data:`FAST_COMPILE_OPTIONS` for tests on CPU. JAX accepts them on top-level jits only: to
      nest the trainer in another transformation use ``init_fn`` / ``train_epoch_fn``.

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

  def init(key: jax.Array, env_steps: jax.Array | int | None = None) -> TrainState:
    """Fresh parameters, optimizer and statistics, and ``num_envs`` reset environments; with
    ``env_steps`` (``[]``), their episodes start as if each env had run that many control steps
    (the curricula's clock, for a resume without saved env states)."""
    param_key, env_key, rng = jax.random.split(key, 3)
    params = networks.init(param_key)
    env_keys = jax.random.split(env_key, config.num_envs)
    if env_steps is None:
      env_state = batch_reset(env_keys)
    else:
      env_state = jax.vmap(env.reset, in_axes=(0, None))(env_keys, env_steps)
    zeros = jnp.zeros((config.num_envs,), jnp.float32)
    scalar = jnp.zeros((), jnp.float32)
    episodes = EpisodeStats(running_return=zeros, running_length=zeros, last_return=scalar,
                            last_length=scalar, running_paper_return=zeros,
                            last_paper_return=scalar)
    return TrainState(params=params, opt_state=optimizer.init(params),
                      normalizer=normalization.init_normalizer(obs_sizes), env_state=env_state,
                      episodes=episodes, rng=rng, iteration=jnp.zeros((), jnp.int32))

  def active_normalizer(normalizer: normalization.Normalizer) -> normalization.Normalizer | None:
    return normalizer if config.normalize_observations else None

  def rollout(params: nets.Params, normalizer: normalization.Normalizer | None, env_state: Any,
              episodes: EpisodeStats, key: jax.Array) -> tuple[RolloutCarry, Transition]:
    """``unroll_length`` steps of all envs: the final loop state and the stacked transitions
    ``[T, B, ...]``."""

    def step(carry: RolloutCarry, step_key: jax.Array) -> tuple[RolloutCarry, Transition]:
      obs = carry.env_state.obs
      dists = networks.policy_apply(params, normalizer, obs)
      actions = nets.sample_actions(step_key, dists)
      log_probs = nets.per_agent(
          groups, {g.name: nets.gaussian_log_prob(dists[g.name], actions[g.name]) for g in groups})
      next_state = batch_step(carry.env_state, assemble_action(groups, actions))
      done = next_state.done
      reward, next_critic_obs, nan_reset = _screen_blowups(next_state)
      paper = jnp.where(nan_reset > 0, 0.0, next_state.metrics.get('paper_reward', reward))
      ret = carry.episode_return + reward
      paper_ret = carry.episode_paper_return + paper
      length = carry.episode_length + 1.0
      carry = RolloutCarry(env_state=next_state, episode_return=ret * (1.0 - done),
                           episode_length=length * (1.0 - done),
                           episode_paper_return=paper_ret * (1.0 - done),
                           done_return=carry.done_return + jnp.sum(ret * done),
                           done_length=carry.done_length + jnp.sum(length * done),
                           done_paper_return=carry.done_paper_return + jnp.sum(paper_ret * done),
                           done_count=carry.done_count + jnp.sum(done))
      transition = Transition(
          obs=obs, actions=actions, log_probs=log_probs, reward=reward, done=done,
          truncation=next_state.info['truncation'], next_critic_obs=next_critic_obs,
          env_metrics=next_state.metrics, nan_reset=nan_reset)
      return carry, transition

    zero = jnp.zeros((), jnp.float32)
    carry = RolloutCarry(env_state=env_state, episode_return=episodes.running_return,
                         episode_length=episodes.running_length,
                         episode_paper_return=episodes.running_paper_return, done_return=zero,
                         done_length=zero, done_paper_return=zero, done_count=zero)
    return jax.lax.scan(step, carry, jax.random.split(key, config.unroll_length))

  def minibatch_step(opt: OptimizerState, batch: losses.LossBatch,
                     normalizer: normalization.Normalizer | None) -> tuple[OptimizerState, Metrics]:
    """One MAPPO gradient step (gradients averaged over devices when sharded)."""
    grads, metrics = loss_gradients(opt.params, normalizer, batch, networks, config, axis_name)
    opt_state = opt.opt_state
    if config.learning_rate_schedule == 'adaptive_kl':
      # The KL of the current policy from the rollout's on this minibatch, before the step (as
      # rsl_rl); averaged over devices above, so every device sets the same rate.
      learning_rate = adapt_learning_rate(
          injected_learning_rate(opt_state), metrics['approx_kl'],
          config.desired_kl)
      opt_state = optax.tree_utils.tree_set(opt_state, learning_rate=learning_rate)
      metrics = {**metrics, 'learning_rate': learning_rate}
    updates, opt_state = optimizer.update(grads, opt_state, opt.params)
    if config.learning_rate_schedule == 'linear':  # the rate this step used
      metrics = {**metrics, 'learning_rate': injected_learning_rate(opt_state)}
    elif config.learning_rate_schedule == 'fixed':
      metrics = {**metrics, 'learning_rate': jnp.asarray(config.learning_rate, jnp.float32)}
    return OptimizerState(optax.apply_updates(opt.params, updates), opt_state), metrics

  def sgd(opt: OptimizerState, normalizer: normalization.Normalizer | None,
          batch: losses.LossBatch, key: jax.Array) -> tuple[OptimizerState, Metrics]:
    """``num_epochs`` shuffled passes of ``num_minibatches`` steps over the flat batch; metrics
    averaged over all steps."""
    n = batch.advantages.shape[0]
    mb = n // config.num_minibatches

    def epoch(opt: OptimizerState, epoch_key: jax.Array) -> tuple[OptimizerState, Metrics]:
      perm = jnp.argsort(jax.random.bits(epoch_key, (n,)))  # one draw + one sort
      shuffled = jax.tree.map(
          lambda x: x[perm].reshape((config.num_minibatches, mb) + x.shape[1:]), batch)
      return jax.lax.scan(lambda o, b: minibatch_step(o, b, normalizer), opt, shuffled)

    opt, metrics = jax.lax.scan(epoch, opt, jax.random.split(key, config.num_epochs))
    return opt, jax.tree.map(jnp.mean, metrics)

  def flatten_time(x: jax.Array) -> jax.Array:
    """``[T, B, ...] -> [T*B, ...]``."""
    return x.reshape((-1,) + x.shape[2:])

  def iteration(state: TrainState) -> tuple[TrainState, Metrics]:
    """One training iteration: rollout, statistics update, GAE, MAPPO epochs."""
    rng, rollout_key, sgd_key = jax.random.split(state.rng, 3)
    rollout_key = _device_key(rollout_key, axis_name)
    sgd_key = _device_key(sgd_key, axis_name)

    ro, tr = rollout(state.params, active_normalizer(state.normalizer), state.env_state,
                     state.episodes, rollout_key)

    # The update sees observations through the statistics the rollout acted with, so the
    # probability ratios start at exactly 1; this rollout's statistics apply from the next one.
    normalizer = active_normalizer(state.normalizer)
    stats = state.normalizer
    if config.normalize_observations:
      stats = normalization.update_normalizer(stats, tr.obs, axis_name)

    values = networks.value_apply(state.params, normalizer, tr.obs['critic'])
    next_values = networks.value_apply(state.params, normalizer, tr.next_critic_obs)
    # Steps into a blown-up state: zero advantage (the episode counts as cut before them, not as a
    # fall) and weight 0 in the advantage statistics and the loss.
    valid = 1.0 - tr.nan_reset
    advantages, returns = losses.compute_gae(tr.reward, values, next_values, tr.done,
                                             tr.truncation, config.gamma, config.gae_lambda,
                                             valid=valid)
    batch = jax.tree.map(flatten_time, losses.LossBatch(
        obs=tr.obs, actions=tr.actions, log_probs=tr.log_probs, values=values,
        advantages=advantages, returns=returns, weights=valid))
    opt, loss_metrics = sgd(OptimizerState(state.params, state.opt_state), normalizer, batch,
                            sgd_key)
    params = opt.params

    done_count = _sum(ro.done_count, axis_name)
    any_done = done_count > 0
    denom = jnp.maximum(done_count, 1.0)
    episodes = EpisodeStats(
        running_return=ro.episode_return, running_length=ro.episode_length,
        last_return=jnp.where(any_done, _sum(ro.done_return, axis_name) / denom,
                              state.episodes.last_return),
        last_length=jnp.where(any_done, _sum(ro.done_length, axis_name) / denom,
                              state.episodes.last_length),
        running_paper_return=ro.episode_paper_return,
        last_paper_return=jnp.where(any_done, _sum(ro.done_paper_return, axis_name) / denom,
                                    state.episodes.last_paper_return))
    metrics = {
        'episode_reward': episodes.last_return,
        'episode_length': episodes.last_length,
        'paper_episode_reward': episodes.last_paper_return,
        'episodes_completed': done_count,
        'step_reward': _mean(tr.reward, axis_name),
        'done_rate': _mean(tr.done, axis_name),
        'nan_resets': _sum(tr.nan_reset, axis_name),
        'value_mean': _mean(values, axis_name),
        'action_std': nets.mean_action_std(params),
        **{k: _mean(v, axis_name) for k, v in tr.env_metrics.items()},
        **loss_metrics,
    }
    new_state = TrainState(params=params, opt_state=opt.opt_state, normalizer=stats,
                           env_state=ro.env_state, episodes=episodes, rng=rng,
                           iteration=state.iteration + 1)
    return new_state, metrics

  def train_epoch_fn(state: TrainState) -> tuple[TrainState, Metrics]:
    """``iterations_per_call`` iterations; metrics stacked to ``[iterations_per_call]``."""
    return jax.lax.scan(lambda s, _: iteration(s), state, None,
                        length=config.iterations_per_call)

  return Trainer(config=config, env=env, networks=networks, optimizer=optimizer,
                 axis_name=axis_name, compiler_options=compiler_options,
                 init_fn=init, init=jax.jit(init, compiler_options=compiler_options),
                 iteration=iteration, update=sgd,
                 train_epoch_fn=train_epoch_fn,
                 train_epoch=jax.jit(train_epoch_fn, donate_argnums=0,
                                     compiler_options=compiler_options))


def seed_keys(seed: int, num_seeds: int) -> jax.Array:
  """``[num_seeds, 2]`` raw keys, seed ``i`` being ``PRNGKey(seed + i)`` (so seed ``i`` of a
  vmapped run equals a single run with ``TrainConfig.seed = seed + i``)."""
  return jnp.stack([jax.random.PRNGKey(seed + i) for i in range(num_seeds)])


def make_seed_trainer(trainer: Trainer) -> Trainer:
  """The same trainer over a leading seed axis.

  ``init(keys [S, 2])`` stacks ``S`` single-seed states; ``train_epoch`` trains the ``S``
  independent runs in one jitted ``vmap`` call (metrics ``[S, iterations_per_call]``);
  ``iteration`` and ``update`` take and return arguments with a leading seed axis.
  """
  if trainer.axis_name is not None:
    raise ValueError('make_seed_trainer expects a trainer built without axis_name.')
  epoch_fn = jax.vmap(trainer.train_epoch_fn)

  def init(keys: jax.Array, env_steps: jax.Array | int | None = None) -> TrainState:
    if isinstance(keys, jax.core.Tracer):  # traced (eval_shape, an enclosing jit): plain vmap
      return jax.vmap(trainer.init_fn, in_axes=(0, None))(keys, env_steps)
    # One single-seed init per key, stacked: reuses the single-seed program (no extra compile)
    # and makes seed i bit-identical to a run started with trainer.init(keys[i]).
    states = [trainer.init(k, env_steps) for k in keys]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *states)

  return trainer._replace(init=init,
                          iteration=jax.vmap(trainer.iteration), update=jax.vmap(trainer.update),
                          train_epoch_fn=epoch_fn,
                          train_epoch=jax.jit(epoch_fn, donate_argnums=0,
                                              compiler_options=trainer.compiler_options))


def state_partition_specs(axis_name: str = 'devices') -> TrainState:
  """``shard_map`` specs of a :class:`TrainState`: env batch and per-env episode sums split over
  ``axis_name``, everything else replicated."""
  batch = P(axis_name)
  return TrainState(params=P(), opt_state=P(), normalizer=P(), env_state=batch,
                    episodes=EpisodeStats(running_return=batch, running_length=batch,
                                          last_return=P(), last_length=P(),
                                          running_paper_return=batch, last_paper_return=P()),
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
                             check_vma: bool = False) -> Callable[[TrainState], tuple[TrainState, Metrics]]:
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
  inner = make_train(trainer.config, trainer.env, axis_name=axis_name,
                     compiler_options=trainer.compiler_options)
  specs = state_partition_specs(axis_name)
  fn = jax.shard_map(inner.train_epoch_fn, mesh=mesh, in_specs=(specs,), out_specs=(specs, P()),
                     check_vma=check_vma)
  # Explicit output shardings: left to itself, jit returns zero-size leaves (MJX keeps some, e.g.
  # ``act`` [B, 0]) replicated rather than split, the next call sees a different input sharding and
  # compiles the whole epoch a second time.
  shardings = jax.tree.map(lambda spec: jax.sharding.NamedSharding(mesh, spec), specs,
                           is_leaf=lambda x: isinstance(x, P))
  return jax.jit(fn, donate_argnums=0, compiler_options=trainer.compiler_options,
                 out_shardings=(shardings, jax.sharding.NamedSharding(mesh, P())))


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
