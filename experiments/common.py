"""Shared command-line plumbing of the entry points: argument parsing, one-line user errors."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from typing import Iterator


class UserError(Exception):
  """A mistake in what the user asked for: printed as one line, exit status 2."""


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
  """Prints known user errors as ``error: <one line>`` and exits 2, without a traceback.

  A Ctrl-C that reaches here (before training's own signal handling is in place, or a second
  Ctrl-C that aborts a run) prints one line and exits 130, also without a traceback.
  """
  from mash import checkpoint, experiment, robots, runs
  known = (UserError, experiment.ConfigError, runs.RunError, robots.SpecError,
           checkpoint.CheckpointError)
  try:
    yield
  except known as e:
    print(f"error: {e}", file=sys.stderr, flush=True)
    sys.exit(2)
  except KeyboardInterrupt:
    print("\ninterrupted (files already on disk are kept; a run resumes from its last complete "
          "checkpoint)", file=sys.stderr, flush=True)
    sys.exit(130)


def exit_status(summary: dict) -> int:
  """0 for a run that finished; 128 + the signal number (130 SIGINT, 143 SIGTERM) for one that a
  signal stopped early, as shells report it, so scripts do not mistake it for a finished run."""
  import signal
  name = summary.get("signal")
  return 128 + signal.Signals[name].value if summary.get("interrupted") and name else 0


class Parser(argparse.ArgumentParser):
  """argparse whose errors are one line (``error: ...``) with exit status 2."""

  def error(self, message: str):  # noqa: D401 - argparse API
    print(f"error: {message} (see --help)", file=sys.stderr, flush=True)
    sys.exit(2)


def default_preset() -> tuple[str, str]:
  """The preset for this machine's JAX backend, and the backend's name."""
  import jax
  backend = jax.default_backend()
  return ("gpu" if backend in ("gpu", "cuda", "rocm", "tpu") else "cpu"), backend


# ------------------------------------------------------------------ several processes (hosts)
DISTRIBUTED_ENV = {"coordinator": "MASH_COORDINATOR", "num_processes": "MASH_NUM_PROCESSES",
                   "process_id": "MASH_PROCESS_ID"}


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
  from mash import distributed
  try:
    distributed.initialize(coordinator, num_processes=n, process_id=pid)
  except ValueError as e:
    raise UserError(str(e).rstrip(".")) from None
  except Exception as e:  # noqa: BLE001 - a failed join (timeout, address in use): one line
    first = (str(e).strip().splitlines() or [""])[0][:200]
    raise UserError(f"process {pid} of {n} could not join the run at {coordinator}: "
                    f"{type(e).__name__}: {first}") from None
  import jax
  return jax.process_index() == 0


def shared_time() -> float:
  """``time.time()`` of process 0, the same in every process (names default run directories)."""
  import jax
  now = time.time()
  if jax.process_count() == 1:
    return now
  import numpy as np
  from jax.experimental import multihost_utils
  return float(multihost_utils.broadcast_one_to_all(np.int32(int(now))))


def devices_note() -> str:
  """``'; 2 devices in 2 processes'`` when training may use several devices, else ``''``."""
  import jax
  n, p = jax.device_count(), jax.process_count()
  if n == 1:
    return ""
  return f"; {n} devices" + (f" in {p} processes" if p > 1 else "")
