"""End-to-end: the smoke preset on the real MJX env, evaluation files, config overrides, CLI errors.

The MJX programs here (one training call, one evaluation rollout) are compiled once per session
through the ``smoke_run`` fixture (tests/conftest.py).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mash.runs import experiment
from mash.runs import loop as runs
from mash.sim import env as env_lib
from mash.sim import env_config, rewards, robots


def _with_robot_numbers(cfg: experiment.ExperimentConfig) -> experiment.ExperimentConfig:
  """``cfg`` with the numbers it leaves to its robot filled in, as the env sees it (a recorded
  config.json from before the robot files holds them explicitly)."""
  return dataclasses.replace(cfg, env=env_config.with_robot_numbers(cfg.env,
                                                                    robots.load(cfg.env.robot)))


def test_smoke_run_writes_every_file(smoke_run):
  """config.json, progress.csv with every column, checkpoints, summary, plot, TensorBoard events;
  no progress_seeds.csv, which for one seed would repeat progress.csv."""
  for name in ("config.json", "progress.csv", "summary.json", "reward_curve.png"):
    assert (smoke_run / name).is_file(), name
  assert not (smoke_run / "progress_seeds.csv").exists()
  assert any((smoke_run / "checkpoints").iterdir())
  assert any(p.name.startswith("events") for p in (smoke_run / "tensorboard").iterdir())
  progress = runs.read_progress(smoke_run)
  for column in runs.BASE_COLUMNS:
    assert column in progress
  for term in rewards.TERMS:
    assert f"reward/{term}" in progress, term
  cfg = runs.load_config(smoke_run)
  np.testing.assert_array_equal(progress["iteration"], np.arange(1, cfg.train.num_iterations + 1))
  np.testing.assert_array_equal(
      progress["env_steps"], progress["iteration"] * cfg.train.num_envs * cfg.train.unroll_length)
  summary = json.loads((smoke_run / "summary.json").read_text())
  assert summary["iterations"] == cfg.train.num_iterations and not summary["interrupted"]


def test_smoke_run_reward_rises(smoke_run):
  """Mean episode reward of the last iterations beats that of the first completed episodes."""
  r = runs.read_progress(smoke_run)["episode_reward"]
  first = r[np.nonzero(r)[0][0]]
  assert np.all(np.isfinite(r))
  assert r[-3:].mean() > first


def test_config_round_trip(smoke_run):
  """config.json parses back to the config the run was made with."""
  cfg = runs.load_config(smoke_run)
  assert cfg == experiment.make_config("bipedal", "mash", "smoke")


def test_overrides_apply_and_reject():
  cfg = experiment.make_config(
      "armswing", "ppo", "smoke", overrides=[
          "train.learning_rate=5e-4", "env.reward_scales.joint_pos=2.0", "env.agent_id=false",
          "train.actor_hidden=32,16"
      ])
  assert cfg.train.learning_rate == 5e-4 and cfg.env.reward_scales.joint_pos == 2.0
  assert cfg.env.agent_id is False and cfg.train.actor_hidden == (32, 16)
  assert cfg.env.partition == "ppo"
  # A field that may be None (the friction curriculum's start) parses as its type, and back.
  cfg = experiment.apply_overrides(cfg, ["env.randomization.friction_initial=[0.1,0.3]"])
  assert cfg.env.randomization.friction_initial == (0.1, 0.3)
  assert experiment.apply_overrides(
      cfg, ["env.randomization.friction_initial=none"]).env.randomization.friction_initial is None
  bad = [["train.nope=1"], ["env.randomization.friction_initial=ice"], ["train.learning_rate=fast"],
         ["learning_rate"], ["env.commands=1"]]
  for overrides in bad:
    with pytest.raises(experiment.ConfigError):
      experiment.make_config("bipedal", "mash", "smoke", overrides=overrides)
  for kwargs in (dict(task="crawl"), dict(task="bipedal", algo="sac"),
                 dict(task="bipedal", preset="huge"), dict(task="bipedal", ablation="magic")):
    with pytest.raises(experiment.ConfigError):
      experiment.make_config(**kwargs)


def test_gpu_preset_is_the_measured_walking_run():
  """The gpu preset is the config of the H100 run that walked (recorded in benchmarks/results),
  but for the run's lean checkpoints, a choice of that lease, and its pushes, held 1 s before the
  default became the paper's per-step draw (that policy falls in 0 of 32 episodes under it)."""
  recorded = Path(__file__).parent.parent / "benchmarks" / "results" / \
      "2026-11-26_h100_gpu_bipedal_mash_penalty_ramp16k" / "config.json"
  measured = experiment.from_json(recorded.read_text())
  assert measured.env.randomization.push_interval_s == 1.0
  preset = _with_robot_numbers(experiment.make_config("bipedal", "mash", "gpu"))
  # The kicks and tracking scales of the cpu recipe (issue 52), on the gpu curriculum's clock.
  kicked = dataclasses.replace(measured.env.randomization, push_interval_s=0.0,
                               kick_velocity=(0.1, 1.0), kick_interval_s=(5.0, 10.0),
                               kick_ramp_start_steps=6400, kick_ramp_steps=8000)
  scales = dataclasses.replace(measured.env.reward_scales, tracking_ang_vel=2.8)
  assert dataclasses.replace(
      measured, checkpoint_env_state=True,
      env=dataclasses.replace(measured.env, randomization=kicked, reward_scales=scales)) == preset
  assert preset.env.reward_params.penalty_ramp_steps == 16_000
  assert preset.train.init_log_std == 0.0


def test_cpu_preset_is_the_measured_walking_run():
  """The cpu preset is the recorded 1875-iteration CPU run of 400 envs under two Newton
  iterations, with the stride reference and the tracking kernel sigma_t 0.1 (friction and
  penalty curricula, linear learning-rate decay, torque noise), and velocity kicks ramped in
  from 40 % to 90 % of the curricula with the yaw-tracking scale 2.8 (candidate O, issue 52)."""
  recorded = Path(__file__).parent.parent / "benchmarks" / "results" / \
      "2026-12-06_cpu_preset_kicks" / "longer_seed0" / "config.json"
  measured = experiment.from_json(recorded.read_text())
  assert json.loads(recorded.read_text())["env"]["randomization"]["torque_noise"] == 0.02
  preset = _with_robot_numbers(experiment.make_config("bipedal", "mash", "cpu"))
  assert preset.env.stride_reference and preset.env.actor_history == 1
  assert (preset.env.physics.iterations, preset.env.physics.ls_iterations) == (2, 2)
  assert preset.train.num_envs == 400
  assert (preset.env.reward_params.tracking_sigma == 0.1 and
          preset.env.reward_params.yaw_sigma == 0.25)
  assert _with_robot_numbers(measured) == preset
  assert preset.env.reward_params.penalty_ramp_steps == 36_000 == 1500 * preset.train.unroll_length
  assert preset.env.randomization.friction_ramp_steps == 36_000
  assert preset.env.randomization.friction == (0.1, 1.2)  # the paper's range, after the ramp
  assert preset.env.randomization.push_interval_s == 0.0
  kicks = preset.env.randomization
  assert kicks.kicks and kicks.kick_velocity == (0.1, 1.0) and kicks.kick_yaw_rate == (0.0, 0.0)
  assert (kicks.kick_ramp_start_steps, kicks.kick_ramp_steps) == (14_400, 18_000)
  smoke = experiment.make_config("bipedal", "mash", "smoke")
  assert not smoke.env.randomization.kicks
  assert smoke.env.reward_params.penalty_ramp_steps == 0 and smoke.train.init_log_std == -1.2
  assert smoke.env.randomization.friction_initial is None


