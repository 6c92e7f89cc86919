"""Geometry measured from a robot's model, and the rotations the env and native MuJoCo share.

Quaternions are MuJoCo's (w, x, y, z). Nothing here assumes a robot's axes: what depends on a
robot's kinematics (:func:`stride_gains`) is measured on its ``MjModel`` at the default pose.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mash.sim import robots


def quat_to_euler(quat: jax.Array | np.ndarray) -> jax.Array | np.ndarray:
  """[4] (w, x, y, z) -> [3] roll, pitch, yaw (rad), ZYX convention.

  A JAX array (traced or not) gives a JAX array; anything else (a NumPy array, as native MuJoCo
  reads it) is computed in NumPy, in its own precision, and gives a NumPy array.
  """
  xp = jnp if isinstance(quat, jax.Array) else np
  quat = xp.asarray(quat)
  w, x, y, z = quat[0], quat[1], quat[2], quat[3]
  roll = xp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
  pitch = xp.arcsin(xp.clip(2 * (w * y - z * x), -1.0, 1.0))
  yaw = xp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
  return xp.stack([roll, pitch, yaw])


def quat_rotate_inverse(quat: jax.Array, vec: jax.Array) -> jax.Array:
  """Rotates a world-frame [3] vector into the frame of the [4] (w, x, y, z) quaternion."""
  w, u = quat[0], quat[1:]
  return vec * (2 * w * w - 1) - 2 * w * jnp.cross(u, vec) + 2 * u * jnp.dot(u, vec)


# Per axis of a stride (0: x, 1: y, 2: yaw): the hip role that moves the foot along it, and the
# ankle role that keeps the sole level against the hip's tilt (None: the sole turns with the leg).
STRIDE_AXES = ((0, "hip_pitch", "ankle_pitch"), (1, "hip_roll", "ankle_roll"), (2, "hip_yaw", None))
AXIS_NAMES = ("x", "y", "yaw")


def _zyx(rot: np.ndarray) -> np.ndarray:
  """``[3, 3]`` rotation -> ``[3]`` yaw, pitch, roll (rad, ZYX)."""
  return np.array([
      np.arctan2(rot[1, 0], rot[0, 0]), -np.arcsin(np.clip(rot[2, 0], -1, 1)),
      np.arctan2(rot[2, 1], rot[2, 2])
  ])


def stride_plan(spec: robots.RobotSpec) -> str:
  """Which joints carry the stride reference on ``spec``'s legs, and what a missing role leaves
  out, in one line (the training command prints it)."""
  roles = next(l for l in spec.limbs if l.group == "legs").roles
  parts = []
  for axis, hip, ankle in STRIDE_AXES:
    if hip not in roles:
      parts.append(f"{AXIS_NAMES[axis]}: none (no {hip})")
    elif ankle is None or ankle in roles:
      parts.append(f"{AXIS_NAMES[axis]}: {hip}" + (f" + {ankle}" if ankle else ""))
    else:
      parts.append(f"{AXIS_NAMES[axis]}: {hip} (no {ankle}: the sole tilts with the leg)")
  return "; ".join(parts)


def stride_gains(model: mujoco.MjModel, spec: robots.RobotSpec, eps: float = 1e-3) -> np.ndarray:
  """[J, 3] joint offset per unit foot displacement x, y (m) and foot yaw (rad), world frame, at
  the default pose: each leg's hip pitch, roll and yaw from finite differences of its foot's
  position and yaw, and its ankle pitch and roll so that the sole keeps its tilt. The foot's
  turn is measured in the world frame against its default-pose orientation, so no axis of the
  foot's own frame is assumed. A role a leg lacks leaves its part out (:func:`stride_plan`).
  """
  data = mujoco.MjData(model)
  home = model.key("home").qpos.copy()

  def foot_pose(limb, offsets, rot0=None):
    data.qpos[:] = home
    for name, delta in offsets.items():
      data.qpos[model.jnt_qposadr[model.joint(name).id]] += delta
    mujoco.mj_kinematics(model, data)
    body = model.body(spec.feet[0] if limb.side > 0 else spec.feet[1]).id
    rot = data.xmat[body].reshape(3, 3)
    turn = _zyx(rot if rot0 is None else rot @ rot0.T)  # yaw, pitch, roll in the world
    return np.array([*data.xpos[body][:2], *turn]), rot.copy()

  joint_pos = {j: i for i, j in enumerate(spec.joints)}
  gain = np.zeros((len(spec.joints), 3))
  for limb in (l for l in spec.limbs if l.group == "legs"):
    _, rot0 = foot_pose(limb, {})
    base, _ = foot_pose(limb, {}, rot0)
    d = {r: (foot_pose(limb, {limb.joint(r): eps}, rot0)[0] - base) / eps for r in limb.roles}
    for axis, hip, ankle in STRIDE_AXES:
      if hip not in limb.roles:
        continue
      g = 1.0 / d[hip][axis]
      gain[joint_pos[limb.joint(hip)], axis] = g
      if ankle in limb.roles:  # the ankle undoes the sole's tilt: pitch (3) for x, roll (4) for y
        tilt = 3 + axis
        gain[joint_pos[limb.joint(ankle)], axis] = -g * d[hip][tilt] / d[ankle][tilt]
  return gain


def measured_mirror(model: mujoco.MjModel, spec: robots.RobotSpec) -> dict[str, float]:
  """Per role that a group's left and right limbs both have, the mirror sign their joint axes
  give at the default pose: +1 when the right joint turns about the mirror image (across the
  sagittal plane) of the left's axis, -1 when about its opposite. A rotation axis is a
  pseudo-vector, so the mirror image of ``(a_x, a_y, a_z)`` is ``(-a_x, a_y, -a_z)``: a pitch
  axis mirrors to itself (+1 on a robot whose both pitch axes point the same way), a roll or yaw
  axis to its opposite (-1 when both point the same way)."""
  data = mujoco.MjData(model)
  data.qpos[:] = model.key("home").qpos
  mujoco.mj_kinematics(model, data)
  signs = {}
  for group in dict.fromkeys(l.group for l in spec.limbs):
    sides = {l.side: l for l in spec.limbs if l.group == group}
    if set(sides) != {1, -1}:
      continue
    for role in sides[1].roles:
      if role not in sides[-1].roles:
        continue
      left = data.xaxis[model.joint(sides[1].joint(role)).id] * np.array([-1.0, 1.0, -1.0])
      right = data.xaxis[model.joint(sides[-1].joint(role)).id]
      signs[role] = 1.0 if float(np.dot(left, right)) >= 0 else -1.0
  return signs


def mirror_mismatches(model: mujoco.MjModel, spec: robots.RobotSpec) -> list[str]:
  """One line per role whose ``mirror`` in the robot file disagrees with the model's axes
  (:func:`measured_mirror`), each starting with the field to change."""
  return [
      f"roles.{role}.mirror is {spec.mirror_sign[role]:+.0f}, but the model's right {role} "
      f"joint turns {'the same way as' if sign > 0 else 'against'} the mirror image of the "
      f"left's: expected {sign:+.0f} (the references and the default pose would not be "
      "mirror images)"
      for role, sign in measured_mirror(model, spec).items()
      if spec.mirror_sign[role] != sign
  ]


def check_mirror(model: mujoco.MjModel, spec: robots.RobotSpec) -> None:
  """The robot file's mirror signs against its model's axes (:func:`mirror_mismatches`).

  Raises:
    robots.SpecError: a role whose ``mirror`` disagrees with the model, naming the field.
  """
  wrong = mirror_mismatches(model, spec)
  if wrong:
    raise robots.SpecError(f"robot '{spec.name}': {wrong[0]}")
