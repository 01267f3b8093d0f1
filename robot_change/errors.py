"""Errors raised by robot_change.

RobotChangeError
 +-- InputError         arrays or parameters a function cannot work with (wrong dtype or shape,
 |    |                 non-finite values where they are not allowed, a leaf size <= 0)
 |    +-- BadValue            one value refused by robot_change.validate (owner, name, value,
 |    |                       what is allowed): config and protocol re-word it as theirs
 |    +-- EmptySceneError     nothing left of a scene after filtering (camera covered? ...)
 |    +-- SceneMismatchError  reference and current made with other intrinsics or parameters
 +-- ConfigError        a configuration file or value is wrong; names the key, value and what
 |                      is allowed
 +-- MixtureFileError   a saved mixture that is truncated, foreign, newer or tampered with
 +-- SceneFileError     a saved scene (station reference) that is truncated, foreign, newer or
 |                      tampered with
 +-- SolverError        a numeric solver failed where it must not (a bug to report, with the
 |                      inputs)
 +-- StoreError         the per-station reference store
 |    +-- StationNameError  a station name that is not allowed (it comes from the serial line)
 |    +-- ReferenceMissing  no usable reference for a station (none, or quarantined)
 +-- ProtocolError      the serial protocol to the base controller
 |    +-- MessageError  a message with invalid fields or payload bytes (carries the NAK reason)
 |    +-- LinkError     the link used in a way the protocol does not allow
 +-- FleetError         the fleet's MQTT broker cannot be reached, refused the connection, or
                        a credential file cannot be read (names the broker and what to check)

ConvergenceWarning (a warning, not an error): an iterative fit stopped at its bound.

Every message says what is wrong and what to change.
"""

from __future__ import annotations


class RobotChangeError(Exception):
    """Base class of every error raised by ``robot_change``."""


class InputError(RobotChangeError, ValueError):
    """An array or parameter a function cannot work with.

    Examples: ``voxel_grid(points, leaf=0)``; points of shape (N, 2); depth given as float64.
    """


class BadValue(InputError):
    """One value refused by :mod:`robot_change.validate`: ``owner.name=value: must be
    <allowed>``.  ``wrong_type``: the value is not even of the right kind (a string for a
    number), as opposed to out of range.  The configuration re-words it as a ConfigError and the
    protocol as a MessageError (with its NAK reason), from these attributes.
    """

    def __init__(self, owner: str, name: str, value: object, allowed: str, *,
                 wrong_type: bool = False) -> None:
        super().__init__(f"{owner}.{name}={value!r}: must be {allowed}")
        self.owner, self.name, self.value, self.allowed = owner, name, value, allowed
        self.wrong_type = wrong_type


class ConfigError(RobotChangeError, ValueError):
    """A configuration file or value is wrong.

    Example: ``voxel.leaf_m = -1`` in robot-change.toml -- the message names the key, the value
    and the allowed range.
    """


class ProtocolError(RobotChangeError):
    """Bytes from the base controller that do not form a valid message."""


class MixtureFileError(RobotChangeError):
    """A saved Gaussian mixture that cannot be read back.

    Examples: the file is truncated or not an .npz; its header names another format or a newer
    version than this robot_change understands; the checksum of its arrays does not match (the
    file was changed or damaged after it was written). The message names the file and what to do
    (fit and save the reference again, or upgrade robot_change).
    """


class ConvergenceWarning(UserWarning):
    """An iterative fit stopped at its iteration bound before it converged.

    The result is still usable (the last iterate); raise ``max_iter`` or ``tol`` if it recurs.
    """


class MessageError(ProtocolError, ValueError):
    """A protocol message whose fields or payload bytes are invalid.

    Raised when a message is built with a bad value (``SetParam(param=1, value=99)``: watch_m
    allows 1..10) and when received payload bytes do not decode.  ``reason`` is the NAK reason
    code (docs/protocol.md, section "NAK") a receiver answers with: 2 bad payload, 4 unknown
    parameter, 5 value out of range.
    """

    def __init__(self, message: str, reason: int = 2) -> None:
        super().__init__(message)
        self.reason = reason


class LinkError(ProtocolError):
    """The link to the base controller was used in a way the protocol does not allow.

    Examples: the module tries to send a base-only message (CHECK); a heartbeat of the wrong
    direction is installed.  The message names the message type and who may send it.
    """


class SceneFileError(RobotChangeError):
    """A saved scene model (a station's reference) that cannot be read back.

    Examples: the file is truncated or not an .npz; its header names another format, or a newer
    format version than this robot_change reads; the checksum over its header and arrays does
    not match (changed or damaged after it was written); arrays are missing or malformed; its
    parameters do not validate.  The message names the file and what to do (capture and save
    the reference again, or upgrade robot_change).
    """


class EmptySceneError(InputError):
    """Depth frames that leave (almost) no points after filtering, so no scene can be built.

    The message says which stage emptied the cloud and what to check: camera covered or
    pointed at nothing, everything beyond the maximum depth, only the floor in view.
    """


class SceneMismatchError(InputError):
    """A reference and a current view that cannot be compared: other image size or
    intrinsics, or other cloud parameters (leaf, depth range, outlier or plane settings).

    The message lists every difference and the fix (recapture the reference with the current
    settings, or pass the reference's intrinsics / parameters).
    """


class SolverError(RobotChangeError, RuntimeError):
    """A numeric solver failed where it must not: the transportation simplex ended in a state
    it cannot (a bug in robot_change; the message names the problem's size and asks for a
    report with the inputs).  The service answers it as FAULT INTERNAL_ERROR and carries on.
    """


class StoreError(RobotChangeError):
    """The reference store cannot do what was asked.

    Examples: the state folder cannot be written (disk full, owned by another user); a file
    cannot be read for lack of permissions.  The message names the station, the path and what
    to check.
    """


class StationNameError(StoreError, ValueError):
    """A station name that is not a plain name (it comes from the serial line).

    Examples: ``""``, ``"../etc"``, ``"a/b"``, ``"dock.prev"``, a name of 33 characters.  The
    message says what a name may hold: 1..32 ASCII letters, digits, '_' or '-'.
    """


class ReferenceMissing(StoreError, LookupError):
    """A station has no usable reference.

    Examples: none was ever captured; its file failed verification (truncated, foreign, newer,
    tampered) and was moved to quarantine.  ``station`` names it; ``quarantined`` is the path
    the bad file was moved to (None when there was no file).  The fix: CAPTURE_REFERENCE again.
    """

    def __init__(self, message: str, station: str = "", quarantined=None) -> None:
        super().__init__(message)
        self.station = station
        self.quarantined = quarantined


class FleetError(RobotChangeError):
    """The fleet's MQTT broker cannot be used.

    Examples: nothing listens at the broker's address; the TLS handshake fails (the broker's
    certificate is not signed by ``fleet.ca_file``); the broker refuses the user name or
    password; ``fleet.password_file`` cannot be read.  The message names the broker URL and
    what to check.  The daemon logs it and retries with a back-off; the robot is never held up
    by it (checks and PAUSE go on, reports wait in the spool).  ``transient``: the broker is
    down or out of reach (it may come back), as opposed to a setting that must be changed.
    """

    def __init__(self, message: str, *, transient: bool = False) -> None:
        super().__init__(message)
        self.transient = transient
