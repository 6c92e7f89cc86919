"""Reliability: physics blow-ups, bad input, interrupted runs, torn checkpoints, determinism.

Cost on 2 CPU cores: every MJX program here is the one the session's ``smoke_run`` fixture compiled.
In this process the ``smoke_trainer`` fixture reuses it (a smoke call is ~4 s); the CLI
subprocesses load it from the persistent compilation cache that ``conftest.py`` turns on (~40 s a
process instead of ~3 min, mostly tracing and lowering). The toy-env tests reuse ``mash_trainer``.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mash.deploy import policy
from mash.rl import losses
from mash.rl.config import TrainConfig
from mash.runs import checkpoint
from mash.runs import loop as runs
from mash.sim import model as model_lib
from mash.sim import robots

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------- helpers
def _rows_without_wall(path: Path) -> list[dict[str, str]]:
  """A progress CSV as text fields, minus the wall-clock column."""
  with path.open() as f:
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in csv.DictReader(f)]


def _tree_digest(root: Path) -> dict[str, str]:
  """``{relative path: sha1}`` of every file under ``root``."""
  return {
      str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
      for p in sorted(root.rglob("*"))
      if p.is_file()
  }


def _tear(step_dir: Path) -> None:
  """Overwrites every file of a checkpoint step with garbage (a torn copy, a bad disk)."""
  for p in step_dir.rglob("*"):
    if p.is_file():
      p.write_bytes(b"\x00garbage\xff")


def _stderr_lines(text: str) -> list[str]:
  """Non-empty stderr lines, without MuJoCo's import notes about the optional warp backend."""
  return [l for l in text.splitlines() if l.strip() and "warp" not in l]


def _subprocess_env() -> dict[str, str]:
  """This environment (with conftest's compilation-cache settings) plus the repository on the
  path."""
  path = os.environ.get("PYTHONPATH", "")
  return dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{path}" if path else str(REPO))


def _finite(tree) -> bool:
  """Every floating-point leaf of ``tree`` is finite."""
  return all(
      bool(np.all(np.isfinite(np.asarray(x))))
      for x in jax.tree.leaves(tree)
      if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating))


# ----------------------------------------------------------------- 1. physics blow-ups (NaN/inf)
def test_gae_gives_a_blown_up_step_zero_advantage():
  """gamma 0.5, lambda 1, one env, one agent; step 1 blew up (NaN reward and next value, done).

  step 2: delta = 1 + 0.5 * 1.0 - 0.5 = 1.0, A2 = 1.0;
  step 1: masked, delta = 0, and done cuts the recursion: A1 = 0, return = V1 = 3;
  step 0: delta = 1 + 0.5 * 4 - 2 = 1.0, A0 = 1.0 + 0.5 * 1 * A1 = 1.0 (bootstrapped from the last
  finite state, not penalized as a fall).
  """
  rewards = jnp.array([[1.0], [jnp.nan], [1.0]])
  values = jnp.array([[[2.0]], [[3.0]], [[0.5]]])
  next_values = jnp.array([[[4.0]], [[jnp.nan]], [[1.0]]])
  dones = jnp.array([[0.0], [1.0], [0.0]])
  zeros = jnp.zeros((3, 1))
  adv, ret = losses.compute_gae(rewards, values, next_values, dones, zeros, 0.5, 1.0,
                                valid=jnp.array([[1.0], [0.0], [1.0]]))
  np.testing.assert_allclose(adv[:, 0, 0], [1.0, 0.0, 1.0])
  np.testing.assert_allclose(ret[:, 0, 0], [3.0, 3.0, 1.5])
  # Unmasked, the NaN reaches the earlier step of the same episode (NaN * 0 is NaN).
  adv, _ = losses.compute_gae(rewards, values, next_values, dones, zeros, 0.5, 1.0)
  assert np.isnan(adv[1, 0, 0]) and np.isnan(adv[0, 0, 0])


def test_masked_samples_leave_advantage_statistics_and_loss():
  # Advantages 1, 3 (weight 1) and NaN (weight 0): mean 2, std 1 -> -1, 1 and exactly 0.
  adv = jnp.array([[1.0], [3.0], [jnp.nan]])
  out = losses.normalize_advantages(adv, weights=jnp.array([1.0, 1.0, 0.0]))
  np.testing.assert_allclose(out[:, 0], [-1.0, 1.0, 0.0], rtol=1e-6)
  # The weighted loss of 3 samples equals the plain loss of the 2 with weight 1.
  k = jax.random.split(jax.random.key(0), 7)
  m, n = 3, 2
  args = [jax.random.normal(k[i], (m, n)) for i in range(7)]  # log_probs ... returns, entropy
  cfg = TrainConfig()
  weighted, wm = losses.mappo_loss_terms(*args, cfg, weights=jnp.array([1.0, 1.0, 0.0]))
  plain, pm = losses.mappo_loss_terms(*[a[:2] for a in args], cfg)
  np.testing.assert_allclose(weighted, plain, rtol=1e-6)
  for key in pm:
    np.testing.assert_allclose(wm[key], pm[key], rtol=1e-6, atol=1e-7)


