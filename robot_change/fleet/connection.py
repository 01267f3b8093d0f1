"""How to reach the fleet's broker: settings, a configured paho client, and what went wrong.

    settings = BrokerSettings("mqtts://broker.lan", ca_file="/etc/robot-change/ca.crt",
                              username="robot-7", password_file="/etc/robot-change/mqtt.pw")
    client = new_client(settings, "robot-change-robot-7")
    open_connection(client, settings)       # FleetError naming the broker and what to check

The robot's publisher speaks MQTT 5 (Mosquitto >= 1.6): its PUBACKs say when the broker refused
a message (an ACL that does not allow the topic), where MQTT 3.1.1's acknowledge it as taken
and drop it.  The fleet's readers speak MQTT 3.1.1.  Both with paho-mqtt's 2.x callback API.
The password is read from its file at each connection (a new password needs no restart) and
never logged or printed.
"""

from __future__ import annotations

import dataclasses
import socket
import ssl
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt

from robot_change import validate
from robot_change.errors import FleetError

__all__ = ["BrokerSettings", "new_client", "open_connection", "refusal", "tls_context"]

#: Longest password read from ``password_file`` (MQTT allows 65535 bytes).
MAX_PASSWORD_BYTES = 65535


@dataclasses.dataclass(frozen=True)
class BrokerSettings:
    """A broker and the credentials to use it.

    ``url``: ``mqtt://HOST[:PORT]`` or ``mqtts://HOST[:PORT]`` (TLS).  ``ca_file``: the CA
    certificates the broker's certificate must be signed by (mqtts; None: the system's).
    ``cert_file`` / ``key_file``: a client certificate (mqtts).  ``username`` and
    ``password_file`` (the password alone in a file; a trailing newline is ignored).
    ``keepalive_s``: MQTT keep-alive; the broker publishes the Last Will after 1.5 times it
    without a word (at once when the TCP connection closes).  ``connect_timeout_s``: the
    longest wait for the TCP connection, the TLS handshake and the broker's CONNACK.
    """

    url: str
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    username: str | None = None
    password_file: str | None = None
    keepalive_s: int = 30
    connect_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        validate.broker_url("BrokerSettings", "url", self.url)
        validate.whole("BrokerSettings", "keepalive_s", self.keepalive_s, 5, 3600,
                       unit=" seconds")
        validate.positive("BrokerSettings", "connect_timeout_s", self.connect_timeout_s, 60.0,
                          unit=" seconds")

    @property
    def scheme(self) -> str:
        return validate.broker_url("BrokerSettings", "url", self.url)[0]

    @property
    def host(self) -> str:
        return validate.broker_url("BrokerSettings", "url", self.url)[1]

    @property
    def port(self) -> int:
        return validate.broker_url("BrokerSettings", "url", self.url)[2]

    @property
    def tls(self) -> bool:
        return self.scheme == "mqtts"

    def cleartext_warning(self) -> str:
        """Why the password would cross the network readable (a password over ``mqtt://`` to
        a host other than this machine), or ""."""
        if self.password_file is None or self.tls or self.host in ("localhost", "127.0.0.1",
                                                                    "::1"):
            return ""
        return (f"the password goes to {self.host} in clear text over mqtt://: use mqtts:// "
                "(docs/deployment.md, \"A fleet on an MQTT broker\")")

    def password(self) -> str | None:
        """The password in ``password_file`` (None without one).  Raises :class:`FleetError`
        naming the file (never its content) when it cannot be read."""
        if self.password_file is None:
            return None
        try:
            raw = Path(self.password_file).read_bytes()
        except OSError as exc:
            raise FleetError(f"{self.url}: cannot read the password file {self.password_file} "
                             f"({exc.strerror}); check fleet.password_file and that the "
                             "service user may read it") from None
        text = raw.decode("utf-8", "replace").rstrip("\r\n")
        if not text or len(text.encode()) > MAX_PASSWORD_BYTES or "\n" in text:
            raise FleetError(f"{self.url}: the password file {self.password_file} must hold "
                             "the password alone on one line")
        return text


