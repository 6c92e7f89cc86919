"""The package as users install it: a wheel built from the checkout carries every shipped robot
file and policy folder, and finds them by importlib.resources (no repository around)."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_wheel_holds_every_robot_file_and_policy_folder(tmp_path):
  out = subprocess.run([
      sys.executable, "-m", "pip", "wheel",
      str(REPO), "--no-deps", "--no-build-isolation", "-q", "-w",
      str(tmp_path)
  ], capture_output=True, text=True, timeout=600)
  assert out.returncode == 0, out.stderr[-2000:]
  (wheel,) = tmp_path.glob("mash_jax-*.whl")
  names = set(zipfile.ZipFile(wheel).namelist())
  assets = REPO / "mash" / "assets"
  robots = sorted(assets.glob("robots/*.toml"))
  policies = sorted(p for p in assets.glob("policies/*") if p.is_dir())
  assert robots and policies
  for path in robots + [f for p in policies for f in p.iterdir()]:
    assert path.relative_to(REPO).as_posix() in names, path
  assert any(n.startswith("experiments/") for n in names)
