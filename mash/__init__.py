"""MASH-JAX: one agent per limb of a single humanoid, trained with MAPPO over MuJoCo MJX."""

import contextlib as _contextlib
import io as _io

__version__ = "0.1.0"

# MJX probes its optional MuJoCo Warp backend when first imported and prints two lines to stdout
# when Warp is not installed ("Failed to import warp: ...", "Failed to import mujoco_warp: ...").
# The JAX backend, this package's default, does not need it: import MJX once here with those two
# lines held back, and pass on anything else it prints. A config that asks for Warp without it is
# refused in one line instead (``model_lib.check_physics``, from the result of this probe).
_WARP_PROBE = ("Failed to import warp:", "Failed to import mujoco_warp:")
with _contextlib.redirect_stdout(_io.StringIO()) as _printed:
  import mujoco.mjx  # noqa: F401,E402
for _line in _printed.getvalue().splitlines():
  if not _line.startswith(_WARP_PROBE):
    print(_line)