def test_toy_env_step_from_nan_state():
  """The toy env treats a NaN state as the real env does: done, zero reward, finite outputs."""
  from toy_env import make_toy_env
  env = make_toy_env("legs", "mash")
  states = jax.vmap(env.reset)(jax.random.split(jax.random.key(0), 2))
  ps = states.pipeline_state
  states = states.replace(pipeline_state=ps.replace(q=ps.q.at[0, 1].set(jnp.nan)))
  out = jax.jit(jax.vmap(env.step))(states, jnp.zeros((2, env.action_size)))
  np.testing.assert_array_equal(out.info["nan_reset"], [1.0, 0.0])
  assert out.done[0] == 1.0 and out.reward[0] == 0.0 and out.info["truncation"][0] == 0.0
  assert _finite((out.obs, out.info, out.metrics, out.pipeline_state))


def test_toy_trainer_survives_a_nan_state(mash_trainer):
  """NaN injected into one env's state: params stay finite, ``nan_resets`` counts it once."""
  state = mash_trainer.init(jax.random.PRNGKey(3))
  ps = state.env_state.pipeline_state
  env_state = state.env_state.replace(pipeline_state=ps.replace(q=ps.q.at[5].set(jnp.nan)))
  state, metrics = mash_trainer.train_epoch(state.replace(env_state=env_state))
  metrics = jax.device_get(metrics)
  np.testing.assert_array_equal(metrics["nan_resets"], [1, 0, 0, 0, 0])
  assert _finite(metrics), {k: v for k, v in metrics.items() if not np.all(np.isfinite(v))}
  assert _finite(jax.device_get((state.params, state.opt_state, state.normalizer, state.env_state)))


def test_mjx_trainer_survives_nan_and_inf_states(smoke_trainer):
  """The real env, batched: env 3's qpos gets a NaN, env 7's qvel an inf. Both envs are reset in
  the first step, counted, and nothing non-finite reaches the parameters or the logged metrics."""
  state = smoke_trainer.init()
  data = state.env_state.pipeline_state
  data = data.replace(qpos=data.qpos.at[3, 2].set(jnp.nan), qvel=data.qvel.at[7, 0].set(jnp.inf))
  env_state = state.env_state.replace(pipeline_state=data)
  state, metrics = smoke_trainer.train_epoch(state.replace(env_state=env_state))
  metrics = jax.device_get(metrics)
  assert metrics["nan_resets"][0] == 2, metrics["nan_resets"]
  assert metrics["episodes_completed"][0] >= 2
  assert _finite(metrics), {k: v for k, v in metrics.items() if not np.all(np.isfinite(v))}
  state = jax.device_get(state)
  assert _finite((state.params, state.opt_state, state.normalizer))
  assert _finite((state.env_state.pipeline_state.qpos, state.env_state.pipeline_state.qvel,
                  state.env_state.obs, state.env_state.info["next_critic_obs"]))


# ------------------------------------------------------------------------------- 2. bad input
def test_robot_spec_with_a_missing_joint_is_one_line(capsys):
  """model_lib.build_model names the limb, the role and the joint (a spec built in code; a file's
  names are checked when it is read); the CLI wrapper prints it as one line, exit 2."""
  from mash import cli as common
  t1 = robots.load("booster_t1")
  leg = t1.limbs[0]
  typo = dataclasses.replace(leg, joints=(leg.joints[0] + "_typo",) + leg.joints[1:])
  bad = dataclasses.replace(t1, limbs=(typo,) + t1.limbs[1:])
  with pytest.raises(
      robots.SpecError, match=rf"limb 'left_leg' joints.hip_pitch: joint "
      rf"'{leg.joints[0]}_typo' is not in the model"):
    model_lib.build_model(bad)
  with pytest.raises(SystemExit) as e, common.user_errors():
    model_lib.build_model(bad)
  assert e.value.code == 2
  lines = _stderr_lines(capsys.readouterr().err)
  assert len(lines) == 1 and lines[0].startswith("error: robot 'booster_t1': limb"), lines


def _main_error(capsys, module: str, argv: list[str]) -> str:
  """Runs an entry point in this process; returns its one error line (exit status 2)."""
  main = __import__(f"experiments.{module}", fromlist=["main"]).main
  run = lambda: main(argv)
  with pytest.raises(SystemExit) as e:
    run()
  captured = capsys.readouterr()
  lines = _stderr_lines(captured.err)
  assert e.value.code == 2 and len(lines) == 1 and lines[0].startswith("error: "), captured
  return lines[0]


