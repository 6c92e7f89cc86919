"""Does a robot file's PD loop hold its default pose at zero action? Scales the pitch chain's kp.

Native MuJoCo, the env's 5 ms substeps, the file's torque limits, 10 s from the default pose with
the soles on the floor; prints (pelvis z, pitch) at the end. Usage:
  python benchmarks/scripts/2026-12-02_g1_stand_gains.py [robot]
"""
import sys
import tomllib

import mujoco
import numpy as np

from mash.sim import robots

PITCH = ("hip_pitch", "knee_pitch", "ankle_pitch")


def stand(name: str, kp_scale: float, roles=PITCH, seconds: float = 10.0):
  d = tomllib.loads(robots.robot_file(name).read_text())
  for r in roles:
    d["roles"][r]["kp"] *= kp_scale
  d["home_height"] = 1.0
  spec = robots.from_dict(d)
  m = robots.build_model(spec)
  data = mujoco.MjData(m)
  data.qpos[:] = m.key("home").qpos
  mujoco.mj_kinematics(m, data)
  soles = [
      g for g in range(m.ngeom)
      if "sole" in (mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or "")
  ]
  data.qpos[2] -= data.geom_xpos[soles, 2].min() - m.geom_size[soles, 0].max() - 0.005
  joints = spec.joints
  qa = [m.jnt_qposadr[m.joint(j).id] for j in joints]
  va = [m.jnt_dofadr[m.joint(j).id] for j in joints]
  q0, kp, kd, limit = (np.array([table[j]
                                 for j in joints])
                       for table in (spec.default_pose, spec.kp, spec.kd, spec.torque_limit))
  for _ in range(int(seconds / m.opt.timestep)):
    data.ctrl[:] = np.clip(kp * (q0 - data.qpos[qa]) - kd * data.qvel[va], -limit, limit)
    mujoco.mj_step(m, data)
  w, x, y, z = data.qpos[3:7]
  return round(float(data.qpos[2]), 3), round(float(np.arcsin(2 * (w * y - z * x))), 2)


if __name__ == "__main__":
  name = sys.argv[1] if len(sys.argv) > 1 else "unitree_g1"
  for scale in (0.25, 0.5, 0.75, 1.0):
    print(f"{name}: pitch-chain kp x{scale:g} of the file's -> (pelvis z m, pitch rad) after 10 s:",
          stand(name, scale))