def test_evaluate_writes_metrics_and_trajectories(smoke_run):
  """evaluate: metrics.json with SPEC §8 keys and trajectories.npz with SPEC §8 arrays."""
  from mash.analysis import evaluation
  from mash.analysis.reports import evaluate_run
  cfg = evaluation.EvalConfig(num_episodes=3, episode_s=1.0)
  result = evaluate_run(str(smoke_run), cfg)
  metrics = json.loads((smoke_run / "eval" / "metrics.json").read_text())
  for key in ("T_conv", "S_action", "S_action_2nd", "S_torso", "C_limb", "fall_rate",
              "forward_speed", "command_vx"):
    assert key in metrics, key
  assert metrics["command_vx"] == pytest.approx(0.4)
  assert metrics["iteration"] == 10  # the latest checkpoint
  assert 0.0 <= metrics["fall_rate"] <= 1.0
  traj = np.load(smoke_run / "eval" / "trajectories.npz")
  steps = 50
  assert traj["actions"].shape == (3, steps, 12)
  assert traj["base_height"].shape == (3, steps)
  assert traj["euler"].shape == (3, steps, 3)
  assert traj["hip_pitch"].shape == (3, steps, 2)
  assert float(traj["dt"]) == pytest.approx(0.02)
  assert (smoke_run / "eval" / "hip_pitch.png").is_file()
  # Each episode's floor friction, drawn from the paper's range, and the falls split by it.
  assert traj["friction"].shape == (3,)
  assert np.all((traj["friction"] >= 0.1) & (traj["friction"] <= 1.2))
  bands = metrics["fall_rate_by_friction"]
  assert sum(b["episodes"] for b in bands) == 3
  falls = sum(b["fall_rate"] * b["episodes"] for b in bands if b["episodes"])
  assert falls == pytest.approx(3 * metrics["fall_rate"])
  # The metrics are recomputable from the file.
  from mash.analysis import metrics as metrics_lib
  alive = traj["alive"].min(axis=1) > 0
  pick = alive if alive.any() else np.ones_like(alive)
  assert metrics_lib.action_smoothness(traj["actions"][pick]) == pytest.approx(
      result["S_action"], rel=1e-5)


def test_falls_by_friction_against_a_hand_count():
  """Episodes binned by floor friction, out-of-range values into the end bands, empty bands None."""
  from mash.analysis import evaluation
  friction = np.array([0.05, 0.1, 0.2, 0.29, 0.3, 0.95, 1.2, 1.5])
  survived = np.array([False, True, False, False, True, True, False, True])
  bands = evaluation.falls_by_friction(friction, survived, edges=(0.1, 0.3, 0.6, 0.9, 1.2))
  assert [b["friction"] for b in bands] == [[0.1, 0.3], [0.3, 0.6], [0.6, 0.9], [0.9, 1.2]]
  assert [b["episodes"] for b in bands] == [4, 1, 0, 3]
  assert bands[0]["fall_rate"] == pytest.approx(0.75)  # 0.05, 0.2, 0.29 fell; 0.1 stood
  assert bands[1]["fall_rate"] == 0.0
  assert bands[2]["fall_rate"] is None
  assert bands[3]["fall_rate"] == pytest.approx(1 / 3)  # 1.2 fell; 0.95 and 1.5 stood
  default = evaluation.falls_by_friction(friction, survived)
  assert [b["episodes"] for b in default] == [2, 2, 1, 0, 3]


def test_metrics_up_to_the_fall_weigh_every_long_enough_episode():
  """Episode 0 survives 200 steps, episode 1 falls at step 100, episode 2 at step 30 (< 50, left
  out): each metric is the mean of episode 0's over 200 steps and episode 1's over its first 100."""
  from mash.analysis import evaluation
  from mash.analysis import metrics as metrics_lib
  rng = np.random.default_rng(0)
  traj = dict(actions=rng.normal(size=(3, 200, 12)), base_height=rng.normal(size=(3, 200)),
              euler=rng.normal(size=(3, 200, 3)), hip_pitch=rng.normal(size=(3, 200, 2)),
              alive=np.ones((3, 200)))
  traj["alive"][1, 100:] = 0
  traj["alive"][2, 30:] = 0
  out = evaluation.metrics_up_to_the_fall(traj)
  assert out["episodes"] == 2 and out["episodes_too_short"] == 1
  first = metrics_lib.action_smoothness(traj["actions"][0])
  fallen = metrics_lib.action_smoothness(traj["actions"][1, :100])
  assert out["S_action"] == pytest.approx((first + fallen) / 2)
  torso = [
      metrics_lib.torso_stability(traj["base_height"][0], traj["euler"][0]),
      metrics_lib.torso_stability(traj["base_height"][1, :100], traj["euler"][1, :100])
  ]
  assert out["S_torso"] == pytest.approx(np.mean(torso))


def test_evaluate_reports_arm_leg_coordination_when_the_arms_act():
  """armswing: C_limb_arm_leg from the shoulders against the opposite hips (here in phase: ~0);
  bipedal (arms held): not reported."""
  from mash.analysis import evaluation
  w = 2 * np.pi * np.arange(500) / 32
  hips = np.stack([np.sin(w), -np.sin(w)], -1)[None].repeat(2, 0)
  traj = dict(actions=np.zeros((2, 500, 20)), base_height=np.ones((2, 500)), euler=np.zeros(
      (2, 500, 3)), hip_pitch=hips, shoulder_pitch=hips[..., ::-1] * 0.3, forward_velocity=np.zeros(
          (2, 500)), alive=np.ones((2, 500)))
  out = evaluation.evaluate(traj, 0.4, arms_act=True)
  assert out["C_limb_arm_leg"] < 0.05 and out["C_limb"] < 0.05
  assert "C_limb_arm_leg" not in evaluation.evaluate(traj, 0.4)


