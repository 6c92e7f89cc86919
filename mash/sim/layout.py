"""The joint and observation layout of a MASH env as plain data, from a robot spec and the env
config alone (no MjModel): joint tables, controlled joints, limbs and their gait-phase offsets,
the agent groups, and every observation as an ordered tuple of named segments.

``MashEnv`` builds its observations in the order given here and exposes the layout as
``env.layout``; the ONNX export, the evaluation and the experiments read these tables instead of
the env's internals. Sizes are computed from the segments, never summed by hand::

  lay = layout.build(robots.load("booster_t1"), EnvConfig(task="armswing"))
  lay.actor["legs"].slice("q")        # slice(0, 6): a leg's joint angles minus the default pose
  lay.actor["arms"].size              # 26: one control step of one arm agent
  lay.critic.offset("command")        # 82
  lay.critic.size                     # 106
  lay.default_pose[lay.controlled]    # [A] default angles of the controlled joints (rad)
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, NamedTuple

import numpy as np

from mash.checks import check_number
from mash.sim import agents, robots, tasks
from mash.sim.env_config import CRITICS, MAX_ACTOR_HISTORY, PARTITIONS, EnvConfig

COMMAND_SIZE = 4  # standing flag (0/1), vx (m/s), vy (m/s), yaw rate (rad/s)
PUSH_SIZE = 5  # force x, y (N) and torque x, y, z (N m) on the torso
KICK_SIZE = 3  # the last kick's velocity change: vx, vy (m/s, world frame), yaw rate (rad/s)
BODY = "body"  # the one group (and agent) of the 'ppo' partition


class Segment(NamedTuple):
  """One named, contiguous part of an observation vector: ``size`` entries."""

  name: str
  size: int


@dataclasses.dataclass(frozen=True)
class Segments:
  """An observation vector as consecutive named segments, in order, without gaps.

  Attributes:
    parts: the segments, first to last; names are unique, sizes >= 1.
  """

  parts: tuple[Segment, ...]

  def __post_init__(self):
    names = [p.name for p in self.parts]
    if len(set(names)) != len(names):
      raise ValueError(f"segment names {names} are not unique")
    for p in self.parts:
      if int(p.size) < 1:
        raise ValueError(f"segment '{p.name}' has size {p.size}; expected >= 1")

  @property
  def names(self) -> tuple[str, ...]:
    return tuple(p.name for p in self.parts)

  @property
  def size(self) -> int:
    """Total size: the sum of the segments' sizes."""
    return sum(p.size for p in self.parts)

  def offsets(self) -> dict[str, tuple[int, int]]:
    """``{name: (start, stop)}`` of every segment, in order."""
    out, start = {}, 0
    for p in self.parts:
      out[p.name] = (start, start + p.size)
      start += p.size
    return out

  def offset(self, name: str) -> int:
    """Where segment ``name`` starts (KeyError if there is none)."""
    return self.offsets()[name][0]

  def slice(self, name: str) -> slice:
    """``obs[..., segments.slice(name)]`` is segment ``name`` of ``obs [..., size]``."""
    return slice(*self.offsets()[name])

  def split(self, obs: Any) -> dict[str, Any]:
    """``obs [..., size]`` (numpy or JAX) -> ``{name: obs[..., start:stop]}``."""
    if obs.shape[-1] != self.size:
      raise ValueError(f"observation of size {obs.shape[-1]}; the segments hold {self.size}")
    return {name: obs[..., start:stop] for name, (start, stop) in self.offsets().items()}