@pytest.mark.parametrize("argv, words", [
    (["--set", "env.task=crawl"], "env.task 'crawl' is unknown; expected one of bipedal, armswing"),
    (["--set", "env.robot=nao"], "env.robot 'nao' is unknown"),
    (["--set", "env.partition=limbs"], "env.partition 'limbs' is unknown"),
    (["--set", "env.ctrl_dt=0.021"], "env.ctrl_dt 0.021 must be a whole multiple"),
    (["--set", "checkpoint_every=0"], "checkpoint_every must be >= 1"),
    (["--set", "env.reward_params.ramped_terms=torque_rat"
     ], "env.reward_params.ramped_terms: 'torque_rat' is not a reward term"),
    (["--set", "env.reward_params.tracking_boost=0.5"
     ], "env.reward_params.tracking_boost must be in [1, 100]"),
    (["--set", "env.randomization.friction_initial=0.3,0.1"
     ], "env.randomization.friction_initial must be a range (lo, hi) with 0 < lo <= hi"),
    (["--set", "env.randomization.friction_ramp_steps=-5"
     ], "env.randomization.friction_ramp_steps must be in [0, 2147483647] steps"),
    (["--set", "algo=sac"], "algo 'sac' is unknown"),
    (["--set", "train.num_envs=0"], "num_envs must be in [1, 1048576]"),
    (["--set", "train.learning_rate_schedule=cosine"
     ], "learning_rate_schedule 'cosine' is unknown; expected one of fixed, adaptive_kl, linear"),
    (["--seeds", "0"], "seeds must be >= 1"),
    (["--resume", "DIR", "--set", "train.num_iterations=20"], "--set cannot be combined"),
])
def test_cli_bad_config_is_one_line(capsys, tmp_path, argv, words):
  """Config mistakes that used to surface as tracebacks from deep inside (or be ignored)."""
  argv = [str(tmp_path) if a == "DIR" else a for a in argv]
  out = tmp_path / "out"
  line = _main_error(
      capsys, "bipedal",
      ["--preset", "smoke", "--out", str(out), *argv] if "--resume" not in argv else argv)
  assert words in line, line
  assert not out.exists()


def test_benchmark_bad_stage_is_one_line(capsys):
  from experiments import benchmark
  with pytest.raises(SystemExit) as e:
    benchmark.main(["--stages", "env,brax"])
  lines = _stderr_lines(capsys.readouterr().err)
  assert e.value.code == 2 and len(lines) == 1, lines
  assert lines[0].startswith("error: --stages 'env,brax': expected a comma-separated subset of "
                             "physics,env,mash,ppo,brax_ppo"), lines


def test_benchmark_ratios_only_for_measured_pairs():
  """A partial run (``--stages env,mash,brax_ppo``) reports the ratios it can, nothing else."""
  from mash.bench import benchmark
  result = {
      "env_steps_per_s": 1000.0, "env_physics_equivalent_per_s": 4000.0,
      "train_env_steps_per_s": {"mash": 750.0, "brax_ppo": 600.0}
  }
  assert benchmark.ratios(result) == {"mash_train_vs_env": 0.75, "mash_vs_brax_ppo": 1.25}
  result.update(physics_steps_per_s=5000.0, train_env_steps_per_s={"mash": 750.0, "ppo": 800.0})
  assert benchmark.ratios(result) == {
      "env_vs_physics": 0.8, "mash_train_vs_env": 0.75, "mash_vs_ppo": 0.9375
  }


def test_device_scaling_writes_table_and_plot(tmp_path):
  """``benchmark_devices`` writes its JSON, a markdown table with every row, and the PNG plot."""
  import json

  from mash.bench import devices
  row = lambda variant, n, sps, ratio: {
      "variant": variant, "processes": n, "envs_per_process": 256 // n, "env_steps_per_s": sps,
      "physics_steps_per_s": 4 * sps, "cpu_cores_used": float(
          n), "compile_s": 30.0, "ratio_vs_one_process": ratio
  }
  result = {
      "batch":
          256, "steps":
              20, "task":
                  "bipedal", "date":
                      "today", "cpu_count":
                          2, "load_average_at_start":
                              0.5, "train_batch":
                                  64,
      "summary": {
          "second_core_buys": 1.9, "second_core_buys_without_collective": 2.0,
          "collective_cost": 0.05, "second_core_buys_training": 1.5
      }, "rows": [
          row("one_process", 1, 1000.0, 1.0),
          row("two_process_mesh", 2, 1900.0, 1.9),
          row("train_one_process", 1, 800.0, 1.0),
          row("train_two_process", 2, 1200.0, 1.5)
      ]
  }
  stem = tmp_path / "scaling_devices"
  devices.write_report(result, stem)
  assert json.loads(stem.with_suffix(".json").read_text()) == result
  table = stem.with_suffix(".md").read_text()
  assert "| two_process_mesh | 2 | 128 | 1.9e+03 |" in table and "**1.90x**" in table
  assert stem.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_bad_run_directories_are_one_line(capsys, smoke_run, tmp_path):
  """--resume / --run at: a directory that is not a run, a file, a broken config.json, a run with
  no checkpoint. Nothing in them changes."""
  (tmp_path / "empty").mkdir()
  line = _main_error(capsys, "bipedal", ["--resume", str(tmp_path / "empty")])
  assert "is not a run directory (no config.json)" in line
  (tmp_path / "file").write_text("x")
  line = _main_error(capsys, "bipedal", ["--preset", "smoke", "--out", str(tmp_path / "file")])
  assert "is a file, not a run directory" in line
  assert (tmp_path / "file").read_text() == "x"
  (tmp_path / "broken").mkdir()
  (tmp_path / "broken" / "config.json").write_text("{not json")
  line = _main_error(capsys, "evaluate", ["--run", str(tmp_path / "broken")])
  assert "config.json" in line and "is not an experiment config" in line
  fresh = tmp_path / "no_checkpoint"
  fresh.mkdir()
  shutil.copy(smoke_run / "config.json", fresh / "config.json")
  before = _tree_digest(fresh)
  line = _main_error(capsys, "bipedal", ["--resume", str(fresh)])
  assert "has no complete checkpoint" in line
  assert _tree_digest(fresh) == before


