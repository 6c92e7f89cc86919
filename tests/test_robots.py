"""Robots as data (mash.sim.robots): the shipped robot files, their validation, roles, a user's own
file, the numbers the env takes from a robot, and the G1 standing under MJX.

Parametrized over every shipped robot (``robots.names()``); none of these compiles a trainer.
"""

import dataclasses
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from mash.analysis import robot_check
from mash.sim import env as env_lib
from mash.sim import env_config, geometry, robots
from mash.sim import layout as layout_lib
from mash.sim import model as model_lib

ROBOTS = robots.names()
ROOT = Path(__file__).resolve().parents[1]


def _t1_table() -> dict:
  return tomllib.loads(robots.robot_file("booster_t1").read_text())


def test_the_shipped_robots():
  assert ROBOTS == ("berkeley_humanoid", "booster_t1", "unitree_g1", "unitree_h1")
  shapes = {n: tuple(len(l.joints) for l in robots.load(n).limbs) for n in ROBOTS}
  assert shapes == {
      "berkeley_humanoid": (6, 6), "booster_t1": (6, 6, 4, 4), "unitree_g1": (6, 6, 4, 4),
      "unitree_h1": (5, 5, 4, 4)
  }


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
  else:  # the MJCF's own, joint by joint
    raw = mujoco.MjModel.from_xml_path(str(robots.mjcf_file(spec)))
    np.testing.assert_allclose(
        model.dof_armature[dofs],
        [raw.dof_armature[raw.jnt_dofadr[raw.joint(j).id]] for j in spec.joints])
  data = mujoco.MjData(model)
  data.qpos[:] = model.key("home").qpos
  mujoco.mj_kinematics(model, data)
  soles = [
      model.geom(f"{side}_sole_{k}").id
      for side in ("left", "right")
      for k in range(len(spec.sole_points[0]))
  ]
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
  groups = tuple(dict.fromkeys(l.group for l in spec.limbs))
  if "arms" in groups:
    assert spec.role_joints(spec.arm_swing_role, "arms") and spec.arm_swing_amplitude > 0
  else:  # a legs-only robot carries no arm-swing fields
    assert spec.arm_swing_role is None and spec.arm_swing_amplitude is None
  for group in groups:
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


BAD_BERKELEY = [
    ("task.arm_swing_role", "shoulder_pitch", "task.arm_swing_role is given, but the robot has no "
     "limb group 'arms' \\(drop it\\)"),
    ("contact.sole_points.right", [[0.0, 0.0, 0.0]], "contact.sole_points: the left foot has 4 "
     "points, the right 1; give each foot as many"),
    ("groups.legs.roles", ["hip_yaw", "hip_roll", "knee_pitch",
                           "ankle_pitch"], "groups.legs.roles has no 'hip_pitch'"),
    ("groups.legs.roles", ["hip_pitch", "knee_pitch",
                           "ankle_pitch"], "groups.legs.roles must name 4 to 7 roles"),
]


@pytest.mark.parametrize("path,value,message", BAD_BERKELEY, ids=[b[0] for b in BAD_BERKELEY])
def test_a_legs_only_file_is_checked_as_one(path, value, message):
  """The Berkeley Humanoid's file (no arms, a sole per foot): arm-swing fields are refused, the
  feet must have as many sole points, the legs need a hip pitch."""
  table = tomllib.loads(robots.robot_file("berkeley_humanoid").read_text())
  *keys, last = path.split(".")
  node = table
  for k in keys:
    node = node[k]
  node[last] = value
  with pytest.raises(robots.SpecError, match=message):
    robots.from_dict(table)


def test_a_misnamed_joint_is_caught_when_the_file_is_read(tmp_path):
  """A name the MJCF lacks stops ``robots.load`` (not the model build): one line naming the
  file, the field, the limb and the role; ``check_config`` passes it on before any work."""
  path = tmp_path / "typo.toml"
  path.write_text(
      robots.robot_file("booster_t1").read_text().replace('"Left_Knee_Pitch"', '"Left_Knee_Pich"'))
  message = (f"robot file '{path}': limb 'left_leg' joints.knee_pitch: joint 'Left_Knee_Pich' "
             "is not in the model")
  with pytest.raises(robots.SpecError, match=message) as e:
    robots.load(str(path))
  assert "\n" not in str(e.value)
  with pytest.raises(ValueError, match=message):
    env_config.check_config(env_config.EnvConfig(robot=str(path)))


