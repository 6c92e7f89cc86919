"""Domain randomization: the paper's eleven parameters (Table "Domain randomization parameters")
and the torque noise its text adds.

Reset-time draws (friction, link masses, CoM offset, gravity, joint damping / friction / armature,
Kp and Kd scales) live in :class:`DomainParams`, one per environment, kept in the env state; the
MJX model each env steps is the shared model with those fields replaced (``apply``), so under
``vmap`` every env has its own physics. Per-step draws (motor delay, pushes, torque noise) happen in
the env step.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct
from mujoco import mjx

from mash.checks import MAX_INT32, Bound, check_bounds


@dataclasses.dataclass(frozen=True)
class DomainRandConfig:
  """Ranges are the paper's (uniform). ``enabled=False`` gives the nominal robot.

  Attributes:
    enabled: draw parameters at all (False: nominal values, no delay, no pushes).
    friction: floor-sole sliding friction coefficient.
    mass_scale: per-link mass (and inertia) multiplier.
    com_offset: torso centre-of-mass offset per axis (m).
    motor_delay_ms: actuation delay, redrawn every control step (ms).
    push_force: horizontal force on the torso per axis (N), redrawn every ``push_interval_s``.
      None (default): the robot's (``RobotSpec.push_force``: the paper's +-20 N on the T1, scaled
      to another robot's mass); the env fills it in.
    push_torque: torque on the torso per axis (N m); the paper's critic sees a push torque but its
      table gives no range: the robot file's (+-5 N m on the T1, ours). None: the robot's.
    push_interval_s: how long one push is held (s); 0 (default) draws a new push every control
      step, as the paper randomizes "external perturbations" "at each simulation step" (SPEC §6:
      per step). Runs before 2026-11-26 held each push 1 s (``push_interval_s=1.0``), a far harder
      disturbance (20 N held 1 s is a 20 N s impulse, ~0.6 m/s on the 31.6 kg T1); it stays here
      as a robustness setting, and their ``config.json`` files keep it.
    gravity: |g| (m/s^2).
    joint_damping: per-joint viscous damping (N m s / rad).
    joint_friction: per-joint dry friction (N m).
    armature: per-joint reflected rotor inertia (kg m^2).
    kp_scale: per-joint multiplier of the PD stiffness.
    kd_scale: per-joint multiplier of the PD damping.
    torque_noise: the paper randomizes "torque noise" at each simulation step without a range;
      ours: every physics substep each motor applies its PD torque plus U[-1, 1] x this fraction
      of its torque limit (2 %: up to 1.2 N m at the knee, 0.36 N m at the arms), clipped to the
      limit. 0 turns it off.
    friction_initial: a curriculum on the floor friction (ours; the paper has none): the range
      ``(lo, hi)`` drawn from at the start of training, moving linearly to ``friction`` over
      ``friction_ramp_steps`` control steps of each env slot (as the penalty curriculum,
      ``RewardParams.penalty_ramp_steps``). None: no curriculum.
    friction_ramp_steps: length of that curriculum (control steps); 0: ``friction`` throughout.
      Evaluation always draws from ``friction``, the range training ends on.
    slippery_share: the fraction of fresh training episodes (ours; the paper has none) whose floor
      friction is drawn from ``slippery_friction`` instead, all through training: the slippery
      floors are where CPU policies fall, and under ``friction`` alone they are ~9 % of the
      episodes. 0 (default): every floor from ``friction`` (or its curriculum). Evaluation never
      applies it.
    slippery_friction: the range of those floors.
    kick_velocity: (ours; the paper has none) velocity kicks of the torso: every
      ``kick_interval_s`` the torso's horizontal velocity jumps by a size drawn from this range
      (m/s) in a direction uniform in the plane, as MuJoCo Playground's and mjlab's velocity tasks
      shove their robots. A shove, unlike the paper's per-step pushes (zero-mean, 1-2 N s net a
      second), is what a robot meets; the critic sees the last kick (privileged), the actors do
      not. (0, 0) (default): no kicks, and no kick in the env state or the critic.
    kick_interval_s: seconds between kicks, drawn anew after each one.
    kick_yaw_rate: a yaw-rate kick (rad/s) drawn with each velocity kick, sign uniform; (0, 0):
      none.
    kick_ramp_steps: a curriculum on the kicks (ours): each kick is scaled by the fraction of
      this many control steps that its env slot has run (the penalty curriculum's clock), so they
      grow from nothing to full size; 0 (default): full size from the start.
    kick_ramp_start_steps: the control steps of an env slot before the kicks begin (ours): the
      curriculum's fraction counts from here, so a gait can form unshoved first; 0 (default):
      from the first step. With ``kick_ramp_steps`` 0 the kicks start at full size here.


  The sane range of every number is checked by :func:`check_config`.
  """

  enabled: bool = True
  friction: tuple[float, float] = (0.1, 1.2)
  mass_scale: tuple[float, float] = (0.9, 1.13)
  com_offset: tuple[float, float] = (-0.03, 0.03)
  motor_delay_ms: tuple[float, float] = (0.0, 3.0)
  push_force: tuple[float, float] | None = None
  push_torque: tuple[float, float] | None = None
  push_interval_s: float = 0.0
  gravity: tuple[float, float] = (9.78, 9.83)
  joint_damping: tuple[float, float] = (0.0, 0.05)
  joint_friction: tuple[float, float] = (0.0, 0.05)
  armature: tuple[float, float] = (0.005, 0.015)
  kp_scale: tuple[float, float] = (0.95, 1.05)
  kd_scale: tuple[float, float] = (0.95, 1.05)
  torque_noise: float = 0.02
  friction_initial: tuple[float, float] | None = None
  friction_ramp_steps: int = 0
  slippery_share: float = 0.0
  slippery_friction: tuple[float, float] = (0.1, 0.3)
  kick_velocity: tuple[float, float] = (0.0, 0.0)
  kick_interval_s: tuple[float, float] = (5.0, 10.0)
  kick_yaw_rate: tuple[float, float] = (0.0, 0.0)
  kick_ramp_steps: int = 0
  kick_ramp_start_steps: int = 0

  @property
  def kicks(self) -> bool:
    """Whether the torso is kicked (a velocity or yaw-rate range above 0, randomization on)."""
    return self.enabled and (self.kick_velocity[1] > 0 or self.kick_yaw_rate[1] > 0)


MAX_INTERVAL_S = 1e5  # s, about a day: a longer hold is a typo (and its step count stays int32)
# The sane bounds of each range and number; ours, each far outside the paper's ranges, so a value
# beyond one is a typo. The pushes' None is the robot's, checked with its file.
BOUNDS = (
    Bound("friction", 0.0, 10.0, "", open_low=True, pair=True),
    Bound("slippery_friction", 0.0, 10.0, "", open_low=True, pair=True),
    Bound("mass_scale", 0.0, 10.0, "", open_low=True, pair=True),
    Bound("com_offset", -1.0, 1.0, "m", pair=True),
    Bound("motor_delay_ms", 0.0, 1000.0, "ms", pair=True),
    Bound("push_force", -1e4, 1e4, "N", pair=True),
    Bound("push_torque", -1e3, 1e3, "N m", pair=True),
    Bound("gravity", 0.0, 100.0, "m/s^2", pair=True),
    Bound("joint_damping", 0.0, 100.0, "N m s/rad", pair=True),
    Bound("joint_friction", 0.0, 100.0, "N m", pair=True),
    Bound("armature", 0.0, 10.0, "kg m^2", pair=True),
    Bound("kp_scale", 0.0, 10.0, "", open_low=True, pair=True),
    Bound("kd_scale", 0.0, 10.0, "", open_low=True, pair=True),
    Bound("friction_initial", 0.0, 10.0, open_low=True, pair=True),
    Bound("push_interval_s", 0.0, MAX_INTERVAL_S, "s"),
    Bound("friction_ramp_steps", 0, MAX_INT32, "steps"),
    Bound("kick_velocity", 0.0, 10.0, "m/s", pair=True),
    Bound("kick_interval_s", 0.0, MAX_INTERVAL_S, "s", open_low=True, pair=True),
    Bound("kick_yaw_rate", 0.0, 20.0, "rad/s", pair=True),
    Bound("kick_ramp_steps", 0, MAX_INT32, "steps"),
    Bound("kick_ramp_start_steps", 0, MAX_INT32, "steps"),
)


def check_config(config: DomainRandConfig) -> None:
  """Checks every range and number of a :class:`DomainRandConfig` without building anything:
  each range and number within ``BOUNDS`` (ranges with lo <= hi), the torque
  noise a fraction in [0, 1), the curriculum's start range as ``friction``'s and its length in
  [0, 2**31 - 1] steps. NaN and inf are never in range.

  Raises:
    ValueError: one line naming the field, its value and what was expected.
  """
  check_bounds(config, BOUNDS)
  if not 0.0 <= config.slippery_share <= 1.0:  # also NaN
    raise ValueError("slippery_share must be a fraction of the episodes in [0, 1], got "
                     f"{config.slippery_share}")
  if not 0.0 <= config.torque_noise < 1.0:  # also NaN
    raise ValueError("torque_noise must be a fraction of the torque limit in [0, 1), got "
                     f"{config.torque_noise}")


@struct.dataclass
class DomainParams:
  """One environment's reset-time draws.

  Attributes:
    friction: [] floor-sole friction.
    mass_scale: [nbody] link mass multipliers (world body included, unused).
    com_offset: [3] torso CoM offset (m).
    gravity: [] |g|.
    joint_damping: [n_joints], joint_friction: [n_joints], armature: [n_joints].
    kp_scale: [n_joints], kd_scale: [n_joints].
    motor_strength: [n_joints] multiplier of each motor's torque, its limit included (1: as the
      robot file says; not randomized in training: the robustness battery weakens motors).
  """

  friction: jax.Array
  mass_scale: jax.Array
  com_offset: jax.Array
  gravity: jax.Array
  joint_damping: jax.Array
  joint_friction: jax.Array
  armature: jax.Array
  kp_scale: jax.Array
  kd_scale: jax.Array
  motor_strength: jax.Array


class JointNominal(NamedTuple):
  """The un-randomized joint model of the actuated joints: damping, friction and armature, each a
  number for every joint or ``[n_joints]``. The defaults are a stand-in for tests of this module;
  ``MashEnv`` passes its robot's, read from its model (``MashEnv.nominal_domain``)."""

  damping: Any = 0.0
  friction: Any = 0.0
  armature: Any = 0.01


