"""The deployable policy of a trained run as one ONNX graph, built by hand with ``onnx.helper``.

The graph holds everything between the robot's sensors and its joint targets, so a hardware or
MuJoCo C controller needs no Python from this package (SPEC §4 observation layout):

  inputs (float32, leading batch dim ``N``; use ``N = 1`` on a robot):
    ``q [N, J]``            absolute joint angles (rad) of ALL actuated joints, ``spec.joints``
                            order
    ``dq [N, J]``           joint velocities (rad/s), same order
    ``last_action [N, A]``  the previous ``action`` output (zeros at start)
    ``gait_phase [N, 1]``   gait clock in cycles, [0, 1); advances ``ctrl_dt / gait_cycle_s`` per
                            control step, frozen while the standing flag of ``command`` is 1
    ``euler [N, 3]``        torso roll, pitch, yaw (rad; ZYX convention)
    ``ang_vel [N, 3]``      torso angular velocity in the torso frame (rad/s)
    ``command [N, 4]``      standing flag (0/1), vx (m/s), vy (m/s), yaw rate (rad/s)
  outputs:
    ``action [N, A]``       policy mean in flat action order (the controlled joints); feed it back
                            as ``last_action`` next step
    ``q_target [N, A]``     PD position targets (rad) of the controlled joints:
                            ``default + action_scale * clip(action, -action_clip, action_clip)``

Inside: each limb's sin/cos phase with the env's offsets (legs 0 / 0.5, each arm with the opposite
leg), one feature row
``[q - default | dq | last_action | sin | cos | euler | ang_vel | command | 0 | 1]`` from which
every agent's observation is one ``Gather`` (joints of its limb, its phase, the one-hot id from the
constant columns), the running-statistics normalization, each group's shared actor MLP
(``MatMul``/``Add``/``Elu``) applied to all agents of the group at once, and the scatter of
per-agent actions into flat order. Joint order, units, control rate, default pose, PD gains and
action scale are in the model's ``metadata_props`` (:func:`read_metadata`).

Why by hand, not traced from the JAX policy (tried with jax 0.10.2, issue 25): jax2onnx >= 0.13.1
requires orbax-checkpoint < 0.11.37, against our >= 0.12; 0.13.0, which pip picks instead, fails on
jax 0.10 (``batching.not_mapped``); and 0.17.1 without its pins cannot batch Flax ``Dense`` (the
per-agent actors) and writes a ``OneHot`` of a scalar (the agent id) that onnxruntime rejects.
What keeps this graph from drifting is :func:`verify`: it compares the file with the env's own
``observe`` and the trained actors, to 1e-5.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import flax.traverse_util
import jax
import jax.numpy as jnp
import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

from mash.deploy import policy as policy_lib
from mash.errors import InputError
from mash.rl import networks as nets
from mash.rl import normalization
from mash.sim import agents
from mash.sim import env as env_lib
from mash.sim import layout as layout_lib

OPSET = 17
IR_VERSION = 8  # the IR of opset 17: loads in onnxruntime >= 1.11 and most embedded runtimes
INPUTS = ("q", "dq", "last_action", "gait_phase", "euler", "ang_vel", "command")
OUTPUTS = ("action", "q_target")


class ExportError(InputError):
  """A run that cannot be exported as asked (one line)."""


class PolicyParts(NamedTuple):
  """What the graph is built from: one seed's actors of a run.

  Attributes:
    env: the run's ``MashEnv`` (observation layout, joint tables, config).
    networks: its ``Networks`` (the JAX reference applies them).
    params: that seed's params ``{'actors': ...}`` (a ``'critic'`` entry beside it is unused).
    normalizer: that seed's ``{stream: RunningStats}``, or None (no normalization).
    obs_clip: clip of normalized observations.
    share_actor: one actor per group (else one per agent: the no-sharing ablation).
    meta: extra metadata (run, iteration, seed, task, algo).
  """

  env: Any
  networks: Any
  params: Any
  normalizer: Any
  obs_clip: float
  share_actor: bool
  meta: Mapping[str, Any]


def policy_parts(policy, env=None) -> PolicyParts:
  """The parts of a :class:`mash.deploy.policy.Policy` (``env``: a ``MashEnv`` of its config, built
  when None)."""
  cfg = policy.config
  env = env_lib.MashEnv(cfg.env) if env is None else env
  normalizer = None
  if policy.normalizer is not None and cfg.train.normalize_observations:
    normalizer = jax.device_get(policy.normalizer)
  meta = {
      "task": cfg.task, "algo": cfg.algo, "ablation": cfg.ablation,
      "checkpoint_iteration": int(policy.iteration), "seed": int(policy.seed)
  }
  return PolicyParts(env, policy_lib.actor_networks(policy, env), jax.device_get(policy.params),
                     normalizer, float(cfg.train.obs_clip), bool(cfg.train.share_actor), meta)


# ------------------------------------------------------------------------------- layout tables
class Layout(NamedTuple):
  """Where every observation entry comes from in the feature row (see module docstring).

  Attributes:
    n_joints: J. n_actions: A. n_limbs: L.
    width: width of the feature row.
    zero: column that is always 0. one: column that is always 1.
    obs_index: ``{group: int64 [n_agents, obs_dim]}`` feature columns of each agent observation.
    phase_offset: ``[L]`` limb phase offsets (cycles).
  """

  n_joints: int
  n_actions: int
  n_limbs: int
  width: int
  zero: int
  one: int
  obs_index: dict[str, np.ndarray]
  phase_offset: np.ndarray


def feature_segments(lay: layout_lib.Layout) -> layout_lib.Segments:
  """The graph's feature row ``[q - default | dq | last_action | sin | cos | euler | ang_vel |
  command | 0 | 1]`` (one sin and one cos per limb, ``lay.limbs`` order) as named segments."""
  J, A, L = lay.n_joints, lay.n_actions, lay.n_limbs
  seg = layout_lib.Segment
  return layout_lib.Segments(
      (seg("q", J), seg("dq", J), seg("last_action", A), seg("sin", L), seg("cos", L),
       seg("euler", 3), seg("ang_vel", 3), seg("command", layout_lib.COMMAND_SIZE), seg("zero", 1),
       seg("one", 1)))


def layout(env) -> Layout:
  """The gather tables reproducing ``MashEnv.observe`` for every agent group of ``env``: each
  segment of ``env.layout.actor[group]`` read from its columns of the feature row."""
  cfg, lay = env.config, env.layout
  if cfg.actor_history != 1:
    raise ExportError(f"env.actor_history={cfg.actor_history}: the ONNX graph takes one step's "
                      "signals, and a policy that reads several steps cannot be exported yet")
  features = feature_segments(lay)
  col = {name: list(range(*span)) for name, span in features.offsets().items()}
  zero, one = col["zero"][0], col["one"][0]
  ctrl = [int(i) for i in lay.controlled]
  pos_in_action = {j: k for k, j in enumerate(ctrl)}

  def phase_cols(limb: str) -> list[int]:
    if not cfg.temporal_director:
      return [zero, zero]
    i = lay.limb_index[limb]
    return [col["sin"][i], col["cos"][i]]

  def row(group: agents.AgentGroup, segments: layout_lib.Segments, limbs: tuple[str, ...],
          joints: list[int], k: int) -> list[int]:
    """Feature columns of agent ``k``'s observation: ``joints`` its joint positions."""
    source = {
        "q": [col["q"][j] for j in joints], "dq": [col["dq"][j] for j in joints], "last_action":
            ([col["last_action"][pos_in_action[j]] if j in pos_in_action else zero for j in joints]
             if group.name != layout_lib.BODY else col["last_action"]), "phase": [
                 c for l in limbs for c in phase_cols(l)
             ], "euler": col["euler"], "ang_vel": col["ang_vel"], "command": col["command"],
        "agent_id": [one if m == k else zero for m in range(group.n_agents)]
    }
    unknown = [n for n in segments.names if n not in source]
    if unknown:
      raise ExportError(f"group '{group.name}': no feature column for observation segment(s) "
                        f"{unknown}")
    return [c for name in segments.names for c in source[name]]

  obs_index = {}
  for group in lay.groups:
    segments, limbs = lay.actor[group.name], lay.group_limbs[group.name]
    if group.name == layout_lib.BODY:
      rows = [row(group, segments, limbs, ctrl, 0)]
    else:
      rows = [
          row(group, segments, (limb,), [int(i)
                                         for i in lay.limb_joints[limb]], k)
          for k, limb in enumerate(limbs)
      ]
    table = np.asarray(rows, np.int64)
    if table.shape != (group.n_agents, group.obs_dim):
      raise ExportError(f"group '{group.name}': observation table {table.shape} does not match "
                        f"the env's ({group.n_agents}, {group.obs_dim})")
    obs_index[group.name] = table
  return Layout(lay.n_joints, lay.n_actions, lay.n_limbs, features.size, zero, one, obs_index,
                np.asarray(lay.phase_offset, np.float32))