@pytest.mark.parametrize("command, argv, words", [
    ("bipedal", ["--preset", "smoke", "--set", "train.learning_rate=nan"
                ], "TrainConfig.learning_rate must be in (0, 1], got nan"),
    ("bipedal", ["--preset", "smoke", "--set", "train.actor_hidden=0"
                ], "TrainConfig.actor_hidden must be one or more layer sizes >= 1"),
    ("bipedal", ["--preset", "smoke", "--set", "train.gamma=inf"], "TrainConfig.gamma must be in"),
    ("bipedal", ["--preset", "smoke", "--out", "/proc/forbidden"
                ], "--out '/proc/forbidden' cannot be written"),
    ("export", ["--run", "SMOKE", "--out", "/proc/x.onnx"
               ], "--out '/proc/x.onnx' cannot be written (folder '/proc'"),
    ("sim2sim", ["--run", "SMOKE", "--video", "/proc/x.mp4"
                ], "--video '/proc/x.mp4' cannot be written (folder '/proc'"),
])
def test_bad_numbers_and_unwritable_outputs_are_one_line_before_any_work(
    capsys, smoke_run, command, argv, words):
  """Issue 27's first five cases: each ends in one error line before any work, nothing written."""
  before = _tree_digest(smoke_run)
  argv = [str(smoke_run) if a == "SMOKE" else a for a in argv]
  line = _main_error(capsys, command, argv)
  assert words in line, line
  assert _tree_digest(smoke_run) == before


def test_out_holding_a_run_is_refused_and_untouched(smoke_run, smoke_config):
  """5. ``runs.train`` into a run directory without ``resume``: refused before anything is
  written, whatever the config (the CLI case is in test_experiments)."""
  before = _tree_digest(smoke_run)
  for cfg in (smoke_config, dataclasses.replace(smoke_config, seeds=2)):
    with pytest.raises(runs.RunError, match="already holds a run; pass --resume"):
      runs.train(cfg, smoke_run, show_progress=False)
  assert _tree_digest(smoke_run) == before


# ------------------------------------------------- 4. determinism, torn checkpoints, exact resume
@pytest.fixture(scope="module")
def second_run(tmp_path_factory, smoke_config, smoke_trainer, smoke_run):
  """The smoke run again, from a fresh state, checkpointing every call (steps 5 and 10)."""
  out = tmp_path_factory.mktemp("runs") / "second"
  runs.train(dataclasses.replace(smoke_config, checkpoint_every=1), out, show_progress=False,
             trainer=smoke_trainer)
  return out


def test_same_seed_gives_bit_identical_progress(smoke_run, second_run):
  """Same seed, same device count: every logged number is equal (``wall_s`` aside)."""
  for name in ("progress.csv",):
    a, b = _rows_without_wall(smoke_run / name), _rows_without_wall(second_run / name)
    assert len(a) == 10 and a == b, name


def test_torn_latest_checkpoint_falls_back_and_resumes(second_run, smoke_trainer, tmp_path, capfd):
  """Garbage in the newest step (10): loading warns once and uses step 5; ``--resume`` moves the
  torn step aside (never deletes it), retrains 6..10 and logs exactly what the intact run logged,
  its clock going on from step 5's logged ``wall_s`` though no ``summary.json`` is left."""
  run = tmp_path / "torn"
  shutil.copytree(second_run, run)
  _tear(run / "checkpoints" / "10")
  torn = _tree_digest(run / "checkpoints" / "10")
  capfd.readouterr()
  loaded = policy.load(run)  # without a trainer, as evaluate, export and sim2sim load
  assert loaded.iteration == 5
  warnings = _stderr_lines(capfd.readouterr().err)
  assert len(warnings) == 1 and warnings[0].startswith("warning: checkpoint step 10") \
      and "trying step 5" in warnings[0], warnings
  assert _tree_digest(run / "checkpoints" / "10") == torn  # loading changes nothing

  # As a kill leaves it: no summary.json. The clock goes on from step 5's row (set to 1000 s here).
  (run / "summary.json").unlink()
  with (run / "progress.csv").open() as f:
    rows = list(csv.DictReader(f))
  rows[4]["wall_s"] = "1000.0"
  with (run / "progress.csv").open("w", newline="") as f:
    writer = csv.DictWriter(f, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)

  cfg = runs.load_config(run)
  summary = runs.train(cfg, run, resume=True, show_progress=False, trainer=smoke_trainer)
  assert summary["iterations"] == 10 and not summary["interrupted"]
  wall = policy.read_progress(run)["wall_s"]
  assert np.all(wall[5:] > 1000.0) and np.all(np.diff(wall[5:]) >= 0), wall
  assert summary["wall_s"] >= wall[-1]
  assert _tree_digest(run / "checkpoints_unrestorable" / "10") == torn
  assert _rows_without_wall(run / "progress.csv") == _rows_without_wall(second_run / "progress.csv")
  assert runs.restore_run(run, smoke_trainer).step == 10
  # A partial step (an interrupted Orbax write: a temporary directory) is never taken for complete.
  shutil.copytree(run / "checkpoints" / "10", run / "checkpoints" / "15.orbax-checkpoint-tmp-1")
  assert runs.restore_run(run, smoke_trainer).step == 10


