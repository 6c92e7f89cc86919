"""The env's configuration: the task, its agents, commands and physics, with their sane bounds.

:class:`EnvConfig` is the ``env`` section of a run's ``config.json``; :func:`check_config` checks
one without building anything, and :func:`with_robot_numbers` fills the numbers it leaves to the
robot file.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mash.checks import Bound, check_bounds
from mash.sim import model as model_lib
from mash.sim import randomize, rewards, robots, tasks

PARTITIONS = ("mash", "ppo", "per_limb")  # how the controlled joints split into agents
CRITICS = ("global", "local")


@dataclasses.dataclass(frozen=True)
class CommandConfig:
  """Velocity commands, resampled within episodes.

  Attributes:
    vx: forward speed range (m/s). vy: lateral (m/s). yaw_rate: (rad/s).
    standing_prob: chance a draw is the standing command (phase frozen, zero velocities).
    resample_s: seconds between draws.
  """

  vx: tuple[float, float] = (-0.3, 0.8)
  vy: tuple[float, float] = (-0.2, 0.2)
  yaw_rate: tuple[float, float] = (-0.5, 0.5)
  standing_prob: float = 0.1
  resample_s: float = 8.0


@dataclasses.dataclass(frozen=True)
class EnvConfig:
  """The task, its agents and the physics around them.

  Attributes:
    task: 'bipedal' (legs act, arms held by PD at the default pose) or 'armswing' (all limbs act).
    partition: 'mash' (one group per limb kind: legs share one actor, arms another), 'ppo' (one
      agent controls the whole body: the single-agent baseline), 'per_limb' (each limb its own
      group).
    robot: a shipped robot's name (``robots.names()``: the files of ``mash/assets/robots/``) or the
      path of a robot file (``.toml``).
    ctrl_dt: control period (s); 50 Hz.
    physics: MJX solver settings.
    episode_length: control steps before time-out (20 s).
    action_scale: q_target = q_default + action_scale * action (rad).
    action_clip: |action| bound before scaling.
    gait_cycle_s: period of the temporal director (1/k in the paper's eq.).
    swing_amplitude: leg reference amplitude (rad, times the robot's gait_reference multipliers).
      None (default): the robot's (``RobotSpec.swing_amplitude``). The paper gives none; the
      T1's 0.25 makes the reference knee swing 0.5 rad, the range of the paper's hardware knee
      plot (1.2 to 1.7 rad), and lifts the swing sole 3.8 cm at its peak (kinematics;
      humanoid-gym's 0.17 lifts it 2.2 cm and, played open loop, keeps the foot on the ground
      94 % of the time). ``RewardParams.feet_height_target`` matches it.
    arm_swing_amplitude: shoulder reference amplitude (rad), armswing only; None: the robot's.
    stride_reference: (ours; off by default, the reference bends the swing leg only, whatever the
      command) add to the legs' reference the stride the commanded velocity needs: each foot
      sweeps from ahead at touchdown to behind at lift-off by ``v * gait_cycle_s / 2`` (hip
      pitch for vx, hip roll for vy, hip yaw for the yaw rate, the ankle keeping the sole level;
      ``MashEnv.stride_offsets``), so the joint-position term, the reward's largest, rewards
      walking at the command instead of taxing it.
    stride_feedback: (ours; 0 by default) where the stride reference and the feet-air-time
      term's stride target take their velocity: ``command + k (measured - command)`` in the plane
      (torso frame; the yaw rate stays the command's). 0: the command, as before. 1: the torso's
      own velocity, so the target foothold is the Raibert neutral point; above 1 it also steps
      against the error (Raibert's foot placement), so after a shove the reward asks for the
      catching step instead of taxing it. The actors never see it (the reward and the critic's
      reference error do). Measured on the T1 with kicks at k = 1.5: it walks 40 % slower than
      commanded, since the reference sets the whole swing's amplitude from the plan
      (docs/decisions.md); no preset uses it.
    agent_id: append the one-hot agent id to each agent's observation (ablation switch).
    critic: 'global' (the 106-dim privileged state, MASH) or 'local' (IPPO ablation: the critic
      input is every agent's own observation, zero-padded to the largest and stacked, so a
      per-agent critic sees only its own agent).
    temporal_director: feed the gait phase to the agents (ablation switch: zeros when off).
    actor_history: control steps each agent observes (ours; the paper's actor sees 1, the
      current step). With H > 1 an agent's observation is its last H per-step observations,
      newest first (``[n_agents, H * frame]``; at reset the first frame repeated), so the shared
      actor can read its velocity and the floor's grip from how its joints moved, as
      humanoid-gym's stacked frames do. The critic is unchanged.
    fall_height: root-body height (m) under which the episode ends as a fall; None: the robot's.
    fall_tilt: |roll| or |pitch| (rad) above which the episode ends as a fall.
    commands, randomization, reward_scales, reward_params: see their classes.
    auto_reset: reset finished episodes inside ``step``.

  The sane range of every number is checked by :func:`check_config`.
  """

  task: str = "bipedal"
  partition: str = "mash"
  robot: str = "booster_t1"
  ctrl_dt: float = 0.02
  physics: model_lib.PhysicsConfig = model_lib.PhysicsConfig()
  episode_length: int = 1000
  action_scale: float = 0.25
  action_clip: float = 10.0
  gait_cycle_s: float = 0.64
  swing_amplitude: float | None = None
  arm_swing_amplitude: float | None = None
  stride_reference: bool = False
  stride_feedback: float = 0.0
  agent_id: bool = True
  critic: str = "global"
  temporal_director: bool = True
  actor_history: int = 1
  fall_height: float | None = None
  fall_tilt: float = 1.0
  commands: CommandConfig = CommandConfig()
  randomization: randomize.DomainRandConfig = randomize.DomainRandConfig()
  reward_scales: rewards.RewardScales = rewards.RewardScales()
  reward_params: rewards.RewardParams = rewards.RewardParams()
  auto_reset: bool = True


MAX_ACTOR_HISTORY = 100
MAX_SUBSTEPS = 1000
MAX_COMMAND = 10.0  # m/s or rad/s
MAX_RESAMPLE_S = 1e5
# The sane bounds of EnvConfig's numbers (None: the robot's, with_robot_numbers). ctrl_dt >= 1 ms,
# with at most MAX_SUBSTEPS physics steps per control step and periods of at most 1e5 s, keeps
# every step count of an episode far below int32's limit.
ENV_BOUNDS = (
    Bound("ctrl_dt", 1e-3, 1.0, "s"),
    Bound("episode_length", 1, 2**30, "control steps"),  # 2**30: "never" (Brax's wrapper)
    Bound("action_scale", 0.0, 10.0, "rad", open_low=True),
    Bound("action_clip", 0.0, 1e3, "", open_low=True),
    Bound("gait_cycle_s", 0.0, 10.0, "s", open_low=True),
    Bound("swing_amplitude", 0.0, np.pi, "rad"),
    Bound("arm_swing_amplitude", 0.0, np.pi, "rad"),
    Bound("fall_height", 0.0, 5.0, "m"),
    Bound("fall_tilt", 0.0, np.pi, "rad", open_low=True),
    Bound("stride_feedback", 0.0, 3.0, ""),
    Bound("actor_history", 1, MAX_ACTOR_HISTORY, "control steps"),
)
COMMAND_BOUNDS = (
    Bound("vx", -MAX_COMMAND, MAX_COMMAND, "m/s", pair=True),
    Bound("vy", -MAX_COMMAND, MAX_COMMAND, "m/s", pair=True),
    Bound("yaw_rate", -MAX_COMMAND, MAX_COMMAND, "rad/s", pair=True),
    Bound("standing_prob", 0.0, 1.0),
    Bound("resample_s", 0.0, MAX_RESAMPLE_S, "s", open_low=True),
)


def check_config(config: EnvConfig, robot_given: bool = False) -> None:
  """Checks an :class:`EnvConfig` without building anything (cheap): its choices, every number
  against its sane range (``ENV_BOUNDS`` and each section's own check; NaN and inf never pass) and
  that ``physics.sim_dt`` divides ``ctrl_dt`` into at most ``MAX_SUBSTEPS`` physics steps.

  Args:
    config: the config.
    robot_given: a robot spec is passed alongside, so ``config.robot`` is not looked up.

  Raises:
    ValueError: one line naming the bad field, its value and what was expected.
  """
  for value, allowed, what in ((config.task, tasks.names(), "task"),
                               (config.partition, PARTITIONS, "partition"), (config.critic, CRITICS,
                                                                             "critic")):
    if value not in allowed:
      raise ValueError(f"{what} '{value}' is unknown; expected one of {', '.join(allowed)}")
  if not robot_given:  # the whole robot file, read and checked (cheap: no model is built)
    try:
      spec = robots.load(config.robot)
    except robots.SpecError as e:
      raise ValueError(str(e)) from None
    missing = [k for k in tasks.get(config.task).acting if not spec.limbs_of(k)]
    if missing:
      where = "" if config.robot == spec.name else f" ({config.robot})"
      raise ValueError(f"task '{config.task}' needs limb group '{missing[0]}', which robot "
                       f"'{spec.name}'{where} does not have: train 'bipedal' on it")
  check_bounds(config, ENV_BOUNDS)
  for check, section, part in ((model_lib.check_physics, "physics",
                                config.physics), (check_commands, "commands", config.commands),
                               (randomize.check_config, "randomization", config.randomization),
                               (rewards.check_scales, "reward_scales", config.reward_scales),
                               (rewards.check_params, "reward_params", config.reward_params)):
    try:
      check(part)
    except ValueError as e:
      raise ValueError(f"{section}.{e}") from None
  n_sub = config.ctrl_dt / config.physics.sim_dt
  if abs(n_sub - round(n_sub)) > 1e-9 or round(n_sub) < 1:
    raise ValueError(f"ctrl_dt {config.ctrl_dt} must be a whole multiple of sim_dt "
                     f"{config.physics.sim_dt}")
  if round(n_sub) > MAX_SUBSTEPS:
    raise ValueError(f"ctrl_dt / physics.sim_dt = {config.ctrl_dt} / {config.physics.sim_dt} = "
                     f"{round(n_sub)} physics steps per control step must be at most "
                     f"{MAX_SUBSTEPS}")


def with_robot_numbers(config: EnvConfig, spec: robots.RobotSpec) -> EnvConfig:
  """``config`` with each robot-dependent number it leaves at None taken from the robot's spec:
  the fall height, the legs' and arms' swing amplitudes, the clearance target and the push
  ranges. A number the config sets (a preset, ``--set``, an older run's config.json) stays."""
  pick = lambda value, robot_value: robot_value if value is None else value
  r, p = config.randomization, config.reward_params
  return dataclasses.replace(
      config, fall_height=pick(config.fall_height, spec.fall_height),
      swing_amplitude=pick(config.swing_amplitude, spec.swing_amplitude), arm_swing_amplitude=pick(
          config.arm_swing_amplitude, spec.arm_swing_amplitude), randomization=dataclasses.replace(
              r, push_force=pick(r.push_force, spec.push_force),
              push_torque=pick(r.push_torque, spec.push_torque)), reward_params=dataclasses.replace(
                  p, feet_height_target=pick(p.feet_height_target, spec.feet_height_target)))


def check_commands(commands: CommandConfig) -> None:
  """Checks a :class:`CommandConfig`: each velocity range within +-10 (m/s, rad/s) with lo <= hi,
  a probability in [0, 1], a resampling period in (0, 1e5] s.

  Raises:
    ValueError: one line naming the field, its value and what was expected.
  """
  check_bounds(commands, COMMAND_BOUNDS)
