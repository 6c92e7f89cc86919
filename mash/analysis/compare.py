"""The MASH-vs-PPO comparison's statistics and report, from the runs' committed records.

Fixed before the runs (issue 54): the **primary family** is the paper's four metrics as the paper
defines them, over the surviving episodes: ``T_conv`` (SPEC's: the first iteration after which a
seed's smoothed reward stays within 5 % of its asymptote), ``S_action``, ``S_torso`` and
``C_limb``; the verdict on the paper's claim is Welch's t-test over seeds with Holm's correction
over these four alone. Everything else (speed, falls, the second-difference and all-episode
variants, ``T_conv`` at a threshold common to both methods and three smoothing windows, the
arms' coordination with the legs, the robustness battery's conditions) is the **secondary
family**, Holm-corrected on its own, reported but not deciding the verdict. Each primary metric
also gets the power of its test at the observed effect and the smallest effect the seed count
detects at 80 % power, at Holm's strictest level (alpha / 4, so a lower bound for Holm's).

The training runs behind a comparison are :mod:`mash.runs.comparison`'s; nothing here trains.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from mash.analysis import metrics as metrics_lib
from mash.deploy import policy as policy_lib
from mash.errors import InputError

# The paper's Table "Evaluation metrics results" (Isaac Gym, BanXing robot).
PAPER = {
    "bipedal": {
        "mash": dict(T_conv=1306, S_action=0.107, S_torso=8.240e-4, C_limb=0.612),
        "ppo": dict(T_conv=1661, S_action=0.547, S_torso=3.398e-3, C_limb=0.974)
    },
    "armswing": {
        "mash": dict(T_conv=1017, S_action=0.124, S_torso=2.720e-3, C_limb=0.421),
        "ppo": dict(T_conv=1238, S_action=0.546, S_torso=2.802e-2, C_limb=0.951)
    },
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
LOWER_IS_BETTER = {
    "T_conv": True, "S_action": True, "S_action_2nd": True, "S_torso": True, "C_limb": True,
    "C_limb_arm_leg": True, "fall_rate": True, "forward_speed": False, "survival": False
}
PAPER_METRICS = ("T_conv", "S_action", "S_torso", "C_limb")
ALL_EPISODE_METRICS = ("S_action", "S_action_2nd", "S_torso", "C_limb")

PRIMARY = PAPER_METRICS  # the verdict's family, fixed before the runs
# The robustness batteries a kept policy may hold (``seed<s>/policy/<folder>/robustness.json``)
# and the prefix of their report keys: ``robustness_mjx/kick 0.5 m/s`` is that condition's
# survival in MJX.
BATTERIES = {
    "robustness_mjx": ("eval_robustness", "MJX"),
    "robustness_native": ("sim2sim_robustness", "MuJoCo C")
}
MIN_BATTERY_SEEDS = 2  # a battery's rows need this many seeds a method (Welch's test needs 2)
ALPHA = 0.05
POWER = 0.8


def _summary(values: list[float]) -> dict:
  lo, hi = metrics_lib.bootstrap_ci(values)
  return {**metrics_lib.seed_summary(values), "ci95": [lo, hi], "values": values}


def _metric_of(key: str) -> str:
  """The metric a report key measures: ``all_episodes/S_action`` and ``T_conv@25`` -> the name
  :data:`LOWER_IS_BETTER` knows; a battery's condition -> ``survival``."""
  if key.split("/")[0] in BATTERIES:
    return "survival"
  return key.split("/")[-1].split("@")[0]


def battery_survival(seed_dir: Path) -> dict[str, float]:
  """``{'<battery>/<condition>': survival}`` of every robustness battery that the seed's kept
  policy holds (none without one)."""
  out = {}
  for prefix, (folder, _) in BATTERIES.items():
    path = Path(seed_dir) / "policy" / folder / "robustness.json"
    if path.is_file():
      for row in json.loads(path.read_text())["conditions"]:
        out[f"{prefix}/{row['name']}"] = float(row["survival"])
  return out