def _du(path: Path) -> int:
  return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def test_checkpoints_without_env_state_are_small_and_resume(smoke_config, smoke_trainer, second_run,
                                                            tmp_path):
  """``checkpoint_env_state = False``: step 5 holds no env state (under half the full step's
  bytes) and the same learning state as the full run's step 5; a resume from it trains 6..10 on
  fresh episodes (iterations 1..5 logged as before), with the curriculum clock at 5 x 16 steps."""
  cfg = dataclasses.replace(smoke_config, checkpoint_env_state=False, checkpoint_every=1)
  run = tmp_path / "lean"
  runs.train(cfg, run, show_progress=False, max_calls=1, trainer=smoke_trainer)
  lean_bytes, full_bytes = _du(run / "checkpoints" / "5"), _du(second_run / "checkpoints" / "5")
  assert lean_bytes < 0.5 * full_bytes, (lean_bytes, full_bytes)
  lean = runs.restore_run(run, smoke_trainer, fields=checkpoint.LEARNING_FIELDS).state
  manager = checkpoint.make_manager(second_run / "checkpoints", max_to_keep=None)
  full = checkpoint.restore(manager, 5, smoke_trainer.state_shapes()).state
  manager.close()
  for name in checkpoint.LEARNING_FIELDS:
    jax.tree.map(np.testing.assert_array_equal, getattr(lean, name), getattr(full, name))
  with pytest.raises(runs.RunError):  # a full restore finds no env state in it
    runs.restore_run(run, smoke_trainer)
  resumed = runs.with_fresh_episodes(smoke_trainer, lean, 5)
  np.testing.assert_array_equal(resumed.env_state.info["env_steps"], 5 * 16)
  np.testing.assert_array_equal(resumed.episodes.running_length, 0.0)
  shapes = lambda tree: [np.shape(x) for x in jax.tree.leaves(tree)]
  assert shapes(resumed) == shapes(full)

  summary = runs.train(runs.load_config(run), run, resume=True, show_progress=False,
                       trainer=smoke_trainer)
  assert summary["iterations"] == 10 and not summary["interrupted"]
  rows, intact = _rows_without_wall(run / "progress.csv"), _rows_without_wall(second_run /
                                                                              "progress.csv")
  assert [r["iteration"] for r in rows] == [str(i) for i in range(1, 11)]
  assert rows[:5] == intact[:5]
  assert all(np.isfinite(float(r["episode_reward"])) for r in rows[5:])


def test_evaluate_cli_on_a_torn_checkpoint_is_one_line(smoke_run, tmp_path):
  """The smoke run's only checkpoint torn: ``evaluate`` says so in one line, exit 2, and leaves
  every file as it was."""
  run = tmp_path / "torn"
  shutil.copytree(smoke_run, run)
  _tear(run / "checkpoints" / "10")
  before = _tree_digest(run)
  out = subprocess.run([
      sys.executable, "-m", "experiments.evaluate", "--run",
      str(run), "--episodes", "3", "--seconds", "1"
  ], capture_output=True, text=True, cwd=REPO, env=_subprocess_env(), timeout=300)
  lines = _stderr_lines(out.stderr)
  assert out.returncode == 2, out.stderr[-3000:]
  assert len(lines) == 1 and lines[0].startswith("error: no checkpoint in") \
      and "restores (steps 10 tried" in lines[0], lines
  assert _tree_digest(run) == before


# ------------------------------------------------------------- 3. signals, kills (SIGKILL), resume
def _fifteen(smoke_config):
  """The smoke preset for 15 iterations: 3 jitted calls of 5, a checkpoint after each."""
  return dataclasses.replace(smoke_config, checkpoint_every=1,
                             train=dataclasses.replace(smoke_config.train, num_iterations=15))


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory, smoke_config, smoke_trainer):
  """``_fifteen`` trained in one go, in this process: what every interrupted run must end with."""
  out = tmp_path_factory.mktemp("runs") / "uninterrupted"
  runs.train(_fifteen(smoke_config), out, show_progress=False, trainer=smoke_trainer)
  return out


