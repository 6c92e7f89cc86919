"""Running the MASH-vs-PPO comparison: the learning-rate search, then paired seeds of both methods.

Both methods get the same small tuning first: seed 0 at each of the learning rates, and one rule
(the highest final paper-weight episode reward) picks each method's rate (``tuning.json``). Then
both train on the same config and budget, one run per method and seed, paired by seed
(``OUT/<algo>/lr<picked>/seed<s>/``, seed 0 being the search's run; each a plain
``python -m experiments.<task>`` run, so on a CPU it uses both cores the same way). Every run is
evaluated right after it trains, while its checkpoint is at hand, keeps its policy as a policy
folder with its ONNX graph (``seed<s>/policy/``, ~200 KB: any later evaluation needs no
retraining), runs the robustness battery in MJX on that policy (``policy/eval_robustness/``,
compared in the report's secondary family), has its record compacted (:mod:`mash.runs.records`),
and the report is rewritten after each pair (:func:`mash.analysis.compare.write_report`).

A comparison continues from its folder: a finished seed is reused, an interrupted one resumes from
its checkpoint (or, when its checkpoints are not on this machine, trains again from the start,
its records moved to ``cut_off/``). Its config is the folder's, never today's preset: each new
seed trains from the config of the method's runs there (``--config``, only ``train.seed``
changed), the runs of a method must agree in everything but the seed, and ``--preset`` or
``--set`` that would change that config are refused in one line (:func:`folder_config`).

``seeds_at_once`` K (for a GPU) trains up to K consecutive seeds of a method that have no run yet
in one vmapped call (``OUT/<algo>/lr<rate>/group_seeds<a>-<b>/``, its ``i``-th seed keyed from
``a + i``: the same recipe and seed, not the same numbers as a single run of that seed, which
draws its keys per process), evaluates them together, then writes each seed's records into
``seed<s>/`` as a single run leaves them (:func:`split_group`), so the report, a resumed
comparison and a CPU finishing it later treat them alike.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from mash.analysis import compare as compare_lib
from mash.analysis import evaluation, reports, robustness
from mash.deploy import export
from mash.deploy import policy as policy_lib
from mash.errors import InputError
from mash.runs import experiment, loop, records

# Fields in which the runs of one method may differ: which seed(s) each trained.
SEED_FIELDS = (("seeds",), ("train", "seed"))


class Plan(NamedTuple):
  """What one ``compare`` command does.

  Attributes:
    task: ``'bipedal'`` or ``'armswing'``.
    out: the comparison's folder.
    preset: the preset of a new comparison (a continued one trains on its folder's config).
    overrides: ``--set`` overrides of a new comparison (checked against a continued one's).
    seeds: seeds per method, 0 .. seeds - 1.
    learning_rates: the search's rates.
    eval_config: each run's evaluation.
    seeds_at_once: consecutive new seeds of a method trained in one vmapped call.
    show_progress: the training runs' progress bars.
  """

  task: str
  out: Path
  preset: str
  overrides: tuple[str, ...]
  seeds: int
  learning_rates: tuple[float, ...]
  eval_config: evaluation.EvalConfig
  seeds_at_once: int = 1
  show_progress: bool = True


# ----------------------------------------------------------------------------- the folder
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
  (a name that :func:`mash.analysis.compare.seed_dirs` does not take for a seed's run)."""
  return Path(parent) / f"group_seeds{seeds[0]}-{seeds[-1]}"


def consecutive_runs(seeds: list[int], most: int) -> list[list[int]]:
  """``seeds`` (ascending) cut into runs of consecutive seeds of at most ``most`` each."""
  groups: list[list[int]] = []
  for s in seeds:
    if groups and s == groups[-1][-1] + 1 and len(groups[-1]) < most:
      groups[-1].append(s)
    else:
      groups.append([s])
  return groups


# ---------------------------------------------------------------------- the config of a folder
def _without_seed(cfg: dict[str, Any]) -> dict[str, Any]:
  cfg = json.loads(json.dumps(cfg))
  for path in SEED_FIELDS:
    parent = cfg
    for key in path[:-1]:
      parent = parent.get(key, {})
    parent.pop(path[-1], None)
  return cfg


def _read_config(path: Path) -> dict[str, Any]:
  """The run's config beside ``path`` (its ``config.json``) as today's code reads it, so that a
  field added since, whose default keeps the old behaviour, is no difference."""
  return experiment.to_dict(loop.load_config(Path(path).parent))


def _first_difference(a: Any, b: Any, path: str = "") -> str | None:
  """The first field (dotted path, ``a -> b``) in which two JSON trees differ, or None."""
  if isinstance(a, dict) and isinstance(b, dict):
    for key in sorted(set(a) | set(b)):
      diff = _first_difference(a.get(key), b.get(key), f"{path}.{key}" if path else key)
      if diff:
        return diff
    return None
  return None if a == b else f"{path} ({json.dumps(a)} -> {json.dumps(b)})"


def folder_config(parent: Path) -> Path | None:
  """The ``config.json`` a method's runs in ``parent`` (``<algo>/lr<rate>/``) share, or None when
  it has none yet (its ``seed<s>/`` runs and groups, not ``cut_off/``).

  Raises:
    InputError: two of them differ in anything but the seed (one line naming the field).
  """
  files = sorted(Path(parent).glob("seed*/config.json")) + sorted(
      Path(parent).glob("group_seeds*/config.json"))
  if not files:
    return None
  first = _without_seed(_read_config(files[0]))
  for other in files[1:]:
    diff = _first_difference(first, _without_seed(_read_config(other)))
    if diff:
      raise InputError(f"'{files[0].parent}' and '{other.parent}' were trained on different "
                       f"configs ({diff}): a comparison's runs may differ only in the seed")
  return files[0]


def check_continued(plan: Plan, algo: str, lr: float, config_file: Path, given: bool) -> None:
  """Refuses (one line) a ``--preset`` / ``--set`` that would train a continued comparison's
  new seeds on another config than its runs' (``given``: the user named one of them)."""
  if not given:
    return
  asked = experiment.to_dict(
      experiment.make_config(plan.task, algo, plan.preset, 1, "none",
                             [*plan.overrides, f"train.learning_rate={lr:g}"]))
  diff = _first_difference(_without_seed(_read_config(config_file)), _without_seed(asked))
  if diff:
    raise InputError(f"'{plan.out}' continues on its runs' own config ({config_file}); "
                     f"--preset/--set would change {diff}: drop them, or start another --out")


# ------------------------------------------------------------------------------ one run
def training_command(plan: Plan, algo: str, lr: float, run: Path, seeds: list[int],
                     state: str) -> list[str]:
  """The ``python -m experiments.<task>`` command that trains, or resumes, ``run``: from the
  method's folder config when it has one (only the seed changed), else from the preset."""
  command = [sys.executable, "-m", f"experiments.{plan.task}"]
  if state == "resume":
    command += ["--resume", str(run)]
  else:
    base = folder_config(lr_dir(plan.out, algo, lr))
    if base is not None:
      command += ["--config", str(base), "--out", str(run), "--set", f"train.seed={seeds[0]}"]
    else:
      command += [
          "--algo", algo, "--preset", plan.preset, "--out",
          str(run), "--set", f"train.seed={seeds[0]}", "--set", f"train.learning_rate={lr:g}"
      ]
      command += [x for o in plan.overrides for x in ("--set", o)]
    command += ["--seeds", str(len(seeds))] if len(seeds) > 1 else []
  return command + ([] if plan.show_progress else ["--no-progress"])


def train_run(plan: Plan, algo: str, lr: float, run: Path, seeds: list[int],
              num_iterations: int) -> Path:
  """Trains the run ``run`` of ``seeds`` (one seed, or consecutive ones in one vmapped call), or
  resumes or reuses it, then evaluates it unless its evaluation is there."""
  which = f"seed {seeds[0]}" + (f"-{seeds[-1]}" if len(seeds) > 1 else "")
  label = f"[{algo} lr {lr:g} {which}]"
  state = seed_state(run, num_iterations)
  what = {
      "done": "trained; reusing it", "resume": "resuming", "new": "training",
      "restart": "stopped early with no checkpoint here; training it again"
  }[state]
  print(f"{label} {what}", flush=True)
  if state == "restart":
    print(f"{label} its records moved to {set_aside(run)}", flush=True)
    state = "new"
  if state != "done":
    code = subprocess.call(training_command(plan, algo, lr, run, seeds, state))
    if code != 0:
      raise InputError(f"the {algo} run of {which} stopped with status {code}; run the same "
                       f"command again to resume it ({run})")
  # Right after training, while the checkpoint is on this machine: checkpoints are not kept in
  # git, so a later session or a clone may hold only the records.
  metrics_file = run / "eval" / "metrics.json"
  fresh = (metrics_file.is_file() and json.loads(metrics_file.read_text()).get(
      "eval_config", {}).get("num_episodes") == plan.eval_config.num_episodes)
  if not fresh:
    print(f"{label} evaluating on {plan.eval_config.num_episodes} episodes", flush=True)
    reports.evaluate_run(str(run), plan.eval_config)
  return run


def keep_policy(run: Path, seed_dir: Path, seed: int = 0) -> None:
  """Writes seed ``seed`` of ``run`` as ``seed_dir/policy/`` with its ONNX graph, when it is not
  there yet and the run's checkpoints are (a clone holds only the records)."""
  folder = seed_dir / "policy"
  if policy_lib.is_policy_folder(folder) or not (run / "checkpoints").is_dir():
    return
  export.save_policy_folder(policy_lib.load(run, seed=seed), folder)
  print(f"[{seed_dir.parent.parent.name} {seed_dir.name}] kept its policy in {folder}", flush=True)


def battery(seed_dir: Path) -> None:
  """The robustness battery in MJX on ``seed_dir/policy/`` (its default conditions and
  episodes), when that policy is there and its battery is not yet."""
  folder = seed_dir / "policy"
  if not policy_lib.is_policy_folder(folder) or (folder / "eval_robustness" /
                                                 "robustness.json").is_file():
    return
  print(f"[{seed_dir.parent.parent.name} {seed_dir.name}] robustness battery in MJX", flush=True)
  reports.robustness_run(str(folder), robustness.BatteryConfig())


def finish_seed(run: Path) -> Path:
  """A trained and evaluated one-seed run: its policy kept and put through the robustness
  battery, its hip-pitch trace saved for the report, its record compacted."""
  keep_policy(run, run)
  battery(run)
  compare_lib.hip_trace(run)  # the few KiB of the hip-pitch plot that the committed records keep
  records.compact_tree(run, records.Tally(), records.Tally())
  return run


def split_group(group: Path, seeds: list[int]) -> list[Path]:
  """Writes each seed of an evaluated multi-seed run ``group`` (its ``i``-th seed being seed
  ``seeds[i]``) into ``<group's parent>/seed<s>/`` with the records a single run of that seed
  leaves: ``config.json`` and ``summary.json`` (the group's, plus ``group`` and ``group_index``;
  its ``wall_s`` covers all the group's seeds), ``progress.csv`` (the seed's rows), ``eval/``
  (``metrics.json`` of that seed alone, ``hip_trace.npz``, ``hip_pitch.png``) and ``policy/``.
  Returns the seed directories."""
  metrics = json.loads((group / "eval" / "metrics.json").read_text())
  if len(metrics["per_seed"]) != len(seeds):
    raise InputError(f"'{group}' has {len(metrics['per_seed'])} evaluated seeds, "
                     f"expected {len(seeds)}")
  config = (group / "config.json").read_text()
  summary = json.loads((group / "summary.json").read_text())
  trajectories = np.load(group / "eval" / "trajectories.npz")
  dirs = []
  for i, seed in enumerate(seeds):
    d = group.parent / f"seed{seed}"
    (d / "eval").mkdir(parents=True, exist_ok=True)
    (d / "config.json").write_text(config)
    _write_seed_progress(group, d / "progress.csv", i)
    picked = trajectories["seed"] == i
    traj = {k: trajectories[k][picked] for k in trajectories.files if k != "dt"}
    alone = reports.summarize([metrics["per_seed"][i]], traj, metrics["eval_config"],
                              metrics["iteration"],
                              reports.learning_curve(policy_lib.read_progress(d, per_seed=True), 0))
    (d / "eval" / "metrics.json").write_text(json.dumps(alone, indent=2))
    compare_lib.save_hip_trace(d / "eval" / "hip_trace.npz", {**traj, "dt": trajectories["dt"]})
    reports.plot_hip_pitch(traj, float(trajectories["dt"]), d / "eval" / "hip_pitch.png",
                           json.loads(config)["algo"])
    keep_policy(group, d, seed=i)
    battery(d)
    # Last: until it is there, the seed reads as stopped early (seed_state).
    (d / "summary.json").write_text(
        json.dumps({**summary, "group": group.name, "group_index": i}, indent=2))
    records.compact_tree(d, records.Tally(), records.Tally())
    dirs.append(d)
  return dirs


def _write_seed_progress(group: Path, path: Path, index: int) -> None:
  """Seed ``index``'s rows of a group's ``progress_seeds.csv``, as a one-seed run's
  ``progress.csv`` (the same cells, without the ``seed`` column)."""
  with open(group / "progress_seeds.csv", newline="") as f:
    reader = csv.DictReader(f)
    columns = [c for c in reader.fieldnames if c != "seed"]
    rows = [r for r in reader if int(float(r["seed"])) == index]
  with open(path, "w", newline="") as f:
    writer = csv.DictWriter(f, columns, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)


# ------------------------------------------------------------------------------ the plan
def _iterations(plan: Plan, algo: str, lr: float) -> int:
  """The runs' length: their folder config's, else the preset's."""
  base = folder_config(lr_dir(plan.out, algo, lr))
  if base is not None:
    return int(json.loads(base.read_text())["train"]["num_iterations"])
  return experiment.make_config(plan.task, algo, plan.preset, 1, "none",
                                plan.overrides).train.num_iterations


def train_seed(plan: Plan, algo: str, lr: float, seed: int) -> Path:
  run = lr_dir(plan.out, algo, lr) / f"seed{seed}"
  return finish_seed(train_run(plan, algo, lr, run, [seed], _iterations(plan, algo, lr)))


def train_block(plan: Plan, algo: str, lr: float, block: list[int]) -> None:
  """Seeds ``block`` of one method: those without a run yet train together, up to
  ``seeds_at_once`` consecutive ones per call, and are split into their ``seed<s>/``; the rest
  as single runs (reused when done, resumed when stopped early)."""
  parent = lr_dir(plan.out, algo, lr)
  n_it = _iterations(plan, algo, lr)
  pending = [s for s in block if seed_state(parent / f"seed{s}", n_it) in ("new", "restart")]
  for group in consecutive_runs(pending, plan.seeds_at_once):
    if len(group) == 1:
      continue
    for s in group:
      if (parent / f"seed{s}" / "config.json").is_file():
        print(
            f"[{algo} lr {lr:g} seed {s}] its records moved to "
            f"{set_aside(parent / f'seed{s}')}", flush=True)
    split_group(train_run(plan, algo, lr, group_dir(parent, group), group, n_it), group)
  for s in block:
    train_seed(plan, algo, lr, s)


def search(plan: Plan) -> dict[str, float]:
  """The same small search for both methods: seed 0 at each rate, the same rule picks
  (:func:`pick_learning_rates`); writes ``tuning.json``."""
  finals = {
      algo: {lr: final_reward(train_seed(plan, algo, lr, 0)) for lr in plan.learning_rates}
      for algo in ("mash", "ppo")
  }
  picked = pick_learning_rates(finals)
  (plan.out / "tuning.json").write_text(
      json.dumps(
          {
              "learning_rates": list(plan.learning_rates), "seed": 0, "picked": picked, "final": {
                  a: {f"{lr:g}": r for lr, r in f.items()} for a, f in finals.items()
              }, "rule": "highest mean paper-weight episode reward over the last 10 % of iterations"
          }, indent=2))
  print(f"learning rates picked by the search: MASH {picked['mash']:g}, PPO {picked['ppo']:g}",
        flush=True)
  return picked


def pick_learning_rates(finals: dict[str, dict[float, float]]) -> dict[str, float]:
  """The search's rule, the same for both methods: per method, the learning rate whose seed-0
  run ends with the highest paper-weight episode reward (mean over its last 10 % of iterations);
  a tie goes to the smaller rate."""
  return {algo: max(sorted(by_lr), key=lambda lr: by_lr[lr]) for algo, by_lr in finals.items()}


def final_reward(run_dir: Path) -> float:
  """Mean paper-weight episode reward over a run's last 10 % of iterations."""
  curve = compare_lib.method_curves(run_dir)[1][0]
  return float(curve[-max(1, int(round(0.1 * len(curve)))):].mean())


def check_plan(plan: Plan, given: bool) -> None:
  """Before any work: every method's runs in the folder share one config, and ``--preset`` /
  ``--set`` (``given``) would not change it (:func:`folder_config`, :func:`check_continued`)."""
  for algo in ("mash", "ppo"):
    for lr in plan.learning_rates:
      base = folder_config(lr_dir(plan.out, algo, lr))
      if base is not None:
        check_continued(plan, algo, lr, base, given)


def run(plan: Plan, given: bool) -> str:
  """The whole comparison (module docstring): the search, then seeds 1 .. ``seeds - 1`` of both
  methods in blocks of ``seeds_at_once``, the report after each block; returns its markdown."""
  check_plan(plan, given)
  picked = search(plan)
  k = plan.seeds_at_once
  blocks = [[0]] + [list(range(a, min(a + k, plan.seeds))) for a in range(1, plan.seeds, k)]
  dirs = {algo: lr_dir(plan.out, algo, picked[algo]) for algo in ("mash", "ppo")}
  md = ""
  for block in blocks:
    for algo in ("mash", "ppo"):
      train_block(plan, algo, picked[algo], block)
    preset = json.loads(folder_config(dirs["mash"]).read_text())["preset"]
    md = compare_lib.write_report(plan.task, plan.out, preset, dirs)
    for plot in ("reward_curves.png", "hip_pitch.png"):  # committed too: compact like the seeds'
      records.compact_plot(plan.out / plot, records.Tally())
    print(f"report after {block[-1] + 1} paired seed(s): {plan.out}/report.md", flush=True)
  return md
