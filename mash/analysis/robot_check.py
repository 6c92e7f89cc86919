"""A robot file checked against its model before anyone trains on it.

:func:`check` reads the file (every name checked against the MJCF), builds the model, compares
the file's mirror signs with the joint axes, holds the default pose at zero action for a few
seconds in MuJoCo C and in MJX (does it stand?), plays one gait cycle of the reference open loop
(each foot's clearance, left against right; each joint's reference range against its limits),
measures each foot's frame (which of its axes points forward and which up) and, where OpenGL
renders, draws the default pose and both swing peaks. Each finding that would spoil training is
an error naming the field to change; ``python -m experiments.robot check FILE`` prints them.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from PIL import Image

from mash.deploy import video as video_lib
from mash.sim import env as env_lib
from mash.sim import env_config, geometry, randomize, robots
from mash.sim import layout as layout_lib
from mash.sim import model as model_lib

# Left and right swing peaks must lift their soles alike: within this share of the higher.
CLEARANCE_TOLERANCE = 0.25
STANDS_HEIGHT = 0.9  # standing: the torso ends above this share of its start height
STANDS_TILT = 0.3  # rad: and tilts less than this


class Finding(NamedTuple):
  """One result of the check: ``level`` 'error' (training would be spoiled), 'warning' or 'ok';
  ``field``: the robot file's field to change (None when none is to blame); ``text``: one line."""

  level: str
  field: str | None
  text: str


def stand_native(spec: robots.RobotSpec, seconds: float) -> np.ndarray:
  """``[T]`` the torso's height (m) every 20 ms while the PD loop holds the default pose at zero
  action in MuJoCo C (2 ms steps, implicit-fast, 10 Newton iterations, full collision)."""
  physics = model_lib.PhysicsConfig(sim_dt=0.002, iterations=10, ls_iterations=10,
                                    integrator="implicitfast")
  m = model_lib.build_model(spec, physics, full_collision=True)
  d = mujoco.MjData(m)
  mujoco.mj_resetDataKeyframe(m, d, m.key("home").id)
  ids = [m.joint(j).id for j in spec.joints]
  qadr, dadr = m.jnt_qposadr[ids], m.jnt_dofadr[ids]
  act = np.array([m.actuator(j).id for j in spec.joints])
  q0 = np.array([spec.default_pose[j] for j in spec.joints])
  kp, kd = (np.array([table[j] for j in spec.joints]) for table in (spec.kp, spec.kd))
  limit = np.array([spec.torque_limit[j] for j in spec.joints])
  heights = []
  for step in range(int(round(seconds / physics.sim_dt))):
    d.ctrl[act] = np.clip(kp * (q0 - d.qpos[qadr]) - kd * d.qvel[dadr], -limit, limit)
    mujoco.mj_step(m, d)
    if step % 10 == 9:
      heights.append(d.qpos[2])
  return np.array(heights)


def stand_mjx(spec_file: str, seconds: float) -> tuple[np.ndarray, np.ndarray]:
  """``([T] torso height above the soles (m), [T] |tilt| (rad))`` every control step while the
  env holds the default pose at zero action in MJX, randomization off."""
  cfg = env_config.EnvConfig(
      robot=spec_file, auto_reset=False, episode_length=2**30,
      randomization=dataclasses.replace(randomize.DomainRandConfig(), enabled=False))
  env = env_lib.MashEnv(cfg)
  steps = int(round(seconds / env.dt))

  def run(key):

    def step(state, _):
      state = env.step(state, jnp.zeros(env.action_size))
      s = env.sensors(state.pipeline_state)
      return state, (s["base_height"], jnp.max(jnp.abs(s["euler"][:2])))

    return jax.lax.scan(step, env.reset(key, command=jnp.array([1.0, 0, 0, 0])), None, steps)[1]

  height, tilt = jax.device_get(jax.jit(run)(jax.random.PRNGKey(0)))
  return np.asarray(height), np.asarray(tilt)


def _stands(name: str, height: np.ndarray, tilt: np.ndarray | None, seconds: float,
            fall_height: float) -> Finding:
  """Whether a stand test stood: the torso above ``STANDS_HEIGHT`` of its start and the fall
  height, level within ``STANDS_TILT``."""
  end = float(height[-1])
  low = float(height.min())
  tilted = tilt is not None and float(tilt.max()) > STANDS_TILT
  if low < fall_height or end < STANDS_HEIGHT * float(height[0]) or tilted:
    when = int(np.argmax(height < max(fall_height, STANDS_HEIGHT * float(height[0]))))
    return Finding(
        "error", "roles.*.kp / roles.*.default",
        f"{name}: does not stand at zero action: the torso goes from "
        f"{height[0]:.3f} m to {end:.3f} m (lowest {low:.3f}; below the bar after "
        f"{when * seconds / len(height):.1f} s): stiffer gains or a pose with the "
        "centre of mass over the feet")
  return Finding(
      "ok", None, f"{name}: stands {seconds:g} s at zero action (torso "
      f"{height[0]:.3f} -> {end:.3f} m)")


