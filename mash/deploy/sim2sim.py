"""Sim-to-sim transfer: the exported ONNX policy driving the robot in native MuJoCo C.

The controller here is what a robot would run: it knows only the ONNX file (joint order, default
pose, PD gains, action scale and control period come from its metadata), reads joint angles and
velocities, torso orientation and angular velocity, runs the policy at the control rate
(``ctrl_dt``, 50 Hz), holds the position targets for the control period and computes the clipped
PD torque in NumPy on every physics step. The physics differs from training on purpose: MuJoCo C
(``mujoco.MjModel`` / ``MjData``, not MJX), a smaller time step, the implicit-fast integrator, ten
or more Newton iterations and the robot's full collision geometry against the floor
(:func:`physics`). Episodes run at a fixed forward command; their trajectories have the layout of
:func:`mash.analysis.evaluation.rollout`, so the paper's metrics are computed by the same code
(:func:`mash.analysis.evaluation.evaluate`) and compared with the MJX evaluation in ``report.md``
(:mod:`mash.deploy.native_report`). :func:`resolve_onnx` finds the ONNX file of a run directory or
policy folder, exported again when it is missing or older than the latest checkpoint.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

import mujoco
import numpy as np

from mash import cli
from mash.checks import MAX_INT32, Bound, check_bounds
from mash.deploy import export
from mash.deploy import policy as policy_lib
from mash.deploy.video import VideoWriter
from mash.sim import geometry, robots
from mash.sim import model as model_lib


@dataclasses.dataclass(frozen=True)
class Sim2SimConfig:
  """Attributes:
    command_vx: fixed forward command (m/s).
    num_episodes: episodes (each from the home pose, with its own random initial gait phase).
    episode_s: episode duration (s).
    sim_dt: physics step (s); must divide the policy's control period.
    iterations: Newton solver iterations.
    ls_iterations: line-search iterations.
    integrator: 'implicitfast' (or 'euler').
    full_collision: the robot's own collision geometry collides with the floor too.
    seed: seed of the initial phases.

  The sane range of every number is checked by :func:`check_config`.
  """

  command_vx: float = 0.4
  num_episodes: int = 4
  episode_s: float = 20.0
  sim_dt: float = 0.002
  iterations: int = 10
  ls_iterations: int = 20
  integrator: str = "implicitfast"
  full_collision: bool = True
  seed: int = 0


MAX_EPISODES = 10_000
MAX_EPISODE_S = 3600.0
MIN_SIM_DT = 1e-5  # 100 kHz; a smaller step makes a control period take forever
BOUNDS = (
    Bound("command_vx", -10.0, 10.0, "m/s"),
    Bound("num_episodes", 1, MAX_EPISODES),
    Bound("episode_s", 0.0, MAX_EPISODE_S, "s", open_low=True),
    Bound("sim_dt", MIN_SIM_DT, 0.1, "s"),
    Bound("seed", 0, MAX_INT32),
)


def check_config(cfg: Sim2SimConfig, labels: Mapping[str, str] | None = None) -> None:
  """Checks a :class:`Sim2SimConfig` without building anything: a forward command within +-10
  m/s, 1 to 10 000 episodes of (0, 3600] s, a physics step in [1e-5, 0.1] s, solver settings as
  :func:`mash.sim.model.check_physics` wants them and a seed in [0, 2**31 - 1]. NaN and inf never
  pass. That ``sim_dt`` divides the policy's control period is checked where the policy is read.

  Args:
    cfg: the settings.
    labels: how to name a field in the message (a command line passes its flags, e.g.
      ``{'sim_dt': '--sim-dt'}``); a field not in it is named as it is.

  Raises:
    ValueError: one line naming the field, its value and what was expected.
  """
  check_bounds(cfg, BOUNDS, labels)
  try:
    model_lib.check_physics(physics(cfg))
  except ValueError as e:
    field, rest = str(e).split(" ", 1)
    raise ValueError(f"{(labels or {}).get(field, field)} {rest}") from None


def physics(cfg: Sim2SimConfig) -> model_lib.PhysicsConfig:
  """The MuJoCo C physics settings of ``cfg`` (time step, solver, integrator)."""
  return model_lib.PhysicsConfig(sim_dt=cfg.sim_dt, iterations=cfg.iterations,
                                 ls_iterations=cfg.ls_iterations, integrator=cfg.integrator)


def physics_record(cfg: Sim2SimConfig, ctrl_dt: float) -> dict[str, Any]:
  """The physics a report names (its ``physics``): the engine and its version, the time steps
  (s), the solver and the collision set; never domain randomization."""
  return {
      "engine": "mujoco C " + mujoco.__version__, "sim_dt": cfg.sim_dt, "iterations":
          cfg.iterations, "ls_iterations": cfg.ls_iterations, "integrator": cfg.integrator,
      "full_collision": cfg.full_collision, "ctrl_dt": float(ctrl_dt), "domain_randomization": False
  }


def latest_step(run_dir: Path) -> int | None:
  """The newest complete checkpoint step of a run, from its directory names (None for a policy
  folder)."""
  steps = [
      int(p.name)
      for p in (run_dir / "checkpoints").glob("*")
      if p.name.isdigit() and not any(p.glob("*.orbax-checkpoint-tmp*"))
  ]
  return max(steps) if steps else None


def resolve_onnx(run_dir: Path, onnx_arg: str | None, seed: int, say: Callable[[str], None],
                 robot: str | None = None) -> Path:
  """The ONNX policy to run: ``--onnx``, an up-to-date ``DIR/policy.onnx``, or a fresh export.

  Args:
    run_dir: a run directory or a policy folder (:mod:`mash.deploy.policy`).
    onnx_arg: the ``--onnx`` file given, or None.
    seed: which seed of a multi-seed run.
    say: prints one line (which file, and whether it was reused or exported).
    robot: the robot file to use instead of the run's ``env.robot``, or None.

  Raises:
    cli.UserError: ``--onnx`` names no file.
    export.ExportError: the policy cannot be exported.
  """
  if onnx_arg:
    path = Path(onnx_arg)
    if not path.is_file():
      raise cli.UserError(f"--onnx '{path}' does not exist; expected an exported policy")
    say(f"using {path} as given")
    return path
  path = run_dir / "policy.onnx"
  if path.is_file():
    try:
      meta = export.read_metadata(path)
    except Exception:  # an unreadable file is replaced below
      meta = {}
    current = (latest_step(run_dir), seed)
    if policy_lib.is_policy_folder(run_dir) and seed == 0:  # its one policy
      info = policy_lib.folder_info(run_dir)
      current = (info["iteration"], info["seed"])
    if (meta.get("checkpoint_iteration"), meta.get("seed")) == current:
      say(f"reusing {path} (checkpoint iteration {meta['checkpoint_iteration']})")
      return path
  policy = policy_lib.load(run_dir, seed=seed, robot=robot)
  export.export_policy(policy, path)
  say(f"exported {path} (checkpoint iteration {policy.iteration}, seed {policy.seed})")
  return path


class Deployment(NamedTuple):
  """What the robot side needs, read from the ONNX metadata (all joint tables in joint order).

  Attributes:
    joints: actuated joint names. ctrl: ``[A]`` positions of the controlled joints in ``joints``.
    default: ``[J]`` default pose (rad). kp, kd, torque_limit: ``[J]`` PD gains and limits.
    ctrl_dt: control period (s). gait_cycle_s: gait period (s).
    fall_height: torso height (m) under which the robot has fallen.
    fall_tilt: the |roll| or |pitch| (rad) beyond which it has fallen.
  """

  joints: tuple[str, ...]
  ctrl: np.ndarray
  default: np.ndarray
  kp: np.ndarray
  kd: np.ndarray
  torque_limit: np.ndarray
  ctrl_dt: float
  gait_cycle_s: float
  fall_height: float
  fall_tilt: float

  @classmethod
  def from_metadata(cls, meta: Mapping[str, Any]) -> "Deployment":
    missing = [
        k for k in ("joint_order", "controlled_index", "default_pose_rad", "kp", "kd",
                    "torque_limit_nm", "ctrl_dt_s", "gait_cycle_s") if k not in meta
    ]
    if missing:
      raise export.ExportError(f"the ONNX file has no metadata '{missing[0]}': not a MASH policy "
                               "export (python -m experiments.export)")
    f = lambda k: np.asarray(meta[k], np.float64)
    return cls(tuple(meta["joint_order"]), np.asarray(meta["controlled_index"], np.int64),
               f("default_pose_rad"), f("kp"), f("kd"), f("torque_limit_nm"),
               float(meta["ctrl_dt_s"]), float(meta["gait_cycle_s"]),
               float(meta.get("fall_height_m", 0.4)), float(meta.get("fall_tilt_rad", 1.0)))


class NativeRobot:
  """The robot in MuJoCo C: sensor reads and the PD loop, as on hardware; :meth:`perturb` changes
  its floor, torso mass and motors (the robustness battery, :mod:`mash.deploy.native_battery`)."""

  def __init__(self, spec: robots.RobotSpec, dep: Deployment, cfg: Sim2SimConfig):
    n_sub = dep.ctrl_dt / cfg.sim_dt
    if cfg.sim_dt <= 0 or abs(n_sub - round(n_sub)) > 1e-6 or round(n_sub) < 1:
      raise export.ExportError(f"sim_dt {cfg.sim_dt} must divide the policy's control period "
                               f"{dep.ctrl_dt} s")
    if cfg.integrator not in ("implicitfast", "euler"):
      raise export.ExportError(f"integrator '{cfg.integrator}' is unknown; expected implicitfast "
                               "or euler")
    self.spec, self.dep, self.n_substeps = spec, dep, int(round(n_sub))
    self.model = model_lib.build_model(spec, physics(cfg), full_collision=cfg.full_collision)
    self.data = mujoco.MjData(self.model)
    m = self.model
    missing = [j for j in dep.joints if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j) < 0]
    if missing:
      raise export.ExportError(f"joint '{missing[0]}' of the policy is not in robot '{spec.name}'")
    if tuple(dep.joints) != spec.joints:  # joint-indexed tables (spec.role_indices) would be off
      raise export.ExportError(f"the policy's joints are not those of robot '{spec.name}' in its "
                               "order; export it again for this robot")
    ids = [m.joint(j).id for j in dep.joints]
    self.qadr = np.array([m.jnt_qposadr[i] for i in ids])
    self.dadr = np.array([m.jnt_dofadr[i] for i in ids])
    self.act = np.array([m.actuator(j).id for j in dep.joints])
    n_sole = len(spec.sole_points[0])
    self.soles = np.array(
        [[m.geom(f"{side}_sole_{k}").id for k in range(n_sole)] for side in ("left", "right")])
    self.root = m.body(spec.root_body).id
    self.home = m.key("home").id
    self.floor_pairs = np.array([
        m.pair(f"{side}_sole_{k}_floor").id for side in ("left", "right") for k in range(n_sole)
    ])
    self.floor = m.geom("floor").id
    self._nominal = (m.pair_friction[self.floor_pairs].copy(), m.geom_friction[self.floor].copy(),
                     int(m.geom_priority[self.floor]), float(m.body_mass[self.root]),
                     m.body_inertia[self.root].copy(), m.actuator_ctrlrange[self.act].copy())
    self.strength = np.ones(len(dep.joints))

  def perturb(self, friction: float = -1.0, mass: float = 1.0,
              strength: np.ndarray | None = None) -> None:
    """Sets the floor and the robot for the next episodes (the defaults: the nominal robot).

    Args:
      friction: the floor-sole pairs' sliding friction (both tangential coefficients, as the
        MJX domain randomization sets it) and the floor's, which then takes precedence in its
        contacts with the robot's own collision geometry (the feet's boxes touch the floor too
        under full collision); negative: the model's own.
      mass: the torso's mass and inertia times this.
      strength: ``[J]`` each motor's torque and its limit times this (None: 1).
    """
    m = self.model
    pair_friction, floor_friction, floor_priority, body_mass, body_inertia, ctrlrange = (
        self._nominal)
    m.pair_friction[self.floor_pairs] = pair_friction
    m.geom_friction[self.floor] = floor_friction
    m.geom_priority[self.floor] = floor_priority
    if friction >= 0:
      m.pair_friction[self.floor_pairs, 0:2] = friction
      m.geom_friction[self.floor, 0] = friction
      m.geom_priority[self.floor] = int(m.geom_priority.max()) + 1
    m.body_mass[self.root] = body_mass * mass
    m.body_inertia[self.root] = body_inertia * mass
    self.strength = np.ones(len(self.dep.joints)) if strength is None else np.asarray(strength)
    m.actuator_ctrlrange[self.act] = ctrlrange * self.strength[:, None]

  def reset(self) -> None:
    mujoco.mj_resetDataKeyframe(self.model, self.data, self.home)
    mujoco.mj_forward(self.model, self.data)

  def sensors(self) -> dict[str, np.ndarray]:
    """Joint and torso readings (the env's ``sensors``), plus foot contacts and base height."""
    d = self.data
    quat = d.qpos[3:7].copy()
    conj = quat * np.array([1.0, -1.0, -1.0, -1.0])
    lin_vel = np.zeros(3)
    mujoco.mju_rotVecQuat(lin_vel, d.qvel[0:3], conj)
    sole_z = d.geom_xpos[self.soles][..., 2] - self.spec.sole_radius
    touching = d.contact.geom[:d.ncon][d.contact.dist[:d.ncon] < 1e-3]  # [n, 2] geom ids
    contact = np.array([np.isin(touching, self.soles[side]).any() for side in range(2)], float)
    return dict(q=d.qpos[self.qadr].copy(), dq=d.qvel[self.dadr].copy(), quat=quat,
                euler=geometry.quat_to_euler(quat), ang_vel=d.qvel[3:6].copy(), lin_vel=lin_vel,
                base_height=float(d.qpos[2] - np.min(sole_z)), contact=contact,
                xy=d.qpos[0:2].copy())

  def step(self, q_target: np.ndarray) -> None:
    """One control period: PD torques from ``q_target [J]`` on every physics step (clipped to the
    limits, then times the motors' :attr:`strength`)."""
    d, dep = self.data, self.dep
    for _ in range(self.n_substeps):
      tau = dep.kp * (q_target - d.qpos[self.qadr]) - dep.kd * d.qvel[self.dadr]
      d.ctrl[self.act] = self.strength * np.clip(tau, -dep.torque_limit, dep.torque_limit)
      mujoco.mj_step(self.model, d)

  def fallen(self, s: Mapping[str, Any]) -> bool:
    """The env's fall condition: torso too low, too tilted, or the state not finite."""
    finite = np.all(np.isfinite(self.data.qpos)) and np.all(np.isfinite(self.data.qvel))
    return bool(s["base_height"] < self.dep.fall_height or
                abs(s["euler"][0]) > self.dep.fall_tilt or
                abs(s["euler"][1]) > self.dep.fall_tilt or not finite)


class Controller:
  """The policy side: ONNX inference, the gait clock and the action feedback.

  With a ``delay`` of d control steps, the action reaches the motors d steps after the policy
  chose it (zero actions, the default pose, before the first), and the action fed back to the
  policy is the one applied, as the MJX battery does it (:mod:`mash.analysis.robustness`).
  """

  def __init__(self, session, dep: Deployment, delay: int = 0):
    self.session, self.dep, self.delay = session, dep, int(delay)
    self.phase = 0.0
    self.last_action = np.zeros(len(dep.ctrl), np.float32)
    self.queue: deque[tuple[np.ndarray, np.ndarray]] = deque()

  def reset(self, phase: float) -> None:
    self.phase = float(phase)
    self.last_action[:] = 0.0
    self.queue = deque(
        (self.last_action.copy(), self.dep.default.copy()) for _ in range(self.delay))

  def act(self, s: Mapping[str, Any], command: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Policy on the current readings; returns the (action [A], full PD target [J]) to apply now
    and advances the gait clock (frozen while ``command[0]``, the standing flag, is set)."""
    row = lambda x: np.asarray(x, np.float32).reshape(1, -1)
    inputs = {
        "q": row(s["q"]), "dq": row(s["dq"]), "last_action": row(self.last_action),
        "gait_phase": row([self.phase]), "euler": row(s["euler"]), "ang_vel": row(s["ang_vel"]),
        "command": row(command)
    }
    action, q_target = self.session.run(list(export.OUTPUTS), inputs)
    action = action[0]
    target = self.dep.default.copy()
    target[self.dep.ctrl] = q_target[0]
    if self.delay:
      self.queue.append((action, target))
      action, target = self.queue.popleft()
    self.last_action = action.copy()
    if command[0] <= 0:
      self.phase = (self.phase + self.dep.ctrl_dt / self.dep.gait_cycle_s) % 1.0
    return action, target


def run_episode(robot: NativeRobot, controller: Controller, command: np.ndarray, steps: int,
                phase: float, hips: Any, video: VideoWriter | None = None, frame_every: int = 1,
                video_steps: int | None = None,
                sense: Callable[[dict[str, Any]], Mapping[str, Any]] | None = None,
                kick: tuple[int, np.ndarray] | None = None) -> dict[str, np.ndarray]:
  """One episode of ``steps`` control steps from the home pose at gait ``phase``.

  Returns ``[T, ...]`` arrays in the layout of :func:`mash.analysis.evaluation.rollout` (after a
  fall the last sample is repeated with ``alive = 0``) plus ``phase [T]`` (the clock after each
  step) and ``xy [T, 2]`` (torso position, m). ``hips`` indexes the two hip pitches in the joints
  (``spec.role_indices("hip_pitch", "legs")``). ``video`` gets a frame every ``frame_every``
  steps for the first ``video_steps`` steps (all when None). ``sense`` maps the readings to what
  the controller reads (None: the readings), e.g. adds sensor noise; ``kick`` ``(t, [2] m/s)``
  adds the velocity to the torso's (world frame) after the controller acted at step ``t``,
  before the physics of that step.
  """
  video_steps = steps if video_steps is None else video_steps
  robot.reset()
  controller.reset(phase)
  keys = ("actions", "base_height", "euler", "hip_pitch", "forward_velocity", "contact", "phase",
          "xy")
  out = {k: [] for k in keys}
  alive = np.zeros(steps, np.float32)
  s = robot.sensors()
  if video is not None:
    video.add(robot.data)
  for t in range(steps):
    action, target = controller.act(s if sense is None else sense(s), command)
    if kick is not None and t == kick[0]:
      robot.data.qvel[0:2] += kick[1]
    robot.step(target)
    s = robot.sensors()
    for k, v in (("actions", action), ("base_height", s["base_height"]), ("euler", s["euler"]),
                 ("hip_pitch", s["q"][hips]), ("forward_velocity", s["lin_vel"][0]),
                 ("contact", s["contact"]), ("phase", controller.phase), ("xy", s["xy"])):
      out[k].append(np.asarray(v, np.float64))
    alive[t] = 1.0
    if video is not None and (t + 1) % frame_every == 0 and t < video_steps:
      video.add(robot.data)
    if robot.fallen(s):
      break
  n = len(out["actions"])
  traj = {k: np.stack(v + [v[-1]] * (steps - n)) for k, v in out.items()}
  traj["alive"] = alive
  return traj


class SimResult(NamedTuple):
  """What :func:`simulate` returns.

  Attributes:
    traj: ``[E, T, ...]`` trajectories (``actions``, ``base_height``, ``euler``, ``hip_pitch``,
      ``hip_pitch_ref`` when a gait reference is given, ``forward_velocity``, ``alive``,
      ``contact``, ``phase``, ``xy``), ``dt`` and ``wall_s [E]`` (wall time per episode).
    video_frames: frames written to the video (0 without one).
    video_error: why the video was not written, or None.
  """

  traj: dict[str, np.ndarray]
  video_frames: int
  video_error: str | None


def simulate(onnx_path: str | os.PathLike, spec: robots.RobotSpec, cfg: Sim2SimConfig,
             gait_reference: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
             video: str | os.PathLike | None = None, video_fps: float = 25.0,
             video_seconds: float | None = None, video_backend: str | None = None,
             progress: Callable[[str], None] | None = print) -> SimResult:
  """Runs ``cfg.num_episodes`` episodes of the ONNX policy in MuJoCo C.

  Args:
    onnx_path: an exported policy (:func:`mash.deploy.export.export_policy`).
    spec: the robot it was trained on.
    cfg: episodes and physics.
    gait_reference: optional ``(phase [T], standing [T]) -> hip_pitch_ref [T, 2]`` (absolute, rad)
      to store the temporal director's reference beside the hip angles.
    video: MP4 path; the first episode is rendered (if rendering cannot start, the episodes run
      without it and ``SimResult.video_error`` says why).
    video_fps: frames per second of the video (a divisor of the control rate works best).
    video_seconds: render at most this long (default: the whole first episode).
    video_backend: the OpenGL backend to render with (:func:`mash.deploy.video.headless_gl`
      finds one; None: the one MuJoCo chose from ``MUJOCO_GL`` when imported).
    progress: called with one line per episode.

  Returns:
    :class:`SimResult`.
  """
  dep = Deployment.from_metadata(export.read_metadata(onnx_path))
  robot = NativeRobot(spec, dep, cfg)
  controller = Controller(export.onnx_session(onnx_path), dep)
  hips = spec.role_indices("hip_pitch", "legs")
  steps = max(1, int(round(cfg.episode_s / dep.ctrl_dt)))
  command = np.array([0.0, cfg.command_vx, 0.0, 0.0])
  phases = np.random.default_rng(cfg.seed).uniform(0.0, 1.0, cfg.num_episodes)
  trajs, walls = [], []
  frames, video_error = 0, None
  for e in range(cfg.num_episodes):
    writer = None
    if video is not None and e == 0:
      try:
        writer = VideoWriter(robot.model, video, video_fps, robot.root, backend=video_backend)
      except Exception as err:  # no OpenGL context / no ffmpeg: run without the video
        video_error = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
        if progress is not None:
          progress(f"video skipped: {video_error}")
    frame_every = max(1, int(round(1.0 / (dep.ctrl_dt * video_fps))))
    t0 = time.perf_counter()
    video_steps = None if video_seconds is None else max(1, int(round(video_seconds / dep.ctrl_dt)))
    try:
      traj = run_episode(robot, controller, command, steps, phases[e], hips, writer, frame_every,
                         video_steps)
    finally:
      if writer is not None:
        writer.close()
        frames = writer.frames
    walls.append(time.perf_counter() - t0)
    trajs.append(traj)
    if progress is not None:
      alive = traj["alive"]
      t_alive = alive.sum() * dep.ctrl_dt
      fell = alive.min() == 0
      vx = float((traj["forward_velocity"] * alive).sum() / max(alive.sum(), 1.0))
      sim_s = alive.sum() * dep.ctrl_dt
      progress(f"episode {e + 1}/{cfg.num_episodes}: " +
               (f"fell at {t_alive:.2f} s" if fell else f"survived {t_alive:.1f} s") +
               f", mean vx {vx:+.3f} m/s (command {cfg.command_vx:g}), "
               f"{walls[-1]:.1f} s wall ({sim_s / max(walls[-1], 1e-9):.1f}x real time)" +
               (f", video {writer.frames} frames -> {video}" if writer is not None else ""))
  out = {k: np.stack([t[k] for t in trajs]) for k in trajs[0]}
  if gait_reference is not None:
    standing = np.zeros_like(out["phase"])
    # The reference of the state reached after each step, from the clock after that step.
    out["hip_pitch_ref"] = np.stack([gait_reference(p, s) for p, s in zip(out["phase"], standing)])
  out["dt"] = np.asarray(dep.ctrl_dt)
  out["wall_s"] = np.asarray(walls)
  return SimResult(out, frames, video_error)


def interactive(onnx_path: str | os.PathLike, spec: robots.RobotSpec, cfg: Sim2SimConfig,
                print_fn: Callable[[str], None] = print) -> None:
  """``mujoco.viewer`` with keyboard commands: up/down vx +-0.1 m/s, left/right yaw rate
  +-0.1 rad/s, space toggles standing, backspace resets; the robot is reset when it falls."""
  import mujoco.viewer  # opens a window through GLFW: only where there is a display

  dep = Deployment.from_metadata(export.read_metadata(onnx_path))
  robot = NativeRobot(spec, dep, cfg)
  controller = Controller(export.onnx_session(onnx_path), dep)
  command = np.array([0.0, cfg.command_vx, 0.0, 0.0])
  state = {"reset": True}
  keys = {265: (1, 0.1), 264: (1, -0.1), 263: (3, 0.1), 262: (3, -0.1)}  # GLFW arrow codes

  def on_key(code: int) -> None:
    if code in keys:
      i, dv = keys[code]
      command[i] = float(np.clip(command[i] + dv, -1.0, 1.0))
    elif code == 32:  # space
      command[0] = 1.0 - command[0]
    elif code == 259:  # backspace
      state["reset"] = True
    print_fn(f"command: standing {int(command[0])}, vx {command[1]:+.1f} m/s, "
             f"yaw rate {command[3]:+.1f} rad/s")

  with mujoco.viewer.launch_passive(robot.model, robot.data, key_callback=on_key) as viewer:
    while viewer.is_running():
      if state["reset"]:
        robot.reset()
        controller.reset(0.0)
        state["reset"] = False
      t0 = time.perf_counter()
      s = robot.sensors()
      _, target = controller.act(s, command if command[0] <= 0 else np.array([1.0, 0.0, 0.0, 0.0]))
      robot.step(target)
      if robot.fallen(robot.sensors()):
        state["reset"] = True
      viewer.sync()
      time.sleep(max(0.0, dep.ctrl_dt - (time.perf_counter() - t0)))