def _dense_layers(variables: Mapping[str, Any]) -> list[tuple[np.ndarray, np.ndarray]]:
  """``[(kernel, bias)]`` of an actor's MLP in layer order (kernels ``[in, out]``, or
  ``[n_agents, in, out]`` for per-agent actors)."""
  flat = flax.traverse_util.flatten_dict(dict(variables["params"]))
  layers = {}
  for path, value in flat.items():
    dense = [p for p in path if str(p).startswith("Dense_")]
    if dense and path[-1] in ("kernel", "bias"):
      layers.setdefault(int(dense[-1].split("_")[1]), {})[path[-1]] = np.asarray(value, np.float32)
  if not layers:
    raise ExportError("actor parameters hold no Dense layers")
  return [(layers[k]["kernel"], layers[k]["bias"]) for k in sorted(layers)]


# ------------------------------------------------------------------------------ graph building
class _Graph:
  """Collects nodes and initializers with unique names."""

  def __init__(self):
    self.nodes: list[onnx.NodeProto] = []
    self.inits: list[onnx.TensorProto] = []
    self._n = 0

  def const(self, value: Any, name: str, dtype=np.float32) -> str:
    self._n += 1
    full = f"{name}_{self._n}"
    self.inits.append(numpy_helper.from_array(np.asarray(value, dtype), full))
    return full

  def op(self, op_type: str, inputs: list[str], name: str, out: str | None = None,
         **attrs: Any) -> str:
    self._n += 1
    out = out or f"{name}_{self._n}"
    self.nodes.append(helper.make_node(op_type, inputs, [out], name=f"{name}_{self._n}", **attrs))
    return out


