"""Two local processes by default on a CPU: the rule that picks them, and the supervisor that runs
them (environment, exit status, signals passed on once), with a stand-in worker instead of a
training run (the training path itself is ``test_distributed``'s)."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from mash.cli import UserError
from mash.runs import launch

ROOT = Path(__file__).resolve().parent.parent


def _args(**kw) -> argparse.Namespace:
  base = dict(local_processes="auto", num_processes=None, coordinator=None, process_id=None)
  base.update(kw)
  return argparse.Namespace(**base)


def test_auto_is_two_processes_for_one_seed_on_a_multicore_cpu(monkeypatch):
  monkeypatch.delenv("MASH_NUM_PROCESSES", raising=False)
  monkeypatch.setattr(os, "cpu_count", lambda: 2)
  assert launch.local_processes_wanted(_args(), "cpu", 1) == 2  # JAX's backend here is the CPU
  assert launch.local_processes_wanted(_args(), "smoke", 1) == 1  # collectives outweigh a core
  assert launch.local_processes_wanted(_args(), "cpu", 3) == 1  # seeds train in one process
  assert launch.local_processes_wanted(_args(num_processes="2"), "cpu", 1) == 1  # joined by hand
  monkeypatch.setattr(os, "cpu_count", lambda: 1)
  assert launch.local_processes_wanted(_args(), "cpu", 1) == 1
  assert launch.local_processes_wanted(_args(local_processes="3"), "smoke", 1) == 3


@pytest.mark.parametrize("kw, words", [
    (dict(local_processes="two"), "--local-processes must be 'auto' or a whole number >= 1"),
    (dict(local_processes="0"), "got '0'"),
    (dict(local_processes="2", coordinator="h:1"), "cannot be combined with --coordinator"),
])
def test_bad_local_processes_is_a_user_error(kw, words):
  with pytest.raises(UserError, match=words):
    launch.local_processes_wanted(_args(**kw), "cpu", 1)


WORKER = textwrap.dedent("""
    import os, signal, sys, time
    pid = os.environ["MASH_PROCESS_ID"]
    out = sys.argv[1]
    def stop(signum, frame):
      with open(f"{out}/signal{pid}", "a") as f:
        f.write(f"{signum}\\n")
      sys.exit(128 + signum)
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    with open(f"{out}/env{pid}", "w") as f:
      f.write(" ".join(os.environ[k] for k in ("MASH_COORDINATOR", "MASH_NUM_PROCESSES",
                                                "MASH_PROCESS_ID", "MASH_LOCAL_PROCESSES")))
    print(f"worker {pid} says hello", flush=True)
    if len(sys.argv) > 2:
      sys.exit(int(sys.argv[2]) if pid == "1" else 0)
    time.sleep(60)
    """)


def _supervise(tmp_path: Path, *worker_args: str) -> subprocess.Popen:
  (tmp_path / "fake_worker.py").write_text(WORKER)
  code = ("import sys; from mash.runs import launch; "
          f"sys.exit(launch.run_local_processes('fake_worker', {list(worker_args)!r}, 2))")
  env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)]))
  return subprocess.Popen([sys.executable, "-c", code], env=env, cwd=ROOT, text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _wait_for(path: Path, timeout_s: float = 30.0) -> None:
  deadline = time.monotonic() + timeout_s
  while not path.exists():
    assert time.monotonic() < deadline, f"{path} never appeared"
    time.sleep(0.05)


def test_supervisor_gives_each_process_its_place_and_passes_a_signal_once(tmp_path):
  """SIGTERM to the supervisor reaches each worker exactly once; it exits with their 143; process
  0's output is the supervisor's, process 1's is not shown when it stopped like process 0."""
  proc = _supervise(tmp_path, str(tmp_path))
  _wait_for(tmp_path / "env0")
  _wait_for(tmp_path / "env1")
  proc.send_signal(signal.SIGTERM)
  out, err = proc.communicate(timeout=30)
  assert proc.returncode == 143, err
  for i in (0, 1):
    coordinator, n, pid, local = (tmp_path / f"env{i}").read_text().split()
    assert coordinator.startswith("127.0.0.1:") and n == "2" and pid == str(i) and local == "1"
    assert (tmp_path / f"signal{i}").read_text().split() == [str(int(signal.SIGTERM))]
  assert (tmp_path / "env0").read_text().split()[0] == (tmp_path / "env1").read_text().split()[0]
  assert "worker 0 says hello" in out and "worker 1" not in out + err


def test_supervisor_reports_a_failed_process_and_its_output(tmp_path):
  proc = _supervise(tmp_path, str(tmp_path), "3")
  out, err = proc.communicate(timeout=30)
  assert proc.returncode == 3
  assert "process 1 of 2 exited with status 3" in err and "worker 1 says hello" in err
