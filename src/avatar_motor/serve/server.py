"""`avatar-motor serve`: one process with the 30-fps world clock, a generation worker thread, a
WebSocket endpoint (/ws) and the web studio (/). Protocol: docs/protocol.md.

Robustness: every message is validated (errors are replied and logged, never raised into the
loop); each client has a two-frame send queue, so a slow client loses frames instead of stalling
the clock; clients come and go freely; any number of viewers share one world.
"""
from __future__ import annotations

import asyncio
import ipaddress
import json
import logging
import threading
import time
from pathlib import Path

from aiohttp import WSMsgType, web

from ..body.motion_state import FPS
from . import protocol as P
from .world import CommandError, World

log = logging.getLogger("avatar_motor.serve")
STATIC = Path(__file__).parent / "static"


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Client:
    def __init__(self, ws: web.WebSocketResponse, needs_token: bool):
        self.ws = ws
        self.format = "binary"
        self.authorized = not needs_token
        self.queue: asyncio.Queue = asyncio.Queue(maxsize=2)

    def offer(self, frames: dict[str, bytes | str]) -> None:
        """Queue the newest frame; a client that has not taken the last two loses the oldest."""
        if not self.authorized:
            return
        if self.queue.full():
            self.queue.get_nowait()
        self.queue.put_nowait(frames[self.format])