def _battery_keys(results: dict) -> list[str]:
  """The battery conditions that at least :data:`MIN_BATTERY_SEEDS` seeds of each method were
  put through, in the batteries' order."""
  keys: list[str] = []
  for m in results["mash"]["per_seed"]:
    keys += [k for k in m if k.split("/")[0] in BATTERIES and k not in keys]
  return [
      k for k in keys if all(
          sum(k in m for m in res["per_seed"]) >= MIN_BATTERY_SEEDS for res in results.values())
  ]


def family_tests(table: dict, keys: list[str], family: str) -> dict:
  """Welch's test, Holm's correction over ``keys`` (one family), Hedges' g (MASH - PPO) and the
  verdict; for the primary family also the power at the observed effect and the smallest
  detectable effect at :data:`POWER`, both at Holm's strictest level ``ALPHA / len(keys)``."""
  # yapf: disable
  out = {
      k: metrics_lib.welch_ttest(table["mash"][k]["values"], table["ppo"][k]["values"])
      for k in keys
  }
  # yapf: enable
  adjusted = metrics_lib.holm([out[k]["p"] for k in keys])
  for k, p_holm in zip(keys, adjusted):
    a, b = table["mash"][k]["values"], table["ppo"][k]["values"]
    g = metrics_lib.hedges_g(a, b)
    out[k].update(
        family=family, p_holm=p_holm, hedges_g=g,
        verdict=metrics_lib.verdict(table["mash"][k]["mean"], table["ppo"][k]["mean"], p_holm,
                                    LOWER_IS_BETTER[_metric_of(k)]))
    if family == "primary":
      alpha = ALPHA / len(keys)
      out[k].update(power=metrics_lib.t_test_power(g, len(a), len(b), alpha),
                    detectable_effect=metrics_lib.detectable_effect(len(a), len(b), alpha,
                                                                    POWER), alpha=alpha)
  return out


def _metric_table(results: dict, convergence: dict | None) -> tuple[dict, dict, list[str]]:
  """Per method and report key, the summary over seeds; the seeds that never reached the common
  threshold; and the secondary family's keys in report order."""
  table = {algo: {} for algo in results}
  secondary = ["S_action_2nd", "fall_rate", "forward_speed"]
  if all("C_limb_arm_leg" in m for res in results.values() for m in res["per_seed"]):
    secondary.insert(0, "C_limb_arm_leg")  # armswing: arms with opposite legs
  for algo, res in results.items():
    for k in [*PRIMARY, *secondary]:
      table[algo][k] = _summary([m[k] for m in res["per_seed"] if m.get(k) is not None])
  unreached = {}
  if convergence is not None:
    for w in convergence["windows"]:
      k = f"T_conv@{w}"
      secondary.append(k)
      for algo in results:
        values = convergence["t_conv"][algo][w]
        table[algo][k] = _summary([v for v in values if v is not None])
        unreached[(algo, k)] = sum(v is None for v in values)
  if all("all_episodes" in m for res in results.values() for m in res["per_seed"]):
    for k in ALL_EPISODE_METRICS:
      secondary.append(f"all_episodes/{k}")
      for algo, res in results.items():
        table[algo][f"all_episodes/{k}"] = _summary([
            m["all_episodes"][k] for m in res["per_seed"] if m["all_episodes"][k] is not None
        ])
  for k in _battery_keys(results):
    secondary.append(k)
    for algo, res in results.items():
      table[algo][k] = _summary([m[k] for m in res["per_seed"] if k in m])
  return table, unreached, secondary


def _cell(table: dict, algo: str, k: str) -> str:
  t = table[algo][k]
  if t["n"] == 0 or not np.isfinite(t["mean"]):
    return "n/a"
  return f"{_fmt(t['mean'], t['std'])} [{t['ci95'][0]:.3g}, {t['ci95'][1]:.3g}]"


