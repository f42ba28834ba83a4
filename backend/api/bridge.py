"""The HTTP server on its own thread and event loop, in front of the service's loop.

Under overload the service's event loop is busy with ingest and the front end for
hundreds of milliseconds at a stretch (measured: loop lag p99 0.36-0.56 s with 100
sensors x 300 Hz offered), and a request served on that loop waits behind it. So uvicorn
(sockets, HTTP parsing, responses) runs on a loop of its own in a thread, and
``LoopBridge`` decides per request where the app runs:

- paths in ``local`` (``/status``, ``/healthz``) run on the HTTP loop; their handlers
  only read what the service publishes for other threads (``Service.status_view``:
  a fresh status from the service loop when it answers within a deadline, else the
  last published snapshot, an immutable dict);
- every other request runs on the service's loop, as before the split: the app is
  called there with ``receive``/``send`` that hop back to the HTTP loop. Handlers keep
  their single-threaded view of the service.

Nothing is locked across an await: the two loops only exchange futures
(``asyncio.run_coroutine_threadsafe``) and whole immutable objects.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any, Awaitable, Callable

Scope = dict[str, Any]
Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]


class LoopBridge:
    """ASGI app for the HTTP thread: runs ``app`` on the service ``loop``, or locally for ``local`` paths."""

    def __init__(self, app: Any, loop: asyncio.AbstractEventLoop, local: frozenset[str]):
        self.app, self.loop, self.local = app, loop, local

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope.get("path") in self.local:
            return await self.app(scope, receive, send)
        here = asyncio.get_running_loop()

        async def receive_there() -> dict[str, Any]:  # on the service loop
            return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(receive(), here))

        async def send_there(message: dict[str, Any]) -> None:  # on the service loop
            await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(send(message), here))

        try:
            fut = asyncio.run_coroutine_threadsafe(self.app(scope, receive_there, send_there), self.loop)
        except RuntimeError:  # the service loop is gone: the service is stopping
            if scope["type"] == "http":
                await _unavailable(send)
            return
        try:
            await asyncio.wrap_future(fut)
        except asyncio.CancelledError:  # the server shuts down or the client left
            fut.cancel()
            raise


async def _unavailable(send: Send) -> None:
    body = b'{"detail": "the service is shutting down"}'
    await send({"type": "http.response.start", "status": 503,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


class ServerThread:
    """Runs ``server.serve(sockets=[sock])`` (a uvicorn.Server) on a new loop in a thread.

    ``await run()`` from the service loop returns when the server has stopped (set
    ``should_exit``) and raises what stopped it otherwise.
    """

    def __init__(self, server: Any, sock: Any):
        self._server, self._sock = server, sock

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        done: asyncio.Future = loop.create_future()

        def finish(error: BaseException | None) -> None:
            if done.done():
                return
            if error is None:
                done.set_result(None)
            else:
                done.set_exception(error)

        def main() -> None:
            error: BaseException | None = None
            try:
                asyncio.run(self._server.serve(sockets=[self._sock]))
            except BaseException as e:  # handed to the service loop
                error = e
            try:
                loop.call_soon_threadsafe(finish, error)
            except RuntimeError:  # the service loop is closed already
                pass

        thread = threading.Thread(target=main, name="extrcal-http", daemon=True)
        thread.start()
        try:
            await asyncio.shield(done)
        except asyncio.CancelledError:
            self._server.should_exit = True
            await asyncio.to_thread(thread.join, 10)
            raise
