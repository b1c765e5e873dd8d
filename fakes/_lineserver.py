"""A small threaded TCP server for CR LF line protocols (the tracker and CMM fakes).

One thread accepts; each client gets its own thread that reads lines and hands them to the
fake's ``handle_line(client, line)``. Clients may come and go, one after the other or at the
same time. ``stop()`` closes everything and joins the threads.
"""

from __future__ import annotations

import logging
import socket
import threading

from calibration.errors import RecalError

log = logging.getLogger(__name__)


class DropConnection(RecalError):
    """Raised by a handler to close the client's connection without replying."""


class Client:
    """One connected client: send lines to it, or drop it."""

    def __init__(self, sock: socket.socket, address):
        self.sock = sock
        self.address = address
        self.state: dict = {}  # per-connection protocol state, owned by the fake
        self._send_lock = threading.Lock()
        self.closed = False

    def send_line(self, text: str) -> None:
        """Send ``text`` + CR LF (latin-1, so garbled bytes pass through)."""
        self.send_raw(text.encode("latin-1") + b"\r\n")

    def send_raw(self, data: bytes) -> None:
        with self._send_lock:
            if self.closed:
                return
            try:
                self.sock.sendall(data)
            except OSError:
                self.closed = True

    def close(self) -> None:
        with self._send_lock:
            self.closed = True
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class LineServer:
    """Base of a fake device on TCP. Subclasses implement ``handle_line`` (and may override
    ``on_connect`` / ``on_disconnect``)."""

    device_name = "device"

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *, max_line: int = 4096):
        self.host = host
        self.port = int(port)
        self.max_line = max_line
        self._server: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self._clients: set[Client] = set()
        self._lock = threading.Lock()
        self._stopping = threading.Event()

    # ----------------------------------------------------------------- lifecycle

    def start(self) -> None:
        """Bind and start accepting; when this returns the port accepts connections."""
        if self._server is not None:
            return
        self._stopping.clear()
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind((self.host, self.port))
        srv.listen(8)
        srv.settimeout(0.2)
        self._server = srv
        self.port = srv.getsockname()[1]
        t = threading.Thread(target=self._accept_loop, name=f"{self.device_name}-accept", daemon=True)
        t.start()
        self._threads.append(t)
        log.info("%s fake listening on %s:%d", self.device_name, self.host, self.port)

    def stop(self) -> None:
        """Close the listening socket and every client; join the threads. Idempotent."""
        self._stopping.set()
        srv, self._server = self._server, None
        if srv is not None:
            try:
                srv.shutdown(socket.SHUT_RDWR)  # wakes a blocked accept() on Linux
            except OSError:
                pass
            srv.close()
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            c.close()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        self._threads = [t for t in self._threads if t.is_alive()]

    def clients(self) -> list[Client]:
        with self._lock:
            return [c for c in self._clients if not c.closed]

    # ----------------------------------------------------------------- hooks

    def on_connect(self, client: Client) -> None:
        """A client connected (override to greet it or set up state)."""

    def on_disconnect(self, client: Client) -> None:
        """A client went away."""

    def handle_line(self, client: Client, line: str) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    # ----------------------------------------------------------------- threads

    def _accept_loop(self) -> None:
        while not self._stopping.is_set():
            srv = self._server
            if srv is None:
                return
            try:
                sock, address = srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = Client(sock, address)
            with self._lock:
                self._clients.add(client)
            t = threading.Thread(
                target=self._client_loop, args=(client,), name=f"{self.device_name}-client", daemon=True
            )
            t.start()
            self._threads = [x for x in self._threads if x.is_alive()] + [t]

    def _client_loop(self, client: Client) -> None:
        buffer = bytearray()
        client.sock.settimeout(0.2)
        try:
            self.on_connect(client)
            while not self._stopping.is_set() and not client.closed:
                try:
                    chunk = client.sock.recv(4096)
                except TimeoutError:
                    continue
                except OSError:
                    break
                if not chunk:
                    break
                buffer += chunk
                while b"\n" in buffer:
                    raw, _, rest = bytes(buffer).partition(b"\n")
                    buffer = bytearray(rest)
                    line = raw.rstrip(b"\r").decode("latin-1")
                    try:
                        self.handle_line(client, line)
                    except DropConnection:
                        log.info("%s fake: dropping the connection (injected fault)", self.device_name)
                        client.close()
                        break
                if len(buffer) > self.max_line:
                    buffer.clear()
        except Exception:  # a fake must not die silently in a thread
            log.exception("%s fake: client handler failed", self.device_name)
        finally:
            client.close()
            with self._lock:
                self._clients.discard(client)
            try:
                self.on_disconnect(client)
            except Exception:  # a fake must not die silently in a thread
                log.exception("%s fake: on_disconnect failed", self.device_name)


def garble(line: str) -> str:
    """A corrupted copy of ``line`` as a noisy serial link or a broken device might send it:
    the middle of it is replaced by non-printable bytes."""
    mid = len(line) // 2
    return line[:mid] + "\x15\x7f?" + line[mid + 2 :]
