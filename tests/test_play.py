"""``experiments.play``: a shipped policy played headless writes a video; bad inputs are one
line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments import play
from mash.deploy import play as play_lib
from mash.deploy import video as video_lib

ROOT = Path(__file__).resolve().parents[1]


def _headless_env() -> dict[str, str]:
  env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
  env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)
  return env


def test_shipped_policies_are_listed():
  assert "t1_bipedal_mash" in play_lib.shipped_policies()


def test_mean_yaw_rate_unwraps_the_heading_and_stops_at_a_fall():
  """A heading turning at +0.5 rad/s through +-pi for 200 steps of 0.02 s, then falling (the
  yaw after it is noise): (199 x 0.01 rad) / (199 x 0.02 s) = 0.5 rad/s; one step alive: 0."""
  t = np.arange(300)
  yaw = np.angle(np.exp(1j * (3.0 + 0.01 * t)))  # wraps from +pi to -pi at step 15
  yaw[200:] = np.random.default_rng(0).uniform(-np.pi, np.pi, 100)
  euler = np.stack([0 * yaw, 0 * yaw, yaw], -1)
  alive = (t < 200).astype(float)
  assert play_lib.mean_yaw_rate(euler, alive, 0.02) == pytest.approx(0.5)
  assert play_lib.mean_yaw_rate(euler, (t < 1).astype(float), 0.02) == 0.0


def test_play_headless_writes_the_video(tmp_path, skip_for_missing_gl):
  """Two seconds of the shipped T1 policy at 0.4 m/s, in a subprocess (MUJOCO_GL is chosen before
  mujoco is imported): it walks, says so, and the MP4 is there."""
  backend, reason = video_lib.headless_gl()
  if backend is None:
    skip_for_missing_gl(reason)
  video = tmp_path / "walk.mp4"
  out = subprocess.run([
      sys.executable, "-m", "experiments.play", "--policy", "t1_bipedal_mash", "--seconds", "2",
      "--video",
      str(video)
  ], capture_output=True, text=True, cwd=tmp_path, env=_headless_env(), timeout=300)
  assert out.returncode == 0, out.stdout + out.stderr[-3000:]
  assert f"wrote {video}" in out.stdout and "walked 2.0 s" in out.stdout, out.stdout
  assert " rad/s; wrote" in out.stdout, out.stdout  # the heading's change is reported
  data = video.read_bytes()
  assert len(data) > 10_000 and data[4:8] == b"ftyp"  # an MP4 container with frames in it


@pytest.mark.parametrize("argv, words", [
    (["--policy", "no_such_policy"], "--policy 'no_such_policy': expected a shipped policy name"),
    (["--policy", "t1_bipedal_mash", "--command", "fast"], "expected VX or VX,VY,YAW_RATE"),
    (["--policy", "t1_bipedal_mash", "--command", "1,2"], "'1,2': expected VX or VX,VY,YAW_RATE"),
    (["--policy", "t1_bipedal_mash", "--command", "2.5"
     ], "--command vx 2.5 m/s is outside the range the policy was trained on, [-0.3, 0.8] m/s, by "
     "more than half its width; expected a command within [-0.85, 1.35] m/s"),
    (["--policy", "t1_bipedal_mash", "--command", "0.4,0,-2"], "--command yaw_rate -2 rad/s"),
    (["--policy", "t1_bipedal_mash", "--seconds", "nan"], "expected a duration in (0, 3600]"),
    (["--policy", "t1_bipedal_mash", "--video", "walk.avi"], "expected a .mp4 (or .gif) file name"),
    (["--policy", "t1_bipedal_mash", "--video", "/proc/x.mp4"], "--video '/proc/x.mp4' cannot be"),
])
def test_bad_inputs_are_one_line(capsys, monkeypatch, argv, words):
  monkeypatch.delenv("DISPLAY", raising=False)
  monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
  monkeypatch.setattr(video_lib, "headless_gl", lambda: ("egl", ""))
  with pytest.raises(SystemExit) as e:
    play.main(argv)
  err = [l for l in capsys.readouterr().err.splitlines() if l.strip()]
  assert e.value.code == 2 and len(err) == 1 and err[0].startswith("error: "), err
  assert words in err[0], err


def test_a_command_just_outside_the_trained_range_plays_with_a_warning():
  """Within half the range's width beyond it: one warning line, no error (the policy never met
  the command, but a user may want to see how it copes); inside: silence; no config: no check."""
  said = []
  ranges = {"vx": (-0.3, 0.8), "vy": (-0.2, 0.2), "yaw_rate": (-0.5, 0.5)}
  play_lib.check_command((1.0, 0.0, 0.0), ranges, said.append)
  assert len(said) == 1 and said[0].startswith("warning: --command vx 1 m/s is outside")
  said.clear()
  play_lib.check_command((0.8, -0.2, 0.5), ranges, said.append)
  play_lib.check_command((9.0, 9.0, 9.0), None, said.append)
  assert said == []