def test_evaluation_wiring_left_hip_first_and_alive_until_the_fall(smoke_config):
  """Seams of the evaluation: the hip-pitch index is (left, right) and the alive mask keeps the
  step that fell (its state is the fall's) and drops everything after, also a second done."""
  from mash.analysis import evaluation
  env = env_lib.MashEnv(smoke_config.env)
  left, right = (env.spec.joints[i] for i in env.spec.role_indices("hip_pitch", "legs"))
  assert left == "Left_Hip_Pitch" and right == "Right_Hip_Pitch"
  shoulders = [env.spec.joints[i] for i in evaluation.shoulder_pitch_index(env)]
  assert shoulders == ["Left_Shoulder_Pitch", "Right_Shoulder_Pitch"]
  done = np.array([[0, 0, 1, 0, 1], [0, 0, 0, 0, 0], [1, 0, 0, 0, 0]], np.float32)
  np.testing.assert_array_equal(evaluation.alive_mask(done),
                                [[1, 1, 1, 0, 0], [1, 1, 1, 1, 1], [1, 0, 0, 0, 0]])


def test_evaluation_without_pushes_keeps_the_other_randomization():
  """``--no-push``: pushes drawn as zero, every other randomized range as trained; its files go
  beside ``eval/``, never over it."""
  from mash.analysis import evaluation
  from mash.analysis.reports import eval_dir_name
  trained = env_config.EnvConfig()
  no_push = evaluation.EvalConfig(pushes=False)
  r = evaluation.eval_env_config(trained, no_push).randomization
  assert r.enabled and r.push_force == (0.0, 0.0) and r.push_torque == (0.0, 0.0)
  assert r.push_force != trained.randomization.push_force
  assert r == dataclasses.replace(trained.randomization, push_force=(0.0, 0.0),
                                  push_torque=(0.0, 0.0))
  assert evaluation.eval_env_config(trained, evaluation.EvalConfig()).randomization == \
      trained.randomization
  assert eval_dir_name(evaluation.EvalConfig()) == "eval"
  assert eval_dir_name(no_push) == "eval_no_push"
  assert eval_dir_name(evaluation.EvalConfig(randomization=False)) == "eval_no_dr"
  # --push-interval: only the hold time changes, and the files go beside eval/ too.
  held = evaluation.EvalConfig(push_interval_s=1.0)
  r = evaluation.eval_env_config(trained, held).randomization
  assert r == dataclasses.replace(trained.randomization, push_interval_s=1.0) != \
      trained.randomization
  assert eval_dir_name(held) == "eval_push_interval_1s"
  assert eval_dir_name(evaluation.EvalConfig(push_interval_s=0.0)) == "eval_push_interval_0s"
  # --iteration N: an earlier checkpoint's evaluation goes beside the latest one's.
  assert eval_dir_name(evaluation.EvalConfig(), 600) == "eval_it600"
  assert eval_dir_name(evaluation.EvalConfig(push_interval_s=0.0), 50) == \
      "eval_push_interval_0s_it50"
  # --friction LO HI: only the floor-friction range changes (e.g. the paper's, for a run trained
  # on a narrower one), and the directory says so.
  narrow = dataclasses.replace(
      trained, randomization=dataclasses.replace(trained.randomization, friction=(0.1, 0.3)))
  paper = evaluation.EvalConfig(push_interval_s=0.0, friction=(0.1, 1.2))
  r = evaluation.eval_env_config(narrow, paper).randomization
  assert r == dataclasses.replace(narrow.randomization, push_interval_s=0.0, friction=(0.1, 1.2))
  assert eval_dir_name(paper, 1000) == "eval_push_interval_0s_friction_0.1-1.2_it1000"
  assert eval_dir_name(evaluation.EvalConfig(friction=(0.1, 0.6))) == "eval_friction_0.1-0.6"
  # --seed S: other episodes beside the default seed's, never over them.
  assert eval_dir_name(evaluation.EvalConfig(seed=7)) == "eval_seed7"
  assert eval_dir_name(dataclasses.replace(paper, seed=7), 1000) == \
      "eval_push_interval_0s_friction_0.1-1.2_seed7_it1000"
  assert eval_dir_name(evaluation.EvalConfig(seed=evaluation.EvalConfig().seed)) == "eval"
  # Training kicks are off unless --kicks: the figures are the paper's randomization's.
  kicked = dataclasses.replace(
      trained, randomization=dataclasses.replace(trained.randomization, kick_velocity=(0.2, 1.2),
                                                 kick_yaw_rate=(0.0, 0.3)))
  r = evaluation.eval_env_config(kicked, evaluation.EvalConfig()).randomization
  assert r == trained.randomization and not r.kicks
  r = evaluation.eval_env_config(kicked, evaluation.EvalConfig(kicks=True)).randomization
  assert r == kicked.randomization and r.kicks
  assert eval_dir_name(evaluation.EvalConfig(kicks=True, seed=7)) == "eval_kicks_seed7"


def test_evaluate_rejects_a_bad_friction_range(tmp_path):
  """--friction HI < LO is one error line naming the option, before any run is read."""
  out = _cli("experiments.evaluate", "--run", str(tmp_path), "--friction", "0.6", "0.1")
  lines = [l for l in out.stderr.splitlines() if l.strip() and "warp" not in l]
  assert out.returncode == 2 and len(lines) == 1 and "--friction" in lines[0], out.stderr


def test_evaluate_iteration_picks_that_checkpoint_or_names_the_saved_ones(smoke_run):
  """--iteration N restores the checkpoint of iteration N; one not saved is one error line that
  lists the saved iterations, and nothing is written."""
  from mash.deploy import policy
  assert policy.load(smoke_run, iteration=10).iteration == 10
  with pytest.raises(policy.RunError, match=r"no checkpoint of step 7 .*steps 10\)"):
    policy.load(smoke_run, iteration=7)
  out = _cli("experiments.evaluate", "--run", str(smoke_run), "--iteration", "7")
  lines = [l for l in out.stderr.splitlines() if l.strip() and "warp" not in l]
  assert out.returncode == 2 and len(lines) == 1 and "step 7" in lines[0], out.stderr
  assert not (smoke_run / "eval_it7").exists()


def _stderr_lines(text: str) -> list[str]:
  """Non-empty stderr lines, without MuJoCo's import notes about the optional warp backend."""
  return [l for l in text.splitlines() if l.strip() and "warp" not in l]


def _cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
  return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, cwd=cwd,
                        timeout=120)


@pytest.mark.parametrize("args, words", [
    (("experiments.bipedal", "--algo", "sac"), "algo 'sac'"),
    (("experiments.bipedal", "--preset", "huge"), "preset 'huge'"),
    (("experiments.armswing", "--ablation", "magic"), "ablation 'magic'"),
    (("experiments.bipedal", "--set", "train.learning_rate"), "path=value"),
    (("experiments.bipedal", "--resume", "/nonexistent/run"), "does not exist"),
    (("experiments.evaluate", "--run", "/nonexistent/run"), "does not exist"),
    (("experiments.evaluate", "--run", "r", "--no-push", "--push-interval", "1"),
     "--push-interval"),
    (("experiments.evaluate", "--run", "r", "--iteration", "0"), "--iteration"),
    (("experiments.evaluate", "--run", "r", "--seed", "-1"), "--seed"),
    (("experiments.evaluate", "--run", "r", "--tracking", "--command-vx", "0.4"), "--command-vx"),
])
def test_cli_bad_input_is_one_line(args, words):
  """Bad input: exit status 2, one line on stderr naming the input, no traceback."""
  out = _cli(*args)
  assert out.returncode == 2
  lines = [l for l in out.stderr.splitlines() if l.strip() and "warp" not in l]
  assert len(lines) == 1 and lines[0].startswith("error:") and words in lines[0], out.stderr