def nominal(nbody: int, n_joints: int, nominal_friction: float = 1.0,
            joints: JointNominal = JointNominal()) -> DomainParams:
  """The un-randomized robot (DR off)."""
  ones = jnp.ones((n_joints,))
  return DomainParams(friction=jnp.asarray(nominal_friction), mass_scale=jnp.ones(
      (nbody,)), com_offset=jnp.zeros((3,)), gravity=jnp.asarray(9.81),
                      joint_damping=jnp.asarray(joints.damping, jnp.float32) * ones,
                      joint_friction=jnp.asarray(joints.friction, jnp.float32) * ones,
                      armature=jnp.asarray(joints.armature, jnp.float32) * ones, kp_scale=ones,
                      kd_scale=ones, motor_strength=ones)


def friction_range(
    config: DomainRandConfig,
    env_steps: jax.Array | None) -> tuple[jax.Array, jax.Array] | tuple[float, float]:
  """The floor-friction range ``(lo, hi)`` after ``env_steps`` control steps of an env slot:
  ``config.friction`` unless the curriculum (``friction_initial``, ``friction_ramp_steps``) is on,
  and then the linear blend from ``friction_initial`` to ``friction`` (``[]`` arrays each)."""
  if config.friction_initial is None or config.friction_ramp_steps <= 0 or env_steps is None:
    return config.friction
  done = jnp.clip(jnp.asarray(env_steps, jnp.float32) / config.friction_ramp_steps, 0.0, 1.0)
  (lo0, hi0), (lo1, hi1) = config.friction_initial, config.friction
  return lo0 + done * (lo1 - lo0), hi0 + done * (hi1 - hi0)


