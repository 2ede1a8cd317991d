"""A node's logger without rclpy's per-call source lookup.

rclpy's logger finds each call's caller with ``inspect.getframeinfo``, which reads the caller's source file and
maps every loaded module to its file the first time: 35 ms of CPU for a node's first line at start-up, and a
fraction of a millisecond for every later one. :class:`NodeLogger` hands the same record (severity, logger name,
message, function, file, line) to the same rcutils call, taking the caller from its frame directly; calls with
rclpy's filters (``throttle_duration_sec``, ``once``, ``skip_first``) and everything else go to rclpy's logger.
"""

from __future__ import annotations

import os
import sys

from rclpy.impl import rcutils_logger
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.impl.logging_severity import LoggingSeverity

__all__ = ['NodeLogger']

_LOG = getattr(_rclpy, 'rclpy_logging_rcutils_log', None)
_ENABLED_FOR = getattr(_rclpy, 'rclpy_logging_logger_is_enabled_for', None)
# rclpy's own path names the first caller outside the files listed here (a list kept for wrappers like this one).
getattr(rcutils_logger, '_internal_callers', []).append(os.path.realpath(__file__))


class NodeLogger:
    """The node's rclpy logger (``logger``) with fast ``debug`` / ``info`` / ``warning`` / ``error`` / ``fatal``."""

    def __init__(self, logger):
        self._logger = logger
        self.name = logger.name
        self._direct = _LOG is not None and _ENABLED_FOR is not None

    def __getattr__(self, name: str):
        return getattr(self._logger, name)

    def _log(self, severity: LoggingSeverity, message: str, kwargs: dict) -> bool:
        if kwargs or not self._direct:
            return self._logger.log(message, severity, **kwargs)
        if not _ENABLED_FOR(self.name, severity):
            return False
        frame = sys._getframe(2)  # the caller of debug/info/...
        code = frame.f_code
        _LOG(severity, self.name, message, code.co_name, os.path.abspath(code.co_filename), frame.f_lineno)
        return True

    def debug(self, message: str, **kwargs) -> bool:
        return self._log(LoggingSeverity.DEBUG, message, kwargs)

    def info(self, message: str, **kwargs) -> bool:
        return self._log(LoggingSeverity.INFO, message, kwargs)

    def warning(self, message: str, **kwargs) -> bool:
        return self._log(LoggingSeverity.WARN, message, kwargs)

    warn = warning

    def error(self, message: str, **kwargs) -> bool:
        return self._log(LoggingSeverity.ERROR, message, kwargs)

    def fatal(self, message: str, **kwargs) -> bool:
        return self._log(LoggingSeverity.FATAL, message, kwargs)