def test_cli_refuses_existing_run_and_wrong_task(smoke_run, tmp_path):
  """--out holding a run is refused; --resume of a bipedal run from armswing is refused."""
  before = (smoke_run / "progress.csv").read_text()
  out = _cli("experiments.bipedal", "--preset", "smoke", "--out", str(smoke_run))
  assert out.returncode == 2 and "already holds a run" in out.stderr
  out = _cli("experiments.armswing", "--resume", str(smoke_run))
  assert out.returncode == 2 and "'bipedal' run" in out.stderr
  (tmp_path / "not_a_run").mkdir()
  out = _cli("experiments.evaluate", "--run", str(tmp_path / "not_a_run"))
  assert out.returncode == 2 and "not a run directory" in out.stderr
  assert (smoke_run / "progress.csv").read_text() == before


def test_compare_report_from_synthetic_results():
  """report.md: the paper's table layout, our rows, Welch p-values within each family (the
  paper's four metrics decide, with their power figures), an honest verdict."""
  from mash.analysis import metrics as metrics_lib
  from mash.analysis.compare import build_report
  rng = np.random.default_rng(0)

  def seeds(base):
    return {
        "per_seed": [{
            "T_conv": base * 100 + i, "S_action": base * 0.1 + 0.01 * i, "S_action_2nd": base * 0.2,
            "S_torso": base * 1e-3, "C_limb": base * 0.3, "fall_rate": 0.0,
            "forward_speed": 0.3 + rng.normal() * 0.01
        } for i in range(3)]
    }

  md, data = build_report("bipedal", {"mash": seeds(1.0), "ppo": seeds(2.0)}, "smoke", 3)
  assert "| metric | MASH (ours) | Single-agent PPO (ours) |" in md and "| ~1306 | ~1661 |" in md
  assert data["table"]["mash"]["T_conv"]["mean"] == pytest.approx(101.0)
  lo, hi = data["table"]["mash"]["T_conv"]["ci95"]
  assert 100.0 <= lo <= 101.0 <= hi <= 102.0
  tests = data["tests"]["S_action"]
  assert tests["p"] < 0.05 and tests["p_holm"] >= tests["p"] and tests["hedges_g"] < 0
  assert tests["verdict"] == "MASH better" and "- S_action: MASH better" in md
  # The primary family is the paper's four metrics, Holm over those four: S_action's adjusted p
  # is its p times 4 at most; its power at the observed g and the detectable g at alpha / 4.
  assert data["families"]["primary"] == ["T_conv", "S_action", "S_torso", "C_limb"]
  assert tests["family"] == "primary" and tests["p_holm"] <= 4 * tests["p"] + 1e-12
  assert tests["alpha"] == pytest.approx(0.0125)
  assert tests["power"] == pytest.approx(metrics_lib.t_test_power(tests["hedges_g"], 3, 3, 0.0125))
  assert metrics_lib.t_test_power(tests["detectable_effect"], 3, 3, 0.0125) == pytest.approx(0.8)
  assert data["tests"]["S_action_2nd"]["family"] == "secondary"
  assert "power" not in data["tests"]["fall_rate"]
  # Equal fall rates: no difference.
  assert data["tests"]["fall_rate"]["verdict"] == "no difference at this power"
  md, data = build_report("bipedal", {"mash": seeds(2.0), "ppo": seeds(1.0)}, "smoke", 3)
  assert "- S_action: PPO better" in md
  # One seed a method (a comparison's first pair): no test, and the report says so.
  one = {a: {"per_seed": seeds(b)["per_seed"][:1]} for a, b in (("mash", 1.0), ("ppo", 2.0))}
  md, _ = build_report("bipedal", one, "smoke", 1)
  assert "nan" not in md and "p = n/a, no test below two seeds a method" in md
  # With the all-episode metrics in the evaluation, they get rows of their own.
  both = {a: seeds(b) for a, b in (("mash", 1.0), ("ppo", 2.0))}
  for res in both.values():
    for m in res["per_seed"]:
      m["all_episodes"] = {k: m[k] * 1.5 for k in ("S_action", "S_action_2nd", "S_torso", "C_limb")}
  md, data = build_report("bipedal", both, "smoke", 3)
  assert "| C_limb (all episodes, up to the fall) |" in md
  assert data["table"]["ppo"]["all_episodes/C_limb"]["mean"] == pytest.approx(0.9)
  assert data["tests"]["all_episodes/C_limb"]["family"] == "secondary"
  assert "C_limb over all episodes" not in md  # the verdict is the primary family's alone
  # T_conv against the threshold common to both methods, one row per smoothing window.
  it = np.arange(1, 101, dtype=float)
  fast, slow = np.minimum(10.0, 0.25 * it), np.minimum(10.0, 0.125 * it)
  conv = metrics_lib.common_threshold_t_conv(
      {"mash": [fast, fast, fast], "ppo": [slow, slow, slow * 0]}, windows=[1, 2, 4])
  md, data = build_report("bipedal", both, "smoke", 3, conv)
  assert data["table"]["mash"]["T_conv@1"]["mean"] == pytest.approx(conv["t_conv"]["mash"][1][0])
  assert data["table"]["ppo"]["T_conv@1"]["n"] == 2  # the flat seed never reached it
  assert "window 2" in md and "never reached: Single-agent PPO 1 seed(s)" in md
  # The README's table: the primary family (SPEC's T_conv beside the paper's), then the middle
  # window's common-threshold T_conv and the rest of the secondary rows, with family and verdict.
  from mash.analysis.compare import readme_table
  data = json.loads(json.dumps(data, default=float))  # as report.json holds it
  rows = readme_table([data]).splitlines()
  t_conv = next(r for r in rows if "| T_conv (iterations) |" in r)
  assert t_conv.startswith("| bipedal (3 seeds) |") and "| primary |" in t_conv
  assert "| 1306 | 1661 |" in t_conv
  common = next(r for r in rows if "(window 2)" in r)
  mean = data["table"]["mash"]["T_conv@2"]["mean"]
  assert "| secondary |" in common and f"| {mean:.3g} ± " in common and "| – | – |" in common
  s_action = next(r for r in rows if "| S_action |" in r)
  assert "| MASH better | 0.107 | 0.547 |" in s_action
  assert not any("arm-leg" in r for r in rows)  # bipedal has no arm agents


