"""The tasks, as data: which limb groups act, which references they follow, and what a task
changes in the env's defaults.

Adding a task is one entry in ``TASKS`` plus its entry point (``experiments/<name>.py`` calling
``mash.runs.launch.train_main("<name>", ...)``); the env, the layout, the presets, evaluation and
compare read the entry and branch on nothing else.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping


@dataclasses.dataclass(frozen=True)
class Task:
  """Attributes:
    name: the task's name (``--task``, ``EnvConfig.task``).
    acting: the robot's limb groups whose joints the policy drives (``robots.Limb.group``), in
      agent order; the other limbs are held at the default pose by their PD loops.
    arm_swing: the arms follow the swing reference (each shoulder with the opposite leg's
      phase, ``EnvConfig.arm_swing_amplitude``); the legs always follow the gait reference.
    commands: overrides of ``EnvConfig.commands`` fields for this task (e.g. ``{"vx": (0.0,
      0.8)}``); empty: the defaults.
    reward_scales: overrides of ``EnvConfig.reward_scales`` fields for this task (e.g.
      ``{"feet_air_time": 2.0}``); empty: the paper's scales.
    description: one line for the help texts.
  """

  name: str
  acting: tuple[str, ...]
  arm_swing: bool = False
  commands: Mapping[str, object] = dataclasses.field(default_factory=dict)
  reward_scales: Mapping[str, float] = dataclasses.field(default_factory=dict)
  description: str = ""

  @property
  def arms_act(self) -> bool:
    return "arms" in self.acting


TASKS: dict[str, Task] = {
    "bipedal":
        Task("bipedal", acting=("legs",),
             description="two leg agents walk; the arms are held at the default pose"),
    "armswing":
        Task("armswing", acting=("legs", "arms"), arm_swing=True,
             description="two leg and two arm agents; each arm swings with the opposite "
             "leg"),
}


def names() -> tuple[str, ...]:
  """The tasks' names, in ``TASKS`` order (read each call, so an entry added to ``TASKS`` is
  known everywhere)."""
  return tuple(TASKS)


def get(name: str) -> Task:
  """The task called ``name``; ValueError (one line) naming the known ones otherwise."""
  if name not in TASKS:
    raise ValueError(f"task '{name}' is unknown; expected one of {', '.join(names())}")
  return TASKS[name]
