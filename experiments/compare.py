"""``python -m experiments.compare --task bipedal --seeds 5``: MASH vs single-agent PPO.

Both methods get the same small tuning first: seed 0 at each of ``--learning-rates``, and one
rule (the highest final paper-weight episode reward) picks each method's rate (``tuning.json``).
Then both train on the same preset, budget and seeds, one run per method and seed, paired by seed
(``OUT/<algo>/lr<picked>/seed<s>/``, seed 0 being the search's run; each a plain ``python -m
experiments.<task>`` run with ``train.seed=s``, so on a CPU it uses both cores the same way).
The command resumes: a finished seed is reused, an interrupted one continues from its
checkpoint (or, when its checkpoints are not on this machine, trains again from the start, its
records moved to ``cut_off/``), so the runs can span several sittings; seeds run in pairs (MASH then PPO for seed 0,
then seed 1, ...). Every run is evaluated right after it trains, while its checkpoint is at hand
(``OUT/<algo>/lr<rate>/seed<s>/eval/``), and the report is rewritten after each pair:
``report.md`` (the paper's metrics table with ours beside it, statistics over seeds),
``report.json``, ``reward_curves.png`` (paper-weight reward, mean and band over seeds) and
``hip_pitch.png``.

``--seeds-at-once K`` (for a GPU) trains up to K consecutive seeds of a method that have no run yet
in one vmapped call (``OUT/<algo>/lr<rate>/group_seeds<a>-<b>/``, its ``i``-th seed keyed from
``a + i``: the same recipe and seed, not the same numbers as a single run of that seed, which
draws its keys per process), evaluates them together, then writes each seed's
records into ``seed<s>/`` as a single run leaves them (:func:`split_group`), so the report, a
resumed comparison and a CPU finishing it later treat them alike.
"""

from __future__ import annotations

import json
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


def _seeds(n: int) -> str:
  return f"{n} seed" + ("" if n == 1 else "s")


# Which way is better, per metric (forward speed: faster, at a command the policies fall short of).
LOWER_IS_BETTER = {"T_conv": True, "S_action": True, "S_action_2nd": True, "S_torso": True,
                   "C_limb": True, "C_limb_arm_leg": True, "fall_rate": True,
                   "forward_speed": False}
PAPER_METRICS = ("T_conv", "S_action", "S_torso", "C_limb")
ALL_EPISODE_METRICS = ("S_action", "S_action_2nd", "S_torso", "C_limb")


def _summary(values: list[float]) -> dict:
  from mash import metrics as metrics_lib
  lo, hi = metrics_lib.bootstrap_ci(values)
  return {**metrics_lib.seed_summary(values), "ci95": [lo, hi], "values": values}


def _tests(table: dict, keys: list[str]) -> dict:
  """Welch's test, Holm's correction over ``keys``, Hedges' g (MASH - PPO) and the verdict."""
  from mash import metrics as metrics_lib
  out = {k: metrics_lib.welch_ttest(table["mash"][k]["values"], table["ppo"][k]["values"])
         for k in keys}
  adjusted = metrics_lib.holm([out[k]["p"] for k in keys])
  for k, p_holm in zip(keys, adjusted):
    metric = k.split("/")[-1].split("@")[0]
    out[k].update(
        p_holm=p_holm,
        hedges_g=metrics_lib.hedges_g(table["mash"][k]["values"], table["ppo"][k]["values"]),
        verdict=metrics_lib.verdict(table["mash"][k]["mean"], table["ppo"][k]["mean"], p_holm,
                                    LOWER_IS_BETTER[metric]))
  return out


