"""Command-line fuzz (issue 27, item 3): a fixed-seed random mix of every entry point's flags.

Each case is an argv for one entry point: valid and invalid flags mixed (wrong types, ``1e999``,
``-0``, empty strings, repeated flags, unicode and very long paths, missing values, unknown flags).
It runs in this process with the work each entry point starts (training, evaluation, export,
sim2sim, the benchmarks, joining processes) replaced by a stand-in that raises :class:`_Started`,
so a case ends in one of three ways that pass: a clean start (the stand-in was reached, nothing on
stderr that says error), ``--help`` (exit 0), or one ``error: ...`` line on stderr with exit
status 2. Anything else (a traceback, a second error line, another exit status) fails the test,
which lists every case that did. No environment, trainer or subprocess is built.
"""

from __future__ import annotations

import random
import sys
import traceback
from typing import Callable

import pytest

from experiments import (
    armswing,
    benchmark,
    benchmark_devices,
    bipedal,
    compare,
    evaluate,
    export,
    play,
    sim2sim,
)
from mash.runs import experiment

CASES_PER_ENTRY = 50
BAD_NUMBERS = ("abc", "", "1e999", "-1e999", "nan", "inf", "-0", "1.5", "0x10", "1_000", "١٢",
               " 7 ", "9" * 400, "--", "-")
GOOD_INTS = ("0", "1", "2", "4", "-1", "64")
GOOD_FLOATS = ("0", "0.5", "0.02", "1", "-1", "20", "1e-3")
ODD_TEXT = ("", " ", "ünï路径🤖", "a" * 5000, "x\ny", "sur\udcffrogate")
GOOD_SETS = ("train.learning_rate=1e-3", "env.action_scale=0.3", "train.seed=3",
             "env.randomization.push_force=-10,10", "env.randomization.friction_initial=none",
             "env.reward_scales.joint_pos=2")
BAD_SETS = ("train.num_envs=abc", "learning_rate", "=", "", "train.nope=1", "env.commands=1",
            "train.actor_hidden=", "train.actor_hidden=0,64", "env.physics.sim_dt=0",
            "env.ctrl_dt=nan", "env.randomization.push_force=nan,1", "train.num_envs=1e999",
            "env.commands.vx=0.1", "trаin.seed=1", "env.physics.integrator=rk4", "seeds=100000",
            "train.gamma=" + "9" * 5000, "env.task=ünï", "x=\n")


class _Started(Exception):
  """Raised by the stand-ins of the entry points' work: the case started cleanly."""


def _started(*args, **kwargs):
  raise _Started


@pytest.fixture
def places(tmp_path):
  """Paths the cases use: a fake run (a valid smoke config.json, no checkpoint), broken ones, a
  file, paths that do not exist, unicode and over-long ones."""
  run = tmp_path / "run"
  run.mkdir()
  (run / "config.json").write_text(
      experiment.to_json(experiment.make_config("bipedal", "mash", "smoke")))
  broken = tmp_path / "broken"
  broken.mkdir()
  (broken / "config.json").write_text("{not json")
  junk = tmp_path / "junk"
  junk.mkdir()
  (junk / "config.json").write_text('{"train": {"num_envs": "many", "gamma": [1]}, "seeds": 1.5}')
  odd = tmp_path / "odd_values"
  odd.mkdir()
  (odd / "config.json").write_text('{"train": {"learning_rate": NaN}, "env": {"ctrl_dt": 1e999}}')
  (tmp_path / "file.txt").write_text("x")
  long_name = str(tmp_path / ("a" * 5000))
  long_path = str(tmp_path) + "/" + "/".join(["d" * 100] * 50)
  runs_ = [
      str(run),
      str(broken),
      str(junk),
      str(odd),
      str(tmp_path / "missing"),
      str(tmp_path / "file.txt"), "", "ünï路径🤖/run", long_name, long_path, "/proc/1/x",
      str(tmp_path / "new\nline"),
      str(tmp_path / "sur\udcffrogate"), "."
  ]
  outs = [
      str(tmp_path / "out"),
      str(tmp_path / "ünï路径🤖" / "out"),
      str(run), "", long_name, long_path, "/proc/forbidden",
      str(tmp_path / "file.txt"),
      str(tmp_path / "x\ny")
  ]
  policies = [
      "t1_bipedal_mash",
      str(run), "no_such_policy", "", long_name, "/proc/1/x",
      str(tmp_path / "file.txt"), "ünï路径🤖"
  ]
  return {
      "run":
          runs_, "out":
              outs, "policy":
                  policies, "file": [
                      str(tmp_path / "p.onnx"),
                      str(tmp_path / "ünï.onnx"),
                      str(run), "", long_name, "/proc/x.onnx",
                      str(tmp_path / "missing" / "deep" / "p.onnx")
                  ], "mp4": [
                      str(tmp_path / "v.mp4"),
                      str(tmp_path / "v.avi"), "", long_name + ".mp4", "/proc/x.mp4",
                      str(tmp_path / "ünï路径🤖.mp4"),
                      str(run)
                  ]
  }


