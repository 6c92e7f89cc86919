"""The MASH environment: one humanoid in MJX, its limbs as agents, Brax's env API.

``MashEnv.reset(key) -> State`` and ``MashEnv.step(state, action) -> State`` are pure and unbatched
(vmap them over environments). ``action`` is the flat vector of the task's controlled joints
(``agents.assemble_action`` builds it from per-agent actions). ``state.obs`` is a dict:
``{group: [n_agents, obs_dim], 'critic': [critic_obs_size]}``. The step runs the PD loop in JAX on
every physics substep, auto-resets finished episodes (``auto_reset``) and keeps the critic
observation of the terminal state in ``info['next_critic_obs']`` so time-outs can be bootstrapped.
A physics blow-up (NaN/inf in ``qpos``/``qvel``) ends the episode like a fall, with its reward,
observations and ``next_critic_obs`` zeroed and ``info['nan_reset'] = 1`` so the trainer can mask
it.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs import base as brax_base
from mujoco import mjx

from mash.sim import agents, geometry, randomize, rewards, robots, tasks
from mash.sim import layout as layout_lib
from mash.sim import model as model_lib
from mash.sim.env_config import EnvConfig, check_config, with_robot_numbers

State = brax_base.State

# Steps since the last kick stop counting here (~4 months of control steps): no int32 overflow.
_KICK_AGE_CAP = 2**28


def pd_torque(q_target: jax.Array, q: jax.Array, dq: jax.Array, kp: jax.Array, kd: jax.Array,
              tau_max: jax.Array) -> jax.Array:
  """PD torque clipped to the motor limits: clip(kp (q_target - q) - kd dq, -tau_max, tau_max).

  All arguments ``[J]`` (rad, rad/s, N m/rad, N m s/rad, N m); returns ``[J]`` (N m).
  """
  return jnp.clip(kp * (q_target - q) - kd * dq, -tau_max, tau_max)


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

  Public attributes: ``config``, ``spec``, ``layout`` (:class:`mash.sim.layout.Layout`: joint
  tables, controlled joints, agent groups, observation segments), ``agent_groups``
  (``layout.groups``), ``n_joints``, ``frame_dims``, ``critic_obs_size``, ``n_substeps``,
  ``mj_model``, ``mjx_model``; the joints' model addresses come from :meth:`joint_addresses`.
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
    self.mj_model = model_lib.build_model(spec, config.physics)
    geometry.check_mirror(self.mj_model, spec)  # references and pose mirror as the model does
    # This process's first device: MJX's default, jax.devices()[0], belongs to process 0 in a
    # multi-process run, and other processes cannot use arrays placed there.
    self.mjx_model, self._data0 = model_lib.put_physics(self.mj_model, config.physics,
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
    n_sole = len(spec.sole_points[0])
    self._soles = np.array(
        [[m.geom(f"{side}_sole_{k}").id for k in range(n_sole)] for side in ("left", "right")])
    self._floor_pairs = jnp.array([
        m.pair(f"{side}_sole_{k}_floor").id for side in ("left", "right") for k in range(n_sole)
    ])
    self._penalty_geoms = np.array([m.geom(f"{a}_penalty").id for a, _ in spec.penalized_pairs])
    self._home_qpos = jnp.array(m.key("home").qpos)
    self._phase_offset = jnp.array(lay.phase_offset)
    self._ctrl = lay.controlled
    self.agent_groups: tuple[agents.AgentGroup, ...] = lay.groups
    # One step's observation per agent (``observe``); the agents see actor_history of them.
    self.frame_dims = lay.frame_dims

    ref_scale, ref_limb = reference_scales(spec, config)
    self._ref_scale = jnp.array(ref_scale)
    self._ref_limb = ref_limb
    self._ref_is_leg = jnp.array([spec.limbs[i].group == "legs" for i in ref_limb])
    self._leg_limbs = np.array([lay.limb_index[l.name] for l in spec.limbs if l.group == "legs"])
    self._stride_gain = (jnp.asarray(geometry.stride_gains(m, spec), jnp.float32)
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
    vel = jnp.stack([
        jax.random.uniform(k[1], minval=c.vx[0], maxval=c.vx[1]),
        jax.random.uniform(k[2], minval=c.vy[0], maxval=c.vy[1]),
        jax.random.uniform(k[3], minval=c.yaw_rate[0], maxval=c.yaw_rate[1])
    ])
    return jnp.concatenate([standing[None].astype(jnp.float32), jnp.where(standing, 0.0, vel)])

  def _sample_push(self, key: jax.Array) -> jax.Array:
    """[5] force x, y (N) and torque x, y, z (N m) on the torso."""
    r = self.config.randomization
    if not r.enabled:
      return jnp.zeros((5,))
    kf, kt = jax.random.split(key)
    return jnp.concatenate([
        jax.random.uniform(kf, (2,), minval=r.push_force[0], maxval=r.push_force[1]),
        jax.random.uniform(kt, (3,), minval=r.push_torque[0], maxval=r.push_torque[1])
    ])

  def limb_phase(self, phase: jax.Array) -> jax.Array:
    """[L] temporal director T_i = sin(2 pi (phase + Delta_i)) as an angle 2 pi (phase +
    Delta_i)."""
    return 2 * jnp.pi * (phase + self._phase_offset)

  def gait(self, phase: jax.Array, standing: jax.Array, command: jax.Array | None = None,
           lin_vel: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """Reference joint offsets [J] and leg stance mask [2] for a gait phase (cycles); with
    ``config.stride_reference`` and the ``command`` [4], the legs' reference also strides at the
    commanded velocity (:meth:`stride_offsets`), or with ``config.stride_feedback`` and the
    torso's ``lin_vel`` [3] at :meth:`stride_velocity`."""
    angle = self.limb_phase(phase)
    s = jnp.sin(angle)
    leg_ref = jnp.maximum(s, 0.0)  # legs: bend only in swing (sin > 0)
    per_joint = jnp.where(self._ref_is_leg, leg_ref[self._ref_limb], s[self._ref_limb])
    q_ref = self._ref_scale * per_joint
    if self._stride_gain is not None and command is not None:
      q_ref = q_ref + self.stride_offsets(angle, self.stride_velocity(command, lin_vel))
    q_ref = q_ref * (1.0 - standing)
    stance = jnp.where(standing > 0, 1.0, (s[self._leg_limbs] < 0.1).astype(jnp.float32))
    return q_ref, stance

  def stride_velocity(self, command: jax.Array, lin_vel: jax.Array | None) -> jax.Array:
    """``[3]`` the velocity (vx, vy m/s, yaw rate rad/s, torso frame) the strides are planned at:
    the ``command`` [4]'s, its planar part moved ``config.stride_feedback`` of the way to the
    measured ``lin_vel`` [3] (none without it, or when 0)."""
    k = self.config.stride_feedback
    if k == 0 or lin_vel is None:
      return command[1:]
    return command[1:].at[:2].add(k * (lin_vel[:2] - command[1:3]))

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
        q=q,
        dq=data.qvel[self._dadr],
        quat=quat,
        euler=geometry.quat_to_euler(quat),
        ang_vel=data.qvel[3:6],  # free-joint angular velocity is already in the body frame
        lin_vel=geometry.quat_rotate_inverse(quat, data.qvel[0:3]),
        gravity=geometry.quat_rotate_inverse(quat, jnp.array([0.0, 0.0, -1.0])),
        base_height=data.qpos[2] - jnp.min(feet_height),
        feet_height=feet_height,
        feet_xy=data.xpos[self._feet][:, :2])

  def contacts(self, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
    """Foot contact mask [2] and normal force of each penalized pair [P] (N).

    A foot touches when one of its sole spheres is within 1 mm of the floor (the plane z = 0),
    read from the geometry, the sphere-plane distance of the contact list, so that both MJX
    implementations agree (Warp lists only the contacts that touch).
    """
    sole_gap = data.geom_xpos[self._soles][..., 2] - self.spec.sole_radius  # [2, n_sole] (m)
    foot = jnp.any(sole_gap < 1e-3, axis=-1)
    dist, geom1, force = model_lib.contact_rows(
        data)  # penalty pairs are condim 1: one row, the normal
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
        "last_action": a0,
        "last_last_action": a0,
        "q_target": self._q_default,
        "last_dq": jnp.zeros((self.n_joints,)),
        "last_torque": jnp.zeros((self.n_joints,)),
        "air_time": jnp.zeros((2,)),
        "last_contact": jnp.ones((2,)),
        "liftoff_xy": data.xpos[self._feet][:, :2],
        "feet_xy": jnp.zeros((2, 2)),
        "push": self._sample_push(k_push),
        **self._fresh_kick(k_push),
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
    metrics = {
        f"reward/{k}": jnp.zeros(())
        for k in rewards.TERMS
        if getattr(self.config.reward_scales, k) != 0.0
    }
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
    q_ref, stance = self.gait(info["phase"], command[0], command, s["lin_vel"])
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
        obs[group.name] = _concat(
            segments,
            dict(q=q_rel[self._ctrl], dq=s["dq"][self._ctrl], last_action=info["last_action"],
                 phase=phase_sc[acting].reshape(-1), euler=s["euler"], ang_vel=s["ang_vel"],
                 command=command))[None]
        continue
      rows = []
      for k, limb in enumerate(limbs):
        idx = lay.limb_joints[limb]
        rows.append(
            _concat(
                segments,
                dict(q=q_rel[idx], dq=s["dq"][idx], last_action=last_full[idx],
                     phase=phase_sc[lay.limb_index[limb]], euler=s["euler"], ang_vel=s["ang_vel"],
                     command=command, agent_id=jax.nn.one_hot(k, len(limbs)))))
      obs[group.name] = jnp.stack(rows)

    if cfg.critic == "local":
      rows = [
          jnp.pad(obs[g.name], ((0, 0), (0, self._local_dim - self.frame_dims[g.name])))
          for g in self.agent_groups
      ]
      obs["critic"] = jnp.concatenate(rows).reshape(-1)
      return obs

    dr = info["dr"]
    base_angle = 2 * jnp.pi * info["phase"]
    obs["critic"] = _concat(
        lay.critic,
        dict(q_rel=q_rel, dq=s["dq"], last_action=last_full, q_rel_minus_ref=q_rel - q_ref,
             phase=jnp.stack([jnp.sin(base_angle),
                              jnp.cos(base_angle)]), command=command, lin_vel=s["lin_vel"],
             euler=s["euler"], ang_vel=s["ang_vel"], push=info["push"], kick=info.get(
                 "kick", jnp.zeros((randomize.KICK_SIZE,))), friction=dr.friction[None],
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

  # ------------------------------------------------------------------------------ step stages
  def step(self, state: State, action: jax.Array) -> State:
    """One control step: act and actuate, advance the clocks, observe and reward, terminate and
    (with ``config.auto_reset``) reset a finished episode."""
    keys = _StepKeys(*jax.random.split(state.info["rng"], 5))
    push = self._next_push(state.info, keys.push)
    state, kick = self._kick(state, keys.push)
    data, torque = self._actuate(state, action, push, keys.delay)
    command, phase = self._advance_clocks(state.info, keys.command)
    s = self.sensors(data)
    contact, penalty_force = self.contacts(data)
    x = self._reward_inputs(state.info, s, action, torque, contact, penalty_force, command, phase)
    paper_terms = rewards.reward_terms(x, self.config.reward_scales, self.config.reward_params,
                                       curricula=False)
    terms = rewards.apply_curricula(paper_terms, x.env_steps, self.config.reward_params)
    if "kick_age" in kick:
      terms = rewards.kick_relief(terms, kick["kick_age"], self.config.ctrl_dt,
                                  self.config.reward_params)
    finite = jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel))
    fall, truncation = self._terminate(state.info, s, finite)
    info = self._next_info(state.info, keys.rng, s, action, torque, contact, command, phase, push,
                           fall, truncation, finite)
    info.update(kick)
    next_state = self._outcome(state, data, info, s, contact, terms, paper_terms, finite,
                               fall | truncation)
    if not self.config.auto_reset:
      return next_state
    return self.auto_reset(next_state, keys.reset)

  def _next_push(self, info: dict[str, Any], key: jax.Array) -> jax.Array:
    """``[5]`` the torso push of this step: a new one every ``push_interval_s`` (every step at 0),
    held in between."""
    push_every = max(1, int(round(self.config.randomization.push_interval_s / self.config.ctrl_dt)))
    new_push = (info["step"] + 1) % push_every == 0
    return jnp.where(new_push, self._sample_push(key), info["push"])

  def _fresh_kick(self, key: jax.Array) -> dict[str, jax.Array]:
    """A fresh episode's kick state (none without kicks): no kick yet, and the control steps
    until the first."""
    r = self.config.randomization
    if not r.kicks:
      return {}
    timer = randomize.kick_interval_steps(jax.random.fold_in(key, 2), r, self.config.ctrl_dt)
    fresh = {"kick": jnp.zeros((randomize.KICK_SIZE,)), "kick_timer": timer}
    if self.config.reward_params.kick_relief_s > 0:  # no kick yet: as if the last were long ago
      fresh["kick_age"] = jnp.asarray(_KICK_AGE_CAP, jnp.int32)
    return fresh

  def _kick(self, state: State, key: jax.Array) -> tuple[State, dict[str, jax.Array]]:
    """The torso kicked when its timer runs out: its horizontal velocity (world frame) and yaw
    rate jump by a fresh kick, and the timer restarts; returns the state to step from and the
    kick state to keep (the last kick, the steps to the next and, with
    ``reward_params.kick_relief_s``, the steps since the last kick above size 0, 0 on its
    step). Nothing without kicks."""
    r = self.config.randomization
    if not r.kicks:
      return state, {}
    k_kick, k_timer = jax.random.split(jax.random.fold_in(key, 2))  # the other streams unmoved
    now = state.info["kick_timer"] <= 1
    fresh = randomize.sample_kick(k_kick, r) * randomize.kick_scale(r, state.info["env_steps"])
    kick = jnp.where(now, fresh, state.info["kick"])
    timer = jnp.where(now, randomize.kick_interval_steps(k_timer, r, self.config.ctrl_dt),
                      state.info["kick_timer"] - 1)
    data = state.pipeline_state
    qvel = data.qvel.at[0:2].add(jnp.where(now, kick[:2],
                                           0.0)).at[5].add(jnp.where(now, kick[2], 0.0))
    kept = {"kick": kick, "kick_timer": timer}
    if "kick_age" in state.info:
      felt = now & jnp.any(fresh != 0.0)  # not the zero kicks before the kick curriculum starts
      kept["kick_age"] = jnp.where(felt, 0, jnp.minimum(state.info["kick_age"] + 1, _KICK_AGE_CAP))
    return state.replace(pipeline_state=data.replace(qvel=qvel)), kept

  def _actuate(self, state: State, action: jax.Array, push: jax.Array,
               k_delay: jax.Array) -> tuple[mjx.Data, jax.Array]:
    """The physics substeps of one control step under the PD loop; returns the MJX state reached
    and the last substep's commanded torque ``[J]`` (N m).

    A motor delay d (drawn each step, in substeps, fractional) keeps the previous target for the
    first d of the step: substep k sees a blend weighted by the part of it that lies before d,
    which is exact for the time-average of the delayed target. Torque noise, drawn anew on every
    substep, adds up to ``torque_noise`` x the limit to what the motors apply (then clipped to
    it); the rewards judge the torque the policy commanded, since noise it cannot see or control
    would otherwise dominate ``torque_rate``.
    """
    cfg, r, dr = self.config, self.config.randomization, state.info["dr"]
    model = self.model_for(dr)
    xfrc = jnp.zeros((self.mj_model.nbody,
                      6)).at[self._root].set(jnp.concatenate([push[:2],
                                                              jnp.zeros(1), push[2:]]))
    data = state.pipeline_state.replace(xfrc_applied=xfrc)
    delay = (jax.random.uniform(k_delay, minval=r.motor_delay_ms[0], maxval=r.motor_delay_ms[1]) *
             1e-3 / cfg.physics.sim_dt) if r.enabled else jnp.zeros(())
    target_new, target_old = self.joint_targets(action), state.info["q_target"]
    kp, kd = self._kp * dr.kp_scale, self._kd * dr.kd_scale
    strength = dr.motor_strength  # scales the torque the motors deliver, their limit included
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
      data = data.replace(ctrl=data.ctrl.at[self._act].set(strength * applied))
      return mjx.step(model, data), tau

    return jax.lax.fori_loop(0, self.n_substeps, substep, (data, jnp.zeros((self.n_joints,))))

  def _advance_clocks(self, info: dict[str, Any], key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The command ``[4]`` (resampled every ``commands.resample_s``) and the gait phase ``[]``
    (cycles; frozen while standing) after this step."""
    cfg = self.config
    resample_every = max(1, int(round(cfg.commands.resample_s / cfg.ctrl_dt)))
    command = jnp.where((info["step"] + 1) % resample_every == 0, self._sample_command(key),
                        info["command"])
    phase = jnp.where(command[0] > 0, info["phase"],
                      jnp.mod(info["phase"] + cfg.ctrl_dt / cfg.gait_cycle_s, 1.0))
    return command, phase

  def _reward_inputs(self, info: dict[str, Any], s: dict[str, jax.Array], action: jax.Array,
                     torque: jax.Array, contact: jax.Array, penalty_force: jax.Array,
                     command: jax.Array, phase: jax.Array) -> rewards.RewardInputs:
    """What the reward terms read of this step (:class:`mash.sim.rewards.RewardInputs`)."""
    cfg = self.config
    q_ref, stance = self.gait(phase, command[0], command, s["lin_vel"])
    feet_vel = (s["feet_xy"] - info["feet_xy"]) / cfg.ctrl_dt
    feet_vel = jnp.where(info["step"] > 0, feet_vel, 0.0)
    # Stride: where the foot landed against where a stride at the commanded velocity (with
    # stride_feedback, the stride velocity) would land.
    yaw = s["euler"][2]
    v = self.stride_velocity(command, s["lin_vel"])
    cmd_world = jnp.array([
        jnp.cos(yaw) * v[0] - jnp.sin(yaw) * v[1],
        jnp.sin(yaw) * v[0] + jnp.cos(yaw) * v[1]
    ])
    stride = s["feet_xy"] - info["liftoff_xy"]
    air_time = info["air_time"] + cfg.ctrl_dt
    return rewards.RewardInputs(
        q_rel=(s["q"] - self._q_default)[self._ctrl], q_ref=q_ref[self._ctrl], dq=s["dq"],
        last_dq=info["last_dq"], torque=torque, last_torque=info["last_torque"],
        torque_limit=self._tau_max, command=command, base_lin_vel=s["lin_vel"],
        base_ang_vel=s["ang_vel"], euler=s["euler"], gravity_proj=s["gravity"],
        base_height=s["base_height"], base_height_target=jnp.asarray(
            self.spec.base_height_target), feet_height=s["feet_height"], feet_vel=feet_vel,
        contact=contact, stance=stance, first_contact=contact * (1.0 - info["last_contact"]),
        air_time=jnp.minimum(air_time, cfg.gait_cycle_s / 2), stride_error=jnp.linalg.norm(
            stride - cmd_world * cfg.gait_cycle_s,
            axis=-1), penalty_force=penalty_force, action=action, last_action=info["last_action"],
        last_last_action=info["last_last_action"], dt=cfg.ctrl_dt, env_steps=info["env_steps"])

  def _terminate(self, info: dict[str, Any], s: dict[str, jax.Array],
                 finite: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(fall, truncation)`` ``[]`` bool: the torso fell (too low or tilted) or the physics blew
    up; the episode ran its length without a fall."""
    cfg = self.config
    fall = ((s["base_height"] < cfg.fall_height) | (jnp.abs(s["euler"][0]) > cfg.fall_tilt) |
            (jnp.abs(s["euler"][1]) > cfg.fall_tilt) | ~finite)
    truncation = (info["step"] + 1 >= cfg.episode_length) & ~fall
    return fall, truncation

  def _next_info(self, info: dict[str, Any], rng: jax.Array, s: dict[str, jax.Array],
                 action: jax.Array, torque: jax.Array, contact: jax.Array, command: jax.Array,
                 phase: jax.Array, push: jax.Array, fall: jax.Array, truncation: jax.Array,
                 finite: jax.Array) -> dict[str, Any]:
    """The env's bookkeeping after this step (the keys :meth:`reset` creates)."""
    liftoff = (1.0 - contact) * info["last_contact"]
    air_time = info["air_time"] + self.config.ctrl_dt
    return {
        **info, "rng": rng, "step": info["step"] + 1, "env_steps": info["env_steps"] + 1, "command":
            command, "phase": phase, "q_target": self.joint_targets(action), "last_action": action,
        "last_last_action": info["last_action"], "last_dq": s["dq"], "last_torque": torque,
        "air_time": air_time * (1.0 - contact), "last_contact": contact, "liftoff_xy": jnp.where(
            liftoff[:, None] > 0, s["feet_xy"],
            info["liftoff_xy"]), "feet_xy": s["feet_xy"], "push": push,
        "truncation": truncation.astype(jnp.float32), "fall": fall.astype(jnp.float32), "nan_reset":
            (~finite).astype(jnp.float32)
    }

  def _outcome(self, state: State, data: mjx.Data, info: dict[str, Any], s: dict[str, jax.Array],
               contact: jax.Array, terms: dict[str, jax.Array], paper_terms: dict[str, jax.Array],
               finite: jax.Array, done: jax.Array) -> State:
    """The state reached, before any reset. A blown-up state (NaN/inf) ends the episode and leaves
    no NaN behind: reward, reward terms, observations and the terminal critic observation are
    zeroed (NaN * 0 is NaN downstream), and ``info['nan_reset']`` tells the trainer to mask the
    transition out of its update."""
    reward = rewards.total_reward(terms, self.config.reward_params)
    paper_reward = rewards.total_reward(paper_terms, self.config.reward_params)
    obs = jax.tree.map(lambda x: jnp.where(finite, x, 0.0),
                       self.with_history(self.observe(s, info, contact), state.obs))
    info = {**info, "next_critic_obs": obs["critic"]}
    metrics = {f"reward/{k}": jnp.where(finite, v, 0.0) for k, v in terms.items()}
    metrics["paper_reward"] = jnp.where(finite, paper_reward, 0.0)
    return State(pipeline_state=data, obs=obs, reward=jnp.where(finite, reward, 0.0),
                 done=done.astype(jnp.float32), metrics=metrics, info=info)

  def auto_reset(self, state: State, key: jax.Array) -> State:
    """``state`` with a fresh episode (:meth:`reset` at the slot's curriculum clock) where it is
    done; the outcome of the step that ended it (``truncation``, ``fall``, ``nan_reset``,
    ``next_critic_obs``) stays in ``info`` for the trainer."""
    info = state.info
    fresh = self.reset(key, info["env_steps"])
    fresh.info.update(truncation=info["truncation"], fall=info["fall"], nan_reset=info["nan_reset"],
                      next_critic_obs=info["next_critic_obs"])
    done = state.done
    pick = lambda new, old: jnp.where(done > 0, new, old)
    return state.replace(
        # Data.where: Warp's contact buffer is shared by the batch, not one per env.
        pipeline_state=state.pipeline_state.where(done > 0, fresh.pipeline_state),
        obs=jax.tree.map(pick, fresh.obs, state.obs),
        info=jax.tree.map(pick, fresh.info, info))


def reference_scales(spec: robots.RobotSpec, config: EnvConfig) -> tuple[np.ndarray, np.ndarray]:
  """Per joint of ``spec.joints``, the gait reference's amplitude (rad) and the limb whose phase
  drives it: ``([J], [J] int)``. A leg joint with a role in ``spec.gait_reference`` bends with the
  swing (``swing_amplitude`` times the role's multiplier); with the task's arm swing, each arm's
  ``arm_swing_role`` joint swings against its leg. A right limb's amplitudes carry their role's
  mirror sign, so the same motion reads the same on a robot whose right joints turn the other
  way."""
  ref_scale = np.zeros(len(spec.joints))
  ref_limb = np.zeros(len(spec.joints), dtype=int)
  position = {j: i for i, j in enumerate(spec.joints)}
  arm_swing = tasks.get(config.task).arm_swing
  for i, limb in enumerate(spec.limbs):
    for j, role in zip(limb.joints, limb.roles):
      sign = spec.mirror_sign[role] if limb.side < 0 else 1.0
      if limb.group == "legs" and role in spec.gait_reference:
        ref_scale[position[j]] = sign * config.swing_amplitude * spec.gait_reference[role]
      elif limb.group == "arms" and arm_swing and role == spec.arm_swing_role:
        ref_scale[position[j]] = -sign * config.arm_swing_amplitude
      ref_limb[position[j]] = i
  return ref_scale, ref_limb


class _StepKeys(NamedTuple):
  """The random streams of one step, split from ``info['rng']`` in this order."""

  rng: jax.Array
  delay: jax.Array
  push: jax.Array
  command: jax.Array
  reset: jax.Array


def make_env(task: str = "bipedal", partition: str = "mash", **overrides: Any) -> MashEnv:
  """``MashEnv(EnvConfig(task=task, partition=partition, **overrides))``."""
  return MashEnv(EnvConfig(task=task, partition=partition, **overrides))
