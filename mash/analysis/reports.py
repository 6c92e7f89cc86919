"""What ``python -m experiments.evaluate`` writes for a run or a policy folder.

:func:`evaluate_run`: deterministic rollouts of every seed's policy at a fixed forward command
(domain randomization on) -> ``eval/metrics.json`` (the paper's metrics per seed and their spread,
the falls split by floor friction), ``eval/trajectories.npz`` and ``eval/hip_pitch.png``.
:func:`tracking_run`: the policy over the command grid
(:data:`mash.analysis.evaluation.TRACKING_GRID`) -> ``eval_tracking/tracking.json``,
``tracking.png`` and ``tracking_trajectories.npz``. A diagnostic (no DR, no pushes, another friction
range, seed or checkpoint) writes to a folder of its own name (:func:`eval_dir_name`), never over
the evaluation as trained.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from mash.analysis import evaluation, robustness
from mash.analysis import metrics as metrics_lib
from mash.deploy import policy as policy_lib
from mash.sim import env as env_lib
from mash.sim import tasks

SEED_METRICS = ("T_conv", "S_action", "S_action_2nd", "S_torso", "C_limb", "fall_rate",
                "forward_speed")


def learning_curve(progress: dict[str, np.ndarray], seed: int) -> np.ndarray | None:
  """Seed ``seed``'s curve of the reward under the paper's weights, whatever curricula trained
  (older runs: the trained reward, the only one they logged), from the columns of a run's
  ``progress_seeds.csv``; None without them (a policy folder has no curve, hence no T_conv)."""
  if not progress:
    return None
  key = "paper_episode_reward" if "paper_episode_reward" in progress else "episode_reward"
  return progress[key][progress["seed"] == seed]


def summarize(per_seed: list[dict], episodes: dict[str, np.ndarray], eval_config: dict,
              iteration: int, curve: np.ndarray | None) -> dict:
  """A run's ``metrics.json``: the mean over seeds of each seed's metrics, their spread
  (``std``), the falls by floor friction over all episodes, and each seed's own (``per_seed``).

  Args:
    per_seed: one :func:`mash.analysis.evaluation.evaluate` result per seed.
    episodes: the seeds' episodes together, ``[E, ...]`` arrays with ``friction`` ``[E]`` and
      ``alive`` ``[E, T]``.
    eval_config: the fields of the :class:`mash.analysis.evaluation.EvalConfig` they ran under.
    iteration: the evaluated checkpoint's.
    curve: the first seed's learning curve (its smoothing window is reported), or None.
  """
  keys = SEED_METRICS + (("C_limb_arm_leg",) if "C_limb_arm_leg" in per_seed[0] else ())
  keys = tuple(k for k in keys if per_seed[0][k] is not None)
  result = {k: float(np.mean([m[k] for m in per_seed])) for k in keys}
  result["T_conv"] = result.get("T_conv")
  result["command_vx"] = eval_config["command_vx"]
  result["iteration"] = iteration
  result["std"] = {k: metrics_lib.seed_summary([m[k] for m in per_seed])["std"] for k in keys}
  result["fall_rate_by_friction"] = evaluation.falls_by_friction(episodes["friction"],
                                                                 episodes["alive"].min(axis=1) > 0)
  result["all_episodes"] = {
      k: (float(np.mean([m["all_episodes"][k]
                         for m in per_seed])) if all(m["all_episodes"][k] is not None
                                                     for m in per_seed) else None
         ) for k in ("S_action", "S_action_2nd", "S_torso", "C_limb")
  }
  result["per_seed"] = per_seed
  result["eval_config"] = eval_config
  result["smoothing_window"] = (None if curve is None else
                                metrics_lib.convergence_iteration(curve)[1]["window"])
  return result


def evaluate_run(run_dir: str, eval_cfg=None, write: bool = True, iteration: int | None = None,
                 robot: str | None = None) -> dict:
  """Evaluates every seed of a run's latest checkpoint (or the one saved at ``iteration``), or
  the policy of a policy folder (:mod:`mash.deploy.policy`); returns (and writes) the metrics."""

  eval_cfg = eval_cfg or evaluation.EvalConfig()
  policies = policy_lib.load_all(run_dir, iteration, robot)
  cfg = policies[0].config
  env = env_lib.MashEnv(evaluation.eval_env_config(cfg.env, eval_cfg))

  # A policy folder has no learning curve: no T_conv.
  progress = ({} if policy_lib.is_policy_folder(run_dir) else policy_lib.read_progress(
      run_dir, per_seed=True))
  per_seed, trajs = [], []
  for policy in policies:
    s = policy.seed
    traj = evaluation.rollout(env, policy_lib.make_inference_fn(policy, env), eval_cfg)
    per_seed.append(
        evaluation.evaluate(traj, eval_cfg.command_vx, learning_curve(progress, s),
                            arms_act=tasks.get(cfg.env.task).arms_act))
    traj["seed"] = np.full(traj["alive"].shape[0], s)
    trajs.append(traj)
  merged = {k: np.concatenate([t[k] for t in trajs]) for k in trajs[0] if k != "dt"}
  result = summarize(per_seed, merged, eval_cfg.__dict__, policies[0].iteration,
                     learning_curve(progress, 0))
  if write:
    out = Path(run_dir) / eval_dir_name(eval_cfg, iteration)
    out.mkdir(exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(result, indent=2))
    np.savez_compressed(out / "trajectories.npz", dt=trajs[0]["dt"], **merged)
    plot_hip_pitch(merged, float(trajs[0]["dt"]), out / "hip_pitch.png", cfg.algo)
  return result


def tracking_run(run_dir: str, eval_cfg, iteration: int | None = None, write: bool = True,
                 robot: str | None = None) -> dict:
  """Rolls every seed of a run's policy over the command grid (``evaluation.TRACKING_GRID``,
  ``eval_cfg.num_episodes`` episodes per command) and returns (and writes) ``tracking.json``'s
  content: the episodes of all seeds together, and ``per_seed`` when the run has several (a
  policy folder: its one policy)."""

  policies = policy_lib.load_all(run_dir, iteration, robot)
  cfg = policies[0].config
  seeds = len(policies)
  commands = evaluation.tracking_commands(eval_cfg.num_episodes)
  grid_cfg = dataclasses.replace(eval_cfg, num_episodes=len(commands))
  env = env_lib.MashEnv(evaluation.eval_env_config(cfg.env, grid_cfg))
  per_seed, trajs = [], []
  for policy in policies:
    traj = evaluation.rollout(env, policy_lib.make_inference_fn(policy, env), grid_cfg,
                              commands=commands)
    per_seed.append(evaluation.tracking(traj, commands))
    trajs.append(traj)
  merged = {
      k: np.concatenate([t[k] for t in trajs])
      for k in ("world_velocity", "euler", "alive", "command")
  }
  all_commands = np.concatenate([commands] * seeds)
  result = evaluation.tracking(merged, all_commands)
  result["iteration"] = policies[0].iteration
  result["seeds"] = seeds
  result["eval_config"] = {
      k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(eval_cfg).items()
  }
  if seeds > 1:
    result["all_episodes"] = {
        k: (float(np.mean([m["all_episodes"][k]
                           for m in per_seed])) if all(m["all_episodes"][k] is not None
                                                       for m in per_seed) else None
           ) for k in ("S_action", "S_action_2nd", "S_torso", "C_limb")
    }
  result["per_seed"] = per_seed
  if write:
    out = Path(run_dir) / tracking_dir_name(eval_cfg, iteration)
    out.mkdir(exist_ok=True)
    (out / "tracking.json").write_text(json.dumps(result, indent=2))
    velocity = evaluation.heading_velocity(merged["world_velocity"], merged["euler"][..., 2])
    # The commands as the env ran them (last step): the grid's, unless something resampled them.
    np.savez_compressed(out / "tracking_trajectories.npz", commands=merged["command"][:, -1],
                        velocity=velocity.astype(np.float32), alive=merged["alive"],
                        dt=trajs[0]["dt"])
    plot_tracking(result, out / "tracking.png",
                  f"{cfg.task} {cfg.algo}, iteration {result['iteration']}")
  return result


def tracking_dir_name(eval_cfg, iteration: int | None = None) -> str:
  """``eval_tracking`` followed by the suffixes of :func:`eval_dir_name` (``_no_push``,
  ``_seed<S>``, ``_it<N>``, ...)."""
  return "eval_tracking" + eval_dir_name(eval_cfg, iteration)[len("eval"):]


def plot_tracking(result: dict, path: Path, title: str) -> None:
  """Commanded against achieved velocity, one panel per axis, each command's fall rate beside it.

  A panel shows the grid commands that vary its axis alone (the others zero, walking), the
  commanded value on x and the achieved mean on y (bars: the standard deviation over episodes),
  with the ideal diagonal; the standing command is a square at 0; a command with falls is ringed
  in red with its fall rate written beside it.
  """

  units = {"vx": "m/s", "vy": "m/s", "yaw_rate": "rad/s"}
  fig = Figure(figsize=(12, 4))
  axes = fig.subplots(1, 3)
  for i, (ax, axis) in enumerate(zip(axes, evaluation.TRACKING_AXES)):
    others = [j for j in range(3) if j != i]
    entries = [
        g for g in result["grid"]
        if g["command"][0] == 0 and all(g["command"][1 + j] == 0 for j in others)
    ]
    entries.sort(key=lambda g: g["command"][1 + i])
    x = np.array([g["command"][1 + i] for g in entries])
    y = np.array([g[axis] for g in entries])
    spread = np.array([g["episode_std"][axis] for g in entries])
    lo, hi = min(x.min(), y.min()) - 0.1, max(x.max(), y.max()) + 0.1
    ax.plot([lo, hi], [lo, hi], "--", color="grey", label="commanded = achieved")
    ax.errorbar(x, y, yerr=spread, fmt="o-", capsize=3, label="achieved (bar: std over episodes)")
    standing = [g for g in result["grid"] if g["command"][0] > 0]
    if standing:
      g = standing[0]
      ax.errorbar([0.0], [g[axis]], yerr=[g["episode_std"][axis]], fmt="s", color="black",
                  capsize=3, label="standing")
      entries = entries + standing
      x, y = np.append(x, 0.0), np.append(y, g[axis])
    for g, xi, yi in zip(entries, x, y):
      if g["fall_rate"] > 0:
        ax.plot(xi, yi, "o", color="red", markersize=9, fillstyle="none")
        ax.annotate(f"{100 * g['fall_rate']:.0f} % falls", (xi, yi), textcoords="offset points",
                    xytext=(4, -12), fontsize=8, color="red")
    ax.set_xlabel(f"commanded {axis} ({units[axis]})")
    ax.set_ylabel(f"achieved {axis} ({units[axis]})")
    ax.set_title(f"{axis}: mean |error| {result['mean_abs_error'][axis]:.3f}")
    ax.grid(alpha=0.3)
  axes[0].legend(loc="upper left", fontsize=8)
  drift = result["standing_drift"]
  fig.suptitle(f"{title}: command tracking, {100 * result['fall_rate']:.1f} % falls" +
               ("" if drift is None else f", standing drift {drift:.3f} m/s"))
  fig.tight_layout()
  fig.savefig(path, dpi=120)


def eval_dir_name(eval_cfg, iteration: int | None = None) -> str:
  """``eval`` for the evaluation of the latest checkpoint with every randomized parameter on as
  trained, else the diagnostic's name; ``_friction_<lo>-<hi>`` appended for another friction
  range, ``_kicks`` with the training's kicks on, ``_seed<S>`` for another rollout seed than the
  default, then ``_it<N>`` for the checkpoint of iteration N."""
  suffix = "" if iteration is None else f"_it{iteration}"
  if eval_cfg.seed != type(eval_cfg).seed:
    suffix = f"_seed{eval_cfg.seed}" + suffix
  if not eval_cfg.randomization:
    return "eval_no_dr" + suffix
  if eval_cfg.friction is not None:
    lo, hi = eval_cfg.friction
    suffix = f"_friction_{lo:g}-{hi:g}" + suffix
  if eval_cfg.kicks:
    suffix = "_kicks" + suffix
  if not eval_cfg.pushes:
    return "eval_no_push" + suffix
  if eval_cfg.push_interval_s is not None:
    return f"eval_push_interval_{eval_cfg.push_interval_s:g}s" + suffix
  return "eval" + suffix


def plot_hip_pitch(traj: dict, dt: float, path: Path, label: str, seconds: float = 3.0) -> None:
  """The paper's joint-position figure: left/right hip pitch vs the temporal director's
  reference."""
  n = min(int(seconds / dt), traj["hip_pitch"].shape[1])
  t = np.arange(n) * dt
  fig = Figure(figsize=(7, 4))
  axes = fig.subplots(2, 1, sharex=True)
  for i, side in enumerate(("left", "right")):
    axes[i].plot(t, traj["hip_pitch"][0, :n, i], label=label)
    axes[i].plot(t, traj["hip_pitch_ref"][0, :n, i], "--", color="green", label="reference")
    axes[i].set_ylabel(f"{side} hip pitch (rad)")
    axes[i].grid(alpha=0.3)
  axes[0].legend(loc="upper right")
  axes[1].set_xlabel("time (s)")
  fig.tight_layout()
  fig.savefig(path, dpi=120)


# The flag that sets each EvalConfig field, to name it in an error.
EVAL_FLAGS = {
    "command_vx": "--command-vx", "num_episodes": "--episodes", "episode_s": "--seconds",
    "push_interval_s": "--push-interval", "friction": "--friction", "seed": "--seed"
}


def print_tracking(result: dict) -> None:
  """The tracking result as the command prints it: one line per command of the grid, then the
  mean errors, falls and standing drift."""
  for g in result["grid"]:
    c = g["command"]
    print(f"  command {'standing' if c[0] else 'walking '} vx {c[1]:+.2f} vy {c[2]:+.2f} "
          f"yaw {c[3]:+.2f} -> vx {g['vx']:+.3f} vy {g['vy']:+.3f} yaw {g['yaw_rate']:+.3f}, "
          f"falls {g['fall_rate']:.3f} of {g['episodes']}")
  err, drift = result["mean_abs_error"], result["standing_drift"]
  print(f"mean |error|: vx {err['vx']:.3f} m/s, vy {err['vy']:.3f} m/s, yaw rate "
        f"{err['yaw_rate']:.3f} rad/s; falls {result['fall_rate']:.3f}; standing drift " +
        ("n/a" if drift is None else f"{drift:.3f} m/s"))
  reach = result.get("reach") or {}
  if any(v is not None for v in reach.values()):
    print("reach (achieved / commanded, one-axis commands): " +
          ", ".join(f"{axis} {v:.2f}" for axis, v in reach.items() if v is not None))


def print_metrics(result: dict) -> None:
  """An evaluation's headline metrics as the command prints them, and the falls by friction."""
  shown = {
      k: result[k] for k in ("T_conv", "S_action", "S_action_2nd", "S_torso", "C_limb", "fall_rate",
                            "forward_speed", "command_vx")
  }
  print(json.dumps(shown, indent=2))
  bands = [
      f"{b['friction'][0]:g}-{b['friction'][1]:g}: {b['fall_rate']:.2f} of {b['episodes']}"
      for b in result["fall_rate_by_friction"]
      if b["episodes"]
  ]
  print("fall rate by floor friction: " + ", ".join(bands))