def _value(rng: random.Random, kind: str, places: dict) -> str:
  """A value for a flag of ``kind``: one that fits more often than not, else one that does not."""
  fits = rng.random() < 0.6
  if kind in ("int", "float"):
    return rng.choice((GOOD_INTS if kind == "int" else GOOD_FLOATS) if fits else BAD_NUMBERS)
  if kind == "set":
    return rng.choice(GOOD_SETS if fits else BAD_SETS)
  if kind in places:  # the first place fits; the others (and odd text) do not
    return places[kind][0] if fits else rng.choice(places[kind][1:] + list(ODD_TEXT[:3]))
  choices = kind.split("|")  # a choice flag: its values (the last one unknown), or odd text
  return rng.choice(choices[:-1] if fits else choices[-1:] + list(ODD_TEXT))


# Each entry point: how to call its main, and its flags as (flag, kind); kind None: a switch;
# "float2": two numbers. A flag in REQUIRED goes into most cases.
TRAIN_FLAGS = (("--algo", "mash|ppo|sac"), ("--preset", "smoke|cpu|gpu|huge"), ("--seeds", "int"),
               ("--out", "out"), ("--resume", "run"), ("--ablation",
                                                       "none|no_sharing|per_limb|magic"),
               ("--set", "set"), ("--set", "set"), ("--no-progress", None), ("--coordinator",
                                                                             "127.0.0.1:1|x"),
               ("--num-processes", "int"), ("--process-id", "int"), ("--local-processes",
                                                                     "auto|1|2|3|x"))
ENTRIES: dict[str, tuple[Callable, tuple, tuple]] = {
    "bipedal": (bipedal.main, TRAIN_FLAGS, ("--preset",)),
    "armswing": (armswing.main, TRAIN_FLAGS, ("--preset",)),
    "evaluate": (evaluate.main, (("--run", "run"), ("--episodes", "int"), ("--seconds", "float"),
                                 ("--command-vx", "float"), ("--no-dr", None), ("--no-push", None),
                                 ("--push-interval", "float"), ("--iteration", "int"),
                                 ("--friction", "float2"), ("--seed", "int"), ("--tracking", None)),
                 ("--run",)),
    "export": (export.main, (("--run", "run"), ("--out", "file"), ("--seed", "int"),
                             ("--check", "int"), ("--tolerance", "float")), ("--run",)),
    "sim2sim":
        (sim2sim.main,
         (("--run", "run"), ("--episodes", "int"), ("--seconds", "float"),
          ("--command-vx", "float"), ("--sim-dt", "float"), ("--iterations", "int"),
          ("--seed", "int"), ("--onnx", "file"), ("--video", "mp4"), ("--video-seconds", "float"),
          ("--viewer", None), ("--no-mjx", None), ("--mjx-episodes", "int"), ("--mjx-dr",
                                                                              None)), ("--run",)),
    "compare":
        (compare.main,
         (("--task", "bipedal|armswing|swim"), ("--seeds", "int"), ("--preset", "smoke|cpu|huge"),
          ("--out", "out"), ("--episodes", "int"), ("--eval-seconds", "float"), ("--set", "set"),
          ("--learning-rates", "1e-3,3e-4|3e-4|1e-3|nan,1e-3"), ("--seeds-at-once", "int"),
          ("--no-progress", None)), ("--preset",)),
    "benchmark":
        (benchmark.main,
         (("--quick", None), ("--batch", "int"), ("--task", "bipedal|armswing|swim"),
          ("--out", "out"), ("--sweep", "batch|physics|other"), ("--breakdown", None),
          ("--batches", "64,256|64|0,-1"), ("--stages", "env,mash|physics|env,brax"), ("--dir",
                                                                                       "out")), ()),
    # With a display (set for these cases) play opens the viewer, whose stand-in starts it.
    "play": (play.main, (("--policy", "policy"), ("--command", "0.4|0.3,0,0.5|-0.2,0.1|fast"),
                         ("--stand", None), ("--seconds", "float"), ("--video", "mp4"),
                         ("--phase", "float")), ("--policy",)),
    # The hidden worker flags are the launcher's own; --worker runs a worker outright.
    "benchmark_devices":
        (benchmark_devices.main,
         (("--batch", "int"), ("--steps", "int"), ("--repeats", "int"),
          ("--task", "bipedal|armswing|swim"), ("--train", None), ("--train-batch", "int"),
          ("--platform", "cpu|gpu|tpu|nope"), ("--out", "out"), ("--process-id",
                                                                 "int"), ("--num-processes", "int"),
          ("--coordinator", "127.0.0.1:1|x"), ("--sync-dir", "out"), ("--result", "file")), ()),
}


