"""Serial links through pyserial's ``serial_for_url``.

Device paths (``/dev/ttyUSB0``, ``/dev/pts/3``, ``COM3``) and pyserial's own
URLs (``socket://host:port``, ``rfc2217://host:port``, ``loop://``,
``spy://...``) all open here. RS232 defaults to 115200 baud 8N1 (guide 2.2.6:
"1 start bit, 8 data bits, no parity, 1 stop bit"); pass ``baudrate=`` to
change it. URL handlers that take options in the query (``rfc2217://``,
``spy://``) keep pyserial's syntax.

Reading: the transport contract is "return as soon as any byte is there, or
b'' after the timeout". When the client knows that a frame still needs N bytes
(:meth:`SerialTransport.read_some`), a POSIX port lets the kernel wait for
them: the terminal's VMIN is set to N (VTIME 0), and in that mode the line
discipline reports the port readable only once N bytes are in (Linux n_tty:
``input_available_p``; POSIX "MIN > 0, TIME = 0"). So an answer wakes the
reader once, when its last byte arrives, instead of once per byte (at 115200
baud a byte takes 87 us; each wake-up costs CPU, and in the bridge it also
costs a hand-over of Python's interpreter lock, on the path between one
answer and the next request). The client asks for no more than the answer's
size where the guide fixes it, less its last two bytes (a thread that slept
through the whole exchange wakes up slower: ``epos_link.link.WAKE_EARLY``),
and no more than the frame being received still needs
(:attr:`FrameDecoder.wanted`); at the deadline whatever has arrived is
returned, so a short or broken answer is seen as before. An answer that comes
in one piece (a USB adapter's packet) is read by one wake-up, and VMIN stays
put from one status poll to the next. Where
VMIN cannot be set (not a terminal), the reader sleeps for the wire time of
the bytes still due instead. pyserial's ``read(n)`` waits for all ``n`` bytes,
so three readers exist, picked by the port's exact class:

* a POSIX port (``serial.Serial``): ``select`` on its file descriptor, then one
  ``os.read`` of whatever is there. A termios call only when the number of
  bytes waited for changes.
* ``socket://``: ``select`` and one ``recv``; pyserial's ``in_waiting`` on a
  socket says only 0 or 1, which would cost a system call per byte.
* anything else (``spy://`` logs inside ``read``, ``loop://``, ``rfc2217://``,
  Windows): the port's own ``read(1)`` with a timeout, then ``in_waiting``
  more bytes. Timeouts are set from a short ladder of values, because setting
  ``Serial.timeout`` reconfigures the port.
"""
from __future__ import annotations

import errno
import os
import re
import select
import struct
import time
import urllib.parse
from typing import Any, Callable, Optional

import serial

from ..errors import TransportError
from .base import Transport

if os.name == "posix":
    import fcntl
    import termios

    _TERMIOS_ERROR: type[BaseException] = termios.error
else:
    _TERMIOS_ERROR = OSError

BITS_PER_BYTE = 10  # 8N1 (guide 2.2.6)
DEFAULT_BAUDRATE = 115200  # guide 2.3.2 / factory setting of the EPOS4 RS232 interface
WRITE_TIMEOUT = 2.0  # a stuck link must not block a write forever
_RETRY_ERRNOS = (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR)
# Open: EBUSY from a port another program opened exclusively (TIOCEXCL);
# EAGAIN/EWOULDBLOCK from pyserial's flock when another program holds the lock.
_BUSY_ERRNOS = (errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK)
# Read timeouts used by the generic reader, largest first: the port keeps one
# of a few values, and the loop in _read_generic makes up the rest.
_LADDER = (0.1, 0.02, 0.005, 0.001, 0.0)
# A TCP server of one link (epos-link sim --tcp, a serial-to-TCP converter)
# serves one host at a time and closes any other: say so where it shows.
_ONE_HOST = " (is another program connected to it? it serves one host at a time)"


