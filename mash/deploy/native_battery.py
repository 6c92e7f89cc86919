"""The robustness battery (:mod:`mash.analysis.robustness`) in native MuJoCo C.

The same conditions (:func:`mash.analysis.robustness.conditions`) and per-episode perturbations
(:func:`mash.analysis.robustness.episodes`) as the MJX battery, summarized by the same code
(:func:`mash.analysis.robustness.summarize`), on the nominal robot (no domain randomization, as
``sim2sim`` runs it) with MuJoCo C's converged solver (:class:`mash.deploy.sim2sim.Sim2SimConfig`),
the ONNX policy driving it through :class:`mash.deploy.sim2sim.Controller` at the battery's forward
command. Each condition as the MJX battery applies it:

- **kick**: the episode's ``[vx, vy]`` added to the free joint's linear velocity (world frame) at
  ``kick_at_s``, after the policy acted on that step and before its physics;
- **friction**: the episode's value on the floor-sole contact pairs (-1: the model's own);
- **torso mass**: the root body's mass and inertia times the factor;
- **motor strength**: each motor's torque and its limit times its strength;
- **sensor noise**: uniform noise of the episode's bounds on what the controller reads (Euler
  angles, angular velocity, joint angles, joint velocities), from a NumPy generator seeded by
  ``(cfg.seed, e)``;
- **latency**: the action applied ``delay`` control steps late (:class:`Controller`'s queue; the
  action fed back to the policy is the one applied, as in MJX).

Episode ``e`` of a condition (``e = 0 .. episodes - 1``) starts at gait phase ``e / episodes``
(:func:`start_phase`; the MJX battery draws its phases from the episodes' keys), so the episodes of
each kick direction (``e mod kick_directions``) meet the whole gait cycle alike, and draws its noise
from ``(cfg.seed, e)``: episode ``e`` is the same under every condition, as in MJX. Episodes run
in a pool of spawned processes, each building its robot and ONNX session once; every episode is
fixed by its index, so the result does not depend on the number of processes.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, NamedTuple

import numpy as np

from mash.analysis import reports, robustness
from mash.deploy import export, sim2sim
from mash.sim import robots

NOISY = ("euler", "ang_vel", "q", "dq")  # the readings the noise bounds apply to, in their order


def start_phase(e: int, episodes: int) -> float:
  """The gait phase (cycles, [0, 1)) episode ``e`` of ``episodes`` starts at, under every
  condition: ``e / episodes``. The kick of episode ``e`` goes in direction ``e mod k`` of ``k``, so
  each direction's episodes start every ``k / episodes`` of a cycle and direction and phase are
  crossed. (Until 2026-12-07 it was ``0.37 e mod 1``, which gave each direction a 0.28-cycle
  window of its own: the survival by direction then measured the phase as much as the direction.)"""
  return e / episodes


def sensor_noise(bounds: np.ndarray,
                 rng: np.random.Generator) -> Callable[[Mapping[str, Any]], dict[str, Any]]:
  """What the controller reads: the readings plus uniform noise of ``bounds [4]`` (:data:`NOISY`:
  rad, rad/s, rad, rad/s), a fresh draw from ``rng`` on every call (all four drawn, whatever
  their bounds, so that the stream depends on nothing else)."""
  bounds = np.asarray(bounds, np.float64)

  def sense(s: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(s)
    for name, b in zip(NOISY, bounds):
      out[name] = s[name] + b * rng.uniform(-1.0, 1.0, np.shape(s[name]))
    return out

  return sense


class Setup(NamedTuple):
  """What every process needs to run episodes (picklable).

  Attributes:
    onnx: the exported policy's path. spec: its robot. physics: MuJoCo C's settings.
    cfg: the battery.
  """

  onnx: str
  spec: robots.RobotSpec
  physics: sim2sim.Sim2SimConfig
  cfg: robustness.BatteryConfig


class Runner:
  """One process's robot and ONNX session (built once) and the episodes it runs."""

  def __init__(self, setup: Setup):
    self.dep = sim2sim.Deployment.from_metadata(export.read_metadata(setup.onnx))
    self.robot = sim2sim.NativeRobot(setup.spec, self.dep, setup.physics)
    self.session = export.onnx_session(setup.onnx)
    self.hips = setup.spec.role_indices("hip_pitch", "legs")
    self.cfg = setup.cfg
    self.steps = int(round(setup.cfg.episode_s / self.dep.ctrl_dt))
    self.kick_step = int(round(setup.cfg.kick_at_s / self.dep.ctrl_dt))
    self.command = np.array([0.0, setup.cfg.command_vx, 0.0, 0.0])

  def __call__(self, job: tuple[int, robustness.Episodes]) -> tuple[np.ndarray, np.ndarray]:
    """Episode ``e`` under one condition (``p``: its row of :class:`robustness.Episodes`):
    ``alive [T]`` (1 until the fall, that step included) and ``forward_velocity [T]`` (m/s)."""
    e, p = job
    self.robot.perturb(float(p.friction), float(p.mass), np.asarray(p.strength, np.float64))
    controller = sim2sim.Controller(self.session, self.dep, delay=int(p.delay))
    noise = np.asarray(p.noise, np.float64)
    sense = (sensor_noise(noise, np.random.default_rng([self.cfg.seed, e])) if np.any(
        noise > 0) else None)
    kick = (self.kick_step, np.asarray(p.kick, np.float64)) if np.any(p.kick != 0) else None
    traj = sim2sim.run_episode(self.robot, controller, self.command, self.steps,
                               start_phase(e, self.cfg.episodes), self.hips, sense=sense, kick=kick)
    return traj["alive"], traj["forward_velocity"].astype(np.float32)