def _assert_same_end(run: Path, reference: Path, trainer) -> None:
  """Both runs logged the same rows (``wall_s`` aside) and their newest checkpoints hold the same
  train state, bit for bit."""
  for name in ("progress.csv",):
    assert _rows_without_wall(run / name) == _rows_without_wall(reference / name), name
  a, b = runs.restore_run(run, trainer), runs.restore_run(reference, trainer)
  assert a.step == b.step
  raw = lambda x: jax.random.key_data(x) if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) else x
  jax.tree.map(np.testing.assert_array_equal, jax.tree.map(raw, a.state),
               jax.tree.map(raw, b.state))


def _signal_on_call(trainer, calls: dict[int, list[signal.Signals]]):
  """``trainer`` whose ``train_epoch`` sends itself ``calls[i]`` before its ``i``-th call (from 1),
  i.e. while ``runs.train``'s signal handlers are installed."""
  count = [0]
  epoch = trainer.train_epoch

  def train_epoch(state):
    count[0] += 1
    for sig in calls.get(count[0], []):
      os.kill(os.getpid(), sig)
    return epoch(state)

  return trainer._replace(train_epoch=train_epoch)


class _Recorder(runs.Hook):
  """A user's hook: what it saw after each call, and whether it was closed."""

  def __init__(self, out: Path):
    self.out, self.seen, self.closed = out, [], False

  def after_call(self, call):
    logged = runs.read_progress(self.out)["iteration"][-1]
    saved = sorted(int(p.name) for p in (self.out / "checkpoints").iterdir() if p.name.isdigit())
    self.seen.append((call.index, call.iteration, call.last, int(logged), saved[-1]))

  def close(self):
    self.closed = True


def test_a_users_hook_runs_after_the_logs_and_checkpoints(smoke_config, smoke_trainer, tmp_path):
  """A hook given to ``runs.train`` sees every call after its rows are logged and its checkpoint
  saved; a SIGTERM during call 2 makes that call the last, and the hook is closed."""
  cfg = _fifteen(smoke_config)
  recorder = _Recorder(tmp_path / "run")
  trainer = _signal_on_call(smoke_trainer, {2: [signal.SIGTERM]})
  summary = runs.train(cfg, tmp_path / "run", show_progress=False, trainer=trainer,
                       hooks=(recorder,))
  assert summary["signal"] == "SIGTERM"
  assert recorder.seen == [(0, 5, False, 5, 5), (1, 10, True, 10, 10)]
  assert recorder.closed


def test_sigterm_saves_and_a_second_signal_aborts(smoke_config, smoke_trainer, tmp_path):
  """SIGTERM during call 1: the call finishes, step 5 is saved, the summary says SIGTERM (exit
  143). Two SIGINTs before call 2 of another run: it aborts at once, step 5 stays loadable."""
  from mash import cli as common
  cfg = _fifteen(smoke_config)
  trainer = _signal_on_call(smoke_trainer, {1: [signal.SIGTERM]})
  summary = runs.train(cfg, tmp_path / "term", show_progress=False, trainer=trainer)
  assert summary["interrupted"] and summary["signal"] == "SIGTERM"
  assert summary["iterations"] == 5 and common.exit_status(summary) == 143
  assert runs.restore_run(tmp_path / "term", smoke_trainer).step == 5

  handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
  trainer = _signal_on_call(smoke_trainer, {2: [signal.SIGINT, signal.SIGINT]})
  with pytest.raises(KeyboardInterrupt):
    runs.train(cfg, tmp_path / "abort", show_progress=False, trainer=trainer)
  assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers
  assert runs.restore_run(tmp_path / "abort", smoke_trainer).step == 5
  np.testing.assert_array_equal(
      runs.read_progress(tmp_path / "abort")["iteration"], np.arange(1, 6))