def test_a_task_needing_arms_is_refused_on_a_legs_only_robot(tmp_path):
  """``armswing`` on a robot without arms: one error line naming the missing group before any
  folder is made; ``bipedal`` builds its layout."""
  cfg = env_config.EnvConfig(robot="berkeley_humanoid", task="armswing")
  with pytest.raises(
      ValueError, match="task 'armswing' needs limb group 'arms', which robot "
      "'berkeley_humanoid' does not have: train 'bipedal'"):
    env_config.check_config(cfg)
  proc = subprocess.run([
      sys.executable, "-m", "experiments.armswing", "--robot", "berkeley_humanoid", "--preset",
      "smoke", "--out",
      str(tmp_path / "run")
  ], capture_output=True, text=True, cwd=ROOT, timeout=120)
  assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
  assert proc.stderr.startswith("error: env.task 'armswing' needs limb group 'arms'")
  assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("name", ROBOTS)
def test_layout_sizes_follow_the_robots_limbs(name):
  """Per robot and task it can do: a limb agent's observation is its joints' angle, velocity and
  last action (3 n), its phase (2), Euler angles, angular velocity (3 + 3), the command (4) and
  a one-hot agent id over its group's 2 limbs; the critic's is 4 J + 26 (+3 with kicks)."""
  spec = robots.load(name)
  tasks = ("bipedal", "armswing") if spec.limbs_of("arms") else ("bipedal",)
  for task in tasks:
    for kicks in (False, True):
      cfg = env_config.EnvConfig(robot=name, task=task)
      if kicks:
        cfg = dataclasses.replace(
            cfg, randomization=dataclasses.replace(cfg.randomization, kick_velocity=(0.1, 1.0)))
      lay = layout_lib.build(spec, cfg)
      acting = ("legs",) if task == "bipedal" else ("legs", "arms")
      assert {g: lay.actor[g].size for g in lay.actor
             } == {g: 3 * len(spec.limbs_of(g)[0].joints) + 12 + 2 for g in acting}
      assert lay.critic.size == 4 * len(spec.joints) + 26 + 3 * kicks


def test_five_joint_legs_leave_the_missing_roles_part_out():
  """The H1's legs have no ankle roll: the stride plan says so, the lateral stride rests on the
  hip roll alone, and every gain is finite."""
  spec = robots.load("unitree_h1")
  assert "ankle_roll" not in spec.limbs[0].roles
  assert geometry.stride_plan(spec) == (
      "x: hip_pitch + ankle_pitch; y: hip_roll (no ankle_roll: the sole tilts with the leg); "
      "yaw: hip_yaw")
  gains = geometry.stride_gains(model_lib.build_model(spec), spec)
  assert np.all(np.isfinite(gains))
  rolls = spec.role_indices("hip_roll", "legs")
  assert np.count_nonzero(gains[:, 1]) == 2 and np.all(gains[rolls, 1] != 0)


def _quat_about(axis: np.ndarray, angle: float) -> np.ndarray:
  return np.array([np.cos(angle / 2), *(np.sin(angle / 2) * axis / np.linalg.norm(axis))])


def test_stride_gains_do_not_assume_the_foot_frame():
  """Turning each foot's body frame (here: y up, z forward, as the Berkeley Humanoid's) changes
  no stride gain: the direction of travel and the vertical are measured, not assumed."""
  spec = robots.load("booster_t1")
  model = model_lib.build_model(spec)
  before = geometry.stride_gains(model, spec)
  turn = _quat_about(np.array([1.0, 1.0, 1.0]), 2 * np.pi / 3)  # x -> y, y -> z, z -> x
  back = np.zeros(9)
  mujoco.mju_quat2Mat(back, turn)
  back = back.reshape(3, 3).T  # old frame's vectors in the new frame
  for foot in spec.feet:
    body = model.body(foot).id
    old = model.body_quat[body].copy()
    mujoco.mju_mulQuat(model.body_quat[body], old, turn)
    for j in np.flatnonzero(model.jnt_bodyid == body):  # the same axes and anchors in the world
      model.jnt_axis[j] = back @ model.jnt_axis[j]
      model.jnt_pos[j] = back @ model.jnt_pos[j]
  np.testing.assert_allclose(geometry.stride_gains(model, spec), before, rtol=1e-6, atol=1e-9)


