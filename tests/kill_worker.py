"""Worker process of ``tests/test_reliability.py``: the training CLI, SIGKILLed at a chosen point.

``python tests/kill_worker.py MARKS KILL -- ARGV...`` runs ``experiments.bipedal ARGV...`` (through
``experiments.bipedal.main``) with nothing changed but two observation points, and creates an
empty file in the folder ``MARKS`` at each (the test waits for them, and checks where a kill fell):

- ``call_N``: the N-th ``train_epoch`` call of this process starts (a jitted call).
- ``killed_in_call_N``, ``killed_in_save_S``: just before the process SIGKILLs itself.

``KILL`` says where to die (``none``: nowhere, the run goes on as the CLI's own):

- ``call:N``: one second into the N-th ``train_epoch`` call, while the jitted program runs (N >= 2,
  so that the call does not also compile). The call is waited on before it returns; when it ends
  before the second is up, the process exits 3 instead (no ``killed_in_call_N``).
- ``save:S``: while checkpoint step S is being written: Orbax has written the state item's files
  into the step's temporary directory and is about to rename that item into place (the step
  itself, renamed last, is not complete).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

SECONDS_INTO_CALL = 0.1  # a smoke call takes ~0.5 s on quiet cores


def _mark(marks: Path, name: str) -> None:
  (marks / name).touch()
  print(f"kill_worker: {name}", flush=True)


def _die(marks: Path, name: str) -> None:
  _mark(marks, name)
  os.kill(os.getpid(), signal.SIGKILL)


def _watch_calls(marks: Path, kill_call: int | None) -> None:
  """Wraps the trainer ``mash.runs.loop.train`` builds: marks each call, kills in call
  ``kill_call``."""
  import jax

  from mash.runs import loop as runs
  build = runs.build_trainer

  def build_trainer(cfg):
    trainer = build(cfg)
    epoch, count = trainer.train_epoch, [0]

    def train_epoch(state):
      count[0] += 1
      n = count[0]
      _mark(marks, f"call_{n}")
      if n != kill_call:
        return epoch(state)
      running = threading.Event()
      running.set()
      timer = threading.Timer(SECONDS_INTO_CALL,
                              lambda: running.is_set() and _die(marks, f"killed_in_call_{n}"))
      timer.start()
      jax.block_until_ready(epoch(state))
      running.clear()
      print(f"kill_worker: call {n} ended within {SECONDS_INTO_CALL} s, before the kill",
            flush=True)
      os._exit(3)

    return trainer._replace(train_epoch=train_epoch)

  runs.build_trainer = build_trainer


def _watch_saves(marks: Path, step: int) -> None:
  """Kills the process when Orbax is about to rename the written ``state`` item of checkpoint
  ``step`` into place, inside the step's still temporary directory."""
  from orbax.checkpoint._src.path import atomicity
  finalize = atomicity.AtomicRenameTemporaryPath.finalize
  step_tmp = f"{step}{atomicity.TMP_DIR_SUFFIX}"

  async def watched(self):
    final = self.get_final()
    if final.name == "state" and final.parent.name == step_tmp:
      _die(marks, f"killed_in_save_{step}")
    return await finalize(self)

  atomicity.AtomicRenameTemporaryPath.finalize = watched


def main() -> None:
  marks, kill, dash, *argv = sys.argv[1:]
  assert dash == "--", sys.argv
  marks = Path(marks)
  what, _, where = kill.partition(":")
  _watch_calls(marks, int(where) if what == "call" else None)
  if what == "save":
    _watch_saves(marks, int(where))
  from experiments import bipedal
  bipedal.main(argv)


if __name__ == "__main__":
  main()