def test_compare_puts_the_robustness_batteries_in_the_secondary_family(tmp_path):
  """Each kept policy's battery (``policy/eval_robustness/``, ``policy/sim2sim_robustness/``)
  becomes one secondary row per condition (its survival, higher better) once two seeds of each
  method hold it; the primary family and its Holm correction stay the paper's four."""
  from mash.analysis import compare

  def battery(folder, survival):
    path = tmp_path / folder / "robustness.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps({
            "conditions": [{"name": "kick 0.5 m/s", "survival": survival},
                           {"name": "latency 40 ms", "survival": 1.0}]
        }))

  battery("s0/policy/eval_robustness", 0.75)
  battery("s0/policy/sim2sim_robustness", 0.5)
  assert compare.battery_survival(tmp_path / "s0") == {
      "robustness_mjx/kick 0.5 m/s": 0.75, "robustness_mjx/latency 40 ms": 1.0,
      "robustness_native/kick 0.5 m/s": 0.5, "robustness_native/latency 40 ms": 1.0
  }
  assert compare.battery_survival(tmp_path / "none") == {}

  def seeds(base, kicks):
    return {
        "per_seed": [{
            "T_conv": 100 + i, "S_action": 0.1 + 0.01 * i, "S_action_2nd": 0.2, "S_torso": 1e-3,
            "C_limb": 0.3, "fall_rate": 0.0, "forward_speed": 0.3 + 0.01 * i,
            **({"robustness_mjx/kick 0.5 m/s": base + 0.01 * i} if i < kicks else {})
        } for i in range(4)]
    }

  _, data = compare.build_report("bipedal", {"mash": seeds(0.9, 3), "ppo": seeds(0.5, 3)}, "smoke",
                                 4)
  key = "robustness_mjx/kick 0.5 m/s"
  assert key in data["families"]["secondary"] and key not in data["families"]["primary"]
  assert data["table"]["mash"][key]["n"] == 3 and data["tests"][key]["verdict"] == "MASH better"
  md, _ = compare.build_report("bipedal", {"mash": seeds(0.5, 3), "ppo": seeds(0.9, 3)}, "smoke", 4)
  assert "| survival: kick 0.5 m/s (MJX battery, 3 seeds) |" in md and "PPO better" in md
  # Held by 4 MASH seeds and 3 PPO ones: the row says both counts.
  md, _ = compare.build_report("bipedal", {"mash": seeds(0.5, 4), "ppo": seeds(0.9, 3)}, "smoke", 4)
  assert "| survival: kick 0.5 m/s (MJX battery, 4 / 3 seeds) |" in md
  # One seed a method holds a battery: no row (no test below two seeds a method).
  _, data = compare.build_report("bipedal", {"mash": seeds(0.9, 1), "ppo": seeds(0.5, 3)}, "smoke",
                                 4)
  assert key not in data["families"]["secondary"]


def test_compare_runs_the_battery_on_each_kept_policy_once(tmp_path, monkeypatch):
  """A seed whose policy was kept goes through the MJX battery (default conditions) once; a seed
  without a kept policy (its checkpoints gone) is left alone."""
  from mash.analysis import reports
  from mash.deploy import policy as policy_lib
  from mash.runs import comparison
  calls = []

  def fake_battery(folder, cfg):
    calls.append((folder, cfg))
    out = Path(folder) / "eval_robustness"
    out.mkdir()
    (out / "robustness.json").write_text("{}")

  monkeypatch.setattr(reports, "robustness_run", fake_battery)
  monkeypatch.setattr(policy_lib, "is_policy_folder",
                      lambda f: Path(f).name == "policy" and Path(f).is_dir())
  (tmp_path / "seed0").mkdir()
  comparison.battery(tmp_path / "seed0")
  assert calls == []
  (tmp_path / "seed1" / "policy").mkdir(parents=True)
  comparison.battery(tmp_path / "seed1")
  comparison.battery(tmp_path / "seed1")
  assert [Path(f).parent.name for f, _ in calls] == ["seed1"]
  assert calls[0][1] == comparison.robustness.BatteryConfig()


def test_readme_table_comes_from_the_committed_reports():
  """The README's MASH-vs-PPO table is what ``compare --readme-table`` prints from the reports
  its marker names (regenerate it with that command after a report changes)."""
  from mash.analysis.compare import README_BEGIN, README_END, readme_block
  repo = Path(__file__).resolve().parents[1]
  readme = (repo / "README.md").read_text()
  assert README_BEGIN in readme, "the README has no generated comparison table"
  start = readme.index(README_BEGIN)
  block = readme[start:readme.index(README_END, start) + len(README_END) + 1]
  dirs = block.splitlines()[0][len(README_BEGIN):].removesuffix("-->").split()
  assert dirs and all((repo / d / "report.json").is_file() for d in dirs)
  assert block == readme_block(dirs, repo), (
      "the README's comparison table is not the reports': replace its block with the output "
      f"of `python -m experiments.compare --readme-table {' '.join(dirs)}`")


def test_compare_resumes_seed_by_seed(evaluated_smoke_run, tmp_path):
  """compare's plan per seed: nothing there -> new; a run stopped early -> resume, or restart
  when its checkpoints are not there; trained to the end -> done. Its report pairs the seeds
  evaluated for both methods."""
  import shutil

  from mash.analysis import compare
  from mash.runs import comparison
  smoke_run = evaluated_smoke_run
  assert comparison.seed_state(tmp_path / "none", 10) == "new"
  out = tmp_path / "cmp"
  for algo, seeds in (("mash", (0, 1)), ("ppo", (0,))):
    for s in seeds:
      shutil.copytree(smoke_run, out / algo / f"seed{s}")
  assert comparison.seed_state(out / "mash" / "seed0", 10) == "done"
  assert comparison.seed_state(out / "mash" / "seed0", 20) == "resume"  # a longer budget
  summary = out / "mash" / "seed1" / "summary.json"
  summary.write_text(json.dumps({**json.loads(summary.read_text()), "interrupted": True}))
  assert comparison.seed_state(out / "mash" / "seed1", 10) == "resume"
  # Cut off with its checkpoints on another machine: trained again, its records kept aside.
  shutil.copytree(out / "mash" / "seed1", out / "mash" / "seed2",
                  ignore=shutil.ignore_patterns("checkpoints"))
  assert comparison.seed_state(out / "mash" / "seed2", 10) == "restart"
  assert comparison.set_aside(out / "mash" / "seed2") == out / "mash" / "cut_off" / "seed2_0"
  assert (out / "mash" / "cut_off" / "seed2_0" / "config.json").is_file()
  assert comparison.seed_state(out / "mash" / "seed2", 10) == "new"
  assert [d.name for d in compare.seed_dirs(out / "mash")] == ["seed0", "seed1"]
  methods = {algo: out / algo for algo in ("mash", "ppo")}
  md, data, dirs = compare.build_from_dirs("bipedal", out, "smoke", methods)
  assert data["seeds_paired"] == ["seed0"] and [d.name for d in dirs["ppo"]] == ["seed0"]
  assert "T_conv (paper reward reaches" in md
  wall = json.loads((out / "mash" / "seed0" / "summary.json").read_text())["wall_s"]
  assert "## Per seed" in md and "| 0 | MASH | " in md and f" | {wall:.0f} |" in md
  compare.write_report("bipedal", out, "smoke", methods)
  for name in ("report.md", "report.json", "reward_curves.png", "hip_pitch.png"):
    assert (out / name).stat().st_size > 0
  # A clone holds the committed records only: no trajectories.npz, the hip trace instead.
  for algo in ("mash", "ppo"):
    (out / algo / "seed0" / "eval" / "trajectories.npz").unlink()
  (out / "hip_pitch.png").unlink()
  compare.write_report("bipedal", out, "smoke", methods)
  assert (out / "hip_pitch.png").stat().st_size > 0
  # The tuning: one rule for both methods (the higher final reward; a tie to the smaller rate),
  # and the seed runs then live under the picked rate.
  assert comparison.pick_learning_rates({"mash": {1e-3: 150.0, 3e-4: 120.0},
                                      "ppo": {1e-3: 90.0, 3e-4: 90.0}}) == \
      {"mash": 1e-3, "ppo": 3e-4}
  final = comparison.final_reward(out / "mash" / "seed0")
  curve = compare.method_curves(out / "mash" / "seed0")[1][0]
  assert final == pytest.approx(curve[-1:].mean())  # 10 iterations: the last one
  (out / "tuning.json").write_text(json.dumps({"picked": {"mash": 1e-3, "ppo": 3e-4}}))
  assert comparison.method_dir(out, "ppo") == out / "ppo" / "lr0.0003"


