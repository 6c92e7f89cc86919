"""A tiny multi-agent stand-in for the MJX humanoid: the trainer's interface, no physics.

Each limb is a small set of "joints" (legs 2 each, arms 1 each) that follow a first-order response
to the commanded position, ``q' = q + gain * (a - q)``. Every limb must track a sinusoid driven by
one shared gait phase with the paper's temporal-director offsets (legs 0 / 0.5, each arm in phase
with the opposite leg). The reward is shared (tracking + alive bonus + action-smoothness penalty);
the episode ends by a "fall" when any limb strays too far from its target, or by time-out at a fixed
length.
The env auto-resets inside ``step`` and reports the terminal critic observation in
``info['next_critic_obs']``, exactly like the real env, so the trainer, tests and notebooks run
in seconds on CPU. Like the real env, a non-finite state (inject one by setting ``q`` to NaN in a
state) ends the episode with zero reward and finite observations and sets ``info['nan_reset']``.

Two partitions of the same task: ``'mash'`` (one group per limb type, agents stacked, one-hot ids in
the observations) and ``'ppo'`` (one agent ``'body'`` seeing every limb's observation, no ids).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State

from mash.sim.agents import AgentGroup, action_size


class Limb(NamedTuple):
  """One limb of the toy robot.

  Attributes:
    name: limb name (agent member name).
    group: group it belongs to under the ``'mash'`` partition.
    n_joints: joints (= action dims) of the limb.
    phase_offset: temporal-director offset Delta, in cycles.
    amplitude: amplitude of the target sinusoid.
  """

  name: str
  group: str
  n_joints: int
  phase_offset: float
  amplitude: float


LEGS = (Limb("left_leg", "legs", 2, 0.0, 0.8), Limb("right_leg", "legs", 2, 0.5, 0.8))
ARMS = (Limb("left_arm", "arms", 1, 0.5, 0.5), Limb("right_arm", "arms", 1, 0.0, 0.5))


@dataclasses.dataclass(frozen=True)
class ToyConfig:
  """Toy task constants.

  Attributes:
    episode_length: steps before time-out.
    period: steps per gait cycle.
    gain: first-order response of a joint towards its commanded position per step.
    fall_error: a limb whose tracking error norm exceeds this "falls" (ends the episode).
    tracking_sigma: width of the tracking kernel ``exp(-err^2 / sigma)``.
    alive: reward per step survived.
    smoothness: scale (negative) of the mean squared action change.
    action_clip: commanded positions are clipped to ``[-action_clip, action_clip]``.
    init_noise: std of the initial joint offset from the target (first episode of each env; later
      episodes restart exactly on target).
  """

  episode_length: int = 40
  period: int = 20
  gain: float = 0.5
  fall_error: float = 1.0
  tracking_sigma: float = 0.25
  alive: float = 0.2
  smoothness: float = -0.05
  action_clip: float = 3.0
  init_noise: float = 0.05


@flax.struct.dataclass
class ToyPipelineState:
  """Internal state (the ``pipeline_state`` of the Brax ``State``).

  Attributes:
    q: ``[action_size]`` joint positions.
    prev_action: ``[action_size]`` last (clipped) action.
    phase: ``[]`` gait phase in cycles, in ``[0, 1)``.
    t: ``[]`` int32 steps since reset.
  """

  q: jax.Array
  prev_action: jax.Array
  phase: jax.Array
  t: jax.Array


class ToyEnv:
  """Phase-tracking limbs; see the module docstring.

  Attributes:
    agent_groups: the agent partition (static).
    action_size: flat action size.
    critic_obs_size: critic observation size: all ``q``, all previous actions, the phase
      (sin, cos) and the privileged time fraction ``t / episode_length``.
    config: task constants.
  """

  def __init__(self, limbs: tuple[Limb, ...], partition: str = "mash",
               config: ToyConfig = ToyConfig()):
    if partition not in ("mash", "ppo"):
      raise ValueError(f"partition must be 'mash' or 'ppo', got {partition!r}.")
    self.config = config
    self.partition = partition
    self._limbs = limbs
    starts = np.cumsum([0] + [l.n_joints for l in limbs])
    self._limb_index = tuple(
        tuple(range(int(s),
                    int(s) + l.n_joints)) for s, l in zip(starts, limbs))
    joints = int(starts[-1])
    self._amplitude = np.concatenate([np.full(l.n_joints, l.amplitude) for l in limbs])
    self._offset = np.concatenate([np.full(l.n_joints, l.phase_offset) for l in limbs])
    self._joint_shift = np.concatenate([np.arange(l.n_joints) * 0.5 * np.pi for l in limbs])
    if partition == "mash":
      names = list(dict.fromkeys(l.group for l in limbs))
      groups = []
      for name in names:
        members = [i for i, l in enumerate(limbs) if l.group == name]
        n_joints = limbs[members[0]].n_joints
        groups.append(
            AgentGroup(name=name, members=tuple(limbs[i].name for i in members),
                       obs_dim=2 * n_joints + 2 + len(members), act_dim=n_joints,
                       action_index=tuple(self._limb_index[i] for i in members)))
      self.agent_groups = tuple(groups)
    else:
      self.agent_groups = (AgentGroup(name="body", members=("body",),
                                      obs_dim=sum(2 * l.n_joints + 2 for l in limbs),
                                      act_dim=joints, action_index=(tuple(range(joints)),)),)
    self.action_size = action_size(self.agent_groups)
    self.critic_obs_size = 2 * joints + 3

  def _targets(self, phase: jax.Array) -> jax.Array:
    """``[action_size]`` target joint positions at ``phase``."""
    angle = 2 * jnp.pi * (phase + self._offset) + self._joint_shift
    return self._amplitude * jnp.sin(angle)

  def _limb_obs(self, ps: ToyPipelineState) -> list[jax.Array]:
    out = []
    for limb, idx in zip(self._limbs, self._limb_index):
      idx = np.asarray(idx)
      angle = 2 * jnp.pi * (ps.phase + limb.phase_offset)
      out.append(
          jnp.concatenate([
              ps.q[idx], ps.prev_action[idx],
              jnp.stack([jnp.sin(angle), jnp.cos(angle)])
          ]))
    return out

  def _obs(self, ps: ToyPipelineState) -> dict[str, jax.Array]:
    limb_obs = self._limb_obs(ps)
    if self.partition == "ppo":
      obs = {"body": jnp.concatenate(limb_obs)[None]}
    else:
      obs = {}
      for g in self.agent_groups:
        stacked = jnp.stack([limb_obs[[l.name for l in self._limbs].index(m)] for m in g.members])
        obs[g.name] = jnp.concatenate([stacked, jnp.eye(g.n_agents, dtype=stacked.dtype)], axis=-1)
    obs["critic"] = self._critic_obs(ps)
    return obs

  def _critic_obs(self, ps: ToyPipelineState) -> jax.Array:
    angle = 2 * jnp.pi * ps.phase
    time_fraction = ps.t.astype(jnp.float32) / self.config.episode_length
    return jnp.concatenate([
        ps.q, ps.prev_action,
        jnp.stack([jnp.sin(angle), jnp.cos(angle), time_fraction])
    ])

  def reset(self, key: jax.Array) -> State:
    """Starts an episode at a random phase with the joints near their targets."""
    phase_key, noise_key = jax.random.split(key)
    phase = jax.random.uniform(phase_key, ())
    q = self._targets(phase) + self.config.init_noise * jax.random.normal(
        noise_key, (self.action_size,))
    ps = ToyPipelineState(q=q, prev_action=jnp.zeros_like(q), phase=phase, t=jnp.zeros((),
                                                                                       jnp.int32))
    obs = self._obs(ps)
    zero = jnp.zeros(())
    metrics = {"reward/tracking": zero, "reward/alive": zero, "reward/smoothness": zero}
    info = {"truncation": zero, "next_critic_obs": obs["critic"], "nan_reset": zero}
    return State(pipeline_state=ps, obs=obs, reward=zero, done=zero, metrics=metrics, info=info)

  def step(self, state: State, action: jax.Array) -> State:
    """One control step with auto-reset; ``action [action_size]`` commanded joint positions."""
    cfg = self.config
    ps = state.pipeline_state
    a = jnp.clip(action, -cfg.action_clip, cfg.action_clip)
    q = ps.q + cfg.gain * (a - ps.q)
    phase = jnp.mod(ps.phase + 1.0 / cfg.period, 1.0)
    nxt = ToyPipelineState(q=q, prev_action=a, phase=phase, t=ps.t + 1)

    sq_err = jnp.square(q - self._targets(phase))
    limb_err = jnp.stack([jnp.sum(sq_err[np.asarray(idx)]) for idx in self._limb_index])
    terms = {
        "reward/tracking": jnp.mean(jnp.exp(-limb_err / cfg.tracking_sigma)),
        "reward/alive": jnp.asarray(cfg.alive, jnp.float32),
        "reward/smoothness": cfg.smoothness * jnp.mean(jnp.square(a - ps.prev_action)),
    }
    # A non-finite state is a blow-up: a fall with zero reward, the terminal obs zeroed.
    finite = jnp.all(jnp.isfinite(q))
    terms = {k: jnp.where(finite, v, 0.0) for k, v in terms.items()}
    reward = sum(terms.values())
    fell = jnp.any(limb_err > cfg.fall_error**2) | ~finite
    timeout = nxt.t >= cfg.episode_length
    done = (fell | timeout).astype(jnp.float32)
    truncation = (timeout & ~fell).astype(jnp.float32)

    # Auto-reset without drawing random numbers (keeps the step program small): the next episode
    # starts on its targets at a phase shifted by the golden ratio, so restarts spread over the
    # cycle.
    restart_phase = jnp.mod(phase + 0.618034, 1.0)
    fresh = ToyPipelineState(q=self._targets(restart_phase), prev_action=jnp.zeros_like(q),
                             phase=restart_phase, t=jnp.zeros((), jnp.int32))
    ps_out = jax.tree.map(lambda r, n: jnp.where(done > 0, r, n), fresh, nxt)
    obs = self._obs(ps_out)
    info = {
        "truncation": truncation, "next_critic_obs": jnp.where(finite, self._critic_obs(nxt), 0.0),
        "nan_reset": (~finite).astype(jnp.float32)
    }
    return State(pipeline_state=ps_out, obs=obs, reward=reward, done=done, metrics=terms, info=info)


def make_toy_env(groups: str = "legs", partition: str = "mash",
                 config: ToyConfig = ToyConfig()) -> ToyEnv:
  """Builds the toy env.

  Args:
    groups: ``'legs'`` (2 leg agents) or ``'legs_arms'`` (2 legs + 2 arms).
    partition: ``'mash'`` (limb agents) or ``'ppo'`` (one whole-body agent).
    config: task constants.

  Raises:
    ValueError: unknown ``groups`` or ``partition``.
  """
  limbs = {"legs": LEGS, "legs_arms": LEGS + ARMS}
  if groups not in limbs:
    raise ValueError(f"groups must be 'legs' or 'legs_arms', got {groups!r}.")
  return ToyEnv(limbs[groups], partition, config)