def metadata(parts: PolicyParts) -> dict[str, str]:
  """The ``metadata_props`` of the exported model (all values are strings; lists as JSON)."""
  spec, cfg, lay = parts.env.spec, parts.env.config, parts.env.layout
  ctrl = [int(i) for i in lay.controlled]
  joints = list(lay.joints)
  props = {
      "format":
          "mash-policy/1",
      "robot":
          spec.name,
      "joint_order":
          json.dumps(joints),
      "controlled_joints":
          json.dumps([joints[i] for i in ctrl]),
      "controlled_index":
          json.dumps(ctrl),
      "default_pose_rad":
          json.dumps([float(x) for x in lay.default_pose]),
      "kp":
          json.dumps([float(x) for x in lay.kp]),
      "kd":
          json.dumps([float(x) for x in lay.kd]),
      "torque_limit_nm":
          json.dumps([float(x) for x in lay.torque_limit]),
      "action_scale":
          repr(float(cfg.action_scale)),
      "action_clip":
          repr(float(cfg.action_clip)),
      "ctrl_dt_s":
          repr(float(cfg.ctrl_dt)),
      "control_rate_hz":
          repr(1.0 / float(cfg.ctrl_dt)),
      "gait_cycle_s":
          repr(float(cfg.gait_cycle_s)),
      "phase_offsets":
          json.dumps([float(x) for x in lay.phase_offset]),
      "limbs":
          json.dumps(list(lay.limbs)),
      "temporal_director":
          json.dumps(bool(cfg.temporal_director)),
      "agent_id":
          json.dumps(bool(cfg.agent_id)),
      "partition":
          cfg.partition,
      "fall_height_m":
          repr(float(cfg.fall_height)),
      "fall_tilt_rad":
          repr(float(cfg.fall_tilt)),
      "inputs":
          json.dumps(list(INPUTS)),
      "outputs":
          json.dumps(list(OUTPUTS)),
      "units":
          json.dumps({
              "q": "rad, absolute, joint_order", "dq": "rad/s, joint_order",
              "last_action": "previous action output (unitless)",
              "gait_phase": "cycles in [0, 1); += ctrl_dt/gait_cycle_s per step unless standing",
              "euler": "rad, roll pitch yaw (ZYX) of the torso", "ang_vel": "rad/s, torso frame",
              "command": "[standing 0/1, vx m/s, vy m/s, yaw rate rad/s]", "action":
                  "unitless, controlled_joints order", "q_target":
                      "rad, absolute, controlled_joints order; PD at every physics step: "
                      "tau = clip(kp (q_target - q) - kd dq, -torque_limit, torque_limit); "
                      "joints not controlled hold default_pose"
          }),
  }
  props.update({k: str(v) for k, v in parts.meta.items()})
  return props