class Server:
    def __init__(self, world: World, host: str = "127.0.0.1", port: int = 8765, token: str | None = None):
        if not is_loopback(host) and not token:
            raise ValueError(f"serving on {host} exposes the server beyond this machine: pass --token SECRET "
                             "(clients then send it in their hello message or as ?token=)")
        self.world, self.host, self.port, self.token = world, host, port, token
        self.clients: set[Client] = set()
        self.running = False
        self.fps_measured = 0.0
        self.app = web.Application(middlewares=[self._same_site])
        self.app.add_routes([
            web.get("/", self.index), web.get("/ws", self.websocket), web.get("/api/info", self.info),
            web.get("/api/record", self.record), web.get("/api/events", self.events),
            web.static("/static", STATIC, show_index=False),
        ])
        self.app.on_startup.append(self._start_background)
        self.app.on_cleanup.append(self._stop_background)

    # ------------------------------------------------------------ http
    @web.middleware
    async def _same_site(self, request, handler):
        """No web page of another site drives this server: a request whose Origin is not the
        server's own (the studio's) or whose Host is not a name of this server (DNS rebinding) is
        refused unless it carries the token. Programs (engines, the Python client) send no
        Origin and pass."""
        if not (self.token and request.query.get("token") == self.token):
            host = request.host.rsplit(":", 1)[0].strip("[]") if request.host else ""
            if not (is_loopback(host) or host == self.host):
                log.warning("refused a request for foreign Host %r", request.host)
                raise web.HTTPForbidden(text=f"Host {request.host!r} is not this server; open it as http://127.0.0.1:{self.port}/")
            origin = request.headers.get("Origin")
            if origin is not None and origin not in (f"http://{request.host}", f"https://{request.host}"):
                log.warning("refused a request from foreign Origin %r", origin)
                raise web.HTTPForbidden(text=f"requests from {origin} are refused: only the studio's own page "
                                             "(or a client with the token) may drive this server")
        return await handler(request)

    async def index(self, request):
        page = STATIC / "index.html"
        if not (STATIC / "dist" / "studio.js").exists():
            return web.Response(status=503, text="The studio page is not built: run 'make web' (npm) first. "
                                                   "The WebSocket API at /ws works without it.")
        return web.FileResponse(page)

    async def info(self, request):
        return web.json_response({**self.world.stats(), "version": P.VERSION, "fps": FPS,
                                  "fps_measured": round(self.fps_measured, 1), "clients": len(self.clients)})

    def _check_token(self, request) -> None:
        if self.token and request.query.get("token") != self.token:
            raise web.HTTPUnauthorized(text="token required: add ?token=...")

    async def record(self, request):
        """The last N seconds of one avatar as a file: ?avatar=0&seconds=10&format=bvh|glb|npz."""
        self._check_token(request)
        import tempfile

        from ..io.export import write_motion
        try:
            i = int(request.query.get("avatar", "0"))
            seconds = float(request.query.get("seconds", "10"))
            fmt = request.query.get("format", "bvh")
            if fmt not in ("bvh", "glb", "npz") or not 0 < seconds <= 600:
                raise ValueError("format must be bvh, glb or npz and seconds in (0, 600]")
            X = self.world.recording(i, seconds)
            shape = self.world.crowd.shape(i)
        except (ValueError, CommandError, KeyError) as e:
            raise web.HTTPBadRequest(text=str(e)) from None
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / f"avatar{i}.{fmt}"
            await asyncio.get_running_loop().run_in_executor(None, write_motion, path, X, shape)
            body = path.read_bytes()
        return web.Response(body=body, content_type="application/octet-stream",
                            headers={"Content-Disposition": f'attachment; filename="avatar{i}_{seconds:g}s.{fmt}"'})

    async def events(self, request):
        """The commands applied so far, as a script for `serve --headless --script`."""
        self._check_token(request)
        with self.world.lock:
            ev = list(self.world.events)
        return web.json_response({"version": P.VERSION, "seed": self.world.seed, "frames": self.world.frame,
                                  "avatars_at_start": self.initial_avatars, "events": ev})

    # ------------------------------------------------------------ websocket
    async def websocket(self, request):
        ws = web.WebSocketResponse(max_msg_size=P.MAX_MESSAGE_BYTES * 4, heartbeat=20)
        await ws.prepare(request)
        client = Client(ws, needs_token=bool(self.token) and request.query.get("token") != self.token)
        self.clients.add(client)
        sender = asyncio.create_task(self._sender(client))
        await self._send_json(client, self._welcome())
        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    await self._handle(client, msg.data)
                elif msg.type == WSMsgType.BINARY:
                    await self._send_json(client, {"type": "error", "error": "commands are JSON text messages, not binary"})
                elif msg.type == WSMsgType.ERROR:
                    log.info("client connection error: %s", ws.exception())
        finally:
            self.clients.discard(client)
            sender.cancel()
        return ws

    def _welcome(self) -> dict:
        from ..body.skeleton import JOINT_NAMES, PARENTS
        from ..runtime.crowd import IMPULSE_PRESETS
        return {"type": "welcome", "version": P.VERSION, "fps": FPS, "model": self.world.motor.name,
                "joint_names": JOINT_NAMES, "parents": PARENTS, "presets": sorted(IMPULSE_PRESETS),
                "commands": P.COMMANDS, "avatars": self.world.crowd.ids(), "adaptor": self._adaptor_info(),
                "licence": self.world.motor.config.get("licence", "")}

    def _adaptor_info(self) -> dict | None:
        """What the loaded adaptor controls, so a client can offer its labels (or a target)."""
        ad = self.world.crowd.adaptor
        if ad is None:
            return None
        return {"control": ad.cfg.control, "labels": list(ad.cfg.labels), "kind": ad.cfg.kind}

    async def _handle(self, client: Client, text: str) -> None:
        cid = None
        try:
            cmd = P.parse_message(text)
            cid = cmd.pop("id", None)
            if cmd["type"] == "hello":
                if self.token and cmd.get("token") == self.token:
                    client.authorized = True
                if "format" in cmd:
                    client.format = cmd["format"]
                if not client.authorized:
                    raise P.ProtocolError("token required: send {\"type\": \"hello\", \"token\": ...}")
                await self._send_json(client, {"type": "ack", "id": cid, "ok": True, "format": client.format})
                return
            if not client.authorized:
                raise P.ProtocolError("token required: send {\"type\": \"hello\", \"token\": ...} first")
            result = self.world.apply(cmd)
            await self._send_json(client, {"type": "ack", "id": cid, "ok": True, **result})
        except (P.ProtocolError, CommandError, ValueError, KeyError) as e:
            log.info("rejected message: %s", str(e)[:200])
            await self._send_json(client, {"type": "error", "id": cid, "error": str(e)[:500]})

    async def _send_json(self, client: Client, obj: dict) -> None:
        try:
            await client.ws.send_str(json.dumps(obj))
        except (ConnectionError, RuntimeError):
            pass

    async def _sender(self, client: Client) -> None:
        try:
            while True:
                data = await client.queue.get()
                if isinstance(data, bytes):
                    await client.ws.send_bytes(data)
                else:
                    await client.ws.send_str(data)
        except (ConnectionError, RuntimeError, asyncio.CancelledError):
            pass

    # ------------------------------------------------------------ clock and worker
    async def _start_background(self, app):
        self.running = True
        self.initial_avatars = len(self.world.crowd)
        # fill the queues before the clock starts, so the first ticks do not stall
        await asyncio.get_running_loop().run_in_executor(None, self._prefill)
        self.worker = threading.Thread(target=self._generation_worker, daemon=True, name="generation")
        self.worker.start()
        self.clock = asyncio.create_task(self._clock())

    async def _stop_background(self, app):
        self.running = False
        self.clock.cancel()
        self.worker.join(timeout=5)

    def _prefill(self) -> None:
        while self.world.needs_generation():
            self.world.generate()

    def _generation_worker(self) -> None:
        while self.running:
            try:
                if self.world.needs_generation():
                    self.world.generate()
                else:
                    time.sleep(0.002)
            except Exception:  # never let one bad batch kill the world
                log.exception("generation failed")
                time.sleep(0.1)

    async def _clock(self) -> None:
        period = 1.0 / FPS
        next_t = time.perf_counter()
        window: list[float] = []
        last_stats = 0.0
        last_behind = 0
        while True:
            now = time.perf_counter()
            if now < next_t:
                await asyncio.sleep(next_t - now)
            next_t += period
            if time.perf_counter() - next_t > 1.0:  # fell far behind (machine paused): resync
                next_t = time.perf_counter()
            states = self.world.tick()
            ids, J, Q = self.world.frame_payload(states)
            J, Q = J.numpy(), Q.numpy()
            frames = {"binary": P.encode_frame_binary(self.world.frame, ids, J, Q),
                      "json": P.encode_frame_json(self.world.frame, ids, J, Q) if any(c.format == "json" for c in self.clients) else ""}
            for c in list(self.clients):
                c.offer(frames)
            window.append(time.perf_counter())
            window = window[-60:]
            if len(window) > 1:
                self.fps_measured = (len(window) - 1) / (window[-1] - window[0])
            if window[-1] - last_stats > 1.0:
                last_stats = window[-1]
                st = {**self.world.stats(), "fps": round(self.fps_measured, 1), "clients": len(self.clients)}
                if self.world.stalls > last_behind:
                    log.warning("generation behind real time: %d stalled frames so far", self.world.stalls)
                    last_behind = self.world.stalls
                for c in list(self.clients):
                    if c.authorized:
                        asyncio.create_task(self._send_json(c, st))

    def run(self) -> None:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
        log.info("studio at http://%s:%d/  (WebSocket ws://%s:%d/ws)", self.host, self.port, self.host, self.port)
        web.run_app(self.app, host=self.host, port=self.port, print=None, handle_signals=True)

