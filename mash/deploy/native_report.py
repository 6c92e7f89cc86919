"""The sim-to-sim command (``python -m experiments.sim2sim``): a run's ONNX policy in native MuJoCo
C, compared with its MJX evaluation.

:func:`run` takes the command's :class:`Options` (checked first by :func:`check_options`), finds
or exports the ONNX file (:func:`mash.deploy.sim2sim.resolve_onnx`), simulates it
(:func:`mash.deploy.sim2sim.simulate`, with the gait's hip reference, :func:`hip_reference`), puts
the paper's metrics of the MuJoCo C episodes (:func:`summarize`) beside those of the MJX
evaluation (:func:`mjx_metrics`: ``DIR/eval/metrics.json``, or a short
:func:`mash.analysis.reports.evaluate_run`), and writes ``DIR/sim2sim/report.json``,
``report.md`` (:func:`markdown`) and ``trajectories.npz`` (:func:`write_report`). With
``--robustness``, :func:`robustness` runs the robustness battery in MuJoCo C instead
(:mod:`mash.deploy.native_battery`) into ``DIR/sim2sim_robustness/``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import jax
import numpy as np

from mash import cli
from mash.analysis import evaluation, reports
from mash.analysis import robustness as battery
from mash.deploy import export, native_battery, sim2sim
from mash.deploy import policy as policy_lib
from mash.deploy import video as video_lib
from mash.sim import env as env_lib
from mash.sim import robots

REPORT_KEYS = ("S_action", "S_action_2nd", "S_torso", "C_limb", "fall_rate", "forward_speed",
               "command_vx")
TABLE_ROWS = (  # (key, label, unit)
    ("fall_rate", "fall rate", ""),
    ("survival_s", "mean survival", "s"),
    ("forward_speed", "forward speed", "m/s"),
    ("command_vx", "command vx", "m/s"),
    ("velocity_rmse", "vx tracking RMSE", "m/s"),
    ("S_action", "S_action (1st diff)", ""),
    ("S_action_2nd", "S_action (2nd diff)", ""),
    ("S_torso", "S_torso", ""),
    ("C_limb", "C_limb", "rad"),
)
# The flag that sets each Sim2SimConfig field, to name it in an error.
SIM2SIM_FLAGS = {
    "command_vx": "--command-vx", "num_episodes": "--episodes", "episode_s": "--seconds",
    "sim_dt": "--sim-dt", "iterations": "--iterations", "seed": "--seed"
}
# The flag that sets each BatteryConfig field (--robustness), to name it in an error.
BATTERY_FLAGS = {"episodes": "--episodes", "episode_s": "--seconds", "seed": "--battery-seed"}
# Flags the battery has no use for: its command, conditions and engine are its own.
NOT_WITH_ROBUSTNESS = {
    "video": "--video", "video_seconds": "--video-seconds", "viewer": "--viewer",
    "no_mjx": "--no-mjx", "command_vx": "--command-vx", "mjx_episodes": "--mjx-episodes",
    "mjx_dr": "--mjx-dr"
}
MJX_EPISODES = 4  # --mjx-episodes' default


@dataclasses.dataclass(frozen=True)
class Options:
  """The command's arguments (one field per flag, named as argparse names it).

  Attributes:
    run: run directory, or policy folder.
    episodes: MuJoCo C episodes, or per condition with ``robustness`` (None: 4, or the
      battery's 64). seconds: episode duration (s; None: 20, or the battery's 8).
    command_vx: forward command (m/s; None: 0.4).
    sim_dt: physics step (s). iterations: Newton iterations.
    seed: which seed of a multi-seed run.
    onnx: the ONNX file to run instead of ``DIR/policy.onnx``, or None.
    video: MP4 file of the first episode, or None. video_seconds: render at most this long.
    viewer: the interactive viewer instead of the episodes (needs a display).
    no_mjx: skip the MJX side of the comparison.
    robot: the robot file to use instead of the run's ``env.robot``, or None.
    mjx_episodes: episodes of the MJX evaluation when ``DIR/eval/metrics.json`` is missing
      (None: 4).
    mjx_dr: that evaluation with domain randomization.
    robustness: the robustness battery instead (:func:`robustness`).
    workers: its processes (None: one per CPU core).
    battery_seed: its seed (None: the battery's default, the MJX battery's).
  """

  run: str
  episodes: int | None = None
  seconds: float | None = None
  command_vx: float | None = None
  sim_dt: float = 0.002
  iterations: int = 10
  seed: int = 0
  onnx: str | None = None
  video: str | None = None
  video_seconds: float | None = None
  viewer: bool = False
  no_mjx: bool = False
  robot: str | None = None
  mjx_episodes: int | None = None
  mjx_dr: bool = False
  robustness: bool = False
  workers: int | None = None
  battery_seed: int | None = None


def check_options(o: Options) -> None:
  """The checks that need nothing loaded: paths, counts, the display for ``--viewer``, the
  video's file name, the flags ``--robustness`` goes with and its battery.

  Raises:
    cli.UserError: one line naming the flag.
  """
  cli.check_paths({"--run": o.run, "--onnx": o.onnx, "--video": o.video})
  if o.video_seconds is not None and not 0 < o.video_seconds < math.inf:
    raise cli.UserError("--video-seconds must be a finite number of seconds > 0, got "
                        f"{o.video_seconds}")
  if o.robustness:
    given = [
        flag for field, flag in NOT_WITH_ROBUSTNESS.items()
        if getattr(o, field) is not None and getattr(o, field) is not False
    ]
    if given:
      raise cli.UserError(f"--robustness runs the battery's own command and conditions in MuJoCo "
                          f"C alone; drop {', '.join(given)}")
    battery_config(o)
  elif o.workers is not None or o.battery_seed is not None:
    raise cli.UserError("--workers and --battery-seed go with --robustness")
  if o.workers is not None and o.workers < 1:
    raise cli.UserError(f"--workers must be >= 1, got {o.workers}")
  if ((o.episodes is not None and o.episodes < 1) or (o.seconds is not None and o.seconds <= 0) or
      (o.mjx_episodes is not None and o.mjx_episodes < 1)):
    raise cli.UserError("--episodes and --mjx-episodes must be >= 1 and --seconds > 0")
  if o.iterations < 1:
    raise cli.UserError(f"--iterations must be >= 1, got {o.iterations}")
  if o.viewer and not video_lib.has_display():
    raise cli.UserError("--viewer needs a display (DISPLAY is not set); use --video OUT.mp4 to "
                        "render offscreen instead")
  if o.video is not None and Path(o.video).suffix.lower() != ".mp4":
    raise cli.UserError(f"--video '{o.video}': expected a .mp4 file name")


def sim2sim_config(o: Options) -> sim2sim.Sim2SimConfig:
  """The :class:`mash.deploy.sim2sim.Sim2SimConfig` of the options, checked together with the
  MJX evaluation's episode count.

  Raises:
    cli.UserError: one line naming the flag, its value and what was expected.
  """
  given = {"command_vx": o.command_vx, "num_episodes": o.episodes, "episode_s": o.seconds}
  cfg = sim2sim.Sim2SimConfig(**{k: v for k, v in given.items() if v is not None}, sim_dt=o.sim_dt,
                              iterations=o.iterations, seed=o.seed)
  try:
    sim2sim.check_config(cfg, SIM2SIM_FLAGS)
    evaluation.check_config(evaluation.EvalConfig(num_episodes=mjx_episodes(o)),
                            {"num_episodes": "--mjx-episodes"})
  except ValueError as e:
    raise cli.UserError(str(e)) from None
  return cfg


def mjx_episodes(o: Options) -> int:
  """The episodes of the MJX evaluation the options ask for."""
  return MJX_EPISODES if o.mjx_episodes is None else o.mjx_episodes


def battery_config(o: Options) -> battery.BatteryConfig:
  """The robustness battery of the options (``--episodes``, ``--seconds``, ``--battery-seed``;
  the rest the battery's defaults), checked.

  Raises:
    cli.UserError: one line naming the flag, its value and what was expected.
  """
  given = {"episodes": o.episodes, "episode_s": o.seconds, "seed": o.battery_seed}
  cfg = battery.BatteryConfig(**{k: v for k, v in given.items() if v is not None})
  try:
    battery.check_config(cfg)
  except ValueError as e:
    field, rest = str(e).split(" ", 1)
    raise cli.UserError(f"{BATTERY_FLAGS.get(field, field)} {rest}") from None
  return cfg


def hip_reference(env: env_lib.MashEnv,
                  command_vx: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
  """The gait's hip-pitch reference at a forward command, for
  :func:`mash.deploy.sim2sim.simulate`.

  Returns:
    ``(phase [T], standing [T]) -> [T, 2]``: the left and right hip-pitch references (absolute,
    rad: the default pose plus the gait's offset).
  """
  hips = env.spec.role_indices("hip_pitch", "legs")
  gait = jax.jit(jax.vmap(env.gait))
  q_default = np.asarray(env.layout.default_pose, np.float32)

  def reference(phase: np.ndarray, standing: np.ndarray) -> np.ndarray:
    standing = np.asarray(standing, np.float32)
    command = np.stack([standing, (1 - standing) * command_vx, 0 * standing, 0 * standing], axis=-1)
    q_ref, _ = gait(np.asarray(phase, np.float32), standing, command)
    return q_default[hips] + np.asarray(q_ref)[:, hips]

  return reference


def summarize(traj: Mapping[str, np.ndarray], command_vx: float) -> dict[str, Any]:
  """The SPEC §8 metrics (via :func:`mash.analysis.evaluation.evaluate`) plus survival and
  tracking, of ``[E, T, ...]`` trajectories (:class:`mash.deploy.sim2sim.SimResult`)."""
  m = evaluation.evaluate(dict(traj), command_vx)
  alive = traj["alive"]
  dt = float(traj["dt"])
  err = (traj["forward_velocity"] - command_vx) * alive
  m.update(
      survival_s=float(alive.sum(axis=1).mean() * dt),
      velocity_rmse=float(np.sqrt((err**2).sum() / max(alive.sum(), 1.0))),
      velocity_error=float(m["forward_speed"] - command_vx),
  )
  return m


def mjx_row(metrics: Mapping[str, Any]) -> dict[str, Any]:
  """The comparable entries of an MJX ``eval/metrics.json`` (or ``evaluate_run`` result)."""
  row = {k: metrics.get(k) for k in REPORT_KEYS + ("T_conv",)}
  row["episodes"] = (metrics.get("eval_config") or {}).get("num_episodes")
  return row


def mjx_metrics(run_dir: Path, episodes: int, seconds: float, command_vx: float, dr: bool,
                say: Callable[[str], None], robot: str | None = None) -> tuple[dict | None, str]:
  """The MJX side of the table: ``DIR/eval/metrics.json`` or a short ``evaluate_run`` (with domain
  randomization only when ``dr``: off, it runs the same nominal robot as the MuJoCo C side).

  Returns:
    ``(row, source)``: :func:`mjx_row` of the metrics, and where they came from.
  """
  existing = run_dir / "eval" / "metrics.json"
  if existing.is_file():
    metrics = json.loads(existing.read_text())
    cfg = metrics.get("eval_config") or {}
    source = (f"{existing} ({cfg.get('num_episodes', '?')} episodes x "
              f"{cfg.get('episode_s', '?')} s, DR "
              f"{'on' if cfg.get('randomization', True) else 'off'})")
    say(f"MJX metrics from {existing}")
    return mjx_row(metrics), source
  cfg = evaluation.EvalConfig(command_vx=command_vx, num_episodes=episodes, episode_s=seconds,
                              randomization=dr)
  say(f"MJX evaluation: {episodes} episodes x {seconds:g} s (compiling the MJX rollout takes "
      "about a minute on CPU; --no-mjx skips it)")
  t0 = time.perf_counter()
  metrics = reports.evaluate_run(str(run_dir), cfg, write=False, robot=robot)
  say(f"MJX evaluation done in {time.perf_counter() - t0:.0f} s")
  return mjx_row(metrics), (f"mash.analysis.reports.evaluate_run, {episodes} episodes x "
                            f"{seconds:g} s, DR {'on' if dr else 'off'} (computed here; "
                            "not written to eval/)")


def build_report(o: Options, onnx_path: Path, cfg: sim2sim.Sim2SimConfig, result: sim2sim.SimResult,
                 wall: float, mujoco_row: dict[str, Any], mjx: tuple[dict | None, str],
                 video: str | None, video_skipped: str | None) -> dict[str, Any]:
  """``report.json``: the settings, the MuJoCo C metrics (``mujoco_row``: :func:`summarize`)
  beside the MJX ones (``mjx``: :func:`mjx_metrics`), each episode's survival and speed (from
  ``result``, which took ``wall`` seconds), and what became of the video."""
  traj = result.traj
  alive = traj["alive"]  # [E, T]
  meta = export.read_metadata(onnx_path)
  return {
      "run": str(Path(o.run)),
      "onnx": str(onnx_path),
      "checkpoint_iteration": meta.get("checkpoint_iteration"),
      "seed": o.seed,
      "command_vx": cfg.command_vx,
      "episodes": cfg.num_episodes,
      "episode_s": cfg.episode_s,
      "physics": sim2sim.physics_record(cfg, float(traj["dt"])),
      "mujoco": mujoco_row,
      "mjx": mjx[0],
      "mjx_source": mjx[1],
      "per_episode": [{
          "survival_s": float(a.sum() * traj["dt"]), "fell": bool(a.min() == 0),
          "forward_speed": float((v * a).sum() / max(a.sum(), 1.0)), "wall_s": float(w)
      } for a, v, w in zip(alive, traj["forward_velocity"], traj["wall_s"])],
      "wall_s": wall,
      "realtime_factor": float(alive.sum() * traj["dt"] / max(wall, 1e-9)),
      "video": video,
      "video_frames": result.video_frames,
      "video_skipped": video_skipped,
  }


def _fmt(x: Any) -> str:
  """A table cell: a number to four significant digits, a missing one as a dash."""
  if x is None:
    return "—"
  if isinstance(x, (int, float)):
    return f"{x:.4g}"
  return str(x)


def markdown(report: Mapping[str, Any]) -> str:
  """``report.md``: MuJoCo C against the MJX evaluation, one metric per row."""
  mj, mjx = report["mujoco"], report.get("mjx")
  phys = report["physics"]
  lines = [
      f"# Sim-to-sim: {report['run']}",
      "",
      f"Policy `{report['onnx']}` (checkpoint iteration {report.get('checkpoint_iteration')}) "
      f"at a fixed forward command of {report['command_vx']:g} m/s.",
      "",
      f"- MuJoCo C: {report['episodes']} episode(s) x {report['episode_s']:g} s, sim_dt "
      f"{phys['sim_dt']} s, {phys['integrator']}, {phys['iterations']} Newton iterations, "
      f"{'full collision geometry' if phys['full_collision'] else 'sole spheres only'}, "
      "no domain randomization, PD in NumPy on every physics step.",
      f"- MJX: {report.get('mjx_source') or 'not compared'}.",
      "",
      "| metric | MuJoCo C (sim2sim) | MJX (evaluation) |",
      "|---|---|---|",
  ]
  for key, label, unit in TABLE_ROWS:
    name = f"{label} ({unit})" if unit else label
    lines.append(f"| {name} | {_fmt(mj.get(key))} | {_fmt(mjx.get(key) if mjx else None)} |")
  lines += [
      "", "S_action, S_torso, C_limb are computed on the episodes that did not fall "
      "(all episodes when every one fell). Lower is better for all but forward speed.", ""
  ]
  return "\n".join(lines)


def write_report(out_dir: str | os.PathLike, report: Mapping[str, Any],
                 traj: Mapping[str, np.ndarray] | None = None) -> Path:
  """Writes ``report.json``, ``report.md`` (and ``trajectories.npz``) to ``out_dir``."""
  out = Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  (out / "report.json").write_text(json.dumps(report, indent=2))
  (out / "report.md").write_text(markdown(report))
  if traj is not None:
    np.savez_compressed(out / "trajectories.npz", **{k: np.asarray(v) for k, v in traj.items()})
  return out


def run(o: Options, say: Callable[[str], None] = print) -> Path | None:
  """The command after :func:`check_options`: the viewer, or the episodes and the report.

  Returns:
    The folder the report was written to (``DIR/sim2sim``), or None after the viewer.

  Raises:
    mash.errors.InputError: a run, robot, setting or ONNX file that cannot be used (one line).
  """
  if o.robustness:
    return robustness(o, say)
  video, video_backend, video_skipped = o.video, None, None
  if video is not None and not o.viewer:
    # MuJoCo was imported with mash, before the arguments were read: the backend found here goes
    # to the video writer (mash.deploy.video.gl_context), not to MUJOCO_GL.
    video_backend, reason = video_lib.headless_gl()
    if video_backend is None:
      video, video_skipped = None, reason
      say(f"video skipped: {reason}")
  run_dir = Path(o.run)
  config = policy_lib.load_config(run_dir, o.robot)
  cli.check_writable_dir(run_dir / "sim2sim", "the run directory")
  if o.video is not None:
    cli.check_writable_file(o.video, "--video")
  cfg = sim2sim_config(o)
  onnx_path = sim2sim.resolve_onnx(run_dir, o.onnx, o.seed, say, o.robot)
  env = env_lib.MashEnv(config.env)
  if o.viewer:
    say("viewer: up/down vx +-0.1 m/s, left/right yaw rate +-0.1 rad/s, space stand/walk, "
        "backspace reset; close the window to quit")
    sim2sim.interactive(onnx_path, env.spec, cfg, say)
    return None
  say(f"MuJoCo C: {cfg.num_episodes} episode(s) x {cfg.episode_s:g} s at vx = "
      f"{cfg.command_vx:g} m/s; sim_dt {cfg.sim_dt} s, {cfg.integrator}, {cfg.iterations} "
      "Newton iterations, full collision geometry")
  t0 = time.perf_counter()
  result = sim2sim.simulate(onnx_path, env.spec, cfg, hip_reference(env, cfg.command_vx), video,
                            video_seconds=o.video_seconds, video_backend=video_backend,
                            progress=say)
  if result.video_error is not None:
    video, video_skipped = None, result.video_error
  wall = time.perf_counter() - t0
  mujoco_row = summarize(result.traj, cfg.command_vx)
  mjx = (None, "skipped (--no-mjx)") if o.no_mjx else mjx_metrics(
      run_dir, mjx_episodes(o), cfg.episode_s, cfg.command_vx, o.mjx_dr, say, o.robot)
  report = build_report(o, onnx_path, cfg, result, wall, mujoco_row, mjx, video, video_skipped)
  out = write_report(run_dir / "sim2sim", report, result.traj)
  say(markdown(report))
  say(f"wrote {out}/report.json, report.md, trajectories.npz" +
      (f"; video {video}" if video else ""))
  return out


def robustness(o: Options, say: Callable[[str], None] = print) -> Path:
  """``--robustness``: the battery in MuJoCo C (:func:`mash.deploy.native_battery.run`), printed
  and written to ``DIR/sim2sim_robustness/`` (``robustness.json``, ``robustness.png``).

  Raises:
    mash.errors.InputError: a run, robot, setting or ONNX file that cannot be used (one line).
  """
  run_dir = Path(o.run)
  config = policy_lib.load_config(run_dir, o.robot)
  out = run_dir / "sim2sim_robustness"
  cli.check_writable_dir(out, "the run directory")
  cfg = battery_config(o)
  physics = sim2sim.Sim2SimConfig(sim_dt=o.sim_dt, iterations=o.iterations)
  try:
    sim2sim.check_config(physics, SIM2SIM_FLAGS)
  except ValueError as e:
    raise cli.UserError(str(e)) from None
  onnx_path = sim2sim.resolve_onnx(run_dir, o.onnx, o.seed, say, o.robot)
  spec = robots.load(config.env.robot)
  meta = export.read_metadata(onnx_path)
  workers = o.workers or native_battery.default_workers()
  n = len(battery.conditions(cfg))
  say(f"robustness in MuJoCo C: {n} conditions x {cfg.episodes} episodes x {cfg.episode_s:g} s "
      f"at vx {cfg.command_vx:g} m/s; sim_dt {physics.sim_dt} s, {physics.integrator}, "
      f"{physics.iterations} Newton iterations, full collision geometry; {workers} worker "
      "process(es)")
  t0 = time.perf_counter()
  rows = native_battery.run(onnx_path, spec, cfg, physics, workers, progress=say)
  wall = time.perf_counter() - t0
  ctrl_dt = sim2sim.Deployment.from_metadata(meta).ctrl_dt
  res = native_battery.result(onnx_path, physics, ctrl_dt, cfg, rows,
                              checkpoint_iteration=meta.get("checkpoint_iteration"), seed=o.seed,
                              workers=workers, wall_s=wall)
  native_battery.write(
      out, res, f"{config.task} {config.algo}, MuJoCo C, iteration "
      f"{meta.get('checkpoint_iteration')}, {cfg.episodes} episodes a condition")
  reports.print_robustness(res)
  say(f"wrote {out}/robustness.json, robustness.png ({wall:.0f} s)")
  return out