def _config_of(command: list[str]) -> str:
  """The config.json a training command (as compare builds it) writes: from ``--config`` or the
  preset, with its ``--seeds`` and ``--set`` (a stand-in for training keeps it faithful)."""
  from mash.runs import experiment
  task = command[command.index("-m") + 1].split(".")[-1]
  sets = [command[i + 1] for i, c in enumerate(command) if c == "--set"]
  seeds = int(command[command.index("--seeds") + 1]) if "--seeds" in command else 1
  if "--config" in command:
    cfg = experiment.config_from_file(command[command.index("--config") + 1], task, seeds, sets)
  else:
    cfg = experiment.make_config(task, command[command.index("--algo") + 1],
                                 command[command.index("--preset") + 1], seeds, "none", sets)
  return experiment.to_json(cfg)


def _stand_ins(monkeypatch, training, evaluation, kept=None):
  """compare's training, evaluation and policy keeping replaced by the given functions."""
  import subprocess as subprocess_lib

  from mash.analysis import reports
  from mash.runs import comparison
  monkeypatch.setattr(subprocess_lib, "call", training)
  monkeypatch.setattr(reports, "evaluate_run", evaluation)
  monkeypatch.setattr(
      comparison, "keep_policy", lambda run, seed_dir, seed=0:
      (kept
       if kept is not None else []).append((run.parent.name + "/" + run.name, seed_dir.name, seed)))


def test_compare_evaluates_each_run_right_after_it_trains(evaluated_smoke_run, tmp_path,
                                                          monkeypatch):
  """compare's whole plan with training and evaluation stood in for: the search trains and
  evaluates each rate's seed 0 in turn, the tie goes to the smaller rate, the other seeds train
  at it and each is evaluated before the next one trains; run again, it does nothing new."""
  import shutil

  from experiments import compare
  from mash.analysis import compare as compare_lib
  smoke_run = evaluated_smoke_run
  events, kept = [], []

  def fake_training(command):  # a finished run's records, as the CLI leaves them
    out = Path(command[command.index("--out") + 1])
    shutil.copytree(smoke_run, out, ignore=shutil.ignore_patterns("eval*"))
    (out / "config.json").write_text(_config_of(command))
    events.append(("train", out.relative_to(tmp_path).as_posix()))
    return 0

  def fake_evaluation(run_dir, cfg):
    d = Path(run_dir)
    shutil.copytree(smoke_run / "eval", d / "eval", dirs_exist_ok=True)
    metrics = json.loads((d / "eval" / "metrics.json").read_text())
    metrics["eval_config"]["num_episodes"] = cfg.num_episodes
    (d / "eval" / "metrics.json").write_text(json.dumps(metrics))
    events.append(("eval", d.relative_to(tmp_path).as_posix()))

  compare_lib.hip_trace(smoke_run)  # a clone's records: the trace, not the trajectories
  _stand_ins(monkeypatch, fake_training, fake_evaluation, kept)
  argv = [
      "--preset", "smoke", "--seeds", "2", "--out",
      str(tmp_path / "cmp"), "--episodes", "4", "--no-progress"
  ]
  compare.main(argv)
  runs_in_order = [
      f"cmp/{a}/lr{lr}/seed{s}" for a, lr, s in (("mash", 0.0003, 0), ("mash", 0.001, 0),
                                                 ("ppo", 0.0003, 0), ("ppo", 0.001, 0),
                                                 ("mash", 0.0003, 1), ("ppo", 0.0003, 1))
  ]
  assert events == [(what, d) for d in runs_in_order for what in ("train", "eval")]
  tuning = json.loads((tmp_path / "cmp" / "tuning.json").read_text())
  assert tuning["picked"] == {"mash": 3e-4, "ppo": 3e-4}  # equal rewards: the smaller rate
  assert json.loads(
      (tmp_path / "cmp" / "report.json").read_text())["seeds_paired"] == ["seed0", "seed1"]
  # Each run kept its policy and its record was compacted (the log gzipped, as committed).
  assert set(kept) == {("/".join(d.split("/")[-2:]), d.split("/")[-1], 0) for d in runs_in_order}
  assert (tmp_path / "cmp" / "mash" / "lr0.0003" / "seed1" / "progress.csv.gz").is_file()
  assert not (tmp_path / "cmp" / "mash" / "lr0.0003" / "seed1" / "progress.csv").exists()
  from PIL import Image
  for plot in ("reward_curves.png", "hip_pitch.png"):  # the report's plots compacted as well
    with Image.open(tmp_path / "cmp" / plot) as image:
      assert image.mode == "P", plot
  events.clear()
  compare.main(argv)
  assert events == []


