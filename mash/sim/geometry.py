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
