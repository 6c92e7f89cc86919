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

from mash import checkpoint, losses, policy, robots, runs
from mash.config import TrainConfig

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------- helpers
def _rows_without_wall(path: Path) -> list[dict[str, str]]:
  """A progress CSV as text fields, minus the wall-clock column."""
  with path.open() as f:
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in csv.DictReader(f)]


def _tree_digest(root: Path) -> dict[str, str]:
  """``{relative path: sha1}`` of every file under ``root``."""
  return {str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
          for p in sorted(root.rglob("*")) if p.is_file()}


def _tear(step_dir: Path) -> None:
  """Overwrites every file of a checkpoint step with garbage (a torn copy, a bad disk)."""
  for p in step_dir.rglob("*"):
    if p.is_file():
      p.write_bytes(b"\x00garbage\xff")


def _stderr_lines(text: str) -> list[str]:
  """Non-empty stderr lines, without MuJoCo's import notes about the optional warp backend."""
  return [l for l in text.splitlines() if l.strip() and "warp" not in l]


def _subprocess_env() -> dict[str, str]:
  """This environment (with conftest's compilation-cache settings) plus the repository on the path."""
  path = os.environ.get("PYTHONPATH", "")
  return dict(os.environ, PYTHONPATH=f"{REPO}{os.pathsep}{path}" if path else str(REPO))


def _finite(tree) -> bool:
  """Every floating-point leaf of ``tree`` is finite."""
  return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree.leaves(tree)
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
  from mash.toy_env import make_toy_env
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
  assert _finite(jax.device_get((state.params, state.opt_state, state.normalizer,
                                 state.env_state)))


def test_mjx_trainer_survives_nan_and_inf_states(smoke_trainer):
  """The real env, batched: env 3's qpos gets a NaN, env 7's qvel an inf. Both envs are reset in
  the first step, counted, and nothing non-finite reaches the parameters or the logged metrics."""
  state = smoke_trainer.init(jax.random.PRNGKey(0))
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
  """robots.build_model names the joint; the CLI wrapper prints it as one line, exit 2."""
  from experiments import common
  t1 = robots.BOOSTER_T1
  leg = t1.limbs[0]
  typo = dataclasses.replace(leg, joints=(leg.joints[0] + "_typo",) + leg.joints[1:])
  bad = dataclasses.replace(t1, limbs=(typo,) + t1.limbs[1:])
  with pytest.raises(robots.SpecError, match=f"joint '{leg.joints[0]}_typo' is not in the model"):
    robots.build_model(bad)
  with pytest.raises(SystemExit) as e, common.user_errors():
    robots.build_model(bad)
  assert e.value.code == 2
  lines = _stderr_lines(capsys.readouterr().err)
  assert len(lines) == 1 and lines[0].startswith("error: robot 'booster_t1': joint"), lines


def _main_error(capsys, module: str, argv: list[str]) -> str:
  """Runs an entry point in this process; returns its one error line (exit status 2)."""
  if module in ("evaluate", "export", "sim2sim"):
    main = __import__(f"experiments.{module}", fromlist=["main"]).main
    run = lambda: main(argv)
  else:
    from experiments.train_task import main
    run = lambda: main(module, argv)
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
    (["--set", "env.reward_params.ramped_terms=torque_rat"],
     "env.reward_params.ramped_terms: 'torque_rat' is not a reward term"),
    (["--set", "env.reward_params.tracking_boost=0.5"],
     "env.reward_params.tracking_boost must be >= 1"),
    (["--set", "env.randomization.friction_initial=0.3,0.1"],
     "env.randomization.friction_initial must be a range (lo, hi) with 0 < lo <= hi"),
    (["--set", "env.randomization.friction_ramp_steps=-5"],
     "env.randomization.friction_ramp_steps must be >= 0"),
    (["--set", "algo=sac"], "algo 'sac' is unknown"),
    (["--set", "train.num_envs=0"], "num_envs must be >= 1"),
    (["--set", "train.learning_rate_schedule=cosine"],
     "learning_rate_schedule 'cosine' is unknown; expected one of fixed, adaptive_kl, linear"),
    (["--seeds", "0"], "seeds must be >= 1"),
    (["--resume", "DIR", "--set", "train.num_iterations=20"], "--set cannot be combined"),
])
def test_cli_bad_config_is_one_line(capsys, tmp_path, argv, words):
  """Config mistakes that used to surface as tracebacks from deep inside (or be ignored)."""
  argv = [str(tmp_path) if a == "DIR" else a for a in argv]
  out = tmp_path / "out"
  line = _main_error(capsys, "bipedal", ["--preset", "smoke", "--out", str(out), *argv]
                     if "--resume" not in argv else argv)
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
  from experiments import benchmark
  result = {"env_steps_per_s": 1000.0, "env_physics_equivalent_per_s": 4000.0,
            "train_env_steps_per_s": {"mash": 750.0, "brax_ppo": 600.0}}
  assert benchmark._ratios(result) == {"mash_train_vs_env": 0.75, "mash_vs_brax_ppo": 1.25}
  result.update(physics_steps_per_s=5000.0, train_env_steps_per_s={"mash": 750.0, "ppo": 800.0})
  assert benchmark._ratios(result) == {"env_vs_physics": 0.8, "mash_train_vs_env": 0.75,
                                       "mash_vs_ppo": 0.9375}


