"""Robots as data: which MJCF to load, how its limbs split into agents, and its PD and pose numbers.

A robot is a TOML file (``mash/assets/robots/<name>.toml``, or any path a user gives): :func:`load`
reads and validates it into a :class:`RobotSpec`, which names joints, bodies and geoms only and
gives each joint a *role* (``hip_pitch``, ``knee_pitch``, ``shoulder_pitch``, ...): the code finds
joints by role, never by their names. ``build_model`` turns a spec into an ``mujoco.MjModel``
ready for MJX (locked joints removed, feet-only floor contact through a few sole spheres, the
explicit pairs the collision penalty needs, motor actuators, MJX-friendly options). Adding a
robot means writing a new file; the env, trainer and deployment code read everything from it.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from pathlib import Path
from typing import Any, Mapping


from mash.checks import check_number
from mash.errors import InputError

ROBOT_DIR = Path(__file__).resolve().parents[1] / "assets" / "robots"


class SpecError(InputError):
  """A robot spec that is malformed or does not match its model (one line, names the culprit)."""


@dataclasses.dataclass(frozen=True)
class Limb:
  """One limb = one agent.

  Attributes:
    name: e.g. ``'left_leg'``.
    group: agents with the same group share an actor (``'legs'``, ``'arms'``).
    joints: joint names, in the order the agent sees and acts on them.
    roles: the role of each joint (``'hip_pitch'``, ...), same order; the limbs of one group have
      the same roles in the same order.
    side: +1 for left, -1 for right (used by the mirror symmetry and the gait reference).
  """

  name: str
  group: str
  joints: tuple[str, ...]
  roles: tuple[str, ...]
  side: int

  def joint(self, role: str) -> str:
    """The joint of this limb with ``role``.

    Raises:
      SpecError: the limb has no joint with that role.
    """
    if role not in self.roles:
      raise SpecError(f"limb '{self.name}' has no joint with role '{role}' (its roles: "
                      f"{', '.join(self.roles)})")
    return self.joints[self.roles.index(role)]


@dataclasses.dataclass(frozen=True)
class RobotSpec:
  """Everything robot-specific the env needs (a robot file, :func:`load`).

  Attributes:
    name: robot name.
    asset_package: Python package holding the MJCF and meshes (found with importlib.resources).
    asset_path: path of the MJCF inside ``asset_package``.
    root_body: the floating base body (torso / trunk / pelvis).
    locked_joints: joints welded at zero (removed from the model).
    limbs: the agents, left before right within a group; legs first.
    default_pose: joint name -> default angle (rad); ``q_target = default + action_scale * a``.
    kp: joint name -> proportional gain (N m / rad).
    kd: joint name -> derivative gain (N m s / rad).
    torque_limit: joint name -> |tau| bound (N m).
    feet: (left, right) foot body names.
    sole_points: sole contact sphere centres in the foot frame (m), shared by both feet.
    sole_radius: radius of those spheres (m).
    penalized_pairs: pairs of (body, body) whose contact the collision penalty counts; each body gets
      a capsule ``(fromto in body frame (6,), radius)`` from ``collision_capsules``.
    collision_capsules: body name -> (fromto (6,), radius) of its penalty capsule.
    gait_reference: leg joint role -> amplitude multiplier of the swing reference (hip pitch -1,
      knee +2, ankle pitch -1 bends the swing leg).
    arm_swing_role: role of the arm joint that swings with the gait (shoulder pitch).
    mirror_sign: joint role -> sign that maps a left joint angle to the mirrored right one.
    base_height_target: standing trunk height above the soles (m).
    home_height: trunk z of the default pose with the feet on the ground (m).
    armature, damping, frictionloss: written into every actuated joint (kg m^2, N m s / rad,
      N m); None keeps the MJCF's own per-joint values.
    fall_height: root-body height (m) under which an episode ends as a fall.
    swing_amplitude: the legs' reference amplitude (rad, times ``gait_reference``).
    feet_height_target: the clearance reward's target (m above the floor), matching it.
    arm_swing_amplitude: the shoulders' reference amplitude (rad), arm-swing task.
    push_force: horizontal push on the root body per axis (N), for the robot's mass.
    push_torque: push torque per axis (N m).

  The env's config can override the task and push numbers (``EnvConfig.fall_height`` ... ``None``
  there means the robot's, these).
  """

  name: str
  asset_package: str
  asset_path: str
  root_body: str
  locked_joints: tuple[str, ...]
  limbs: tuple[Limb, ...]
  default_pose: Mapping[str, float]
  kp: Mapping[str, float]
  kd: Mapping[str, float]
  torque_limit: Mapping[str, float]
  feet: tuple[str, str]
  sole_points: tuple[tuple[float, float, float], ...]
  sole_radius: float
  penalized_pairs: tuple[tuple[str, str], ...]
  collision_capsules: Mapping[str, tuple[tuple[float, ...], float]]
  gait_reference: Mapping[str, float]
  arm_swing_role: str
  mirror_sign: Mapping[str, float]
  base_height_target: float
  home_height: float
  armature: float | None
  damping: float | None
  frictionloss: float | None
  fall_height: float
  swing_amplitude: float
  feet_height_target: float
  arm_swing_amplitude: float
  push_force: tuple[float, float]
  push_torque: tuple[float, float]

  @property
  def joints(self) -> tuple[str, ...]:
    """All actuated joints, limb by limb (legs first): the order of every joint-sized vector."""
    return tuple(j for limb in self.limbs for j in limb.joints)

  def limbs_of(self, group: str) -> tuple[Limb, ...]:
    return tuple(l for l in self.limbs if l.group == group)

  def role_joints(self, role: str, group: str) -> tuple[str, ...]:
    """The joint with ``role`` of each limb of ``group`` (left first), e.g. the two hip pitches.

    Raises:
      SpecError: a limb of the group lacks the role, or the robot has no such group.
    """
    limbs = self.limbs_of(group)
    if not limbs:
      raise SpecError(f"robot '{self.name}' has no limb group '{group}'")
    return tuple(l.joint(role) for l in limbs)

  def role_indices(self, role: str, group: str) -> list[int]:
    """Positions in :attr:`joints` of :meth:`role_joints` (left first), e.g. of the two hip
    pitches for ``("hip_pitch", "legs")``; a list, so that ``x[..., idx]`` picks them from a
    ``[..., J]`` NumPy or JAX array."""
    return [self.joints.index(j) for j in self.role_joints(role, group)]

  def role_of(self, joint: str) -> str:
    """The role of ``joint`` (one of :attr:`joints`)."""
    for limb in self.limbs:
      if joint in limb.joints:
        return limb.roles[limb.joints.index(joint)]
    raise SpecError(f"robot '{self.name}' has no actuated joint '{joint}'")


# ------------------------------------------------------------------------------- robot files
# Each key of a robot file: its TOML section, its kind, and (numbers) the sane bounds, ours, each
# far outside any humanoid's (a value beyond one is a typo).
_TOP_KEYS = ("name", "asset_package", "asset_path", "root_body", "locked_joints", "feet",
             "base_height_target", "home_height", "joint_model", "contact", "task", "groups",
             "limbs", "roles")
_JOINT_MODEL = {"armature": (0.0, 10.0, "kg m^2"), "damping": (0.0, 1e3, "N m s/rad"),
                "frictionloss": (0.0, 1e3, "N m")}
_ROLE_NUMBERS = {"default": (-2 * math.pi, 2 * math.pi, "rad", False),
                 "kp": (0.0, 1e5, "N m/rad", True), "kd": (0.0, 1e4, "N m s/rad", False),
                 "torque_limit": (0.0, 1e4, "N m", True)}
_TASK_NUMBERS = {"fall_height": (0.0, 5.0, "m"), "swing_amplitude": (0.0, math.pi, "rad"),
                 "feet_height_target": (0.0, 1.0, "m"), "arm_swing_amplitude": (0.0, math.pi, "rad")}
_TASK_RANGES = {"push_force": (-1e4, 1e4, "N"), "push_torque": (-1e3, 1e3, "N m")}


def names() -> tuple[str, ...]:
  """The robots this package ships: the files of ``mash/assets/robots/``, by name."""
  return tuple(sorted(p.stem for p in ROBOT_DIR.glob("*.toml")))


def robot_file(robot: str) -> Path:
  """The file of ``robot``: a shipped robot's name (``'booster_t1'``) or a path to a TOML file.

  Raises:
    SpecError: neither a shipped name nor an existing ``.toml`` file.
  """
  if robot in names():
    return ROBOT_DIR / f"{robot}.toml"
  path = Path(os.path.expanduser(robot))
  if path.suffix == ".toml" and path.is_file():
    return path
  raise SpecError(f"robot '{robot}' is unknown: expected one of {', '.join(names())} or the path "
                  "of a robot file (.toml, see mash/assets/robots/)")


_CACHE: dict[Path, tuple[float, RobotSpec]] = {}


def load(robot: str | os.PathLike) -> RobotSpec:
  """Reads and validates a robot file (a shipped name or a path, :func:`robot_file`).

  Raises:
    SpecError: one line naming the file, the field (and the joint or role) and what was expected.
  """
  path = robot_file(str(robot)).resolve()
  mtime = path.stat().st_mtime
  if path in _CACHE and _CACHE[path][0] == mtime:
    return _CACHE[path][1]
  try:
    data = tomllib.loads(path.read_text())
  except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
    raise SpecError(f"robot file '{path}' is not valid TOML: {e}") from None
  try:
    spec = from_dict(data)
  except SpecError as e:
    raise SpecError(f"robot file '{path}': {e}") from None
  _CACHE[path] = (mtime, spec)
  return spec


_KIND_NAMES = {float: "a number", int: "an integer", str: "a string", list: "a list",
               dict: "a table"}


def _need(d: Mapping[str, Any], key: str, where: str, kind: type) -> Any:
  """``d[key]``, which must be of ``kind`` (``float``: any number)."""
  if key not in d:
    raise SpecError(f"{where}{key} is missing")
  value = d[key]
  ok = isinstance(value, (int, float)) if kind is float else isinstance(value, kind)
  if not ok or isinstance(value, bool):
    raise SpecError(f"{where}{key} must be {_KIND_NAMES[kind]}, got {value!r}")
  return value


def _unknown(d: Mapping[str, Any], known: tuple[str, ...] | Mapping[str, Any], where: str) -> None:
  extra = [k for k in d if k not in known]
  if extra:
    raise SpecError(f"{where}{extra[0]} is not a field of a robot file (expected: "
                    f"{', '.join(known)})")


def _number(value: Any, where: str, low: float, high: float, unit: str,
            open_low: bool = False) -> float:
  if not isinstance(value, (int, float)) or isinstance(value, bool):
    raise SpecError(f"{where} must be a number, got {value!r}")
  try:
    check_number(where, float(value), low, high, unit, open_low)
  except ValueError as e:
    raise SpecError(str(e)) from None
  return float(value)


def _numbers(value: Any, where: str, n: int) -> tuple[float, ...]:
  if (not isinstance(value, list) or len(value) != n
      or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                 for x in value)):
    raise SpecError(f"{where} must be a list of {n} finite numbers, got {value!r}")
  return tuple(float(x) for x in value)


def _strings(value: Any, where: str) -> tuple[str, ...]:
  if not isinstance(value, list) or not all(isinstance(x, str) and x for x in value):
    raise SpecError(f"{where} must be a list of names, got {value!r}")
  return tuple(value)


def from_dict(d: Mapping[str, Any]) -> RobotSpec:
  """A :class:`RobotSpec` from a robot file's table (its format: ``mash/assets/robots/*.toml``).

  Checks every field without the model (:func:`build_model` checks the names against it): the
  kinds, the ranges of the numbers, each group's roles present in each of its limbs once, each
  role with its numbers, the gait reference's and the arm swing's roles among the legs' and
  arms' roles, legs with a hip pitch, a capsule for each penalized body.

  Raises:
    SpecError: one line naming the field (and its limb, joint or role).
  """
  _unknown(d, _TOP_KEYS, "")
  name = _need(d, "name", "", str)
  jm = _need(d, "joint_model", "", dict)
  _unknown(jm, _JOINT_MODEL, "joint_model.")
  joint_model = {}
  for key, (low, high, unit) in _JOINT_MODEL.items():
    if key not in jm:
      raise SpecError(f"joint_model.{key} is missing")
    value = jm[key]
    if isinstance(value, str):
      if value != "model":
        raise SpecError(f"joint_model.{key} must be a number or \"model\" (the MJCF's own), "
                        f"got {value!r}")
      joint_model[key] = None
    else:
      joint_model[key] = _number(value, f"joint_model.{key}", low, high, unit)

  groups = _need(d, "groups", "", dict)
  group_roles = {}
  for group, table in groups.items():
    if not isinstance(table, dict):
      raise SpecError(f"groups.{group} must be a table with roles = [...], got {table!r}")
    _unknown(table, ("roles",), f"groups.{group}.")
    roles = _strings(_need(table, "roles", f"groups.{group}.", list), f"groups.{group}.roles")
    if len(set(roles)) != len(roles) or not roles:
      raise SpecError(f"groups.{group}.roles must name each role once, got {list(roles)}")
    group_roles[group] = roles

  role_table = _need(d, "roles", "", dict)
  default_pose, kp, kd, torque_limit, mirror = {}, {}, {}, {}, {}
  for role, numbers in role_table.items():
    if not any(role in r for r in group_roles.values()):
      raise SpecError(f"roles.{role} is the role of no group's joint (groups.*.roles)")
    if not isinstance(numbers, dict):
      raise SpecError(f"roles.{role} must be a table {{default, kp, kd, torque_limit, mirror}}")
    _unknown(numbers, (*_ROLE_NUMBERS, "mirror"), f"roles.{role}.")
    for key, (low, high, unit, open_low) in _ROLE_NUMBERS.items():
      _number(_need(numbers, key, f"roles.{role}.", float), f"roles.{role}.{key}", low, high,
              unit, open_low)
    m = _need(numbers, "mirror", f"roles.{role}.", int)
    if m not in (1, -1):
      raise SpecError(f"roles.{role}.mirror must be 1 or -1, got {m}")
    mirror[role] = float(m)

  limbs = []
  raw_limbs = _need(d, "limbs", "", list)
  for k, limb in enumerate(raw_limbs):
    where = f"limbs[{k}]."
    if not isinstance(limb, dict):
      raise SpecError(f"limbs[{k}] must be a table")
    _unknown(limb, ("name", "group", "side", "joints"), where)
    limb_name = _need(limb, "name", where, str)
    where = f"limb '{limb_name}': "
    group = _need(limb, "group", where, str)
    if group not in group_roles:
      raise SpecError(f"{where}group '{group}' is not in groups ({', '.join(group_roles)})")
    side = _need(limb, "side", where, int)
    if side not in (1, -1):
      raise SpecError(f"{where}side must be 1 (left) or -1 (right), got {side}")
    by_role = _need(limb, "joints", where, dict)
    roles = group_roles[group]
    for role in by_role:
      if role not in roles:
        raise SpecError(f"{where}joints.{role} is not a role of group '{group}' "
                        f"({', '.join(roles)})")
    for role in roles:
      joint = _need(by_role, role, f"{where}joints.", str)
      if role not in role_table:
        raise SpecError(f"{where}joint '{joint}' has role '{role}', which roles has no entry for")
      numbers = role_table[role]
      sign = mirror[role] if side < 0 else 1.0
      default_pose[joint] = sign * float(numbers["default"])
      kp[joint], kd[joint] = float(numbers["kp"]), float(numbers["kd"])
      torque_limit[joint] = float(numbers["torque_limit"])
    limbs.append(Limb(limb_name, group, tuple(by_role[r] for r in roles), roles, side))
  if not limbs:
    raise SpecError("limbs is empty: a robot needs at least its two legs")
  joints = [j for l in limbs for j in l.joints]
  twice = [j for j in joints if joints.count(j) > 1]
  if twice:
    raise SpecError(f"joint '{twice[0]}' belongs to two limbs")
  if len({l.name for l in limbs}) != len(limbs):
    raise SpecError("limbs: two limbs have the same name")
  legs = [l for l in limbs if l.group == "legs"]
  if len(legs) != 2 or limbs[0].group != "legs":
    raise SpecError("limbs: expected two limbs of group 'legs' (left, then right), listed first")
  for group in group_roles:
    sides = [l.side for l in limbs if l.group == group]
    if sides and sides[0] != 1:
      raise SpecError(f"limbs: group '{group}' must list its left limb (side 1) first")
  if "hip_pitch" not in group_roles["legs"]:
    raise SpecError("groups.legs.roles has no 'hip_pitch' (the gait metrics and the reference "
                    "read it)")

  task = _need(d, "task", "", dict)
  _unknown(task, (*_TASK_NUMBERS, *_TASK_RANGES, "gait_reference", "arm_swing_role"), "task.")
  numbers = {k: _number(_need(task, k, "task.", float), f"task.{k}", *b)
             for k, b in _TASK_NUMBERS.items()}
  ranges = {}
  for key, (low, high, unit) in _TASK_RANGES.items():
    lo, hi = _numbers(_need(task, key, "task.", list), f"task.{key}", 2)
    if not low <= lo <= hi <= high:
      raise SpecError(f"task.{key} must be a range [lo, hi] with {low:g} <= lo <= hi <= {high:g} "
                      f"{unit}, got {[lo, hi]}")
    ranges[key] = (lo, hi)
  gait = _need(task, "gait_reference", "task.", dict)
  for role, value in gait.items():
    if role not in group_roles["legs"]:
      raise SpecError(f"task.gait_reference.{role} is not a role of the legs "
                      f"({', '.join(group_roles['legs'])})")
    _number(value, f"task.gait_reference.{role}", -10.0, 10.0, "")
  if not gait:
    raise SpecError("task.gait_reference is empty: the legs would have no reference")
  arm_role = _need(task, "arm_swing_role", "task.", str)
  if "arms" in group_roles and arm_role not in group_roles["arms"]:
    raise SpecError(f"task.arm_swing_role '{arm_role}' is not a role of the arms "
                    f"({', '.join(group_roles['arms'])})")

  contact = _need(d, "contact", "", dict)
  _unknown(contact, ("sole_points", "sole_radius", "penalized_pairs", "capsules"), "contact.")
  raw_points = _need(contact, "sole_points", "contact.", list)
  if not raw_points:
    raise SpecError("contact.sole_points is empty: the feet would not touch the floor")
  sole_points = tuple(_numbers(p, f"contact.sole_points[{k}]", 3) for k, p in enumerate(raw_points))
  sole_radius = _number(_need(contact, "sole_radius", "contact.", float), "contact.sole_radius",
                        0.0, 1.0, "m", open_low=True)
  capsules = {}
  for body, cap in _need(contact, "capsules", "contact.", dict).items():
    where = f"contact.capsules.{body}"
    if not isinstance(cap, dict):
      raise SpecError(f"{where} must be a table {{fromto, radius}}")
    _unknown(cap, ("fromto", "radius"), where + ".")
    capsules[body] = (_numbers(_need(cap, "fromto", where + ".", list), where + ".fromto", 6),
                      _number(_need(cap, "radius", where + ".", float), where + ".radius", 0.0,
                              1.0, "m", open_low=True))
  pairs = []
  for k, pair in enumerate(_need(contact, "penalized_pairs", "contact.", list)):
    a, b = _pair(pair, f"contact.penalized_pairs[{k}]")
    for body in (a, b):
      if body not in capsules:
        raise SpecError(f"contact.penalized_pairs[{k}]: body '{body}' has no capsule "
                        "(contact.capsules)")
    pairs.append((a, b))

  feet = _pair(_need(d, "feet", "", list), "feet")
  return RobotSpec(
      name=name, asset_package=_need(d, "asset_package", "", str),
      asset_path=_need(d, "asset_path", "", str), root_body=_need(d, "root_body", "", str),
      locked_joints=_strings(d.get("locked_joints", []), "locked_joints"),
      limbs=tuple(limbs), default_pose=default_pose, kp=kp, kd=kd, torque_limit=torque_limit,
      feet=feet, sole_points=sole_points, sole_radius=sole_radius, penalized_pairs=tuple(pairs),
      collision_capsules=capsules, gait_reference={r: float(v) for r, v in gait.items()},
      arm_swing_role=arm_role, mirror_sign=mirror,
      base_height_target=_number(_need(d, "base_height_target", "", float), "base_height_target",
                                 0.0, 5.0, "m", open_low=True),
      home_height=_number(_need(d, "home_height", "", float), "home_height", 0.0, 5.0, "m",
                          open_low=True),
      **joint_model, **numbers, **ranges)


def _pair(value: Any, where: str) -> tuple[str, str]:
  if not isinstance(value, list) or len(value) != 2 or not all(isinstance(x, str) for x in value):
    raise SpecError(f"{where} must be a pair of body names, got {value!r}")
  return value[0], value[1]


