"""Launching a training command: several processes on one host or several hosts, joined by
``jax.distributed`` before any other JAX work, and the supervision of local child processes.

On a CPU with 2+ cores a one-seed run above the ``smoke`` preset trains as two local processes
joined on 127.0.0.1 (:func:`local_processes_wanted`, :func:`run_local_processes`); several hosts
run the same command with ``--coordinator``/``--num-processes``/``--process-id``
(:func:`join_processes`). ``docs/multi_device.md`` has the rules.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import jax
import numpy as np
from jax.experimental import multihost_utils

from mash import cli
from mash.cli import UserError
from mash.rl import distributed
from mash.rl.config import derived
from mash.runs import experiment, loop
from mash.sim import geometry, robots

DISTRIBUTED_ENV = {
    "coordinator": "MASH_COORDINATOR", "num_processes": "MASH_NUM_PROCESSES",
    "process_id": "MASH_PROCESS_ID"
}
MAX_LOCAL_PROCESSES = 64


def add_distributed_args(parser: argparse.ArgumentParser) -> None:
  """``--coordinator``, ``--num-processes``, ``--process-id`` (defaults from ``MASH_*``)."""
  g = parser.add_argument_group(
      "several processes (hosts)", "run the same command in every process; default: one process "
      "(it uses every device it sees)")
  g.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                 help="address of process 0, reachable from every process (env MASH_COORDINATOR)")
  g.add_argument("--num-processes", default=None, metavar="N",
                 help="processes in the run (env MASH_NUM_PROCESSES; default 1)")
  g.add_argument("--process-id", default=None, metavar="I",
                 help="this process's index, 0 .. N-1; 0 writes the run (env MASH_PROCESS_ID)")
  g.add_argument(
      "--local-processes", default="auto", metavar="N",
      help="train as N processes on this host joined on 127.0.0.1 (default auto: 2 on "
      "a CPU with 2+ cores for one seed above the smoke preset, else 1)")


def _int_option(value: str | None, flag: str, env: str) -> int | None:
  source = flag
  if value is None:
    value, source = os.environ.get(env) or None, env
  if value is None:
    return None
  try:
    return int(value)
  except ValueError:
    raise UserError(f"{source} must be an integer, got '{value}'") from None


def join_processes(args: argparse.Namespace) -> bool:
  """Joins this process to the others (``jax.distributed``) when ``--num-processes`` > 1; call
  before any other JAX work. Returns whether this is process 0 (the one that prints and writes).

  Raises:
    UserError: a missing or malformed flag, or the processes could not join (one line).
  """
  n = _int_option(args.num_processes, "--num-processes", DISTRIBUTED_ENV["num_processes"])
  pid = _int_option(args.process_id, "--process-id", DISTRIBUTED_ENV["process_id"])
  coordinator = args.coordinator or os.environ.get(DISTRIBUTED_ENV["coordinator"]) or None
  n = 1 if n is None else n
  if n < 1:
    raise UserError(f"--num-processes must be >= 1, got {n}")
  if n == 1:
    if pid not in (None, 0):
      raise UserError(f"--process-id {pid} needs --num-processes {pid + 1} or more")
    return True
  if coordinator is None:
    raise UserError(f"--num-processes {n} needs --coordinator HOST:PORT (process 0's address, "
                    "the same in every process)")
  if pid is None:
    raise UserError(f"--num-processes {n} needs --process-id (0 .. {n - 1}, different in every "
                    "process)")
  if not 0 <= pid < n:
    raise UserError(f"--process-id must be in 0 .. {n - 1} for --num-processes {n}, got {pid}")
  try:
    distributed.initialize(coordinator, num_processes=n, process_id=pid)
  except ValueError as e:
    raise UserError(str(e).rstrip(".")) from None
  except Exception as e:  # noqa: BLE001 - a failed join (timeout, address in use): one line
    first = (str(e).strip().splitlines() or [""])[0][:200]
    raise UserError(f"process {pid} of {n} could not join the run at {coordinator}: "
                    f"{type(e).__name__}: {first}") from None
  return jax.process_index() == 0


def joined_by_hand(args: argparse.Namespace) -> bool:
  """Whether the multi-host flags (or their ``MASH_*`` variables) join processes by hand."""
  return bool(args.num_processes or os.environ.get(DISTRIBUTED_ENV["num_processes"]) or
              args.coordinator or args.process_id is not None)


def local_processes_wanted(args: argparse.Namespace, preset: str, seeds: int) -> int:
  """How many processes this command should run on this host: ``--local-processes`` when given,
  else (``auto``) 2 when JAX's backend is the CPU, the host has 2 or more cores, the run trains
  one seed at a preset other than ``smoke``, and no ``--num-processes`` / ``MASH_NUM_PROCESSES``
  joins processes by hand; 1 otherwise.

  Why 2 on a CPU: one process keeps about 1.3 of 2 cores busy, two processes on a global 2-device
  mesh step about 1.3-1.9x the envs of one (``benchmarks/scaling_devices.md``). Not for ``smoke``:
  at its 64 envs the per-step collectives cost more than the second core brings (0.52x measured).

  Raises:
    UserError: ``--local-processes`` is not ``auto`` or a whole number >= 1, or it is combined with
      the multi-host flags.
  """
  value = args.local_processes
  by_hand = joined_by_hand(args)
  if value == "auto":
    if by_hand or seeds != 1 or preset == "smoke":
      return 1
    return 2 if jax.default_backend() == "cpu" and (os.cpu_count() or 1) >= 2 else 1
  try:
    n = int(value)
  except ValueError:
    n = 0
  if n < 1:
    raise UserError(f"--local-processes must be 'auto' or a whole number >= 1, got '{value}'")
  if n > MAX_LOCAL_PROCESSES:
    raise UserError(f"--local-processes must be at most {MAX_LOCAL_PROCESSES} (processes on one "
                    f"host), got {n}")
  if n > 1 and by_hand:
    raise UserError("--local-processes cannot be combined with --coordinator / --num-processes / "
                    "--process-id (they join processes by hand)")
  return n


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
  """Linux: the child gets SIGTERM (and saves a checkpoint) if the supervising process dies."""
  try:
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
  except (OSError, AttributeError):
    pass


def run_local_processes(module: str, argv: list[str], n: int) -> int:
  """Runs ``python -m module *argv`` as ``n`` processes on this host joined on 127.0.0.1 (the
  multi-host path on one machine) and supervises them; returns the exit status to leave with.

  Process 0 prints as a one-process run would; the others' output goes to a temporary file,
  shown only when one of them fails. SIGINT and SIGTERM reaching this process are passed once to
  every child (they stop together after the call in flight, with a checkpoint); the children run
  in their own session, so a terminal's Ctrl-C reaches them only through here.
  """
  with socket.socket() as sock:
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
  env = dict(os.environ)
  env.update({
      DISTRIBUTED_ENV["coordinator"]: f"127.0.0.1:{port}", DISTRIBUTED_ENV["num_processes"]: str(n),
      "MASH_LOCAL_PROCESSES": "1"
  })
  logs, procs = [], []
  for i in range(n):
    env[DISTRIBUTED_ENV["process_id"]] = str(i)
    log = None if i == 0 else tempfile.TemporaryFile(mode="w+")
    logs.append(log)
    with warnings.catch_warnings():
      # The child execs a fresh interpreter at once (after one prctl call), so the fork of this
      # process, whose JAX has threads, cannot deadlock it, as Python's warning fears.
      warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
      procs.append(
          subprocess.Popen([sys.executable, "-m", module, *argv], env=dict(env), stdout=log,
                           stderr=subprocess.STDOUT if log else None, start_new_session=True,
                           preexec_fn=_die_with_parent))

  def forward(signum, frame):
    for p in procs:
      if p.poll() is None:
        p.send_signal(signum)

  previous = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM)}
  try:
    while any(p.poll() is None for p in procs):
      failed = [p for p in procs if p.poll() not in (None, 0, 130, 143)]
      if failed:  # a dead peer leaves the others waiting in a collective: stop them
        time.sleep(5)
        for p in procs:
          if p.poll() is None:
            p.terminate()
      time.sleep(0.2)
  finally:
    for s, handler in previous.items():
      signal.signal(s, handler)
  codes = [p.wait() for p in procs]
  for i, (code, log) in enumerate(zip(codes, logs)):
    if log is not None and code not in (0, codes[0]):
      log.seek(0)
      tail = log.read().strip().splitlines()[-20:]
      print(f"process {i} of {n} exited with status {code}:", *tail, sep="\n  ", file=sys.stderr)
  return next((c for c in codes if c != 0), 0)


def shared_time() -> float:
  """``time.time()`` of process 0, the same in every process (names default run directories)."""
  now = time.time()
  if jax.process_count() == 1:
    return now
  return float(multihost_utils.broadcast_one_to_all(np.int32(int(now))))


def devices_note() -> str:
  """``'; 2 devices in 2 processes'`` when training may use several devices, else ``''``."""
  n, p = jax.device_count(), jax.process_count()
  if n == 1:
    return ""
  return f"; {n} devices" + (f" in {p} processes" if p > 1 else "")


# ------------------------------------------------------------------------------ train command
TRAIN_EPILOG = """\
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