def _os_reason(exc: BaseException) -> str:
    """Why an open failed, in the operating system's words, without the port's name.

    pyserial words it as "could not open port X: [Errno 2] ...: 'X'", so
    quoting it after our own "cannot open X:" would name the port three times.
    """
    for cause in (exc, exc.__cause__, exc.__context__):
        code = getattr(cause, "errno", None)
        if isinstance(code, int) and code > 0:
            return os.strerror(code)
    return str(exc)


def _open_hint(url: str, exc: BaseException) -> str:
    text = str(exc)
    code = getattr(exc, "errno", None)
    if isinstance(exc, OSError) and code == errno.EACCES or "Permission denied" in text:
        return (f"cannot open {url}: permission denied. On Linux add your user to the group "
                f"that owns the port (usually 'dialout': sudo usermod -aG dialout $USER, "
                f"then log in again)")
    if code in _BUSY_ERRNOS:
        return (f"cannot open {url}: the port is busy: another program has it open "
                f"(tcp-bridge, another epos-link command, a terminal program); stop it first")
    return f"cannot open {url}: {_os_reason(exc)}{_socket_hint(url)}"


# HOST:PORT as a user types it for a TCP link: a name or IPv4 address, or [IPv6].
_HOST_PORT = re.compile(r"(?:\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.-]*):[0-9]{1,5}")


def _socket_hint(url: str) -> str:
    """`` (did you mean socket://HOST:PORT?)`` for a URL without a scheme that looks
    like HOST:PORT and is no file: without the scheme it is opened as a device path.
    Every epos-link command opens its URL here, so all of them give the hint."""
    if "://" in url or not _HOST_PORT.fullmatch(url) or os.path.exists(url):
        return ""
    return f" (did you mean socket://{url}?)"


def _url_problem(url: str) -> Optional[str]:
    """Why a network URL cannot name a port, said before pyserial would say it in its own
    words (``'<=' not supported between instances of 'int' and 'NoneType'`` for
    ``socket://localhost``); None if it can."""
    scheme = url.partition("://")[0].lower() if "://" in url else ""
    if scheme not in ("socket", "rfc2217"):
        return None
    parts = urllib.parse.urlsplit(url)
    try:
        port = parts.port
    except ValueError:  # not a number, or beyond 65535
        port = -1
    if not parts.hostname or port is None or not 0 < port < 65536:
        return (f"cannot open {url}: a {scheme}:// URL needs a host and a port 1..65535: "
                f"{scheme}://HOST:PORT, e.g. {scheme}://localhost:4001")
    return None