def test_references_carry_each_roles_mirror_sign():
  """A right joint's gait and arm-swing amplitude is the left's times its role's mirror sign
  (the T1: pitch +1; a file whose knee turns the other way: -1 on the right knee)."""
  t1 = robots.load("booster_t1")
  cfg = env_config.with_robot_numbers(env_config.EnvConfig(task="armswing"), t1)
  scale, _ = env_lib.reference_scales(t1, cfg)
  knees = t1.role_indices("knee_pitch", "legs")
  shoulders = t1.role_indices("shoulder_pitch", "arms")
  np.testing.assert_allclose(scale[knees], [0.25 * 2.0, 0.25 * 2.0])  # swing x gait multiplier
  np.testing.assert_allclose(scale[shoulders], [-0.3, -0.3])
  flipped = robots.from_dict(_mutated("roles.knee_pitch.mirror", -1))
  scale, _ = env_lib.reference_scales(flipped, cfg)
  np.testing.assert_allclose(scale[knees], [0.5, -0.5])
  assert flipped.default_pose["Right_Knee_Pitch"] == -flipped.default_pose["Left_Knee_Pitch"]


def test_a_mirrored_axis_left_out_of_the_file_is_named():
  """The T1 with its right knee's axis turned over (as on robots whose right pitch joints turn
  about -y) and the file left at mirror +1: the mirror check names ``roles.knee_pitch.mirror``
  with the sign it should be, the env refuses it, and the reference's feet lift differently.
  With the sign given, the same model lifts both feet alike."""
  spec = robots.load("booster_t1")
  model = model_lib.build_model(spec)
  knee = model.joint("Right_Knee_Pitch").id
  model.jnt_axis[knee] *= -1
  model.qpos0[model.jnt_qposadr[knee]] *= -1
  model.key_qpos[0, model.jnt_qposadr[knee]] *= -1
  wrong = geometry.mirror_mismatches(model, spec)
  assert len(wrong) == 1 and wrong[0].startswith("roles.knee_pitch.mirror is +1") and ("expected -1"
                                                                                       in wrong[0])
  with pytest.raises(robots.SpecError, match="roles.knee_pitch.mirror is \\+1"):
    geometry.check_mirror(model, spec)
  cfg = env_config.EnvConfig()
  found = robot_check.clearance_findings(robot_check.gait_cycle(spec, model, cfg), 0.04)
  assert found[0].level == "error" and found[0].field == "roles.<pitch roles>.mirror"
  fixed = robots.from_dict(_mutated("roles.knee_pitch.mirror", -1))
  assert geometry.mirror_mismatches(model, fixed) == []
  found = robot_check.clearance_findings(robot_check.gait_cycle(fixed, model, cfg), 0.04)
  assert found[0].level == "ok"


@pytest.mark.parametrize("name", ROBOTS)
def test_every_shipped_robot_passes_its_check_without_mjx(name):
  """``experiments.robot check``'s MuJoCo C part on each shipped file: it stands 10 s at zero
  action, the mirror signs match the axes, both feet lift alike in the reference, every
  reference stays within the joint limits: no error and no warning."""
  findings, record = robot_check.check(name, seconds=10.0, mjx=False)
  assert [f.level for f in findings] == ["ok"] * len(findings), findings
  left, right = record["clearance_cm"]
  assert abs(left - right) <= robot_check.CLEARANCE_TOLERANCE * max(left, right)


def test_model_names_are_checked_against_the_mjcf():
  spec = robots.from_dict(_mutated("contact.capsules.Shank_Left.radius", 0.05))
  assert model_lib.build_model(spec).nu == 20
  typo = robots.from_dict(_mutated("feet", ["left_foot_lnk", "right_foot_link"]))
  with pytest.raises(robots.SpecError,
                     match=r"feet\[0\] \(left\): body 'left_foot_lnk' is not in the model"):
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
    with pytest.raises(
        ValueError, match=f"robot '{bad}' is unknown: expected one of "
        f"{', '.join(ROBOTS)} or the path of a robot file"):
      env_config.check_config(env_config.EnvConfig(robot=bad))
  (tmp_path / "broken.toml").write_text("name = \n")
  with pytest.raises(ValueError, match="is not valid TOML"):
    env_config.check_config(env_config.EnvConfig(robot=str(tmp_path / "broken.toml")))