def add_train_args(parser: argparse.ArgumentParser) -> None:
  """The training commands' arguments (``experiments.bipedal``, ``experiments.armswing``)."""
  p = parser
  p.add_argument("--algo", default="mash", help="mash (limb agents, MAPPO) | ppo (single agent)")
  p.add_argument("--preset", default=None, help="smoke | cpu | gpu (default: from the backend)")
  p.add_argument("--seeds", type=int, default=1, help="independent seeds trained in one jit")
  p.add_argument("--out", default=None,
                 help="run directory (default: runs/<task>_<algo>_<preset>_<time>)")
  p.add_argument("--resume", default=None, metavar="DIR", help="continue the run in DIR")
  p.add_argument(
      "--config", default=None, metavar="FILE.json",
      help="train a new run on this config (e.g. another run's config.json) instead "
      "of a preset; --seeds and --set apply on top")
  p.add_argument("--ablation", default="none", help="one of mash.runs.experiment.ABLATIONS")
  p.add_argument(
      "--robot", default=None, metavar="NAME|FILE.toml",
      help=f"a shipped robot ({', '.join(robots.names())}) or a robot file (default: "
      "booster_t1; the same as --set env.robot=...)")
  p.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                 help="override a config field, e.g. train.learning_rate=1e-3 (repeatable)")
  p.add_argument("--no-progress", action="store_true", help="no progress bar")
  add_distributed_args(p)


