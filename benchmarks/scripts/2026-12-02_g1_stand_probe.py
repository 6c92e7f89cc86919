"""Does the G1 stand at zero action under the PD loop? Tries crouch poses and gains (native MuJoCo).

  python benchmarks/scripts/2026-12-02_g1_stand_probe.py
"""
import tomllib

import mujoco
import numpy as np

from mash.sim import robots


def trial(pose, gains={}, steps=2000):
  d = tomllib.loads(robots.robot_file("unitree_g1").read_text())
  for r, v in pose.items():
    d["roles"][r]["default"] = v
  for r, (kp, kd) in gains.items():
    d["roles"][r]["kp"] = kp
    d["roles"][r]["kd"] = kd
  d["home_height"] = 1.0
  s = robots.from_dict(d)
  m = robots.build_model(s)
  da = mujoco.MjData(m)
  da.qpos[:] = m.key("home").qpos
  mujoco.mj_kinematics(m, da)
  soles = [m.geom(f"{side}_sole_{k}").id for side in ("left", "right") for k in range(4)]
  da.qpos[2] -= da.geom_xpos[soles, 2].min() - 0.01
  mujoco.mj_forward(m, da)
  com = da.subtree_com[1][0]
  h0 = da.qpos[2]
  J = s.joints
  qa = [m.jnt_qposadr[m.joint(j).id] for j in J]
  va = [m.jnt_dofadr[m.joint(j).id] for j in J]
  q0 = np.array([s.default_pose[j] for j in J])
  kp = np.array([s.kp[j] for j in J])
  kd = np.array([s.kd[j] for j in J])
  tl = np.array([s.torque_limit[j] for j in J])
  for i in range(steps):
    da.ctrl[:] = np.clip(kp * (q0 - da.qpos[qa]) - kd * da.qvel[va], -tl, tl)
    mujoco.mj_step(m, da)
  w, x, y, z = da.qpos[3:7]
  return round(com, 3), round(h0, 3), round(da.qpos[2], 3), round(np.arcsin(2 * (w * y - z * x)), 3)


for pose in [
    dict(),
    dict(shoulder_pitch=0.0),
    dict(shoulder_pitch=0.0, hip_pitch=-0.3, knee_pitch=0.6, ankle_pitch=-0.3),
    dict(shoulder_pitch=0.0, hip_pitch=-0.35, knee_pitch=0.55, ankle_pitch=-0.2),
    dict(shoulder_pitch=0.0, hip_pitch=-0.4, knee_pitch=0.7, ankle_pitch=-0.3),
    dict(shoulder_pitch=0.0, hip_pitch=-0.1, knee_pitch=0.3, ankle_pitch=-0.2)
]:
  print(pose, trial(pose), trial(pose, {"ankle_pitch": (100, 2), "ankle_roll": (100, 2)}))
print("---")
arms = {r: (40, 0.3) for r in ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow_pitch")}
for g in [
    arms, {**arms, "ankle_pitch": (100, 2), "ankle_roll": (100, 2)},
    {**{r: (20, 0.2) for r in arms}, "ankle_pitch": (60, 1.5), "ankle_roll": (60, 1.5)}
]:
  print(trial(dict(shoulder_pitch=0.0), g))
