"""The paper's sixteen reward terms (Table "Reward function"), one small function each.

Each function returns the *unscaled* term for one environment; its sign is the paper's formula's,
and the scale (with its sign) lives in :class:`RewardScales`. :func:`reward_terms` multiplies by
scale and control dt (legged_gym's convention, which the paper's Isaac Gym code base follows) and
skips zero-scale terms at trace time.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from mash.checks import MAX_INT32, Bound, check_bounds


@dataclasses.dataclass(frozen=True)
class RewardScales:
  """Paper scales. A zero removes the term from the traced program; :func:`check_scales` bounds
  them."""

  joint_pos: float = 3.5
  tracking_lin_vel: float = 1.5
  tracking_ang_vel: float = 1.4
  dof_torques: float = -2e-3
  dof_vel: float = -5e-4
  dof_acc: float = -1e-7
  feet_air_time: float = 2.0
  feet_clearance: float = 2.0
  feet_contact_number: float = 1.2
  orientation: float = 1.0
  collision: float = -1.0
  feet_slip: float = -5e-2
  base_height: float = 0.2
  action_smoothness_1: float = -0.1
  action_smoothness_2: float = -0.1
  torque_rate: float = -2e-4


@dataclasses.dataclass(frozen=True)
class RewardParams:
  """Constants inside the terms (the paper leaves them open; ours, mostly humanoid-gym's).

  Attributes:
    tracking_sigma: sigma_t of linear velocity tracking (m^2/s^2).
    yaw_sigma: sigma_yaw of yaw-rate tracking (rad^2/s^2).
    air_time_alpha: alpha of feet air time (1/m), on the stride error.
    feet_height_target: h_target of feet clearance (m above the floor). The paper gives none.
      None (default): the robot's (``RobotSpec.feet_height_target``), the peak swing height of
      the temporal director's reference (on the T1 3.8 cm at its swing amplitude 0.25), so
      following the reference earns the term; the env fills it in. The 8 cm used before was out
      of the reference's reach.
    feet_height_tolerance: delta of feet clearance (m).
    orientation_k_euler: k of exp(-k |roll, pitch|) (1/rad).
    orientation_k_gravity: k of exp(-k |g_proj,xy|).
    base_height_k: k of exp(-k |h - h_target|) (1/m).
    collision_force: contact force above which a penalized pair counts (N).
    only_positive: clip the summed reward at zero (legged_gym's default), so early falls are not
      a way out of penalties.
    penalty_ramp_steps: a curriculum (ours; the paper has none): over this many control steps of
      each env slot since training began, the scales of ``ramped_terms`` grow linearly from 0 to
      their full value, so early exploration noise is not taxed. 0 (default): the paper's reward
      from the first step. Episode resets do not restart the count; a resumed run continues it.
    ramped_terms: the terms the curriculum phases in. Default: the action-smoothness and
      torque-rate penalties, the ones that grow with the action noise itself.
    tracking_boost: a second curriculum (ours): the scales of ``boosted_terms`` start at this
      multiple of their value and fall linearly to it (x1) over ``tracking_boost_steps`` control
      steps of each env slot, so that following the command is learned while the policy is still
      exploring and the reward after the curriculum is the paper's. 1 (default): off.
    tracking_boost_steps: length of that curriculum in control steps per env slot.
    boosted_terms: the terms it multiplies. Default: the two velocity-tracking terms.
    kick_relief_s: (ours) for this many seconds after each velocity kick of the torso
      (``DomainRandConfig.kick_velocity``) the ``relieved_terms`` are off, so a recovery step
      out of the gait's rhythm (a crossover, a quick second step) is not taxed for leaving the
      reference; the rest of the reward, tracking and survival included, stays. A kick the kick
      curriculum scales to nothing relieves nothing; without kicks it does nothing. 0 (default):
      off. Measured on the T1 at 1 s: it walks at half the command and survives fewer 1 m/s
      kicks, not more (``benchmarks/results/2026-12-06_cpu_preset_kicks/kick_relief_seed0``).
    relieved_terms: the terms it turns off. Default: the three that bind the legs to the gait
      clock (the reference pose, the stance schedule, the swing height of the scheduled swing).


  The sane range of every number is checked by :func:`check_params`.
  """

  tracking_sigma: float = 0.25
  yaw_sigma: float = 0.25
  air_time_alpha: float = 5.0
  feet_height_target: float | None = None
  feet_height_tolerance: float = 0.02
  orientation_k_euler: float = 10.0
  orientation_k_gravity: float = 20.0
  base_height_k: float = 100.0
  collision_force: float = 0.1
  only_positive: bool = True
  penalty_ramp_steps: int = 0
  ramped_terms: tuple[str, ...] = ("action_smoothness_1", "action_smoothness_2", "torque_rate")
  tracking_boost: float = 1.0
  tracking_boost_steps: int = 0
  boosted_terms: tuple[str, ...] = ("tracking_lin_vel", "tracking_ang_vel")
  kick_relief_s: float = 0.0
  relieved_terms: tuple[str, ...] = ("joint_pos", "feet_contact_number", "feet_clearance")


class RewardInputs(NamedTuple):
  """What the terms read, for one environment after one control step.

  Attributes:
    q_rel: [C] controlled joint angles minus default (rad).
    q_ref: [C] reference offsets from the temporal director (rad).
    dq: [J] all actuated joint velocities (rad/s); last_dq: [J] at the previous step.
    torque: [J] applied PD torque (N m); last_torque: [J] previous step; torque_limit: [J].
    command: [4] standing flag, vx, vy, yaw rate.
    base_lin_vel: [3] torso linear velocity, torso frame (m/s).
    base_ang_vel: [3] torso angular velocity, torso frame (rad/s).
    euler: [3] roll, pitch, yaw (rad).
    gravity_proj: [3] gravity direction in the torso frame.
    base_height: [] torso height above the lower sole (m); base_height_target: [].
    feet_height: [2] sole height above the floor (m).
    feet_vel: [2, 2] horizontal foot velocity (m/s).
    contact: [2] foot in contact; stance: [2] foot should be in stance (0/1 floats).
    first_contact: [2] touchdown this step; air_time: [2] duration of the swing just ended (s).
    stride_error: [2] touchdown stride minus commanded stride (m).
    penalty_force: [P] normal force of each penalized contact pair (N).
    action: [C], last_action: [C], last_last_action: [C].
    dt: control period (s).
    env_steps: [] control steps this env slot has run since training began (across episodes);
      read only by the ``penalty_ramp_steps`` curriculum (None where it is off).
  """

  q_rel: jax.Array
  q_ref: jax.Array
  dq: jax.Array
  last_dq: jax.Array
  torque: jax.Array
  last_torque: jax.Array
  torque_limit: jax.Array
  command: jax.Array
  base_lin_vel: jax.Array
  base_ang_vel: jax.Array
  euler: jax.Array
  gravity_proj: jax.Array
  base_height: jax.Array
  base_height_target: jax.Array
  feet_height: jax.Array
  feet_vel: jax.Array
  contact: jax.Array
  stance: jax.Array
  first_contact: jax.Array
  air_time: jax.Array
  stride_error: jax.Array
  penalty_force: jax.Array
  action: jax.Array
  last_action: jax.Array
  last_last_action: jax.Array
  dt: float
  env_steps: jax.Array | None = None


def joint_pos(x: RewardInputs, p: RewardParams) -> jax.Array:
  """exp(-||q - q_default - q_ref||): following the temporal director's reference pose."""
  return jnp.exp(-jnp.linalg.norm(x.q_rel - x.q_ref))


def tracking_lin_vel(x: RewardInputs, p: RewardParams) -> jax.Array:
  """exp(-||v_cmd,xy - v_b,xy||^2 / sigma_t): planar velocity tracking in the torso frame."""
  err = jnp.sum(jnp.square(x.command[1:3] - x.base_lin_vel[:2]))
  return jnp.exp(-err / p.tracking_sigma)


def tracking_ang_vel(x: RewardInputs, p: RewardParams) -> jax.Array:
  """exp(-(w_cmd,z - w_b,z)^2 / sigma_yaw): yaw-rate tracking."""
  return jnp.exp(-jnp.square(x.command[3] - x.base_ang_vel[2]) / p.yaw_sigma)


def dof_torques(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum (tau / tau_max)^2 over actuated joints (dimensionless effort)."""
  return jnp.sum(jnp.square(x.torque / x.torque_limit))


def dof_vel(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum dq^2 (rad^2/s^2)."""
  return jnp.sum(jnp.square(x.dq))


def dof_acc(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum ((dq_t - dq_{t-1}) / dt)^2 (rad^2/s^4)."""
  return jnp.sum(jnp.square((x.dq - x.last_dq) / x.dt))


def feet_air_time(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum over touchdowns of t_air * exp(-alpha ||dx||): long swings whose stride fits the command.

  dx is the touchdown stride minus the stride the command asks for (m); zero while standing.
  """
  per_foot = x.first_contact * x.air_time * jnp.exp(-p.air_time_alpha * jnp.abs(x.stride_error))
  return jnp.sum(per_foot) * (1.0 - x.command[0])


def feet_clearance(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum over swing feet of (|z_foot - h_target| < delta): swing feet at the target height."""
  near = jnp.abs(x.feet_height - p.feet_height_target) < p.feet_height_tolerance
  return jnp.sum(near * (1.0 - x.stance))


def feet_contact_number(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum over feet of +1 if contact matches the gait's stance, else -0.3."""
  return jnp.sum(jnp.where(x.contact == x.stance, 1.0, -0.3))


def orientation(x: RewardInputs, p: RewardParams) -> jax.Array:
  """exp(-k1 |roll, pitch|_1) + exp(-k2 ||g_proj,xy||): upright torso (max 2)."""
  return (jnp.exp(-p.orientation_k_euler * jnp.sum(jnp.abs(x.euler[:2]))) +
          jnp.exp(-p.orientation_k_gravity * jnp.linalg.norm(x.gravity_proj[:2])))


def collision(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum 1(||f_c|| > 0.1 N) over penalized pairs (knees, feet, hands against thighs)."""
  return jnp.sum(x.penalty_force > p.collision_force).astype(jnp.float32)


def feet_slip(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum c_f ||v_f,xy||^2: feet sliding while in contact (m^2/s^2)."""
  return jnp.sum(x.contact * jnp.sum(jnp.square(x.feet_vel), axis=-1))


def base_height(x: RewardInputs, p: RewardParams) -> jax.Array:
  """exp(-k |h_base - h_target|): torso height above the soles."""
  return jnp.exp(-p.base_height_k * jnp.abs(x.base_height - x.base_height_target))


def action_smoothness_1(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum (a_t - a_{t-1})^2."""
  return jnp.sum(jnp.square(x.action - x.last_action))


def action_smoothness_2(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum (a_t - 2 a_{t-1} + a_{t-2})^2."""
  return jnp.sum(jnp.square(x.action - 2.0 * x.last_action + x.last_last_action))


def torque_rate(x: RewardInputs, p: RewardParams) -> jax.Array:
  """sum ((tau_t - tau_{t-1}) / (tau_max dt))^2 (1/s^2)."""
  return jnp.sum(jnp.square((x.torque - x.last_torque) / (x.torque_limit * x.dt)))


TERMS = {f.name: globals()[f.name] for f in dataclasses.fields(RewardScales)}

# A scale this large (about 300 times the paper's largest, 3.5) is a typo, not a weighting.
MAX_ABS_SCALE = 1e3
# The sane range of each constant (feet_height_target's None: the robot's) and curriculum length.
PARAM_BOUNDS = (
    Bound("tracking_sigma", 0.0, 100.0, "m^2/s^2", open_low=True),
    Bound("yaw_sigma", 0.0, 100.0, "rad^2/s^2", open_low=True),
    Bound("air_time_alpha", 0.0, 1e3, "1/m"),
    Bound("feet_height_target", 0.0, 1.0, "m"),
    Bound("feet_height_tolerance", 0.0, 1.0, "m", open_low=True),
    Bound("orientation_k_euler", 0.0, 1e4, "1/rad"),
    Bound("orientation_k_gravity", 0.0, 1e4, ""),
    Bound("base_height_k", 0.0, 1e4, "1/m"),
    Bound("collision_force", 0.0, 1e5, "N"),
    Bound("tracking_boost", 1.0, 100.0, "(1 = no curriculum)"),
    Bound("penalty_ramp_steps", 0, MAX_INT32, "steps (0 = no curriculum)"),
    Bound("tracking_boost_steps", 0, MAX_INT32, "steps (0 = no curriculum)"),
    Bound("kick_relief_s", 0.0, 60.0, "s (0 = off)"),
)


def check_scales(scales: RewardScales) -> None:
  """Checks that every scale is a number in [-1000, 1000] (NaN and inf are not).

  Raises:
    ValueError: one line naming the term, its value and what was expected.
  """
  check_bounds(scales, [Bound(name, -MAX_ABS_SCALE, MAX_ABS_SCALE) for name in TERMS])


def check_params(params: RewardParams) -> None:
  """Checks the constants of the terms (``PARAM_BOUNDS``), the curricula's lengths (whole steps
  in [0, 2**31 - 1]) and that the curricula name reward terms.

  Raises:
    ValueError: one line naming the field, its value and what was expected.
  """
  for field in ("ramped_terms", "boosted_terms", "relieved_terms"):
    unknown = [t for t in getattr(params, field) if t not in TERMS]
    if unknown:
      raise ValueError(f"{field}: '{unknown[0]}' is not a reward term; expected names from "
                       f"{', '.join(TERMS)}")
  check_bounds(params, PARAM_BOUNDS)


def penalty_ramp(env_steps: jax.Array | None, params: RewardParams) -> jax.Array:
  """[] fraction in [0, 1] of the ``ramped_terms``' scales in force after ``env_steps`` steps."""
  if params.penalty_ramp_steps <= 0:
    return jnp.ones(())
  if env_steps is None:
    raise ValueError("reward_params.penalty_ramp_steps is set but RewardInputs.env_steps is None")
  return jnp.clip(jnp.asarray(env_steps, jnp.float32) / params.penalty_ramp_steps, 0.0, 1.0)


def tracking_boost(env_steps: jax.Array | None, params: RewardParams) -> jax.Array:
  """[] multiplier of the ``boosted_terms``' scales after ``env_steps`` steps: from
  ``params.tracking_boost`` down to 1 at ``params.tracking_boost_steps``, 1 after (and when off)."""
  if params.tracking_boost == 1.0 or params.tracking_boost_steps <= 0:
    return jnp.ones(())
  if env_steps is None:
    raise ValueError("reward_params.tracking_boost is set but RewardInputs.env_steps is None")
  left = 1.0 - jnp.clip(jnp.asarray(env_steps, jnp.float32) / params.tracking_boost_steps, 0, 1)
  return 1.0 + (params.tracking_boost - 1.0) * left


def reward_terms(x: RewardInputs, scales: RewardScales, params: RewardParams,
                 curricula: bool = True) -> dict[str, jax.Array]:
  """Each non-zero term times its scale and dt: ``{name: []}``; their sum is the step reward.

  With ``curricula`` the terms are then passed through :func:`apply_curricula` (no change unless
  a curriculum is on); without, they are the paper's, whatever the curricula say.
  """
  terms = {
      name: fn(x, params) * getattr(scales, name) * x.dt
      for name, fn in TERMS.items()
      if getattr(scales, name) != 0.0
  }
  return apply_curricula(terms, x.env_steps, params) if curricula else terms


def apply_curricula(terms: dict[str, jax.Array], env_steps: jax.Array | None,
                    params: RewardParams) -> dict[str, jax.Array]:
  """The paper-scale ``terms`` with the ``params.ramped_terms`` multiplied by
  :func:`penalty_ramp` and the ``params.boosted_terms`` by :func:`tracking_boost`."""
  ramp = penalty_ramp(env_steps, params)
  boost = tracking_boost(env_steps, params)

  def factor(name):
    return ((ramp if name in params.ramped_terms else 1.0) *
            (boost if name in params.boosted_terms else 1.0))

  return {name: value * factor(name) for name, value in terms.items()}


def kick_relief(terms: dict[str, jax.Array], steps_since_kick: jax.Array, dt: float,
                params: RewardParams) -> dict[str, jax.Array]:
  """``terms`` with the ``params.relieved_terms`` zeroed while ``steps_since_kick`` control steps
  of ``dt`` seconds are fewer than ``params.kick_relief_s`` (rounded to whole steps; the kick's
  own step counts as 0); ``terms`` unchanged when the relief is off."""
  if params.kick_relief_s <= 0:
    return terms
  relief_steps = round(params.kick_relief_s / dt)
  after = (steps_since_kick >= relief_steps).astype(jnp.float32)
  return {
      name: value * after if name in params.relieved_terms else value
      for name, value in terms.items()
  }


def total_reward(terms: dict[str, jax.Array], params: RewardParams) -> jax.Array:
  """Sum of the scaled terms, clipped at zero when ``params.only_positive``."""
  total = sum(terms.values())
  return jnp.maximum(total, 0.0) if params.only_positive else total
