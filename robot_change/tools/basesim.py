"""A simulated base controller: the other end of the serial link, for tests, demos and bring-up.

It speaks the protocol through the same codec and session as the module
(robot_change.link.protocol, robot_change.link.session), follows the base's pause rules
(docs/protocol.md 7.6) and prints every message it receives in a readable form.  Interactive:
commands typed on stdin.  Scripted (``--script``):
one command per line, plus ``wait``, ``expect`` and ``expect-none`` lines; a failed expectation
ends the run with exit status 1.

Commands::

    capture STATION | check STATION | watch STATION     CAPTURE_REFERENCE / CHECK / WATCH
    stop | arm | disarm | resume | status               STOP / ARM / DISARM / RESUME / STATUS_QUERY
    set PARAM VALUE | get PARAM                         SET_PARAM / GET_PARAM (see `params`)
    motion parked|moving|unknown                        what BASE_HEARTBEAT says
    raw HEX | garbage N                                 write bytes as they are / N random bytes
    params | help | quit
  scripts only:
    wait SECONDS
    expect WHAT [field=value ...] [TIMEOUT]             default timeout 2 s
    expect-none WHAT [field=value ...] SECONDS

WHAT is a message type (PAUSE, CHANGE_REPORT, HEARTBEAT, ...), REPORT (a whole change report),
FAILED (one of our commands was not delivered), LINK (a link state change, e.g. ``new=up``) or
BASE (the base's own pause state, ``paused=1``).  ``expect`` matches an event no earlier
``expect`` matched, that arrived after the last command (or the last match, if that came
earlier): so ``check kitchen`` then ``expect PAUSE`` finds a PAUSE that came during a ``wait``
in between, and the replies to one command may be expected in any order.
"""

from __future__ import annotations

import os
import queue
import shlex
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any, TextIO

from hw.serial_port import open_port
from robot_change.errors import InputError, ProtocolError
from robot_change.link.protocol import (
    PARAM_BY_NAME,
    PARAMS,
    VERSION,
    WEAK_BITS,
    Arm,
    BaseHeartbeat,
    CaptureReference,
    ChangeReport,
    Check,
    CheckResult,
    Disarm,
    GetParam,
    Heartbeat,
    Message,
    Motion,
    MsgType,
    ReportAssembler,
    Resume,
    Role,
    SetParam,
    StatusQuery,
    Stop,
    Watch,
    describe,
)
from robot_change.link.session import (
    Delivered,
    Link,
    LinkConfig,
    LinkRunner,
    LinkState,
    PortProblem,
    Received,
    SendFailed,
    StateChanged,
)

#: The base pauses after this long without a valid frame from the module (docs/protocol.md 7.6).
PAUSE_SILENCE = 0.4
DEFAULT_EXPECT_TIMEOUT = 2.0
PSEUDO = ("REPORT", "FAILED", "LINK", "BASE")


@dataclass(frozen=True)
class BaseState:
    """The base's own pause state, logged as ``BASE`` for ``expect``."""

    paused: bool
    why: str


@dataclass(frozen=True)
class Entry:
    """One thing that happened, for ``expect``: its name, the object, when."""

    name: str
    obj: Any
    t: float


def _station(args: list[str], verb: str) -> str:
    if len(args) != 1:
        raise InputError(f"`{verb}` takes one station name, e.g. `{verb} kitchen`")
    return args[0]


def _param(name: str) -> int:
    if name not in PARAM_BY_NAME:
        raise InputError(f"unknown parameter {name!r}; known: {', '.join(PARAM_BY_NAME)}")
    return PARAM_BY_NAME[name].id


