"""The live-view server: one page, a JSON state, server-sent events, three buttons.

aiohttp (a maintained asyncio HTTP server; the page needs long-lived event streams, which a
thread-per-request server handles poorly) runs in a background thread with its own event loop.
Security: bound to 127.0.0.1 unless told otherwise; a random token is printed with the URL and
required by every API call (``X-Token`` header; the event stream, which browsers cannot give
headers, takes it as ``?token=``); state changes only on POST; every asset is served by the
package (no CDN: the lab PC may be offline).

Events are pushed, not polled by the page: the runner's observer (in the running process) and a
watcher of the journal's row counts (for ``setmem-hil view`` of another process's run) wake the
streams; the page then fetches ``/api/state`` once.
"""

from __future__ import annotations

import asyncio
import json
import secrets
import threading
import time
from importlib.resources import files
from pathlib import Path
from typing import Any

from setmem_hil.errors import SetmemError
from setmem_hil.io.atomic_file import json_safe
from setmem_hil.live.control import LiveControl
from setmem_hil.live.state import journal_state

__all__ = ["LiveServer"]

WATCH_PERIOD_S = 0.3


class LiveServer:
    """Serve the live view of the run in ``run_dir`` (``control`` None: read-only viewer)."""

    def __init__(self, run_dir: str | Path, control: LiveControl | None = None, host: str = "127.0.0.1", port: int = 0):
        self.run_dir = Path(run_dir)
        self.control = control
        self.host, self.port = host, int(port)
        self.token = secrets.token_urlsafe(18)
        self._dwell: dict | None = None
        self._started = time.monotonic()
        self._version = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._changed: asyncio.Condition | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._error: BaseException | None = None

    # -- lifecycle -----------------------------------------------------------------------
    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/?token={self.token}"

    def start(self) -> "LiveServer":
        self._thread = threading.Thread(target=self._serve, name="live-view", daemon=True)
        self._thread.start()
        self._ready.wait(10.0)
        if self._error is not None:
            raise self._error
        return self

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def __enter__(self) -> "LiveServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- the runner's observer -----------------------------------------------------------
    def observe(self, event: str, **info: Any) -> None:
        """Subscriber of the campaign runner: remembers the current dwell and wakes the pages."""
        if event == "measure":
            self._dwell = {"index": info.get("index"), "total": info.get("total"), "omega_rad_s": info.get("omega_rad_s"),
                           "replayed": bool(info.get("replayed")), "started_s": time.monotonic() - self._started}
        elif event == "finished":
            self._dwell = None
        self.notify()

    def notify(self) -> None:
        if self._loop is not None and self._changed is not None:
            self._loop.call_soon_threadsafe(lambda: asyncio.ensure_future(self._bump()))

    async def _bump(self) -> None:
        async with self._changed:
            self._version += 1
            self._changed.notify_all()

    # -- server --------------------------------------------------------------------------
    def _serve(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._error = exc
            self._ready.set()

    async def _main(self) -> None:
        from aiohttp import web

        self._loop = asyncio.get_running_loop()
        self._changed = asyncio.Condition()
        self._stop = asyncio.Event()
        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_get("/api/state", self._state)
        app.router.add_get("/api/events", self._events)
        for action in ("pause", "resume", "abort"):
            app.router.add_post(f"/api/{action}", self._action(action))
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, self.host, self.port)
        await site.start()
        self.port = site._server.sockets[0].getsockname()[1]
        self._ready.set()
        watcher = asyncio.ensure_future(self._watch_journal())
        try:
            await self._stop.wait()
        finally:
            watcher.cancel()
            await runner.cleanup()

    async def _watch_journal(self) -> None:
        """Wake the pages when the journal changes (a run in another process, or a finish)."""
        last = None
        while True:
            await asyncio.sleep(WATCH_PERIOD_S)
            try:
                stat = (self.run_dir / "journal.sqlite-wal").stat() if (self.run_dir / "journal.sqlite-wal").exists() else (self.run_dir / "journal.sqlite").stat()
                sig = (stat.st_mtime_ns, stat.st_size)
            except OSError:
                continue
            if sig != last:
                last = sig
                await self._bump()

    def _authorised(self, request, allow_query: bool = False) -> bool:
        given = request.headers.get("X-Token") or (request.query.get("token") if allow_query else None)
        return given is not None and secrets.compare_digest(given, self.token)

    def _live(self) -> dict:
        live: dict[str, Any] = {"dwell": self._dwell}
        if self.control is not None:
            live["status"] = self.control.status
        return live

    async def _index(self, request):
        from aiohttp import web

        page = files("setmem_hil.live").joinpath("static/index.html").read_text(encoding="utf-8")
        return web.Response(text=page, content_type="text/html", headers={"Cache-Control": "no-store"})

    async def _state(self, request):
        from aiohttp import web

        if not self._authorised(request):
            return web.json_response({"error": "missing or wrong X-Token"}, status=401)
        try:
            state = await asyncio.get_running_loop().run_in_executor(None, journal_state, self.run_dir, self._live())
        except SetmemError:  # the journal is not created yet (the rig is being opened)
            state = {"status": "starting", "iteration": 0, "n_points": 0, "mu_peak": None, "rig_s": None, "dwell": None,
                     "measurements": [], "iterations": [], "model_band": {}, "events": [], "procedure": None, "backend": None}
        # the run's own elapsed time (a viewer of a finished run is not the run); the server's
        # uptime only before the journal exists
        run_elapsed = state.get("run_elapsed_s")
        state["elapsed_s"] = run_elapsed if run_elapsed is not None else time.monotonic() - self._started
        state["read_only"] = self.control is None
        return web.Response(text=json.dumps(json_safe(state)), content_type="application/json",
                            headers={"Cache-Control": "no-store"})

    async def _events(self, request):
        from aiohttp import web

        if not self._authorised(request, allow_query=True):
            return web.json_response({"error": "missing or wrong token"}, status=401)
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-store"})
        await response.prepare(request)
        seen = -1
        try:
            while not self._stop.is_set():
                async with self._changed:
                    if self._version == seen:
                        try:
                            await asyncio.wait_for(self._changed.wait(), timeout=15.0)
                        except asyncio.TimeoutError:
                            await response.write(b": keep-alive\n\n")
                            continue
                    seen = self._version
                await response.write(f"data: {seen}\n\n".encode())
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        return response

    def _action(self, action: str):
        from aiohttp import web

        async def handler(request):
            if not self._authorised(request):
                return web.json_response({"error": "missing or wrong X-Token"}, status=401)
            if self.control is None:
                return web.json_response({"error": "read-only view: the run is controlled by its own process"}, status=409)
            getattr(self.control, action)()
            await self._bump()
            return web.json_response({"status": self.control.status})

        return handler
