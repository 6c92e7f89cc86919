"""Benchmark sweeps: throughput against batch size, and each solver setting's speed and drift.

Each sweep returns its rows and writes them as a table (``.json``, ``.md``; the batch sweep also a
``.png`` plot) beside a given stem, as ``experiments.benchmark --sweep`` does.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import mujoco
import numpy as np
from matplotlib.figure import Figure

from mash.bench import benchmark, throughput
from mash.sim import env as env_lib
from mash.sim import env_config
from mash.sim import model as model_lib

PHYSICS_SETTINGS = ((0.005, 1), (0.005, 3), (0.004, 1), (0.002, 3))  # (sim_dt, solver iterations)
BATCH_CURVES = ("physics_steps_per_s", "env_steps_per_s", "train_env_steps_per_s")


def sweep_batch(batches: list[int], task: str, stem: Path | None = None, impl: str = "jax",
                robot: str = "booster_t1") -> list[dict]:
  """Physics, env and MASH training throughput per batch size (one process), through MJX's
  ``impl``.

  With ``stem``, the table is rewritten after every batch (a run stopped early keeps its rows)."""
  env = env_lib.MashEnv(benchmark.bench_env_config(task, impl, max(batches), robot))
  rows = []
  for b in batches:
    print(f"batch {b}", file=sys.stderr, flush=True)
    phys, _ = throughput.bare_physics(env, b, 10, repeats=1)
    envs, _ = throughput.env_steps(env, b, 10, repeats=1)
    cfg = benchmark.bench_train_config(b, unroll=16, iterations=1)
    train_sps, _ = benchmark.train_throughput(env, cfg, calls=1)
    rows.append({
        "batch": b, "physics_steps_per_s": phys, "env_steps_per_s": envs,
        "train_env_steps_per_s": train_sps, "device": benchmark.device_kind(), "impl": impl
    })
    if stem is not None:
      write_table(rows, stem, "batch")
  return rows


def _standing(env: env_lib.MashEnv, sim_dt: float, seconds: float = 10.0) -> dict:
  """Runs MuJoCo C on the env's model from its first keyframe for ``seconds``, PD at the default
  pose and zero action; returns the drift of the base (m) and whether it is still upright."""
  lay, m, addr = env.layout, env.mj_model, env.joint_addresses()
  d = mujoco.MjData(m)
  mujoco.mj_resetDataKeyframe(m, d, 0)
  q0, kp, kd, lim = lay.default_pose, lay.kp, lay.kd, lay.torque_limit
  start = d.qpos[:3].copy()
  for _ in range(int(seconds / sim_dt)):
    d.ctrl[addr.actuator] = np.clip(kp * (q0 - d.qpos[addr.qpos]) - kd * d.qvel[addr.dof], -lim,
                                    lim)
    mujoco.mj_step(m, d)
  return {
      "standing_drift_xy_m": float(np.linalg.norm(d.qpos[:2] - start[:2])),
      "standing_height_change_m": float(d.qpos[2] - start[2]),
      "upright_after_10s": bool(d.qpos[2] > 0.6)
  }


def sweep_physics(task: str, robot: str = "booster_t1", stem: Path | None = None) -> list[dict]:
  """Each solver setting of :data:`PHYSICS_SETTINGS`: MJX physics steps/s (batch 256) and standing
  drift over 10 s (MuJoCo C, same model and options, PD at the default pose, zero action).

  With ``stem``, the table is written there once every setting is measured."""
  rows = []
  for sim_dt, iterations in PHYSICS_SETTINGS:
    print(f"sim_dt {sim_dt}, iterations {iterations}", file=sys.stderr, flush=True)
    physics = model_lib.PhysicsConfig(sim_dt=sim_dt, iterations=iterations)
    env = env_lib.MashEnv(env_config.EnvConfig(task=task, robot=robot, physics=physics))
    phys, _ = throughput.bare_physics(env, 256, 10, repeats=1)
    rows.append({
        "sim_dt": sim_dt, "iterations": iterations, "substeps": env.n_substeps,
        "physics_steps_per_s": phys, "control_steps_per_s": phys / env.n_substeps,
        **_standing(env, sim_dt)
    })
  if stem is not None:
    write_table(rows, stem, "sim_dt")
  return rows


def write_table(rows: list[dict], stem: Path, x: str) -> None:
  """Writes ``rows`` to ``stem.json`` and as a markdown table keyed by column ``x`` to ``stem.md``;
  for ``x == 'batch'`` also plots the throughput curves to ``stem.png``."""
  stem.parent.mkdir(parents=True, exist_ok=True)
  stem.with_suffix(".json").write_text(json.dumps(rows, indent=2))
  keys = [k for k in rows[0] if k != x and isinstance(rows[0][k], (int, float))]
  lines = ["| " + " | ".join([x] + keys) + " |", "|" + "---|" * (len(keys) + 1)]
  for r in rows:
    lines.append("| " + " | ".join(
        [str(r[x])] + [f"{r[k]:,.3g}" if isinstance(r[k], float) else str(r[k]) for k in keys]) +
                 " |")
  stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
  if x == "batch":
    _plot_batch(rows, stem.with_suffix(".png"))


def _plot_batch(rows: list[dict], path: Path) -> None:
  """Steps/s of physics, env and training against batch size (log 2 axis)."""
  fig = Figure(figsize=(6, 3.5))
  ax = fig.subplots()
  for k in BATCH_CURVES:
    ax.plot([r["batch"] for r in rows], [r[k] for r in rows], "o-", label=k)
  ax.set_xscale("log", base=2)
  ax.set_xlabel("batch (envs)")
  ax.set_ylabel("steps / s")
  ax.legend(fontsize=8)
  ax.grid(alpha=0.3)
  fig.tight_layout()
  fig.savefig(path, dpi=120)