def _check_resume_flags(args: argparse.Namespace) -> None:
  """``--resume`` continues a run with its own config: no flag that would change it."""
  given = [
      name for name, value, default in (("--algo", args.algo, "mash"),
                                        ("--preset", args.preset, None), ("--seeds", args.seeds, 1),
                                        ("--ablation", args.ablation,
                                         "none"), ("--set", args.set, []), ("--robot", args.robot,
                                                                            None),
                                        ("--out", args.out, None), ("--config", args.config, None))
      if value != default
  ]
  if given and not (given == ["--out"] and str(args.out) == str(args.resume)):
    raise UserError(f"--resume continues a run with its own config; {', '.join(given)} "
                    "cannot be combined with it")


def _new_config(task: str, args: argparse.Namespace) -> experiment.ExperimentConfig:
  """A new run's config: the preset's (``--preset``, else the backend's), or the ``--config``
  file's, then ``--set`` on top."""
  if args.config is not None:
    given = [
        name for name, value, default in (("--algo", args.algo,
                                           "mash"), ("--preset", args.preset,
                                                     None), ("--ablation", args.ablation, "none"),
                                          ("--robot", args.robot, None)) if value != default
    ]
    if given:
      raise UserError(f"--config gives the whole config; {', '.join(given)} cannot be combined "
                      "with it (use --set on top)")
    return experiment.config_from_file(args.config, task, args.seeds, args.set)
  preset = args.preset or cli.default_preset()[0]
  return experiment.make_config(task, args.algo, preset, args.seeds, args.ablation, args.set)


def _check_out(args: argparse.Namespace) -> None:
  """A new run's folder: refused when it holds a run or cannot be written, before any work."""
  if args.out is None:  # the default runs/<name>_<time>/ goes in runs/
    cli.check_writable_dir("runs", "the default run folder")
    return
  loop.check_new_run_dir(Path(args.out))
  cli.check_writable_dir(args.out, "--out")