def test_compare_trains_seeds_together_and_splits_them(evaluated_smoke_run, tmp_path, monkeypatch):
  """``--seeds-at-once 2`` with training and evaluation stood in for: after the search, seeds 1
  and 2 of each method train in one call (``--seeds 2``, ``train.seed=1``) and are evaluated
  together, then each gets its ``seed<s>/`` records (its own curve rows, metrics and hip trace)
  and the report pairs seeds 0-2; run again, it does nothing new."""
  import csv
  import shutil

  from experiments import compare
  from mash.analysis import compare as compare_lib
  from mash.runs import comparison
  smoke_run = evaluated_smoke_run
  events, kept = [], []

  def fake_training(command):  # a finished run; a group's seed i has reward + 100 i
    out = Path(command[command.index("--out") + 1])
    seeds = int(command[command.index("--seeds") + 1]) if "--seeds" in command else 1
    shutil.copytree(smoke_run, out, ignore=shutil.ignore_patterns("eval*"))
    (out / "config.json").write_text(_config_of(command))
    with open(out / "progress.csv", newline="") as f:
      reader = csv.DictReader(f)
      fields, rows = [*reader.fieldnames, "seed"], list(reader)
    with open(out / "progress_seeds.csv", "w", newline="") as f:
      writer = csv.DictWriter(f, fields)
      writer.writeheader()
      for i in range(seeds):
        writer.writerows({
            **r, "seed": str(i), "paper_episode_reward": str(
                float(r["paper_episode_reward"]) + 100 * i)
        } for r in rows)
    events.append(
        ("train", out.relative_to(tmp_path).as_posix(), command[command.index("--set") + 1], seeds))
    return 0

  def fake_evaluation(run_dir, cfg):  # a group's seed i falls in 0.01 + 0.1 i of the episodes
    d = Path(run_dir)
    shutil.copytree(smoke_run / "eval", d / "eval", dirs_exist_ok=True)
    metrics = json.loads((d / "eval" / "metrics.json").read_text())
    metrics["eval_config"]["num_episodes"] = cfg.num_episodes
    if d.name.startswith("group_"):
      one = metrics["per_seed"][0]
      metrics["per_seed"] = [{**one, "fall_rate": 0.01 + 0.1 * i} for i in range(2)]
      tr = dict(np.load(d / "eval" / "trajectories.npz"))
      both = {k: np.concatenate([v, v]) for k, v in tr.items() if k != "dt"}
      both["seed"] = np.repeat([0, 1], len(tr["seed"]))
      np.savez(d / "eval" / "trajectories.npz", dt=tr["dt"], **both)
    (d / "eval" / "metrics.json").write_text(json.dumps(metrics))
    events.append(("eval", d.relative_to(tmp_path).as_posix()))

  _stand_ins(monkeypatch, fake_training, fake_evaluation, kept)
  argv = [
      "--preset", "smoke", "--seeds", "3", "--seeds-at-once", "2", "--out",
      str(tmp_path / "cmp"), "--episodes", "4", "--no-progress"
  ]
  compare.main(argv)
  assert events[8:] == [("train", "cmp/mash/lr0.0003/group_seeds1-2", "train.seed=1", 2),
                        ("eval", "cmp/mash/lr0.0003/group_seeds1-2"),
                        ("train", "cmp/ppo/lr0.0003/group_seeds1-2", "train.seed=1", 2),
                        ("eval", "cmp/ppo/lr0.0003/group_seeds1-2")]
  mash = tmp_path / "cmp" / "mash" / "lr0.0003"
  base = compare_lib.method_curves(mash / "seed0")[1][0]
  single = json.loads((smoke_run / "eval" / "metrics.json").read_text())
  for s in (1, 2):
    d = mash / f"seed{s}"
    assert comparison.seed_state(d, 10) == "done"
    summary = json.loads((d / "summary.json").read_text())
    assert summary["group"] == "group_seeds1-2" and summary["group_index"] == s - 1
    np.testing.assert_allclose(compare_lib.method_curves(d)[1], [base + 100 * (s - 1)], rtol=1e-6)
    metrics = json.loads((d / "eval" / "metrics.json").read_text())
    assert metrics["fall_rate"] == metrics["per_seed"][0]["fall_rate"] == 0.01 + 0.1 * (s - 1)
    assert len(metrics["per_seed"]) == 1 and (d / "eval" / "hip_trace.npz").is_file()
    assert set(metrics) == set(single) and metrics["std"]["fall_rate"] == 0.0
  assert [d.name for d in compare_lib.seed_dirs(mash)] == ["seed0", "seed1", "seed2"]
  assert ("lr0.0003/group_seeds1-2", "seed1", 0) in kept
  assert ("lr0.0003/group_seeds1-2", "seed2", 1) in kept
  assert json.loads((tmp_path / "cmp" / "report.json").read_text())["seeds_paired"] == [
      "seed0", "seed1", "seed2"
  ]
  assert " (group_seeds1-2) |" in (tmp_path / "cmp" / "report.md").read_text()
  events.clear()
  compare.main(argv)
  assert events == []


def test_a_continued_comparison_keeps_its_own_config(evaluated_smoke_run, tmp_path, monkeypatch,
                                                     capsys):
  """A comparison continues on its folder's config, never today's preset: a new seed trains from
  the config.json of the method's runs with only ``train.seed`` changed; a ``--preset`` that
  would change it, or runs of one method that differ in more than the seed, are refused in one
  line before anything trains. A field added to the config since a run (its default keeping the
  old behaviour) is no difference."""
  import shutil

  from experiments import compare
  from mash.runs import experiment
  out = tmp_path / "cmp"
  (out).mkdir()
  (out / "tuning.json").write_text(
      json.dumps({
          "learning_rates": [1e-3], "seed": 0, "picked": {"mash": 1e-3, "ppo": 1e-3},
          "final": {"mash": {"0.001": 1.0}, "ppo": {"0.001": 1.0}}
      }))
  for algo in ("mash", "ppo"):  # seed 0 trained on an earlier preset: another action scale
    cfg = experiment.to_dict(
        experiment.make_config("bipedal", algo, "smoke", 1, "none",
                               ["train.learning_rate=1e-3", "env.action_scale=0.3"]))
    for field in [f for f in cfg["env"]["randomization"] if f.startswith("kick")]:
      del cfg["env"]["randomization"][field]  # and by code older than the kicks (off by default)
    seed0 = out / algo / "lr0.001" / "seed0"
    shutil.copytree(evaluated_smoke_run, seed0)
    (seed0 / "config.json").write_text(json.dumps(cfg))
  commands = []

  def fake_training(command):
    commands.append(command)
    run = Path(command[command.index("--out") + 1])
    shutil.copytree(evaluated_smoke_run, run, ignore=shutil.ignore_patterns("eval*"))
    (run / "config.json").write_text(_config_of(command))
    return 0

  def fake_evaluation(run_dir, cfg):
    shutil.copytree(evaluated_smoke_run / "eval", Path(run_dir) / "eval", dirs_exist_ok=True)

  _stand_ins(monkeypatch, fake_training, fake_evaluation)
  argv = [
      "--seeds", "2", "--learning-rates", "1e-3", "--out",
      str(out), "--episodes", "3", "--no-progress"
  ]
  with pytest.raises(SystemExit) as e:  # today's smoke preset is not the folder's config
    compare.main([*argv, "--preset", "smoke"])
  lines = _stderr_lines(capsys.readouterr().err)
  assert e.value.code == 2 and len(lines) == 1 and "env.action_scale (0.3 -> 0.25)" in lines[0]
  assert commands == []
  compare.main(argv)
  assert [c[c.index("--out") + 1].split("/cmp/")[1] for c in commands
         ] == ["mash/lr0.001/seed1", "ppo/lr0.001/seed1"]
  for c, algo in zip(commands, ("mash", "ppo")):
    assert c[c.index("--config") + 1] == str(out / algo / "lr0.001" / "seed0" / "config.json")
    assert "--preset" not in c and [c[i + 1] for i, x in enumerate(c) if x == "--set"
                                   ] == ["train.seed=1"]
    seed1 = json.loads((out / algo / "lr0.001" / "seed1" / "config.json").read_text())
    assert seed1["env"]["action_scale"] == 0.3 and seed1["train"]["seed"] == 1
  compare.main(argv)  # seed 1's config names the kick fields seed 0's lacks: still one recipe
  assert len(commands) == 2
  # Runs of one method that differ in more than the seed cannot be paired in one report.
  seed1 = out / "mash" / "lr0.001" / "seed1" / "config.json"
  seed1.write_text(seed1.read_text().replace('"fall_tilt": 1.0', '"fall_tilt": 0.9'))
  with pytest.raises(SystemExit) as e:
    compare.main([*argv[:1], "3", *argv[2:]])
  lines = _stderr_lines(capsys.readouterr().err)
  assert e.value.code == 2 and len(lines) == 1 and "env.fall_tilt (1.0 -> 0.9)" in lines[0]
  assert len(commands) == 2