def _worker(marks: Path, kill: str, argv: list[str]) -> subprocess.Popen:
  """``tests/kill_worker.py``: the training CLI with ``argv``, SIGKILLed where ``kill`` says,
  leaving its marks in ``marks``."""
  marks.mkdir()
  return subprocess.Popen(
      [sys.executable,
       str(REPO / "tests" / "kill_worker.py"),
       str(marks), kill, "--", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
      cwd=REPO, env=_subprocess_env())


def _wait_killed(proc: subprocess.Popen, mark: Path) -> None:
  """The worker died of its own SIGKILL where it was told to (``mark``)."""
  try:
    stdout, stderr = proc.communicate(timeout=400)
  finally:
    if proc.poll() is None:
      proc.kill()
  assert proc.returncode == -signal.SIGKILL and mark.exists(), \
      f"exit {proc.returncode}\n{stdout}{stderr[-3000:]}"


def _iterations(run: Path) -> list[int]:
  return [int(r["iteration"]) for r in _rows_without_wall(run / "progress.csv")]


def test_ctrl_c_kills_and_resumes_in_subprocesses(smoke_run, smoke_trainer, uninterrupted,
                                                  tmp_path):
  """A CLI run of 15 iterations (3 jitted calls, a checkpoint after each), stopped three times.

  1. Ctrl-C (SIGINT) in call 1: the call finishes, step 5 is saved, exit 130 with how to go on.
  2. ``--resume``, SIGKILLed while step 10 is being written: step 10 is only a temporary
     directory, step 5 restores, rows 1..10 are logged (before the save).
  3. The logs' last row cut as a kill during the append of rows 6..10 leaves it (row 10 after its
     first character, which reads as iteration 1); ``--resume``, SIGKILLed one second into call 2
     (11..15), once it saved step 10 over the leftover temporary directory: steps 5 and 10
     restore, rows 1..10 once each (the cut row and those past step 5 were dropped and retrained).
  4. ``--resume`` (the plain CLI) to the end: rows 1..15 once each, 1..10 equal to the smoke
     run's, and the rows and final train state equal to the uninterrupted run's, bit for bit.
  """
  out = tmp_path / "run"
  proc = _worker(tmp_path / "marks1", "none", [
      "--preset", "smoke", "--out",
      str(out), "--no-progress", "--set", "train.num_iterations=15", "--set", "checkpoint_every=1"
  ])
  try:
    deadline = time.monotonic() + 400
    while not (tmp_path / "marks1" / "call_1").exists():
      assert proc.poll() is None, proc.communicate()
      assert time.monotonic() < deadline, "no training call within 400 s"
      time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=300)
  finally:
    if proc.poll() is None:
      proc.kill()
  assert proc.returncode == 130, stdout + stderr[-3000:]
  assert "signal SIGINT" in stdout and f"--resume {out}" in stdout, stdout
  assert "Traceback" not in stderr, stderr[-3000:]
  assert _iterations(out) == list(range(1, 6))  # the call in flight was finished, and only it
  assert runs.restore_run(out, smoke_trainer).step == 5

  resume = ["--resume", str(out), "--no-progress"]
  checkpoints = out / "checkpoints"
  _wait_killed(_worker(tmp_path / "marks2", "save:10", resume),
               tmp_path / "marks2" / "killed_in_save_10")
  partial = checkpoints / "10.orbax-checkpoint-tmp"
  assert not (checkpoints / "10").exists()
  assert any((partial / "state.orbax-checkpoint-tmp").iterdir())  # the kill fell mid-write
  assert runs.restore_run(out, smoke_trainer).step == 5
  assert policy.load(out).iteration == 5
  assert _iterations(out) == list(range(1, 11))

  for name in ("progress.csv",):
    text = (out / name).read_bytes()
    (out / name).write_bytes(text[:text.rindex(b"\n10,") + 2])
  _wait_killed(_worker(tmp_path / "marks3", "call:2", resume),
               tmp_path / "marks3" / "killed_in_call_2")
  assert not partial.exists()
  for step in (5, 10):
    assert runs.restore_run(out, smoke_trainer, iteration=step).step == step
  assert runs.restore_run(out, smoke_trainer).step == 10
  assert _iterations(out) == list(range(1, 11))

  resumed = subprocess.run([sys.executable, "-m", "experiments.bipedal", *resume],
                           capture_output=True, text=True, cwd=REPO, env=_subprocess_env(),
                           timeout=400)
  assert resumed.returncode == 0, resumed.stdout + resumed.stderr[-3000:]
  assert _iterations(out) == list(range(1, 16))
  assert _rows_without_wall(out / "progress.csv")[:10] == _rows_without_wall(smoke_run /
                                                                             "progress.csv")
  _assert_same_end(out, uninterrupted, smoke_trainer)


