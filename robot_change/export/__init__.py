"""A check for other tools: the messages of a check for Foxglove (:mod:`.foxglove`), written to
an MCAP file (:mod:`.mcap`) or served live over the Foxglove WebSocket protocol (:mod:`.live`).

Imports change (and below); the service and the command line import it.  foxglove-sdk (the
``viz`` extra) is imported on first use: without it every entry point raises an InputError
that names the extra."""