def gait_cycle(spec: robots.RobotSpec, model: mujoco.MjModel, config: env_config.EnvConfig,
               n: int = 64) -> dict[str, np.ndarray]:
  """One cycle of the reference played open loop with the torso held at its home pose:
  ``phase [n]``, ``q [n, J]`` (rad, absolute), ``sole [n, 2]``, each foot's lowest sole point
  above the floor (m), and ``stance [2]``, the same at the default pose."""
  ref_scale, ref_limb = env_lib.reference_scales(spec, env_config.with_robot_numbers(config, spec))
  offsets = np.array([layout_lib.phase_offset(l) for l in spec.limbs])
  is_leg = np.array([spec.limbs[i].group == "legs" for i in ref_limb])
  d = mujoco.MjData(model)
  home = model.key("home").qpos.copy()
  ids = [model.joint(j).id for j in spec.joints]
  qadr = model.jnt_qposadr[ids]
  soles = [[model.geom(f"{side}_sole_{k}").id
            for k in range(len(spec.sole_points[0]))]
           for side in ("left", "right")]

  def lowest(q):
    d.qpos[:] = home
    d.qpos[qadr] = q
    mujoco.mj_kinematics(model, d)
    return [d.geom_xpos[g][:, 2].min() - spec.sole_radius for g in soles]

  phases = np.arange(n) / n
  qs = [
      home[qadr] + ref_scale * np.where(is_leg, np.maximum(s, 0.0), s)
      for s in np.sin(2 * np.pi * (phases[:, None] + offsets))[:, ref_limb]
  ]
  return {
      "phase": phases, "q": np.array(qs), "sole": np.array([lowest(q) for q in qs]),
      "stance": np.array(lowest(home[qadr]))
  }


def clearance_findings(cycle: dict[str, np.ndarray], target: float) -> list[Finding]:
  """Each foot's swing peak above its height at the default pose, against the other's and the
  clearance reward's target."""
  peak = (cycle["sole"] - cycle["stance"]).max(axis=0)
  text = f"swing clearance: left {100 * peak[0]:.1f} cm, right {100 * peak[1]:.1f} cm"
  if abs(peak[0] - peak[1]) > CLEARANCE_TOLERANCE * max(peak.max(), 1e-6):
    return [
        Finding(
            "error", "roles.<pitch roles>.mirror",
            f"{text}: the feet lift differently (more than {CLEARANCE_TOLERANCE:.0%} "
            "apart): a right joint's reference turns the wrong way")
    ]
  out = [Finding("ok", None, f"{text} (they match within {CLEARANCE_TOLERANCE:.0%})")]
  if not 0.5 * target <= peak.mean() <= 2.0 * target:
    out.append(
        Finding(
            "warning", "task.feet_height_target",
            f"the clearance reward's target {100 * target:.1f} cm is far from the "
            f"reference's {100 * peak.mean():.1f} cm: match task.swing_amplitude and "
            "task.feet_height_target"))
  return out


def limit_findings(spec: robots.RobotSpec, model: mujoco.MjModel,
                   cycle: dict[str, np.ndarray]) -> list[Finding]:
  """Each joint's default and reference range against the joint's limits in the MJCF."""
  out = []
  for k, joint in enumerate(spec.joints):
    jid = model.joint(joint).id
    if not model.jnt_limited[jid]:
      continue
    lo, hi = model.jnt_range[jid]
    q = cycle["q"][:, k]
    role = spec.role_of(joint)
    if not lo <= spec.default_pose[joint] <= hi:
      out.append(
          Finding(
              "error", f"roles.{role}.default",
              f"joint '{joint}': default {spec.default_pose[joint]:+.3f} rad is outside "
              f"its limits [{lo:+.3f}, {hi:+.3f}]"))
    elif q.min() < lo - 1e-6 or q.max() > hi + 1e-6:
      out.append(
          Finding(
              "error", "task.swing_amplitude",
              f"joint '{joint}' ({role}): the reference swings over "
              f"[{q.min():+.3f}, {q.max():+.3f}] rad, beyond its limits "
              f"[{lo:+.3f}, {hi:+.3f}]"))
  if not out:
    out.append(
        Finding("ok", None, "every joint's default pose and reference lie within its "
                "limits"))
  return out


