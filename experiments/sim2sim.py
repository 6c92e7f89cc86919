"""``python -m experiments.sim2sim --run DIR``: the run's ONNX policy in native MuJoCo C.

Exports ``DIR/policy.onnx`` (or reuses it when it is of the latest checkpoint), runs it with
onnxruntime in MuJoCo C on a different physics setup (1-2 ms steps, implicit-fast, 10+ Newton
iterations, full collision geometry; PD in NumPy on every physics step, 50 Hz control) at a fixed
forward command, and writes ``DIR/sim2sim/report.json``, ``report.md`` (MuJoCo C against the MJX
evaluation: ``DIR/eval/metrics.json`` when it exists, else a short ``evaluate_run``) and
``trajectories.npz``. ``DIR`` may also be a policy folder (:mod:`mash.deploy.policy`).

``--robustness`` runs the robustness battery (:mod:`mash.analysis.robustness`: kicks, floors,
torso mass, weak motors, sensor noise, latency) in MuJoCo C instead, ``--episodes`` per condition
(default 64) of ``--seconds`` (default 8) at vx 0.4 m/s, in ``--workers`` processes (default: one
per CPU core), and writes ``DIR/sim2sim_robustness/robustness.json`` and ``robustness.png`` in the
format of the MJX battery's (``python -m experiments.evaluate --robustness``).

Examples:
  python -m experiments.sim2sim --run runs/bipedal_mash_cpu_X
  python -m experiments.sim2sim --run DIR --robustness --episodes 8
  python -m experiments.sim2sim --run DIR --episodes 2 --seconds 10 --video walk.mp4
  python -m experiments.sim2sim --run DIR --viewer      # arrows: vx / yaw rate, space: stand
"""

from __future__ import annotations

import argparse

from mash import cli as common
from mash.deploy import native_report


def main(argv=None) -> None:
  p = common.Parser(prog="python -m experiments.sim2sim", description=__doc__.splitlines()[0],
                    formatter_class=argparse.RawDescriptionHelpFormatter,
                    epilog="\n".join(__doc__.splitlines()[2:]))
  p.add_argument("--run", required=True,
                 help="run directory, or policy folder (mash.deploy.policy)")
  p.add_argument(
      "--episodes", type=int, default=None,
      help="MuJoCo C episodes (default 4), or per condition with --robustness "
      "(default 64, a multiple of 8)")
  p.add_argument("--seconds", type=float, default=None,
                 help="episode duration (s; default 20, or 8 with --robustness)")
  p.add_argument("--command-vx", type=float, default=None, help="forward command (m/s, default "
                 "0.4)")
  p.add_argument("--sim-dt", type=float, default=0.002, help="physics step (s): 0.001 or 0.002")
  p.add_argument("--iterations", type=int, default=10, help="Newton iterations (>= 10)")
  p.add_argument("--seed", type=int, default=0, help="which seed of a multi-seed run")
  p.add_argument("--onnx", default=None, help="run this ONNX file instead of DIR/policy.onnx")
  p.add_argument("--video", default=None, metavar="OUT.mp4", help="render the first episode")
  p.add_argument("--video-seconds", type=float, default=None, help="render at most this long")
  p.add_argument("--viewer", action="store_true",
                 help="interactive mujoco viewer (needs a display); arrows change vx / yaw rate")
  p.add_argument("--no-mjx", action="store_true", help="skip the MJX side of the comparison")
  p.add_argument(
      "--robot", default=None, metavar="NAME|FILE.toml",
      help="the robot file to use instead of the run's env.robot (the same robot, "
      "e.g. a user's file that has moved)")
  p.add_argument(
      "--mjx-episodes", type=int, default=None,
      help="episodes of the MJX evaluation when DIR/eval/metrics.json is missing "
      "(default 4)")
  p.add_argument(
      "--mjx-dr", action="store_true",
      help="that MJX evaluation with domain randomization (default: off, the nominal "
      "robot, like the MuJoCo C side)")
  p.add_argument(
      "--robustness", action="store_true",
      help="the robustness battery in MuJoCo C instead (writes "
      "DIR/sim2sim_robustness/robustness.json, robustness.png)")
  p.add_argument("--workers", type=int, default=None, metavar="N",
                 help="--robustness: processes running episodes (default: one per CPU core)")
  p.add_argument(
      "--battery-seed", type=int, default=None, metavar="S",
      help="--robustness: the battery's seed (its floors, noise; default 2026, the "
      "MJX battery's); --seed still picks the seed of a multi-seed run")
  args = p.parse_args(argv)
  options = native_report.Options(**vars(args))
  try:
    native_report.check_options(options)
  except common.UserError as e:
    p.error(str(e))
  with common.user_errors():
    native_report.run(options, say=lambda msg: print(msg, flush=True))


if __name__ == "__main__":
  main()