def _processes_for(args: argparse.Namespace, cfg: experiment.ExperimentConfig) -> int:
  """How many local processes to train ``cfg`` with; when more than one, the split of the env
  batch is checked here first, so a mistake is one line from one process, before any starts."""
  n = local_processes_wanted(args, cfg.preset, cfg.seeds)
  summary = Path(args.resume or "", "summary.json")
  if args.resume and args.local_processes == "auto" and summary.is_file():
    # A resume restores the env state as it was split: keep the run's own process count.
    try:
      n = int(json.loads(summary.read_text()).get("processes", n))
    except (ValueError, TypeError, AttributeError):
      pass
  if n > 1:
    try:
      derived(cfg.train, n)
    except ValueError as e:
      raise UserError(f"{str(e).rstrip('.')}: the env batch is split over {n} local "
                      "processes (--local-processes 1 trains in one)") from None
  return n


def train_main(task: str, args: argparse.Namespace, argv: list[str] | None) -> None:
  """The training command of ``task`` with its parsed ``args`` (``argv``: the arguments they came
  from, for local child processes): checks everything before any work, then trains (or resumes)
  into the run folder, as one process, as local processes, or as one of several joined by hand.
  Exits with :func:`mash.cli.exit_status`."""
  with cli.user_errors():
    cli.check_paths({"--out": args.out, "--resume": args.resume, "--config": args.config})
    if args.resume:
      _check_resume_flags(args)
    if args.robot is not None:  # before the --set overrides, so that those still win
      args.set = [f"env.robot={cli.robot_arg(args.robot)}", *args.set]
    cfg = None
    if "MASH_LOCAL_PROCESSES" not in os.environ and not joined_by_hand(args):
      # Not one of the supervised children, nor joined by hand: JAX may start here.
      cfg = loop.load_config(args.resume) if args.resume else _new_config(task, args)
      if not args.resume:
        _check_out(args)
      n = _processes_for(args, cfg)
      if n > 1:
        sys.exit(
            run_local_processes(f"experiments.{task}", sys.argv[1:] if argv is None else list(argv),
                                n))
    primary = join_processes(args)  # before any other JAX work
    say = print if primary else (lambda *a, **k: None)
    if args.resume:
      cfg = cfg or loop.load_config(args.resume)
      if cfg.task != task:
        raise UserError(f"--resume {args.resume} is a '{cfg.task}' run, not '{task}'")
      say(
          f"resuming {args.resume}: task {cfg.task}, algo {cfg.algo}, preset {cfg.preset}"
          f"{devices_note()}", flush=True)
      summary = loop.train(cfg, args.resume, resume=True, show_progress=not args.no_progress)
      out = args.resume
    else:
      cfg = cfg or _new_config(task, args)  # joined processes: loop.train checks the folder
      chosen = "given" if args.preset else f"chosen from the backend '{cli.default_preset()[1]}'"
      stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(shared_time()))
      out = args.out or f"runs/{task}_{cfg.algo}_{cfg.preset}_{stamp}"
      say(
          f"preset: {cfg.preset} ({chosen}); task {task}, algo {cfg.algo}, seeds {cfg.seeds}, "
          f"{cfg.train.num_envs} envs x {cfg.train.unroll_length} steps x "
          f"{cfg.train.num_iterations} iterations -> {out}{devices_note()}", flush=True)
      if cfg.env.stride_reference:
        say(
            f"stride reference on {cfg.env.robot}: "
            f"{geometry.stride_plan(robots.load(cfg.env.robot))}"
            f"{_feedback_note(cfg.env.stride_feedback)}", flush=True)
      summary = loop.train(cfg, out, show_progress=not args.no_progress)
    _say_outcome(say, task, out, summary)
  status = cli.exit_status(summary)
  if status:
    sys.exit(status)


def _feedback_note(k: float) -> str:
  """The startup line's note on ``env.stride_feedback`` (nothing at 0)."""
  return f"; planned at the command + {k:g} x (measured - command)" if k else ""


def _say_outcome(say, task: str, out: str, summary: dict) -> None:
  state = "interrupted at" if summary["interrupted"] else "finished"
  reward = summary["final_episode_reward"]
  reward = "n/a" if reward is None else f"{reward:.3f}"
  say(
      f"{state} iteration {summary['iterations']}: {summary['env_steps']:,} env steps in "
      f"{summary['wall_s']:.0f} s, final episode reward {reward}; run in {out}", flush=True)
  if summary["interrupted"]:
    again = " (on every process, with the same flags)" if summary.get("processes", 1) > 1 else ""
    say(f"continue with: python -m experiments.{task} --resume {out}{again}", flush=True)
