"""Transports on pymavlink's standard connection strings, made safe for a fixed-rate sender thread.

pymavlink's ``mavutil`` opens the sockets/ports; this layer parses the string first (clear errors instead of a
ValueError deep in mavutil), never blocks the sender (TCP reconnects happen on a helper thread), and reports
whether the link is up. Supported: ``udpout:HOST:PORT``, ``udpin:HOST:PORT`` (replies to whoever sent last),
``udp:HOST:PORT`` (= udpin), ``tcp:HOST:PORT`` (client, reconnects), ``tcpin:HOST:PORT`` (server),
serial ``/dev/ttyACM0[,BAUD]``, ``COM3[,BAUD]`` or ``serial:DEVICE[:BAUD]``.
"""

from __future__ import annotations

import re
import socket
import threading
import time
from dataclasses import dataclass

from aerial_loc_env.errors import AerialLocError, ConfigError, MissingExtraError

NET_KINDS = ("udpout", "udpin", "udp", "tcp", "tcpin")
EXAMPLES = ("udpout:127.0.0.1:14550, udpin:0.0.0.0:14550, tcp:127.0.0.1:5760, tcpin:0.0.0.0:5760, "
            "/dev/ttyACM0,921600")


class LinkError(AerialLocError, OSError):
    """The link cannot be opened at all (address in use, no such serial device)."""


@dataclass(frozen=True)
class Endpoint:
    kind: str          # one of NET_KINDS or "serial"
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 57600

    @property
    def mavutil_device(self) -> str:
        return self.device if self.kind == "serial" else f"{self.kind}:{self.host}:{self.port}"

    @property
    def is_server(self) -> bool:
        return self.kind in ("udpin", "udp", "tcpin")


def parse_connection(text: str, *, baud: int = 57600, field: str = "connect") -> Endpoint:
    """Parse a pymavlink connection string or raise ConfigError naming the field, the problem and examples."""
    def bad(problem: str) -> ConfigError:
        return ConfigError(f"{field} = {text!r}: {problem}; examples: {EXAMPLES}")

    if not isinstance(text, str) or not text.strip():
        raise bad("empty connection string")
    text = text.strip()
    scheme, sep, rest = text.partition(":")
    if sep and scheme in NET_KINDS:
        host, sep2, port_s = rest.rpartition(":")
        if not sep2 or not host:
            raise bad(f"expected {scheme}:HOST:PORT")
        if not port_s.isdigit() or not 1 <= int(port_s) <= 65535:
            raise bad(f"port {port_s!r} must be an integer in 1..65535")
        return Endpoint(scheme, host=host, port=int(port_s), baud=baud)
    if scheme == "serial" and sep:
        device, _, baud_s = rest.partition(":")
        return _serial(device, baud_s, baud, bad)
    if text.startswith("/dev/") or re.fullmatch(r"COM\d+(,\d+)?", text, flags=re.IGNORECASE):
        device, _, baud_s = text.partition(",")
        return _serial(device, baud_s, baud, bad)
    raise bad(f"unknown scheme {scheme!r}; use one of {', '.join(NET_KINDS)}, a serial device "
              "or serial:DEVICE:BAUD")


def _serial(device: str, baud_s: str, baud: int, bad) -> Endpoint:
    if not device:
        raise bad("missing serial device")
    if baud_s:
        if not baud_s.isdigit() or int(baud_s) <= 0:
            raise bad(f"baud rate {baud_s!r} must be a positive integer")
        baud = int(baud_s)
    return Endpoint("serial", device=device, baud=baud)


