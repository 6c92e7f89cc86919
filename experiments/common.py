"""Shared command-line plumbing of the entry points: argument parsing, one-line user errors."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path
from typing import Iterator


class UserError(Exception):
  """A mistake in what the user asked for: printed as one line, exit status 2."""


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
  """Prints known user errors as ``error: <one line>`` and exits 2, without a traceback.

  A write the storage refuses (a full disk, a quota, a read-only file system: ``ENOSPC``,
  ``EDQUOT``, ``EROFS``), from training (:class:`mash.checkpoint.StorageError`, which names what is
  kept) or from any other command (a metrics file, an ONNX export), is one ``error:`` line too,
  with exit status 1: not a mistake in the input, and the same command succeeds once there is room.

  A Ctrl-C that reaches here (before training's own signal handling is in place, or a second
  Ctrl-C that aborts a run) prints one line and exits 130, also without a traceback.

  Standard output that refuses what it cannot encode is set to escape it instead: a file name
  with bytes that are not UTF-8 (argv holds them as lone surrogates) is then printed as
  ``\\udcff`` rather than ending the command with a UnicodeEncodeError.
  """
  from mash import checkpoint, experiment, policy, robots  # not mash.runs: it imports training
  known = (UserError, experiment.ConfigError, policy.RunError, robots.SpecError,
           checkpoint.CheckpointError)
  if getattr(sys.stdout, "errors", None) == "strict" and hasattr(sys.stdout, "reconfigure"):
    sys.stdout.reconfigure(errors="backslashreplace")
  try:
    yield
  except known as e:
    print(f"error: {one_line(str(e))}", file=sys.stderr, flush=True)
    sys.exit(2)
  except checkpoint.StorageError as e:
    print(f"error: {one_line(str(e))}", file=sys.stderr, flush=True)
    sys.exit(1)
  except Exception as e:  # noqa: BLE001 - only a refusing storage is handled here
    code = checkpoint.storage_errno(e)
    if code is None:
      raise
    name = getattr(e, "filename", None)
    where = f" '{shown_path(name)}'" if name else ""
    print(f"error: cannot write{one_line(where)}: {os.strerror(code)}; free space, then run the "
          "command again", file=sys.stderr, flush=True)
    sys.exit(1)
  except KeyboardInterrupt:
    print("\ninterrupted (files already on disk are kept; a run resumes from its last complete "
          "checkpoint)", file=sys.stderr, flush=True)
    sys.exit(130)


def one_line(text: str) -> str:
  """``text`` as one printable line: line breaks shown as ``\\n`` / ``\\r`` (a value typed with
  one, such as a path, must not split an error message) and the undecodable bytes of a file name
  (lone surrogates, which no stream can encode) as ``\\udcff``."""
  text = text.replace("\r", "\\r").replace("\n", "\\n")
  return text.encode("utf-8", "backslashreplace").decode("utf-8")


def shown_path(path: str | os.PathLike, limit: int = 120) -> str:
  """``path`` for a message: as it is, or its first and last characters around an ellipsis and
  its length when it is longer than ``limit``."""
  text = str(path)
  if len(text) <= limit:
    return text
  return f"{text[:limit // 2]}...{text[-limit // 4:]} ({len(text)} characters)"


def check_path(path: str, flag: str) -> None:
  """Checks, before any work, that ``path`` can name a file or folder on this system: not empty,
  no NUL character, not too long (each name, and the whole path), representable in the file
  system's encoding. Whether it exists or can be written is for the caller to check.

  Raises:
    UserError: one line naming ``flag``, the path (shortened when long) and the reason.
  """
  if not path.strip():
    raise UserError(f"{flag} is empty; expected a path")
  try:
    os.stat(path)
  except (FileNotFoundError, NotADirectoryError, PermissionError):
    pass  # a path that does not exist (yet), or not here, is the caller's to judge
  except OSError as e:
    raise UserError(f"{flag} '{shown_path(path)}' cannot be used: {e.strerror or e}") from None
  except ValueError as e:  # a NUL character, or one the file system's encoding cannot hold
    raise UserError(f"{flag} '{shown_path(path)}' cannot be used: {e}") from None


def check_task(task: str) -> None:
  """``--task``: one of the tasks (``mash.tasks``); a UserError naming them otherwise."""
  from mash import tasks
  try:
    tasks.get(task)
  except ValueError as e:
    raise UserError(f"--task: {e}") from None


def check_paths(paths: dict[str, str | None]) -> None:
  """:func:`check_path` on each ``{flag: path}`` given (a None is a flag left out)."""
  for flag, path in paths.items():
    if path is not None:
      check_path(path, flag)


def _unwritable(folder) -> str | None:
  """Why a file cannot be written in ``folder`` (made if missing, as the work would make it; the
  probe file is removed), or None when it can."""
  if folder.exists() and not folder.is_dir():
    return "it is a file, not a folder"
  try:
    folder.mkdir(parents=True, exist_ok=True)
    probe = folder / f".mash_write_probe_{os.getpid()}"
    probe.write_bytes(b"")
    probe.unlink()
  except OSError as e:
    return e.strerror or str(e)
  return None


def check_writable_dir(path: str | os.PathLike, flag: str) -> None:
  """Checks, before any work, that files can be written in the folder ``path``.

  Raises:
    UserError: one line naming ``flag``, the path and the reason.
  """
  reason = _unwritable(Path(path))
  if reason:
    raise UserError(f"{flag} '{path}' cannot be written: {reason}")


def check_writable_file(path: str | os.PathLike, flag: str) -> None:
  """Checks, before any work, that the file ``path`` can be written: not a folder, and its folder
  takes a new file.

  Raises:
    UserError: one line naming ``flag``, the path and the reason.
  """
  file = Path(path)
  if file.is_dir():
    raise UserError(f"{flag} '{file}' is a folder; expected a file path")
  reason = _unwritable(file.parent)
  if reason:
    raise UserError(f"{flag} '{file}' cannot be written (folder '{file.parent}': {reason})")


def exit_status(summary: dict) -> int:
  """0 for a run that finished; 128 + the signal number (130 SIGINT, 143 SIGTERM) for one that a
  signal stopped early, as shells report it, so scripts do not mistake it for a finished run."""
  import signal
  name = summary.get("signal")
  return 128 + signal.Signals[name].value if summary.get("interrupted") and name else 0


class Parser(argparse.ArgumentParser):
  """argparse whose errors are one line (``error: ...``) with exit status 2."""

  def error(self, message: str):  # noqa: D401 - argparse API
    print(f"error: {one_line(message)} (see --help)", file=sys.stderr, flush=True)
    sys.exit(2)


def robot_arg(robot: str) -> str:
  """``--robot``: a shipped robot's name as given, a robot file as its absolute path (so that the
  run's config.json names it from any working directory)."""
  from mash import robots
  if robot in robots.names():
    return robot
  return str(Path(robot).expanduser().resolve()) if Path(robot).expanduser().is_file() else robot