def build_model(parts: PolicyParts) -> onnx.ModelProto:
  """The ONNX model of ``parts`` (see module docstring for inputs and outputs)."""
  env, cfg = parts.env, parts.env.config
  lay = layout(env)
  g = _Graph()
  features = _feature_row(g, env, lay)
  flat_parts, flat_index = [], []
  for group in env.agent_groups:
    flat_parts.append(_group_actions(g, parts, group, lay, features))  # [N, n_agents * act_dim]
    flat_index.extend(np.asarray(group.action_index).reshape(-1).tolist())
  _targets(g, env, flat_parts, flat_index, lay.n_actions)
  graph = helper.make_graph(g.nodes, "mash_policy", _value_infos(INPUTS, lay),
                            _value_infos(OUTPUTS, lay), initializer=g.inits)
  model = helper.make_model(graph, producer_name="mash-jax",
                            opset_imports=[helper.make_opsetid("", OPSET)])
  model.ir_version = IR_VERSION
  model.doc_string = (
      f"MASH policy ({parts.meta.get('algo', '?')}, {cfg.task}) for {env.spec.name}: "
      f"{cfg.partition} partition, {len(env.agent_groups)} actor group(s). Run at "
      f"{1.0 / cfg.ctrl_dt:g} Hz; inputs {', '.join(INPUTS)}; outputs {', '.join(OUTPUTS)}. "
      "See metadata_props for joint order, units, default pose and PD gains.")
  helper.set_model_props(model, metadata(parts))
  onnx.checker.check_model(model, full_check=True)
  return model


def _feature_row(g: "_Graph", env, lay: "Layout") -> str:
  """The feature row ``[N, width]``: ``q - default | dq | last_action | sin | cos | euler |
  ang_vel | command | 0 | 1``, each limb's phase with its offset."""
  q_default = np.asarray(env.layout.default_pose, np.float32)
  q_rel = g.op("Sub", ["q", g.const(q_default, "q_default")], "q_rel")
  angle = g.op("Mul", [
      g.op("Add", ["gait_phase", g.const(lay.phase_offset, "phase_offset")], "limb_phase"),
      g.const(np.float32(2 * np.pi), "two_pi")
  ], "limb_angle")
  sin = g.op("Sin", [angle], "phase_sin")
  cos = g.op("Cos", [angle], "phase_cos")
  batch = g.op("Shape", ["q"], "batch", end=1)
  const_shape = g.op("Concat", [batch, g.const([2], "two", np.int64)], "const_shape", axis=0)
  const_cols = g.op("Expand", [g.const([[0.0, 1.0]], "zero_one"), const_shape], "const_cols")
  return g.op("Concat",
              [q_rel, "dq", "last_action", sin, cos, "euler", "ang_vel", "command", const_cols],
              "features", axis=1)


