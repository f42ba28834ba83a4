"""Running the service: its HTTP listening socket, the uvicorn server on a thread of its
own (backend/api/bridge.py), ``serve`` until SIGTERM/SIGINT, and ``ServiceThread``, the
whole service in a background thread for tests, benchmarks and tools."""

from __future__ import annotations

import asyncio
import contextlib
import socket
from typing import Any, Callable

from .service import Service
from .settings import ServiceSettings

SWITCH_INTERVAL = 0.001  # s: how soon a thread waiting for the GIL gets it (the HTTP thread)


def bind_socket(host: str, port: int) -> socket.socket:
    """The HTTP listening socket, bound before anything else starts: a clear error if taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # IPPROTO_TCP, not 0: asyncio sets TCP_NODELAY only on sockets that say they are TCP,
    # and without it every response (headers, then body) waits ~40 ms for a delayed ACK
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise OSError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
    sock.listen(128)
    sock.setblocking(False)
    return sock


def make_server(app: Any, sock: socket.socket, *, log_level: str = "warning") -> Any:
    """A uvicorn server on a bound socket that leaves signals to the service."""
    import uvicorn

    class _Server(uvicorn.Server):
        @contextlib.contextmanager
        def capture_signals(self):  # the service handles SIGTERM/SIGINT itself
            yield

    host, port = sock.getsockname()[:2]
    config = uvicorn.Config(app, host=host, port=port, log_level=log_level, lifespan="off",
                            timeout_graceful_shutdown=3, access_log=False)
    server = _Server(config)
    return server


async def serve(settings: ServiceSettings, *, install_signals: bool = True,
                on_started: Callable[[Service], None] | None = None, log_level: str = "warning",
                service: Service | None = None) -> Service:
    """Run the whole service (Zenoh, pipeline, REST) until SIGTERM/SIGINT or request_stop()."""
    from .api import create_app

    import sys

    from .api.bridge import LoopBridge

    # The HTTP thread waits for the GIL each time it wakes up; the loop thread is CPU-bound
    # under overload and gives the GIL up every switch interval (5 ms by default).
    sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL))
    service = service or Service(settings)
    sock = bind_socket(settings.http.host, settings.http.port)
    service.http_address = sock.getsockname()[:2]
    app = create_app(settings, service)
    # the HTTP server runs on a thread of its own: see backend/api/bridge.py
    bridged = LoopBridge(app, asyncio.get_running_loop(), HTTP_LOCAL_PATHS)
    server = make_server(bridged, sock, log_level=log_level)

    server_proxy = _ServerWithSocket(server, sock)
    if on_started is not None:
        async def notify() -> None:
            await service.started.wait()
            on_started(service)
        waiter = asyncio.ensure_future(notify())
    try:
        await service.run(server_proxy, install_signals=install_signals)
    finally:
        if on_started is not None:
            waiter.cancel()
        sock.close()
    return service


HTTP_LOCAL_PATHS = frozenset({"/status", "/healthz"})  # answered on the HTTP thread (Service.status_view)


class _ServerWithSocket:
    """uvicorn.Server serving a socket we bound, on its own thread, as the service's ``server``."""

    def __init__(self, server: Any, sock: socket.socket):
        self._server, self._sock = server, sock

    async def serve(self) -> None:
        from .api.bridge import ServerThread

        await ServerThread(self._server, self._sock).run()

    @property
    def started(self) -> bool:
        return self._server.started

    @property
    def should_exit(self) -> bool:
        return self._server.should_exit

    @should_exit.setter
    def should_exit(self, value: bool) -> None:
        self._server.should_exit = value


class ServiceThread:
    """The whole service on its own event loop in a background thread.

    For tests, benchmarks and tools that drive the service from synchronous code::

        with ServiceThread(settings) as st:
            httpx.get(st.url + "/status")

    ``start`` returns once the service is ``started`` (Zenoh declared, HTTP listening).
    """

    def __init__(self, settings: ServiceSettings, *, timeout: float = 60.0):
        import threading

        self.settings = settings
        self.timeout = timeout
        self.service: Service | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.error: BaseException | None = None
        self._started = threading.Event()
        self._thread = threading.Thread(target=self._main, name="extrcal-service", daemon=True)

    def _main(self) -> None:
        async def main() -> None:
            self.loop = asyncio.get_running_loop()
            self.service = Service(self.settings)
            await serve(self.settings, service=self.service, install_signals=False,
                        on_started=lambda _: self._started.set())

        try:
            asyncio.run(main())
        except BaseException as e:  # handed to the caller by start()/stop()
            self.error = e
        finally:
            self._started.set()

    def start(self) -> "ServiceThread":
        self._thread.start()
        if not self._started.wait(self.timeout):
            raise TimeoutError(f"the service did not start within {self.timeout} s")
        if self.error is not None:
            raise RuntimeError(f"the service failed to start: {self.error!r}") from self.error
        return self

    @property
    def url(self) -> str:
        assert self.service is not None and self.service.http_address is not None
        host, port = self.service.http_address
        return f"http://{'[' + host + ']' if ':' in host else host}:{port}"

    def call(self, fn: Callable[[], Any], timeout: float = 30.0) -> Any:
        """Run ``fn`` on the service's loop and return its result (a coroutine is awaited)."""
        import concurrent.futures

        assert self.loop is not None

        async def wrap() -> Any:
            r = fn()
            if asyncio.iscoroutine(r):
                r = await r
            return r

        fut: concurrent.futures.Future = asyncio.run_coroutine_threadsafe(wrap(), self.loop)
        return fut.result(timeout)

    def stop(self, timeout: float = 60.0) -> None:
        if self.loop is not None and self._thread.is_alive():
            with contextlib.suppress(RuntimeError):
                self.loop.call_soon_threadsafe(self.service.request_stop)
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise TimeoutError(f"the service did not stop within {timeout} s")
        if self.error is not None:
            raise RuntimeError(f"the service failed: {self.error!r}") from self.error

    def __enter__(self) -> "ServiceThread":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
