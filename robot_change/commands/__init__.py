"""The command implementations of ``robot-change`` (the ``cmd_*`` functions robot_change.cli's
parser dispatches to), one module per group of commands that share their helpers."""