def build_report(task: str, results: dict, preset: str, seeds: int,
                 convergence: dict | None = None) -> tuple[str, dict]:
  """Markdown and JSON of the comparison from per-method evaluation results.

  ``convergence`` (``mash.metrics.common_threshold_t_conv`` of both methods' curves) adds one
  T_conv row per smoothing window: the first iteration a seed's smoothed paper-weight reward
  reaches the threshold common to both methods (seeds that never do are left out and counted).

  Per metric and method: mean, std and a 95 % bootstrap CI over seeds; between the methods:
  Welch's t-test, Holm's correction across every metric of the report, Hedges' g and a verdict
  ("MASH better", "PPO better" or "no difference at this power"). The smoothness, torso and
  coordination metrics are given twice: over the surviving episodes (the paper's) and over every
  episode up to its fall (``all_episodes``, when the evaluation has them), so that caution cannot
  win on its own.
  """
  table = {algo: {} for algo in results}
  keys = list(METRICS)
  if all("C_limb_arm_leg" in m for res in results.values() for m in res["per_seed"]):
    keys.insert(keys.index("C_limb") + 1, "C_limb_arm_leg")  # armswing: arms with opposite legs
  for algo, res in results.items():
    for k in keys:
      table[algo][k] = _summary([m[k] for m in res["per_seed"] if m.get(k) is not None])
  unreached = {}
  if convergence is not None:
    for w in convergence["windows"]:
      k = f"T_conv@{w}"
      keys.append(k)
      for algo in results:
        values = convergence["t_conv"][algo][w]
        table[algo][k] = _summary([v for v in values if v is not None])
        unreached[(algo, k)] = sum(v is None for v in values)
  if all("all_episodes" in m for res in results.values() for m in res["per_seed"]):
    for k in ALL_EPISODE_METRICS:
      keys.append(f"all_episodes/{k}")
      for algo, res in results.items():
        table[algo][f"all_episodes/{k}"] = _summary(
            [m["all_episodes"][k] for m in res["per_seed"] if m["all_episodes"][k] is not None])
  tests = _tests(table, keys)

  def cell(algo, k):
    t = table[algo][k]
    if t["n"] == 0 or not np.isfinite(t["mean"]):
      return "n/a"
    return f"{_fmt(t['mean'], t['std'])} [{t['ci95'][0]:.3g}, {t['ci95'][1]:.3g}]"

  lines = [f"# MASH vs single-agent PPO: {task}", "",
           f"Preset `{preset}`, {_seeds(seeds)} per method, same budget; evaluation: deterministic "
           "policy, DR on, fixed forward command. Lower is better for T_conv, S_action, S_torso, "
           "C_limb and the fall rate, higher for the forward speed. Mean ± std over seeds "
           "[95 % bootstrap CI]; p: Welch's t-test, Holm-adjusted over every metric below; g: "
           "Hedges' g of MASH - PPO.", "",
           "| metric | MASH (ours) | Single-agent PPO (ours) | p (Holm) | g | verdict | "
           "MASH (paper) | PPO (paper) |", "|---|---|---|---|---|---|---|---|"]
  for k in keys:
    t = tests[k]
    p_holm = "n/a" if not np.isfinite(t["p_holm"]) else f"{t['p_holm']:.3g}"
    g = "n/a" if not np.isfinite(t["hedges_g"]) else f"{t['hedges_g']:+.2f}"
    paper = [PAPER[task][a].get(k, "–") for a in ("mash", "ppo")]
    paper = [f"~{v}" if k == "T_conv" else (f"{v:.3g}" if isinstance(v, float) else v)
             for v in paper]
    name = k.replace("all_episodes/", "") + (" (all episodes, up to the fall)"
                                              if k.startswith("all_episodes/") else "")
    if "@" in k:
      w = k.split("@")[1]
      missed = [f"{NAMES[a]} {unreached[(a, k)]} seed(s)" for a in ("mash", "ppo")
                if unreached[(a, k)]]
      name = (f"T_conv (paper reward reaches {convergence['threshold']:.1f}, window {w})"
              + (f"; never reached: {', '.join(missed)}" if missed else ""))
    lines.append(f"| {name} | {cell('mash', k)} | {cell('ppo', k)} | {p_holm} | {g} | "
                 f"{t['verdict']} | {paper[0]} | {paper[1]} |")
  lines += ["", "## Verdict", ""]
  for k in [k for k in keys if k.split("/")[-1].split("@")[0] in PAPER_METRICS]:
    m, p_ = table["mash"][k]["mean"], table["ppo"][k]["mean"]
    label = k.replace("all_episodes/", "") + (" over all episodes" if "/" in k else "")
    if "@" in k:
      label = f"T_conv (common threshold, window {k.split('@')[1]})"
    if not (np.isfinite(m) and np.isfinite(p_)):
      lines.append(f"- {label}: not available.")
      continue
    p_holm = tests[k]["p_holm"]
    p_text = f"{p_holm:.3g}" if np.isfinite(p_holm) else "n/a, no test below two seeds a method"
    lines.append(f"- {label}: {tests[k]['verdict']} (MASH {m:.4g} vs PPO {p_:.4g}, Holm-adjusted "
                 f"p = {p_text}); the paper reports MASH lower.")
  return "\n".join(lines) + "\n", {"task": task, "preset": preset, "seeds": seeds,
                                    "table": table, "tests": tests, "paper": PAPER[task],
                                    "convergence": convergence}