def _normalized(g: "_Graph", parts: PolicyParts, name: str, obs: str) -> str:
  """A group's observations through its running statistics, clipped as in training."""
  stats = parts.normalizer[name]
  mean = np.asarray(stats.mean, np.float32)
  std = np.asarray(
      normalization.RunningStats(jnp.asarray(stats.count), jnp.asarray(stats.mean),
                                 jnp.asarray(stats.m2)).std, np.float32)
  obs = g.op("Div", [
      g.op("Sub", [obs, g.const(mean, f"{name}_obs_mean")], f"{name}_centred"),
      g.const(std, f"{name}_obs_std")
  ], f"{name}_scaled")
  return g.op("Clip", [
      obs,
      g.const(np.float32(-parts.obs_clip), "obs_clip_lo"),
      g.const(np.float32(parts.obs_clip), "obs_clip_hi")
  ], f"{name}_normalized")


def _group_actions(g: "_Graph", parts: PolicyParts, group, lay: "Layout", features: str) -> str:
  """One group's actions ``[N, n_agents * act_dim]``: every agent's observation gathered from the
  feature row, normalized, through the group's actor MLP (shared, or one per agent)."""
  name = group.name
  obs = g.op("Gather",
             [features, g.const(lay.obs_index[name], f"{name}_obs_index", np.int64)], f"{name}_obs",
             axis=1)  # [N, n_agents, obs_dim]
  if parts.normalizer is not None:
    obs = _normalized(g, parts, name, obs)
  layers = _dense_layers(parts.params["actors"][name])
  per_agent = layers[0][0].ndim == 3
  x = obs
  if per_agent:  # [N, n, 1, in] @ [n, in, out]: each agent its own weights
    x = g.op("Unsqueeze", [x, g.const([2], "axis2", np.int64)], f"{name}_rows")
  for k, (kernel, bias) in enumerate(layers):
    if per_agent:
      bias = bias[:, None, :]
    x = g.op("Add", [
        g.op("MatMul", [x, g.const(kernel, f"{name}_W{k}")], f"{name}_mm{k}"),
        g.const(bias, f"{name}_b{k}")
    ], f"{name}_dense{k}")
    if k < len(layers) - 1:
      x = g.op("Elu", [x], f"{name}_elu{k}", alpha=1.0)
  if per_agent:
    x = g.op("Squeeze", [x, g.const([2], "axis2", np.int64)], f"{name}_mean")
  return g.op("Reshape", [x, g.const([0, -1], "flat_shape", np.int64)], f"{name}_flat")


def _targets(g: "_Graph", env, flat_parts: list[str], flat_index: list[int],
             n_actions: int) -> None:
  """The outputs: the groups' actions in flat order (``action``) and the PD targets they set
  (``q_target = default + action_scale * clip(action)``)."""
  cfg = env.config
  stacked = (flat_parts[0]
             if len(flat_parts) == 1 else g.op("Concat", flat_parts, "stacked_actions", axis=1))
  if sorted(flat_index) != list(range(n_actions)):
    raise ExportError(f"agent action indices {flat_index} do not cover the {n_actions} actions "
                      "once")
  order = np.argsort(np.asarray(flat_index))  # flat[j] = stacked[order[j]]
  if np.array_equal(order, np.arange(n_actions)):
    g.op("Identity", [stacked], "action", out="action")
  else:
    g.op("Gather", [stacked, g.const(order, "action_order", np.int64)], "action", out="action",
         axis=1)
  clipped = g.op("Clip", [
      "action",
      g.const(np.float32(-cfg.action_clip), "action_clip_lo"),
      g.const(np.float32(cfg.action_clip), "action_clip_hi")
  ], "action_clipped")
  scaled = g.op("Mul", [g.const(np.float32(cfg.action_scale), "action_scale"), clipped], "scaled")
  q_default = np.asarray(env.layout.default_pose, np.float32)
  g.op("Add", [g.const(q_default[env.layout.controlled], "default_ctrl"), scaled], "q_target",
       out="q_target")


