"""The live view: checks served over the Foxglove WebSocket protocol (foxglove-sdk's server,
subprotocol ``foxglove.sdk.v1``), on the channels of
:class:`robot_change.export.foxglove.CheckChannels`, so Foxglove's "Open connection" to
``ws://HOST:PORT`` shows each check as it happens.

The topics are latched, as ROS's transient-local ones: a client that subscribes after a check
gets that check's message of the topic at once (resent from a thread of the view's own, never
from the server's callback).
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any

from robot_change.export.foxglove import TOPICS, CheckChannels

__all__ = ["DEFAULT_HOST", "DEFAULT_PORT", "LiveView"]

log = logging.getLogger(__name__)

#: This machine only: the view is for a person on the robot's computer or through an SSH
#: tunnel (``ssh -L 8765:localhost:8765 robot``); 0.0.0.0 serves every network.
DEFAULT_HOST = "127.0.0.1"
#: Foxglove's own default port.
DEFAULT_PORT = 8765


class LiveView:
    """A running WebSocket server on ``host``:``port`` (0: any free port; :attr:`port` says
    which).  :meth:`publish` sends a check's messages to every subscriber; :meth:`close`
    stops it.  Raises InputError without foxglove-sdk, and whatever the server raises when it
    cannot listen (the port taken, an address not of this machine)."""

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                 name: str = "robot-change") -> None:
        self.channels = CheckChannels()
        fox = self.channels.fox
        self._latest: dict[str, tuple[Any, int]] = {}
        self._lock = threading.Lock()
        self._resend: queue.SimpleQueue = queue.SimpleQueue()
        view = self

        class Listener(fox.websocket.ServerListener):
            def on_subscribe(self, client: Any, channel: Any) -> None:
                view._resend.put(channel.topic)  # only queue here: the server waits for us

        self.server = fox.start_server(name=name, host=host, port=port,
                                       context=self.channels.context,
                                       server_listener=Listener())
        self.host = host
        self.port = int(self.server.port)
        self._thread = threading.Thread(target=self._resend_main, name="rc-live", daemon=True)
        self._thread.start()

    def publish(self, messages: list[tuple[str, Any]], stamp_ns: int) -> None:
        """Send a check (:func:`~robot_change.export.foxglove.check_messages`) to every
        subscriber, and keep it for those who subscribe later."""
        with self._lock:
            for topic, message in messages:
                self._latest[topic] = (message, stamp_ns)
                self.channels.log(topic, message, stamp_ns)

    def _resend_main(self) -> None:
        while True:
            topic = self._resend.get()
            if topic is None:
                return
            try:
                with self._lock:
                    latest = self._latest.get(topic)
                    if latest is not None and topic in TOPICS:
                        self.channels.log(topic, *latest)
            except Exception:  # noqa: BLE001 -- a viewer's subscription never stops the view
                log.warning("live view: could not resend %s", topic, exc_info=True)

    def close(self) -> None:
        """Stop the server (clients are disconnected) and the resending thread."""
        self._resend.put(None)
        self.server.stop()
        self._thread.join(1.0)