class SerialTransport(Transport):
    """A pyserial port behind the :class:`Transport` interface."""

    def __init__(self, url: str, *, baudrate: int = DEFAULT_BAUDRATE,
                 port_factory: Callable[..., Any] = serial.serial_for_url, **port_options: Any) -> None:
        self.url = url
        self.baudrate = baudrate
        self._factory = port_factory
        self._options = port_options
        self._port: Any = None
        self._read: Callable[[int, float], bytes] = self._read_generic
        self._sleep: Callable[[float], None] = time.sleep
        self._fd = -1
        self._sock: Any = None
        self._vmin = 1  # the terminal's VMIN as we last set it; 0: it cannot be set
        self.open()

    # --- life cycle -------------------------------------------------------

    def open(self) -> None:
        if self._port is not None:
            return
        problem = _url_problem(self.url)
        if problem is not None:
            raise TransportError(problem)
        options = dict(self._options)
        if os.name == "posix" and "://" not in self.url:
            # A device path is opened with pyserial's advisory lock (flock): a
            # second program on one EPOS4 link would mix its frames into ours
            # (the device serves one host, guide 2.3.2), so it is told "busy".
            options.setdefault("exclusive", True)
        try:
            port = self._factory(self.url, baudrate=self.baudrate, bytesize=8, parity="N",
                                 stopbits=1, timeout=0, write_timeout=WRITE_TIMEOUT, **options)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(_open_hint(self.url, exc)) from exc
        self._port = port
        cls = type(port)
        if os.name == "posix" and cls is serial.Serial and getattr(port, "fd", None) is not None:
            self._fd = port.fd
            self._read = self._read_fd
            self._vmin = 1 if _set_vmin(port.fd, 1) else 0  # pyserial leaves 0: polls like 1
        elif cls.__module__.endswith("protocol_socket") and getattr(port, "_socket", None):
            self._sock = port._socket
            self._read = self._read_socket
        else:
            self._read = self._read_generic

    def close(self) -> None:
        port, self._port = self._port, None
        sock, self._sock = self._sock, None
        self._fd = -1
        if sock is not None:
            # pyserial's socket handler sleeps 0.3 s in close() "for quick
            # reconnects"; every CLI call would pay it. Close the socket here
            # and mark the port closed so its close() has nothing left to do.
            try:
                sock.shutdown(2)  # SHUT_RDWR
            except OSError:
                pass
            sock.close()
            port._socket = None
            port.is_open = False
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass  # closing a vanished device: nothing left to release

    def reopen(self) -> None:
        self.close()
        self.open()

    # --- I/O --------------------------------------------------------------

    def _closed(self) -> TransportError:
        return TransportError(f"{self.url} is closed")

    def write(self, data: bytes) -> None:
        port = self._port
        if port is None:
            raise self._closed()
        if self._fd >= 0:
            self._write_fd(data)
            return
        try:
            port.write(data)
        except (serial.SerialException, OSError) as exc:
            raise TransportError(f"write to {self.url} failed: {exc}") from exc

    def read(self, max_bytes: int, timeout: float) -> bytes:
        if self._port is None:
            raise self._closed()
        if self._vmin > 1:
            self._wait_for(1)
        return self._read(max_bytes, timeout if timeout > 0 else 0.0)

    def read_some(self, max_bytes: int, timeout: float, wanted: int = 1) -> bytes:
        """:meth:`read`, but on a POSIX port wake up only once ``wanted`` bytes are
        in, or at the deadline with whatever came (module docstring)."""
        if self._vmin and self._fd >= 0:
            if self._port is None:
                raise self._closed()
            self._wait_for(wanted)
            return self._read_fd(max_bytes, timeout if timeout > 0 else 0.0)
        if wanted > 2 and self._fd >= 0 and timeout > 0:
            try:
                waiting = struct.unpack("i", fcntl.ioctl(self._fd, termios.FIONREAD,
                                                         b"\0\0\0\0"))[0]
            except OSError:
                waiting = 0  # the read below reports a vanished device
            on_wire = (wanted - waiting - 1) * BITS_PER_BYTE / self.baudrate
            if on_wire > 0:
                pause = min(on_wire, timeout)
                self._sleep(pause)
                timeout -= pause
        return self.read(max_bytes, timeout)

    def _wait_for(self, wanted: int) -> None:
        """Set the terminal's VMIN to ``wanted`` (at most 255, the field's range)."""
        vmin = max(1, min(wanted, 255))
        if vmin != self._vmin:
            self._vmin = vmin if _set_vmin(self._fd, vmin) else 0

    def reset_input(self) -> None:
        port = self._port
        if port is None:
            raise self._closed()
        try:
            if self._fd >= 0:
                termios.tcflush(self._fd, termios.TCIFLUSH)  # what pyserial does, directly
                return
            port.reset_input_buffer()
        except (serial.SerialException, OSError, _TERMIOS_ERROR) as exc:
            raise TransportError(f"flushing {self.url} failed: {exc}") from exc

    def _write_fd(self, data: bytes) -> None:
        """pyserial's write, without its select after a write that took everything
        (a system call per request, on the path from one answer to the next request)."""
        fd, view = self._fd, memoryview(data)
        deadline: Optional[float] = None
        try:
            while True:
                try:
                    view = view[os.write(fd, view):]
                except OSError as exc:
                    if exc.errno not in _RETRY_ERRNOS:
                        raise
                if not view:
                    return
                if deadline is None:
                    deadline = time.monotonic() + WRITE_TIMEOUT
                left = deadline - time.monotonic()
                if left <= 0 or not select.select((), (fd,), (), left)[1]:
                    raise TransportError(f"write to {self.url} failed: timed out after "
                                         f"{WRITE_TIMEOUT:g} s (the port takes no data)")
        except OSError as exc:
            raise TransportError(f"write to {self.url} failed: {exc}") from exc

    def _read_fd(self, max_bytes: int, timeout: float) -> bytes:
        fd = self._fd
        try:
            if not select.select((fd,), (), (), timeout)[0]:
                if self._vmin <= 1:
                    return b""
                # The deadline, with fewer than VMIN bytes in: hand over what came
                # (the fd is non-blocking: nothing there is EAGAIN, i.e. b"").
            data = os.read(fd, max_bytes)
        except OSError as exc:
            if exc.errno in _RETRY_ERRNOS:
                return b""
            raise TransportError(f"read from {self.url} failed: {exc}") from exc
        if not data:
            # select said readable and there is nothing: the device is gone
            # (pyserial reports the same case the same way).
            raise TransportError(f"{self.url}: readable but no data (device disconnected?)")
        return data

    def _read_socket(self, max_bytes: int, timeout: float) -> bytes:
        sock = self._sock
        try:
            if not select.select((sock,), (), (), timeout)[0]:
                return b""
            data: bytes = sock.recv(max_bytes)
        except OSError as exc:
            if exc.errno in _RETRY_ERRNOS:
                return b""
            if exc.errno == errno.ECONNRESET:
                raise TransportError(f"{self.url}: connection reset by the peer{_ONE_HOST}") from exc
            raise TransportError(f"read from {self.url} failed: {exc}") from exc
        if not data:
            raise TransportError(f"{self.url}: connection closed by the peer{_ONE_HOST}")
        return data

    def _read_generic(self, max_bytes: int, timeout: float) -> bytes:
        port = self._port
        deadline = time.monotonic() + timeout
        try:
            while True:
                waiting = port.in_waiting
                if waiting:
                    return bytes(port.read(min(waiting, max_bytes)))
                left = deadline - time.monotonic()
                step = next(s for s in _LADDER if s <= left) if left > 0 else 0.0
                if port.timeout != step:
                    port.timeout = step
                first = port.read(1)
                if first:
                    more = port.in_waiting if max_bytes > 1 else 0
                    return bytes(first) + bytes(port.read(min(more, max_bytes - 1))) if more else bytes(first)
                if step == 0.0:
                    return b""
        except (serial.SerialException, OSError) as exc:
            raise TransportError(f"read from {self.url} failed: {exc}") from exc


def _set_vmin(fd: int, vmin: int) -> bool:
    """VMIN = ``vmin``, VTIME = 0 on a terminal; False where that cannot be done."""
    if os.name != "posix":
        return False
    try:
        attrs = termios.tcgetattr(fd)
        cc = attrs[6]
        if cc[termios.VMIN] != vmin or cc[termios.VTIME] != 0:
            cc[termios.VMIN], cc[termios.VTIME] = vmin, 0
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except (_TERMIOS_ERROR, OSError):
        return False
    return True


def open_serial(url: str, *, baudrate: Optional[int] = None, **options: Any) -> SerialTransport:
    """Open ``url`` with ``serial.serial_for_url`` (115200 8N1 unless ``baudrate`` is given)."""
    if baudrate is not None and not 50 <= baudrate <= 12_000_000:
        raise TransportError(f"baud rate {baudrate} is outside 50..12000000")
    return SerialTransport(url, baudrate=baudrate or DEFAULT_BAUDRATE, **options)


__all__ = ["DEFAULT_BAUDRATE", "SerialTransport", "open_serial"]
