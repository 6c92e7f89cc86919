"""``python -m experiments.compare --task bipedal --seeds 5``: MASH vs single-agent PPO.

Trains both methods on the same budget and seeds (each method's seeds in one jitted call),
evaluates every seed, and writes ``report.md`` (the paper's metrics table with ours beside it),
``report.json``, ``reward_curves.png`` (mean and band over seeds) and ``hip_pitch.png``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from experiments import common

# The paper's Table "Evaluation metrics results" (Isaac Gym, BanXing robot).
PAPER = {
    "bipedal": {"mash": dict(T_conv=1306, S_action=0.107, S_torso=8.240e-4, C_limb=0.612),
                "ppo": dict(T_conv=1661, S_action=0.547, S_torso=3.398e-3, C_limb=0.974)},
    "armswing": {"mash": dict(T_conv=1017, S_action=0.124, S_torso=2.720e-3, C_limb=0.421),
                 "ppo": dict(T_conv=1238, S_action=0.546, S_torso=2.802e-2, C_limb=0.951)},
}
METRICS = ("T_conv", "S_action", "S_action_2nd", "S_torso", "C_limb", "fall_rate", "forward_speed")
NAMES = {"mash": "MASH", "ppo": "Single-agent PPO"}


def _fmt(mean: float, std: float) -> str:
  if mean is None or not np.isfinite(mean):
    return "n/a"
  if abs(mean) >= 100:
    return f"{mean:.0f} ± {std:.0f}"
  return f"{mean:.3g} ± {std:.2g}"


def build_report(task: str, results: dict, preset: str, seeds: int) -> tuple[str, dict]:
  """Markdown and JSON of the comparison from per-method evaluation results."""
  from mash import metrics as metrics_lib
  table = {}
  for algo, res in results.items():
    table[algo] = {}
    for k in METRICS:
      vals = [m[k] for m in res["per_seed"] if m.get(k) is not None]
      table[algo][k] = {**metrics_lib.seed_summary(vals), "values": vals}
  tests = {k: metrics_lib.welch_ttest(table["mash"][k]["values"], table["ppo"][k]["values"])
           for k in METRICS}
  lines = [f"# MASH vs single-agent PPO: {task}", "",
           f"Preset `{preset}`, {seeds} seeds per method, same budget; evaluation: deterministic "
           "policy, DR on, fixed forward command. Lower is better for T_conv, S_action, S_torso, "
           "C_limb. Mean ± std over seeds; p: Welch's t-test MASH vs PPO.", "",
           "| Method | T_conv | S_action | S_action (2nd diff.) | S_torso | C_limb | fall rate | "
           "forward speed (m/s) |", "|---|---|---|---|---|---|---|---|"]
  for algo in ("mash", "ppo"):
    row = [NAMES[algo] + " (ours)"] + [_fmt(table[algo][k]["mean"], table[algo][k]["std"])
                                       for k in METRICS]
    lines.append("| " + " | ".join(row) + " |")
  lines.append("| p (Welch) | " + " | ".join(
      "n/a" if not np.isfinite(tests[k]["p"]) else f"{tests[k]['p']:.3g}" for k in METRICS) + " |")
  for algo in ("mash", "ppo"):
    paper = PAPER[task][algo]
    lines.append(f"| {NAMES[algo]} (paper) | ~{paper['T_conv']} | {paper['S_action']} | – | "
                 f"{paper['S_torso']:.3g} | {paper['C_limb']} | – | – |")
  lines += ["", "## Verdict", ""]
  for k in ("T_conv", "S_action", "S_torso", "C_limb"):
    m, p_ = table["mash"][k]["mean"], table["ppo"][k]["mean"]
    if m is None or p_ is None or not (np.isfinite(m) and np.isfinite(p_)):
      lines.append(f"- {k}: not available.")
      continue
    better = m < p_
    sig = np.isfinite(tests[k]["p"]) and tests[k]["p"] < 0.05
    lines.append(f"- {k}: MASH {'lower' if better else 'not lower'} than PPO ({m:.4g} vs {p_:.4g})"
                 f"{', significant at p < 0.05' if sig else ', not significant'}"
                 f"; the paper reports MASH lower.")
  return "\n".join(lines) + "\n", {"task": task, "preset": preset, "seeds": seeds,
                                   "table": table, "welch": tests, "paper": PAPER[task]}


def plot_curves(run_dirs: dict, path: Path | None = None, names: dict | None = None):
  """Mean episode reward with a +-std band over seeds, one line per run directory."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  from mash import runs
  fig, ax = plt.subplots(figsize=(6.5, 3.8))
  for algo, d in run_dirs.items():
    p = runs.read_progress(d, per_seed=True)
    seeds = np.unique(p["seed"]).astype(int)
    curves = np.stack([p["episode_reward"][p["seed"] == s] for s in seeds])
    it = p["iteration"][p["seed"] == seeds[0]]
    mean, std = curves.mean(0), curves.std(0)
    ax.plot(it, mean, label=(names or NAMES).get(algo, algo))
    ax.fill_between(it, mean - std, mean + std, alpha=0.25)
  ax.set_xlabel("iteration")
  ax.set_ylabel("mean episode reward")
  ax.legend()
  ax.grid(alpha=0.3)
  fig.tight_layout()
  if path is not None:
    fig.savefig(path, dpi=120)
    plt.close(fig)
  return fig


