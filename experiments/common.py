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
  """Prints known user errors as ``error: <one line>`` and exits 2, without a traceback."""
  from mash import experiment, robots, runs
  known = (UserError, experiment.ConfigError, runs.RunError, robots.SpecError)
  try:
    yield
  except known as e:
    print(f"error: {e}", file=sys.stderr, flush=True)
    sys.exit(2)


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
