"""The root of the errors lego_loam_py raises on purpose, and the exit code each gives on the command line.

Every module's own error class derives from :class:`LegoLoamError` (and from the built-in it used to be, so
``except ValueError`` still catches a ParameterError). The commands of ``lego_loam_py`` raise them and
``lego_loam_py.cli.run_command`` turns them into one ``error: ...`` line and the exit code, in one place:

* 2: the command was given something it cannot start with (an option, a parameter): :class:`UsageError`,
  ``ParameterError``;
* 1: the run failed on its data (a bag that cannot be read, a capture that cannot be decoded, ...): every
  other LegoLoamError.

No traceback is shown for these: the message is written for the user.
"""

from __future__ import annotations

__all__ = ['LegoLoamError', 'UsageError']


class LegoLoamError(Exception):
    """An error with a message for the user; ``exit_code`` is what the command line exits with."""

    exit_code = 1


class UsageError(LegoLoamError, ValueError):
    """An option or a combination of options that a command cannot run with."""

    exit_code = 2
