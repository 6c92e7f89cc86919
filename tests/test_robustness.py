"""The robustness battery in MJX (mash.analysis.robustness): its conditions, the episodes' fixed
perturbations, the summary against hand values, its checks, and one tiny battery of the shipped
T1 policy (one compiled program). The MuJoCo C battery is tested in test_sim2sim.py.
"""

import dataclasses

import numpy as np
import pytest

from mash.analysis import reports, robustness
from mash.sim import robots

SHIPPED = robots.ROBOT_DIR.parent / "policies" / "t1_bipedal_mash"


def test_the_default_battery_is_the_issues_list():
  """Kicks 0.25-1 m/s in 8 directions, three friction bands, torso mass +-20 %, motors at 80 %
  everywhere and 60 % on one leg, IMU and encoder noise, latency 0/20/40 ms, at vx 0.4."""
  cfg = robustness.BatteryConfig()
  assert [c.name for c in robustness.conditions(cfg)] == [
      "kick 0.25 m/s", "kick 0.5 m/s", "kick 0.75 m/s", "kick 1 m/s", "friction 0.1-0.2",
      "friction 0.2-0.3", "friction 0.3-1.2", "torso mass -20 %", "torso mass +20 %",
      "motor strength 80 % (all)", "motor strength 60 % (left leg)", "IMU noise", "encoder noise",
      "latency 0 ms", "latency 20 ms", "latency 40 ms"
  ]
  assert cfg.command_vx == 0.4 and cfg.kick_directions == 8 and cfg.episodes % 8 == 0
  assert {c.group for c in robustness.conditions(cfg)} == set(robustness.GROUPS)


def test_episodes_hand_values():
  """Per condition ``episodes`` rows: kicks spread evenly over the directions, the one-leg motor
  condition weakens only the left leg's joints, latency in whole control steps, the friction
  draws inside their band and the same for the same seed."""
  cfg = robustness.BatteryConfig(episodes=4, kick_directions=4, kick_sizes=(0.5,),
                                 friction_bands=((0.2, 0.3),), torso_mass=(0.2,), latency_ms=(20.0,
                                                                                              30.0))
  conds = robustness.conditions(cfg)
  left = robustness.left_leg_mask(robots.load("booster_t1"))
  assert left.sum() == 6 and left[:6].all()  # the T1's left leg comes first in spec order
  eps = robustness.episodes(conds, cfg, left, 0.02)
  assert eps.kick.shape == (4 * len(conds), 2) and eps.strength.shape == (4 * len(conds), 20)
  np.testing.assert_allclose(eps.kick[:4], [[0.5, 0], [0, 0.5], [-0.5, 0], [0, -0.5]], atol=1e-6)
  np.testing.assert_array_equal(eps.kick[4:], 0.0)
  friction = eps.friction[4:8]
  assert np.all((friction >= 0.2) & (friction <= 0.3)) and np.all(eps.friction[8:] == -1)
  np.testing.assert_allclose(eps.mass[8:12], 1.2)
  one_leg = [i for i, c in enumerate(conds) if c.name.endswith("(left leg)")][0]
  np.testing.assert_allclose(eps.strength[4 * one_leg], np.where(left, 0.6, 1.0))
  assert list(eps.delay[-8:]) == [1] * 4 + [2] * 4  # 20 ms, 30 ms -> round(1.5) = 2 steps
  np.testing.assert_array_equal(robustness.episodes(conds, cfg, left, 0.02).friction, eps.friction)


def test_summarize_hand_values():
  """Survival: the share of episodes alive at the end; speed: the mean over steps alive; per
  kick direction its episodes' survival."""
  cfg = robustness.BatteryConfig(episodes=4, kick_directions=2, kick_sizes=(1.0,),
                                 friction_bands=(), torso_mass=(), latency_ms=())
  conds = robustness.conditions(cfg)[:1]
  alive = np.array([[1, 1, 1], [1, 1, 0], [1, 1, 1], [1, 0, 0]], float)
  speed = np.array([[0.3, 0.4, 0.5], [0.2, 0.2, 9.0], [0.4, 0.4, 0.4], [0.1, 9.0, 9.0]])
  row, = robustness.summarize(conds, alive, speed, cfg)
  assert row["survival"] == 0.5 and row["episodes"] == 4
  assert row["forward_speed"] == pytest.approx((1.2 + 0.4 + 1.2 + 0.1) / 9)
  assert row["survival_by_direction"] == [1.0, 0.0]  # episodes 0, 2 | 1, 3


@pytest.mark.parametrize("change,message", [
    (dict(episodes=12), "episodes 12 must be a multiple of kick_directions 8"),
    (dict(kick_at_s=9.0), "kick_at_s 9.0 must come before the episode ends"),
    (dict(motor_strength_all=0.0), "motor_strength_all"),
])
def test_bad_battery_configs_are_one_line(change, message):
  with pytest.raises(ValueError, match=message):
    robustness.check_config(dataclasses.replace(robustness.BatteryConfig(), **change))


@pytest.mark.slow
def test_a_tiny_battery_of_the_shipped_policy(tmp_path):
  """One compiled program for every condition: without a shove the shipped T1 walks on, a
  10 m/s kick fells it in every direction, motors at 5 % let it sink; figures in range, the
  JSON and the plot written into the policy folder's copy."""
  import shutil
  folder = tmp_path / "t1_bipedal_mash"
  shutil.copytree(SHIPPED, folder)
  cfg = robustness.BatteryConfig(episode_s=1.5, episodes=2, kick_at_s=0.5, kick_sizes=(0.0, 10.0),
                                 kick_directions=2, friction_bands=((0.3, 1.2),), torso_mass=(),
                                 motor_strength_all=0.05, latency_ms=(20.0,))
  result = reports.robustness_run(str(folder), cfg)
  rows = {r["name"]: r for r in result["conditions"]}
  assert list(rows) == [c.name for c in robustness.conditions(cfg)]
  assert rows["kick 0 m/s"]["survival"] == 1.0 and rows["kick 0 m/s"]["forward_speed"] > 0.1
  assert rows["kick 10 m/s"]["survival"] == 0.0
  assert rows["motor strength 5 % (all)"]["survival"] == 0.0
  assert rows["latency 20 ms"]["survival"] == 1.0
  assert all(0 <= r["survival"] <= 1 for r in rows.values())
  assert result["engine"] == "mjx" and result["seeds"] == 1
  assert (folder / "eval_robustness" / "robustness.json").is_file()
  assert (folder / "eval_robustness" / "robustness.png").stat().st_size > 0