# --------------------------------------------------------- 5. a full disk (ENOSPC, simulated)
def _no_space(path) -> OSError:
  import errno
  return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def _refused(capfd, run) -> str:
  """Runs ``run()`` under the CLI's error handling; returns its one error line (exit status 1)."""
  from mash import cli as common
  capfd.readouterr()
  with pytest.raises(SystemExit) as e, common.user_errors():
    run()
  err = capfd.readouterr().err
  lines = _stderr_lines(err)
  assert e.value.code == 1 and len(lines) == 1 and lines[0].startswith("error: "), err[-3000:]
  return lines[0]


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_full_disk_at_a_checkpoint_is_one_line_and_resumes(smoke_config, smoke_trainer,
                                                           uninterrupted, tmp_path, monkeypatch,
                                                           capfd, caplog):
  """Orbax's writes of small files into checkpoint step 10 fail with ENOSPC (in its threads, as a
  full disk fails them): one line names the step, the reason and step 5, which still loads, and
  nothing else is reported (Orbax logs an error per thread, and its writes still in flight end in
  'Event loop is closed' tracebacks: both silenced); once there is room, a resume trains to 15
  and ends as the uninterrupted run."""
  import asyncio
  import logging

  from orbax.checkpoint._src.path import async_path
  write_text = async_path.write_text

  async def full_at_step_10(path, text):
    if "10.orbax-checkpoint-tmp" not in Path(str(path)).parts:
      return await write_text(path, text)

    def write():
      raise _no_space(path)

    return await asyncio.to_thread(write)

  monkeypatch.setattr(async_path, "write_text", full_at_step_10)
  out = tmp_path / "full"
  cfg = _fifteen(smoke_config)
  line = _refused(capfd, lambda: runs.train(cfg, out, show_progress=False, trainer=smoke_trainer))
  assert line == (f"error: cannot write checkpoint step 10 in '{out / 'checkpoints'}': No space "
                  f"left on device; checkpoint step 5 is complete: free space, then --resume {out}")
  assert not [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
  monkeypatch.undo()
  assert not (out / "checkpoints" / "10").exists()
  assert runs.restore_run(out, smoke_trainer).step == 5
  assert policy.load(out).iteration == 5

  summary = runs.train(cfg, out, resume=True, show_progress=False, trainer=smoke_trainer)
  assert summary["iterations"] == 15 and not summary["interrupted"]
  _assert_same_end(out, uninterrupted, smoke_trainer)


class _FullFile:
  """A text file that takes ``writes`` more writes (a CSV row each) and ``chars`` characters of the
  next, then fails as a full disk does; what fit stays written."""

  def __init__(self, file, writes: int, chars: int):
    self.file, self.writes, self.chars = file, writes, chars

  def write(self, text: str) -> int:
    if self.writes == 0:
      self.file.write(text[:self.chars])
      raise _no_space(self.file.name)
    self.writes -= 1
    return self.file.write(text)

  def __enter__(self):
    return self

  def __exit__(self, *exc) -> None:
    self.file.close()


def test_full_disk_at_a_results_file_is_one_line_and_resumes(smoke_config, smoke_trainer,
                                                             uninterrupted, tmp_path, monkeypatch,
                                                             capfd):
  """1. The append of rows 11..15 to ``progress.csv`` runs out of room after rows 11, 12 and the
  first character of row 13, which reads as iteration 1: one line names the file and step 10,
  which still loads. 2. A resume drops the rows past step 10 and the cut one, trains to 15, and
  then ``summary.json`` does not fit (half of its temporary file is written): one line names it
  and step 15. 3. A resume with room trains nothing and writes the summary; the run ends as the
  uninterrupted one."""
  out = tmp_path / "full"
  cfg = _fifteen(smoke_config)
  opened, appends = Path.open, []

  def open_(self, mode="r", *args, **kwargs):
    file = opened(self, mode, *args, **kwargs)
    if self == out / "progress.csv" and mode == "a":
      appends.append(self)
      if len(appends) == 3:
        return _FullFile(file, writes=2, chars=1)
    return file

  monkeypatch.setattr(Path, "open", open_)
  line = _refused(capfd, lambda: runs.train(cfg, out, show_progress=False, trainer=smoke_trainer))
  assert line == (f"error: cannot write '{out / 'progress.csv'}': No space left on device; "
                  f"checkpoint step 10 is complete: free space, then --resume {out}")
  monkeypatch.undo()
  assert (out / "progress.csv").read_bytes().endswith(b"\n1")
  assert runs.restore_run(out, smoke_trainer).step == 10

  written = Path.write_text

  def write_text(self, data, *args, **kwargs):
    if self.name == ".summary.json.tmp":
      written(self, data[:len(data) // 2])
      raise _no_space(self)
    return written(self, data, *args, **kwargs)

  monkeypatch.setattr(Path, "write_text", write_text)
  line = _refused(
      capfd, lambda: runs.train(cfg, out, resume=True, show_progress=False, trainer=smoke_trainer))
  assert line == (f"error: cannot write '{out / 'summary.json'}': No space left on device; "
                  f"checkpoint step 15 is complete: free space, then --resume {out}")
  monkeypatch.undo()
  assert not (out / "summary.json").exists()
  assert runs.restore_run(out, smoke_trainer).step == 15

  summary = runs.train(cfg, out, resume=True, show_progress=False, trainer=smoke_trainer)
  assert summary["iterations"] == 15 and not summary["interrupted"]
  assert (out / "summary.json").is_file()
  _assert_same_end(out, uninterrupted, smoke_trainer)


@pytest.mark.parametrize(
    "error, line",
    [
        (_no_space("eval/metrics.json"),
         "error: cannot write 'eval/metrics.json': No space left on device; free space, then run "
         "the command again"),
        (OSError(30, "Read-only file system", "run/policy.onnx"),
         "error: cannot write 'run/policy.onnx': Read-only file system; free space, then run the "
         "command again"),
        # TensorStore (Orbax's array writer) on a real full disk (a 2 MB tmpfs), abridged.
        (ValueError("RESOURCE_EXHAUSTED: Error writing \"['params']['w']/0\" in OCDBT database at "
                    'local file "/full/ck/10.orbax-checkpoint-tmp/state.orbax-checkpoint-tmp/'
                    'ocdbt.process_0/": Failed to write 1575916 bytes to file 4: No space left on '
                    "device [os_error_code='28']"),
         "error: cannot write: No space left on device; free space, then run the command again"),
    ])
def test_a_refused_write_in_any_command_is_one_line(capfd, error, line):
  """Evaluation's metrics, an ONNX export, a checkpoint outside ``runs.train``: one line, exit 1.
  Any other error is not the storage's and goes on as it was."""

  def fail():
    raise error

  assert _refused(capfd, fail) == line
  from mash import cli as common
  with pytest.raises(FileNotFoundError), common.user_errors():
    Path("/nonexistent/metrics.json").write_text("{}")
