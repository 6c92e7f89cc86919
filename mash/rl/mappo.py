"""MAPPO as pure functions: the rollout, GAE and the clipped-surrogate epochs of one iteration.

``make_mappo(config, env)`` returns a :class:`Mappo` of pure, unjitted functions:

- ``init(key, env_steps=None) -> TrainState``: parameters, Adam state, observation statistics, a
  batch of ``num_envs`` reset environments, episode bookkeeping, the rng and the iteration counter;
- ``iteration(state) -> (state, metrics)``: a rollout of ``unroll_length`` steps over all envs, a
  normalizer update, per-agent GAE, and ``num_epochs x num_minibatches`` MAPPO steps;
- ``train_epoch(state) -> (state, metrics)``: ``iterations_per_call`` iterations in one
  ``lax.scan``, ``metrics`` one value per iteration (``[iterations_per_call]``).

Nothing here is jitted or placed on devices: :mod:`mash.rl.trainer` does that, for one seed, many
seeds (``vmap``) or an env batch split over a mesh (``shard_map``). When built with an
``axis_name``, gradients, observation statistics, advantage statistics, episode statistics and
logged metrics are averaged over that axis, and each device draws its own random numbers. The
MASH and single-agent PPO runs differ only in the env's agent partition. A step into a blown-up
physics state (NaN/inf) is masked out of GAE and the loss and counted in the per-iteration
metric ``nan_resets``.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, NamedTuple, Protocol

import flax.struct
import jax
import jax.numpy as jnp
import optax

from mash.rl import losses, normalization
from mash.rl import networks as nets
from mash.rl.config import MAX_LEARNING_RATE, MIN_LEARNING_RATE, TrainConfig, derived
from mash.sim.agents import AgentGroup, assemble_action

Metrics = dict[str, jax.Array]


class MultiAgentEnv(Protocol):
  """The environment contract the trainer relies on (the MJX env and :mod:`toy_env` meet it).

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
    """``action``: ``[action_size]`` flat action (see :func:`mash.sim.agents.assemble_action`)."""
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


class Mappo(NamedTuple):
  """MAPPO for one env and config, as pure functions (nothing jitted: :mod:`mash.rl.trainer`).

  Attributes:
    config: the training config.
    env: the environment (``agent_groups``, ``reset``, ``step``, ...).
    networks: actor/critic apply functions.
    optimizer: the optax transformation.
    axis_name: mesh axis the update is averaged over, or ``None``.
    init: ``(key, env_steps=None) -> TrainState``.
    iteration: ``TrainState -> (TrainState, metrics)``: one training iteration.
    update: ``(OptimizerState, normalizer, flat LossBatch [T*B, ...], key) -> (OptimizerState,
      metrics)``: the ``num_epochs x num_minibatches`` MAPPO steps of one iteration (the
      benchmark times it alone).
    train_epoch: ``TrainState -> (TrainState, metrics [iterations_per_call])``.
  """

  config: TrainConfig
  env: MultiAgentEnv
  networks: nets.Networks
  optimizer: optax.GradientTransformation
  axis_name: str | None
  init: Callable[..., TrainState]
  iteration: Callable[[TrainState], tuple[TrainState, Metrics]]
  update: Callable[..., tuple[OptimizerState, Metrics]]
  train_epoch: Callable[[TrainState], tuple[TrainState, Metrics]]


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
  """Global-norm gradient clipping followed by Adam.

  Under ``learning_rate_schedule='adaptive_kl'`` or ``'linear'`` the rate lives in the optimizer
  state (``optax.inject_hyperparams``; read and set with ``optax.tree_utils.tree_get/tree_set``
  under the name ``learning_rate``), so it is checkpointed and resumed with it. The update runs on
  all parameters raveled into one vector (``optax.flatten``): the same math, but a handful of fused
  kernels instead of a few per parameter array, which shortens compilation.
  """
  if config.learning_rate_schedule == "adaptive_kl":
    adam = optax.inject_hyperparams(optax.adam)(learning_rate=config.learning_rate)
  elif config.learning_rate_schedule == "linear":
    adam = optax.inject_hyperparams(optax.adam)(learning_rate=linear_learning_rate(config))
  else:
    adam = optax.adam(config.learning_rate)
  return optax.flatten(optax.chain(optax.clip_by_global_norm(config.max_grad_norm), adam))