def foot_axes(spec: robots.RobotSpec, model: mujoco.MjModel) -> dict[str, dict[str, list]]:
  """Per foot, the world's forward (x) and up (z) directions in the foot's own frame at the
  default pose: what a file's sole points are given in."""
  d = mujoco.MjData(model)
  d.qpos[:] = model.key("home").qpos
  mujoco.mj_kinematics(model, d)
  out = {}
  for side, foot in zip(("left", "right"), spec.feet):
    rot = d.xmat[model.body(foot).id].reshape(3, 3)  # foot frame -> world
    out[side] = {"forward": np.round(rot[0], 3).tolist(), "up": np.round(rot[2], 3).tolist()}
  return out


def picture(spec: robots.RobotSpec, model: mujoco.MjModel, cycle: dict[str, np.ndarray],
            path: Path) -> str | None:
  """Draws the default pose and both swing peaks side by side into ``path`` (PNG); returns why
  it could not (no headless OpenGL), or None."""
  backend, reason = video_lib.headless_gl()
  if backend is None:
    return reason
  peaks = [int(np.argmax(cycle["sole"][:, side])) for side in (0, 1)]
  d = mujoco.MjData(model)
  ids = [model.joint(j).id for j in spec.joints]
  writer = video_lib.VideoWriter(model, path.with_suffix(".gif"), 1.0,
                                 model.body(spec.root_body).id, 480, 400, backend)
  writer.camera.azimuth, writer.camera.elevation = 150.0, -10.0
  frames = []
  try:
    for q in (model.key("home").qpos[model.jnt_qposadr[ids]], *cycle["q"][peaks]):
      d.qpos[:] = model.key("home").qpos
      d.qpos[model.jnt_qposadr[ids]] = q
      mujoco.mj_forward(model, d)
      frames.append(writer.render(d))
  finally:
    writer.close()
  Image.fromarray(np.concatenate(frames, axis=1)).save(path)
  return None


def check(robot: str, seconds: float = 10.0, out: Path | None = None,
          mjx: bool = True) -> tuple[list[Finding], dict[str, Any]]:
  """Every check of the module docstring on the robot file ``robot`` (a path or a shipped name);
  writes ``out/<name>_check.json`` and ``<name>_check.png`` when ``out`` is given.

  Returns:
    ``(findings, record)``: the findings in order, and what was measured (JSON-ready).

  Raises:
    mash.sim.robots.SpecError: the file cannot be read (one line naming the field).
  """
  spec = robots.load(robot)
  config = env_config.EnvConfig(robot=robot)
  findings = [
      Finding(
          "ok", None, f"read {robots.robot_file(robot)}: {len(spec.limbs)} limbs, "
          f"{len(spec.joints)} joints, every name in the model")
  ]
  model = model_lib.build_model(spec)
  wrong = geometry.mirror_mismatches(model, spec)
  findings += [Finding("error", w.split(" ")[0], w) for w in wrong]
  if not wrong:
    findings.append(Finding("ok", None, "mirror signs match the joint axes"))
  robot_numbers = env_config.with_robot_numbers(config, spec)
  native = stand_native(spec, seconds)
  findings.append(_stands("MuJoCo C", native, None, seconds, robot_numbers.fall_height))
  record: dict[str, Any] = {
      "robot": spec.name, "file": str(robots.robot_file(robot)),
      "stand_native_height": native[::5].round(4).tolist()
  }
  if mjx:
    height, tilt = stand_mjx(robot, seconds)
    findings.append(_stands("MJX", height, tilt, seconds, robot_numbers.fall_height))
    record["stand_mjx_height"] = height[::5].round(4).tolist()
  cycle = gait_cycle(spec, model, config)
  findings += clearance_findings(cycle, robot_numbers.reward_params.feet_height_target)
  findings += limit_findings(spec, model, cycle)
  record.update(foot_axes=foot_axes(spec, model), stride=geometry.stride_plan(spec),
                clearance_cm=(100 * (cycle["sole"] - cycle["stance"]).max(0)).round(2).tolist(),
                findings=[f._asdict() for f in findings])
  findings.append(Finding("ok", None, f"stride reference: {record['stride']}"))
  if out is not None:
    out.mkdir(parents=True, exist_ok=True)
    skipped = picture(spec, model, cycle, out / f"{spec.name}_check.png")
    if skipped:
      findings.append(Finding("warning", None, f"no picture: {skipped}"))
    (out / f"{spec.name}_check.json").write_text(json.dumps(record, indent=2))
  return findings, record
