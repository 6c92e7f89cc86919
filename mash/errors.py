"""The two kinds of failure a command reports in one line instead of a traceback.

Every error a user's input can cause (a robot file, a setting, a path, a run folder, a checkpoint,
an export) derives from :class:`InputError`: the command-line tools print ``error: <message>`` and
exit with status 2. :class:`StorageError` is a write the storage refused (a full disk, a quota, a
read-only file system): not the user's input, so the tools exit 1 on it.
"""

from __future__ import annotations

import errno
import re


class InputError(ValueError):
  """A mistake in what the user asked for: one line naming the input and what was expected."""


class StorageError(Exception):
  """The storage refused a write (a full disk, a quota, a read-only file system): one line naming
  the file or checkpoint step and the reason (:func:`mash.runs.loop.train` adds what is kept)."""


# errno values of a storage that refuses writes, whatever is written.
STORAGE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)
# How TensorStore (Orbax's array writer) reports an OS error: a ValueError whose message ends so.
_OS_ERROR_CODE = re.compile(r"\[os_error_code='(\d+)'\]")


def storage_errno(error: BaseException) -> int | None:
  """The errno of :data:`STORAGE_ERRNOS` behind ``error`` (an ``OSError``, TensorStore's
  ``ValueError`` with ``[os_error_code='28']``, or one of them as its cause), else None."""
  seen = set()
  while error is not None and id(error) not in seen:
    seen.add(id(error))
    code = error.errno if isinstance(error, OSError) else None
    if code is None and (match := _OS_ERROR_CODE.search(str(error))):
      code = int(match.group(1))
    if code in STORAGE_ERRNOS:
      return code
    error = error.__cause__ or error.__context__
  return None