def linear_learning_rate(config: TrainConfig) -> optax.Schedule:
  """``learning_rate`` decaying linearly to 0 at the last minibatch step of ``num_iterations``
  (PureJaxRL's and CleanRL's ``anneal_lr``): ``step -> []``."""
  return optax.linear_schedule(config.learning_rate, 0.0,
                               config.num_iterations * config.num_epochs * config.num_minibatches)


def injected_learning_rate(opt_state: optax.OptState) -> jax.Array:
  """``[]`` the rate in the optimizer state under ``'adaptive_kl'`` or ``'linear'`` (for
  ``'linear'``, the last step's; the schedule's own step counter sits in the state under the
  same name, hence the filter)."""
  return optax.tree_utils.tree_get(opt_state, "learning_rate",
                                   filtering=lambda _, value: hasattr(value, "dtype"))


def adapt_learning_rate(learning_rate: jax.Array, kl: jax.Array, desired_kl: float) -> jax.Array:
  """rsl_rl's adaptive rule: ``[] -> []``, the rate / 1.5 when ``kl > 2 desired_kl``, x 1.5 when
  ``0 < kl < desired_kl / 2``, else unchanged; clipped to [MIN_LEARNING_RATE, MAX_LEARNING_RATE]."""
  lower = jnp.maximum(learning_rate / 1.5, MIN_LEARNING_RATE)
  higher = jnp.minimum(learning_rate * 1.5, MAX_LEARNING_RATE)
  return jnp.where(kl > 2.0 * desired_kl, lower,
                   jnp.where((kl < 0.5 * desired_kl) & (kl > 0.0), higher, learning_rate))