def _case(rng: random.Random, flags: tuple, required: tuple, places: dict) -> list[str]:
  """One argv: the required flags most of the time, then a few random ones, sometimes an
  unknown flag, a stray word, a repeated flag or a flag left without its value at the end."""
  argv = []
  chosen = [f for f in flags if f[0] in required and rng.random() < 0.85]
  chosen += rng.sample(flags, rng.randint(0, min(5, len(flags))))
  for flag, kind in chosen:
    argv.append(flag)
    if kind == "float2":
      argv += [_value(rng, "float", places) for _ in range(rng.choice((2, 2, 2, 1)))]
    elif kind is not None:
      argv.append(_value(rng, kind, places))
  roll = rng.random()
  if roll < 0.08:
    argv.insert(rng.randint(0, len(argv)), rng.choice(("--bogus", "--see", "-x", "--pre")))
  elif roll < 0.12:
    argv.append(rng.choice(ODD_TEXT))
  elif roll < 0.2 and argv:
    argv = argv + argv[-2:]  # a flag given twice
  elif roll < 0.28:
    argv.append(rng.choice([f for f, kind in flags if kind is not None]))  # no value follows
  elif roll < 0.3:
    argv.append("--help")
  return argv


def _short(text: str, limit: int = 160) -> str:
  """``text`` cut to ``limit`` characters for the report."""
  return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def _outcome(run: Callable[[], None], capsys) -> tuple[str, str | None]:
  """Runs one case: ``('started' | 'help' | 'error', None)`` when it ended as it may, else
  ``('bad', why)``."""
  try:
    run()
    ended, code = "returned", None
  except _Started:
    ended, code = "started", None
  except SystemExit as e:
    ended, code = "exit", e.code
  except BaseException:  # noqa: BLE001 - any other exception is what the test looks for
    capsys.readouterr()
    return "bad", "\n".join(_short(l) for l in traceback.format_exc(limit=-2).splitlines())
  captured = capsys.readouterr()
  lines = [l for l in captured.err.splitlines() if l.strip() and "warp" not in l]
  errors = [l for l in lines if "error" in l.lower() or "Traceback" in l]
  if ended == "started" and not errors:
    return "started", None
  if ended == "exit" and code == 0 and "usage:" in captured.out:
    return "help", None
  if ended == "exit" and code == 2 and len(lines) == 1 and lines[0].startswith("error: "):
    return "error", None
  return "bad", f"{ended} {code!r}; stderr: {[_short(l) for l in lines[:4]]}"


def test_every_entry_point_starts_cleanly_or_says_one_error_line(places, tmp_path, monkeypatch,
                                                                 capsys):
  monkeypatch.chdir(tmp_path)  # default output folders (runs/, benchmark.json) land here
  for name in ("MASH_COORDINATOR", "MASH_NUM_PROCESSES", "MASH_PROCESS_ID", "MASH_LOCAL_PROCESSES",
               "DISPLAY", "WAYLAND_DISPLAY"):
    monkeypatch.delenv(name, raising=False)
  import subprocess

  from mash.analysis import reports
  from mash.bench import benchmark as bench
  from mash.bench import devices as bench_devices
  from mash.bench import sweeps
  from mash.deploy import policy
  from mash.deploy import sim2sim as sim2sim_lib
  from mash.deploy import video as video_lib
  from mash.rl import distributed
  from mash.runs import launch
  from mash.runs import loop as runs
  from mash.sim import env as env_lib
  for owner, attr in ((runs, "train"), (policy, "load"), (policy, "load_all"),
                      (launch, "run_local_processes"), (distributed, "initialize"),
                      (reports, "evaluate_run"), (reports, "tracking_run"),
                      (sim2sim_lib, "resolve_onnx"), (subprocess, "call"), (bench, "run_benchmark"),
                      (sweeps, "sweep_batch"), (sweeps, "sweep_physics"), (env_lib, "MashEnv"),
                      (bench_devices, "run_scaling"), (bench_devices,
                                                       "run_worker"), (sim2sim_lib, "interactive")):
    monkeypatch.setattr(owner, attr, _started)
  monkeypatch.setattr(video_lib, "headless_gl", lambda: (None, "no OpenGL in this test"))
  monkeypatch.setattr(sys, "argv", ["fuzz"])

  rng = random.Random(0)
  counts, bad = {}, []
  for entry, (main, flags, required) in ENTRIES.items():
    tally = counts.setdefault(entry, {"started": 0, "help": 0, "error": 0, "bad": 0})
    if entry == "play":
      monkeypatch.setenv("DISPLAY", ":99")
    for _ in range(CASES_PER_ENTRY):
      argv = _case(rng, flags, required, places)
      result, why = _outcome(lambda: main(list(argv)), capsys)
      tally[result] += 1
      if why:
        bad.append(f"{entry} {[_short(a, 60) for a in argv]!r}:\n{why}")
  total = sum(sum(t.values()) for t in counts.values())
  with capsys.disabled():
    print(f"\ncommand-line fuzz: {total} cases")
    for entry, tally in counts.items():
      print(f"  {entry}: {sum(tally.values())} cases, " +
            ", ".join(f"{n} {k}" for k, n in tally.items()))
  assert total >= 300
  assert not bad, f"{len(bad)} of {total} cases ended badly:\n\n" + "\n\n".join(bad[:15])