def test_device_scaling_writes_table_and_plot(tmp_path):
  """``benchmark_devices`` writes its JSON, a markdown table with every row, and the PNG plot."""
  import json
  from experiments import benchmark_devices
  row = lambda variant, n, sps, ratio: {
      "variant": variant, "processes": n, "envs_per_process": 256 // n, "env_steps_per_s": sps,
      "physics_steps_per_s": 4 * sps, "cpu_cores_used": float(n), "compile_s": 30.0,
      "ratio_vs_one_process": ratio}
  result = {"batch": 256, "steps": 20, "task": "bipedal", "date": "today", "cpu_count": 2,
            "load_average_at_start": 0.5, "train_batch": 64,
            "summary": {"second_core_buys": 1.9, "second_core_buys_without_collective": 2.0,
                        "collective_cost": 0.05, "second_core_buys_training": 1.5},
            "rows": [row("one_process", 1, 1000.0, 1.0), row("two_process_mesh", 2, 1900.0, 1.9),
                     row("train_one_process", 1, 800.0, 1.0),
                     row("train_two_process", 2, 1200.0, 1.5)]}
  stem = tmp_path / "scaling_devices"
  benchmark_devices._write(result, stem)
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
    ("bipedal", ["--preset", "smoke", "--set", "train.learning_rate=nan"],
     "TrainConfig.learning_rate must be a finite number > 0, got nan"),
    ("bipedal", ["--preset", "smoke", "--set", "train.actor_hidden=0"],
     "TrainConfig.actor_hidden must be one or more layer sizes >= 1"),
    ("bipedal", ["--preset", "smoke", "--set", "train.gamma=inf"], "TrainConfig.gamma must be in"),
    ("bipedal", ["--preset", "smoke", "--out", "/proc/forbidden"],
     "--out '/proc/forbidden' cannot be written"),
    ("export", ["--run", "SMOKE", "--out", "/proc/x.onnx"],
     "--out '/proc/x.onnx' cannot be written (folder '/proc'"),
    ("sim2sim", ["--run", "SMOKE", "--video", "/proc/x.mp4"],
     "--video '/proc/x.mp4' cannot be written (folder '/proc'"),
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
  for name in ("progress.csv", "progress_seeds.csv"):
    a, b = _rows_without_wall(smoke_run / name), _rows_without_wall(second_run / name)
    assert len(a) == 10 and a == b, name


def test_torn_latest_checkpoint_falls_back_and_resumes(second_run, smoke_trainer, tmp_path,
                                                       capfd):
  """Garbage in the newest step (10): loading warns once and uses step 5; ``--resume`` moves the
  torn step aside (never deletes it), retrains 6..10 and logs exactly what the intact run logged."""
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

  cfg = runs.load_config(run)
  summary = runs.train(cfg, run, resume=True, show_progress=False, trainer=smoke_trainer)
  assert summary["iterations"] == 10 and not summary["interrupted"]
  assert _tree_digest(run / "checkpoints_unrestorable" / "10") == torn
  assert _rows_without_wall(run / "progress.csv") == _rows_without_wall(second_run / "progress.csv")
  assert runs.restore_run(run, smoke_trainer, cfg).step == 10
  # A partial step (an interrupted Orbax write: a temporary directory) is never taken for complete.
  shutil.copytree(run / "checkpoints" / "10", run / "checkpoints" / "15.orbax-checkpoint-tmp-1")
  assert runs.restore_run(run, smoke_trainer, cfg).step == 10