def test_config_file_trains_another_run_on_the_same_recipe(smoke_run, tmp_path):
  """``--config FILE``: a run's config.json with ``--seeds`` and ``--set`` on top; another
  task's file, a file that is not a config, or a preset beside it are one line each."""
  from mash.runs import experiment
  cfg = experiment.config_from_file(smoke_run / "config.json", "bipedal", 2, ["train.seed=7"])
  reference = experiment.from_json((smoke_run / "config.json").read_text())
  assert cfg.seeds == 2 and cfg.train.seed == 7
  assert cfg.env == reference.env and cfg.preset == reference.preset
  with pytest.raises(experiment.ConfigError, match="is a 'bipedal' config, not 'armswing'"):
    experiment.config_from_file(smoke_run / "config.json", "armswing")
  (tmp_path / "bad.json").write_text("{")
  with pytest.raises(experiment.ConfigError, match="bad.json"):
    experiment.config_from_file(tmp_path / "bad.json", "bipedal")
  out = _cli("experiments.bipedal", "--config", str(smoke_run / "config.json"), "--preset", "smoke",
             "--out", str(tmp_path / "x"))
  assert out.returncode == 2 and "--config gives the whole config; --preset" in out.stderr
  assert not (tmp_path / "x").exists()


def test_keep_policy_writes_a_checked_policy_folder(smoke_run, tmp_path):
  """compare keeps every run's policy: ``seed<s>/policy/`` with policy.npz, policy.json,
  config.json and an ONNX graph that matches the JAX policy; not again once it is there."""
  from mash.deploy import policy as policy_lib
  from mash.runs import comparison
  seed_dir = tmp_path / "seed5"
  comparison.keep_policy(smoke_run, seed_dir)
  folder = seed_dir / "policy"
  for name in ("policy.npz", "policy.json", "config.json", "policy.onnx", "card.md"):
    assert (folder / name).is_file(), name
  assert policy_lib.load(folder).iteration == policy_lib.load(smoke_run).iteration
  stamp = (folder / "policy.onnx").stat().st_mtime_ns
  comparison.keep_policy(smoke_run, seed_dir)
  assert (folder / "policy.onnx").stat().st_mtime_ns == stamp


def test_expected_duration_line_from_the_timed_calls():
  """Calls of 4 s and 6 s with 10 iterations each: median 5 s = 0.5 s per iteration (2 it/s);
  100 iterations left take 50 s, about 1 min."""
  line = runs._expected_duration([4.0, 6.0], 10, 100)
  assert line.startswith("timed: 0.50 s per iteration (2.00 it/s) after compiling; the remaining "
                         "100 iterations take about 1 min (done around ")


def test_a_quiet_start():
  """Importing the package prints nothing: no 'Failed to import warp' lines from MJX's probe of
  its optional Warp backend."""
  out = subprocess.run(
      [sys.executable, "-c", "import mash.sim.env, mash.runs.loop, mash.analysis.evaluation"],
      capture_output=True, text=True, timeout=120)
  assert out.returncode == 0 and out.stdout == "" and "warp" not in out.stderr, out


def test_wandb_logs_every_row_and_resumes_the_same_run(smoke_config, smoke_trainer, tmp_path,
                                                       monkeypatch):
  """``wandb=true``: every progress row reaches W&B at its iteration, and a resume continues the
  same W&B run (its id kept in the run directory). First through a stand-in that records the
  calls, then through the real library in offline mode, which writes the run's file."""
  pytest.importorskip(
      "wandb", reason="Weights & Biases is an optional extra: pip install -e "
      "'.[wandb]' (the dev extra has it)")
  import wandb

  from mash.runs import loggers
  from mash.runs import loop as runs
  cfg = dataclasses.replace(smoke_config, wandb=True, checkpoint_every=1)
  calls = []

  class FakeRun:

    def log(self, data, step):
      calls.append(("log", step, dict(data)))

    def finish(self):
      calls.append(("finish",))

  def fake_init(**kwargs):
    calls.append(("init", kwargs))
    return FakeRun()

  with monkeypatch.context() as m:
    m.setattr(wandb, "init", fake_init)
    out = tmp_path / "fake"
    runs.train(cfg, out, show_progress=False, max_calls=1, trainer=smoke_trainer)
    runs.train(cfg, out, resume=True, show_progress=False, max_calls=1, trainer=smoke_trainer)
  inits = [c[1] for c in calls if c[0] == "init"]
  assert len(inits) == 2 and inits[0]["id"] == inits[1]["id"] and inits[1]["resume"] == "allow"
  assert inits[0]["project"] == "mash-jax" and inits[0]["config"]["train"]["num_envs"] == 64
  logged = {c[1]: c[2] for c in calls if c[0] == "log"}
  progress = runs.read_progress(out)
  assert sorted(logged) == progress["iteration"].tolist() == list(range(1, 11))
  for i, it in enumerate(progress["iteration"]):
    assert logged[it]["episode_reward"] == pytest.approx(progress["episode_reward"][i])
    assert logged[it]["env_steps"] == progress["env_steps"][i]
  assert sum(c[0] == "finish" for c in calls) == 2

  monkeypatch.setenv("WANDB_MODE", "offline")
  monkeypatch.setenv("WANDB_SILENT", "true")
  out = tmp_path / "offline"
  runs.train(cfg, out, show_progress=False, max_calls=1, trainer=smoke_trainer)
  run_id = (out / loggers.WANDB_ID_FILE).read_text().strip()
  files = list((out / "wandb").glob(f"offline-run-*-{run_id}/run-{run_id}.wandb"))
  assert len(files) == 1 and files[0].stat().st_size > 0, list((out / "wandb").rglob("*"))