def _row_name(k: str, convergence: dict | None, unreached: dict, table: dict | None = None) -> str:
  if k.split("/")[0] in BATTERIES:
    seeds = ""
    if table:  # where the methods hold the battery on different seed counts: both, MASH's first
      n_mash, n_ppo = (table[a][k]["n"] for a in ("mash", "ppo"))
      seeds = f", {n_mash} seeds" if n_mash == n_ppo else f", {n_mash} / {n_ppo} seeds"
    return f"survival: {k.split('/', 1)[1]} ({BATTERIES[k.split('/')[0]][1]} battery{seeds})"
  name = k.replace("all_episodes/", "") + (" (all episodes, up to the fall)"
                                           if k.startswith("all_episodes/") else "")
  if "@" in k:
    missed = [
        f"{NAMES[a]} {unreached[(a, k)]} seed(s)" for a in ("mash", "ppo") if unreached[(a, k)]
    ]
    name = (f"T_conv (paper reward reaches {convergence['threshold']:.1f}, window "
            f"{k.split('@')[1]})" + (f"; never reached: {', '.join(missed)}" if missed else ""))
  return name


def _family_rows(task: str, table: dict, tests: dict, keys: list[str], convergence: dict | None,
                 unreached: dict) -> list[str]:
  primary = tests[keys[0]]["family"] == "primary"
  head = "| metric | MASH (ours) | Single-agent PPO (ours) | p (Holm) | g |"
  head += " power | detectable g |" if primary else ""
  head += " verdict | MASH (paper) | PPO (paper) |"
  lines = [head, "|" + "---|" * (head.count("|") - 1)]
  for k in keys:
    t = tests[k]
    p_holm = "n/a" if not np.isfinite(t["p_holm"]) else f"{t['p_holm']:.3g}"
    g = "n/a" if not np.isfinite(t["hedges_g"]) else f"{t['hedges_g']:+.2f}"
    paper = [PAPER[task][a].get(k, "–") for a in ("mash", "ppo")]
    paper = [
        f"~{v}" if k == "T_conv" else (f"{v:.3g}" if isinstance(v, float) else v) for v in paper
    ]
    power = ""
    if primary:
      power = (f" {t['power']:.2f} | {t['detectable_effect']:.2f} |"
               if np.isfinite(t["power"]) else " n/a | n/a |")
    lines.append(f"| {_row_name(k, convergence, unreached, table)} | {_cell(table, 'mash', k)} | "
                 f"{_cell(table, 'ppo', k)} | {p_holm} | {g} |{power} {t['verdict']} | "
                 f"{paper[0]} | {paper[1]} |")
  return lines


def _verdict_lines(table: dict, tests: dict) -> list[str]:
  lines = []
  for k in PRIMARY:
    m, p_ = table["mash"][k]["mean"], table["ppo"][k]["mean"]
    if not (np.isfinite(m) and np.isfinite(p_)):
      lines.append(f"- {k}: not available.")
      continue
    t = tests[k]
    p_text = (f"{t['p_holm']:.3g}"
              if np.isfinite(t["p_holm"]) else "n/a, no test below two seeds a method")
    power = (f"; power {t['power']:.2f} at the observed g {t['hedges_g']:+.2f}, "
             f"{POWER:.0%} power from |g| {t['detectable_effect']:.2f}"
             if np.isfinite(t["power"]) else "")
    lines.append(f"- {k}: {t['verdict']} (MASH {m:.4g} vs PPO {p_:.4g}, Holm-adjusted "
                 f"p = {p_text}{power}); the paper reports MASH lower.")
  return lines


