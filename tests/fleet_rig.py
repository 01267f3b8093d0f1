"""A real Mosquitto broker for the fleet tests and bench/bench_fleet.py: Debian's ``mosquitto``
started on a free loopback port with a generated configuration (never the system service),
optionally TLS (a test CA made with ``openssl``) and password accounts; and a plain paho
subscriber that keeps everything it receives.

Every wait is bounded.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import ssl
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest

MOSQUITTO = shutil.which("mosquitto") or ("/usr/sbin/mosquitto"
                                          if os.access("/usr/sbin/mosquitto", os.X_OK) else None)
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd")
OPENSSL = shutil.which("openssl")


def need_mosquitto() -> str:
    """The broker's binary, or skip: ``./setup.sh test`` installs Debian's mosquitto."""
    if MOSQUITTO is None:
        pytest.skip("Debian's mosquitto broker is not installed (./setup.sh test,viz installs "
                    "it; or apt-get install mosquitto)")
    return MOSQUITTO


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Certificates:
    """A test CA, a server certificate for localhost / 127.0.0.1 signed by it, and an
    unrelated CA (whose trust must not let a client in), made with ``openssl`` in ``folder``."""

    def __init__(self, folder: Path) -> None:
        if OPENSSL is None:
            pytest.skip("openssl is not installed (./setup.sh test,viz installs it)")
        folder.mkdir(parents=True, exist_ok=True)
        self.ca, self.ca_key = folder / "ca.crt", folder / "ca.key"
        self.cert, self.key = folder / "server.crt", folder / "server.key"
        self.other_ca = folder / "other-ca.crt"
        ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]

        def run(*args: str) -> None:
            subprocess.run([OPENSSL, *args], check=True, capture_output=True, timeout=60)

        run("req", "-x509", *ec, "-keyout", str(self.ca_key), "-out", str(self.ca), "-days",
            "2", "-subj", "/CN=robot-change test CA")
        run("req", "-x509", *ec, "-keyout", str(folder / "other-ca.key"), "-out",
            str(self.other_ca), "-days", "2", "-subj", "/CN=another CA")
        csr = folder / "server.csr"
        run("req", *ec, "-keyout", str(self.key), "-out", str(csr), "-subj", "/CN=localhost")
        ext = folder / "server.ext"
        ext.write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
        run("x509", "-req", "-in", str(csr), "-CA", str(self.ca), "-CAkey", str(self.ca_key),
            "-CAcreateserial", "-out", str(self.cert), "-days", "2", "-extfile", str(ext))


class Broker:
    """``mosquitto -c <generated file>`` on 127.0.0.1 (``port``: a free one by default), with
    persistence in ``folder`` (a persistent session's messages outlive a restart), ``tls``
    certificates, ``accounts`` (user -> password; anonymous clients are then refused) and an
    ``acl`` (Mosquitto's acl_file lines; :meth:`reload` reads it again)."""

    def __init__(self, folder: Path, *, port: int | None = None,
                 tls: Certificates | None = None, accounts: dict[str, str] | None = None,
                 acl: str | None = None) -> None:
        self.binary = need_mosquitto()
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.tls = tls
        lines = [f"listener {self.port} 127.0.0.1", "persistence true",
                 f"persistence_location {folder}/", "max_queued_messages 100000",
                 f"log_dest file {folder / 'mosquitto.log'}", "log_type all"]
        if os.geteuid() == 0:
            lines.append("user root")  # else it drops to the user mosquitto: no access here
        if tls is not None:
            lines += [f"cafile {tls.ca}", f"certfile {tls.cert}", f"keyfile {tls.key}"]
        if accounts:
            if MOSQUITTO_PASSWD is None:
                pytest.skip("mosquitto_passwd is not installed (Debian's mosquitto has it)")
            passwords = folder / "passwords"
            for user, password in accounts.items():
                subprocess.run([MOSQUITTO_PASSWD, "-b", *([] if passwords.exists() else ["-c"]),
                                str(passwords), user, password], check=True,
                               capture_output=True, timeout=30)
            lines += ["allow_anonymous false", f"password_file {passwords}"]
        else:
            lines.append("allow_anonymous true")
        if acl is not None:
            (folder / "acl").write_text(acl)
            lines.append(f"acl_file {folder / 'acl'}")
        self.config = folder / "mosquitto.conf"
        self.config.write_text("\n".join(lines) + "\n")
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return (f"{'mqtts' if self.tls else 'mqtt'}://"
                f"{'localhost' if self.tls else '127.0.0.1'}:{self.port}")

    def start(self) -> Broker:
        out = open(self.folder / "mosquitto.out", "a")
        self.proc = subprocess.Popen([self.binary, "-c", str(self.config)], stdout=out,
                                     stderr=subprocess.STDOUT)
        out.close()
        end = time.monotonic() + 15
        while time.monotonic() < end:
            assert self.proc.poll() is None, self.log()
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.5).close()
                return self
            except OSError:
                time.sleep(0.05)
        raise AssertionError(f"mosquitto did not listen on {self.port}:\n{self.log()}")

    def reload(self, acl: str) -> None:
        """A new ACL, read by the running broker (SIGHUP), logged as read."""
        (self.folder / "acl").write_text(acl)
        assert self.proc is not None
        self.proc.send_signal(signal.SIGHUP)
        end = time.monotonic() + 10
        while "Reloading config" not in self.log():
            assert time.monotonic() < end, self.log()
            time.sleep(0.05)

    def stop(self) -> None:
        """SIGTERM: a clean stop (the persistence file is written)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.proc = None

    def log(self) -> str:
        text = ""
        for name in ("mosquitto.out", "mosquitto.log"):
            if (self.folder / name).exists():
                text += (self.folder / name).read_text(errors="replace")[-4000:]
        return text

    def __enter__(self) -> Broker:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class Collector:
    """A plain paho subscriber (QoS 1) that keeps every message: (topic, qos, retain, JSON
    payload).  ``session``: a persistent session (the broker keeps what comes while it is
    away); it reconnects by itself after the broker restarts."""

    def __init__(self, broker: Broker, topics: tuple[str, ...] = ("robot-change/#",), *,
                 session: str | None = None, username: str | None = None,
                 password: str | None = None) -> None:
        self.messages: list[tuple[str, int, bool, Any]] = []
        self.lock = threading.Lock()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2,
                                  client_id=session or "", clean_session=session is None)
        self.client.reconnect_delay_set(0.2, 1.0)
        if broker.tls is not None:
            self.client.tls_set_context(ssl.create_default_context(cafile=str(broker.tls.ca)))
        if username is not None:
            self.client.username_pw_set(username, password)
        self.subscribed = threading.Event()
        self.topics = topics

        def on_connect(client, _u, _f, reason, _p) -> None:
            if not reason.is_failure:
                client.subscribe([(t, 1) for t in topics])

        def on_subscribe(*_args) -> None:
            self.subscribed.set()

        def on_message(_c, _u, m) -> None:
            try:
                payload = json.loads(m.payload)
            except ValueError:
                payload = m.payload
            with self.lock:
                self.messages.append((m.topic, m.qos, bool(m.retain), payload))

        self.client.on_connect = on_connect
        self.client.on_subscribe = on_subscribe
        self.client.on_message = on_message
        self.client.connect("localhost" if broker.tls else "127.0.0.1", broker.port, 5)
        self.client.loop_start()
        assert self.subscribed.wait(10), "the test's subscriber was not subscribed in 10 s"

    def of(self, part: str) -> list[tuple[str, int, bool, Any]]:
        """The messages whose topic holds ``part`` (e.g. "/checks/"), in arrival order."""
        with self.lock:
            return [m for m in self.messages if part in m[0]]

    def wait(self, test: Callable[[Collector], bool], timeout: float, what: str) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if test(self):
                return
            time.sleep(0.05)
        with self.lock:
            got = [(t, str(p)[:120]) for t, _q, _r, p in self.messages[-10:]]
        raise AssertionError(f"{what}: not within {timeout} s; last messages: {got}")

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()