def seed_dirs(run_dir) -> list[Path]:
  """The per-seed run directories of one method (``seed<s>/``, in seed order), the directory
  itself when it is a run (older layout: all seeds in one run), or the given list of them."""
  if isinstance(run_dir, (list, tuple)):
    return [Path(d) for d in run_dir]
  d = Path(run_dir)
  if (d / "config.json").is_file():
    return [d]
  return sorted((p for p in d.glob("seed*") if (p / "config.json").is_file()),
                key=lambda p: int(p.name[4:]) if p.name[4:].isdigit() else -1)


def method_curves(run_dir, key: str = "paper_episode_reward") -> tuple[np.ndarray, np.ndarray]:
  """``(iterations [N], curves [S, N])`` of a method's seeds (truncated to the shortest);
  ``run_dir`` as for :func:`seed_dirs`."""
  from mash import runs
  curves, iterations = [], None
  for d in seed_dirs(run_dir):
    p = runs.read_progress(d, per_seed=True)
    k = key if key in p else "episode_reward"
    for s in np.unique(p["seed"]).astype(int):
      curves.append(p[k][p["seed"] == s])
      if iterations is None or len(p["iteration"][p["seed"] == s]) < len(iterations):
        iterations = p["iteration"][p["seed"] == s]
  n = min(len(c) for c in curves)
  return iterations[:n], np.stack([c[:n] for c in curves])


def plot_curves(run_dirs: dict, path: Path | None = None, names: dict | None = None):
  """Mean paper-weight episode reward (the trained one for runs logged before it existed) with a
  +-std band over seeds, one line per method; ``run_dirs`` maps a method to its run directory or
  to the folder of its ``seed<s>/`` runs."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, ax = plt.subplots(figsize=(6.5, 3.8))
  for algo, d in run_dirs.items():
    it, curves = method_curves(d)
    mean, std = curves.mean(0), curves.std(0)
    ax.plot(it, mean, label=f"{(names or NAMES).get(algo, algo)} ({len(curves)} seeds)")
    ax.fill_between(it, mean - std, mean + std, alpha=0.25)
  ax.set_xlabel("iteration")
  ax.set_ylabel("episode reward (paper weights)")
  ax.legend()
  ax.grid(alpha=0.3)
  fig.tight_layout()
  if path is not None:
    fig.savefig(path, dpi=120)
    plt.close(fig)
  return fig


def hip_trace(seed_dir: Path, seconds: float = 3.0) -> dict:
  """The first evaluation episode's first ``seconds``: ``dt``, ``hip_pitch [T, 2]`` and
  ``hip_pitch_ref [T, 2]``, kept in ``eval/hip_trace.npz`` (a few KiB) the first time it is read
  from ``eval/trajectories.npz`` (megabytes, not committed), so that a report can be rebuilt from a
  comparison's committed records."""
  trace = Path(seed_dir) / "eval" / "hip_trace.npz"
  if not trace.is_file():
    save_hip_trace(trace, np.load(Path(seed_dir) / "eval" / "trajectories.npz"), seconds)
  with np.load(trace) as tr:
    return {k: tr[k] for k in tr.files}


def save_hip_trace(path: Path, trajectories, seconds: float = 3.0) -> None:
  """Writes the first episode's first ``seconds`` of ``trajectories`` (``dt``, ``hip_pitch
  [E, T, 2]``, ``hip_pitch_ref``) to ``path``: the arrays :func:`hip_trace` returns."""
  n = min(int(seconds / float(trajectories["dt"])), trajectories["hip_pitch"].shape[1])
  np.savez(path, dt=trajectories["dt"], hip_pitch=trajectories["hip_pitch"][0, :n],
           hip_pitch_ref=trajectories["hip_pitch_ref"][0, :n])


