"""Probe (issue 52): does a kick's direction or the gait phase it meets decide the fall?

The MuJoCo C battery starts episode ``e`` at gait phase ``0.37 e mod 1`` and kicks it in direction
``e mod 8``; over 64 episodes each direction then meets only a 0.28-cycle window of phases, a
different window per direction. This probe kicks every policy given at one size in each of the 8
directions at 16 evenly spread phases (128 episodes, MuJoCo C, the battery's physics, command and
kick time), so that direction and phase are crossed, and writes one JSON line per policy:
survival per (direction, phase) and the margins.

  python benchmarks/scripts/2026-12-07_kick_phase_probe.py --kick 1.0 RUN_DIR [RUN_DIR ...]

Each RUN_DIR holds ``policy.onnx`` (``experiments.export``) and ``config.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from mash.analysis import robustness
from mash.deploy import native_battery, policy, sim2sim
from mash.sim import robots

PHASES = 16
DIRECTIONS = 8


def probe(run_dir: Path, kick: float, out) -> None:
  config = policy.load_config(run_dir, None)
  spec = robots.load(config.env.robot)
  onnx = str(run_dir / "policy.onnx")
  cfg = robustness.BatteryConfig()
  runner = native_battery.Runner(native_battery.Setup(onnx, spec, sim2sim.Sim2SimConfig(), cfg))
  cycle = config.env.gait_cycle_s
  alive = np.zeros((DIRECTIONS, PHASES))
  t0 = time.perf_counter()
  for d in range(DIRECTIONS):
    angle = 2 * np.pi * d / DIRECTIONS
    vec = kick * np.array([np.cos(angle), np.sin(angle)])
    for j in range(PHASES):
      runner.robot.perturb(-1.0, 1.0, np.ones(len(robustness.left_leg_mask(spec))))
      controller = sim2sim.Controller(runner.session, runner.dep, delay=0)
      traj = sim2sim.run_episode(runner.robot, controller, runner.command, runner.steps, j / PHASES,
                                 runner.hips, kick=(runner.kick_step, vec))
      alive[d, j] = traj["alive"][-1]
    print(
        f"{run_dir.name} direction {d}: {alive[d].mean():.2f} "
        f"({time.perf_counter() - t0:.0f} s)", flush=True)
  record = {
      "run": str(run_dir), "kick_m_s": kick, "directions_deg": [45 * d for d in range(8)],
      "start_phases": [j / PHASES for j in range(PHASES)], "phase_at_kick": [
          (j / PHASES + cfg.kick_at_s / cycle) % 1.0 for j in range(PHASES)
      ], "survival": float(alive.mean()), "by_direction": alive.mean(1).tolist(),
      "by_start_phase": alive.mean(0).tolist(), "alive": alive.astype(int).tolist(),
      "wall_s": round(time.perf_counter() - t0, 1)
  }
  out.write(json.dumps(record) + "\n")
  out.flush()


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("runs", nargs="+", type=Path)
  parser.add_argument("--kick", type=float, default=1.0, help="kick size (m/s)")
  parser.add_argument("--out", type=Path, default=Path("kick_phase_probe.jsonl"))
  args = parser.parse_args()
  with open(args.out, "a") as out:
    for run_dir in args.runs:
      probe(run_dir, args.kick, out)


if __name__ == "__main__":
  main()
