"""``python -m experiments.benchmark_devices [--batch 256] [--steps 20]``: what a second CPU device
buys.

Times the real MJX env's batched env step (and with ``--train`` the MASH trainer) in one process
vs two joined by ``jax.distributed`` into a global mesh vs two unconnected, each in worker
processes this script launches (``--worker``); see :mod:`mash.bench.devices`. Prints the table as
JSON and writes ``benchmarks/scaling_devices.json``, ``.md`` and ``.png`` with
``ratio_vs_one_process``. The machine may be shared: quote the ratios, not the absolute figures.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mash import cli
from mash.bench import devices

PLATFORMS = ("cpu", "gpu", "cuda", "rocm", "tpu")  # JAX_PLATFORMS values for the workers
# Sanity caps: TrainConfig's own on the envs; steps x batch x action floats fit in memory.
MAX_BATCH, MAX_STEPS, MAX_REPEATS = 2**20, 100_000, 1000


def _parser() -> cli.Parser:
  p = cli.Parser(prog="python -m experiments.benchmark_devices",
                 description=__doc__.splitlines()[0])
  p.add_argument("--batch", type=int, default=256, help="global env batch (even)")
  p.add_argument("--steps", type=int, default=20, help="control steps per timed call")
  p.add_argument("--repeats", type=int, default=3, help="timed calls (best kept)")
  p.add_argument("--task", default="bipedal")
  p.add_argument("--train", action="store_true", help="also time MASH training, 1 vs 2 processes")
  p.add_argument("--train-batch", type=int, default=256, help="global env batch of --train")
  p.add_argument("--platform", default="cpu", help="JAX platform of the workers")
  p.add_argument("--out", default="benchmarks/scaling_devices",
                 help="output stem (.json, .md, .png)")
  # Worker-side arguments (set by the launcher, which also sets the worker's JAX_PLATFORMS).
  hidden = argparse.SUPPRESS
  p.add_argument("--worker", default=None, help=hidden)
  p.add_argument("--process-id", type=int, default=0, help=hidden)
  p.add_argument("--num-processes", type=int, default=1, help=hidden)
  p.add_argument("--coordinator", default="127.0.0.1:12355", help=hidden)
  p.add_argument("--sync-dir", default=None, help=hidden)
  p.add_argument("--result", default=None, help=hidden)
  return p


def _check(args: argparse.Namespace) -> None:
  cli.check_path(args.out, "--out")
  if args.batch < 2 or args.batch % 2 or args.batch > MAX_BATCH:
    raise cli.UserError(f"--batch must be an even number in [2, {MAX_BATCH}], got {args.batch}")
  if not (1 <= args.steps <= MAX_STEPS and 1 <= args.repeats <= MAX_REPEATS):
    raise cli.UserError(f"--steps must be in [1, {MAX_STEPS}] and --repeats in [1, "
                        f"{MAX_REPEATS}], got {args.steps} and {args.repeats}")
  if args.train and (args.train_batch < 4 or args.train_batch % 4 or args.train_batch > MAX_BATCH):
    raise cli.UserError(f"--train-batch must be a multiple of 4 in [4, {MAX_BATCH}], got "
                        f"{args.train_batch}")
  cli.check_task(args.task)
  if args.platform not in PLATFORMS:
    raise cli.UserError(f"--platform '{args.platform}' is unknown; expected one of "
                        f"{', '.join(PLATFORMS)}")
  cli.check_writable_file(Path(args.out).with_suffix(".json"), "--out")


def main(argv: list[str] | None = None) -> None:
  args = _parser().parse_args(argv)
  config = devices.ScalingConfig(args.batch, args.steps, args.repeats, args.task, args.train,
                                 args.train_batch, args.platform)
  if args.worker is not None:
    devices.run_worker(
        config,
        devices.Worker(args.worker, args.process_id, args.num_processes, args.coordinator,
                       args.sync_dir, args.result))
    return
  with cli.user_errors():
    _check(args)
    result = devices.run_scaling(config)
    devices.write_report(result, Path(args.out))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
  main()