def describe(cfg: evaluation.EvalConfig, seed_given: bool) -> str:
  """How an evaluation randomizes, in words (``on``, ``off``, with its diagnostics)."""
  dr = "off" if not cfg.randomization else ("on without pushes" if not cfg.pushes else "on")
  if cfg.push_interval_s is not None:
    dr += (", a new push every control step"
           if cfg.push_interval_s == 0 else f", each push held {cfg.push_interval_s:g} s")
  if cfg.friction is not None:
    dr += f", floor friction U[{cfg.friction[0]:g}, {cfg.friction[1]:g}]"
  if seed_given:
    dr += f", rollout seed {cfg.seed}"
  return dr


def robustness_run(run_dir: str, cfg: robustness.BatteryConfig = robustness.BatteryConfig(),
                   iteration: int | None = None, robot: str | None = None,
                   write: bool = True) -> dict:
  """The robustness battery (:mod:`mash.analysis.robustness`) for every seed of a run's policy
  (or a policy folder's one) in MJX; returns (and writes) ``eval_robustness/robustness.json``
  (per condition the survival and speed, the mean over seeds, and ``per_seed``) and
  ``robustness.png``."""
  policies = policy_lib.load_all(run_dir, iteration, robot)
  env = env_lib.MashEnv(robustness.battery_env_config(policies[0].config.env, cfg))
  per_seed = [robustness.run(env, policy_lib.make_inference_fn(p, env), cfg) for p in policies]
  rows = [{
      **row, "survival": float(np.mean([s[i]["survival"] for s in per_seed])),
      "forward_speed": float(np.mean([s[i]["forward_speed"] for s in per_seed]))
  } for i, row in enumerate(per_seed[0])]
  for row in rows:
    row.pop("survival_by_direction", None)
  result = {
      "engine": "mjx", "iteration": policies[0].iteration, "seeds": len(policies),
      "battery": dataclasses.asdict(cfg), "conditions": rows, "per_seed": per_seed
  }
  if write:
    out = Path(run_dir) / ("eval_robustness" + ("" if iteration is None else f"_it{iteration}"))
    out.mkdir(exist_ok=True)
    (out / "robustness.json").write_text(json.dumps(result, indent=2))
    plot_robustness(
        rows, out / "robustness.png",
        f"{policies[0].config.task} {policies[0].config.algo}, MJX, iteration "
        f"{policies[0].iteration}, {cfg.episodes} episodes a condition")
  return result