def sample(
    key: jax.Array, config: DomainRandConfig, nbody: int, n_joints: int,
    env_steps: jax.Array | None = None, joints: JointNominal = JointNominal()) -> DomainParams:
  """Draws one environment's parameters (nominal when ``config.enabled`` is False).

  ``env_steps`` ([] int, control steps of this env slot since training began) places the floor
  friction's draw on its curriculum (:func:`friction_range`); None: the final range. With
  ``config.slippery_share`` > 0 that share of the draws comes from ``slippery_friction``.
  ``joints``: the robot's nominal joint model, used when randomization is off (on, the paper's
  absolute ranges replace it, for every robot).
  """
  if not config.enabled:
    return nominal(nbody, n_joints, joints=joints)
  k = jax.random.split(key, 9)
  u = lambda key, r, shape=(): jax.random.uniform(key, shape, minval=r[0], maxval=r[1])
  friction = u(k[0], friction_range(config, env_steps))
  if config.slippery_share > 0:  # its own keys: the other draws stay as they were without it
    k_pick, k_slip = jax.random.split(jax.random.fold_in(key, 9))
    friction = jnp.where(
        jax.random.uniform(k_pick) < config.slippery_share, u(k_slip, config.slippery_friction),
        friction)
  return DomainParams(friction=friction, mass_scale=u(k[1], config.mass_scale, (nbody,)),
                      com_offset=u(k[2], config.com_offset, (3,)), gravity=u(k[3], config.gravity),
                      joint_damping=u(k[4], config.joint_damping, (n_joints,)), joint_friction=u(
                          k[5], config.joint_friction,
                          (n_joints,)), armature=u(k[6], config.armature, (n_joints,)),
                      kp_scale=u(k[7], config.kp_scale, (n_joints,)), kd_scale=u(
                          k[8], config.kd_scale, (n_joints,)), motor_strength=jnp.ones((n_joints,)))