def _du(path: Path) -> int:
  return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def test_checkpoints_without_env_state_are_small_and_resume(smoke_config, smoke_trainer,
                                                            second_run, tmp_path):
  """``checkpoint_env_state = False``: step 5 holds no env state (under half the full step's
  bytes) and the same learning state as the full run's step 5; a resume from it trains 6..10 on
  fresh episodes (iterations 1..5 logged as before), with the curriculum clock at 5 x 16 steps."""
  cfg = dataclasses.replace(smoke_config, checkpoint_env_state=False, checkpoint_every=1)
  run = tmp_path / "lean"
  runs.train(cfg, run, show_progress=False, max_calls=1, trainer=smoke_trainer)
  lean_bytes, full_bytes = _du(run / "checkpoints" / "5"), _du(second_run / "checkpoints" / "5")
  assert lean_bytes < 0.5 * full_bytes, (lean_bytes, full_bytes)
  lean = runs.restore_run(run, smoke_trainer, cfg, fields=checkpoint.LEARNING_FIELDS).state
  manager = checkpoint.make_manager(second_run / "checkpoints", max_to_keep=None)
  full = checkpoint.restore(manager, 5, runs.state_shapes(smoke_trainer, smoke_config)).state
  manager.close()
  for name in checkpoint.LEARNING_FIELDS:
    jax.tree.map(np.testing.assert_array_equal, getattr(lean, name), getattr(full, name))
  with pytest.raises(runs.RunError):  # a full restore finds no env state in it
    runs.restore_run(run, smoke_trainer, smoke_config)
  resumed = runs.with_fresh_episodes(smoke_trainer, cfg, lean, 5)
  np.testing.assert_array_equal(resumed.env_state.info["env_steps"], 5 * 16)
  np.testing.assert_array_equal(resumed.episodes.running_length, 0.0)
  shapes = lambda tree: [np.shape(x) for x in jax.tree.leaves(tree)]
  assert shapes(resumed) == shapes(full)

  summary = runs.train(runs.load_config(run), run, resume=True, show_progress=False,
                       trainer=smoke_trainer)
  assert summary["iterations"] == 10 and not summary["interrupted"]
  rows, intact = _rows_without_wall(run / "progress.csv"), _rows_without_wall(
      second_run / "progress.csv")
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
  out = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--run", str(run),
                        "--episodes", "3", "--seconds", "1"], capture_output=True, text=True,
                       cwd=REPO, env=_subprocess_env(), timeout=300)
  lines = _stderr_lines(out.stderr)
  assert out.returncode == 2, out.stderr[-3000:]
  assert len(lines) == 1 and lines[0].startswith("error: no checkpoint in") \
      and "restores (steps 10 tried" in lines[0], lines
  assert _tree_digest(run) == before


# ---------------------------------------------------------------------- 3. signals and resume
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


def test_sigterm_saves_and_a_second_signal_aborts(smoke_config, smoke_trainer, tmp_path):
  """SIGTERM during call 1: the call finishes, step 5 is saved, the summary says SIGTERM (exit
  143). Two SIGINTs before call 2 of another run: it aborts at once, step 5 stays loadable."""
  from experiments import common
  cfg = dataclasses.replace(smoke_config, checkpoint_every=1,
                            train=dataclasses.replace(smoke_config.train, num_iterations=15))
  trainer = _signal_on_call(smoke_trainer, {1: [signal.SIGTERM]})
  summary = runs.train(cfg, tmp_path / "term", show_progress=False, trainer=trainer)
  assert summary["interrupted"] and summary["signal"] == "SIGTERM"
  assert summary["iterations"] == 5 and common.exit_status(summary) == 143
  assert runs.restore_run(tmp_path / "term", smoke_trainer, cfg).step == 5

  handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
  trainer = _signal_on_call(smoke_trainer, {2: [signal.SIGINT, signal.SIGINT]})
  with pytest.raises(KeyboardInterrupt):
    runs.train(cfg, tmp_path / "abort", show_progress=False, trainer=trainer)
  assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers
  assert runs.restore_run(tmp_path / "abort", smoke_trainer, cfg).step == 5
  np.testing.assert_array_equal(runs.read_progress(tmp_path / "abort")["iteration"],
                                np.arange(1, 6))


def test_ctrl_c_then_resume_in_subprocesses(smoke_run, smoke_trainer, tmp_path):
  """Ctrl-C a CLI training run once its first checkpoint is complete: it finishes the call in
  flight, saves, exits 130; the checkpoint restores; ``--resume`` finishes the run; every iteration
  is logged exactly once, and iterations 1..10 equal the smoke run's bit for bit."""
  out = tmp_path / "run"
  env = _subprocess_env()
  proc = subprocess.Popen(
      [sys.executable, "-m", "experiments.bipedal", "--preset", "smoke", "--out", str(out),
       "--no-progress", "--set", "train.num_iterations=15", "--set", "checkpoint_every=1"],
      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
  try:
    deadline = time.monotonic() + 400
    while not (out / "checkpoints" / "5").is_dir():
      assert proc.poll() is None, proc.communicate()
      assert time.monotonic() < deadline, "no checkpoint within 400 s"
      time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=300)
  finally:
    if proc.poll() is None:
      proc.kill()
  assert proc.returncode == 130, stdout + stderr[-3000:]
  assert "signal SIGINT" in stdout and f"--resume {out}" in stdout, stdout
  assert "Traceback" not in stderr, stderr[-3000:]
  done = runs.read_progress(out)["iteration"]
  assert done[-1] in (5, 10), done  # the call in flight when the signal came was finished
  cfg = runs.load_config(out)
  assert runs.restore_run(out, smoke_trainer, cfg).step == done[-1]

  resumed = subprocess.run([sys.executable, "-m", "experiments.bipedal", "--resume", str(out),
                            "--no-progress"], capture_output=True, text=True, cwd=REPO, env=env,
                           timeout=400)
  assert resumed.returncode == 0, resumed.stdout + resumed.stderr[-3000:]
  rows = _rows_without_wall(out / "progress.csv")
  assert [int(r["iteration"]) for r in rows] == list(range(1, 16))
  assert rows[:10] == _rows_without_wall(smoke_run / "progress.csv")
  assert runs.restore_run(out, smoke_trainer, cfg).step == 15
