"""The house's architecture, checked from the source (no imports, no JAX): folders by concern
without import circles, thin entry points, short functions, imports at the top."""

from __future__ import annotations

import ast
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("sim", "rl", "runs", "deploy", "analysis", "bench")
# Imports a function may make itself: optional extras, and the viewer and OpenGL contexts that
# need a display or a system library.
OPTIONAL = ("warp", "mujoco.mjx.third_party", "mujoco.mjx.warp", "wandb", "mujoco.viewer",
            "mujoco.egl", "mujoco.osmesa", "mujoco.glfw")
MAX_FUNCTION_LINES = 80
MAX_EXPERIMENTS_LINES = 1000


def _modules() -> dict[str, Path]:
  """``{dotted name: file}`` of every module of the ``mash`` package."""
  out = {}
  for path in sorted((REPO / "mash").rglob("*.py")):
    parts = path.relative_to(REPO).with_suffix("").parts
    out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
  return out


def _imported(tree: ast.AST, top_level_only: bool) -> set[str]:
  """The modules an AST's import statements name (``from a import b`` names ``a`` and
  ``a.b``); with ``top_level_only``, those outside functions."""
  nodes = tree.body if top_level_only else list(ast.walk(tree))
  names = set()
  for node in nodes:
    if isinstance(node, ast.Import):
      names.update(a.name for a in node.names)
    elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
      names.add(node.module)
      names.update(f"{node.module}.{a.name}" for a in node.names)
  return names


def _graph() -> dict[str, set[str]]:
  modules = _modules()
  return {
      name: {m for m in _imported(ast.parse(path.read_text()), True) if m in modules and m != name}
      for name, path in modules.items()
  }


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
  """One import circle of ``graph`` (a path that comes back to its start), or None."""
  state: dict[str, int] = {}  # 1: on the current path, 2: done

  def visit(node: str, path: list[str]) -> list[str] | None:
    state[node] = 1
    for nxt in sorted(graph[node]):
      if state.get(nxt) == 1:
        return path[path.index(nxt):] + [nxt] if nxt in path else [node, nxt]
      if nxt not in state and (found := visit(nxt, path + [nxt])):
        return found
    state[node] = 2
    return None

  for start in sorted(graph):
    if start not in state and (found := visit(start, [start])):
      return found
  return None


def test_the_cycle_finder_finds_a_circle():
  """A guard on the check below: a circle a -> b -> c -> a is found, a tree is not."""
  assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
  assert _cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_library_is_folders_by_concern_without_import_circles():
  graph = _graph()
  assert {name.split(".")[1] for name in graph if name.count(".") >= 2} == set(PACKAGES)
  assert len(graph) > 40, sorted(graph)  # the walk found the modules
  assert _cycle(graph) is None, f"import circle: {' -> '.join(_cycle(graph))}"


def test_imports_sit_at_the_top_unless_optional():
  """No import inside a function of ``mash/``, except of an optional dependency."""
  inner = []
  for name, path in _modules().items():
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
      if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
        for sub in ast.walk(node):
          if isinstance(sub, ast.Import):
            named = [a.name for a in sub.names]
          elif isinstance(sub, ast.ImportFrom):
            named = [f"{sub.module}.{a.name}" for a in sub.names]
          else:
            continue
          inner += [
              f"{name}.{node.name}: {m}" for m in named
              if not any(m == o or m.startswith(o + ".") for o in OPTIONAL)
          ]
  assert inner == []


def test_functions_are_short():
  long = []
  for name, path in _modules().items():
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
        n = node.end_lineno - node.lineno + 1
        if n > MAX_FUNCTION_LINES:
          long.append(f"{name}.{node.name}: {n} lines")
  assert long == []


def test_entry_points_are_thin():
  """Each ``experiments/<name>.py`` parses its arguments and calls the library: none imports
  another entry point, and all of them together stay small."""
  files = sorted((REPO / "experiments").glob("*.py"))
  assert len(files) > 5
  for path in files:
    named = _imported(ast.parse(path.read_text()), False)
    assert not [m for m in named if m == "experiments" or m.startswith("experiments.")], path
  total = sum(len(p.read_text().splitlines()) for p in files)
  assert total < MAX_EXPERIMENTS_LINES, total


MAX_TRACKED_MB = 30
MAX_README_LINES = 250


def test_the_readme_is_a_guide_not_a_log():
  """The README stays a user guide of about 250 lines; history goes to docs/."""
  readme = (REPO / "README.md").read_text().splitlines()
  assert len(readme) <= MAX_README_LINES, len(readme)


def test_the_repository_is_code_not_bulk():
  """The tracked tree, records included, stays under 30 MB."""
  listed = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=False)
  if listed.returncode != 0:
    pytest.skip("not a git checkout (an unpacked sdist or a copy): no tracked tree to measure")
  files = [REPO / f for f in listed.stdout.decode().split("\0") if f]
  assert len(files) > 100  # the listing worked
  total = sum(f.stat().st_size for f in files if f.is_file())
  assert total < MAX_TRACKED_MB * 1e6, f"{total / 1e6:.1f} MB tracked"