def default_preset() -> tuple[str, str]:
  """The preset for this machine's JAX backend, and the backend's name."""
  import jax
  backend = jax.default_backend()
  return ("gpu" if backend in ("gpu", "cuda", "rocm", "tpu") else "cpu"), backend


# ------------------------------------------------------------------ several processes (hosts)
DISTRIBUTED_ENV = {"coordinator": "MASH_COORDINATOR", "num_processes": "MASH_NUM_PROCESSES",
                   "process_id": "MASH_PROCESS_ID"}
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
  g.add_argument("--local-processes", default="auto", metavar="N",
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


def joined_by_hand(args: argparse.Namespace) -> bool:
  """Whether the multi-host flags (or their ``MASH_*`` variables) join processes by hand."""
  return bool(args.num_processes or os.environ.get(DISTRIBUTED_ENV["num_processes"])
              or args.coordinator or args.process_id is not None)


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
    import jax
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
    import ctypes
    import signal
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
  import signal
  import socket
  import subprocess
  import tempfile
  import warnings

  with socket.socket() as sock:
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
  env = dict(os.environ)
  env.update({DISTRIBUTED_ENV["coordinator"]: f"127.0.0.1:{port}",
              DISTRIBUTED_ENV["num_processes"]: str(n), "MASH_LOCAL_PROCESSES": "1"})
  logs, procs = [], []
  for i in range(n):
    env[DISTRIBUTED_ENV["process_id"]] = str(i)
    log = None if i == 0 else tempfile.TemporaryFile(mode="w+")
    logs.append(log)
    with warnings.catch_warnings():
      # The child execs a fresh interpreter at once (after one prctl call), so the fork of this
      # process, whose JAX has threads, cannot deadlock it, as Python's warning fears.
      warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called",
                              category=RuntimeWarning)
      procs.append(subprocess.Popen([sys.executable, "-m", module, *argv], env=dict(env),
                                    stdout=log, stderr=subprocess.STDOUT if log else None,
                                    start_new_session=True, preexec_fn=_die_with_parent))

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
