"""Training configuration for MAPPO / PPO: one frozen dataclass and the quantities derived from it.

``TrainConfig`` holds every knob of the learner with the paper's values as defaults where the paper
gives them (``num_iterations``, ``unroll_length``) and the legged_gym / humanoid-gym (rsl_rl PPO)
values otherwise; each field's docstring names its source. Derived sizes (batch, minibatch, env
steps) come from the pure function :func:`derived`, which is also where inconsistent sizes are
rejected. The same config trains MASH (limb agents) and the single-agent PPO baseline: the agent
partition belongs to the environment, not to this config.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, NamedTuple

from mash.checks import MAX_INT32, Bound, check_bounds


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """MAPPO hyper-parameters.

  Attributes:
    num_iterations: training iterations (rollout + update). Paper: "3000 episodes" of training.
    unroll_length: environment steps per env per iteration. Paper: "episode length of 48 steps".
    num_envs: parallel environments (legged_gym / humanoid-gym default 4096).
    iterations_per_call: iterations fused into one jitted ``lax.scan`` call (host logging,
      checkpointing and evaluation happen between calls). Our choice.
    num_epochs: passes over each rollout batch (rsl_rl ``num_learning_epochs`` = 5).
    num_minibatches: minibatches per epoch (rsl_rl ``num_mini_batches`` = 4).
    learning_rate: Adam step size (the start value under ``learning_rate_schedule='adaptive_kl'``).
      legged_gym starts at 1e-3 and humanoid-gym at 1e-5, both with an adaptive-KL schedule; by
      default we keep a fixed rate and take the standard PPO value 3e-4 (Schulman et al. 2017,
      continuous control).
    learning_rate_schedule: ``'fixed'``, ``'adaptive_kl'`` (rsl_rl's ``schedule='adaptive'``):
      before every minibatch step the rate is divided by 1.5 when the policy's KL from the
      rollout policy exceeds ``2 * desired_kl`` and multiplied by 1.5 when it is below
      ``desired_kl / 2`` (and not 0), within [1e-5, 1e-2]. The KL is the loss's ``approx_kl``;
      or ``'linear'`` (PureJaxRL's / CleanRL's ``anneal_lr``): from ``learning_rate`` down to 0
      at the last step of ``num_iterations``.
    desired_kl: the KL the adaptive schedule aims at (rsl_rl ``desired_kl`` = 0.01).
    gamma: discount (legged_gym 0.99; humanoid-gym uses 0.994).
    gae_lambda: GAE lambda (legged_gym 0.95; humanoid-gym uses 0.9).
    clip_epsilon: policy ratio clip (rsl_rl ``clip_param`` = 0.2).
    value_clip: clip of the value change around the rollout value (rsl_rl clips with
      ``clip_param`` = 0.2 too); ``0`` or negative disables value clipping.
    entropy_coef: entropy bonus (humanoid-gym 0.001; legged_gym uses 0.01).
    value_loss_coef: weight of the value loss (rsl_rl 1.0).
    max_grad_norm: global gradient-norm clip (rsl_rl 1.0).
    normalize_advantages: normalize advantages per agent over each minibatch (rsl_rl: yes).
    actor_hidden: actor MLP hidden sizes (legged_gym / humanoid-gym actor (512, 256, 128)).
    critic_hidden: critic MLP hidden sizes (legged_gym critic (512, 256, 128); humanoid-gym uses
      (768, 256, 128)).
    init_log_std: initial log standard deviation of every Gaussian action dimension
      (rsl_rl ``init_noise_std`` = 1.0, i.e. log-std 0).
    share_actor: agents of one group share one actor network (MASH). ``False`` (ablation) gives
      each agent its own parameters.
    local_critic: ablation (IPPO): each agent's critic sees only its own observation (the env must
      be built with ``critic='local'``) instead of the centralized critic on the global state.
    shared_value_head: ablation: the critic has a single value head broadcast to all agents
      instead of one head per agent (paper: ``V_t in R^{N_agents}``).
    normalize_observations: running mean/variance normalization of actor and critic inputs
      (rsl_rl ``empirical_normalization``).
    obs_clip: normalized observations are clipped to ``[-obs_clip, obs_clip]`` (our choice; only
      used when ``normalize_observations``).
    seed: base random seed.
  """

  num_iterations: int = 3000
  unroll_length: int = 48
  num_envs: int = 4096
  iterations_per_call: int = 10
  num_epochs: int = 5
  num_minibatches: int = 4
  learning_rate: float = 3e-4
  learning_rate_schedule: str = "fixed"
  desired_kl: float = 0.01
  gamma: float = 0.99
  gae_lambda: float = 0.95
  clip_epsilon: float = 0.2
  value_clip: float = 0.2
  entropy_coef: float = 0.001
  value_loss_coef: float = 1.0
  max_grad_norm: float = 1.0
  normalize_advantages: bool = True
  actor_hidden: tuple[int, ...] = (512, 256, 128)
  critic_hidden: tuple[int, ...] = (512, 256, 128)
  init_log_std: float = 0.0
  share_actor: bool = True
  shared_value_head: bool = False
  local_critic: bool = False
  normalize_observations: bool = True
  obs_clip: float = 10.0
  seed: int = 0


LEARNING_RATE_SCHEDULES = ("fixed", "adaptive_kl", "linear")
# rsl_rl's bounds for the adaptive schedule.
MIN_LEARNING_RATE, MAX_LEARNING_RATE = 1e-5, 1e-2
# Caps on sizes, far above any run's (the gpu preset: 4096 envs x 48 steps, layers of 512) and low
# enough that a typo is refused here instead of exhausting memory when the trainer starts.
SIZE_CAPS = {
    "num_iterations": MAX_INT32, "unroll_length": 10_000, "num_envs": 2**20,
    "iterations_per_call": 10_000, "num_epochs": 1000, "num_minibatches": MAX_INT32
}
MAX_LAYER_SIZE = 8192
BOUNDS = (
    *(Bound(name, 1, cap) for name, cap in SIZE_CAPS.items()),
    Bound("learning_rate", 0.0, 1.0, open_low=True),
    Bound("desired_kl", 0.0, 10.0, open_low=True),
    Bound("gamma", 0.0, 1.0, open_low=True),
    Bound("gae_lambda", 0.0, 1.0),
    Bound("clip_epsilon", 0.0, 10.0, open_low=True),
    Bound("value_clip", -1e6, 1e6, "(<= 0: no value clip)"),
    Bound("entropy_coef", 0.0, 1e3),
    Bound("value_loss_coef", 0.0, 1e3),
    Bound("max_grad_norm", 0.0, 1e6, open_low=True),
    Bound("init_log_std", -20.0, 5.0, "(a log standard deviation)"),
    Bound("obs_clip", 0.0, 1e6, open_low=True),
    Bound("seed", 0, MAX_INT32),
)


class Derived(NamedTuple):
  """Sizes that follow from a :class:`TrainConfig`.

  Attributes:
    batch_size: transitions per iteration, ``num_envs * unroll_length``.
    minibatch_size: transitions per gradient step, ``batch_size // num_minibatches``.
    updates_per_iteration: gradient steps per iteration, ``num_epochs * num_minibatches``.
    env_steps_per_iteration: environment steps per iteration (= ``batch_size``).
    env_steps_per_call: environment steps per jitted call.
    num_calls: jitted calls needed to reach ``num_iterations`` (rounded up).
  """

  batch_size: int
  minibatch_size: int
  updates_per_iteration: int
  env_steps_per_iteration: int
  env_steps_per_call: int
  num_calls: int


def derived(config: TrainConfig, num_devices: int = 1) -> Derived:
  """Computes the derived sizes and checks that they are consistent.

  Args:
    config: the training config.
    num_devices: devices the env batch is split over; every device must get whole minibatches.

  Returns:
    The derived sizes (global, i.e. summed over devices).

  Raises:
    ValueError: a size is not positive or above its cap (``SIZE_CAPS``, ``MAX_LAYER_SIZE``), a
      number is outside its range (NaN and inf always are), ``num_envs`` is not divisible by
      ``num_devices``, or the per-device batch ``num_envs / num_devices * unroll_length`` is not
      divisible by ``num_minibatches``. One line naming the field, its value and what was expected.
  """
  try:
    check_bounds(config, BOUNDS)
  except ValueError as e:
    raise ValueError(f"TrainConfig.{e}.") from None
  if config.learning_rate_schedule not in LEARNING_RATE_SCHEDULES:
    raise ValueError(f"TrainConfig.learning_rate_schedule '{config.learning_rate_schedule}' is "
                     f"unknown; expected one of {', '.join(LEARNING_RATE_SCHEDULES)}.")
  for name in ("actor_hidden", "critic_hidden"):
    sizes = getattr(config, name)
    if not sizes or any(int(h) != h or not 1 <= h <= MAX_LAYER_SIZE for h in sizes):
      raise ValueError(f"TrainConfig.{name} must be one or more layer sizes >= 1 and <= "
                       f"{MAX_LAYER_SIZE}, got {sizes}.")
  if num_devices < 1 or config.num_envs % num_devices:
    raise ValueError(f"TrainConfig.num_envs={config.num_envs} must be divisible by the number of "
                     f"devices ({num_devices}).")
  batch = config.num_envs * config.unroll_length
  if batch > MAX_INT32:
    raise ValueError(f"TrainConfig: num_envs * unroll_length = {batch} transitions per iteration "
                     f"must be at most {MAX_INT32} (int32 indices).")
  local_batch = config.num_envs // num_devices * config.unroll_length
  if local_batch % config.num_minibatches:
    raise ValueError(
        f"TrainConfig: num_envs/devices * unroll_length = {config.num_envs // num_devices} * "
        f"{config.unroll_length} = {local_batch} must be divisible by num_minibatches="
        f"{config.num_minibatches}.")
  return Derived(
      batch_size=batch,
      minibatch_size=batch // config.num_minibatches,
      updates_per_iteration=config.num_epochs * config.num_minibatches,
      env_steps_per_iteration=batch,
      env_steps_per_call=batch * config.iterations_per_call,
      num_calls=-(-config.num_iterations // config.iterations_per_call),
  )


def config_to_dict(config: TrainConfig) -> dict[str, Any]:
  """JSON-ready dict of a config (tuples become lists)."""
  return dataclasses.asdict(config)


def config_from_dict(d: Mapping[str, Any]) -> TrainConfig:
  """Inverse of :func:`config_to_dict`.

  Raises:
    ValueError: ``d`` has a key that is not a ``TrainConfig`` field.
  """
  fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
  unknown = sorted(set(d) - set(fields))
  if unknown:
    raise ValueError(f"Unknown TrainConfig field(s) {unknown}; expected some of {sorted(fields)}.")
  kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
  return TrainConfig(**kwargs)
