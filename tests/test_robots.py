"""Robots as data (mash.sim.robots): the shipped robot files, their validation, roles, a user's own
file, the numbers the env takes from a robot, and the G1 standing under MJX.

Parametrized over every shipped robot (``robots.names()``); none of these compiles a trainer.
"""

import dataclasses
import tomllib

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from mash.sim import env as env_lib
from mash.sim import layout as layout_lib
from mash.sim import robots
from mash.sim import env_config
from mash.sim import model as model_lib

ROBOTS = robots.names()


def _t1_table() -> dict:
  return tomllib.loads(robots.robot_file("booster_t1").read_text())


def test_the_shipped_robots_are_the_t1_and_the_g1():
  assert ROBOTS == ("booster_t1", "unitree_g1")


@pytest.mark.parametrize("name", ROBOTS)
def test_robot_file_builds_with_its_home_pose_on_the_floor(name):
  """The model builds from the file alone: motors on every limb joint in spec order, locked
  joints gone, the file's (or the model's) joint model written, and the home keyframe's lowest
  sole sphere within 2 mm of the floor (so home_height matches the kinematics)."""
  spec = robots.load(name)
  model = model_lib.build_model(spec)
  assert model.nu == len(spec.joints) and model.njnt == len(spec.joints) + 1
  assert [model.actuator(i).name for i in range(model.nu)] == list(spec.joints)
  for j in spec.locked_joints:
    with pytest.raises(KeyError):
      model.joint(j)
  dofs = [model.jnt_dofadr[model.joint(j).id] for j in spec.joints]
  if spec.armature is not None:
    np.testing.assert_allclose(model.dof_armature[dofs], spec.armature)
  else:  # the MJCF's own: the G1's rotors differ per joint
    assert np.all(model.dof_armature[dofs] > 0) and np.ptp(model.dof_armature[dofs]) > 0
  data = mujoco.MjData(model)
  data.qpos[:] = model.key("home").qpos
  mujoco.mj_kinematics(model, data)
  soles = [model.geom(f"{side}_sole_{k}").id for side in ("left", "right")
           for k in range(len(spec.sole_points))]
  lowest = data.geom_xpos[soles, 2].min() - spec.sole_radius
  assert abs(lowest) < 2e-3, lowest
  for joint in spec.joints:
    np.testing.assert_allclose(data.qpos[model.jnt_qposadr[model.joint(joint).id]],
                               spec.default_pose[joint])


@pytest.mark.parametrize("name", ROBOTS)
def test_joints_are_found_by_role_and_the_pose_is_mirror_symmetric(name):
  """Each group's limbs have the same roles in the same order; the right limb's default angle is
  mirror_sign x the left's; role_joints gives one joint per limb, left first."""
  spec = robots.load(name)
  hips = spec.role_joints("hip_pitch", "legs")
  assert len(hips) == 2 and spec.role_of(hips[0]) == spec.role_of(hips[1]) == "hip_pitch"
  assert spec.role_joints(spec.arm_swing_role, "arms")
  for group in ("legs", "arms"):
    left, right = spec.limbs_of(group)
    assert left.roles == right.roles and (left.side, right.side) == (1, -1)
    for role, lj, rj in zip(left.roles, left.joints, right.joints):
      assert spec.default_pose[rj] == spec.mirror_sign[role] * spec.default_pose[lj], role
      assert spec.kp[lj] == spec.kp[rj] and spec.torque_limit[lj] == spec.torque_limit[rj]
  with pytest.raises(robots.SpecError, match="has no joint with role 'tail'"):
    spec.role_joints("tail", "legs")


def _mutated(path: str, value):
  """The T1's table with the entry at ``path`` (dotted; list items by index) set to ``value``,
  or deleted when ``value`` is ``...``."""
  d = _t1_table()
  *keys, last = path.split(".")
  node = d
  for k in keys:
    node = node[int(k)] if isinstance(node, list) else node[k]
  if value is ...:
    del node[last]
  else:
    node[int(last) if isinstance(node, list) else last] = value
  return d


