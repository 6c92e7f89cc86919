"""Shared command-line plumbing of the entry points: argument parsing, one-line user errors."""

from __future__ import annotations

import argparse
import contextlib
import sys
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
