"""A check for other tools: the messages of a check for Foxglove (:mod:`.foxglove`), written to
an MCAP file (:mod:`.mcap`) or served live over the Foxglove WebSocket protocol (:mod:`.live`).

Imports change (and below); the service and the command line import it.  foxglove-sdk (the
``viz`` extra) is imported on first use: without it every entry point raises an InputError
that names the extra."""

#: The colours of what changed, in every picture, point file and view (r, g, b in 0..1): what
#: appeared green, what disappeared red.
APPEARED_RGB = (0.1, 0.8, 0.2)
DISAPPEARED_RGB = (0.9, 0.15, 0.1)
