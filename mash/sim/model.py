"""The MuJoCo model of a robot: its MJCF edited for MJX in code, and the MJX model and data.

:func:`build_model` turns a :class:`mash.sim.robots.RobotSpec` into a ``mujoco.MjModel`` ready for
MJX (locked joints removed, feet-only floor contact through a few sole spheres, the explicit pairs
the collision penalty needs, motor actuators, the solver settings of :class:`PhysicsConfig`);
:func:`put_physics` places it for MJX's JAX or Warp implementation, and :func:`contact_rows`
reads an env's contacts from either.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from mash.checks import check_number
from mash.sim import robots
from mash.sim.robots import RobotSpec, SpecError


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
MAX_WARP_ENVS = 2**20  # TrainConfig's cap on num_envs (mash.rl.config.SIZE_CAPS)


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


def build_model(spec: RobotSpec, physics: PhysicsConfig = PhysicsConfig(),
                full_collision: bool = False) -> mujoco.MjModel:
  """Builds the MuJoCo model of ``spec`` from its MJCF, edited in code.

  Args:
    spec: the robot.
    physics: solver options.
    full_collision: keep the robot's own collision geoms against the floor too (used by sim2sim in
      MuJoCo C, which is not limited to MJX's collision set).

  Returns:
    A compiled ``MjModel`` with motor actuators on ``spec.joints`` (in that order), a floor, the
    sole spheres, the penalty capsules and their pairs, and a ``home`` keyframe.
  """
  mj = mujoco.MjSpec.from_file(str(robots.mjcf_file(spec)))
  try:
    robots.check_names(spec, mj)
  except SpecError as e:  # a spec built in code (a robot file's were checked when read)
    raise SpecError(f"robot '{spec.name}': {e}") from None
  for element in [*mj.keys, *mj.actuators, *mj.sensors]:
    mj.delete(element)
  for name in spec.locked_joints:
    mj.delete(mj.joint(name))
  _add_contacts(mj, spec, full_collision)
  _add_motors(mj, spec)
  _set_options(mj, physics)
  model = mj.compile()
  qpos = model.qpos0.copy()
  qpos[2] = spec.home_height
  for name in spec.joints:
    qpos[model.jnt_qposadr[model.joint(name).id]] = spec.default_pose[name]
  mj.add_key(name="home", qpos=qpos, ctrl=np.zeros(model.nu))
  return mj.compile()


def _add_contacts(mj: mujoco.MjSpec, spec: RobotSpec, full_collision: bool) -> None:
  """The floor, the sole spheres and their floor pairs, the penalty capsules and their pairs.
  No other geom collides, unless ``full_collision`` keeps the robot's own collision geoms
  (group 3) against the floor."""
  for geom in mj.geoms:
    if not full_collision or geom.group != 3:
      geom.contype = 0
      geom.conaffinity = 0
  floor = mj.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05],
                                rgba=[0.6, 0.7, 0.8, 1])
  floor.contype = 1 if full_collision else 0
  floor.conaffinity = 1 if full_collision else 0
  mj.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1],
                         type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
  for side, foot, points in zip(("left", "right"), spec.feet, spec.sole_points):
    body = mj.body(foot)
    for k, p in enumerate(points):
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


def _add_motors(mj: mujoco.MjSpec, spec: RobotSpec) -> None:
  """A torque motor on each actuated joint (the PD loop is the env's), and the robot file's
  joint model (armature, damping, friction loss) where it gives one."""
  for name in spec.joints:
    mj.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT,
                    ctrlrange=[-spec.torque_limit[name], spec.torque_limit[name]], ctrllimited=1)
    joint = mj.joint(name)
    if spec.frictionloss is not None:
      joint.frictionloss = spec.frictionloss
    if spec.armature is not None:
      joint.armature = spec.armature
    if spec.damping is not None:
      joint.damping = np.full_like(joint.damping, spec.damping)


def _set_options(mj: mujoco.MjSpec, physics: PhysicsConfig) -> None:
  """The solver settings of ``physics``: Newton, its iterations, the integrator, no Euler
  damping."""
  mj.option.timestep = physics.sim_dt
  mj.option.iterations = physics.iterations
  mj.option.ls_iterations = physics.ls_iterations
  mj.option.integrator = {
      "euler": mujoco.mjtIntegrator.mjINT_EULER,
      "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST
  }[physics.integrator]
  mj.option.solver = mujoco.mjtSolver.mjSOL_NEWTON
  mj.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_EULERDAMP


# MuJoCo's contact constraint types: condim 1, a pyramidal and an elliptic friction cone.
_CONTACT_ROWS = tuple(
    int(c) for c in (mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS,
                     mujoco.mjtConstraint.mjCNSTR_CONTACT_PYRAMIDAL,
                     mujoco.mjtConstraint.mjCNSTR_CONTACT_ELLIPTIC))


def put_physics(model: mujoco.MjModel, physics: PhysicsConfig,
                device: jax.Device) -> tuple[mjx.Model, mjx.Data]:
  """The MJX model of ``model`` and one env's fresh MJX data, for ``physics.impl``, on ``device``.

  For Warp, the contact buffer is sized for ``physics.warp_max_envs`` envs, and Warp's report of
  a solver that used all its iterations, which ours does by choice (``physics.iterations``), is off.

  Raises:
    ValueError: impl 'warp' on a device other than a GPU or the CPU.
  """
  if physics.impl == "jax":
    mjx_model = mjx.put_model(model, impl="jax", device=device)
    return mjx_model, mjx.make_data(mjx_model, impl="jax", device=device)
  if device.platform not in ("gpu", "cpu"):
    raise ValueError(f"physics.impl 'warp' runs on an NVIDIA GPU or the CPU, not on "
                     f"{device.platform} ({device.device_kind}); use impl jax")
  import warp
  from mujoco.mjx.third_party import mujoco_warp
  warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)  # no startup banner
  mjx_model = mjx.put_model(model, impl="warp", device=device)
  opt = mjx_model.opt._impl
  quiet = opt.warn_overflow & ~(mujoco_warp.OverflowType.ITERATIONS |
                                mujoco_warp.OverflowType.LS_ITERATIONS)
  mjx_model = mjx_model.replace(opt=mjx_model.opt.replace(_impl=opt.replace(
      warn_overflow=int(quiet))))
  data = mjx.make_data(model, impl="warp", device=device,
                       naconmax=2 * model.npair * physics.warp_max_envs)
  return mjx_model, data


def contact_rows(data: mjx.Data) -> tuple[jax.Array, jax.Array, jax.Array]:
  """One env's contacts as rows ``[C]``: distance (m; +inf where a row is no contact), first geom
  id, and the force of the constraint row (N; a condim-1 contact's one row is its normal force).

  MJX keeps contacts in its implementation-specific part. The JAX implementation has one fixed
  list per env (every candidate pair, touching or not), each row the contact's first constraint
  row. MuJoCo Warp keeps one buffer for all the envs of a batch (``contact__*``), so an env finds
  its contacts from its own constraint rows (``efc__*``): touching contacts only, a contact with
  friction once per row of its cone.
  """
  impl = data._impl
  if data.impl == mjx.Impl.JAX:
    return impl.contact.dist, impl.contact.geom1, impl.efc_force[impl.contact.efc_address]
  rows = jnp.arange(impl.efc__type.shape[-1])
  is_contact = (rows < impl.nefc) & jnp.isin(impl.efc__type, jnp.array(_CONTACT_ROWS))
  con = jnp.where(is_contact, impl.efc__id, 0)
  dist = jnp.where(is_contact, impl.contact__dist[con], jnp.inf)
  return dist, impl.contact__geom[con, 0], impl.efc__force