def build_report(task: str, results: dict, preset: str, seeds: int,
                 convergence: dict | None = None) -> tuple[str, dict]:
  """Markdown and JSON of the comparison from per-method evaluation results.

  ``results[algo]['per_seed']``: each paired seed's ``eval/metrics.json`` ``per_seed[0]``;
  ``convergence`` (:func:`mash.analysis.metrics.common_threshold_t_conv` of both methods' curves)
  adds the secondary family's T_conv rows, one per smoothing window. Per metric and method: mean,
  std and a 95 % bootstrap CI over seeds; between the methods, per family (module docstring):
  Welch's t-test, Holm's correction, Hedges' g and a verdict ("MASH better", "PPO better" or
  "no difference at this power"); the primary family's rows add the power figures.
  """
  table, unreached, secondary = _metric_table(results, convergence)
  tests = {
      **family_tests(table, list(PRIMARY), "primary"), **family_tests(table, secondary, "secondary")
  }
  lines = [
      f"# MASH vs single-agent PPO: {task}", "",
      f"Preset `{preset}`, {_seeds(seeds)} per method, same budget; evaluation: deterministic "
      "policy, DR on, fixed forward command. Lower is better for T_conv, S_action, S_torso, "
      "C_limb and the fall rate, higher for the forward speed. Mean ± std over seeds "
      "[95 % bootstrap CI]; p: Welch's t-test, Holm-adjusted within its family; g: "
      "Hedges' g of MASH - PPO.", "",
      "## Primary family: the paper's four metrics (they decide the verdict)", "",
      f"Holm over these four. Power: of each test at the observed g, at Holm's strictest "
      f"level alpha = {ALPHA:g} / {len(PRIMARY)}; detectable g: the smallest effect "
      f"{_seeds(seeds)} per method detect with {POWER:.0%} power there.", "",
      *_family_rows(task, table, tests, list(PRIMARY), convergence, unreached), "",
      "## Secondary family (reported; Holm over these rows; not deciding the verdict)", "",
      *_family_rows(task, table, tests, secondary, convergence, unreached), "",
      "## Verdict (primary family)", "", *_verdict_lines(table, tests)
  ]
  data = {
      "task": task, "preset": preset, "seeds": seeds, "table": table, "tests": tests, "families": {
          "primary": list(PRIMARY), "secondary": secondary, "alpha": ALPHA, "power": POWER
      }, "paper": PAPER[task], "convergence": convergence
  }
  return "\n".join(lines) + "\n", data


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
  curves, iterations = [], None
  for d in seed_dirs(run_dir):
    p = policy_lib.read_progress(d, per_seed=True)
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
  fig = Figure(figsize=(6.5, 3.8))
  ax = fig.subplots()
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
  fig = Figure(figsize=(7, 4.5))
  axes = fig.subplots(2, 1, sharex=True)
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


