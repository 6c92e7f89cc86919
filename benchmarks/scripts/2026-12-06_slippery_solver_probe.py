"""Why kicked policies fall on the slipperiest floors in MuJoCo C and not in MJX.

  python benchmarks/scripts/2026-12-06_slippery_solver_probe.py ONNX VARIANT[,VARIANT...] [LO HI]

runs the robustness battery's floor-friction condition (``friction LO-HI``, default 0.1-0.2: 64
episodes of 8 s at vx 0.4 m/s, the battery's seed 2026, the same episodes as
``sim2sim --robustness``) in MuJoCo C for one exported policy under each physics variant, in one
process, and prints one JSON line per variant. The variants change one thing at a time between
sim2sim's physics (2 ms implicit-fast, 10 Newton / 20 line-search iterations, full collision) and
the training's (5 ms Euler, the preset's 2 / 2, sole spheres only): see ``VARIANTS``; the
``*_no_warmstart`` ones start the solver from the unconstrained acceleration instead of the last
step's.
"""

import json
import sys
import time

import mujoco
import numpy as np

from mash.analysis import robustness
from mash.deploy import export, native_battery, sim2sim
from mash.sim import robots


def _mjx_like(iterations: int, ls_iterations: int) -> sim2sim.Sim2SimConfig:
  """The training's time step, integrator and collision set, at this solver setting."""
  return sim2sim.Sim2SimConfig(sim_dt=0.005, integrator="euler", iterations=iterations,
                               ls_iterations=ls_iterations, full_collision=False)


VARIANTS = {
    "sim2sim": sim2sim.Sim2SimConfig(),
    "soles_only": sim2sim.Sim2SimConfig(full_collision=False),
    "5ms_euler_10it": _mjx_like(10, 20),
    "as_trained": _mjx_like(2, 2),
    "as_trained_ls20": _mjx_like(2, 20),
    "1it": _mjx_like(1, 1),
    "3it": _mjx_like(3, 3),
    "4it": _mjx_like(4, 4),
    "6it": _mjx_like(6, 6),
    "as_trained_no_warmstart": _mjx_like(2, 2),
    "3it_no_warmstart": _mjx_like(3, 3),
}
NO_WARMSTART = ("as_trained_no_warmstart", "3it_no_warmstart")  # the solver starts from qacc_smooth


def main(argv: list[str]) -> None:
  onnx, names = argv[0], argv[1].split(",")
  unknown = [n for n in names if n not in VARIANTS]
  if unknown:
    sys.exit(f"error: variant {unknown[0]!r} is unknown; expected one of {', '.join(VARIANTS)}")
  band = (float(argv[2]), float(argv[3])) if len(argv) > 3 else (0.1, 0.2)
  cfg = robustness.BatteryConfig(friction_bands=(band,))
  spec = robots.load("booster_t1")
  dep = sim2sim.Deployment.from_metadata(export.read_metadata(onnx))
  conds = robustness.conditions(cfg)
  k = [c.name for c in conds].index(f"friction {band[0]:g}-{band[1]:g}")
  eps = robustness.episodes(conds, cfg, robustness.left_leg_mask(spec), dep.ctrl_dt)
  n = cfg.episodes
  jobs = [(i % n, robustness.Episodes(*(f[i] for f in eps))) for i in range(k * n, (k + 1) * n)]
  for name in names:
    t0 = time.perf_counter()
    runner = native_battery.Runner(native_battery.Setup(onnx, spec, VARIANTS[name], cfg))
    if name in NO_WARMSTART:
      runner.robot.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_WARMSTART
    alive, speed = zip(*(runner(j) for j in jobs))
    row = robustness.summarize([conds[k]], np.stack(alive), np.stack(speed), cfg)[0]
    print(
        json.dumps({
            "onnx": onnx, "variant": name, "friction": band, "episodes": n,
            "survival": row["survival"], "forward_speed": row["forward_speed"],
            "seconds": round(time.perf_counter() - t0)
        }), flush=True)


if __name__ == "__main__":
  main(sys.argv[1:])
