"""Command tracking: the metrics against a hand computation, and ``evaluate --tracking`` end to end
on the smoke run (one more compiled MJX rollout: the grid's 11 episodes)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mash.analysis import evaluation


def _hand_trajectory():
  """Two commands x two episodes x 4 steps, built so every figure is hand-computable."""
  commands = np.array([[0, 0.4, 0, 0], [0, 0.4, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0]], np.float32)
  world = np.zeros((4, 4, 3))
  yaw = np.zeros((4, 4))
  alive = np.ones((4, 4))
  # Episode 0 faces +y (yaw pi/2) and moves along world +y at 0.3 m/s, turning at 0.1 rad/s:
  # forward speed 0.3 in its heading frame, no sideways speed.
  yaw[0] = np.pi / 2
  world[0] = [0.0, 0.3, 0.1]
  # Episode 1 faces +x, moves at 0.5 then 0.5, then falls: steps 2-3 (0 m/s) are not counted.
  world[1, :2] = [0.5, 0.1, 0.0]
  alive[1, 2:] = 0
  # Episode 2 (standing) faces -x (yaw pi) and drifts along world -x at 0.04 m/s and world +y at
  # 0.03 m/s: heading frame vx = +0.04, vy = -0.03, speed 0.05.
  yaw[2] = np.pi
  world[2] = [-0.04, 0.03, 0.0]
  # Episode 3 (standing) stands still.
  return {"world_velocity": world, "euler": np.stack([0 * yaw, 0 * yaw, yaw], -1),
          "alive": alive}, commands


def test_tracking_against_a_hand_computation():
  traj, commands = _hand_trajectory()
  out = evaluation.tracking(traj, commands)
  walk, stand = out["grid"]
  assert walk["command"] == [0.0, pytest.approx(0.4), 0.0, 0.0] and walk["episodes"] == 2
  assert stand["command"] == [1.0, 0.0, 0.0, 0.0] and stand["episodes"] == 2
  # Walking: episode means (0.3, 0, 0.1) over 4 steps and (0.5, 0.1, 0) over 2 steps alive.
  # Pooled over the 6 steps alive: vx (4*0.3 + 2*0.5)/6 = 2.2/6, vy 0.2/6, yaw 0.4/6.
  assert walk["vx"] == pytest.approx(2.2 / 6)
  assert walk["vy"] == pytest.approx(0.2 / 6)
  assert walk["yaw_rate"] == pytest.approx(0.4 / 6)
  # |error| per episode, then the mean: vx (0.1 + 0.1)/2, vy (0 + 0.1)/2, yaw (0.1 + 0)/2.
  assert walk["abs_error"]["vx"] == pytest.approx(0.1)
  assert walk["abs_error"]["vy"] == pytest.approx(0.05)
  assert walk["abs_error"]["yaw_rate"] == pytest.approx(0.05)
  assert walk["fall_rate"] == pytest.approx(0.5)
  assert walk["episode_std"]["vx"] == pytest.approx(0.1)  # episode means 0.3 and 0.5
  # Standing: episode means (0.04, -0.03, 0) and 0: pooled vx 0.02, vy -0.015.
  assert stand["vx"] == pytest.approx(0.02) and stand["vy"] == pytest.approx(-0.015)
  assert stand["abs_error"]["vx"] == pytest.approx(0.02)
  assert stand["abs_error"]["vy"] == pytest.approx(0.015)
  assert stand["fall_rate"] == 0.0
  # Grid means of the per-command errors; falls over all 4 episodes; drift (0.05 + 0) / 2.
  assert out["mean_abs_error"]["vx"] == pytest.approx((0.1 + 0.02) / 2)
  assert out["mean_abs_error"]["vy"] == pytest.approx((0.05 + 0.015) / 2)
  assert out["mean_abs_error"]["yaw_rate"] == pytest.approx(0.025)
  assert out["fall_rate"] == pytest.approx(0.25)
  assert out["standing_drift"] == pytest.approx(0.025)
  # Reach: the walking command (0.4, 0, 0) pooled 2.2/6 m/s; no one-axis vy or yaw command.
  assert out["reach"]["vx"] == pytest.approx(2.2 / 6 / 0.4)
  assert out["reach"]["vy"] is None and out["reach"]["yaw_rate"] is None


def test_reach_averages_the_one_axis_commands_and_skips_the_rest():
  """Turning at 0.1 of +0.5 and -0.2 of -0.5 rad/s reaches (0.2 + 0.4) / 2 = 0.3; the mixed,
  standing and zero commands count for no axis."""

  def entry(command, vx=0.0, vy=0.0, yaw=0.0):
    return {"command": command, "vx": vx, "vy": vy, "yaw_rate": yaw}

  grid = [
      entry([1, 0, 0, 0], vx=0.3),
      entry([0, 0, 0, 0], vx=0.1),
      entry([0, 0, 0, 0.5], yaw=0.1),
      entry([0, 0, 0, -0.5], yaw=-0.2),
      entry([0, 0.4, 0, 0.5], vx=0.0, yaw=0.0),
      entry([0, -0.3, 0, 0], vx=-0.15),
      entry([0, 0.8, 0, 0], vx=0.8)
  ]
  reach = evaluation.command_reach(grid)
  assert reach["yaw_rate"] == pytest.approx(0.3)
  assert reach["vx"] == pytest.approx((0.5 + 1.0) / 2)
  assert reach["vy"] is None


def test_heading_velocity_turns_with_the_yaw_alone():
  """World (1, 0) seen from a heading of +45 degrees: (cos 45, -sin 45); the yaw rate is kept."""
  v = evaluation.heading_velocity(np.array([1.0, 0.0, 0.3]), np.array(np.pi / 4))
  np.testing.assert_allclose(v, [np.sqrt(0.5), -np.sqrt(0.5), 0.3], atol=1e-12)


def test_tracking_grid_covers_the_issue_commands():
  grid = np.asarray(evaluation.TRACKING_GRID)
  assert [1, 0, 0, 0] in grid.tolist()
  walking = grid[grid[:, 0] == 0]
  forward = sorted(walking[(walking[:, 2] == 0) & (walking[:, 3] == 0), 1].tolist())
  assert forward == pytest.approx([-0.3, 0.0, 0.2, 0.4, 0.6, 0.8])
  assert sorted(walking[walking[:, 2] != 0, 2].tolist()) == pytest.approx([-0.2, 0.2])
  assert sorted(walking[walking[:, 3] != 0, 3].tolist()) == pytest.approx([-0.5, 0.5])
  cmds = evaluation.tracking_commands(3)
  assert cmds.shape == (3 * len(grid), 4) and np.all(cmds[:3] == grid[0])


@pytest.mark.slow
def test_evaluate_tracking_writes_the_grid(smoke_run):
  """``evaluate --tracking`` on the smoke run: one entry per grid command with the issue's keys,
  the plot, and trajectories from which the figures are recomputed."""
  from mash.analysis.reports import tracking_run
  cfg = evaluation.EvalConfig(num_episodes=1, episode_s=0.2)
  result = tracking_run(str(smoke_run), cfg)
  out = smoke_run / "eval_tracking"
  data = json.loads((out / "tracking.json").read_text())
  assert set(data) >= {"grid", "mean_abs_error", "fall_rate", "standing_drift", "reach"}
  assert len(data["grid"]) == len(evaluation.TRACKING_GRID)
  for g, command in zip(data["grid"], evaluation.TRACKING_GRID):
    assert g["command"] == pytest.approx(list(command))
    assert set(g) >= {"command", "episodes", "fall_rate", "vx", "vy", "yaw_rate"}
    assert g["episodes"] == 1
  assert set(data["mean_abs_error"]) == {"vx", "vy", "yaw_rate"}
  assert data["standing_drift"] is not None and data["iteration"] == 10
  assert (out / "tracking.png").stat().st_size > 0
  npz = np.load(out / "tracking_trajectories.npz")
  assert npz["velocity"].shape == (len(evaluation.TRACKING_GRID), 10, 3)
  assert npz["commands"].shape == (len(evaluation.TRACKING_GRID), 4)
  alive = npz["alive"]
  ep = (npz["velocity"] * alive[..., None]).sum(1) / np.maximum(alive.sum(1), 1)[:, None]
  assert result["grid"][4]["vx"] == pytest.approx(float(ep[4, 0]), rel=1e-5, abs=1e-6)
  # The env ran each episode on its grid command to the end.
  np.testing.assert_allclose(npz["commands"], evaluation.tracking_commands(1))