def per_seed_table(results: dict, convergence: dict | None, dirs: dict, paired: list[str]) -> str:
  """The report's "Per seed" section: each paired seed's evaluation, T_conv (the common
  threshold, middle window) and training wall time (``summary.json``), MASH then PPO."""
  arms = all("C_limb_arm_leg" in m for res in results.values() for m in res["per_seed"])
  w = convergence["windows"][len(convergence["windows"]) // 2] if convergence else None
  head = ["seed", "method", "falls", "forward speed (m/s)", "S_action", "S_torso", "C_limb (rad)"]
  head += ["C_limb arm-leg (rad)"] * arms + ([f"T_conv (window {w})"] if w else [])
  head += ["training wall (s)"]
  lines = [
      "", "## Per seed", "",
      "Each seed's evaluation (`<algo>/lr<rate>/seed<s>/eval/metrics.json`); T_conv at the "
      "common threshold; the wall time includes whatever shared the cores (for seeds "
      "trained together, the whole group's, named beside it).", "", "| " + " | ".join(head) + " |",
      "|" + "---|" * len(head)
  ]
  for i, name in enumerate(paired):
    for algo in ("mash", "ppo"):
      m = results[algo]["per_seed"][i]
      summary = dirs[algo][i] / "summary.json"
      summary = json.loads(summary.read_text()) if summary.is_file() else {}
      wall, group = summary.get("wall_s"), summary.get("group")
      row = [
          name[4:], NAMES[algo], f"{100 * m['fall_rate']:.1f} %", f"{m['forward_speed']:.3f}",
          f"{m['S_action']:.3f}", f"{m['S_torso']:.3f}", f"{m['C_limb']:.3f}"
      ]
      if arms:
        row.append(f"{m['C_limb_arm_leg']:.3f}")
      if w:
        t = convergence["t_conv"][algo][w][i]
        row.append("not reached" if t is None else str(t))
      row.append("n/a" if wall is None else f"{wall:.0f}" + (f" ({group})" if group else ""))
      lines.append("| " + " | ".join(row) + " |")
  return "\n".join(lines) + "\n"


def build_from_dirs(task: str, out: Path, preset: str,
                    method_dirs: dict[str, Path]) -> tuple[str, dict, dict]:
  """The report of the seeds evaluated so far in ``method_dirs`` (a method -> the folder of its
  ``seed<s>/`` runs), paired by seed: ``(markdown, data, {algo: [seed run directories]})``."""
  evaluated = {
      algo: {
          _seed_key(d): d
          for d in seed_dirs(method_dirs[algo])
          if (d / "eval" / "metrics.json").is_file()
      } for algo in ("mash", "ppo")
  }
  paired = sorted(set(evaluated["mash"]) & set(evaluated["ppo"]), key=lambda n: int(n[4:]))
  if not paired:
    raise InputError(f"'{out}' has no seed evaluated for both methods yet")
  dirs = {algo: [evaluated[algo][n] for n in paired] for algo in evaluated}
  results = {
      algo: {
          "per_seed": [{
              **json.loads((d / "eval" / "metrics.json").read_text())["per_seed"][0],
              **battery_survival(d)
          } for d in dirs[algo]]
      } for algo in dirs
  }
  curves = {algo: method_curves(dirs[algo])[1] for algo in dirs}
  n_it = min(c.shape[1] for c in curves.values())
  convergence = metrics_lib.common_threshold_t_conv({a: c[:, :n_it] for a, c in curves.items()})
  md, data = build_report(task, results, preset, len(paired), convergence)
  data["seeds_paired"] = paired
  md += per_seed_table(results, convergence, dirs, paired)
  tuning = Path(out) / "tuning.json"
  if tuning.is_file():
    data["tuning"] = json.loads(tuning.read_text())
    md += _tuning_text(data["tuning"])
  return md, data, dirs


def _tuning_text(t: dict) -> str:
  return ("\n## Tuning\n\nThe same search for both methods: learning rates " +
          ", ".join(f"{lr:g}" for lr in t["learning_rates"]) + ", seed 0 each, the preset's "
          "budget; the rule picks the rate whose run ends with the highest paper-weight episode "
          "reward (mean of its last 10 % of iterations). Final rewards: " +
          "; ".join(f"{NAMES[a]} " + ", ".join(f"{lr} -> {r:.1f}"
                                               for lr, r in t["final"][a].items())
                    for a in ("mash", "ppo")) +
          f". Picked: MASH {t['picked']['mash']:g}, PPO {t['picked']['ppo']:g}.\n")


def write_report(task: str, out: Path, preset: str, method_dirs: dict[str, Path]) -> str:
  """Writes ``report.md``, ``report.json``, ``reward_curves.png`` and ``hip_pitch.png`` of the
  seeds evaluated so far (:func:`build_from_dirs`); returns the markdown."""
  md, data, dirs = build_from_dirs(task, out, preset, method_dirs)
  (out / "report.md").write_text(md)
  (out / "report.json").write_text(json.dumps(data, indent=2, default=float))
  plot_curves(dirs, out / "reward_curves.png")
  plot_hip({algo: d[0] for algo, d in dirs.items()}, out / "hip_pitch.png")
  return md


def _seed_key(d: Path) -> str:
  return d.name if d.name.startswith("seed") and d.name[4:].isdigit() else "seed0"


# The README's rows: the primary family, then these of the secondary one (T_conv at the common
# threshold and the middle window first), in this order.
README_SECONDARY = (("C_limb_arm_leg", "C_limb arm-leg (rad)"), ("fall_rate", "fall rate"),
                    ("forward_speed", "forward speed (m/s)"))
README_PRIMARY = (("T_conv", "T_conv (iterations)"), ("S_action", "S_action"),
                  ("S_torso", "S_torso"), ("C_limb", "C_limb (rad)"))
README_BEGIN = "<!-- generated by: python -m experiments.compare --readme-table"
README_END = "<!-- end of the generated table -->"


def _readme_cell(summary: dict) -> str:
  """Mean ± std over seeds; the mean alone for one seed, whose spread is unknown."""
  if summary["n"] == 0:
    return "n/a"
  if summary["n"] == 1:
    return f"{summary['mean']:.0f}" if abs(summary["mean"]) >= 100 else f"{summary['mean']:.3g}"
  return _fmt(summary["mean"], summary["std"])


def _readme_rows(rep: dict) -> list[tuple[str, str, str, str]]:
  """``(report key, paper key, label, family)`` of one report's README rows."""
  table = rep["table"]["mash"]
  rows = [(k, k, label, "primary") for k, label in README_PRIMARY]
  conv = rep.get("convergence")
  if conv and conv["windows"]:
    w = conv["windows"][len(conv["windows"]) // 2]
    rows.append((f"T_conv@{w}", "", f"T_conv to {conv['threshold']:.1f} (window {w})", "secondary"))
  rows += [(k, k, label, "secondary") for k, label in README_SECONDARY if k in table]
  return rows


def readme_table(reports: list[dict]) -> str:
  """The README's table from comparison reports (``report.json`` of each task): per task and
  metric, ours (mean ± std over the paired seeds) beside the paper's, with the metric's family,
  its Holm-adjusted p within the family, and the report's verdict (only the primary family
  decides the paper's claim; the paper's T_conv is its own definition on its own runs, so only
  the direction compares)."""
  lines = [
      "| task | metric | family | MASH (ours) | PPO (ours) | p (Holm) | verdict (ours) | "
      "MASH (paper) | PPO (paper) |", "|---|---|---|---|---|---|---|---|---|"
  ]
  for rep in reports:
    task, table, tests = rep["task"], rep["table"], rep["tests"]
    for k, key, label, family in _readme_rows(rep):
      cells = [_readme_cell(table[a][k]) for a in ("mash", "ppo")]
      paper = [PAPER[task][a].get(key) for a in ("mash", "ppo")]
      paper = ["–" if v is None else f"{v:.4g}" for v in paper]
      p = tests[k]["p_holm"]
      p = "n/a" if p is None or not np.isfinite(p) else f"{p:.2g}"
      lines.append(f"| {task} ({_seeds(rep['seeds'])}) | {label} | {family} | {cells[0]} | "
                   f"{cells[1]} | {p} | {tests[k]['verdict']} | {paper[0]} | {paper[1]} |")
  return "\n".join(lines) + "\n"


def readme_block(dirs: list[str], root: Path | None = None) -> str:
  """The README's generated block: the marker naming the command and ``dirs`` (relative to
  ``root``, default the working directory), the table of their ``report.json``, the end marker."""
  reports = []
  for d in dirs:
    f = Path(root or ".") / d / "report.json"
    if not f.is_file():
      raise InputError(f"--readme-table {d}: expected a comparison folder with a "
                       "report.json (it comes after the first seed pair)")
    reports.append(json.loads(f.read_text()))
  return f"{README_BEGIN} {' '.join(dirs)} -->\n{readme_table(reports)}{README_END}\n"
