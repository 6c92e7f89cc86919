"""The notebooks run end to end at a tiny size (parameters injected after their parameters cell).

Each notebook is executed in a fresh kernel with nbclient; its parameters cell is followed by an
injected cell with tiny values (as papermill does). The tiny sizes reuse the programs the
``smoke_run`` fixture compiled (the persistent compilation cache is shared with the kernel).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import nbformat
from nbclient import NotebookClient

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
REPO = NOTEBOOKS.parent


def run_notebook(name: str, parameters: dict, tmp_path: Path) -> nbformat.NotebookNode:
  nb = nbformat.read(NOTEBOOKS / name, as_version=4)
  index = next(i for i, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", []))
  source = "\n".join(f"{k} = {v!r}" for k, v in parameters.items())
  nb.cells.insert(index + 1, nbformat.v4.new_code_cell("# Injected parameters\n" + source))
  env_path = os.environ.get("PYTHONPATH", "")
  os.environ["PYTHONPATH"] = f"{REPO}{os.pathsep}{env_path}" if env_path else str(REPO)
  NotebookClient(nb, timeout=600, kernel_name="python3",
                 resources={"metadata": {"path": str(tmp_path)}}).execute()
  return nb


def test_notebooks_are_stored_without_outputs():
  for path in NOTEBOOKS.glob("*.ipynb"):
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
      if cell.cell_type == "code":
        assert not cell.outputs and cell.execution_count is None, path.name
    assert any("parameters" in c.metadata.get("tags", []) for c in nb.cells), path.name


def test_mash_vs_ppo_notebook(evaluated_smoke_run, tmp_path):
  smoke_run = evaluated_smoke_run
  root = tmp_path / "compare"
  for algo in ("mash", "ppo"):  # the smoke run stands in for both methods: the plumbing is tested
    shutil.copytree(smoke_run, root / algo)
  nb = run_notebook("mash_vs_ppo.ipynb", {"COMPARE_DIR": str(root), "TASK": "bipedal"}, tmp_path)
  text = "".join(
      str(o.get("data", {}).get("text/markdown", "")) for c in nb.cells if c.cell_type == "code"
      for o in c.outputs)
  assert "MASH vs single-agent PPO" in text


def test_ablations_notebook(tmp_path):
  run_notebook(
      "ablations.ipynb", {
          "TASK": "bipedal", "PRESET": "smoke", "SEEDS": 1, "ABLATIONS": ["none"], "OUT": str(
              tmp_path / "abl"), "OVERRIDES": []
      }, tmp_path)
  assert (tmp_path / "abl" / "bipedal_none" / "progress.csv").is_file()


def test_robustness_notebook(smoke_run, tmp_path):
  nb = run_notebook(
      "robustness.ipynb", {
          "RUN_DIR": str(smoke_run), "FRICTIONS": [0.3, 1.0], "PUSHES": [0.0, 100.0],
          "EPISODES_PER_VALUE": 1, "SECONDS": 1.0
      }, tmp_path)
  text = "".join(
      str(o.get("data", {}).get("text/markdown", "")) for c in nb.cells if c.cell_type == "code"
      for o in c.outputs)
  assert "| friction | 0.3 |" in text and "| push | 100 |" in text
