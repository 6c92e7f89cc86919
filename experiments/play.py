"""``python -m experiments.play --policy NAME``: a trained policy walking in native MuJoCo.

NAME is a shipped policy (a folder of assets/policies/, e.g. t1_bipedal_mash), a policy folder
holding policy.onnx, an ONNX file, or a run directory (its policy.onnx, exported first when it is
missing or older than the run's latest checkpoint). It plays the ONNX file in MuJoCo C through
the controller a robot would run (mash.sim2sim), without the training code.

With a display, MuJoCo's viewer opens with keyboard commands (up/down: forward speed +-0.1 m/s,
left/right: yaw rate +-0.1 rad/s, space: stand / walk, backspace: reset). Without one, or with
--video, the policy plays --seconds at --command and writes an MP4 or a GIF (software rendering:
about 0.1 s per frame on a CPU).

Examples:
  python -m experiments.play --policy t1_bipedal_mash
  python -m experiments.play --policy t1_bipedal_mash --video walk.mp4 --seconds 10 --command 0.6,0,0
  python -m experiments.play --policy runs/bipedal_mash_cpu_X --stand --video stand.mp4
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

from experiments import common

SHIPPED = Path(__file__).resolve().parents[1] / "assets" / "policies"


def shipped_policies() -> list[str]:
  """Names of the policies in assets/policies/ (folders holding a policy.onnx)."""
  return sorted(p.name for p in SHIPPED.glob("*") if (p / "policy.onnx").is_file())


def resolve_policy(arg: str, say) -> tuple[Path, str]:
  """The ONNX file ``--policy`` names, and a short name for it.

  Raises:
    common.UserError: nothing playable at ``arg`` (one line listing the shipped names).
  """
  path = Path(arg)
  if not path.exists() and "/" not in arg and (SHIPPED / arg).is_dir():
    path = SHIPPED / arg
  if path.is_file() and path.suffix == ".onnx":
    return path, path.stem
  if path.is_dir() and (path / "checkpoints").is_dir() and (path / "config.json").is_file():
    from experiments.sim2sim import resolve_onnx  # a run directory: export when needed (JAX)
    onnx_path, _ = resolve_onnx(path, None, 0, say)
    return onnx_path, path.name
  if path.is_dir() and (path / "policy.onnx").is_file():
    return path / "policy.onnx", path.name
  names = ", ".join(shipped_policies()) or "none installed"
  raise common.UserError(f"--policy '{arg}': expected a shipped policy name ({names}), a policy "
                         "folder with policy.onnx, an .onnx file or a run directory")


def _command(text: str) -> tuple[float, float, float]:
  """``'VX[,VY[,YAW]]'`` -> (vx m/s, vy m/s, yaw rate rad/s), each finite."""
  try:
    values = [float(t) for t in text.split(",")]
  except ValueError:
    values = []
  if not 1 <= len(values) <= 3 or not all(math.isfinite(v) for v in values):
    raise argparse.ArgumentTypeError(f"'{text}': expected VX[,VY[,YAW_RATE]] (m/s, m/s, rad/s), "
                                     "e.g. 0.4 or 0.3,0,0.5")
  return tuple(values + [0.0] * (3 - len(values)))


def _seconds(text: str) -> float:
  try:
    value = float(text)
  except ValueError:
    value = float("nan")
  if not 0 < value <= 3600:
    raise argparse.ArgumentTypeError(f"'{text}': expected a duration in (0, 3600] seconds")
  return value


def has_display() -> bool:
  return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def main(argv=None) -> None:
  p = common.Parser(prog="python -m experiments.play", description=__doc__.splitlines()[0],
                    formatter_class=argparse.RawDescriptionHelpFormatter,
                    epilog="\n".join(__doc__.splitlines()[2:]))
  p.add_argument("--policy", required=True,
                 help="shipped policy name, policy folder, .onnx file or run directory")
  p.add_argument("--command", type=_command, default=(0.4, 0.0, 0.0), metavar="VX[,VY,YAW]",
                 help="velocity command when playing headless (default 0.4,0,0)")
  p.add_argument("--stand", action="store_true", help="the standing command instead")
  p.add_argument("--seconds", type=_seconds, default=10.0, help="how long to play headless")
  p.add_argument("--video", default=None, metavar="OUT.mp4",
                 help="write an MP4 (or an animated GIF: OUT.gif, 400x300 at 12.5 fps) instead of "
                      "opening the viewer (the default without a display: <policy name>.mp4)")
  p.add_argument("--phase", type=float, default=0.0, help="initial gait phase in [0, 1)")
  p.add_argument("--robot", default=None, metavar="NAME|FILE.toml",
                 help="the robot file to play on (default: the shipped robot the policy names)")
  args = p.parse_args(argv)
  if not 0.0 <= args.phase < 1.0:
    p.error(f"--phase {args.phase}: expected a gait phase in [0, 1)")
  say = lambda msg: print(msg, flush=True)

  viewer = args.video is None and has_display()
  video = args.video
  try:
    common.check_paths({"--policy": args.policy, "--video": video})
    if not viewer:  # MUJOCO_GL is read when mujoco is first imported: choose it before mash is
      if video is None:
        video = f"{Path(args.policy.rstrip('/')).stem or 'policy'}.mp4"
        common.check_path(video, "the video's file name (--video)")
        say(f"no display: playing headless, the video goes to {video}")
      if Path(video).suffix.lower() not in (".mp4", ".gif"):
        p.error(f"--video '{common.shown_path(video)}': expected a .mp4 (or .gif) file name")
      common.check_writable_file(video, "--video")
  except common.UserError as e:
    p.error(str(e))
  if not viewer:
    from experiments.sim2sim import headless_gl
    backend, reason = headless_gl()
    if backend is None:
      p.error(f"cannot render a video: {reason}")
    os.environ["MUJOCO_GL"] = backend
    os.environ.setdefault("PYOPENGL_PLATFORM", backend)

  with common.user_errors():
    onnx_path, _ = resolve_policy(args.policy, say)
    import numpy as np
    from mash import export, robots, sim2sim
    meta = export.read_metadata(onnx_path)
    robot_name = meta.get("robot")
    if args.robot is None and robot_name not in robots.names():
      raise common.UserError(f"'{onnx_path}' was exported for robot '{robot_name}', which this "
                             f"version does not ship (shipped: {', '.join(robots.names())}); "
                             "pass its robot file with --robot FILE.toml")
    spec = robots.load(args.robot or robot_name)
    if spec.name != robot_name:
      raise common.UserError(f"--robot {args.robot} is robot '{spec.name}', but '{onnx_path}' was "
                             f"exported for robot '{robot_name}'")
    vx, vy, yaw = args.command
    cfg = sim2sim.Sim2SimConfig(command_vx=vx, num_episodes=1, episode_s=args.seconds)
    try:
      if viewer:
        say(f"{onnx_path}: viewer; up/down vx +-0.1 m/s, left/right yaw rate +-0.1 rad/s, space "
            "stand/walk, backspace reset; close the window to quit")
        sim2sim.interactive(onnx_path, spec, cfg, say)
        return
      dep = sim2sim.Deployment.from_metadata(meta)
      robot = sim2sim.NativeRobot(spec, dep, cfg)
      controller = sim2sim.Controller(export.onnx_session(onnx_path), dep)
      command = np.array([1.0, 0.0, 0.0, 0.0]) if args.stand else np.array([0.0, vx, vy, yaw])
      steps = max(1, int(round(args.seconds / dep.ctrl_dt)))
      gif = Path(video).suffix.lower() == ".gif"  # small and slow: for a README or a slide
      fps, (width, height) = (12.5, (400, 300)) if gif else (25.0, (640, 480))
      say(f"playing {onnx_path} for {args.seconds:g} s at "
          + ("the standing command" if args.stand else
             f"vx {vx:+.2f} m/s, vy {vy:+.2f} m/s, yaw rate {yaw:+.2f} rad/s")
          + f" (rendering {int(args.seconds * fps)} frames, about {0.12 * args.seconds * fps:.0f} s "
          "on a CPU)")
      writer = sim2sim.VideoWriter(robot.model, video, fps, robot.root, width, height)
      t0 = time.perf_counter()
      try:
        traj = sim2sim.run_episode(robot, controller, command, steps, args.phase,
                                   sim2sim.hip_pitch_index(dep, spec), writer,
                                   frame_every=max(1, int(round(1.0 / (dep.ctrl_dt * fps)))))
      finally:
        writer.close()
    except export.ExportError as e:
      raise common.UserError(str(e)) from None
    alive = traj["alive"]
    held = alive.sum() * dep.ctrl_dt
    speed = float((traj["forward_velocity"] * alive).sum() / max(alive.sum(), 1.0))
    say(("fell after " if alive.min() == 0 else "walked ") + f"{held:.1f} s, mean vx "
        f"{speed:+.3f} m/s; wrote {video} ({writer.frames} frames, "
        f"{time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
  main()