def _value_infos(names: tuple[str, ...], lay: "Layout") -> list:
  """The graph's inputs or outputs ``names`` as typed, documented ``[N, size]`` tensors."""
  J, A = lay.n_joints, lay.n_actions
  docs = {
      "q": (J, f"[N, {J}] absolute joint angles (rad), metadata joint_order"),
      "dq": (J, f"[N, {J}] joint velocities (rad/s), metadata joint_order"),
      "last_action": (A, f"[N, {A}] previous 'action' output (zeros at start)"),
      "gait_phase": (1, "[N, 1] gait clock (cycles, [0, 1)); frozen while standing"),
      "euler": (3, "[N, 3] torso roll, pitch, yaw (rad, ZYX)"),
      "ang_vel": (3, "[N, 3] torso angular velocity, torso frame (rad/s)"),
      "command": (4, "[N, 4] standing flag, vx (m/s), vy (m/s), yaw rate (rad/s)"),
      "action": (A, f"[N, {A}] policy mean, metadata controlled_joints order"),
      "q_target": (A, f"[N, {A}] PD targets (rad), metadata controlled_joints order"),
  }
  return [
      helper.make_tensor_value_info(n, TensorProto.FLOAT, ["N", docs[n][0]], doc_string=docs[n][1])
      for n in names
  ]


def export_policy(policy, path: str | os.PathLike) -> Path:
  """Writes the ONNX graph of ``policy`` (a :class:`mash.deploy.policy.Policy`, or its
  :class:`PolicyParts`) to ``path``."""
  path = Path(path)
  model = build_model(policy if isinstance(policy, PolicyParts) else policy_parts(policy))
  path.parent.mkdir(parents=True, exist_ok=True)
  onnx.save(model, str(path))
  return path


# The export check's bound on |onnx - jax| (rad, and action units): float32 rounding is ~1e-7.
TOLERANCE = 1e-5


def save_policy_folder(policy, folder: str | os.PathLike) -> Path:
  """Writes ``policy`` (a :class:`mash.deploy.policy.Policy`) as a policy folder
  (:func:`mash.deploy.policy.save`) with its deployable graph, ``policy.onnx``, checked against
  the JAX policy on 64 observations (:func:`verify`); returns the folder.

  Raises:
    ExportError: the graph differs from the JAX policy by more than :data:`TOLERANCE` (the
      folder is kept without it).
  """
  folder = policy_lib.save(policy, folder)
  parts = policy_parts(policy)
  path = export_policy(parts, folder / policy_lib.ONNX)
  diff = verify(path, parts, n=64)
  if max(diff["action"], diff["q_target"]) > TOLERANCE:
    path.unlink()
    raise ExportError(f"the ONNX graph of '{folder}' differs from its JAX policy by "
                      f"{max(diff['action'], diff['q_target']):.2e} > {TOLERANCE:.0e}; not kept")
  return folder


def read_metadata(path: str | os.PathLike) -> dict[str, Any]:
  """The metadata of an exported policy, JSON values decoded (numbers as floats)."""
  model = onnx.load(str(path), load_external_data=False)
  out = {}
  for prop in model.metadata_props:
    try:
      out[prop.key] = json.loads(prop.value)
    except json.JSONDecodeError:
      out[prop.key] = prop.value
  return out


