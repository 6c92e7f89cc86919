"""Env-step throughput of the kicked candidate's env at each physics step / solver setting.

  python benchmarks/scripts/2026-12-06_solver_substep_cost.py [OUT.json]

One process, the `cpu` preset's env with candidate D's kicks (late_kicks_seed0's config), 400 envs
x 24 control steps, best of 2 timed calls per setting: prints one JSON line per (physics step,
Newton iterations, line-search iterations) and writes them all to OUT.json (default
``benchmarks/results/2026-12-06_cpu_preset_kicks/solver_substep_cost.json``). Run it with nothing
else on the cores.
"""

import dataclasses
import json
import sys
from pathlib import Path

from mash.bench import throughput
from mash.runs import experiment

RESULTS = Path(__file__).resolve().parents[1] / "results" / "2026-12-06_cpu_preset_kicks"
SETTINGS = [(0.005, 2, 2), (0.005, 3, 3), (0.005, 4, 4), (0.005, 6, 6), (0.005, 10, 10),
            (0.02 / 3, 2, 2), (0.02 / 3, 3, 3), (0.005, 2, 2)]

out = Path(sys.argv[1]) if len(sys.argv) > 1 else RESULTS / "solver_substep_cost.json"
base = experiment.config_from_file(RESULTS / "late_kicks_seed0" / "config.json", "bipedal")
rows = []
for sim_dt, iterations, ls_iterations in SETTINGS:
  physics = dataclasses.replace(base.env.physics, sim_dt=sim_dt, iterations=iterations,
                                ls_iterations=ls_iterations)
  cfg = dataclasses.replace(base, env=dataclasses.replace(base.env, physics=physics))
  steps_per_s, timing = throughput.env_steps(experiment.make_env(cfg), 400, 24, repeats=2)
  rows.append({
      "sim_dt": sim_dt, "substeps": round(0.02 / sim_dt), "iterations": iterations,
      "ls_iterations": ls_iterations, "env_steps_per_s": steps_per_s, "compile_s": timing.compile_s
  })
  print(json.dumps(rows[-1]), flush=True)
out.write_text(json.dumps(rows, indent=1) + "\n")