BAD_FILES = [
    ("roles.knee_pitch.kp", -5.0, r"roles.knee_pitch.kp must be in \(0, 100000\] N m/rad, got -5"),
    ("roles.hip_roll.mirror", 2, "roles.hip_roll.mirror must be 1 or -1, got 2"),
    ("roles.ankle_roll", ..., "limb 'left_leg': joint 'Left_Ankle_Roll' has role 'ankle_roll', "
     "which roles has no entry for"),
    ("limbs.1.joints.knee_pitch", ..., "limb 'right_leg': joints.knee_pitch is missing"),
    ("limbs.0.joints.tail", "Left_Tail", "limb 'left_leg': joints.tail is not a role of group "
     "'legs'"),
    ("limbs.0.side", 0, "limb 'left_leg': side must be 1 \\(left\\) or -1 \\(right\\), got 0"),
    ("task.gait_reference", {"knee": 2.0}, "task.gait_reference.knee is not a role of the legs"),
    ("task.arm_swing_role", "wrist", "task.arm_swing_role 'wrist' is not a role of the arms"),
    ("task.push_force", [20.0, -20.0], r"task.push_force must be a range \[lo, hi\]"),
    ("task.fall_height", "low", "task.fall_height must be a number, got 'low'"),
    ("joint_model.armature", "modle", 'joint_model.armature must be a number or "model"'),
    ("contact.capsules.Shank_Left", ..., "contact.penalized_pairs\\[0\\]: body 'Shank_Left' has no "
     "capsule"),
    ("contact.sole_points", [[0.1, 0.0]], r"contact.sole_points\[0\] must be a list of 3 finite"),
    ("groups.legs.roles", ["hip_pitch", "hip_pitch"], "groups.legs.roles must name each role once"),
    ("feet", ["left_foot_link"], "feet must be a pair of body names"),
    ("kp", 1.0, "kp is not a field of a robot file"),
    ("root_body", ..., "root_body is missing"),
]