def plot_hip(run_dirs: dict, path: Path, seconds: float = 3.0) -> None:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(2, 1, figsize=(7, 4.5), sharex=True)
  for algo, d in run_dirs.items():
    tr = hip_trace(seed_dirs(d)[0], seconds)
    n = min(int(seconds / float(tr["dt"])), tr["hip_pitch"].shape[0])
    t = np.arange(n) * float(tr["dt"])
    for i in range(2):
      axes[i].plot(t, tr["hip_pitch"][:n, i], label=NAMES[algo])
      if algo == "mash":
        axes[i].plot(t, tr["hip_pitch_ref"][:n, i], "--", color="green", label="reference")
  for i, side in enumerate(("left", "right")):
    axes[i].set_ylabel(f"{side} hip pitch (rad)")
    axes[i].grid(alpha=0.3)
  axes[0].legend(loc="upper right", fontsize=8)
  axes[1].set_xlabel("time (s)")
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def seed_state(run_dir: Path, num_iterations: int) -> str:
  """``'done'`` (trained to ``num_iterations``), ``'resume'`` (a run that stopped early, with a
  checkpoint to go on from), ``'restart'`` (one that stopped early whose checkpoints are not
  here: a clone or a fresh machine holds the committed records only) or ``'new'`` (nothing
  there yet) for one seed's run directory."""
  if not (run_dir / "config.json").is_file():
    return "new"
  summary = run_dir / "summary.json"
  if summary.is_file():
    s = json.loads(summary.read_text())
    if not s.get("interrupted") and s.get("iterations", 0) >= num_iterations:
      return "done"
  checkpoints = run_dir / "checkpoints"
  if checkpoints.is_dir() and any(c.name.isdigit() for c in checkpoints.iterdir()):
    return "resume"
  return "restart"


def set_aside(run_dir: Path) -> Path:
  """Moves a cut-off seed's records to ``<its parent>/cut_off/<name>_<k>/`` (the first free
  ``k``), out of the report's way and never deleted; returns where they went."""
  k = 0
  while (dest := run_dir.parent / "cut_off" / f"{run_dir.name}_{k}").exists():
    k += 1
  dest.parent.mkdir(parents=True, exist_ok=True)
  run_dir.rename(dest)
  return dest


def group_dir(parent: Path, seeds: list[int]) -> Path:
  """Where seeds ``seeds`` (consecutive) of one method train together: ``group_seeds<a>-<b>/``
  (a name that :func:`seed_dirs` does not take for a seed's run)."""
  return Path(parent) / f"group_seeds{seeds[0]}-{seeds[-1]}"


