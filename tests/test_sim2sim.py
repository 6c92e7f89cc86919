"""Sim-to-sim in MuJoCo C: the CLI on the smoke run (report, comparison table, video), the
robustness battery in MuJoCo C on a shipped policy, and helpers.

Kept short: one 2 s episode in process, the video from a subprocess (``MUJOCO_GL`` must be chosen
before mujoco is imported, and this test process imported it long ago), no MJX evaluation (a
stand-in ``eval/metrics.json`` exercises the comparison table), a battery of 9 conditions x 2
episodes x 1.5 s.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mash.analysis import robustness
from mash.deploy import native_battery, sim2sim
from mash.runs import loop as runs
from mash.sim import geometry, robots

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def run_copy(smoke_run, tmp_path_factory):
  """A private copy of the smoke run (sim2sim writes policy.onnx and sim2sim/ into it)."""
  out = tmp_path_factory.mktemp("sim2sim") / "run"
  shutil.copytree(smoke_run, out, ignore=shutil.ignore_patterns("eval", "sim2sim", "policy.onnx"))
  return out


def test_quat_to_euler_numpy_matches_jax():
  """One function for the env (JAX in, JAX out) and native MuJoCo (NumPy in, NumPy out)."""
  rng = np.random.default_rng(0)
  for _ in range(20):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    euler = geometry.quat_to_euler(q)
    assert isinstance(euler, np.ndarray) and euler.dtype == np.float64 and euler.shape == (3,)
    from_jax = geometry.quat_to_euler(jnp.asarray(q, jnp.float32))
    assert isinstance(from_jax, jax.Array)
    np.testing.assert_allclose(euler, np.asarray(from_jax), atol=1e-5)


def test_native_battery_on_a_shipped_policy(tmp_path):
  """The battery in MuJoCo C: the MJX battery's conditions and row format, the same rows whatever
  the worker count (each episode fixed by its index); a 10 m/s kick fells the robot, none does
  not. Tiny: every group once or twice, 2 episodes (2 kick directions) x 1.5 s, kick at 0.5 s."""
  cfg = robustness.BatteryConfig(episode_s=1.5, episodes=2, kick_at_s=0.5, kick_sizes=(0.0, 10.0),
                                 kick_directions=2, friction_bands=((0.2, 0.3),), torso_mass=(0.2,),
                                 latency_ms=(20.0,))
  onnx = robots.ROBOT_DIR.parent / "policies" / "t1_bipedal_mash" / "policy.onnx"
  spec = robots.load("booster_t1")
  rows = native_battery.run(onnx, spec, cfg, workers=1, progress=None)
  assert [r["name"] for r in rows] == [c.name for c in robustness.conditions(cfg)]
  assert all(0.0 <= r["survival"] <= 1.0 and r["episodes"] == 2 for r in rows)
  by_name = {r["name"]: r for r in rows}
  assert by_name["kick 0 m/s"]["survival"] == 1.0 and "survival_by_direction" not in by_name[
      "kick 0 m/s"]
  assert by_name["kick 10 m/s"]["survival"] == 0.0
  assert by_name["kick 10 m/s"]["survival_by_direction"] == [0.0, 0.0]
  assert native_battery.run(onnx, spec, cfg, workers=2, progress=None) == rows

  physics = sim2sim.Sim2SimConfig()
  out = native_battery.write(tmp_path, native_battery.result(onnx, physics, 0.02, cfg, rows),
                             "test")
  saved = json.loads((out / "robustness.json").read_text())
  assert saved["engine"] == "mujoco" and saved["conditions"] == rows
  assert saved["battery"]["episodes"] == 2 and saved["physics"]["iterations"] == 10
  assert (out / "robustness.png").stat().st_size > 0


def test_each_kick_direction_meets_the_whole_gait_cycle():
  """The default battery's 64 episodes start at 64 distinct phases, and each of the 8 kick
  directions' 8 episodes start every 1/8 of a cycle (the old 0.37 e mod 1 gave each direction a
  0.28-cycle window of its own)."""
  cfg = robustness.BatteryConfig()
  n, k = cfg.episodes, cfg.kick_directions
  phases = np.array([native_battery.start_phase(e, n) for e in range(n)])
  assert len(np.unique(phases)) == n and phases.min() >= 0.0 and phases.max() < 1.0
  for d in range(k):
    mine = np.sort(phases[d::k])
    np.testing.assert_allclose(np.diff(mine), k / n)
    np.testing.assert_allclose(mine[0], d / n)


def test_robustness_flags(tmp_path, capsys):
  """--robustness runs its own conditions in MuJoCo C: a flag it has no use for is one error
  line, and so are --workers without it and a bad --episodes."""
  from experiments import sim2sim as cli
  for argv, expected in ((["--robustness", "--video", "x.mp4", "--no-mjx"],
                          "drop --video, --no-mjx"), (["--robustness", "--command-vx",
                                                       "0"], "drop --command-vx"),
                         (["--robustness", "--episodes",
                           "6"], "--episodes 6 must be a multiple of kick_directions"),
                         (["--workers", "2"], "--workers and --battery-seed go with --robustness")):
    with pytest.raises(SystemExit) as e:
      cli.main(["--run", str(tmp_path), *argv])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert expected in err and "\n" not in err, err


def test_sim2sim_report(run_copy, capsys):
  from experiments import sim2sim as cli
  # A stand-in MJX evaluation: the report must carry its numbers into the table.
  (run_copy / "eval").mkdir()
  fake = {
      "S_action": 0.125, "S_action_2nd": 0.0625, "S_torso": 0.01, "C_limb": 0.5, "fall_rate": 0.25,
      "forward_speed": 0.375, "command_vx": 0.4, "T_conv": 3.0,
      "eval_config": {"num_episodes": 2, "episode_s": 1.0, "randomization": True}
  }
  (run_copy / "eval" / "metrics.json").write_text(json.dumps(fake))
  cli.main(["--run", str(run_copy), "--episodes", "1", "--seconds", "2"])
  text = capsys.readouterr().out
  assert "exported" in text and "episode 1/1:" in text

  report = json.loads((run_copy / "sim2sim" / "report.json").read_text())
  for key in ("run", "onnx", "checkpoint_iteration", "command_vx", "episodes", "episode_s",
              "physics", "mujoco", "mjx", "mjx_source", "per_episode", "wall_s", "realtime_factor"):
    assert key in report, key
  mj = report["mujoco"]
  for key in ("S_action", "S_action_2nd", "S_torso", "C_limb", "fall_rate", "forward_speed",
              "command_vx", "survival_s", "velocity_rmse"):
    assert isinstance(mj[key], float), key
  assert 0.0 <= mj["fall_rate"] <= 1.0 and 0.0 < mj["survival_s"] <= 2.0
  phys = report["physics"]
  assert phys["sim_dt"] == 0.002 and phys["integrator"] == "implicitfast"
  assert phys["iterations"] >= 10 and phys["full_collision"] and phys["ctrl_dt"] == 0.02
  assert report["mjx"]["S_action"] == 0.125 and report["mjx"]["episodes"] == 2
  assert report["checkpoint_iteration"] == runs.load_config(run_copy).train.num_iterations
  assert len(report["per_episode"]) == 1

  md = (run_copy / "sim2sim" / "report.md").read_text()
  assert "| metric | MuJoCo C (sim2sim) | MJX (evaluation) |" in md
  assert "| S_action (1st diff) |" in md and "| 0.125 |" in md

  traj = np.load(run_copy / "sim2sim" / "trajectories.npz")
  assert traj["actions"].shape == (1, 100, 12)  # 2 s at 50 Hz, 12 leg joints
  assert traj["hip_pitch"].shape == traj["hip_pitch_ref"].shape == (1, 100, 2)
  assert traj["base_height"].shape == traj["alive"].shape == (1, 100)
  assert traj["alive"][0, 0] == 1.0


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")
def test_sim2sim_video(run_copy, tmp_path, skip_for_missing_gl):
  video = tmp_path / "clip.mp4"
  env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
  env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
  r = subprocess.run([
      sys.executable, "-m", "experiments.sim2sim", "--run",
      str(run_copy), "--episodes", "1", "--seconds", "0.3", "--video",
      str(video), "--no-mjx"
  ], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
  assert r.returncode == 0, r.stderr[-2000:]
  skipped = [l for l in r.stdout.splitlines() if l.startswith("video skipped: ")]
  if skipped:  # no EGL/OSMesa system library here: the line says which failed
    skip_for_missing_gl(skipped[0])
  import imageio.v2 as imageio
  frames = [f for f in imageio.get_reader(str(video))]
  assert len(frames) >= 5  # the start + one frame every 2 control steps of 15
  assert frames[0].shape == (480, 640, 3) and frames[-1].std() > 1.0  # not a blank image


def test_viewer_needs_display(tmp_path, monkeypatch, capsys):
  from experiments import sim2sim as cli
  monkeypatch.delenv("DISPLAY", raising=False)
  monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
  with pytest.raises(SystemExit) as e:
    cli.main(["--run", str(tmp_path), "--viewer"])
  assert e.value.code == 2
  err = capsys.readouterr().err.strip()
  assert "--viewer needs a display" in err and "\n" not in err


def test_not_a_policy(tmp_path):
  import onnx
  from onnx import TensorProto, helper
  graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g",
                            [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
                            [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])])
  onnx.save(helper.make_model(graph), str(tmp_path / "other.onnx"))
  from mash.deploy import export
  with pytest.raises(export.ExportError, match="no metadata 'joint_order'"):
    sim2sim.Deployment.from_metadata(export.read_metadata(tmp_path / "other.onnx"))
