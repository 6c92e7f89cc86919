"""The MASH environment: one humanoid in MJX, its limbs as agents, Brax's env API.

``MashEnv.reset(key) -> State`` and ``MashEnv.step(state, action) -> State`` are pure and unbatched
(vmap them over environments). ``action`` is the flat vector of the task's controlled joints
(``agents.assemble_action`` builds it from per-agent actions). ``state.obs`` is a dict:
``{group: [n_agents, obs_dim], 'critic': [critic_obs_size]}``. The step runs the PD loop in JAX on
every physics substep, auto-resets finished episodes (``auto_reset``) and keeps the critic
observation of the terminal state in ``info['next_critic_obs']`` so time-outs can be bootstrapped.
A physics blow-up (NaN/inf in ``qpos``/``qvel``) ends the episode like a fall, with its reward,
observations and ``next_critic_obs`` zeroed and ``info['nan_reset'] = 1`` so the trainer can mask it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs import base as brax_base
from mujoco import mjx

from mash import agents
from mash import layout as layout_lib
from mash import randomize
from mash import rewards
from mash import robots
from mash import tasks
from mash.config import check_number, check_range

State = brax_base.State

PARTITIONS = layout_lib.PARTITIONS


@dataclasses.dataclass(frozen=True)
class CommandConfig:
  """Velocity commands, resampled within episodes.

  Attributes:
    vx: forward speed range (m/s). vy: lateral (m/s). yaw_rate: (rad/s).
    standing_prob: chance a draw is the standing command (phase frozen, zero velocities).
    resample_s: seconds between draws.
  """

  vx: tuple[float, float] = (-0.3, 0.8)
  vy: tuple[float, float] = (-0.2, 0.2)
  yaw_rate: tuple[float, float] = (-0.5, 0.5)
  standing_prob: float = 0.1
  resample_s: float = 8.0


@dataclasses.dataclass(frozen=True)
class EnvConfig:
  """The task, its agents and the physics around them.

  Attributes:
    task: 'bipedal' (legs act, arms held by PD at the default pose) or 'armswing' (all limbs act).
    partition: 'mash' (one group per limb kind: legs share one actor, arms another), 'ppo' (one
      agent controls the whole body: the single-agent baseline), 'per_limb' (each limb its own group).
    robot: a shipped robot's name (``robots.names()``: the files of ``assets/robots/``) or the
      path of a robot file (``.toml``).
    ctrl_dt: control period (s); 50 Hz.
    physics: MJX solver settings.
    episode_length: control steps before time-out (20 s).
    action_scale: q_target = q_default + action_scale * action (rad).
    action_clip: |action| bound before scaling.
    gait_cycle_s: period of the temporal director (1/k in the paper's eq.).
    swing_amplitude: leg reference amplitude (rad, times the robot's gait_reference multipliers).
      None (default): the robot's (``RobotSpec.swing_amplitude``). The paper gives none; the
      T1's 0.25 makes the reference knee swing 0.5 rad, the range of the paper's hardware knee
      plot (1.2 to 1.7 rad), and lifts the swing sole 3.8 cm at its peak (kinematics;
      humanoid-gym's 0.17 lifts it 2.2 cm and, played open loop, keeps the foot on the ground
      94 % of the time). ``RewardParams.feet_height_target`` matches it.
    arm_swing_amplitude: shoulder reference amplitude (rad), armswing only; None: the robot's.
    stride_reference: (ours; off by default, the reference bends the swing leg only, whatever the
      command) add to the legs' reference the stride the commanded velocity needs: each foot
      sweeps from ahead at touchdown to behind at lift-off by ``v * gait_cycle_s / 2`` (hip
      pitch for vx, hip roll for vy, hip yaw for the yaw rate, the ankle keeping the sole level;
      ``MashEnv.stride_offsets``), so the joint-position term, the reward's largest, rewards
      walking at the command instead of taxing it.
    agent_id: append the one-hot agent id to each agent's observation (ablation switch).
    critic: 'global' (the 106-dim privileged state, MASH) or 'local' (IPPO ablation: the critic
      input is every agent's own observation, zero-padded to the largest and stacked, so a
      per-agent critic sees only its own agent).
    temporal_director: feed the gait phase to the agents (ablation switch: zeros when off).
    actor_history: control steps each agent observes (ours; the paper's actor sees 1, the
      current step). With H > 1 an agent's observation is its last H per-step observations,
      newest first (``[n_agents, H * frame]``; at reset the first frame repeated), so the shared
      actor can read its velocity and the floor's grip from how its joints moved, as
      humanoid-gym's stacked frames do. The critic is unchanged.
    fall_height: root-body height (m) under which the episode ends as a fall; None: the robot's.
    fall_tilt: |roll| or |pitch| (rad) above which the episode ends as a fall.
    commands, randomization, reward_scales, reward_params: see their classes.
    auto_reset: reset finished episodes inside ``step``.

  The sane range of every number is checked by :func:`check_config`.
  """

  task: str = "bipedal"
  partition: str = "mash"
  robot: str = "booster_t1"
  ctrl_dt: float = 0.02
  physics: robots.PhysicsConfig = robots.PhysicsConfig()
  episode_length: int = 1000
  action_scale: float = 0.25
  action_clip: float = 10.0
  gait_cycle_s: float = 0.64
  swing_amplitude: float | None = None
  arm_swing_amplitude: float | None = None
  stride_reference: bool = False
  agent_id: bool = True
  critic: str = "global"
  temporal_director: bool = True
  actor_history: int = 1
  fall_height: float | None = None
  fall_tilt: float = 1.0
  commands: CommandConfig = CommandConfig()
  randomization: randomize.DomainRandConfig = randomize.DomainRandConfig()
  reward_scales: rewards.RewardScales = rewards.RewardScales()
  reward_params: rewards.RewardParams = rewards.RewardParams()
  auto_reset: bool = True


# The sane bounds of EnvConfig's numbers: (field, lowest, highest, unit, must be above the lowest).
# ctrl_dt >= 1 ms, with at most MAX_SUBSTEPS physics steps per control step and periods of at most
# 1e5 s, keeps every step count of an episode far below int32's limit.
ENV_BOUNDS = (
    ("ctrl_dt", 1e-3, 1.0, "s", False),
    ("episode_length", 1, 2**30, "control steps", False),  # 2**30: "never" (Brax's wrapper)
    ("action_scale", 0.0, 10.0, "rad", True),
    ("action_clip", 0.0, 1e3, "", True),
    ("gait_cycle_s", 0.0, 10.0, "s", True),
    ("swing_amplitude", 0.0, np.pi, "rad", False),
    ("arm_swing_amplitude", 0.0, np.pi, "rad", False),
    ("fall_height", 0.0, 5.0, "m", False),
    ("fall_tilt", 0.0, np.pi, "rad", True),
)
MAX_ACTOR_HISTORY = 100
MAX_SUBSTEPS = 1000
MAX_COMMAND = 10.0  # m/s or rad/s
MAX_RESAMPLE_S = 1e5


def pd_torque(q_target: jax.Array, q: jax.Array, dq: jax.Array, kp: jax.Array, kd: jax.Array,
              tau_max: jax.Array) -> jax.Array:
  """PD torque clipped to the motor limits: clip(kp (q_target - q) - kd dq, -tau_max, tau_max).

  All arguments ``[J]`` (rad, rad/s, N m/rad, N m s/rad, N m); returns ``[J]`` (N m).
  """
  return jnp.clip(kp * (q_target - q) - kd * dq, -tau_max, tau_max)


def quat_to_euler(quat: jax.Array) -> jax.Array:
  """[4] (w, x, y, z) -> [3] roll, pitch, yaw (rad), ZYX convention."""
  w, x, y, z = quat[0], quat[1], quat[2], quat[3]
  roll = jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
  pitch = jnp.arcsin(jnp.clip(2 * (w * y - z * x), -1.0, 1.0))
  yaw = jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
  return jnp.stack([roll, pitch, yaw])


def quat_rotate_inverse(quat: jax.Array, vec: jax.Array) -> jax.Array:
  """Rotates a world-frame [3] vector into the frame of the [4] (w, x, y, z) quaternion."""
  w, u = quat[0], quat[1:]
  return vec * (2 * w * w - 1) - 2 * w * jnp.cross(u, vec) + 2 * u * jnp.dot(u, vec)


def check_config(config: EnvConfig, robot_given: bool = False) -> None:
  """Checks an :class:`EnvConfig` without building anything (cheap): its choices, every number
  against its sane range (``ENV_BOUNDS`` and each section's own check; NaN and inf never pass) and
  that ``physics.sim_dt`` divides ``ctrl_dt`` into at most ``MAX_SUBSTEPS`` physics steps.

  Args:
    config: the config.
    robot_given: a robot spec is passed alongside, so ``config.robot`` is not looked up.

  Raises:
    ValueError: one line naming the bad field, its value and what was expected.
  """
  for value, allowed, what in ((config.task, tasks.names(), "task"),
                               (config.partition, PARTITIONS, "partition"),
                               (config.critic, ("global", "local"), "critic")):
    if value not in allowed:
      raise ValueError(f"{what} '{value}' is unknown; expected one of {', '.join(allowed)}")
  if not robot_given:  # the whole robot file, read and checked (cheap: no model is built)
    try:
      robots.load(config.robot)
    except robots.SpecError as e:
      raise ValueError(str(e)) from None
  for name, low, high, unit, open_low in ENV_BOUNDS:
    if getattr(config, name) is not None:  # None: the robot's (with_robot_numbers)
      check_number(name, getattr(config, name), low, high, unit, open_low)
  if config.actor_history < 1:
    raise ValueError(f"actor_history must be >= 1 (control steps), got {config.actor_history}")
  check_number("actor_history", config.actor_history, 1, MAX_ACTOR_HISTORY, "control steps")
  for check, section, part in ((robots.check_physics, "physics", config.physics),
                               (check_commands, "commands", config.commands),
                               (randomize.check_config, "randomization", config.randomization),
                               (rewards.check_scales, "reward_scales", config.reward_scales),
                               (rewards.check_params, "reward_params", config.reward_params)):
    try:
      check(part)
    except ValueError as e:
      raise ValueError(f"{section}.{e}") from None
  n_sub = config.ctrl_dt / config.physics.sim_dt
  if abs(n_sub - round(n_sub)) > 1e-9 or round(n_sub) < 1:
    raise ValueError(f"ctrl_dt {config.ctrl_dt} must be a whole multiple of sim_dt "
                     f"{config.physics.sim_dt}")
  if round(n_sub) > MAX_SUBSTEPS:
    raise ValueError(f"ctrl_dt / physics.sim_dt = {config.ctrl_dt} / {config.physics.sim_dt} = "
                     f"{round(n_sub)} physics steps per control step must be at most "
                     f"{MAX_SUBSTEPS}")


def with_robot_numbers(config: EnvConfig, spec: robots.RobotSpec) -> EnvConfig:
  """``config`` with each robot-dependent number it leaves at None taken from the robot's spec:
  the fall height, the legs' and arms' swing amplitudes, the clearance target and the push
  ranges. A number the config sets (a preset, ``--set``, an older run's config.json) stays."""
  pick = lambda value, robot_value: robot_value if value is None else value
  r, p = config.randomization, config.reward_params
  return dataclasses.replace(
      config, fall_height=pick(config.fall_height, spec.fall_height),
      swing_amplitude=pick(config.swing_amplitude, spec.swing_amplitude),
      arm_swing_amplitude=pick(config.arm_swing_amplitude, spec.arm_swing_amplitude),
      randomization=dataclasses.replace(r, push_force=pick(r.push_force, spec.push_force),
                                        push_torque=pick(r.push_torque, spec.push_torque)),
      reward_params=dataclasses.replace(
          p, feet_height_target=pick(p.feet_height_target, spec.feet_height_target)))


def check_commands(commands: CommandConfig) -> None:
  """Checks a :class:`CommandConfig`: each velocity range within +-10 (m/s, rad/s) with lo <= hi,
  a probability in [0, 1], a resampling period in (0, 1e5] s.

  Raises:
    ValueError: one line naming the field, its value and what was expected.
  """
  for name, unit in (("vx", "m/s"), ("vy", "m/s"), ("yaw_rate", "rad/s")):
    check_range(name, getattr(commands, name), -MAX_COMMAND, MAX_COMMAND, unit)
  check_number("standing_prob", commands.standing_prob, 0.0, 1.0)
  check_number("resample_s", commands.resample_s, 0.0, MAX_RESAMPLE_S, "s", open_low=True)


STRIDE_ROLES = ("hip_pitch", "hip_roll", "hip_yaw", "ankle_pitch", "ankle_roll")


def stride_gains(model: mujoco.MjModel, spec: robots.RobotSpec, eps: float = 1e-3) -> np.ndarray:
  """[J, 3] joint offset per unit foot displacement x, y (m) and foot yaw (rad), torso frame, at
  the default pose: each leg's hip pitch, roll and yaw from finite differences of its foot's
  position and yaw, and its ankle pitch and roll so that the sole keeps its tilt.

  Raises:
    robots.SpecError: a leg lacks a joint of one of those roles (``STRIDE_ROLES``).
  """
  data = mujoco.MjData(model)
  home = model.key("home").qpos.copy()

  def foot_pose(limb, offsets):
    data.qpos[:] = home
    for name, delta in offsets.items():
      data.qpos[model.jnt_qposadr[model.joint(name).id]] += delta
    mujoco.mj_kinematics(model, data)
    body = spec.feet[0] if limb.side > 0 else spec.feet[1]
    mat = data.xmat[model.body(body).id].reshape(3, 3)
    pitch = -np.arcsin(np.clip(mat[2, 0], -1, 1))
    roll = np.arctan2(mat[2, 1], mat[2, 2])
    yaw = np.arctan2(mat[1, 0], mat[0, 0])
    return np.array([*data.xpos[model.body(body).id][:2], yaw, pitch, roll])

  joint_pos = {j: i for i, j in enumerate(spec.joints)}
  gain = np.zeros((len(spec.joints), 3))
  for limb in spec.limbs:
    if limb.group != "legs":
      continue
    missing = [r for r in STRIDE_ROLES if r not in limb.roles]
    if missing:
      raise robots.SpecError(f"robot '{spec.name}': leg '{limb.name}' has no joint with role "
                             f"'{missing[0]}', which the stride reference needs")
    base = foot_pose(limb, {})
    d = {r: (foot_pose(limb, {limb.joint(r): eps}) - base) / eps for r in STRIDE_ROLES}
    # axis 0 (x) -> hip pitch, 1 (y) -> hip roll, 2 (yaw) -> hip yaw; ankles undo the sole's tilt.
    for axis, hip, ankle, tilt in ((0, "hip_pitch", "ankle_pitch", 3),
                                   (1, "hip_roll", "ankle_roll", 4)):
      g = 1.0 / d[hip][axis]
      gain[joint_pos[limb.joint(hip)], axis] = g
      gain[joint_pos[limb.joint(ankle)], axis] = -g * d[hip][tilt] / d[ankle][tilt]
    gain[joint_pos[limb.joint("hip_yaw")], 2] = 1.0 / d["hip_yaw"][2]
  return gain


# MuJoCo's contact constraint types: condim 1, a pyramidal and an elliptic friction cone.
_CONTACT_ROWS = tuple(int(c) for c in (mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS,
                                        mujoco.mjtConstraint.mjCNSTR_CONTACT_PYRAMIDAL,
                                        mujoco.mjtConstraint.mjCNSTR_CONTACT_ELLIPTIC))


def put_physics(model: mujoco.MjModel, physics: robots.PhysicsConfig,
                device: jax.Device) -> tuple[mjx.Model, mjx.Data]:
  """The MJX model of ``model`` and one env's fresh MJX data, for ``physics.impl``, on ``device``.

  For Warp, the contact buffer is sized for ``physics.warp_max_envs`` envs, and Warp's report of
  a solver that used all its iterations, which ours does by choice (``physics.iterations``), is off.

  Raises:
    ValueError: impl 'warp' on a device other than a GPU or the CPU.
  """
  if physics.impl == "jax":
    mjx_model = mjx.put_model(model, impl="jax", device=device)
    return mjx_model, mjx.make_data(mjx_model, impl="jax", device=device)
  if device.platform not in ("gpu", "cpu"):
    raise ValueError(f"physics.impl 'warp' runs on an NVIDIA GPU or the CPU, not on "
                     f"{device.platform} ({device.device_kind}); use impl jax")
  import warp
  from mujoco.mjx.third_party import mujoco_warp
  warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)  # no startup banner
  mjx_model = mjx.put_model(model, impl="warp", device=device)
  opt = mjx_model.opt._impl
  quiet = opt.warn_overflow & ~(mujoco_warp.OverflowType.ITERATIONS
                                | mujoco_warp.OverflowType.LS_ITERATIONS)
  mjx_model = mjx_model.replace(opt=mjx_model.opt.replace(_impl=opt.replace(
      warn_overflow=int(quiet))))
  data = mjx.make_data(model, impl="warp", device=device,
                       naconmax=2 * model.npair * physics.warp_max_envs)
  return mjx_model, data


def contact_rows(data: mjx.Data) -> tuple[jax.Array, jax.Array, jax.Array]:
  """One env's contacts as rows ``[C]``: distance (m; +inf where a row is no contact), first geom
  id, and the force of the constraint row (N; a condim-1 contact's one row is its normal force).

  MJX keeps contacts in its implementation-specific part. The JAX implementation has one fixed
  list per env (every candidate pair, touching or not), each row the contact's first constraint
  row. MuJoCo Warp keeps one buffer for all the envs of a batch (``contact__*``), so an env finds
  its contacts from its own constraint rows (``efc__*``): touching contacts only, a contact with
  friction once per row of its cone.
  """
  impl = data._impl
  if data.impl == mjx.Impl.JAX:
    return impl.contact.dist, impl.contact.geom1, impl.efc_force[impl.contact.efc_address]
  rows = jnp.arange(impl.efc__type.shape[-1])
  is_contact = (rows < impl.nefc) & jnp.isin(impl.efc__type, jnp.array(_CONTACT_ROWS))
  con = jnp.where(is_contact, impl.efc__id, 0)
  dist = jnp.where(is_contact, impl.contact__dist[con], jnp.inf)
  return dist, impl.contact__geom[con, 0], impl.efc__force


def _concat(segments: layout_lib.Segments, values: dict[str, jax.Array]) -> jax.Array:
  """``[segments.size]``: the ``values`` of the segments' names, in their order (extra values,
  such as an agent id the config leaves out, are ignored); each must have its segment's size."""
  parts = []
  for name, size in segments.parts:
    part = jnp.reshape(values[name], (-1,))
    if part.shape != (size,):
      raise ValueError(f"observation segment '{name}' has {part.shape[0]} entries; the layout "
                       f"says {size}")
    parts.append(part)
  return jnp.concatenate(parts)


class JointAddresses(NamedTuple):
  """Model addresses of the joints, int ``[J]`` each in ``layout.joints`` order.

  Attributes:
    qpos: index of each joint's angle in ``qpos``. dof: of its velocity in ``qvel``.
    actuator: of its motor in ``ctrl``.
  """

  qpos: np.ndarray
  dof: np.ndarray
  actuator: np.ndarray


class MashEnv(brax_base.Env):
  """A humanoid whose limbs are agents (see module docstring).

  Public attributes: ``config``, ``spec``, ``layout`` (:class:`mash.layout.Layout`: joint tables,
  controlled joints, agent groups, observation segments), ``agent_groups`` (``layout.groups``),
  ``n_joints``, ``frame_dims``, ``critic_obs_size``, ``n_substeps``, ``mj_model``, ``mjx_model``;
  the joints' model addresses come from :meth:`joint_addresses`.
  """

  def __init__(self, config: EnvConfig = EnvConfig(), spec: robots.RobotSpec | None = None):
    check_config(config, robot_given=spec is not None)
    if spec is None:
      spec = robots.load(config.robot)
    config = with_robot_numbers(config, spec)
    self.config = config
    self.spec = spec
    # The joint and observation layout: pure data from the spec and the config (the MjModel below
    # adds only the addresses).
    self.layout = layout_lib.build(spec, config)
    self.n_substeps = int(round(config.ctrl_dt / config.physics.sim_dt))
    self.mj_model = robots.build_model(spec, config.physics)
    # This process's first device: MJX's default, jax.devices()[0], belongs to process 0 in a
    # multi-process run, and other processes cannot use arrays placed there.
    self.mjx_model, self._data0 = put_physics(self.mj_model, config.physics,
                                              jax.local_devices()[0])
    m = self.mj_model

    lay = self.layout
    self.n_joints = lay.n_joints
    joint_ids = [m.joint(j).id for j in lay.joints]
    self._qadr = np.array([m.jnt_qposadr[i] for i in joint_ids])
    self._dadr = np.array([m.jnt_dofadr[i] for i in joint_ids])
    self._act = np.array([m.actuator(j).id for j in lay.joints])
    self._q_default = jnp.array(lay.default_pose)
    self._kp = jnp.array(lay.kp)
    self._kd = jnp.array(lay.kd)
    self._tau_max = jnp.array(lay.torque_limit)
    self._root = m.body(spec.root_body).id
    self._feet = np.array([m.body(f).id for f in spec.feet])
    n_sole = len(spec.sole_points)
    self._soles = np.array([[m.geom(f"{side}_sole_{k}").id for k in range(n_sole)]
                            for side in ("left", "right")])
    self._floor_pairs = jnp.array([m.pair(f"{side}_sole_{k}_floor").id
                                   for side in ("left", "right") for k in range(n_sole)])
    self._penalty_geoms = np.array([m.geom(f"{a}_penalty").id for a, _ in spec.penalized_pairs])
    self._home_qpos = jnp.array(m.key("home").qpos)
    self._phase_offset = jnp.array(lay.phase_offset)
    self._ctrl = lay.controlled
    self.agent_groups: tuple[agents.AgentGroup, ...] = lay.groups
    # One step's observation per agent (``observe``); the agents see actor_history of them.
    self.frame_dims = lay.frame_dims

    # q_ref: per joint, which limb's phase drives it and with what multiplier.
    joint_pos = {j: i for i, j in enumerate(lay.joints)}
    ref_scale = np.zeros(self.n_joints)
    ref_limb = np.zeros(self.n_joints, dtype=int)
    arm_swing = tasks.get(config.task).arm_swing
    for i, limb in enumerate(spec.limbs):
      for j, role in zip(limb.joints, limb.roles):
        if limb.group == "legs" and role in spec.gait_reference:
          ref_scale[joint_pos[j]] = config.swing_amplitude * spec.gait_reference[role]
        elif limb.group == "arms" and arm_swing and role == spec.arm_swing_role:
          ref_scale[joint_pos[j]] = -config.arm_swing_amplitude
        ref_limb[joint_pos[j]] = i
    self._ref_scale = jnp.array(ref_scale)
    self._ref_limb = ref_limb
    self._ref_is_leg = jnp.array([spec.limbs[i].group == "legs" for i in ref_limb])
    self._leg_limbs = np.array([lay.limb_index[l.name] for l in spec.limbs if l.group == "legs"])
    self._stride_gain = (jnp.asarray(stride_gains(m, spec), jnp.float32)
                         if config.stride_reference else None)
    self._local_dim = max(self.frame_dims.values())
    self.critic_obs_size = lay.critic.size
    self._nominal_mass = float(np.sum(m.body_mass))
    # The robot's joint model (its file's numbers or the MJCF's), which DR off keeps.
    self._joint_nominal = randomize.JointNominal(
        damping=np.asarray(m.dof_damping[self._dadr], np.float32),
        friction=np.asarray(m.dof_frictionloss[self._dadr], np.float32),
        armature=np.asarray(m.dof_armature[self._dadr], np.float32))

  # ----------------------------------------------------------------------------------- Brax API
  @property
  def action_size(self) -> int:
    return len(self._ctrl)

  @property
  def observation_size(self) -> dict[str, tuple[int, ...]]:
    return self.layout.observation_size

  @property
  def backend(self) -> str:
    return "mjx"

  @property
  def dt(self) -> float:
    return self.config.ctrl_dt

  def nominal_domain(self) -> randomize.DomainParams:
    """The un-randomized robot's parameters (randomization off), with its own joint model."""
    return randomize.nominal(self.mj_model.nbody, self.n_joints, joints=self._joint_nominal)

  # ------------------------------------------------------------------------------------ helpers
  def model_for(self, params: randomize.DomainParams) -> mjx.Model:
    """The MJX model with one environment's randomized parameters."""
    return randomize.apply(self.mjx_model, params, jnp.asarray(self._dadr), self._root,
                           self._floor_pairs)

  def _sample_command(self, key: jax.Array) -> jax.Array:
    c = self.config.commands
    k = jax.random.split(key, 4)
    standing = jax.random.uniform(k[0]) < c.standing_prob
    vel = jnp.stack([jax.random.uniform(k[1], minval=c.vx[0], maxval=c.vx[1]),
                     jax.random.uniform(k[2], minval=c.vy[0], maxval=c.vy[1]),
                     jax.random.uniform(k[3], minval=c.yaw_rate[0], maxval=c.yaw_rate[1])])
    return jnp.concatenate([standing[None].astype(jnp.float32), jnp.where(standing, 0.0, vel)])

  def _sample_push(self, key: jax.Array) -> jax.Array:
    """[5] force x, y (N) and torque x, y, z (N m) on the torso."""
    r = self.config.randomization
    if not r.enabled:
      return jnp.zeros((5,))
    kf, kt = jax.random.split(key)
    return jnp.concatenate([
        jax.random.uniform(kf, (2,), minval=r.push_force[0], maxval=r.push_force[1]),
        jax.random.uniform(kt, (3,), minval=r.push_torque[0], maxval=r.push_torque[1])])

  def limb_phase(self, phase: jax.Array) -> jax.Array:
    """[L] temporal director T_i = sin(2 pi (phase + Delta_i)) as an angle 2 pi (phase + Delta_i)."""
    return 2 * jnp.pi * (phase + self._phase_offset)

  def gait(self, phase: jax.Array, standing: jax.Array,
           command: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """Reference joint offsets [J] and leg stance mask [2] for a gait phase (cycles); with
    ``config.stride_reference`` and the ``command`` [4], the legs' reference also strides at the
    commanded velocity (:meth:`stride_offsets`)."""
    angle = self.limb_phase(phase)
    s = jnp.sin(angle)
    leg_ref = jnp.maximum(s, 0.0)  # legs: bend only in swing (sin > 0)
    per_joint = jnp.where(self._ref_is_leg, leg_ref[self._ref_limb], s[self._ref_limb])
    q_ref = self._ref_scale * per_joint
    if self._stride_gain is not None and command is not None:
      q_ref = q_ref + self.stride_offsets(angle, command[1:])
    q_ref = q_ref * (1.0 - standing)
    stance = jnp.where(standing > 0, 1.0, (s[self._leg_limbs] < 0.1).astype(jnp.float32))
    return q_ref, stance

  def stride_offsets(self, angle: jax.Array, velocity: jax.Array) -> jax.Array:
    """[J] leg joint offsets that carry each foot through a stride at ``velocity`` [3] (vx, vy m/s,
    yaw rate rad/s, torso frame), for the limbs' phase angles ``angle`` [L].

    A stance foot is fixed on the floor while the torso moves ``velocity * gait_cycle_s / 2``
    over the half cycle of stance, so relative to the torso the foot goes from half that ahead at
    touchdown (angle pi) to half behind at lift-off (angle 0) and back during the swing:
    ``-cos(angle) * velocity * gait_cycle_s / 4``, turned into hip pitch / roll / yaw offsets by
    the leg's kinematics at the default pose, with the ankle keeping the sole level.
    """
    reach = -jnp.cos(angle)[:, None] * velocity * (self.config.gait_cycle_s / 4.0)  # [L, 3]
    return jnp.sum(self._stride_gain * reach[self._ref_limb], axis=-1)

  def sensors(self, data: mjx.Data) -> dict[str, jax.Array]:
    """Torso and joint quantities read from the MJX state."""
    quat = data.qpos[3:7]
    q = data.qpos[self._qadr]
    sole_z = data.geom_xpos[self._soles][..., 2] - self.spec.sole_radius  # [2, n_sole]
    feet_height = jnp.min(sole_z, axis=-1)
    return dict(
        q=q, dq=data.qvel[self._dadr], quat=quat, euler=quat_to_euler(quat),
        ang_vel=data.qvel[3:6],  # free-joint angular velocity is already in the body frame
        lin_vel=quat_rotate_inverse(quat, data.qvel[0:3]),
        gravity=quat_rotate_inverse(quat, jnp.array([0.0, 0.0, -1.0])),
        base_height=data.qpos[2] - jnp.min(feet_height), feet_height=feet_height,
        feet_xy=data.xpos[self._feet][:, :2])

  def contacts(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
    """Foot contact mask [2] and normal force of each penalized pair [P] (N).

    A foot touches when one of its sole spheres is within 1 mm of the floor (the plane z = 0),
    read from the geometry, the sphere-plane distance of the contact list, so that both MJX
    implementations agree (Warp lists only the contacts that touch).
    """
    sole_gap = data.geom_xpos[self._soles][..., 2] - self.spec.sole_radius  # [2, n_sole] (m)
    foot = jnp.any(sole_gap < 1e-3, axis=-1)
    dist, geom1, force = contact_rows(data)  # penalty pairs are condim 1: one row, the normal
    is_pair = geom1[:, None] == self._penalty_geoms[None, :]
    penalty = jnp.sum(jnp.where(is_pair & (dist < 0)[:, None], force[:, None], 0.0), 0)
    return foot.astype(jnp.float32), penalty

  def joint_addresses(self) -> JointAddresses:
    """Where the joints of ``layout.joints`` live in the MjModel (``mj_model``, native MuJoCo or
    MJX): their ``qpos``, ``qvel`` and ``ctrl`` indices."""
    return JointAddresses(self._qadr.copy(), self._dadr.copy(), self._act.copy())

  def initial_data(self) -> mjx.Data:
    """The MJX state of one env at the home pose, at rest."""
    return self._data0.replace(qpos=self._home_qpos)

  def joint_targets(self, action: jax.Array) -> jax.Array:
    """``[J]`` PD targets (rad) from the flat ``action [A]``: controlled joints at
    ``default + action_scale * clip(action, -action_clip, action_clip)``, held joints at default."""
    scaled = self.config.action_scale * jnp.clip(action, -self.config.action_clip,
                                                 self.config.action_clip)
    return self._q_default.at[self._ctrl].add(scaled)

  # --------------------------------------------------------------------------------- reset/step
  def reset(self, rng: jax.Array, env_steps: jax.Array | int = 0,
            command: jax.Array | None = None) -> State:
    """A fresh episode in an env slot that has run ``env_steps`` control steps (``[]`` int; the
    curricula's clock, e.g. the friction range it draws from; 0 for a fresh run). ``command``
    ``[4]`` (standing flag, vx, vy, yaw rate) starts the episode on that command instead of one
    drawn from ``config.commands`` (evaluation grids); it is still resampled every
    ``commands.resample_s``."""
    env_steps = jnp.asarray(env_steps, jnp.int32)
    k_dr, k_cmd, k_push, k_phase, rng = jax.random.split(rng, 5)
    dr = randomize.sample(k_dr, self.config.randomization, self.mj_model.nbody, self.n_joints,
                          env_steps, self._joint_nominal)
    data = self.initial_data()
    if command is None:
      command = self._sample_command(k_cmd)
    else:
      command = jnp.asarray(command, jnp.float32).reshape(4)
    a0 = jnp.zeros((self.action_size,))
    info: dict[str, Any] = {
        "rng": rng,
        "step": jnp.zeros((), jnp.int32),
        "env_steps": env_steps,
        "command": command,
        "phase": jax.random.uniform(k_phase) * (1.0 - command[0]),
        "last_action": a0, "last_last_action": a0,
        "q_target": self._q_default,
        "last_dq": jnp.zeros((self.n_joints,)),
        "last_torque": jnp.zeros((self.n_joints,)),
        "air_time": jnp.zeros((2,)),
        "last_contact": jnp.ones((2,)),
        "liftoff_xy": data.xpos[self._feet][:, :2],
        "feet_xy": jnp.zeros((2, 2)),
        "push": self._sample_push(k_push),
        "dr": dr,
        "truncation": jnp.zeros(()),
        "fall": jnp.zeros(()),
        "nan_reset": jnp.zeros(()),
    }
    sensors = self.sensors(data)
    sensors["base_height"] = jnp.asarray(self.spec.base_height_target)
    contact = jnp.ones((2,))
    obs = self.with_history(self.observe(sensors, info, contact), None)
    info["next_critic_obs"] = obs["critic"]
    metrics = {f"reward/{k}": jnp.zeros(()) for k in rewards.TERMS
               if getattr(self.config.reward_scales, k) != 0.0}
    metrics["paper_reward"] = jnp.zeros(())
    zero = jnp.zeros(())
    return State(pipeline_state=data, obs=obs, reward=zero, done=zero, metrics=metrics, info=info)

  def observe(self, s: dict[str, jax.Array], info: dict[str, Any],
               contact: jax.Array) -> dict[str, jax.Array]:
    """Agent observations per group ``{group: [n_agents, frame]}`` and the critic observation
    ``[critic size]``, each agent row and the critic laid out as ``layout.actor[group]`` and
    ``layout.critic`` say (one step: :meth:`with_history` stacks the agents' frames)."""
    cfg = self.config
    command = info["command"]
    q_ref, stance = self.gait(info["phase"], command[0], command)
    angle = self.limb_phase(info["phase"])
    phase_sc = jnp.stack([jnp.sin(angle), jnp.cos(angle)], axis=-1)  # [L, 2]
    if not cfg.temporal_director:
      phase_sc = jnp.zeros_like(phase_sc)
    q_rel = s["q"] - self._q_default
    last_full = jnp.zeros((self.n_joints,)).at[self._ctrl].set(info["last_action"])

    obs = {}
    lay = self.layout
    for group in self.agent_groups:
      limbs = lay.group_limbs[group.name]
      segments = lay.actor[group.name]
      if group.name == layout_lib.BODY:
        acting = np.array([lay.limb_index[l] for l in limbs])
        obs[group.name] = _concat(segments, dict(
            q=q_rel[self._ctrl], dq=s["dq"][self._ctrl], last_action=info["last_action"],
            phase=phase_sc[acting].reshape(-1), euler=s["euler"], ang_vel=s["ang_vel"],
            command=command))[None]
        continue
      rows = []
      for k, limb in enumerate(limbs):
        idx = lay.limb_joints[limb]
        rows.append(_concat(segments, dict(
            q=q_rel[idx], dq=s["dq"][idx], last_action=last_full[idx],
            phase=phase_sc[lay.limb_index[limb]], euler=s["euler"], ang_vel=s["ang_vel"],
            command=command, agent_id=jax.nn.one_hot(k, len(limbs)))))
      obs[group.name] = jnp.stack(rows)

    if cfg.critic == "local":
      rows = [jnp.pad(obs[g.name], ((0, 0), (0, self._local_dim - self.frame_dims[g.name])))
              for g in self.agent_groups]
      obs["critic"] = jnp.concatenate(rows).reshape(-1)
      return obs

    dr = info["dr"]
    base_angle = 2 * jnp.pi * info["phase"]
    obs["critic"] = _concat(lay.critic, dict(
        q_rel=q_rel, dq=s["dq"], last_action=last_full, q_rel_minus_ref=q_rel - q_ref,
        phase=jnp.stack([jnp.sin(base_angle), jnp.cos(base_angle)]), command=command,
        lin_vel=s["lin_vel"], euler=s["euler"], ang_vel=s["ang_vel"], push=info["push"],
        friction=dr.friction[None],
        mass_offset=randomize.total_mass(self.mjx_model, dr)[None] - self._nominal_mass,
        stance=stance, contact=contact))
    return obs

  def with_history(self, frames: dict[str, jax.Array],
                   previous: dict[str, jax.Array] | None) -> dict[str, jax.Array]:
    """The agents' observations from this step's ``frames`` (``observe``) and the ``previous``
    step's observations (None at reset): ``{group: [n_agents, H * frame]}``, newest first, the
    oldest frame dropped; at reset the frame repeated H times. The critic's is ``frames``'."""
    h = self.config.actor_history
    if h == 1:
      return frames
    obs = dict(frames)
    for g in self.agent_groups:
      frame = frames[g.name]
      if previous is None:
        obs[g.name] = jnp.tile(frame, (1, h))
      else:
        kept = previous[g.name][:, :self.frame_dims[g.name] * (h - 1)]
        obs[g.name] = jnp.concatenate([frame, kept], axis=-1)
    return obs

  def step(self, state: State, action: jax.Array) -> State:
    cfg = self.config
    info = dict(state.info)
    rng, k_delay, k_push, k_cmd, k_reset = jax.random.split(info["rng"], 5)
    dr = info["dr"]
    model = self.model_for(dr)

    # Pushes: a new one every push_interval_s (every step at 0), held in between.
    push_every = max(1, int(round(cfg.randomization.push_interval_s / cfg.ctrl_dt)))
    new_push = (info["step"] + 1) % push_every == 0
    push = jnp.where(new_push, self._sample_push(k_push), info["push"])
    xfrc = jnp.zeros((self.mj_model.nbody, 6)).at[self._root].set(
        jnp.concatenate([push[:2], jnp.zeros(1), push[2:]]))
    data = state.pipeline_state.replace(xfrc_applied=xfrc)

    # PD loop on every substep. A motor delay d (drawn each step, in substeps, fractional) keeps the
    # previous target for the first d of the step: substep k sees a blend weighted by the part of
    # it that lies before d, which is exact for the time-average of the delayed target.
    r = cfg.randomization
    delay = (jax.random.uniform(k_delay, minval=r.motor_delay_ms[0], maxval=r.motor_delay_ms[1])
             * 1e-3 / cfg.physics.sim_dt) if r.enabled else jnp.zeros(())
    target_new = self.joint_targets(action)
    target_old = info["q_target"]
    kp, kd = self._kp * dr.kp_scale, self._kd * dr.kd_scale

    # Torque noise, drawn anew on every substep: the motors apply the PD torque plus a uniform
    # error of up to torque_noise x their limit (then clipped to it). The rewards judge the torque
    # the policy commanded: noise it cannot see or control would otherwise dominate torque_rate.
    noise_scale = r.torque_noise * self._tau_max if r.enabled and r.torque_noise > 0 else None
    k_noise = jax.random.fold_in(k_delay, 1)  # leaves every other random stream as it was

    def substep(k, carry):
      data, _ = carry
      w_old = jnp.clip(delay - k, 0.0, 1.0)
      target = w_old * target_old + (1.0 - w_old) * target_new
      tau = pd_torque(target, data.qpos[self._qadr], data.qvel[self._dadr], kp, kd, self._tau_max)
      applied = tau
      if noise_scale is not None:
        noise = jax.random.uniform(jax.random.fold_in(k_noise, k), tau.shape, minval=-1.0,
                                   maxval=1.0) * noise_scale
        applied = jnp.clip(tau + noise, -self._tau_max, self._tau_max)
      data = data.replace(ctrl=data.ctrl.at[self._act].set(applied))
      return mjx.step(model, data), tau

    data, torque = jax.lax.fori_loop(0, self.n_substeps, substep,
                                     (data, jnp.zeros((self.n_joints,))))

    # Gait clock, command resampling.
    command = info["command"]
    resample_every = max(1, int(round(cfg.commands.resample_s / cfg.ctrl_dt)))
    step_count = info["step"] + 1
    command = jnp.where(step_count % resample_every == 0, self._sample_command(k_cmd), command)
    phase = jnp.where(command[0] > 0, info["phase"],
                      jnp.mod(info["phase"] + cfg.ctrl_dt / cfg.gait_cycle_s, 1.0))

    s = self.sensors(data)
    contact, penalty_force = self.contacts(data)
    q_ref, stance = self.gait(phase, command[0], command)
    first_contact = contact * (1.0 - info["last_contact"])
    air_time = info["air_time"] + cfg.ctrl_dt
    feet_vel = (s["feet_xy"] - info["feet_xy"]) / cfg.ctrl_dt
    feet_vel = jnp.where(state.info["step"] > 0, feet_vel, 0.0)
    # Stride: where the foot landed against where a stride at the commanded velocity would land.
    yaw = s["euler"][2]
    cmd_world = jnp.array([jnp.cos(yaw) * command[1] - jnp.sin(yaw) * command[2],
                           jnp.sin(yaw) * command[1] + jnp.cos(yaw) * command[2]])
    stride = s["feet_xy"] - info["liftoff_xy"]
    stride_error = jnp.linalg.norm(stride - cmd_world * cfg.gait_cycle_s, axis=-1)
    liftoff = (1.0 - contact) * info["last_contact"]

    x = rewards.RewardInputs(
        q_rel=(s["q"] - self._q_default)[self._ctrl], q_ref=q_ref[self._ctrl], dq=s["dq"],
        last_dq=info["last_dq"], torque=torque, last_torque=info["last_torque"],
        torque_limit=self._tau_max, command=command, base_lin_vel=s["lin_vel"],
        base_ang_vel=s["ang_vel"], euler=s["euler"], gravity_proj=s["gravity"],
        base_height=s["base_height"], base_height_target=jnp.asarray(self.spec.base_height_target),
        feet_height=s["feet_height"], feet_vel=feet_vel, contact=contact, stance=stance,
        first_contact=first_contact, air_time=jnp.minimum(air_time, cfg.gait_cycle_s / 2),
        stride_error=stride_error, penalty_force=penalty_force, action=action,
        last_action=info["last_action"], last_last_action=info["last_last_action"],
        dt=cfg.ctrl_dt, env_steps=info["env_steps"])
    paper_terms = rewards.reward_terms(x, cfg.reward_scales, cfg.reward_params, curricula=False)
    terms = rewards.apply_curricula(paper_terms, x.env_steps, cfg.reward_params)
    reward = rewards.total_reward(terms, cfg.reward_params)
    paper_reward = rewards.total_reward(paper_terms, cfg.reward_params)

    finite = jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel))
    fall = ((s["base_height"] < cfg.fall_height) | (jnp.abs(s["euler"][0]) > cfg.fall_tilt)
            | (jnp.abs(s["euler"][1]) > cfg.fall_tilt) | ~finite)
    truncation = (step_count >= cfg.episode_length) & ~fall
    done = (fall | truncation).astype(jnp.float32)

    info.update(
        rng=rng, step=step_count, env_steps=info["env_steps"] + 1, command=command, phase=phase,
        q_target=target_new, last_action=action, last_last_action=info["last_action"],
        last_dq=s["dq"], last_torque=torque, air_time=air_time * (1.0 - contact),
        last_contact=contact,
        liftoff_xy=jnp.where(liftoff[:, None] > 0, s["feet_xy"], info["liftoff_xy"]),
        feet_xy=s["feet_xy"], push=push, truncation=truncation.astype(jnp.float32),
        fall=fall.astype(jnp.float32), nan_reset=(~finite).astype(jnp.float32))
    # A blown-up state (NaN/inf) ends the episode and leaves no NaN behind: reward, reward terms,
    # observations and the terminal critic observation are zeroed (NaN * 0 is NaN downstream), and
    # info['nan_reset'] tells the trainer to mask the transition out of its update.
    obs = jax.tree.map(lambda x: jnp.where(finite, x, 0.0),
                       self.with_history(self.observe(s, info, contact), state.obs))
    info["next_critic_obs"] = obs["critic"]
    reward = jnp.where(finite, reward, 0.0)
    metrics = {f"reward/{k}": jnp.where(finite, v, 0.0) for k, v in terms.items()}
    metrics["paper_reward"] = jnp.where(finite, paper_reward, 0.0)
    next_state = State(pipeline_state=data, obs=obs, reward=reward, done=done, metrics=metrics,
                       info=info)
    if not cfg.auto_reset:
      return next_state
    fresh = self.reset(k_reset, info["env_steps"])
    fresh.info.update(truncation=info["truncation"], fall=info["fall"],
                      nan_reset=info["nan_reset"], next_critic_obs=info["next_critic_obs"])
    pick = lambda new, old: jnp.where(done > 0, new, old)
    return next_state.replace(
        # Data.where: Warp's contact buffer is shared by the batch, not one per env.
        pipeline_state=data.where(done > 0, fresh.pipeline_state),
        obs=jax.tree.map(pick, fresh.obs, obs),
        info=jax.tree.map(pick, fresh.info, info))


def make_env(task: str = "bipedal", partition: str = "mash", **overrides: Any) -> MashEnv:
  """``MashEnv(EnvConfig(task=task, partition=partition, **overrides))``."""
  return MashEnv(EnvConfig(task=task, partition=partition, **overrides))