def apply(model: mjx.Model, params: DomainParams, dof_index: jax.Array, root_body: int,
          floor_pairs: jax.Array) -> mjx.Model:
  """The shared model with one environment's parameters written in.

  Args:
    model: the nominal MJX model.
    params: that environment's draws.
    dof_index: [n_joints] dof address of each actuated joint.
    root_body: body id of the torso (gets the CoM offset).
    floor_pairs: [n_pairs] ids of the sole-floor contact pairs (get the friction).
  """
  pair_friction = model.pair_friction.at[floor_pairs, 0].set(params.friction)
  pair_friction = pair_friction.at[floor_pairs, 1].set(params.friction)
  return model.tree_replace({
      "pair_friction": pair_friction,
      "body_mass": model.body_mass * params.mass_scale,
      "body_inertia": model.body_inertia * params.mass_scale[:, None],
      "body_ipos": model.body_ipos.at[root_body].add(params.com_offset),
      "opt.gravity": jnp.array([0.0, 0.0, -1.0]) * params.gravity,
      "dof_damping": model.dof_damping.at[dof_index].set(params.joint_damping),
      "dof_frictionloss": model.dof_frictionloss.at[dof_index].set(params.joint_friction),
      "dof_armature": model.dof_armature.at[dof_index].set(params.armature),
  })


def total_mass(model: mjx.Model, params: DomainParams) -> jax.Array:
  """Randomized total mass (kg), which the critic observes."""
  return jnp.sum(model.body_mass * params.mass_scale)


KICK_SIZE = 3  # the torso's velocity change: vx, vy (m/s, world frame) and yaw rate (rad/s)


def sample_kick(key: jax.Array, config: DomainRandConfig) -> jax.Array:
  """``[3]`` one kick: a horizontal velocity change of a size from ``kick_velocity`` in a
  direction uniform in the plane (m/s, world frame), and a yaw-rate change of a size from
  ``kick_yaw_rate`` with a random sign (rad/s)."""
  k_size, k_dir, k_yaw, k_sign = jax.random.split(key, 4)
  size = jax.random.uniform(k_size, minval=config.kick_velocity[0], maxval=config.kick_velocity[1])
  angle = jax.random.uniform(k_dir, maxval=2 * jnp.pi)
  yaw = jax.random.uniform(k_yaw, minval=config.kick_yaw_rate[0], maxval=config.kick_yaw_rate[1])
  sign = jnp.where(jax.random.bernoulli(k_sign), 1.0, -1.0)
  return jnp.stack([size * jnp.cos(angle), size * jnp.sin(angle), sign * yaw])


def kick_scale(config: DomainRandConfig, env_steps: jax.Array) -> jax.Array:
  """``[]`` the kicks' size after ``env_steps`` control steps of an env slot, as a fraction of
  full size: 0 before ``kick_ramp_start_steps``, then growing linearly to 1 over
  ``kick_ramp_steps`` (at once when that is 0)."""
  since = jnp.asarray(env_steps, jnp.float32) - config.kick_ramp_start_steps
  if config.kick_ramp_steps <= 0:
    return jnp.where(since >= 0, 1.0, 0.0)
  return jnp.clip(since / config.kick_ramp_steps, 0.0, 1.0)


def kick_interval_steps(key: jax.Array, config: DomainRandConfig, ctrl_dt: float) -> jax.Array:
  """``[]`` int32 control steps until the next kick, from ``kick_interval_s`` (at least 1)."""
  s = jax.random.uniform(key, minval=config.kick_interval_s[0], maxval=config.kick_interval_s[1])
  return jnp.maximum(1, jnp.round(s / ctrl_dt)).astype(jnp.int32)
