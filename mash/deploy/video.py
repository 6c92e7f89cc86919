"""Video of the robot in native MuJoCo: which OpenGL backend renders on this machine, and the
MP4 / GIF writer of a torso-tracking camera.

MuJoCo reads ``MUJOCO_GL`` once, when it is first imported, and importing :mod:`mash` imports it;
a command learns whether and how it can render only later, from its arguments and a probe
(:func:`headless_gl`). So :class:`VideoWriter` opens the OpenGL context of the backend it is
given itself (:func:`gl_context`) instead of relying on the backend chosen at import.
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import imageio.v2 as imageio
import mujoco
import numpy as np
from PIL import Image

# Renders one frame of a one-geom model: run in a subprocess, so that a backend that crashes or
# hangs while it starts cannot take the command with it.
_GL_PROBE = """
import mujoco
m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=".1"/></worldbody></mujoco>')
r = mujoco.Renderer(m, 16, 16)
r.update_scene(mujoco.MjData(m))
r.render()
"""


def has_display() -> bool:
  """Whether a window can open here (``DISPLAY`` or ``WAYLAND_DISPLAY`` is set)."""
  return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def headless_gl() -> tuple[str | None, str]:
  """The first ``MUJOCO_GL`` backend (egl, osmesa) that renders here, tried in subprocesses.

  ``MUJOCO_GL``, when set, is taken as it is.

  Returns:
    ``(backend, '')``, or ``(None, reason)`` naming what failed.
  """
  if os.environ.get("MUJOCO_GL"):
    return os.environ["MUJOCO_GL"], ""
  failures = []
  for backend in ("egl", "osmesa"):
    env = dict(os.environ, MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
    try:
      r = subprocess.run([sys.executable, "-c", _GL_PROBE], env=env, capture_output=True, text=True,
                         timeout=60)
    except subprocess.TimeoutExpired:
      failures.append(f"{backend}: timed out")
      continue
    if r.returncode == 0:
      return backend, ""
    last = (r.stderr.strip().splitlines() or ["failed"])[-1]
    failures.append(f"{backend}: {last[:120]}")
  return None, ("no headless OpenGL backend works here (" + "; ".join(failures) + "); install "
                "Debian's libegl1 and libgl1-mesa-dri (EGL) or libosmesa6 (OSMesa)")


def gl_context(backend: str | None, width: int, height: int):
  """A new OpenGL context of ``width`` x ``height`` pixels, made current.

  Args:
    backend: ``'egl'`` or ``'osmesa'`` (headless); anything else, or None, is the backend MuJoCo
      chose from ``MUJOCO_GL`` when it was imported (GLFW when unset: needs a display).
    width, height: the largest frame it renders (pixels).

  Returns:
    MuJoCo's ``GLContext`` of that backend (``make_current()``, ``free()``).
  """
  # Each headless backend's module loads its system library (libEGL, libOSMesa) and PyOpenGL for
  # that platform when imported: only the one asked for, and only when a video is rendered.
  if backend == "egl":
    from mujoco.egl import GLContext
  elif backend == "osmesa":
    from mujoco.osmesa import GLContext
  else:
    GLContext = mujoco.GLContext
  context = GLContext(width, height)
  context.make_current()
  return context


class VideoWriter:
  """Offscreen frames of a torso-tracking camera, written to an MP4 with imageio-ffmpeg, or to an
  animated GIF (a ``.gif`` path; kept in memory and written by Pillow on ``close``, for short
  clips such as the README's).

  Shadows and reflections are off: with software OpenGL (Mesa llvmpipe behind EGL) they make a
  640x480 frame of the T1's meshes cost about 0.8 s instead of 0.12 s.

  Args:
    model: the robot's model (its floor is darkened in place).
    path: the ``.mp4`` or ``.gif`` file to write.
    fps: frames per second of the video.
    track_body: id of the body the camera follows.
    width, height: frame size (pixels), at most the model's offscreen buffer.
    backend: the OpenGL backend to render with (:func:`gl_context`; :func:`headless_gl` finds one).
  """

  def __init__(self, model: mujoco.MjModel, path: str | os.PathLike, fps: float, track_body: int,
               width: int = 640, height: int = 480, backend: str | None = None):
    buffer = model.vis.global_
    if width > buffer.offwidth or height > buffer.offheight:
      raise ValueError(f"a {width}x{height} frame exceeds the model's offscreen buffer "
                       f"({buffer.offwidth}x{buffer.offheight})")
    self.model, self.track_body = model, track_body
    self.camera = mujoco.MjvCamera()
    self.camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    self.camera.trackbodyid = track_body
    self.camera.distance, self.camera.elevation, self.camera.azimuth = 2.5, -15.0, 120.0
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    if floor >= 0:  # a darker floor with grid lines (added to the scene below) shows the motion
      model.geom_rgba[floor] = (0.32, 0.36, 0.42, 1.0)
    self.context = gl_context(backend, width, height)
    self.scene = mujoco.MjvScene(model, maxgeom=10_000)
    self.option = mujoco.MjvOption()
    self.mjr = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150.value)
    mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self.mjr)
    self.rect = mujoco.MjrRect(0, 0, width, height)
    self.pixels = np.empty((height, width, 3), np.uint8)
    self.path, self.fps = Path(path), fps
    self.gif_frames = [] if self.path.suffix.lower() == ".gif" else None
    self.writer = None if self.gif_frames is not None else imageio.get_writer(
        str(path), fps=fps, codec="libx264", quality=7, macro_block_size=8,
        ffmpeg_log_level="error")
    self.frames = 0

  def _grid(self, data: mujoco.MjData, spacing: float = 0.5, half: int = 8) -> None:
    """Thin floor lines every ``spacing`` m around the tracked body, as scene-only geoms."""
    scene = self.scene
    cx, cy = (np.round(data.xpos[self.track_body][:2] / spacing) * spacing)
    extent = spacing * half
    rgba = np.array([0.75, 0.78, 0.82, 1.0], np.float32)
    for axis in range(2):
      for k in range(-half, half + 1):
        if scene.ngeom >= scene.maxgeom:
          return
        pos = np.array([cx, cy, 0.001])
        pos[axis] += k * spacing
        size = np.array([0.006, extent, 0.0005]) if axis == 0 else np.array([extent, 0.006, 0.0005])
        mujoco.mjv_initGeom(scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_BOX, size, pos,
                            np.eye(3).reshape(-1), rgba)
        scene.ngeom += 1

  def render(self, data: mujoco.MjData) -> np.ndarray:
    """``[height, width, 3]`` uint8: the frame of ``data`` from the tracking camera."""
    mujoco.mjv_updateScene(self.model, data, self.option, None, self.camera,
                           mujoco.mjtCatBit.mjCAT_ALL.value, self.scene)
    self.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    self.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    self._grid(data)
    self.context.make_current()
    mujoco.mjr_render(self.rect, self.scene, self.mjr)
    mujoco.mjr_readPixels(self.pixels, None, self.rect, self.mjr)
    return self.pixels[::-1].copy()  # OpenGL's rows run from the bottom up

  def add(self, data: mujoco.MjData) -> None:
    """Renders ``data`` and appends the frame."""
    frame = self.render(data)
    if self.gif_frames is not None:
      self.gif_frames.append(frame)
    else:
      with warnings.catch_warnings():  # the first frame starts ffmpeg: a harmless fork warning
        warnings.filterwarnings("ignore", message=".*os.fork", category=RuntimeWarning)
        self.writer.append_data(frame)
    self.frames += 1

  def close(self) -> None:
    """Writes the GIF or closes the MP4, then frees the OpenGL context."""
    if self.gif_frames:
      images = [Image.fromarray(f).quantize(colors=128) for f in self.gif_frames]
      images[0].save(self.path, save_all=True, append_images=images[1:], loop=0,
                     duration=round(1000.0 / self.fps), optimize=True)
    elif self.writer is not None:
      self.writer.close()
    if self.mjr is not None:
      self.context.make_current()
      self.mjr.free()
      self.mjr = None
      self.context.free()
