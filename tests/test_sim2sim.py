"""Sim-to-sim in MuJoCo C: the CLI on the smoke run (report, comparison table, video) and helpers.

Kept short: one 2 s episode in process, the video from a subprocess (``MUJOCO_GL`` must be chosen
before mujoco is imported, and this test process imported it long ago), no MJX evaluation (a
stand-in ``eval/metrics.json`` exercises the comparison table).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mash.runs import loop as runs
from mash.deploy import sim2sim
from mash.sim import geometry

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def run_copy(smoke_run, tmp_path_factory):
  """A private copy of the smoke run (sim2sim writes policy.onnx and sim2sim/ into it)."""
  out = tmp_path_factory.mktemp("sim2sim") / "run"
  shutil.copytree(smoke_run, out, ignore=shutil.ignore_patterns("eval", "sim2sim", "policy.onnx"))
  return out


def test_quat_to_euler_matches_env():
  rng = np.random.default_rng(0)
  for _ in range(20):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    np.testing.assert_allclose(sim2sim.quat_to_euler(q), np.asarray(geometry.quat_to_euler(q)),
                               atol=1e-5)


def test_sim2sim_report(run_copy, capsys):
  from experiments import sim2sim as cli
  # A stand-in MJX evaluation: the report must carry its numbers into the table.
  (run_copy / "eval").mkdir()
  fake = {"S_action": 0.125, "S_action_2nd": 0.0625, "S_torso": 0.01, "C_limb": 0.5,
          "fall_rate": 0.25, "forward_speed": 0.375, "command_vx": 0.4, "T_conv": 3.0,
          "eval_config": {"num_episodes": 2, "episode_s": 1.0, "randomization": True}}
  (run_copy / "eval" / "metrics.json").write_text(json.dumps(fake))
  cli.main(["--run", str(run_copy), "--episodes", "1", "--seconds", "2"])
  text = capsys.readouterr().out
  assert "exported" in text and "episode 1/1:" in text

  report = json.loads((run_copy / "sim2sim" / "report.json").read_text())
  for key in ("run", "onnx", "checkpoint_iteration", "command_vx", "episodes", "episode_s",
              "physics", "mujoco", "mjx", "mjx_source", "per_episode", "wall_s",
              "realtime_factor"):
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
  r = subprocess.run([sys.executable, "-m", "experiments.sim2sim", "--run", str(run_copy),
                      "--episodes", "1", "--seconds", "0.3", "--video", str(video), "--no-mjx"],
                     cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
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