def tls_context(settings: BrokerSettings) -> ssl.SSLContext:
    """The TLS context of an mqtts:// broker: its CA file and the client certificate loaded.
    Raises :class:`FleetError` naming the file that cannot be used."""
    try:
        context = ssl.create_default_context(cafile=settings.ca_file)
    except (OSError, ssl.SSLError) as exc:
        raise FleetError(f"{settings.url}: cannot use the CA file {settings.ca_file} "
                         f"({getattr(exc, 'strerror', None) or exc}); fleet.ca_file must be "
                         "PEM certificates") from None
    if settings.cert_file is not None:
        try:
            context.load_cert_chain(settings.cert_file, settings.key_file)
        except (OSError, ssl.SSLError) as exc:
            raise FleetError(f"{settings.url}: cannot use the client certificate "
                             f"{settings.cert_file} with the key {settings.key_file} "
                             f"({getattr(exc, 'strerror', None) or exc}); check fleet.cert_file "
                             "and fleet.key_file (PEM, the key unencrypted)") from None
    return context


def new_client(settings: BrokerSettings, client_id: str, *, clean_session: bool = True,
               will: tuple[str, bytes, int, bool] | None = None, v5: bool = False
               ) -> mqtt.Client:
    """A paho client for ``settings`` (TLS, user name and password set; not connected yet).
    ``will``: (topic, payload, qos, retain) the broker publishes when the client vanishes.
    ``v5``: MQTT 5, a clean start every connection (``clean_session`` is 3.1.1's); else
    MQTT 3.1.1.  Raises :class:`FleetError` for unreadable TLS or password files."""
    client = (mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id,
                          protocol=mqtt.MQTTv5) if v5 else
              mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id,
                          clean_session=clean_session, protocol=mqtt.MQTTv311))
    client.connect_timeout = settings.connect_timeout_s
    if settings.tls:
        client.tls_set_context(tls_context(settings))
    if settings.username is not None:
        client.username_pw_set(settings.username, settings.password())
    if will is not None:
        client.will_set(*will)
    return client


def open_connection(client: mqtt.Client, settings: BrokerSettings) -> None:
    """TCP connection, TLS handshake and CONNECT (the CONNACK comes in a later ``loop()``).
    Raises :class:`FleetError` that names the broker and what to check."""
    where = f"{settings.url} ({settings.host} port {settings.port})"
    try:
        client.connect(settings.host, settings.port, settings.keepalive_s)
    except ssl.SSLCertVerificationError as exc:
        raise FleetError(f"{where}: the broker's certificate is not trusted "
                         f"({exc.verify_message}); check fleet.ca_file and that the URL's "
                         "host is a name in the certificate") from None
    except ssl.SSLError as exc:
        raise FleetError(f"{where}: the TLS handshake failed ({exc.reason or exc}); is the "
                         "broker's port a TLS listener (mqtts://) and does it accept this "
                         "client's certificate?") from None
    except ConnectionRefusedError:
        raise FleetError(f"{where}: connection refused; is the broker running and listening "
                         "on that port?", transient=True) from None
    except socket.gaierror as exc:
        raise FleetError(f"{where}: cannot resolve the host name ({exc.strerror})",
                         transient=True) from None
    except TimeoutError:
        raise FleetError(f"{where}: no answer within {settings.connect_timeout_s:g} s; is the "
                         "address right and the network up?", transient=True) from None
    except OSError as exc:
        raise FleetError(f"{where}: {exc.strerror or exc}", transient=True) from None


def refusal(settings: BrokerSettings, reason: Any) -> str:
    """What a refused CONNACK means, for the log: the broker's reason and what to change."""
    text = str(reason)
    lowered = text.lower()
    if "user name or password" in lowered or "bad username" in lowered:
        hint = "check fleet.username and the password in fleet.password_file"
    elif "not authori" in lowered:
        hint = ("check fleet.username and the password in fleet.password_file, and that the "
                "broker has an account and an ACL for this robot")
    elif "identifier" in lowered:
        hint = "the broker refused the client id (robot-change-<robot_id>)"
    elif "protocol" in lowered:
        hint = "the robot speaks MQTT 5: the broker must too (Mosquitto 1.6 or later)"
    else:
        hint = "see the broker's log"
    return f"{settings.url}: the broker refused the connection: {text}; {hint}"