def _obs_sizes(groups: tuple[AgentGroup, ...], critic_obs_size: int) -> dict[str, int]:
  return {**{g.name: g.obs_dim for g in groups}, "critic": critic_obs_size}


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
  """Gradient of the MAPPO loss (:func:`mash.rl.losses.mappo_loss`) on this device's part of a
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
  """Reward ``[B]``, ``next_critic_obs`` ``[B, ...]`` and the blow-up mask ``[B]`` of a batched
  step.

  A step is a blow-up when the env says so (``info['nan_reset']``) or when its reward or terminal
  critic observation is not finite; its reward and critic observation are zeroed so that no NaN
  reaches GAE (``0 * NaN`` is NaN).
  """
  reward, next_critic_obs = state.reward, state.info["next_critic_obs"]
  flagged = state.info.get("nan_reset", jnp.zeros_like(reward)) > 0
  obs_finite = jnp.all(jnp.isfinite(next_critic_obs.reshape(reward.shape + (-1,))), axis=-1)
  blown = flagged | ~jnp.isfinite(reward) | ~obs_finite
  mask = blown.reshape(blown.shape + (1,) * (next_critic_obs.ndim - blown.ndim))
  return (jnp.where(blown, 0.0, reward), jnp.where(mask, 0.0, next_critic_obs),
          blown.astype(jnp.float32))


def _make_init(config: TrainConfig, env: MultiAgentEnv, networks: nets.Networks,
               optimizer: optax.GradientTransformation) -> Callable[..., TrainState]:
  obs_sizes = _obs_sizes(tuple(env.agent_groups), env.critic_obs_size)
  batch_reset = jax.vmap(env.reset)

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

  return init


def _make_rollout(config: TrainConfig, env: MultiAgentEnv,
                  networks: nets.Networks) -> Callable[..., tuple[RolloutCarry, Transition]]:
  groups = tuple(env.agent_groups)
  batch_step = jax.vmap(env.step)

  def step(params: nets.Params, normalizer: normalization.Normalizer | None, carry: RolloutCarry,
           step_key: jax.Array) -> tuple[RolloutCarry, Transition]:
    obs = carry.env_state.obs
    dists = networks.policy_apply(params, normalizer, obs)
    actions = nets.sample_actions(step_key, dists)
    log_probs = nets.per_agent(
        groups, {g.name: nets.gaussian_log_prob(dists[g.name], actions[g.name]) for g in groups})
    next_state = batch_step(carry.env_state, assemble_action(groups, actions))
    done = next_state.done
    reward, next_critic_obs, nan_reset = _screen_blowups(next_state)
    paper = jnp.where(nan_reset > 0, 0.0, next_state.metrics.get("paper_reward", reward))
    ret = carry.episode_return + reward
    paper_ret = carry.episode_paper_return + paper
    length = carry.episode_length + 1.0
    carry = RolloutCarry(env_state=next_state, episode_return=ret * (1.0 - done),
                         episode_length=length * (1.0 - done), episode_paper_return=paper_ret *
                         (1.0 - done), done_return=carry.done_return + jnp.sum(ret * done),
                         done_length=carry.done_length + jnp.sum(length * done),
                         done_paper_return=carry.done_paper_return + jnp.sum(paper_ret * done),
                         done_count=carry.done_count + jnp.sum(done))
    transition = Transition(obs=obs, actions=actions, log_probs=log_probs, reward=reward, done=done,
                            truncation=next_state.info["truncation"],
                            next_critic_obs=next_critic_obs, env_metrics=next_state.metrics,
                            nan_reset=nan_reset)
    return carry, transition

  def rollout(params: nets.Params, normalizer: normalization.Normalizer | None, env_state: Any,
              episodes: EpisodeStats, key: jax.Array) -> tuple[RolloutCarry, Transition]:
    """``unroll_length`` steps of all envs: the final loop state and the stacked transitions
    ``[T, B, ...]``."""
    zero = jnp.zeros((), jnp.float32)
    carry = RolloutCarry(env_state=env_state, episode_return=episodes.running_return,
                         episode_length=episodes.running_length,
                         episode_paper_return=episodes.running_paper_return, done_return=zero,
                         done_length=zero, done_paper_return=zero, done_count=zero)
    return jax.lax.scan(lambda c, k: step(params, normalizer, c, k), carry,
                        jax.random.split(key, config.unroll_length))

  return rollout


def _make_update(config: TrainConfig, networks: nets.Networks,
                 optimizer: optax.GradientTransformation,
                 axis_name: str | None) -> Callable[..., tuple[OptimizerState, Metrics]]:

  def minibatch_step(opt: OptimizerState, batch: losses.LossBatch,
                     normalizer: normalization.Normalizer | None) -> tuple[OptimizerState, Metrics]:
    """One MAPPO gradient step (gradients averaged over devices when sharded)."""
    grads, metrics = loss_gradients(opt.params, normalizer, batch, networks, config, axis_name)
    opt_state = opt.opt_state
    if config.learning_rate_schedule == "adaptive_kl":
      # The KL of the current policy from the rollout's on this minibatch, before the step (as
      # rsl_rl); averaged over devices above, so every device sets the same rate.
      learning_rate = adapt_learning_rate(injected_learning_rate(opt_state), metrics["approx_kl"],
                                          config.desired_kl)
      opt_state = optax.tree_utils.tree_set(opt_state, learning_rate=learning_rate)
      metrics = {**metrics, "learning_rate": learning_rate}
    updates, opt_state = optimizer.update(grads, opt_state, opt.params)
    if config.learning_rate_schedule == "linear":  # the rate this step used
      metrics = {**metrics, "learning_rate": injected_learning_rate(opt_state)}
    elif config.learning_rate_schedule == "fixed":
      metrics = {**metrics, "learning_rate": jnp.asarray(config.learning_rate, jnp.float32)}
    return OptimizerState(optax.apply_updates(opt.params, updates), opt_state), metrics

  def update(opt: OptimizerState, normalizer: normalization.Normalizer | None,
             batch: losses.LossBatch, key: jax.Array) -> tuple[OptimizerState, Metrics]:
    """``num_epochs`` shuffled passes of ``num_minibatches`` steps over the flat batch; metrics
    averaged over all steps."""
    n = batch.advantages.shape[0]
    mb = n // config.num_minibatches

    def epoch(opt: OptimizerState, epoch_key: jax.Array) -> tuple[OptimizerState, Metrics]:
      perm = jnp.argsort(jax.random.bits(epoch_key, (n,)))  # one draw + one sort
      shuffled = jax.tree.map(lambda x: x[perm].reshape((config.num_minibatches, mb) + x.shape[1:]),
                              batch)
      return jax.lax.scan(lambda o, b: minibatch_step(o, b, normalizer), opt, shuffled)

    opt, metrics = jax.lax.scan(epoch, opt, jax.random.split(key, config.num_epochs))
    return opt, jax.tree.map(jnp.mean, metrics)

  return update


def _flatten_time(x: jax.Array) -> jax.Array:
  """``[T, B, ...] -> [T*B, ...]``."""
  return x.reshape((-1,) + x.shape[2:])


def _episode_stats(ro: RolloutCarry, previous: EpisodeStats,
                   axis_name: str | None) -> tuple[EpisodeStats, jax.Array]:
  """The episode bookkeeping after a rollout, and the episodes it completed (all devices)."""
  done_count = _sum(ro.done_count, axis_name)
  any_done = done_count > 0
  denom = jnp.maximum(done_count, 1.0)
  completed = lambda total, last: jnp.where(any_done, _sum(total, axis_name) / denom, last)
  episodes = EpisodeStats(
      running_return=ro.episode_return, running_length=ro.episode_length,
      last_return=completed(ro.done_return, previous.last_return), last_length=completed(
          ro.done_length, previous.last_length), running_paper_return=ro.episode_paper_return,
      last_paper_return=completed(ro.done_paper_return, previous.last_paper_return))
  return episodes, done_count


def make_mappo(config: TrainConfig, env: MultiAgentEnv, axis_name: str | None = None) -> Mappo:
  """MAPPO for ``env``'s agent partition, as pure functions.

  Args:
    config: training config (sizes validated by :func:`mash.rl.config.derived`).
    env: a :class:`MultiAgentEnv`.
    axis_name: when given, the functions must run inside ``shard_map`` over that mesh axis (the env
      batch split over devices) and average their updates over it.

  Returns:
    The :class:`Mappo`.
  """
  derived(config)
  networks = nets.make_networks(tuple(env.agent_groups), env.critic_obs_size, config)
  optimizer = make_optimizer(config)
  rollout = _make_rollout(config, env, networks)
  update = _make_update(config, networks, optimizer, axis_name)

  def active_normalizer(normalizer: normalization.Normalizer) -> normalization.Normalizer | None:
    return normalizer if config.normalize_observations else None

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

    values = networks.value_apply(state.params, normalizer, tr.obs["critic"])
    next_values = networks.value_apply(state.params, normalizer, tr.next_critic_obs)
    # Steps into a blown-up state: zero advantage (the episode counts as cut before them, not as a
    # fall) and weight 0 in the advantage statistics and the loss.
    valid = 1.0 - tr.nan_reset
    advantages, returns = losses.compute_gae(tr.reward, values, next_values, tr.done, tr.truncation,
                                             config.gamma, config.gae_lambda, valid=valid)
    batch = jax.tree.map(
        _flatten_time,
        losses.LossBatch(obs=tr.obs, actions=tr.actions, log_probs=tr.log_probs, values=values,
                         advantages=advantages, returns=returns, weights=valid))
    opt, loss_metrics = update(OptimizerState(state.params, state.opt_state), normalizer, batch,
                               sgd_key)
    episodes, done_count = _episode_stats(ro, state.episodes, axis_name)
    metrics = {
        "episode_reward": episodes.last_return,
        "episode_length": episodes.last_length,
        "paper_episode_reward": episodes.last_paper_return,
        "episodes_completed": done_count,
        "step_reward": _mean(tr.reward, axis_name),
        "done_rate": _mean(tr.done, axis_name),
        "nan_resets": _sum(tr.nan_reset, axis_name),
        "value_mean": _mean(values, axis_name),
        "action_std": nets.mean_action_std(opt.params),
        **{k: _mean(v, axis_name) for k, v in tr.env_metrics.items()},
        **loss_metrics,
    }
    new_state = TrainState(params=opt.params, opt_state=opt.opt_state, normalizer=stats,
                           env_state=ro.env_state, episodes=episodes, rng=rng,
                           iteration=state.iteration + 1)
    return new_state, metrics

  def train_epoch(state: TrainState) -> tuple[TrainState, Metrics]:
    """``iterations_per_call`` iterations; metrics stacked to ``[iterations_per_call]``."""
    return jax.lax.scan(lambda s, _: iteration(s), state, None, length=config.iterations_per_call)

  return Mappo(config=config, env=env, networks=networks, optimizer=optimizer, axis_name=axis_name,
               init=_make_init(config, env, networks, optimizer), iteration=iteration,
               update=update, train_epoch=train_epoch)
