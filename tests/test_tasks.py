"""Tasks as data (mash.sim.tasks): an entry names its acting limb groups, its references, its
command ranges and reward-scale overrides, and the layout, the env's reference and the presets
follow it with no other change."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from mash.runs import experiment
from mash.sim import env as env_lib
from mash.sim import env_config, layout, robots, tasks

T1 = robots.load("booster_t1")


@pytest.fixture
def arms_free(monkeypatch):
  """A task added as one entry: all four limbs act, the arms without a swing reference, a
  narrower forward range and a doubled air-time reward."""
  task = tasks.Task("arms_free", acting=("legs", "arms"), arm_swing=False,
                    commands={"vx": (0.0, 0.5)}, reward_scales={"feet_air_time": 2.0})
  monkeypatch.setitem(tasks.TASKS, task.name, task)
  return task


def test_the_two_tasks_as_the_paper_has_them():
  assert tasks.names() == ("bipedal", "armswing")
  assert tasks.get("bipedal").acting == ("legs",) and not tasks.get("bipedal").arm_swing
  assert tasks.get("armswing").acting == ("legs", "arms") and tasks.get("armswing").arm_swing
  with pytest.raises(ValueError, match=r"^task 'swim' is unknown; expected one of bipedal, "
                     r"armswing$"):
    tasks.get("swim")


def test_a_new_task_is_one_entry(arms_free):
  cfg = experiment.make_config("arms_free", "mash", "smoke")
  assert cfg.env.commands.vx == (0.0, 0.5) and cfg.env.commands.vy == (-0.2, 0.2)
  assert cfg.env.reward_scales.feet_air_time == 2.0
  assert cfg.env.reward_scales.joint_pos == env_config.EnvConfig().reward_scales.joint_pos
  lay = layout.build(T1, cfg.env)
  assert [g.name for g in lay.groups] == ["legs", "arms"] and lay.n_actions == 20
  # The reference: the legs swing, the arms (no swing reference in this task) hold still.
  env = env_lib.MashEnv(cfg.env)
  q_ref, _ = env.gait(jnp.asarray(0.25), jnp.asarray(0.0))
  arms = np.array([
      i for i, j in enumerate(lay.joints)
      if any(j in l.joints for l in T1.limbs if l.group == "arms")
  ])
  legs = np.setdiff1d(np.arange(lay.n_joints), arms)
  assert np.all(np.asarray(q_ref)[arms] == 0.0) and np.any(np.asarray(q_ref)[legs] != 0.0)
  swing = env_lib.MashEnv(dataclasses.replace(cfg.env, task="armswing"))
  q_swing, _ = swing.gait(jnp.asarray(0.25), jnp.asarray(0.0))
  assert np.any(np.asarray(q_swing)[arms] != 0.0)