def test_robot_numbers_fill_only_what_the_config_leaves_open():
  g1 = robots.load("unitree_g1")
  filled = env_config.with_robot_numbers(env_config.EnvConfig(robot="unitree_g1"), g1)
  assert (filled.fall_height, filled.swing_amplitude,
          filled.arm_swing_amplitude) == (g1.fall_height, g1.swing_amplitude,
                                          g1.arm_swing_amplitude)
  assert filled.randomization.push_force == g1.push_force == (-21.0, 21.0)
  assert filled.randomization.push_torque == g1.push_torque
  assert filled.reward_params.feet_height_target == g1.feet_height_target
  mine = dataclasses.replace(env_config.EnvConfig(robot="unitree_g1"), fall_height=0.5)
  assert env_config.with_robot_numbers(mine, g1).fall_height == 0.5
  t1 = robots.load("booster_t1")  # the T1's file holds the numbers the defaults used to be
  t1_cfg = env_config.with_robot_numbers(env_config.EnvConfig(), t1)
  assert (t1_cfg.fall_height, t1_cfg.swing_amplitude, t1_cfg.arm_swing_amplitude,
          t1_cfg.randomization.push_force, t1_cfg.randomization.push_torque,
          t1_cfg.reward_params.feet_height_target) == (0.4, 0.25, 0.3, (-20.0, 20.0), (-5.0, 5.0),
                                                       0.04)


@pytest.mark.slow
@pytest.mark.parametrize("name", ROBOTS)
def test_each_robot_steps_under_mjx_with_its_file_alone(name):
  """Each robot's env (armswing where it has arms, else bipedal) from its file alone: the
  layout's sizes, and 25 control steps (0.5 s) of the nominal robot at zero action stay finite
  with the torso within 2 cm of its standing height. (The G1 does not hold the pose for long at
  zero action: it tips over within about 2 s, see benchmarks/results/2026-12-02_g1_spec/.)"""
  spec = robots.load(name)
  task = "armswing" if spec.limbs_of("arms") else "bipedal"
  cfg = env_config.EnvConfig(robot=name, task=task)
  cfg = dataclasses.replace(cfg, randomization=dataclasses.replace(cfg.randomization,
                                                                   enabled=False))
  env = env_lib.MashEnv(cfg)
  lay = layout_lib.build(spec, cfg)
  assert env.n_joints == len(spec.joints) and env.action_size == len(lay.controlled)
  assert {g.name: (g.n_agents, g.obs_dim) for g in env.agent_groups
         } == {g: (2, lay.actor[g].size) for g in lay.actor}
  root = env.mj_model.body(spec.root_body).id

  def run(key):
    state = env.reset(key)

    def body(s, _):
      s = env.step(s, jnp.zeros((env.action_size,)))
      return s, (s.done, s.pipeline_state.xpos[root, 2], s.reward)

    return jax.lax.scan(body, state, None, length=25)[1]

  done, height, reward = jax.jit(run)(jax.random.PRNGKey(0))
  assert not bool(done.any()) and np.all(np.isfinite(np.asarray(reward)))
  assert abs(float(height[-1]) - spec.base_height_target) < 0.02, height[-1]


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


def test_robot_check_command(tmp_path, capsys):
  """``python -m experiments.robot check``: a shipped robot passes (exit 0, the figures written
  as JSON); a file with a misnamed joint is one ``error:`` line naming it (exit 2)."""
  from experiments import robot as cli
  cli.main(["check", "booster_t1", "--no-mjx", "--seconds", "2", "--out", str(tmp_path)])
  out = capsys.readouterr()
  assert "error" not in out.err and "ok: MuJoCo C: stands 2 s at zero action" in out.out
  record = json.loads((tmp_path / "booster_t1_check.json").read_text())
  assert record["robot"] == "booster_t1" and len(record["clearance_cm"]) == 2
  typo = tmp_path / "typo.toml"
  typo.write_text(
      robots.robot_file("booster_t1").read_text().replace('"Right_Hip_Roll"', '"Right_Hip_Rol"'))
  with pytest.raises(SystemExit) as e:
    cli.main(["check", str(typo), "--no-mjx", "--out", str(tmp_path)])
  err = capsys.readouterr().err.strip()
  assert e.value.code == 2 and "\n" not in err
  assert err.startswith(f"error: robot file '{typo}': limb 'right_leg' joints.hip_roll: joint "
                        "'Right_Hip_Rol' is not in the model")