def _int(text: str, what: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise InputError(f"{what} {text!r} is not an integer") from None


def _seconds(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{what} {text!r} is not a number of seconds") from None
    if not 0 <= value <= 3600:
        raise InputError(f"{what} {value} s: give 0..3600 seconds")
    return value


_SIMPLE: dict[str, Callable[[], Message]] = {
    "stop": Stop, "arm": Arm, "disarm": Disarm, "resume": Resume, "status": StatusQuery,
}


def parse_command(line: str) -> tuple[str, list[str], Message | None]:
    """Split a command line into (verb, args, message to send or None); InputError when wrong."""
    try:
        words = shlex.split(line, comments=True)
    except ValueError as exc:
        raise InputError(f"cannot read {line!r}: {exc}") from None
    if not words:
        return "", [], None
    verb, args = words[0].lower(), words[1:]
    try:
        if verb == "capture":
            return verb, args, CaptureReference(_station(args, verb))
        if verb in ("check", "watch"):
            return verb, args, (Check if verb == "check" else Watch)(_station(args, verb))
        if verb in _SIMPLE:
            if args:
                raise InputError(f"`{verb}` takes no argument")
            return verb, args, _SIMPLE[verb]()
        if verb == "set":
            if len(args) != 2:
                raise InputError("`set` takes a parameter and a value, e.g. `set watch_m 3`")
            return verb, args, SetParam(_param(args[0]), _int(args[1], "value"))
        if verb == "get":
            if len(args) != 1:
                raise InputError("`get` takes a parameter, e.g. `get watch_m`")
            return verb, args, GetParam(_param(args[0]))
    except ProtocolError as exc:  # a value the protocol refuses (station name, parameter bounds)
        raise InputError(str(exc)) from None
    if verb == "motion":
        if (len(args) != 1 or args[0].upper() not in Motion.__members__
                or args[0].upper() == "PAUSED"):
            raise InputError("`motion` takes parked, moving or unknown")
    elif verb == "raw":
        try:
            bytes.fromhex(" ".join(args))
        except ValueError:
            raise InputError("`raw` takes hex bytes, e.g. "
                             "`raw 04 01 02 05 01 03 bd c5 00`") from None
    elif verb == "garbage":
        if len(args) != 1 or not 0 < _int(args[0], "byte count") <= 100_000:
            raise InputError("`garbage` takes a byte count, 1..100000")
    elif verb in ("wait",):
        if len(args) != 1:
            raise InputError("`wait` takes seconds, e.g. `wait 0.5`")
        _seconds(args[0], "wait")
    elif verb in ("expect", "expect-none"):
        _parse_expect(verb, args)
    elif verb not in ("help", "params", "quit", "exit"):
        raise InputError(f"unknown command {verb!r}; type `help`")
    return verb, args, None


def _parse_expect(verb: str, args: list[str]) -> tuple[str, dict[str, str], float]:
    if not args:
        raise InputError(f"`{verb}` takes what to expect, e.g. `{verb} PAUSE 2.0`")
    what = args[0].upper()
    if what not in MsgType.__members__ and what not in PSEUDO:
        raise InputError(f"`{verb} {args[0]}`: expect a message type "
                         f"({', '.join(MsgType.__members__)}) or {', '.join(PSEUDO)}")
    filters, timeout = {}, None
    for arg in args[1:]:
        if "=" in arg:
            key, _, value = arg.partition("=")
            filters[key] = value
        elif timeout is None:
            timeout = _seconds(arg, f"`{verb}` timeout")
        else:
            raise InputError(f"`{verb}`: unexpected {arg!r} (filters are field=value)")
    if timeout is None:
        if verb == "expect-none":
            raise InputError("`expect-none` needs the seconds to watch, e.g. "
                             "`expect-none PAUSE 1.0`")
        timeout = DEFAULT_EXPECT_TIMEOUT
    return what, filters, timeout


def _matches(obj: Any, filters: dict[str, str]) -> bool:
    for key, want in filters.items():
        if not hasattr(obj, key):
            return False
        value = getattr(obj, key)
        if isinstance(value, Enum):
            ok = want.upper() in (value.name, str(value.value).upper())
        elif isinstance(value, bool):
            ok = want.lower() in (("1", "true", "yes") if value else ("0", "false", "no"))
        elif isinstance(value, int):
            try:
                ok = int(want, 0) == value
            except ValueError:
                ok = False
        elif isinstance(value, tuple):
            ok = want == str(len(value))
        else:
            ok = str(value) == want
        if not ok:
            return False
    return True


class BaseSim:
    """The simulated base over ``port`` (anything LinkRunner accepts).  Single-threaded: call
    :meth:`pump` to let time pass; :meth:`command` to act; read :attr:`log`.
    """

    def __init__(self, port: Any, *, out: TextIO | None = None, verbose: bool = False,
                 clock: Callable[[], float] = time.monotonic, baudrate: int = 115200,
                 proto_max: int = VERSION) -> None:
        self.out = out or sys.stdout
        self.verbose = verbose
        self.clock = clock
        self.link = Link(Role.BASE, clock=clock, config=LinkConfig.for_baud(baudrate),
                         proto_max=proto_max)
        self.runner = LinkRunner(self.link, port)
        self.port = port
        self.t0 = clock()
        self.log: list[Entry] = []
        self.cursor = 0  # just past the entry the last ``expect`` matched
        self.mark = 0  # len(log) when the last command was sent
        self.consumed: set[int] = set()  # entries an ``expect`` already matched
        self.assembler = ReportAssembler()
        self.motion = Motion.PARKED
        self.paused = True  # until the module is heard
        self.pause_why = "module not heard yet"
        self._latched = False
        self._resume_acked = False
        self._clear_beat = False  # a HEARTBEAT with paused = 0 was heard (7.6)
        self._last_beat: tuple | None = None
        self.failed: list[SendFailed] = []
        self.runner.set_heartbeat(BaseHeartbeat(self.motion))

    # -- output -----------------------------------------------------------------------------------

    def say(self, text: str) -> None:
        print(f"[{self.clock() - self.t0:8.3f}] {text}", file=self.out, flush=True)

    def _record(self, name: str, obj: Any) -> None:
        self.log.append(Entry(name, obj, self.clock()))

    # -- time -----------------------------------------------------------------------------------

    def pump(self, seconds: float, until: Callable[[], bool] | None = None) -> bool:
        """Run the link for ``seconds`` (or until ``until()`` is true: then return True)."""
        end = self.clock() + seconds
        while True:
            if until is not None and until():
                return True
            left = end - self.clock()
            if left <= 0:
                return False
            for event in self.runner.step(min(0.01, left)):
                self._handle(event)
            self._pause_rules()

    def _handle(self, event: Any) -> None:
        if isinstance(event, Received):
            self._on_message(event.message, event.seq)
        elif isinstance(event, Delivered):
            if isinstance(event.message, Resume):
                self._resume_acked = True
            if self.verbose or not isinstance(event.message, StatusQuery):
                self.say(f"ok {event.message.TYPE.name} seq {event.seq} "
                         f"({event.rtt * 1000:.1f} ms, "
                         f"{event.tries} tr{'y' if event.tries == 1 else 'ies'})")
        elif isinstance(event, SendFailed):
            self.failed.append(event)
            self._record("FAILED", event)
            self.say(f"!! {describe(event.message)} seq {event.seq} failed: {event.reason}")
        elif isinstance(event, StateChanged):
            self._record("LINK", event)
            self.say(f"== link {event.new.value}: {event.why}")
        elif isinstance(event, PortProblem):
            self.say(f"== port {'back' if event.up else 'lost'}: {event.detail}")

    def _on_message(self, message: Message, seq: int) -> None:
        self._record(message.TYPE.name, message)
        if isinstance(message, Heartbeat):
            self._clear_beat = not message.paused
            if message.paused:
                self._latched = True
            elif self._latched and self._resume_acked:
                self._latched = False  # RESUME acked, then a heartbeat with the latch clear
            key = (message.state, message.paused, message.armed, message.fault)
            if self.verbose or key != self._last_beat:
                self.say(f"<- {describe(message)}")
            self._last_beat = key
            return
        if not self.verbose and message.TYPE == MsgType.BASE_HEARTBEAT:
            return
        self.say(f"<- {describe(message)}" + (f"  (seq {seq})" if seq else ""))
        if message.TYPE == MsgType.PAUSE:
            self._latched = True
            self._resume_acked = False
        if isinstance(message, CheckResult):
            dx, dy, dz = message.offset_mm
            roll, pitch, yaw = (v / 100 for v in message.rotation_cdeg)
            weak = [n for n, bit in WEAK_BITS.items() if message.weak & bit]
            self.say(f"     {message.outcome.name.lower()}; the robot stands {dx} mm forward, "
                     f"{dy} mm left, {dz} mm up, roll {roll:.2f} pitch {pitch:.2f} yaw "
                     f"{yaw:.2f} deg off its station pose; fitness "
                     f"{message.fitness_permille / 10:.1f} %"
                     + (f"; weak: {', '.join(weak)}" if weak else ""))
        if isinstance(message, ChangeReport):
            frame = ("forward, left, up" if self.link.version >= 2
                     else "camera x right, y down, z forward")
            for region in message.regions:
                x, y, z = region.centroid_mm
                dx, dy, dz = region.extent_mm
                self.say(f"     {region.kind.name.lower():11s} at ({x}, {y}, {z}) mm ({frame}), "
                         f"{dx} x {dy} x {dz} mm, {region.points} points")
            report = self.assembler.add(message)
            if report is not None:
                self._record("REPORT", report)
                self.say(f"   report {report.report_id} for {report.station}: "
                         f"{len(report.regions)} region(s)" if report.regions else
                         f"   report {report.report_id} for {report.station}: no change")

    def _pause_rules(self) -> None:
        """docs/protocol.md 7.6 as the base applies them: latch, silence, faulty link."""
        silent = self.clock() - self.link.last_heard
        reasons = []
        if self.link.stats.frames_in == 0:
            reasons.append("module not heard yet")
        elif not self._clear_beat and not self._latched:
            reasons.append("no HEARTBEAT with paused = 0 yet")
        if self._latched:
            reasons.append("the module's pause latch is set")
        if silent > PAUSE_SILENCE:
            reasons.append(f"module silent for {silent:.2f} s")
        if self.link.state == LinkState.FAULTY:
            reasons.append("link faulty")
        paused = bool(reasons)
        if paused != self.paused:
            self.paused = paused
            self.pause_why = "; ".join(reasons) or "latch clear, module heard"
            self._record("BASE", BaseState(paused, self.pause_why))
            self.say(f"** base {'PAUSED' if paused else 'may move'}: {self.pause_why}")
            self.runner.set_heartbeat(BaseHeartbeat(Motion.PAUSED if paused else self.motion))

    # -- commands -------------------------------------------------------------------------------

    def command(self, line: str) -> bool:
        """Carry out one interactive command; False on quit.  InputError when it is wrong."""
        verb, args, message = parse_command(line)
        if message is not None:
            self.mark = len(self.log)  # expect() looks at what arrives from here on
            seq = self.runner.send(message)
            self.say(f"-> {describe(message)}  (seq {seq})")
        elif verb == "motion":
            self.motion = Motion[args[0].upper()]
            if not self.paused:
                self.runner.set_heartbeat(BaseHeartbeat(self.motion))
            self.say(f"   motion {self.motion.name}")
        elif verb == "raw":
            self.port.write(bytes.fromhex(" ".join(args)))
            self.say(f"-> raw {' '.join(args)}")
        elif verb == "garbage":
            self.port.write(os.urandom(int(args[0], 0)))
            self.say(f"-> {args[0]} random bytes")
        elif verb == "params":
            for p in PARAMS:
                print(f"  {p.name:22s} {p.minimum}..{p.maximum} {p.unit} (default {p.default}): "
                      f"{p.meaning}", file=self.out)
        elif verb == "help":
            print(__doc__.split("Commands::", 1)[1].split("WHAT is", 1)[0].rstrip(), file=self.out)
        elif verb in ("quit", "exit"):
            return False
        elif verb in ("wait", "expect", "expect-none"):
            raise InputError(f"`{verb}` is for scripts (--script FILE)")
        return True

    def expect(self, what: str, filters: dict[str, str], timeout: float) -> Entry | None:
        """Wait up to ``timeout`` s for a matching entry that no earlier ``expect`` matched and
        that arrived after the last command was sent or after the last match, whichever came
        first.  So the replies to one command may be expected in any order (a PAUSE, the
        base's own pause state and a report arrive in an order the line decides), while
        nothing from before both is matched again."""
        found: list[Entry] = []

        def seen() -> bool:
            for i in range(min(self.cursor, self.mark), len(self.log)):
                entry = self.log[i]
                if (i not in self.consumed and entry.name == what
                        and _matches(entry.obj, filters)):
                    found.append(entry)
                    self.consumed.add(i)
                    self.cursor = max(self.cursor, i + 1)
                    return True
            return False

        self.pump(timeout, until=seen)
        return found[0] if found else None

    def expect_none(self, what: str, filters: dict[str, str], seconds: float) -> Entry | None:
        """Watch ``seconds``: return the first matching entry that arrives, or None."""
        start = len(self.log)
        hit: list[Entry] = []

        def seen() -> bool:
            hit.extend(e for e in self.log[start:] if e.name == what and _matches(e.obj, filters))
            return bool(hit)

        self.pump(seconds, until=seen)
        return hit[0] if hit else None

    def run_script(self, lines: list[str], connect_timeout: float = 5.0) -> int:
        """Run a script (already checked by :func:`check_script`); 0 when every line held."""
        if not self.pump(connect_timeout, until=lambda: self.link.state == LinkState.UP):
            self.say(f"FAIL: no answer from the module within {connect_timeout:g} s "
                     "(is the daemon running on the other end, at the same baud rate?)")
            return 1
        for number, line in lines:
            verb, args, _ = parse_command(line)
            if not verb:
                continue
            if verb == "wait":
                self.pump(float(args[0]))
            elif verb == "expect":
                what, filters, timeout = _parse_expect(verb, args)
                if self.expect(what, filters, timeout) is None:
                    got = ", ".join(sorted({e.name for e in self.log[self.cursor:]})) or "nothing"
                    self.say(f"FAIL line {number}: `{line.strip()}` not met within {timeout:g} s "
                             f"(received since the last match: {got})")
                    return 1
                self.say(f"   line {number}: {line.strip()} -- ok")
            elif verb == "expect-none":
                what, filters, seconds = _parse_expect(verb, args)
                hit = self.expect_none(what, filters, seconds)
                if hit is not None:
                    self.say(f"FAIL line {number}: `{line.strip()}`: got {hit.name} "
                             f"after {hit.t - self.clock() + seconds:.2f} s")
                    return 1
                self.say(f"   line {number}: {line.strip()} -- ok")
            else:
                self.mark = len(self.log)
                if not self.command(line):
                    break
            self.pump(0.0)
        self.pump(1.0, until=lambda: self.link.in_flight == 0 and self.link.queued == 0)
        if self.failed:
            self.say(f"FAIL: {len(self.failed)} command(s) not delivered")
            return 1
        return 0

    def run_interactive(self, stdin: TextIO) -> int:
        """Read commands from ``stdin`` until EOF or `quit`, pumping the link meanwhile."""
        lines: queue.Queue[str | None] = queue.Queue()

        def reader() -> None:
            for text in stdin:
                lines.put(text)
            lines.put(None)

        threading.Thread(target=reader, name="base-sim-stdin", daemon=True).start()
        self.say("base-sim ready; type `help`")
        while True:
            self.pump(0.05)
            try:
                while True:
                    text = lines.get_nowait()
                    if text is None:
                        self.pump(0.5, until=lambda: (self.link.in_flight == 0
                                                      and self.link.queued == 0))
                        return 0
                    try:
                        if not self.command(text):
                            return 0
                    except InputError as exc:
                        self.say(f"error: {exc}")
            except queue.Empty:
                pass


def check_script(path: str | Path) -> list[tuple[int, str]]:
    """Read and check a whole script before running it: (line number, text) of each command."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read the script {path}: {exc.strerror or exc}") from None
    lines = []
    for number, line in enumerate(text.splitlines(), 1):
        try:
            verb, _, _ = parse_command(line)
        except InputError as exc:
            raise InputError(f"{path}:{number}: {exc}") from None
        if verb:
            lines.append((number, line))
    return lines


def run_base_sim(port_url: Any, script_path: str | Path | None = None, *, baudrate: int = 115200,
                 verbose: bool = False, stdin: TextIO | None = None, out: TextIO | None = None,
                 connect_timeout: float = 5.0, proto_max: int = VERSION) -> int:
    """``robot-change base-sim``: exit status 0 (ok) or 1 (an expectation or a command failed).

    ``port_url`` is a port URL/path (opened with hw.serial_port.open_port) or an open port.
    Raises InputError for a bad script (before opening the port) and hw PortError/UriError when
    the port cannot be opened.
    """
    lines = check_script(script_path) if script_path is not None else None
    if isinstance(port_url, str) and port_url.strip().lower().startswith("loop://"):
        raise InputError("--port loop:// would send the base's own frames back to it (a HELLO "
                         "with the base's role, refused as WRONG_DIRECTION): give the port the "
                         "module is on, e.g. /dev/ttyUSB0 or socket://HOST:PORT, or test both "
                         "ends together with `robot-change link-bench`")
    port, owned = port_url, False
    if isinstance(port_url, str):
        port, owned = open_port(port_url, baudrate=baudrate, timeout=0.01), True
    try:
        sim = BaseSim(port, out=out, verbose=verbose, baudrate=baudrate, proto_max=proto_max)
        if lines is not None:
            return sim.run_script(lines, connect_timeout)
        return sim.run_interactive(stdin or sys.stdin)
    finally:
        if owned:
            port.close()


__all__ = ["BaseSim", "BaseState", "check_script", "parse_command", "run_base_sim"]
