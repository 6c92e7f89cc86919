"""Command-line plumbing shared by every entry point: argument parsing, checks of paths before any
work, and one-line errors (``error: ...``) instead of tracebacks. Nothing here imports training
code, so deployment commands use it too; launching training processes is :mod:`mash.runs.launch`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
from pathlib import Path
from typing import Iterator

import jax

from mash import errors
from mash.sim import robots, tasks


class UserError(errors.InputError):
  """A mistake in a command's arguments: printed as one line, exit status 2."""


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
  """Prints known user errors as ``error: <one line>`` and exits 2, without a traceback.

  A write the storage refuses (a full disk, a quota, a read-only file system: ``ENOSPC``,
  ``EDQUOT``, ``EROFS``), from training (:class:`mash.errors.StorageError`, which names what is
  kept) or from any other command (a metrics file, an ONNX export), is one ``error:`` line too,
  with exit status 1: not a mistake in the input, and the same command succeeds once there is room.

  A Ctrl-C that reaches here (before training's own signal handling is in place, or a second
  Ctrl-C that aborts a run) prints one line and exits 130, also without a traceback.

  Standard output that refuses what it cannot encode is set to escape it instead: a file name
  with bytes that are not UTF-8 (argv holds them as lone surrogates) is then printed as
  ``\\udcff`` rather than ending the command with a UnicodeEncodeError.
  """
  if getattr(sys.stdout, "errors", None) == "strict" and hasattr(sys.stdout, "reconfigure"):
    sys.stdout.reconfigure(errors="backslashreplace")
  try:
    yield
  except errors.InputError as e:
    print(f"error: {one_line(str(e))}", file=sys.stderr, flush=True)
    sys.exit(2)
  except errors.StorageError as e:
    print(f"error: {one_line(str(e))}", file=sys.stderr, flush=True)
    sys.exit(1)
  except Exception as e:  # noqa: BLE001 - only a refusing storage is handled here
    code = errors.storage_errno(e)
    if code is None:
      raise
    name = getattr(e, "filename", None)
    where = f" '{shown_path(name)}'" if name else ""
    print(
        f"error: cannot write{one_line(where)}: {os.strerror(code)}; free space, then run the "
        "command again", file=sys.stderr, flush=True)
    sys.exit(1)
  except KeyboardInterrupt:
    print(
        "\ninterrupted (files already on disk are kept; a run resumes from its last complete "
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
  """``--task``: one of the tasks (``mash.sim.tasks``); a UserError naming them otherwise."""
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
  if robot in robots.names():
    return robot
  return str(Path(robot).expanduser().resolve()) if Path(robot).expanduser().is_file() else robot


def default_preset() -> tuple[str, str]:
  """The preset for this machine's JAX backend, and the backend's name."""
  backend = jax.default_backend()
  return ("gpu" if backend in ("gpu", "cuda", "rocm", "tpu") else "cpu"), backend
