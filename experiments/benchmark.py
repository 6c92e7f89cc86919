"""``python -m experiments.benchmark [--quick]``: throughput of physics, env and training, in one
process.

Prints one JSON object and writes it to ``benchmark.json``: bare ``mjx.step`` physics, the batched
env step, and full training for MASH, our PPO and Brax's PPO on the same env and sizes, compile
times and peak memory (:func:`mash.bench.benchmark.run_benchmark`). ``--stages env,mash,brax_ppo``
measures only the named stages; ``--impl warp`` runs the physics through MuJoCo Warp.
``--breakdown`` splits an iteration's time (``breakdown.json``); ``--sweep batch`` writes
``benchmarks/scaling_batch.*`` and ``--sweep physics`` ``benchmarks/physics_settings.*``
(:mod:`mash.bench.sweeps`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mash import cli
from mash.bench import benchmark as bench
from mash.bench import sweeps
from mash.sim import env_config, robots
from mash.sim import model as model_lib

MAX_BATCH = 2**20  # envs; TrainConfig's own cap (mash.rl.config.SIZE_CAPS)


def _parser() -> cli.Parser:
  p = cli.Parser(prog="python -m experiments.benchmark", description=__doc__.splitlines()[0])
  p.add_argument("--quick", action="store_true",
                 help="smaller batch and fewer repeats (< 15 min CPU)")
  p.add_argument("--batch", type=int, default=None)
  p.add_argument("--task", default="bipedal")
  p.add_argument("--out", default=None,
                 help="JSON file (default benchmark.json, or breakdown.json with --breakdown)")
  p.add_argument("--sweep", default=None, help="batch | physics")
  p.add_argument(
      "--breakdown", action="store_true",
      help="time the env rollout, the updates and the rest of a MASH and a PPO "
      "iteration")
  p.add_argument("--batches", default="64,256,1024,4096")
  p.add_argument("--stages", default=",".join(bench.STAGES),
                 help=f"comma-separated subset of {','.join(bench.STAGES)} (default: all)")
  p.add_argument("--dir", default="benchmarks", help="where --sweep writes its table and plot")
  p.add_argument("--robot", default="booster_t1", metavar="NAME|FILE.toml",
                 help=f"a shipped robot ({', '.join(robots.names())}) or a robot file")
  p.add_argument("--impl", default="jax",
                 help="MJX implementation of the physics: jax (default) or warp (MuJoCo Warp)")
  return p


def _check(args: argparse.Namespace) -> None:
  """The arguments every mode shares: paths, ``--impl``, ``--robot``, ``--task``, ``--batch``."""
  cli.check_paths({"--out": args.out, "--dir": args.dir})
  try:
    model_lib.check_physics(model_lib.PhysicsConfig(impl=args.impl))
  except ValueError as e:
    raise cli.UserError(f"--{e}") from None
  if args.impl != "jax" and args.sweep == "physics":  # its drift figures come from MuJoCo C
    raise cli.UserError("--sweep physics measures the jax implementation only; drop --impl")
  try:
    env_config.check_config(env_config.EnvConfig(robot=args.robot))
  except ValueError as e:
    raise cli.UserError(f"--robot: {e}") from None
  cli.check_task(args.task)
  if args.batch is not None and not 0 <= args.batch <= MAX_BATCH:
    raise cli.UserError(f"--batch must be a number of envs in [1, {MAX_BATCH}] (0: the "
                        f"default), got {args.batch}")
  if args.sweep in ("batch", "physics"):
    cli.check_writable_dir(args.dir, "--dir")
  else:
    cli.check_writable_file(args.out or ("breakdown.json" if args.breakdown else "benchmark.json"),
                            "--out")


def _batches(text: str) -> list[int]:
  try:
    batches = [int(b) for b in text.split(",")]
  except ValueError:
    batches = []
  if not batches or not all(1 <= b <= MAX_BATCH for b in batches):
    raise cli.UserError(f"--batches '{text}': expected comma-separated numbers of "
                        f"envs in [1, {MAX_BATCH}], e.g. 64,256,1024")
  return batches


def _stages(text: str) -> tuple[str, ...]:
  stages = tuple(text.split(","))
  if any(s not in bench.STAGES for s in stages):
    raise cli.UserError(f"--stages '{text}': expected a comma-separated subset of "
                        f"{','.join(bench.STAGES)}")
  return stages


def main(argv: list[str] | None = None) -> None:
  args = _parser().parse_args(argv)
  with cli.user_errors():
    _check(args)
    if args.sweep == "batch":
      report = sweeps.sweep_batch(_batches(args.batches), args.task,
                                  Path(args.dir) / "scaling_batch", args.impl, args.robot)
    elif args.sweep == "physics":
      report = sweeps.sweep_physics(args.task, args.robot, Path(args.dir) / "physics_settings")
    elif args.breakdown:
      report = bench.breakdown(args.task, args.batch, args.impl, args.robot,
                               Path(args.out or "breakdown.json"))
    elif args.sweep is not None:
      raise cli.UserError(f"--sweep '{args.sweep}' is unknown; expected batch or physics")
    else:
      result = bench.run_benchmark(args.quick, args.batch, args.task,
                                   Path(args.out or "benchmark.json"), _stages(args.stages),
                                   args.impl, args.robot)
      print(json.dumps(result))
      return
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
  main()
