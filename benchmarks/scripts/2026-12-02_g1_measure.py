"""Measures a robot file's kinematic numbers from its model (run from the repository root):

  python benchmarks/scripts/2026-12-02_g1_measure.py unitree_g1

home_height: root z that puts the lowest sole sphere on the floor at the default pose;
base_height_target: the root's height above the soles there; feet_height_target: the swing
sole's peak lift when the leg takes the gait reference at its peak (phase 0.25: each role's
multiplier x swing_amplitude), the root held. Prints them and the numbers the file holds now.
"""

import dataclasses
import sys

import mujoco

from mash.sim import robots


def sole_bottoms(model, data, spec, side):
  ids = [model.geom(f"{side}_sole_{k}").id for k in range(len(spec.sole_points))]
  return data.geom_xpos[ids, 2] - spec.sole_radius


def measure(spec):
  spec = dataclasses.replace(spec, home_height=1.0)  # any height: measured relative to the root
  model = robots.build_model(spec)
  data = mujoco.MjData(model)
  data.qpos[:] = model.key("home").qpos
  mujoco.mj_kinematics(model, data)
  root_z = data.xpos[model.body(spec.root_body).id][2]
  low = min(
      sole_bottoms(model, data, spec, "left").min(),
      sole_bottoms(model, data, spec, "right").min())
  home_height = root_z - low
  left = spec.limbs_of("legs")[0]
  for role, k in spec.gait_reference.items():
    data.qpos[model.jnt_qposadr[model.joint(left.joint(role)).id]] += k * spec.swing_amplitude
  mujoco.mj_kinematics(model, data)
  lift = sole_bottoms(model, data, spec, "left").min() - low
  return {"home_height": home_height, "base_height_target": home_height, "feet_height_target": lift}


if __name__ == "__main__":
  import tomllib
  name = sys.argv[1] if len(sys.argv) > 1 else "unitree_g1"
  d = tomllib.loads(robots.robot_file(name).read_text())
  for key in ("home_height", "base_height_target"):
    d[key] = d[key] or 1.0
  d["task"]["feet_height_target"] = d["task"]["feet_height_target"] or 0.05
  spec = robots.from_dict(d)
  got = measure(spec)
  for key, value in got.items():
    now = getattr(spec, key)
    print(f"{key}: measured {value:.4f} m (file: {now})")