@dataclasses.dataclass(frozen=True, eq=False)
class Layout:
  """Where every joint, action and observation entry of one env configuration lives.

  Joint-indexed arrays are ``[J]`` in ``joints`` order (``spec.joints``: limb by limb, legs
  first); "positions" index into that order. The arrays are read-only.

  Attributes:
    joints: the J actuated joint names.
    default_pose: ``[J]`` default angles (rad, float64); q_target = default + action_scale * a.
    kp: ``[J]`` PD stiffness (N m/rad). kd: ``[J]`` PD damping (N m s/rad).
    torque_limit: ``[J]`` |tau| bound (N m).
    limbs: the L limb names, spec order (the order of ``phase_offset``).
    limb_index: limb name -> its position in ``limbs``.
    limb_joints: limb name -> int ``[n]`` positions of its joints, in the order it sees them.
    phase_offset: ``[L]`` temporal-director offsets (cycles): legs 0 (left) / 0.5 (right), each
      arm with the opposite leg (left arm 0.5, right arm 0).
    controlled: int ``[A]`` positions of the controlled joints, in flat action order.
    groups: the agent groups (``obs_dim`` counts ``actor_history`` frames).
    group_limbs: group name -> names of its acting limbs (one per agent; the 'body' group's one
      agent acts for all of them).
    actor: group name -> the segments of one control step's observation of one of its agents.
    actor_history: control steps each agent observes (its observation is that many frames of
      ``actor[group]``, newest first).
    critic: the segments of the critic observation.
  """

  joints: tuple[str, ...]
  default_pose: np.ndarray
  kp: np.ndarray
  kd: np.ndarray
  torque_limit: np.ndarray
  limbs: tuple[str, ...]
  limb_index: Mapping[str, int]
  limb_joints: Mapping[str, np.ndarray]
  phase_offset: np.ndarray
  controlled: np.ndarray
  groups: tuple[agents.AgentGroup, ...]
  group_limbs: Mapping[str, tuple[str, ...]]
  actor: Mapping[str, Segments]
  actor_history: int
  critic: Segments

  @property
  def n_joints(self) -> int:
    return len(self.joints)

  @property
  def n_actions(self) -> int:
    return len(self.controlled)

  @property
  def n_limbs(self) -> int:
    return len(self.limbs)

  @property
  def frame_dims(self) -> dict[str, int]:
    """``{group: size of one control step's observation of one agent}``."""
    return {g.name: self.actor[g.name].size for g in self.groups}

  @property
  def observation_size(self) -> dict[str, tuple[int, ...]]:
    """``{group: (n_agents, obs_dim), 'critic': (critic size,)}``, as ``MashEnv`` reports it."""
    sizes = {g.name: (g.n_agents, g.obs_dim) for g in self.groups}
    sizes["critic"] = (self.critic.size,)
    return sizes

  def group(self, name: str) -> agents.AgentGroup:
    """The agent group called ``name`` (KeyError if there is none)."""
    for g in self.groups:
      if g.name == name:
        return g
    raise KeyError(name)


def phase_offset(limb: robots.Limb) -> float:
  """A limb's temporal-director offset (cycles): legs 0 (left) / 0.5 (right); each arm swings with
  the opposite leg."""
  if limb.group == "arms":
    return 0.5 if limb.side > 0 else 0.0
  return 0.0 if limb.side > 0 else 0.5


def acting_groups(spec: robots.RobotSpec,
                  config: EnvConfig) -> tuple[tuple[str, tuple[robots.Limb, ...]], ...]:
  """Which limbs act, and how they are grouped into shared-actor agent groups:
  ``((group name, its limbs), ...)``."""
  kinds = tasks.get(config.task).acting
  missing = [k for k in kinds if not spec.limbs_of(k)]
  if missing:
    raise robots.SpecError(f"task '{config.task}' needs limb group '{missing[0]}', which robot "
                           f"'{spec.name}' does not have (its groups: "
                           f"{', '.join(dict.fromkeys(l.group for l in spec.limbs))})")
  acting = tuple(l for l in spec.limbs if l.group in kinds)
  if config.partition == "mash":
    return tuple((k, spec.limbs_of(k)) for k in kinds)
  if config.partition == "per_limb":
    return tuple((l.name, (l,)) for l in acting)
  return ((BODY, acting),)


def actor_segments(n_joints: int, n_last_action: int, n_phase_limbs: int,
                   n_agent_id: int) -> Segments:
  """One agent's one-step observation: its joints' angles minus the default pose, velocities and
  last actions, the sin/cos gait phase of each limb it acts for (pairs, limb by limb; zeros with the
  temporal director off), torso euler and angular velocity, the command, and (``n_agent_id`` > 0)
  its one-hot id."""
  parts = [
      Segment("q", n_joints),
      Segment("dq", n_joints),
      Segment("last_action", n_last_action),
      Segment("phase", 2 * n_phase_limbs),
      Segment("euler", 3),
      Segment("ang_vel", 3),
      Segment("command", COMMAND_SIZE)
  ]
  if n_agent_id:
    parts.append(Segment("agent_id", n_agent_id))
  return Segments(tuple(parts))


