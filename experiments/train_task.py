"""``python -m experiments.bipedal`` / ``experiments.armswing``: train MASH or the PPO baseline.

Examples:
  python -m experiments.bipedal                          # MASH, preset from the backend
  python -m experiments.bipedal --algo ppo --seeds 3 --preset smoke --out runs/ppo_smoke
  python -m experiments.armswing --set train.learning_rate=5e-4 --set env.action_scale=0.3
  python -m experiments.bipedal --resume runs/bipedal_mash_cpu_20261125-120000
  python -m experiments.bipedal --robot unitree_g1 --preset smoke   # or --robot my_robot.toml

Devices: one process trains on every device it sees (several GPUs: the env batch is split over
them). On a CPU with 2 or more cores, a one-seed run above the smoke preset trains as two local
processes joined on 127.0.0.1 (--local-processes 1 keeps one process). Several hosts run the
SAME command, each with --coordinator HOST:PORT (process 0's address) --num-processes N
--process-id I (0 .. N-1), or the environment variables MASH_COORDINATOR, MASH_NUM_PROCESSES,
MASH_PROCESS_ID; process 0 writes the run and prints. See docs/multi_device.md.

Exit status: 0 finished; 1 a checkpoint or run file could not be written (a full disk, a quota,
a read-only file system: one line on stderr naming it and the last complete checkpoint, which
still loads: free space, then --resume); 2 bad input (one line on stderr, nothing written);
130 / 143 stopped by Ctrl-C (SIGINT) / SIGTERM after saving a checkpoint: continue with --resume.
A run killed outright (SIGKILL, a power cut) also continues with --resume, from its last complete
checkpoint.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from experiments import common


def _check_new_run(task: str, args) -> None:
  """A new run's config, then its folder (refused when it holds a run or cannot be written), all
  before anything else is built."""
  from mash import experiment, runs
  experiment.make_config(task, args.algo, args.preset or common.default_preset()[0], args.seeds,
                         args.ablation, args.set)
  if args.out is None:  # the default runs/<name>_<time>/ goes in runs/
    common.check_writable_dir("runs", "the default run folder")
    return
  if Path(args.out).is_file():
    raise common.UserError(f"'{args.out}' is a file, not a run directory")
  if runs.is_run(Path(args.out)):
    raise common.UserError(f"'{args.out}' already holds a run; pass --resume {args.out} to "
                           "continue it, or choose another --out")
  common.check_writable_dir(args.out, "--out")


def _local_processes(task: str, args) -> int:
  """How many local processes to train with (``common.local_processes_wanted``); when more than
  one, the config, the run directory and the split of the env batch are checked here first, so a
  mistake is one line from one process, before any process starts."""
  from mash import config as train_config, experiment, runs
  if common.joined_by_hand(args):  # decided without JAX, which must not start before the join
    return common.local_processes_wanted(args, "", 1)
  if args.resume:
    cfg = runs.load_config(args.resume)
  else:
    cfg = experiment.make_config(task, args.algo, args.preset or common.default_preset()[0],
                                 args.seeds, args.ablation, args.set)
  n = common.local_processes_wanted(args, cfg.preset, cfg.seeds)
  summary = Path(args.resume or "", "summary.json")
  if args.resume and args.local_processes == "auto" and summary.is_file():
    # A resume restores the env state as it was split: keep the run's own process count.
    try:
      n = int(json.loads(summary.read_text()).get("processes", n))
    except (ValueError, TypeError, AttributeError):
      pass
  if n > 1:
    if not args.resume:
      _check_new_run(task, args)
    try:
      train_config.derived(cfg.train, n)
    except ValueError as e:
      raise common.UserError(f"{str(e).rstrip('.')}: the env batch is split over {n} local "
                             "processes (--local-processes 1 trains in one)") from None
  return n


def main(task: str, argv: list[str] | None = None) -> None:
  p = common.Parser(prog=f"python -m experiments.{task}", description=__doc__.splitlines()[0],
                    formatter_class=__import__("argparse").RawDescriptionHelpFormatter,
                    epilog="\n".join(__doc__.splitlines()[2:]))
  p.add_argument("--algo", default="mash", help="mash (limb agents, MAPPO) | ppo (single agent)")
  p.add_argument("--preset", default=None, help="smoke | cpu | gpu (default: from the backend)")
  p.add_argument("--seeds", type=int, default=1, help="independent seeds trained in one jit")
  p.add_argument("--out", default=None, help="run directory (default: runs/<task>_<algo>_<preset>_<time>)")
  p.add_argument("--resume", default=None, metavar="DIR", help="continue the run in DIR")
  p.add_argument("--ablation", default="none", help="one of mash.experiment.ABLATIONS")
  p.add_argument("--robot", default=None, metavar="NAME|FILE.toml",
                 help="a shipped robot (booster_t1, unitree_g1) or a robot file (default: "
                      "booster_t1; the same as --set env.robot=...)")
  p.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                 help="override a config field, e.g. train.learning_rate=1e-3 (repeatable)")
  p.add_argument("--no-progress", action="store_true", help="no progress bar")
  common.add_distributed_args(p)
  args = p.parse_args(argv)

  with common.user_errors():
    common.check_paths({"--out": args.out, "--resume": args.resume})
    if args.resume:
      given = [name for name, value, default in (
          ("--algo", args.algo, "mash"), ("--preset", args.preset, None), ("--seeds", args.seeds, 1),
          ("--ablation", args.ablation, "none"), ("--set", args.set, []),
          ("--robot", args.robot, None),
          ("--out", args.out, None)) if value != default]
      if given and not (given == ["--out"] and str(args.out) == str(args.resume)):
        raise common.UserError(f"--resume continues a run with its own config; {', '.join(given)} "
                               "cannot be combined with it")
    if args.robot is not None:  # before the --set overrides, so that those still win
      args.set = [f"env.robot={common.robot_arg(args.robot)}", *args.set]
    if "MASH_LOCAL_PROCESSES" not in os.environ:  # not already one of the supervised processes
      n = _local_processes(task, args)
      if n > 1:
        sys.exit(common.run_local_processes(f"experiments.{task}",
                                            sys.argv[1:] if argv is None else list(argv), n))
    primary = common.join_processes(args)  # before any other JAX work
    if not args.resume and not common.joined_by_hand(args):
      _check_new_run(task, args)
    say = print if primary else (lambda *a, **k: None)
    from mash import experiment, runs
    preset, backend = common.default_preset()
    chosen = "given" if args.preset else f"chosen from the backend '{backend}'"
    if args.resume:
      cfg = runs.load_config(args.resume)
      if cfg.task != task:
        raise common.UserError(f"--resume {args.resume} is a '{cfg.task}' run, not '{task}'")
      say(f"resuming {args.resume}: task {cfg.task}, algo {cfg.algo}, preset {cfg.preset}"
          f"{common.devices_note()}", flush=True)
      summary = runs.train(cfg, args.resume, resume=True, show_progress=not args.no_progress)
      out = args.resume
    else:
      preset = args.preset or preset
      cfg = experiment.make_config(task, args.algo, preset, args.seeds, args.ablation, args.set)
      stamp = time.strftime('%Y%m%d-%H%M%S', time.localtime(common.shared_time()))
      out = args.out or f"runs/{task}_{cfg.algo}_{preset}_{stamp}"
      say(f"preset: {preset} ({chosen}); task {task}, algo {cfg.algo}, seeds {cfg.seeds}, "
          f"{cfg.train.num_envs} envs x {cfg.train.unroll_length} steps x "
          f"{cfg.train.num_iterations} iterations -> {out}{common.devices_note()}", flush=True)
      summary = runs.train(cfg, out, show_progress=not args.no_progress)
    state = "interrupted at" if summary["interrupted"] else "finished"
    reward = summary["final_episode_reward"]
    reward = "n/a" if reward is None else f"{reward:.3f}"
    say(f"{state} iteration {summary['iterations']}: {summary['env_steps']:,} env steps in "
        f"{summary['wall_s']:.0f} s, final episode reward {reward}; run in {out}", flush=True)
    if summary["interrupted"]:
      again = " (on every process, with the same flags)" if summary.get("processes", 1) > 1 else ""
      say(f"continue with: python -m experiments.{task} --resume {out}{again}", flush=True)
  status = common.exit_status(summary)
  if status:
    sys.exit(status)
