"""The play command (``python -m experiments.play``): a trained policy walking in native MuJoCo,
for a person to watch.

:func:`resolve_policy` turns what the user typed into an ONNX file: a shipped policy
(:data:`SHIPPED`, :func:`shipped_policies`), a policy folder, an ``.onnx`` file or a run directory
(exported when stale, :func:`mash.deploy.sim2sim.resolve_onnx`). :func:`prepare` checks the
command's :class:`Options` and picks where the video goes and the OpenGL backend to render it
with; :func:`run` opens the viewer (with a display) or records one episode (:func:`record`)
through the controller a robot would run (:mod:`mash.deploy.sim2sim`).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from mash import cli
from mash.deploy import export, sim2sim
from mash.deploy import policy as policy_lib
from mash.deploy import video as video_lib
from mash.sim import robots

SHIPPED = Path(__file__).resolve().parents[1] / "assets" / "policies"


def shipped_policies() -> list[str]:
  """Names of the policies in mash/assets/policies/ (folders holding a policy.onnx)."""
  return sorted(p.name for p in SHIPPED.glob("*") if (p / "policy.onnx").is_file())


def resolve_policy(arg: str, say: Callable[[str], None]) -> tuple[Path, str]:
  """The ONNX file ``--policy`` names, and a short name for it.

  Raises:
    cli.UserError: nothing playable at ``arg`` (one line listing the shipped names).
  """
  path = Path(arg)
  if not path.exists() and "/" not in arg and (SHIPPED / arg).is_dir():
    path = SHIPPED / arg
  if path.is_file() and path.suffix == ".onnx":
    return path, path.stem
  if path.is_dir() and (path / "checkpoints").is_dir() and (path / "config.json").is_file():
    onnx_path = sim2sim.resolve_onnx(path, None, 0, say)  # a run directory: export when needed
    return onnx_path, path.name
  if path.is_dir() and (path / "policy.onnx").is_file():
    return path / "policy.onnx", path.name
  names = ", ".join(shipped_policies()) or "none installed"
  raise cli.UserError(f"--policy '{arg}': expected a shipped policy name ({names}), a policy "
                      "folder with policy.onnx, an .onnx file or a run directory")


def command_arg(text: str) -> tuple[float, float, float]:
  """``--command``: ``'VX'`` or ``'VX,VY,YAW'`` -> (vx m/s, vy m/s, yaw rate rad/s), each finite
  (two values are refused: which axis the second is would be a guess)."""
  try:
    values = [float(t) for t in text.split(",")]
  except ValueError:
    values = []
  if len(values) not in (1, 3) or not all(math.isfinite(v) for v in values):
    raise argparse.ArgumentTypeError(f"'{text}': expected VX or VX,VY,YAW_RATE (m/s, m/s, "
                                     "rad/s), e.g. 0.4 or 0.3,0,0.5")
  return tuple(values + [0.0] * (3 - len(values)))


# How far beyond its trained command range a policy is played: half the range's width.
COMMAND_MARGIN = 0.5


def check_command(command: tuple[float, float, float], trained: Mapping[str, Any] | None,
                  say: Callable[[str], None]) -> None:
  """``--command`` against the ranges the policy was trained on (``trained``: the run's
  ``env.commands``; None when the policy does not say, e.g. a bare ONNX file): a warning line
  just outside a range, an error beyond half its width (the policy never met such a command).

  Raises:
    cli.UserError: a command far outside a trained range (one line naming it and the range).
  """
  if trained is None:
    return
  for value, axis, unit in zip(command, ("vx", "vy", "yaw_rate"), ("m/s", "m/s", "rad/s")):
    lo, hi = trained[axis]
    margin = COMMAND_MARGIN * (hi - lo)
    if lo - margin <= value <= hi + margin and lo <= value <= hi:
      continue
    what = (f"--command {axis} {value:g} {unit} is outside the range the policy was trained on, "
            f"[{lo:g}, {hi:g}] {unit}")
    if not lo - margin <= value <= hi + margin:
      raise cli.UserError(f"{what}, by more than half its width; expected a command within "
                          f"[{lo - margin:g}, {hi + margin:g}] {unit}")
    say(f"warning: {what}: expect it to fall short of the command or fall")


def trained_commands(arg: str) -> Mapping[str, Any] | None:
  """The command ranges of the run or policy folder ``--policy`` names (a shipped name, a
  folder, or an ONNX file inside one: its ``config.json``), or None for an ONNX file alone."""
  path = Path(arg)
  if not path.exists() and "/" not in arg and (SHIPPED / arg).is_dir():
    path = SHIPPED / arg
  folder = path.parent if path.is_file() else path
  if not (folder / policy_lib.CONFIG).is_file():
    return None
  return dataclasses.asdict(policy_lib.load_config(folder).env.commands)


def seconds_arg(text: str) -> float:
  """``--seconds``: a duration in (0, 3600] s."""
  try:
    value = float(text)
  except ValueError:
    value = float("nan")
  if not 0 < value <= 3600:
    raise argparse.ArgumentTypeError(f"'{text}': expected a duration in (0, 3600] seconds")
  return value


@dataclasses.dataclass(frozen=True)
class Options:
  """The command's arguments (one field per flag, named as argparse names it).

  Attributes:
    policy: shipped policy name, policy folder, ``.onnx`` file or run directory.
    command: (vx m/s, vy m/s, yaw rate rad/s) when playing headless.
    stand: the standing command instead.
    seconds: how long to play headless (s).
    video: the ``.mp4`` or ``.gif`` to write, or None: the viewer with a display, else
      ``<policy name>.mp4``.
    phase: initial gait phase in [0, 1).
    robot: the robot file to play on, or None: the shipped robot the policy names.
  """

  policy: str
  command: tuple[float, float, float] = (0.4, 0.0, 0.0)
  stand: bool = False
  seconds: float = 10.0
  video: str | None = None
  phase: float = 0.0
  robot: str | None = None


def prepare(o: Options, say: Callable[[str], None]) -> tuple[Options, str | None]:
  """Checks the options before any work and picks the output: the viewer when there is a display
  and no ``--video``, else a video, by default ``<policy name>.mp4`` (said in one line).

  Returns:
    ``(options, backend)``: the options with the video's file name (None: the viewer), and the
    OpenGL backend to render it with (:func:`mash.deploy.video.headless_gl`; None: the viewer).

  Raises:
    cli.UserError: one line naming the flag, or that no OpenGL backend renders here.
  """
  if not 0.0 <= o.phase < 1.0:
    raise cli.UserError(f"--phase {o.phase}: expected a gait phase in [0, 1)")
  cli.check_paths({"--policy": o.policy})
  if not o.stand:
    check_command(o.command, trained_commands(o.policy), say)
  viewer = o.video is None and video_lib.has_display()
  video = o.video
  cli.check_paths({"--policy": o.policy, "--video": video})
  if viewer:
    return o, None
  if video is None:
    video = f"{Path(o.policy.rstrip('/')).stem or 'policy'}.mp4"
    cli.check_path(video, "the video's file name (--video)")
    say(f"no display: playing headless, the video goes to {video}")
  if Path(video).suffix.lower() not in (".mp4", ".gif"):
    raise cli.UserError(f"--video '{cli.shown_path(video)}': expected a .mp4 (or .gif) file name")
  cli.check_writable_file(video, "--video")
  # MuJoCo is already imported (with mash): the backend goes to the video writer, not MUJOCO_GL.
  backend, reason = video_lib.headless_gl()
  if backend is None:
    raise cli.UserError(f"cannot render a video: {reason}")
  return dataclasses.replace(o, video=video), backend


def robot_of(onnx_path: Path, meta: Mapping[str, Any], robot: str | None) -> robots.RobotSpec:
  """The robot to play ``onnx_path`` on: ``robot`` (a name or file), else the shipped robot its
  metadata names.

  Raises:
    cli.UserError: the policy's robot is not shipped and none is given, or ``robot`` is another.
  """
  robot_name = meta.get("robot")
  if robot is None and robot_name not in robots.names():
    raise cli.UserError(f"'{onnx_path}' was exported for robot '{robot_name}', which this "
                        f"version does not ship (shipped: {', '.join(robots.names())}); "
                        "pass its robot file with --robot FILE.toml")
  spec = robots.load(robot or robot_name)
  if spec.name != robot_name:
    raise cli.UserError(f"--robot {robot} is robot '{spec.name}', but '{onnx_path}' was "
                        f"exported for robot '{robot_name}'")
  return spec


def record(o: Options, onnx_path: Path, spec: robots.RobotSpec, meta: Mapping[str, Any],
           backend: str | None, say: Callable[[str], None]) -> None:
  """One episode of ``o.seconds`` at ``o.command`` (or standing) from gait phase ``o.phase``,
  rendered to ``o.video`` with OpenGL ``backend``; says how far the robot walked."""
  vx, vy, yaw = o.command
  cfg = sim2sim.Sim2SimConfig(command_vx=vx, num_episodes=1, episode_s=o.seconds)
  dep = sim2sim.Deployment.from_metadata(meta)
  robot = sim2sim.NativeRobot(spec, dep, cfg)
  controller = sim2sim.Controller(export.onnx_session(onnx_path), dep)
  command = np.array([1.0, 0.0, 0.0, 0.0]) if o.stand else np.array([0.0, vx, vy, yaw])
  steps = max(1, int(round(o.seconds / dep.ctrl_dt)))
  gif = Path(o.video).suffix.lower() == ".gif"  # small and slow: for a README or a slide
  fps, (width, height) = (12.5, (400, 300)) if gif else (25.0, (640, 480))
  say(f"playing {onnx_path} for {o.seconds:g} s at " +
      ("the standing command" if o.
       stand else f"vx {vx:+.2f} m/s, vy {vy:+.2f} m/s, yaw rate {yaw:+.2f} rad/s") +
      f" (rendering {int(o.seconds * fps)} frames, about {0.12 * o.seconds * fps:.0f} s "
      "on a CPU)")
  writer = video_lib.VideoWriter(robot.model, o.video, fps, robot.root, width, height, backend)
  t0 = time.perf_counter()
  try:
    traj = sim2sim.run_episode(robot, controller, command, steps, o.phase,
                               spec.role_indices("hip_pitch", "legs"), writer,
                               frame_every=max(1, int(round(1.0 / (dep.ctrl_dt * fps)))))
  finally:
    writer.close()
  alive = traj["alive"]  # [T]
  held = alive.sum() * dep.ctrl_dt
  speed = float((traj["forward_velocity"] * alive).sum() / max(alive.sum(), 1.0))
  say(("fell after " if alive.min() == 0 else "walked ") + f"{held:.1f} s, mean vx "
      f"{speed:+.3f} m/s, yaw rate {mean_yaw_rate(traj['euler'], alive, dep.ctrl_dt):+.3f} rad/s; "
      f"wrote {o.video} ({writer.frames} frames, {time.perf_counter() - t0:.0f} s)")


def mean_yaw_rate(euler: np.ndarray, alive: np.ndarray, dt: float) -> float:
  """The torso's mean yaw rate (rad/s) over the steps alive: its net heading change, unwrapped
  across +-pi, over their time. ``euler`` ``[T, 3]`` (roll, pitch, yaw), ``alive`` ``[T]``."""
  n = int(np.asarray(alive).sum())
  if n < 2:
    return 0.0
  yaw = np.unwrap(np.asarray(euler)[:n, 2])
  return float((yaw[-1] - yaw[0]) / ((n - 1) * dt))


def run(o: Options, backend: str | None, say: Callable[[str], None] = print) -> None:
  """The command after :func:`prepare`: the viewer (``o.video`` None) or :func:`record`.

  Raises:
    mash.errors.InputError: a policy, robot or ONNX file that cannot be used (one line).
  """
  onnx_path, _ = resolve_policy(o.policy, say)
  meta = export.read_metadata(onnx_path)
  spec = robot_of(onnx_path, meta, o.robot)
  if o.video is None:
    say(f"{onnx_path}: viewer; up/down vx +-0.1 m/s, left/right yaw rate +-0.1 rad/s, space "
        "stand/walk, backspace reset; close the window to quit")
    cfg = sim2sim.Sim2SimConfig(command_vx=o.command[0], num_episodes=1, episode_s=o.seconds)
    sim2sim.interactive(onnx_path, spec, cfg, say)
    return
  record(o, onnx_path, spec, meta, backend, say)