_SETUP: Setup | None = None  # a pool process's setup (set by _init_worker) and runner (lazily)
_RUNNER: Runner | None = None


def _init_worker(setup: Setup) -> None:
  """A pool process's start: keeps the setup (nothing that can fail)."""
  global _SETUP
  _SETUP = setup


def _run_job(job: tuple[int, robustness.Episodes]) -> tuple[np.ndarray, np.ndarray]:
  """A pool process's episode; its runner is built on its first (an error reaches the caller,
  where a failing pool initializer would be restarted forever)."""
  global _RUNNER
  if _RUNNER is None:
    _RUNNER = Runner(_SETUP)
  return _RUNNER(job)


def default_workers() -> int:
  """One process per CPU core this process may use."""
  try:
    return len(os.sched_getaffinity(0))
  except AttributeError:  # not on Linux
    return os.cpu_count() or 1


def _results(setup: Setup, jobs: list, workers: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
  """Each job's result in the jobs' order: here (one worker) or in a spawned pool."""
  if workers == 1:
    yield from map(Runner(setup), jobs)
    return
  with multiprocessing.get_context("spawn").Pool(workers, _init_worker, (setup,)) as pool:
    yield from pool.imap(_run_job, jobs, chunksize=1)


def run(onnx_path: str | os.PathLike, spec: robots.RobotSpec,
        cfg: robustness.BatteryConfig = robustness.BatteryConfig(),
        physics: sim2sim.Sim2SimConfig = sim2sim.Sim2SimConfig(), workers: int | None = None,
        progress: Callable[[str], None] | None = print) -> list[dict[str, Any]]:
  """The whole battery in MuJoCo C for an ONNX policy.

  Args:
    onnx_path: an exported policy (:func:`mash.deploy.export.export_policy`).
    spec: the robot it was trained on.
    cfg: the battery (its command, episodes and seed; ``physics``' own are not used).
    physics: MuJoCo C's time step, solver and collision set.
    workers: processes (None: :func:`default_workers`; never more than the episodes).
    progress: called with one line per condition (with the time to go after the first).

  Returns:
    :func:`mash.analysis.robustness.summarize`'s rows, one per condition.
  """
  robustness.check_config(cfg)
  dep = sim2sim.Deployment.from_metadata(export.read_metadata(onnx_path))
  conds = robustness.conditions(cfg)
  eps = robustness.episodes(conds, cfg, robustness.left_leg_mask(spec), dep.ctrl_dt)
  n = cfg.episodes
  jobs = [
      (i % n, robustness.Episodes(*(field[i] for field in eps))) for i in range(len(eps.friction))
  ]
  workers = max(1, min(default_workers() if workers is None else workers, len(jobs)))
  alive, speed = [], []
  t0 = t_first = time.perf_counter()
  for i, (a, v) in enumerate(_results(Setup(str(onnx_path), spec, physics, cfg), jobs, workers)):
    alive.append(a)
    speed.append(v)
    now = time.perf_counter()
    t_first = now if i == 0 else t_first  # the processes' start-up is behind us from here on
    if (i + 1) % n == 0 and progress is not None:
      k = (i + 1) // n
      row = robustness.summarize([conds[k - 1]], np.stack(alive[-n:]), np.stack(speed[-n:]), cfg)[0]
      per_episode = (now - t_first) / i if i > 0 else now - t0
      to_go = per_episode * (len(jobs) - i - 1)
      progress(f"condition {k}/{len(conds)} {row['name']}: survival "
               f"{100 * row['survival']:.1f} %, forward speed {row['forward_speed']:.3f} m/s "
               f"({now - t0:.0f} s so far" + (f", about {to_go:.0f} s to go)" if to_go else ")"))
  return robustness.summarize(conds, np.stack(alive), np.stack(speed), cfg)


def result(onnx_path: str | os.PathLike, physics: sim2sim.Sim2SimConfig, ctrl_dt: float,
           cfg: robustness.BatteryConfig, rows: list[dict[str,
                                                          Any]], **extra: Any) -> dict[str, Any]:
  """``robustness.json``: the engine, its physics, the policy, the battery and its rows (the MJX
  battery's format, ``survival_by_direction`` kept for kicks), then ``extra`` entries."""
  return {
      "engine": "mujoco", "physics": sim2sim.physics_record(physics, ctrl_dt),
      "onnx": str(onnx_path), "battery": dataclasses.asdict(cfg), "conditions": rows, **extra
  }


def write(out_dir: str | os.PathLike, res: Mapping[str, Any], title: str) -> Path:
  """Writes ``robustness.json`` and ``robustness.png`` (:func:`mash.analysis.reports.
  plot_robustness`, titled ``title``) to ``out_dir``; returns the folder."""
  out = Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  (out / "robustness.json").write_text(json.dumps(res, indent=2))
  reports.plot_robustness(list(res["conditions"]), out / "robustness.png", title)
  return out