class Link:
    """One MAVLink transport: write frames, read bytes, know if it is up, reconnect TCP in the background."""

    def __init__(self, endpoint: Endpoint, *, reconnect_s: float = 1.0) -> None:
        self.endpoint = endpoint
        self.reconnect_s = reconnect_s
        self._conn = None
        self._lock = threading.Lock()
        self._connector: threading.Thread | None = None
        self._last_attempt_s = -float("inf")
        self.reconnects = 0
        self.last_error: str | None = None
        self._closed = False

    # -- opening ---------------------------------------------------------------------------------------------
    def open(self) -> None:
        """Open the link. Fatal problems (unresolvable host, port in use, no serial device) raise LinkError;
        a TCP server that is not up yet is not fatal: the link retries every ``reconnect_s``."""
        ep = self.endpoint
        if ep.kind != "serial":
            try:
                socket.getaddrinfo(ep.host, ep.port)
            except OSError as exc:
                raise LinkError(f"connect: cannot resolve host {ep.host!r} of {ep.mavutil_device!r}: "
                                f"{exc}") from exc
        if ep.kind == "tcp":
            self._try_connect()
            return
        if ep.kind == "serial":
            try:
                import serial  # noqa: F401  (pymavlink opens serial ports through pyserial)
            except ImportError as exc:
                raise MissingExtraError(
                    f"connect: serial device {ep.device!r} needs the optional package 'pyserial', which is not "
                    "installed. Install it with: pip install 'aerial-loc-env[mavlink]'") from exc
        try:
            self._conn = self._mavutil_open()
        except (OSError, ValueError) as exc:
            raise LinkError(f"connect: cannot open {ep.mavutil_device!r}: {exc}") from exc
        except Exception as exc:  # pyserial raises its own SerialException
            raise LinkError(f"connect: cannot open {ep.mavutil_device!r}: {exc}") from exc

    def _mavutil_open(self):
        from pymavlink import mavutil

        ep = self.endpoint
        if ep.kind == "serial":
            return mavutil.mavlink_connection(ep.device, baud=ep.baud, autoreconnect=True)
        # retries=0: one attempt, no sleeping or printing inside mavutil; we retry ourselves.
        return mavutil.mavlink_connection(ep.mavutil_device, retries=0, autoreconnect=False)

    def _try_connect(self) -> None:
        self._last_attempt_s = time.monotonic()
        try:
            conn = self._mavutil_open()
        except OSError as exc:
            self.last_error = f"{self.endpoint.mavutil_device}: {exc}"
            return
        with self._lock:
            if self._closed:
                conn.close()
                return
            self._conn = conn
            self.reconnects += 1
            self.last_error = None

    def _maybe_reconnect(self) -> None:
        """Start a background connect attempt if the TCP link is down and the retry interval has passed."""
        if self.endpoint.kind != "tcp" or self._closed:
            return
        if self._connector is not None and self._connector.is_alive():
            return
        if time.monotonic() - self._last_attempt_s < self.reconnect_s:
            return
        self._connector = threading.Thread(target=self._try_connect, name="mavlink-tcp-connect", daemon=True)
        self._connector.start()

    @property
    def up(self) -> bool:
        """Whether frames can be handed to the OS now (a UDP link is always up: UDP has no connection)."""
        return self._conn is not None

    def _drop(self, why: str) -> None:
        with self._lock:
            conn, self._conn = self._conn, None
        self.last_error = why
        if conn is not None:
            try:
                conn.close()
            except OSError:
                pass

    # -- I/O -------------------------------------------------------------------------------------------------
    def write(self, buf: bytes) -> bool:
        """Send one frame; False when it could not be handed over (link down, peer gone, buffer full)."""
        conn = self._conn
        if conn is None:
            self._maybe_reconnect()
            return False
        if self.endpoint.kind == "tcp":
            try:
                conn.port.sendall(buf)
            except BlockingIOError:
                return False
            except OSError as exc:
                self._drop(f"tcp peer gone: {exc}")
                return False
            return True
        if self.endpoint.kind in ("udpin", "udp") and not conn.clients:
            return False  # nobody has talked to us yet: nowhere to send
        if self.endpoint.kind == "tcpin" and conn.port is None:
            return False
        conn.write(buf)
        return True

    def read(self, max_bytes: int = 65536) -> bytes:
        """Whatever bytes arrived (non-blocking); b'' if none."""
        conn = self._conn
        if conn is None:
            return b""
        try:
            if self.endpoint.kind == "tcp":
                data = conn.port.recv(max_bytes)
                if not data:
                    self._drop("tcp peer closed the connection")
                return data
            data = conn.recv(max_bytes)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if self.endpoint.kind == "tcp":
                self._drop(f"tcp peer gone: {exc}")
            return b""
        return data.encode("latin-1") if isinstance(data, str) else bytes(data or b"")

    def close(self) -> None:
        self._closed = True
        self._drop("closed")