def plot_hip(run_dirs: dict, path: Path, seconds: float = 3.0) -> None:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(2, 1, figsize=(7, 4.5), sharex=True)
  for algo, d in run_dirs.items():
    tr = np.load(Path(d) / "eval" / "trajectories.npz")
    n = min(int(seconds / float(tr["dt"])), tr["hip_pitch"].shape[1])
    t = np.arange(n) * float(tr["dt"])
    for i in range(2):
      axes[i].plot(t, tr["hip_pitch"][0, :n, i], label=NAMES[algo])
      if algo == "mash":
        axes[i].plot(t, tr["hip_pitch_ref"][0, :n, i], "--", color="green", label="reference")
  for i, side in enumerate(("left", "right")):
    axes[i].set_ylabel(f"{side} hip pitch (rad)")
    axes[i].grid(alpha=0.3)
  axes[0].legend(loc="upper right", fontsize=8)
  axes[1].set_xlabel("time (s)")
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def main(argv=None) -> None:
  p = common.Parser(prog="python -m experiments.compare", description=__doc__.splitlines()[0])
  p.add_argument("--task", default="bipedal", help="bipedal | armswing")
  p.add_argument("--seeds", type=int, default=5)
  p.add_argument("--preset", default=None, help="smoke | cpu | gpu (default: from the backend)")
  p.add_argument("--out", default=None, help="output directory (default: runs/compare_<task>_<time>)")
  p.add_argument("--episodes", type=int, default=16, help="evaluation episodes per seed")
  p.add_argument("--eval-seconds", type=float, default=20.0)
  p.add_argument("--set", action="append", default=[], metavar="PATH=VALUE")
  p.add_argument("--no-progress", action="store_true")
  args = p.parse_args(argv)
  with common.user_errors():
    from mash import evaluation, experiment, runs
    from experiments.evaluate import evaluate_run
    preset = args.preset or common.default_preset()[0]
    cfgs = {algo: experiment.make_config(args.task, algo, preset, args.seeds, "none", args.set)
            for algo in ("mash", "ppo")}
    out = Path(args.out or f"runs/compare_{args.task}_{preset}_{time.strftime('%Y%m%d-%H%M%S')}")
    print(f"preset: {preset}; comparing MASH and PPO on {args.task}, {args.seeds} seeds each -> "
          f"{out}", flush=True)
    eval_cfg = evaluation.EvalConfig(num_episodes=args.episodes, episode_s=args.eval_seconds)
    run_dirs, results = {}, {}
    for algo, cfg in cfgs.items():
      d = out / algo
      run_dirs[algo] = d
      if runs.is_run(d) and (d / "summary.json").exists() and not json.loads(
          (d / "summary.json").read_text()).get("interrupted"):
        print(f"[{algo}] already trained in {d}; reusing it", flush=True)
      else:
        print(f"[{algo}] training", flush=True)
        runs.train(cfg, d, resume=runs.is_run(d), show_progress=not args.no_progress)
      print(f"[{algo}] evaluating", flush=True)
      results[algo] = evaluate_run(str(d), eval_cfg)
    md, data = build_report(args.task, results, preset, args.seeds)
    (out / "report.md").write_text(md)
    (out / "report.json").write_text(json.dumps(data, indent=2, default=float))
    plot_curves(run_dirs, out / "reward_curves.png")
    plot_hip(run_dirs, out / "hip_pitch.png")
    print(md)
    print(f"wrote {out}/report.md, report.json, reward_curves.png, hip_pitch.png")


if __name__ == "__main__":
  main()