@pytest.mark.parametrize("path,value,message", BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_a_bad_robot_file_is_one_spec_error_naming_the_field(path, value, message):
  with pytest.raises(robots.SpecError, match=message) as e:
    robots.from_dict(_mutated(path, value))
  assert "\n" not in str(e.value)


def test_model_names_are_checked_against_the_mjcf():
  spec = robots.from_dict(_mutated("contact.capsules.Shank_Left.radius", 0.05))
  assert model_lib.build_model(spec).nu == 20
  typo = robots.from_dict(_mutated("feet", ["left_foot_lnk", "right_foot_link"]))
  with pytest.raises(robots.SpecError, match="feet body 'left_foot_lnk' is not in the model"):
    model_lib.build_model(typo)


def test_a_users_robot_file_by_path_needs_no_package_edit(tmp_path):
  """A copy of the T1's file under another name, anywhere: the env config takes its path, its
  numbers reach the env; an unknown name or a missing file is one error naming the choices."""
  path = tmp_path / "my_robot.toml"
  text = robots.robot_file("booster_t1").read_text().replace('name = "booster_t1"',
                                                              'name = "my_robot"')
  path.write_text(text.replace("fall_height = 0.4 ", "fall_height = 0.35 "))
  spec = robots.load(str(path))
  assert spec.name == "my_robot" and spec.fall_height == 0.35
  env_config.check_config(env_config.EnvConfig(robot=str(path)))
  lay = layout_lib.build(spec, env_config.EnvConfig(robot=str(path)))
  assert lay.joints == robots.load("booster_t1").joints
  for bad in ("t2", str(tmp_path / "missing.toml")):
    with pytest.raises(ValueError, match=f"robot '{bad}' is unknown: expected one of "
                                         "booster_t1, unitree_g1 or the path of a robot file"):
      env_config.check_config(env_config.EnvConfig(robot=bad))
  (tmp_path / "broken.toml").write_text("name = \n")
  with pytest.raises(ValueError, match="is not valid TOML"):
    env_config.check_config(env_config.EnvConfig(robot=str(tmp_path / "broken.toml")))


def test_robot_numbers_fill_only_what_the_config_leaves_open():
  g1 = robots.load("unitree_g1")
  filled = env_config.with_robot_numbers(env_config.EnvConfig(robot="unitree_g1"), g1)
  assert (filled.fall_height, filled.swing_amplitude, filled.arm_swing_amplitude) == (
      g1.fall_height, g1.swing_amplitude, g1.arm_swing_amplitude)
  assert filled.randomization.push_force == g1.push_force == (-21.0, 21.0)
  assert filled.randomization.push_torque == g1.push_torque
  assert filled.reward_params.feet_height_target == g1.feet_height_target
  mine = dataclasses.replace(env_config.EnvConfig(robot="unitree_g1"), fall_height=0.5)
  assert env_config.with_robot_numbers(mine, g1).fall_height == 0.5
  t1 = robots.load("booster_t1")  # the T1's file holds the numbers the defaults used to be
  t1_cfg = env_config.with_robot_numbers(env_config.EnvConfig(), t1)
  assert (t1_cfg.fall_height, t1_cfg.swing_amplitude, t1_cfg.arm_swing_amplitude,
          t1_cfg.randomization.push_force, t1_cfg.randomization.push_torque,
          t1_cfg.reward_params.feet_height_target) == (0.4, 0.25, 0.3, (-20.0, 20.0),
                                                       (-5.0, 5.0), 0.04)


@pytest.mark.slow
def test_g1_arm_swing_env_steps_under_mjx_with_its_file_alone():
  """The G1's arm-swing env (20 joints: legs 6+6, arms 4+4) from its file alone: its groups and
  observation sizes, and 20 control steps of the nominal robot at zero action stay finite with the
  pelvis near its standing height. (It does not hold the pose for long at zero action: it tips
  over within about 2 s, see benchmarks/results/2026-12-02_g1_spec/.)"""
  cfg = env_config.EnvConfig(robot="unitree_g1", task="armswing")
  cfg = dataclasses.replace(cfg, randomization=dataclasses.replace(cfg.randomization,
                                                                   enabled=False))
  env = env_lib.MashEnv(cfg)
  assert env.n_joints == 20 and env.action_size == 20
  assert {g.name: (g.n_agents, g.obs_dim) for g in env.agent_groups} == {"legs": (2, 32),
                                                                        "arms": (2, 26)}
  assert env.config.fall_height == 0.45 and env.config.randomization.push_force == (-21.0, 21.0)

  def run(key):
    state = env.reset(key)
    def body(s, _):
      s = env.step(s, jnp.zeros((env.action_size,)))
      return s, (s.done, s.pipeline_state.xpos[env.mj_model.body("pelvis").id, 2], s.reward)
    return jax.lax.scan(body, state, None, length=20)[1]

  done, height, reward = jax.jit(run)(jax.random.PRNGKey(0))
  assert not bool(done.any()) and np.all(np.isfinite(np.asarray(reward)))
  assert abs(float(height[-1]) - robots.load("unitree_g1").base_height_target) < 0.02, height[-1]


def test_robot_flag_stores_a_file_absolute_and_deployment_checks_the_name(tmp_path, monkeypatch):
  """``--robot my.toml`` (relative) is stored as an absolute path, so evaluate/export/sim2sim
  find it from anywhere; their ``--robot`` must be the robot the run was trained on."""
  from mash import cli as common
  from mash.deploy import policy
  (tmp_path / "my.toml").write_text(robots.robot_file("booster_t1").read_text())
  monkeypatch.chdir(tmp_path)
  assert common.robot_arg("my.toml") == str(tmp_path / "my.toml")
  assert common.robot_arg("unitree_g1") == "unitree_g1"
  shipped = robots.ROBOT_DIR.parents[0] / "policies" / "t1_bipedal_mash"
  cfg = policy.load_config(shipped, robot=str(tmp_path / "my.toml"))
  assert cfg.env.robot == str(tmp_path / "my.toml")
  with pytest.raises(policy.RunError, match="is robot 'unitree_g1', but .* was trained on "
                                            "'booster_t1'"):
    policy.load_config(shipped, robot="unitree_g1")
