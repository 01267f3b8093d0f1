"""Errors raised by robot_change.

RobotChangeError
 +-- InputError      arrays or parameters a function cannot work with (wrong dtype or shape,
 |                   non-finite values where they are not allowed, a leaf size <= 0)
 +-- ConfigError     a configuration file or value is wrong; names the key, value and what is allowed
 +-- ProtocolError   bytes from the base controller that do not form a valid message

Every message says what is wrong and what to change.
"""

from __future__ import annotations


class RobotChangeError(Exception):
    """Base class of every error raised by ``robot_change``."""


class InputError(RobotChangeError, ValueError):
    """An array or parameter a function cannot work with.

    Examples: ``voxel_grid(points, leaf=0)``; points of shape (N, 2); depth given as float64.
    """


class ConfigError(RobotChangeError, ValueError):
    """A configuration file or value is wrong.

    Example: ``voxel.leaf_m = -1`` in robot-change.toml -- the message names the key, the value
    and the allowed range.
    """


class ProtocolError(RobotChangeError):
    """Bytes from the base controller that do not form a valid message."""