def critic_segments(n_joints: int, n_legs: int, n_feet: int, kicks: bool = False) -> Segments:
  """The global (privileged) critic observation: joint angles minus the default pose, velocities,
  last actions of every joint (0 where not controlled), angle error to the gait reference
  ``q_rel - q_ref``, the base gait phase's sin/cos, the command, torso linear velocity (torso
  frame), euler and angular velocity, the push, with ``kicks`` the last velocity kick, floor
  friction, total mass minus nominal (kg), the legs' reference stance mask and the feet's contact
  mask."""
  kick = (Segment("kick", KICK_SIZE),) if kicks else ()
  return Segments((Segment("q_rel", n_joints), Segment("dq", n_joints),
                   Segment("last_action", n_joints), Segment("q_rel_minus_ref", n_joints),
                   Segment("phase", 2), Segment("command", COMMAND_SIZE), Segment("lin_vel", 3),
                   Segment("euler", 3), Segment("ang_vel", 3), Segment("push", PUSH_SIZE), *kick,
                   Segment("friction", 1), Segment("mass_offset", 1), Segment("stance", n_legs),
                   Segment("contact", n_feet)))


def _frozen(x: Any, dtype: Any) -> np.ndarray:
  out = np.array(x, dtype)
  out.setflags(write=False)
  return out


def build(spec: robots.RobotSpec, config: EnvConfig) -> Layout:
  """The layout of ``spec`` under ``config`` (an ``EnvConfig``; reads its task, partition,
  agent_id, temporal_director, actor_history and critic).

  Raises:
    ValueError: an unknown task, partition or critic, or actor_history < 1.
    robots.SpecError: the limbs of one group have different joint counts (one actor cannot
      serve them).
  """
  for value, allowed, what in ((config.task, tasks.names(), "task"),
                               (config.partition, PARTITIONS, "partition"), (config.critic, CRITICS,
                                                                             "critic")):
    if value not in allowed:
      raise ValueError(f"{what} '{value}' is unknown; expected one of {', '.join(allowed)}")
  check_number("actor_history", config.actor_history, 1, MAX_ACTOR_HISTORY, "control steps")
  joints = spec.joints
  position = {j: i for i, j in enumerate(joints)}
  limb_index = {l.name: i for i, l in enumerate(spec.limbs)}
  limb_joints = {l.name: _frozen([position[j] for j in l.joints], np.int64) for l in spec.limbs}

  grouped = acting_groups(spec, config)
  controlled = [position[j] for _, limbs in grouped for l in limbs for j in l.joints]
  n_actions = len(controlled)
  groups, actor, cursor = [], {}, 0
  for name, limbs in grouped:
    if name == BODY:
      n_ctrl = sum(len(l.joints) for l in limbs)
      actor[name] = actor_segments(n_ctrl, n_actions, len(limbs), 0)  # acting limbs' phases only
      index = (tuple(range(cursor, cursor + n_ctrl)),)
      cursor += n_ctrl
      groups.append(agents.AgentGroup(name, (BODY,), actor[name].size, n_ctrl, index))
      continue
    sizes = {len(l.joints) for l in limbs}
    if len(sizes) != 1:
      raise robots.SpecError(f"group '{name}': limbs {[l.name for l in limbs]} have different "
                             "joint counts and cannot share an actor")
    n = sizes.pop()
    actor[name] = actor_segments(n, n, 1, len(limbs) if config.agent_id else 0)
    index = tuple(tuple(range(cursor + k * n, cursor + (k + 1) * n)) for k in range(len(limbs)))
    cursor += n * len(limbs)
    groups.append(agents.AgentGroup(name, tuple(l.name for l in limbs), actor[name].size, n, index))
  groups = tuple(g._replace(obs_dim=g.obs_dim * config.actor_history) for g in groups)

  if config.critic == "local":
    # Every agent's own one-step observation, zero-padded to the largest, agent by agent.
    width = max(s.size for s in actor.values())
    critic = Segments(tuple(Segment(m, width) for g in groups for m in g.members))
  else:
    n_legs = sum(1 for l in spec.limbs if l.group == "legs")
    critic = critic_segments(len(joints), n_legs, len(spec.feet), config.randomization.kicks)

  return Layout(joints=joints, default_pose=_frozen([spec.default_pose[j] for j in joints],
                                                    np.float64),
                kp=_frozen([spec.kp[j] for j in joints],
                           np.float64), kd=_frozen([spec.kd[j] for j in joints], np.float64),
                torque_limit=_frozen([spec.torque_limit[j] for j in joints],
                                     np.float64), limbs=tuple(l.name for l in spec.limbs),
                limb_index=limb_index, limb_joints=limb_joints, phase_offset=_frozen(
                    [phase_offset(l) for l in spec.limbs], np.float64), controlled=_frozen(
                        controlled, np.int64), groups=groups, group_limbs={
                            name: tuple(l.name for l in limbs) for name, limbs in grouped
                        }, actor=actor, actor_history=int(config.actor_history), critic=critic)
