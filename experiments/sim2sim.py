"""``python -m experiments.sim2sim --run DIR``: the run's ONNX policy in native MuJoCo C.

Exports ``DIR/policy.onnx`` (or reuses it when it is of the latest checkpoint), runs it with
onnxruntime in MuJoCo C on a different physics setup (1-2 ms steps, implicit-fast, 10+ Newton
iterations, full collision geometry; PD in NumPy on every physics step, 50 Hz control) at a fixed
forward command, and writes ``DIR/sim2sim/report.json``, ``report.md`` (MuJoCo C against the MJX
evaluation: ``DIR/eval/metrics.json`` when it exists, else a short ``evaluate_run``) and
``trajectories.npz``. ``DIR`` may also be a policy folder (:mod:`mash.policy`).

Examples:
  python -m experiments.sim2sim --run runs/bipedal_mash_cpu_X
  python -m experiments.sim2sim --run DIR --episodes 2 --seconds 10 --video walk.mp4
  python -m experiments.sim2sim --run DIR --viewer      # arrows: vx / yaw rate, space: stand
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from experiments import common

_GL_PROBE = """
import mujoco
m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=".1"/></worldbody></mujoco>')
r = mujoco.Renderer(m, 16, 16)
r.update_scene(mujoco.MjData(m))
r.render()
"""


def headless_gl() -> tuple[str | None, str]:
  """The first ``MUJOCO_GL`` backend (egl, osmesa) that renders here, tried in subprocesses.

  Returns:
    ``(backend, '')``, or ``(None, reason)`` naming what failed.
  """
  if os.environ.get("MUJOCO_GL"):
    return os.environ["MUJOCO_GL"], ""
  failures = []
  for backend in ("egl", "osmesa"):
    env = dict(os.environ, MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
    try:
      r = subprocess.run([sys.executable, "-c", _GL_PROBE], env=env, capture_output=True,
                         text=True, timeout=60)
    except subprocess.TimeoutExpired:
      failures.append(f"{backend}: timed out")
      continue
    if r.returncode == 0:
      return backend, ""
    last = (r.stderr.strip().splitlines() or ["failed"])[-1]
    failures.append(f"{backend}: {last[:120]}")
  return None, ("no headless OpenGL backend works here (" + "; ".join(failures) + "); install "
                "Debian's libegl1 and libgl1-mesa-dri (EGL) or libosmesa6 (OSMesa)")


def latest_step(run_dir: Path) -> int | None:
  """The newest complete checkpoint step of a run, from its directory names (None for a policy
  folder)."""
  steps = [int(p.name) for p in (run_dir / "checkpoints").glob("*")
           if p.name.isdigit() and not any(p.glob("*.orbax-checkpoint-tmp*"))]
  return max(steps) if steps else None


def resolve_onnx(run_dir: Path, onnx_arg: str | None, seed: int, say,
                 robot: str | None = None) -> Path:
  """The ONNX policy to run: ``--onnx``, an up-to-date ``DIR/policy.onnx``, or a fresh export
  (``DIR``: a run directory or a policy folder)."""
  from mash import export, policy as policy_lib
  if onnx_arg:
    path = Path(onnx_arg)
    if not path.is_file():
      raise common.UserError(f"--onnx '{path}' does not exist; expected an exported policy")
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
  try:
    export.export_policy(policy, path)
  except export.ExportError as e:
    raise common.UserError(str(e)) from None
  say(f"exported {path} (checkpoint iteration {policy.iteration}, seed {policy.seed})")
  return path


def mjx_metrics(run_dir: Path, episodes: int, seconds: float, command_vx: float, dr: bool, say,
                robot: str | None = None) -> tuple[dict | None, str]:
  """The MJX side of the table: ``DIR/eval/metrics.json`` or a short ``evaluate_run`` (with domain
  randomization only when ``dr``: off, it runs the same nominal robot as the MuJoCo C side)."""
  from experiments.evaluate import evaluate_run
  from mash import evaluation, sim2sim
  existing = run_dir / "eval" / "metrics.json"
  if existing.is_file():
    metrics = json.loads(existing.read_text())
    cfg = metrics.get("eval_config") or {}
    source = (f"{existing} ({cfg.get('num_episodes', '?')} episodes x "
              f"{cfg.get('episode_s', '?')} s, DR {'on' if cfg.get('randomization', True) else 'off'})")
    say(f"MJX metrics from {existing}")
    return sim2sim.mjx_row(metrics), source
  cfg = evaluation.EvalConfig(command_vx=command_vx, num_episodes=episodes, episode_s=seconds,
                              randomization=dr)
  say(f"MJX evaluation: {episodes} episodes x {seconds:g} s (compiling the MJX rollout takes "
      "about a minute on CPU; --no-mjx skips it)")
  t0 = time.perf_counter()
  metrics = evaluate_run(str(run_dir), cfg, write=False, robot=robot)
  say(f"MJX evaluation done in {time.perf_counter() - t0:.0f} s")
  return sim2sim.mjx_row(metrics), (f"experiments.evaluate.evaluate_run, {episodes} episodes x "
                                    f"{seconds:g} s, DR {'on' if dr else 'off'} (computed here; "
                                    "not written to eval/)")


# The flag that sets each Sim2SimConfig field, to name it in an error.
SIM2SIM_FLAGS = {"command_vx": "--command-vx", "num_episodes": "--episodes",
                 "episode_s": "--seconds", "sim_dt": "--sim-dt", "iterations": "--iterations",
                 "seed": "--seed"}


def main(argv=None) -> None:
  p = common.Parser(prog="python -m experiments.sim2sim", description=__doc__.splitlines()[0],
                    formatter_class=argparse.RawDescriptionHelpFormatter,
                    epilog="\n".join(__doc__.splitlines()[2:]))
  p.add_argument("--run", required=True, help="run directory, or policy folder (mash.policy)")
  p.add_argument("--episodes", type=int, default=4, help="MuJoCo C episodes")
  p.add_argument("--seconds", type=float, default=20.0, help="episode duration (s)")
  p.add_argument("--command-vx", type=float, default=0.4, help="forward command (m/s)")
  p.add_argument("--sim-dt", type=float, default=0.002, help="physics step (s): 0.001 or 0.002")
  p.add_argument("--iterations", type=int, default=10, help="Newton iterations (>= 10)")
  p.add_argument("--seed", type=int, default=0, help="which seed of a multi-seed run")
  p.add_argument("--onnx", default=None, help="run this ONNX file instead of DIR/policy.onnx")
  p.add_argument("--video", default=None, metavar="OUT.mp4", help="render the first episode")
  p.add_argument("--video-seconds", type=float, default=None, help="render at most this long")
  p.add_argument("--viewer", action="store_true",
                 help="interactive mujoco viewer (needs a display); arrows change vx / yaw rate")
  p.add_argument("--no-mjx", action="store_true", help="skip the MJX side of the comparison")
  p.add_argument("--robot", default=None, metavar="NAME|FILE.toml",
                 help="the robot file to use instead of the run's env.robot (the same robot, "
                      "e.g. a user's file that has moved)")
  p.add_argument("--mjx-episodes", type=int, default=4,
                 help="episodes of the MJX evaluation when DIR/eval/metrics.json is missing")
  p.add_argument("--mjx-dr", action="store_true",
                 help="that MJX evaluation with domain randomization (default: off, the nominal "
                      "robot, like the MuJoCo C side)")
  args = p.parse_args(argv)

  say = lambda msg: print(msg, flush=True)
  try:
    common.check_paths({"--run": args.run, "--onnx": args.onnx, "--video": args.video})
  except common.UserError as e:
    p.error(str(e))
  if args.video_seconds is not None and not 0 < args.video_seconds < math.inf:
    p.error(f"--video-seconds must be a finite number of seconds > 0, got {args.video_seconds}")
  if args.episodes < 1 or args.seconds <= 0 or args.mjx_episodes < 1:
    p.error("--episodes and --mjx-episodes must be >= 1 and --seconds > 0")
  if args.iterations < 1:
    p.error(f"--iterations must be >= 1, got {args.iterations}")
  if args.viewer and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    p.error("--viewer needs a display (DISPLAY is not set); use --video OUT.mp4 to render "
            "offscreen instead")
  # MUJOCO_GL is read when mujoco is imported: choose it before anything imports mash.
  video, video_skipped = args.video, None
  if video is not None:
    if Path(video).suffix.lower() != ".mp4":
      p.error(f"--video '{video}': expected a .mp4 file name")
    if not args.viewer:
      backend, reason = headless_gl()
      if backend is None:
        video, video_skipped = None, reason
        say(f"video skipped: {reason}")
      else:
        os.environ["MUJOCO_GL"] = backend
        if backend in ("egl", "osmesa"):
          os.environ.setdefault("PYOPENGL_PLATFORM", backend)

  with common.user_errors():
    from mash import env as env_lib, evaluation, export, policy as policy_lib, sim2sim
    import jax
    import numpy as np

    run_dir = Path(args.run)
    config = policy_lib.load_config(run_dir, args.robot)
    common.check_writable_dir(run_dir / "sim2sim", "the run directory")
    if args.video is not None:
      common.check_writable_file(args.video, "--video")
    cfg = sim2sim.Sim2SimConfig(command_vx=args.command_vx, num_episodes=args.episodes,
                                episode_s=args.seconds, sim_dt=args.sim_dt,
                                iterations=args.iterations, seed=args.seed)
    try:
      sim2sim.check_config(cfg, SIM2SIM_FLAGS)
      evaluation.check_config(evaluation.EvalConfig(num_episodes=args.mjx_episodes),
                              {"num_episodes": "--mjx-episodes"})
    except ValueError as e:
      raise common.UserError(str(e)) from None
    onnx_path = resolve_onnx(run_dir, args.onnx, args.seed, say, args.robot)
    env = env_lib.MashEnv(config.env)
    try:
      if args.viewer:
        say("viewer: up/down vx +-0.1 m/s, left/right yaw rate +-0.1 rad/s, space stand/walk, "
            "backspace reset; close the window to quit")
        sim2sim.interactive(onnx_path, env.spec, cfg, say)
        return
      hips = evaluation.hip_pitch_index(env)
      gait = jax.jit(jax.vmap(env.gait))
      q_default = np.asarray(env.layout.default_pose, np.float32)

      def hip_reference(phase, standing):
        standing = np.asarray(standing, np.float32)
        command = np.stack([standing, (1 - standing) * cfg.command_vx, 0 * standing,
                            0 * standing], axis=-1)
        q_ref, _ = gait(np.asarray(phase, np.float32), standing, command)
        return q_default[hips] + np.asarray(q_ref)[:, hips]

      say(f"MuJoCo C: {cfg.num_episodes} episode(s) x {cfg.episode_s:g} s at vx = "
          f"{cfg.command_vx:g} m/s; sim_dt {cfg.sim_dt} s, {cfg.integrator}, {cfg.iterations} "
          "Newton iterations, full collision geometry")
      t0 = time.perf_counter()
      result = sim2sim.simulate(onnx_path, env.spec, cfg, hip_reference, video,
                                video_seconds=args.video_seconds, progress=say)
      traj = result.traj
      if result.video_error is not None:
        video, video_skipped = None, result.video_error
      wall = time.perf_counter() - t0
    except export.ExportError as e:
      raise common.UserError(str(e)) from None
    mujoco_row = sim2sim.summarize(traj, cfg.command_vx)

    mjx, source = (None, "skipped (--no-mjx)") if args.no_mjx else mjx_metrics(
        run_dir, args.mjx_episodes, args.seconds, args.command_vx, args.mjx_dr, say, args.robot)
    meta = export.read_metadata(onnx_path)
    alive = traj["alive"]
    report = {
        "run": str(run_dir), "onnx": str(onnx_path),
        "checkpoint_iteration": meta.get("checkpoint_iteration"), "seed": args.seed,
        "command_vx": cfg.command_vx, "episodes": cfg.num_episodes, "episode_s": cfg.episode_s,
        "physics": {"engine": "mujoco C " + __import__("mujoco").__version__, "sim_dt": cfg.sim_dt,
                    "iterations": cfg.iterations, "ls_iterations": cfg.ls_iterations,
                    "integrator": cfg.integrator, "full_collision": cfg.full_collision,
                    "ctrl_dt": float(traj["dt"]), "domain_randomization": False},
        "mujoco": mujoco_row,
        "mjx": mjx, "mjx_source": source,
        "per_episode": [{"survival_s": float(a.sum() * traj["dt"]), "fell": bool(a.min() == 0),
                         "forward_speed": float((v * a).sum() / max(a.sum(), 1.0)),
                         "wall_s": float(w)}
                        for a, v, w in zip(alive, traj["forward_velocity"], traj["wall_s"])],
        "wall_s": wall,
        "realtime_factor": float(alive.sum() * traj["dt"] / max(wall, 1e-9)),
        "video": video, "video_frames": result.video_frames, "video_skipped": video_skipped,
    }
    out = sim2sim.write_report(run_dir / "sim2sim", report, traj)
    say(sim2sim.markdown(report))
    say(f"wrote {out}/report.json, report.md, trajectories.npz"
        + (f"; video {video}" if video else ""))


if __name__ == "__main__":
  main()
