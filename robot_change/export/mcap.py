"""A check as one MCAP file for Foxglove: the messages of
:func:`robot_change.export.foxglove.check_messages`, zstd-compressed chunks, written
atomically (:mod:`hw.atomic`: a reader, or a crash, sees the old file or the whole new one).
"""

from __future__ import annotations

import os
from typing import Any

from hw.atomic import AtomicFile
from robot_change.export.foxglove import CheckChannels

__all__ = ["CheckFileWriter", "PROFILE"]

#: The MCAP header's profile: no ROS message definitions, Foxglove's own schemas.
PROFILE = ""


class CheckFileWriter:
    """Writes checks to MCAP files, one file per check, through one set of channels (kept for
    the writer's life: a daemon writes many).  Not for two threads at once."""

    def __init__(self) -> None:
        self.channels = CheckChannels()

    def write(self, path: str | os.PathLike, messages: list[tuple[str, Any]], stamp_ns: int,
              metadata: dict[str, str] | None = None) -> int:
        """Write ``messages`` (log time ``stamp_ns``) and a ``robot_change`` metadata record
        to ``path``; returns the file's size in bytes.  Raises OSError when the folder cannot
        be written (the old file, if any, is left as it was)."""
        fox = self.channels.fox
        options = fox.mcap.MCAPWriteOptions(compression=fox.mcap.MCAPCompression.Zstd,
                                            compression_threads=0, profile=PROFILE)
        with AtomicFile(path) as handle:
            with fox.open_mcap(handle, context=self.channels.context,
                               writer_options=options) as writer:
                self.channels.log_all(messages, stamp_ns)
                if metadata:
                    writer.write_metadata("robot_change", dict(metadata))
            size = os.fstat(handle.fileno()).st_size
        return size
