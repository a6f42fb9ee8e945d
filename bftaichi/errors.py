"""User-facing errors.

Everything a user can get wrong (a missing file, a bad key, an absurd voxel size) raises
:class:`BftaichiError` (a ``ValueError``) with a message that names the file, frame or key.
The CLI turns it into ``error: <message>`` and exit code 2, never a traceback.
"""


class BftaichiError(ValueError):
    """Bad input or configuration; the message says which file, frame or key, and why."""


class ConfigError(BftaichiError):
    """A scene file or ``--set`` override is invalid (unknown key, wrong type, out of range)."""


class DataError(BftaichiError):
    """A dataset, frame or mesh file is missing, unreadable or inconsistent."""


class NoSurfaceError(BftaichiError):
    """The frames were read but no voxel was observed, so there is no surface to mesh."""


class BftaichiWarning(UserWarning):
    """Something probably wrong that does not stop the work (a partial copy of a sequence, a
    default camera, a stale lock broken); the CLI prints ``warning: <message>`` on stderr."""