def split_group(group: Path, seeds: list[int]) -> list[Path]:
  """Writes each seed of an evaluated multi-seed run ``group`` (its ``i``-th seed being seed
  ``seeds[i]``) into ``<group's parent>/seed<s>/`` with the records a single run of that seed
  leaves: ``config.json`` and ``summary.json`` (the group's, plus ``group`` and ``group_index``;
  its ``wall_s`` covers all the group's seeds), ``progress_seeds.csv`` and ``progress.csv`` (the
  seed's rows, seed column 0) and ``eval/`` (``metrics.json`` of that seed alone,
  ``hip_trace.npz``, ``hip_pitch.png``). Returns the seed directories."""
  import csv
  from experiments import evaluate
  from mash import policy as policy_lib
  metrics = json.loads((group / "eval" / "metrics.json").read_text())
  if len(metrics["per_seed"]) != len(seeds):
    raise common.UserError(f"'{group}' has {len(metrics['per_seed'])} evaluated seeds, "
                           f"expected {len(seeds)}")
  config = (group / "config.json").read_text()
  summary = json.loads((group / "summary.json").read_text())
  with open(group / "progress_seeds.csv", newline="") as f:
    reader = csv.DictReader(f)
    fields, rows = reader.fieldnames, list(reader)
  trajectories = np.load(group / "eval" / "trajectories.npz")
  dirs = []
  for i, seed in enumerate(seeds):
    d = group.parent / f"seed{seed}"
    (d / "eval").mkdir(parents=True, exist_ok=True)
    (d / "config.json").write_text(config)
    mine = [{**r, "seed": "0"} for r in rows if int(float(r["seed"])) == i]
    for name, columns in (("progress_seeds.csv", fields),
                          ("progress.csv", [c for c in fields if c != "seed"])):
      with open(d / name, "w", newline="") as f:
        writer = csv.DictWriter(f, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(mine)
    picked = trajectories["seed"] == i
    traj = {k: trajectories[k][picked] for k in trajectories.files if k != "dt"}
    alone = evaluate.summarize([metrics["per_seed"][i]], traj, metrics["eval_config"],
                               metrics["iteration"], evaluate.learning_curve(
                                   policy_lib.read_progress(d, per_seed=True), 0))
    (d / "eval" / "metrics.json").write_text(json.dumps(alone, indent=2))
    save_hip_trace(d / "eval" / "hip_trace.npz", {**traj, "dt": trajectories["dt"]})
    evaluate.plot_hip_pitch(traj, float(trajectories["dt"]), d / "eval" / "hip_pitch.png",
                            json.loads(config)["algo"])
    # Last: until it is there, the seed reads as stopped early (seed_state).
    (d / "summary.json").write_text(json.dumps(
        {**summary, "group": group.name, "group_index": i}, indent=2))
    dirs.append(d)
  return dirs


def consecutive_runs(seeds: list[int], most: int) -> list[list[int]]:
  """``seeds`` (ascending) cut into runs of consecutive seeds of at most ``most`` each."""
  groups: list[list[int]] = []
  for s in seeds:
    if groups and s == groups[-1][-1] + 1 and len(groups[-1]) < most:
      groups[-1].append(s)
    else:
      groups.append([s])
  return groups


def lr_dir(out: Path, algo: str, lr: float) -> Path:
  """Where a method's runs at one learning rate live: ``out/<algo>/lr<lr>/``."""
  return Path(out) / algo / f"lr{lr:g}"


def method_dir(out: Path, algo: str) -> Path:
  """A method's seed runs: ``out/<algo>/lr<picked>/`` when ``out/tuning.json`` names the picked
  learning rate, else ``out/<algo>/`` (a comparison without the search)."""
  tuning = Path(out) / "tuning.json"
  if tuning.is_file():
    return lr_dir(out, algo, json.loads(tuning.read_text())["picked"][algo])
  return Path(out) / algo


def pick_learning_rates(finals: dict[str, dict[float, float]]) -> dict[str, float]:
  """The search's rule, the same for both methods: per method, the learning rate whose seed-0
  run ends with the highest paper-weight episode reward (mean over its last 10 % of iterations);
  a tie goes to the smaller rate."""
  return {algo: max(sorted(by_lr), key=lambda lr: by_lr[lr]) for algo, by_lr in finals.items()}


def final_reward(run_dir: Path) -> float:
  """Mean paper-weight episode reward over a run's last 10 % of iterations."""
  curve = method_curves(run_dir)[1][0]
  return float(curve[-max(1, int(round(0.1 * len(curve)))):].mean())


def _seed_key(d: Path) -> str:
  return d.name if d.name.startswith("seed") and d.name[4:].isdigit() else "seed0"


def per_seed_table(results: dict, convergence: dict | None, dirs: dict, paired: list[str]) -> str:
  """The report's "Per seed" section: each paired seed's evaluation, T_conv (the common
  threshold, middle window) and training wall time (``summary.json``), MASH then PPO."""
  arms = all("C_limb_arm_leg" in m for res in results.values() for m in res["per_seed"])
  w = convergence["windows"][len(convergence["windows"]) // 2] if convergence else None
  head = ["seed", "method", "falls", "forward speed (m/s)", "S_action", "S_torso", "C_limb (rad)"]
  head += ["C_limb arm-leg (rad)"] * arms + ([f"T_conv (window {w})"] if w else [])
  head += ["training wall (s)"]
  lines = ["", "## Per seed", "",
           "Each seed's evaluation (`<algo>/lr<rate>/seed<s>/eval/metrics.json`); T_conv at the "
           "common threshold; the wall time includes whatever shared the cores (for seeds "
           "trained together, the whole group's, named beside it).", "",
           "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  for i, name in enumerate(paired):
    for algo in ("mash", "ppo"):
      m = results[algo]["per_seed"][i]
      summary = dirs[algo][i] / "summary.json"
      summary = json.loads(summary.read_text()) if summary.is_file() else {}
      wall, group = summary.get("wall_s"), summary.get("group")
      row = [name[4:], NAMES[algo], f"{100 * m['fall_rate']:.1f} %", f"{m['forward_speed']:.3f}",
             f"{m['S_action']:.3f}", f"{m['S_torso']:.3f}", f"{m['C_limb']:.3f}"]
      if arms:
        row.append(f"{m['C_limb_arm_leg']:.3f}")
      if w:
        t = convergence["t_conv"][algo][w][i]
        row.append("not reached" if t is None else str(t))
      row.append("n/a" if wall is None else f"{wall:.0f}" + (f" ({group})" if group else ""))
      lines.append("| " + " | ".join(row) + " |")
  return "\n".join(lines) + "\n"


def build_from_dirs(task: str, out: Path, preset: str) -> tuple[str, dict, dict]:
  """The report of the seeds evaluated so far in ``out/mash/`` and ``out/ppo/``, paired by seed:
  ``(markdown, data, {algo: [seed run directories]})``."""
  from mash import metrics as metrics_lib
  evaluated = {algo: {_seed_key(d): d for d in seed_dirs(method_dir(out, algo))
                      if (d / "eval" / "metrics.json").is_file()} for algo in ("mash", "ppo")}
  paired = sorted(set(evaluated["mash"]) & set(evaluated["ppo"]), key=lambda n: int(n[4:]))
  if not paired:
    raise common.UserError(f"'{out}' has no seed evaluated for both methods yet")
  dirs = {algo: [evaluated[algo][n] for n in paired] for algo in evaluated}
  results = {algo: {"per_seed": [json.loads((d / "eval" / "metrics.json").read_text())
                                 ["per_seed"][0] for d in dirs[algo]]} for algo in dirs}
  curves = {algo: method_curves(dirs[algo])[1] for algo in dirs}
  n_it = min(c.shape[1] for c in curves.values())
  convergence = metrics_lib.common_threshold_t_conv({a: c[:, :n_it] for a, c in curves.items()})
  md, data = build_report(task, results, preset, len(paired), convergence)
  data["seeds_paired"] = paired
  md += per_seed_table(results, convergence, dirs, paired)
  tuning = Path(out) / "tuning.json"
  if tuning.is_file():
    data["tuning"] = json.loads(tuning.read_text())
    t = data["tuning"]
    md += ("\n## Tuning\n\nThe same search for both methods: learning rates "
           + ", ".join(f"{lr:g}" for lr in t["learning_rates"]) + ", seed 0 each, the preset's "
           "budget; the rule picks the rate whose run ends with the highest paper-weight episode "
           "reward (mean of its last 10 % of iterations). Final rewards: "
           + "; ".join(f"{NAMES[a]} " + ", ".join(f"{lr} -> {r:.1f}"
                                                   for lr, r in t["final"][a].items())
                       for a in ("mash", "ppo"))
           + f". Picked: MASH {t['picked']['mash']:g}, PPO {t['picked']['ppo']:g}.\n")
  return md, data, dirs


def report(task: str, out: Path, preset: str) -> str:
  """Writes ``report.md``, ``report.json``, ``reward_curves.png`` and ``hip_pitch.png`` of the
  seeds evaluated so far (:func:`build_from_dirs`); returns the markdown."""
  md, data, dirs = build_from_dirs(task, out, preset)
  (out / "report.md").write_text(md)
  (out / "report.json").write_text(json.dumps(data, indent=2, default=float))
  plot_curves(dirs, out / "reward_curves.png")
  plot_hip({algo: d[0] for algo, d in dirs.items()}, out / "hip_pitch.png")
  return md


# After T_conv (the common-threshold one at the middle window), these rows, in this order.
README_ROWS = (("S_action", "S_action"), ("S_torso", "S_torso"), ("C_limb", "C_limb (rad)"),
               ("C_limb_arm_leg", "C_limb arm-leg (rad)"), ("fall_rate", "fall rate"),
               ("forward_speed", "forward speed (m/s)"))
README_BEGIN = "<!-- generated by: python -m experiments.compare --readme-table"
README_END = "<!-- end of the generated table -->"


def _cell(summary: dict) -> str:
  """Mean ± std over seeds; the mean alone for one seed, whose spread is unknown."""
  if summary["n"] == 0:
    return "n/a"
  if summary["n"] == 1:
    return f"{summary['mean']:.0f}" if abs(summary["mean"]) >= 100 else f"{summary['mean']:.3g}"
  return _fmt(summary["mean"], summary["std"])


def readme_table(reports: list[dict]) -> str:
  """The README's table from comparison reports (``report.json`` of each task): per task and
  metric, ours (mean ± std over the paired seeds) beside the paper's, with the report's verdict.
  T_conv is the common-threshold one at the middle smoothing window (the paper's T_conv is taken
  on its own runs and budget, so only the direction compares)."""
  lines = ["| task | metric | MASH (ours) | PPO (ours) | verdict (ours) | MASH (paper) | "
           "PPO (paper) |", "|---|---|---|---|---|---|---|"]
  for rep in reports:
    task, table, tests = rep["task"], rep["table"], rep["tests"]
    rows = [(key, key, label) for key, label in README_ROWS if key in table["mash"]]
    conv = rep.get("convergence")
    if conv and conv["windows"]:
      w = conv["windows"][len(conv["windows"]) // 2]
      rows.insert(0, (f"T_conv@{w}", "T_conv",
                      f"T_conv (iterations to {conv['threshold']:.1f}, window {w})"))
    for k, key, label in rows:
      cells = [_cell(table[a][k]) for a in ("mash", "ppo")]
      paper = [PAPER[task][a].get(key) for a in ("mash", "ppo")]
      paper = ["–" if v is None else f"{v:.4g}" for v in paper]
      lines.append(f"| {task} ({_seeds(rep['seeds'])}) | {label} | {cells[0]} | {cells[1]} | "
                   f"{tests[k]['verdict']} | {paper[0]} | {paper[1]} |")
  return "\n".join(lines) + "\n"


def readme_block(dirs: list[str], root: Path | None = None) -> str:
  """The README's generated block: the marker naming the command and ``dirs`` (relative to
  ``root``, default the working directory), the table of their ``report.json``, the end marker."""
  reports = []
  for d in dirs:
    f = Path(root or ".") / d / "report.json"
    if not f.is_file():
      raise common.UserError(f"--readme-table {d}: expected a comparison folder with a "
                             "report.json (it comes after the first seed pair)")
    reports.append(json.loads(f.read_text()))
  return f"{README_BEGIN} {' '.join(dirs)} -->\n{readme_table(reports)}{README_END}\n"


def main(argv=None) -> None:
  p = common.Parser(prog="python -m experiments.compare", description=__doc__.splitlines()[0])
  p.add_argument("--task", default="bipedal", help="bipedal | armswing")
  p.add_argument("--seeds", type=int, default=5)
  p.add_argument("--preset", default=None, help="smoke | cpu | gpu (default: from the backend)")
  p.add_argument("--out", default=None,
                 help="output directory; run the same command again to continue it (default: "
                      "runs/compare_<task>_<preset>)")
  p.add_argument("--episodes", type=int, default=128, help="evaluation episodes per seed")
  p.add_argument("--eval-seconds", type=float, default=20.0)
  p.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                 help="override a config field of both methods (repeatable)")
  p.add_argument("--learning-rates", default="1e-3,3e-4", metavar="LR,LR",
                 help="the search both methods get: seed 0 at each rate, the same rule picks "
                      "each method's (default 1e-3,3e-4)")
  p.add_argument("--robot", default=None, metavar="NAME|FILE.toml",
                 help="a shipped robot (booster_t1, unitree_g1) or a robot file (default: "
                      "booster_t1; the same as --set env.robot=...)")
  p.add_argument("--seeds-at-once", type=int, default=1, metavar="K",
                 help="train up to K seeds of a method without a run yet in one vmapped call "
                      "(for a GPU; default 1: one run per seed)")
  p.add_argument("--no-progress", action="store_true")
  p.add_argument("--readme-table", nargs="+", default=None, metavar="DIR",
                 help="print the README's table from these comparison folders' report.json "
                      "(one per task) instead of running anything")
  args = p.parse_args(argv)
  if args.readme_table is not None:
    with common.user_errors():
      print(readme_block(args.readme_table), end="")
    return
  with common.user_errors():
    import subprocess
    import sys
    from mash import evaluation, experiment
    from experiments.evaluate import evaluate_run
    common.check_paths({"--out": args.out})
    common.check_task(args.task)
    if args.seeds < 1 or args.episodes < 1 or not args.eval_seconds > 0:
      raise common.UserError("--seeds and --episodes must be >= 1 and --eval-seconds > 0")
    if args.seeds_at_once < 1:
      raise common.UserError(f"--seeds-at-once must be >= 1, got {args.seeds_at_once}")
    try:
      evaluation.check_config(
          evaluation.EvalConfig(num_episodes=args.episodes, episode_s=args.eval_seconds),
          {"num_episodes": "--episodes", "episode_s": "--eval-seconds"})
    except ValueError as e:
      raise common.UserError(str(e)) from None
    try:
      learning_rates = sorted({float(x) for x in args.learning_rates.split(",") if x.strip()})
    except ValueError:
      learning_rates = []
    if not learning_rates or not all(0 < lr < 1 for lr in learning_rates):
      raise common.UserError(f"--learning-rates '{args.learning_rates}': expected rates in (0, 1) "
                             "separated by commas, e.g. 1e-3,3e-4")
    if args.robot is not None:  # before the --set overrides, so that those still win
      args.set = [f"env.robot={common.robot_arg(args.robot)}", *args.set]
    preset = args.preset or common.default_preset()[0]
    cfgs = {algo: experiment.make_config(args.task, algo, preset, 1, "none", args.set)
            for algo in ("mash", "ppo")}
    out = Path(args.out or f"runs/compare_{args.task}_{preset}")
    common.check_writable_dir(out, "--out")
    print(f"preset: {preset}; MASH vs PPO on {args.task}, seeds 0-{args.seeds - 1}, one run per "
          f"method and seed -> {out} (a finished seed is reused, an interrupted one resumed)",
          flush=True)
    eval_cfg = evaluation.EvalConfig(num_episodes=args.episodes, episode_s=args.eval_seconds)

    def train_run(algo: str, lr: float, d: Path, seeds: list[int]) -> Path:
      """Trains the run ``d`` of ``seeds`` (one seed, or consecutive ones in one vmapped call),
      or resumes or reuses it, then evaluates it unless its evaluation is there."""
      which = f"seed {seeds[0]}" + (f"-{seeds[-1]}" if len(seeds) > 1 else "")
      label = f"[{algo} lr {lr:g} {which}]"
      state = seed_state(d, cfgs[algo].train.num_iterations)
      what = {"done": "trained; reusing it", "resume": "resuming", "new": "training",
              "restart": "stopped early with no checkpoint here; training it again"}[state]
      print(f"{label} {what}", flush=True)
      if state == "restart":
        print(f"{label} its records moved to {set_aside(d)}", flush=True)
      if state != "done":
        command = [sys.executable, "-m", f"experiments.{args.task}"]
        if state == "resume":
          command += ["--resume", str(d)]
        else:
          command += ["--algo", algo, "--preset", preset, "--out", str(d),
                      "--set", f"train.seed={seeds[0]}", "--set", f"train.learning_rate={lr:g}"]
          command += ["--seeds", str(len(seeds))] if len(seeds) > 1 else []
          command += [x for o in args.set for x in ("--set", o)]
        if args.no_progress:
          command.append("--no-progress")
        code = subprocess.call(command)
        if code != 0:
          raise common.UserError(f"the {algo} run of {which} stopped with status {code}; run "
                                 f"the same command again to resume it ({d})")
      # Right after training, while the checkpoint is on this machine: checkpoints are not
      # kept in git, so a later session or a clone may hold only the records.
      metrics_file = d / "eval" / "metrics.json"
      fresh = (metrics_file.is_file() and json.loads(metrics_file.read_text())
               .get("eval_config", {}).get("num_episodes") == args.episodes)
      if not fresh:
        print(f"{label} evaluating on {args.episodes} episodes", flush=True)
        evaluate_run(str(d), eval_cfg)
      return d

    def train_seed(algo: str, lr: float, seed: int) -> Path:
      d = train_run(algo, lr, lr_dir(out, algo, lr) / f"seed{seed}", [seed])
      hip_trace(d)  # the few KiB of the hip-pitch plot that the committed records keep
      return d

    def train_block(algo: str, lr: float, block: list[int]) -> None:
      """Seeds ``block`` of one method: those without a run yet train together, up to
      ``--seeds-at-once`` consecutive ones per call, and are split into their ``seed<s>/``;
      the rest as single runs (reused when done, resumed when stopped early)."""
      parent = lr_dir(out, algo, lr)
      n_it = cfgs[algo].train.num_iterations
      pending = [s for s in block if seed_state(parent / f"seed{s}", n_it) in ("new", "restart")]
      for group in consecutive_runs(pending, args.seeds_at_once):
        if len(group) == 1:
          continue
        for s in group:
          if (parent / f"seed{s}" / "config.json").is_file():
            print(f"[{algo} lr {lr:g} seed {s}] its records moved to "
                  f"{set_aside(parent / f'seed{s}')}", flush=True)
        split_group(train_run(algo, lr, group_dir(parent, group), group), group)
      for s in block:
        train_seed(algo, lr, s)

    # The same small search for both methods: seed 0 at each rate, the same rule picks.
    finals = {algo: {lr: final_reward(train_seed(algo, lr, 0)) for lr in learning_rates}
              for algo in cfgs}
    picked = pick_learning_rates(finals)
    (out / "tuning.json").write_text(json.dumps({
        "learning_rates": learning_rates, "seed": 0, "picked": picked,
        "final": {a: {f"{lr:g}": r for lr, r in f.items()} for a, f in finals.items()},
        "rule": "highest mean paper-weight episode reward over the last 10 % of iterations"},
        indent=2))
    print(f"learning rates picked by the search: MASH {picked['mash']:g}, PPO {picked['ppo']:g}",
          flush=True)
    # Seed 0 is the search's run; the others go in blocks of --seeds-at-once.
    k = args.seeds_at_once
    blocks = [[0]] + [list(range(a, min(a + k, args.seeds))) for a in range(1, args.seeds, k)]
    for block in blocks:
      for algo in cfgs:
        train_block(algo, picked[algo], block)
      md = report(args.task, out, preset)
      print(f"report after {block[-1] + 1} paired seed(s): {out}/report.md", flush=True)
    print(md)
    print(f"wrote {out}/report.md, report.json, reward_curves.png, hip_pitch.png")


if __name__ == "__main__":
  main()