# ---------------------------------------------------------------------------- reference & check
def random_inputs(env, n: int, seed: int = 0) -> dict[str, np.ndarray]:
  """``n`` random but plausible observations (float32, leading batch dim) for the checks."""
  rng = np.random.default_rng(seed)
  J, A = env.n_joints, env.action_size
  f32 = lambda x: np.asarray(x, np.float32)
  q_default = np.asarray(env.layout.default_pose, np.float32)  # float32, as the env holds it
  standing = (rng.uniform(size=n) < 0.2).astype(np.float32)
  return {
      "q":
          f32(q_default[None] + rng.normal(0.0, 0.3, (n, J))),
      "dq":
          f32(rng.normal(0.0, 2.0, (n, J))),
      "last_action":
          f32(rng.normal(0.0, 1.0, (n, A))),
      "gait_phase":
          f32(rng.uniform(0.0, 1.0, (n, 1))),
      "euler":
          f32(rng.uniform(-0.3, 0.3, (n, 3))),
      "ang_vel":
          f32(rng.normal(0.0, 0.7, (n, 3))),
      "command":
          f32(
              np.stack([
                  standing,
                  rng.uniform(-0.3, 0.8, n) * (1 - standing),
                  rng.uniform(-0.2, 0.2, n) * (1 - standing),
                  rng.uniform(-0.5, 0.5, n) * (1 - standing)
              ], axis=1)),
  }


def reference_fn(parts: PolicyParts):
  """``inputs {name: [N, ...]} -> (action [N, A], q_target [N, A])`` in JAX, through the env's
  own ``observe`` and the networks' ``policy_apply`` (independent of the graph's gather tables)."""
  env = parts.env
  policy = nets.make_policy_fn(parts.networks, deterministic=True)
  dr = env.nominal_domain()

  def one(q, dq, last_action, gait_phase, euler, ang_vel, command):
    sensors = dict(q=q, dq=dq, euler=euler, ang_vel=ang_vel, lin_vel=jnp.zeros(3))
    info = dict(command=command, phase=gait_phase[0], last_action=last_action, push=jnp.zeros(5),
                dr=dr)
    obs = env.observe(sensors, info, jnp.ones(2))
    action = policy(parts.params, parts.normalizer, obs)
    return action, env.joint_targets(action)[env.layout.controlled]

  batched = jax.jit(jax.vmap(one))
  return lambda inputs: tuple(
      np.asarray(x) for x in batched(*(jnp.asarray(inputs[k]) for k in INPUTS)))


def onnx_session(path: str | os.PathLike):
  """An onnxruntime CPU session of an exported policy (one thread: tiny MLP, low latency)."""
  opts = ort.SessionOptions()
  opts.intra_op_num_threads = 1
  opts.inter_op_num_threads = 1
  return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def verify(path: str | os.PathLike, policy, n: int = 256, input_seed: int = 0) -> dict[str, float]:
  """Runs the ONNX file and the JAX reference of ``policy`` (a :class:`mash.deploy.policy.Policy`,
  or its :class:`PolicyParts`) on ``n`` random observations.

  On an accelerator the reference runs at full float32 matmul precision: there JAX's default for
  float32 matmuls is lower (TF32 on NVIDIA: measured 6e-4 off on an H200, against 6e-7 at
  'highest'), which would measure the GPU's shortcut, not the export. On CPU the default already is
  float32 (and 'highest' picks other kernels, 1e-5 further from onnxruntime), so it is left alone.

  Returns:
    ``{'action': max |diff|, 'q_target': max |diff|, 'n': n}``.
  """
  parts = policy if isinstance(policy, PolicyParts) else policy_parts(policy)
  inputs = random_inputs(parts.env, n, input_seed)
  precision = (contextlib.nullcontext()
               if jax.default_backend() == "cpu" else jax.default_matmul_precision("highest"))
  with precision:
    ref_action, ref_target = reference_fn(parts)(inputs)
  action, target = onnx_session(path).run(list(OUTPUTS), inputs)
  return {
      "action": float(np.max(np.abs(action - ref_action))),
      "q_target": float(np.max(np.abs(target - ref_target))), "n": n
  }