def plot_robustness(rows: list[dict], path: Path, title: str) -> None:
  """One panel per group of conditions: the share of episodes that survived (bars) and the mean
  forward speed over the steps alive (numbers on the bars)."""
  groups = [g for g in robustness.GROUPS if any(r["group"] == g for r in rows)]
  fig = Figure(figsize=(3.0 * len(groups), 3.6))
  axes = np.atleast_1d(fig.subplots(1, len(groups), sharey=True))
  for ax, group in zip(axes, groups):
    mine = [r for r in rows if r["group"] == group]
    x = np.arange(len(mine))
    ax.bar(x, [100 * r["survival"] for r in mine], color="tab:blue")
    for xi, r in zip(x, mine):
      ax.annotate(f"{r['forward_speed']:.2f} m/s", (xi, 100 * r["survival"]), ha="center",
                  xytext=(0, 3), textcoords="offset points", fontsize=7)
    ax.set_xticks(x, [r["name"].removeprefix(group).strip() or r["name"] for r in mine],
                  rotation=30, ha="right", fontsize=8)
    ax.set_title(group, fontsize=9)
    ax.set_ylim(0, 110)
    ax.grid(alpha=0.3, axis="y")
  axes[0].set_ylabel("episodes survived (%)")
  fig.suptitle(title, fontsize=9)
  fig.tight_layout()
  fig.savefig(path, dpi=120)


def print_robustness(result: dict) -> None:
  """The battery's result as the command prints it: one line per condition."""
  for r in result["conditions"]:
    print(f"  {r['name']:<32} survival {100 * r['survival']:5.1f} %, forward speed "
          f"{r['forward_speed']:.3f} m/s ({r['episodes']} episodes)")
