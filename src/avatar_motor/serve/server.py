"""`avatar-motor serve`: one process with the 30-fps world clock, a generation worker thread, a
WebSocket endpoint (/ws) and the web studio (/). Protocol: docs/protocol.md.

Robustness: every message is validated (errors are replied, never raised into the loop); each
client has a two-frame send queue, so a slow client loses frames instead of stalling the clock,
a message rate limit, and a share of the avatars; the loop yields between messages, so a flooding
client cannot starve the clock; rejected messages are logged as a summary per interval; clients
come and go freely; any number of viewers share one world.
"""
from __future__ import annotations

import asyncio
import gc
import hmac
import io
import ipaddress
import json
import logging
import threading
import time
from pathlib import Path

from aiohttp import WSMsgType, web
from aiohttp.abc import AbstractAccessLogger

from ..body.motion_state import FPS
from . import protocol as P
from .world import FAILURES_BEFORE_RESET, CommandError, Pacer, World, measure_capacity

log = logging.getLogger("avatar_motor.serve")
STATIC = Path(__file__).parent / "static"
# commands after which every client is sent the world's `environment` (also in each stats message,
# since a slow client's queue may drop one message)
ENVIRONMENT_COMMANDS = ("ground", "obstacle", "remove_obstacle")
RATE = 120.0  # commands per second per client (a 60-Hz stick and clicks fit; a flood does not)
BURST = 240  # commands a client may send at once
FLOOD = 2000  # messages over the limit within a second that close the connection
NOTICES_KEPT = 8  # a client's unsent notices kept (one a second at most is made)
SUMMARY_EVERY = 10.0  # seconds between log lines about rejected or dropped messages
GUESSES = 10  # wrong tokens from one address within LOCKOUT seconds before it is refused for LOCKOUT
LOCKOUT = 60.0
AUTH_TIMEOUT = 30.0  # seconds a socket may stay open without giving the token


class AccessLogger(AbstractAccessLogger):
    """One line per request without its query string: the token is never written to a log."""

    def log(self, request, response, time):
        self.logger.info("%s %s %s %d %.1f ms", request.remote, request.method, request.path, response.status, 1e3 * time)


class Summary:
    """Counts events and logs them at most once per interval (a flood writes one line, not one per message)."""

    def __init__(self, what: str, every: float = SUMMARY_EVERY):
        self.what, self.every = what, every
        self.count, self.last, self.example = 0, 0.0, ""

    def add(self, example: str = "") -> None:
        self.count += 1
        self.example = example or self.example
        now = time.monotonic()
        if now - self.last >= self.every:
            log.info("%s: %d since the last such line (latest: %s)", self.what, self.count, self.example[:200])
            self.count, self.last = 0, now


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Client:
    def __init__(self, ws: web.WebSocketResponse, address: str, needs_token: bool, rate: float = RATE):
        self.ws, self.address = ws, address
        self.format = "binary"
        self.authorized = not needs_token
        self.queue: asyncio.Queue = asyncio.Queue(maxsize=2)
        self.rate, self.allowance, self.last = rate, float(BURST), time.monotonic()
        self.dropped = 0  # messages over the rate limit since the client was last told
        # messages a client must get (a frame may be lost behind a slow reader, a notice not): sent
        # before the next frame, the newest few kept
        self.notices: list[str] = []
        self.spawned: set[int] = set()  # avatars this client spawned (its share of the world)

    def admit(self) -> bool:
        """Token bucket: RATE messages per second, bursts of BURST."""
        now = time.monotonic()
        self.allowance = min(float(BURST), self.allowance + (now - self.last) * self.rate)
        self.last = now
        if self.allowance < 1.0:
            self.dropped += 1
            return False
        self.allowance -= 1.0
        return True

    def offer(self, data: bytes | str) -> None:
        """Queue the newest frame or stats; a client that has not taken the last two loses the oldest."""
        if not self.authorized:
            return
        if self.queue.full():
            self.queue.get_nowait()
        self.queue.put_nowait(data)

    def tell(self, text: str) -> None:
        """Queue a notice sent ahead of the next frame, never dropped for a newer frame."""
        if self.authorized:
            self.notices.append(text)
            del self.notices[:-NOTICES_KEPT]


class Server:
    def __init__(self, world: World, host: str = "127.0.0.1", port: int = 8765, token: str | None = None,
                 max_avatars: int | None = None, per_client: int | None = None, rate: float = RATE):
        """max_avatars: the world's cap (None: measured at start-up, what this machine keeps in real
        time); per_client: avatars one client may spawn (None: half the cap); rate: commands per
        second per client."""
        if not is_loopback(host) and not token:
            raise ValueError(f"serving on {host} exposes the server beyond this machine: pass --token SECRET "
                             "(clients then send it in their hello message or as ?token=)")
        self.world, self.host, self.port, self.token = world, host, port, token
        self.max_avatars, self.per_client, self.rate = max_avatars, per_client, rate
        self.clients: set[Client] = set()
        self.running = False
        self.fps_measured = 0.0
        self.rejected = Summary("rejected messages")
        self.flooded = Summary("messages dropped over the rate limit")
        self.guesses: dict[str, list[float]] = {}  # address -> times of its wrong tokens
        self.app = web.Application(middlewares=[self._guard])
        self.app.add_routes([
            web.get("/", self.index), web.get("/ws", self.websocket), web.get("/api/info", self.info),
            web.get("/api/record", self.record), web.get("/api/events", self.events), web.get("/api/human", self.human),
            web.static("/static", STATIC, show_index=False),
        ])
        self.app.on_startup.append(self._start_background)
        self.app.on_cleanup.append(self._stop_background)

    # ------------------------------------------------------------ http
    def _locked_out(self, address: str) -> bool:
        now = time.monotonic()
        recent = [t for t in self.guesses.get(address, []) if now - t < LOCKOUT]
        if recent:
            self.guesses[address] = recent
        else:
            self.guesses.pop(address, None)  # no entry per address that never guessed
        return len(recent) >= GUESSES

    def _token_ok(self, given: str | None, address: str) -> bool:
        """Whether `given` is the token; a wrong one counts as a guess from that address."""
        if given is None or not self.token:
            return False
        if hmac.compare_digest(given.encode(), self.token.encode()):
            return True
        self.guesses.setdefault(address, []).append(time.monotonic())
        log.warning("a wrong token from %s", address)
        return False

    @web.middleware
    async def _guard(self, request, handler):
        """Who may use this server.
        - Token: with --token every route but the static files needs it (`?token=`; the WebSocket
          may instead send it in `hello`); an address that sent GUESSES wrong tokens within
          LOCKOUT seconds is refused for LOCKOUT seconds.
        - Same site: no web page of another site drives this server. A request whose Origin is not
          the server's own (the studio's) or whose Host is not a name of this server (DNS
          rebinding) is refused unless it carries the token. Programs (engines, the Python client)
          send no Origin and pass."""
        address = request.remote or "?"
        if self._locked_out(address):
            raise web.HTTPTooManyRequests(text=f"too many wrong tokens from {address}: wait {LOCKOUT:.0f} s")
        given = request.query.get("token")
        has_token = request["has_token"] = self._token_ok(given, address)
        if self.token and not has_token and request.path != "/ws" and not request.path.startswith("/static/"):
            raise web.HTTPUnauthorized(text="token required: add ?token=... to the address")
        if not has_token:
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

    async def record(self, request):
        """The last N seconds of one avatar as a file: ?avatar=0&seconds=10&format=bvh|glb|npz|fbx
        &skeleton=smpl|mixamo|ue5 (io/skeletons.py; FBX through Blender)."""
        import functools
        import tempfile

        from ..io.export import MOTION_FORMATS, write_motion
        from ..io.skeletons import joint_names
        try:
            i = int(request.query.get("avatar", "0"))
            seconds = float(request.query.get("seconds", "10"))
            fmt = request.query.get("format", "bvh")
            skeleton = request.query.get("skeleton", "smpl")
            if f".{fmt}" not in MOTION_FORMATS or not 0 < seconds <= 600:
                raise ValueError(f"format must be one of {[f[1:] for f in MOTION_FORMATS]} and seconds in (0, 600]")
            joint_names(skeleton)
            X = self.world.recording(i, seconds)
            shape = self.world.crowd.shape(i)
        except (ValueError, CommandError, KeyError) as e:
            raise web.HTTPBadRequest(text=str(e)) from None
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / f"avatar{i}.{fmt}"
            try:
                await asyncio.get_running_loop().run_in_executor(
                    None, functools.partial(write_motion, path, X, shape, skeleton=skeleton))
            except ValueError as e:  # FBX without Blender, or Blender failing: the message says which
                raise web.HTTPBadRequest(text=str(e)) from None
            body = path.read_bytes()
        return web.Response(body=body, content_type="application/octet-stream",
                            headers={"Content-Disposition": f'attachment; filename="avatar{i}_{seconds:g}s.{fmt}"'})

    async def human(self, request):
        """?avatar=ID: the skinned human fitted to that avatar's body (body/human.py) as a .glb of
        its skeleton in its current pose, for the studio to drive from the stream; cached per body
        shape (fitting takes ~0.1 s). &detail=low: the coarser mesh (the studio's low quality)."""
        from ..body.human import DETAILS
        from ..io.gltf import write_glb
        detail = request.query.get("detail", "full")
        if detail not in DETAILS:
            raise web.HTTPBadRequest(text=f"detail must be one of {list(DETAILS)}, got {detail!r}")
        try:
            i = int(request.query.get("avatar", "0"))
            X = self.world.recording(i, 1.0 / FPS)
            shape = self.world.crowd.shape(i)
        except (ValueError, CommandError, KeyError) as e:
            raise web.HTTPBadRequest(text=str(e)) from None

        def glb() -> bytes:
            buf = io.BytesIO()
            write_glb(buf, X, shape, detail=detail)
            return buf.getvalue()
        body = await asyncio.get_running_loop().run_in_executor(None, glb)
        return web.Response(body=body, content_type="model/gltf-binary")

    async def events(self, request):
        """The commands applied (the newest world.EVENTS_KEPT), as a script for `serve --headless
        --script`; serialised off the event loop."""
        script = {"version": P.VERSION, **self.world.script(), "avatars_at_start": self.initial_avatars}
        text = await asyncio.get_running_loop().run_in_executor(None, json.dumps, script)
        return web.Response(text=text, content_type="application/json")

    # ------------------------------------------------------------ websocket
    async def websocket(self, request):
        ws = web.WebSocketResponse(max_msg_size=P.MAX_SOCKET_MESSAGE_BYTES, heartbeat=20)
        await ws.prepare(request)
        address = request.remote or "?"
        client = Client(ws, address, needs_token=bool(self.token) and not request.get("has_token", False), rate=self.rate)
        self.clients.add(client)
        sender = asyncio.create_task(self._sender(client))
        if not client.authorized:
            asyncio.get_running_loop().call_later(AUTH_TIMEOUT, self._close_unauthorized, client)
        await self._send_json(client, self._welcome(client))
        try:
            flooder = f"client {address}"
            yielded = time.monotonic()
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    if client.admit():
                        await self._handle(client, msg.data)
                    else:
                        self.flooded.add(flooder)
                        if client.dropped > FLOOD:  # reading a flood costs the clock: stop reading it
                            log.warning("closed %s: more than %d messages over the rate limit within a second", address, FLOOD)
                            await ws.close(code=1008, message=f"rate limit: more than {FLOOD} messages over the limit "
                                                              "within a second; connection closed".encode())
                            break
                elif msg.type == WSMsgType.BINARY:
                    if client.admit():
                        await self._send_json(client, {"type": "error", "id": None,
                                                       "error": "commands are JSON text messages, not binary"})
                elif msg.type == WSMsgType.ERROR:
                    log.info("client connection error: %s", ws.exception())
                if self.token and not client.authorized and self._locked_out(address):
                    await ws.close(code=1008, message=b"too many wrong tokens")
                    break
                # messages already received are returned without suspending: yield every 2 ms, so
                # a client sending thousands at once cannot keep the clock (and every viewer)
                # waiting (yielding after every message cost a loop turn per dropped message)
                now = time.monotonic()
                if now - yielded > 0.002:
                    await asyncio.sleep(0)
                    yielded = time.monotonic()
        finally:
            self.clients.discard(client)
            sender.cancel()
        return ws

    def _close_unauthorized(self, client: Client) -> None:
        if not client.authorized and not client.ws.closed:
            asyncio.ensure_future(client.ws.close(code=1008, message=b"no token given"))

    def _welcome(self, client: Client) -> dict:
        from ..body.skeleton import JOINT_NAMES, PARENTS
        from ..runtime.crowd import IMPULSE_PRESETS
        if not client.authorized:  # nothing about the world before the token
            return {"type": "welcome", "version": P.VERSION, "auth": "token required: send {\"type\": \"hello\", \"token\": ...}"}
        return {"type": "welcome", "version": P.VERSION, "fps": FPS, "model": self.world.motor.name,
                "joint_names": JOINT_NAMES, "parents": PARENTS, "presets": sorted(IMPULSE_PRESETS),
                "commands": P.COMMANDS, "avatars": self.world.crowd.ids(), "adaptors": self._adaptor_info(),
                "licence": self.world.motor.config.get("licence", ""),
                "persona": bool(self.world.motor.net.cfg.persona),
                "environment": self.world.environment_payload(),
                "limits": {"avatars": self.world.max_avatars, "avatars_per_client": self.per_client,
                           "commands_per_second": self.rate, "burst": BURST}}

    def _adaptor_info(self) -> list[dict]:
        """What each loaded adaptor controls, so a client can offer its labels (or a target)."""
        return [{"name": ad.name, "control": ad.cfg.control, "labels": list(ad.cfg.labels), "kind": ad.cfg.kind,
                 "scale": ad.default_scale}
                for ad in self.world.crowd.adaptors]

    async def _handle(self, client: Client, text: str) -> None:
        cid = None
        try:
            cmd = P.parse_message(text)
            cid = cmd.pop("id", None)
            if cmd["type"] == "hello":
                was = client.authorized
                if self._token_ok(cmd.get("token"), client.address):
                    client.authorized = True
                if not client.authorized:
                    raise P.ProtocolError("token required: send {\"type\": \"hello\", \"token\": ...}")
                if "format" in cmd:
                    client.format = cmd["format"]
                await self._send_json(client, {"type": "ack", "id": cid, "ok": True, "format": client.format})
                if not was:  # now the world may be described
                    await self._send_json(client, self._welcome(client))
                return
            if not client.authorized:
                raise P.ProtocolError("token required: send {\"type\": \"hello\", \"token\": ...} first")
            if cmd["type"] == "spawn":
                mine = client.spawned & set(self.world.crowd.ids())
                if len(mine) >= self.per_client:
                    raise CommandError(f"one client may spawn at most {self.per_client} avatars (this one has "
                                       f"{sorted(mine)}); remove one first")
            result = self.world.apply(cmd)
            if cmd["type"] == "spawn":
                client.spawned.add(result["avatar"])
            await self._send_json(client, {"type": "ack", "id": cid, "ok": True, **result})
            if cmd["type"] in ENVIRONMENT_COMMANDS:  # every client draws the same world
                with self.world.lock:
                    msg = json.dumps(self.world.environment_payload())
                for c in list(self.clients):
                    c.offer(msg)
        except (P.ProtocolError, CommandError, ValueError, KeyError) as e:
            if isinstance(e, P.ProtocolError) and e.id is not None:
                cid = e.id
            self.rejected.add(str(e))
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
                while client.notices:
                    await client.ws.send_str(client.notices.pop(0))
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
        loop = asyncio.get_running_loop()
        if self.max_avatars is None:
            w = self.world
            cap, keep, line = await loop.run_in_executor(None, measure_capacity, w.motor, w.config, w.crowd.adaptors)
            log.info(line)
            self.max_avatars, w.crowd.keep_on_cut = cap, keep
        self.world.max_avatars = self.max_avatars
        if self.per_client is None:
            self.per_client = max(1, (self.max_avatars + 1) // 2)
        if self.initial_avatars > self.max_avatars:
            log.warning("%d avatars at start, more than the %d this machine keeps in real time: expect stalls",
                        self.initial_avatars, self.max_avatars)
        # fill the queues before the clock starts, so the first ticks do not stall
        await loop.run_in_executor(None, self._prefill)
        # what exists now (the model, the imports) is never garbage: out of the collector's way, a
        # full collection during a message flood otherwise held the clock for up to 0.46 s
        gc.collect()
        gc.freeze()
        self.loop, self.wake = loop, asyncio.Event()  # the worker wakes the clock when a segment commits
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
        crowd = self.world.crowd
        ema = per_row = None
        while self.running:
            try:
                if self.world.needs_generation():
                    self.world.generate()
                    # the frames a cut keeps follow how long a batch takes now (this machine's
                    # speed varies) and where the clock stands (World.frames_to_keep_now)
                    t = crowd.timings.get("total", 0.0)
                    ema = t if ema is None else 0.9 * ema + 0.1 * t
                    self.world.segment_seconds = ema  # a command's cut keeps what this covers
                    # and the draws of the next batches what fits (a row's cost follows the load faster)
                    row = t / max(crowd.timings.get("rows", 1), 1)
                    per_row = row if per_row is None else 0.7 * per_row + 0.3 * row
                    self.world.row_cost = per_row
                    self.loop.call_soon_threadsafe(self.wake.set)
                else:
                    time.sleep(0.002)
            except Exception:  # never let one bad batch kill the world (World.generate gives it up in the end)
                log.exception("generation failed (try %d of %d before its avatars are stood up)",
                              self.world.failures, FAILURES_BEFORE_RESET)
                time.sleep(0.1)

    async def _clock(self) -> None:
        pacer = Pacer.start(time.perf_counter())
        window: list[float] = []
        last_stats = 0.0
        last_behind = 0
        had_balls = False
        while True:
            while True:  # until the pacer says tick: its time, or a command's segment ready early
                self.wake.clear()  # before looking, so a commit from now on wakes the wait below
                now = time.perf_counter()
                wait = pacer.wait(now, self.world.frames_ready(), self.world.cut_pending)
                if wait <= 0:
                    break
                try:
                    await asyncio.wait_for(self.wake.wait(), wait)
                except asyncio.TimeoutError:
                    pass
            states = self.world.tick()
            pacer.ticked(now)
            # read by a command's cut (World.frames_to_keep_now)
            self.world.next_tick, self.world.tick_allowance = pacer.next_t, pacer.allowance()
            ids, J, Q = self.world.frame_payload(states)
            J, Q = J.numpy(), Q.numpy()
            frames = {"binary": P.encode_frame_binary(self.world.frame, ids, J, Q),
                      "json": P.encode_frame_json(self.world.frame, ids, J, Q) if any(c.format == "json" for c in self.clients) else ""}
            for c in list(self.clients):
                c.offer(frames[c.format])
            with self.world.lock:
                balls = self.world.balls_payload()
            if balls or had_balls:  # once more when the last one is gone, so clients clear them
                msg = json.dumps({"type": "balls", "frame": self.world.frame, "balls": balls})
                for c in list(self.clients):
                    c.offer(msg)
            had_balls = bool(balls)
            if self.world.notices:  # avatars a failing batch stood up (World._give_up): every client is told
                with self.world.lock:
                    notices, self.world.notices = self.world.notices, []
                for n in notices:
                    log.warning("%s", n["error"])
                    for c in list(self.clients):
                        c.tell(json.dumps(n))
            window.append(time.perf_counter())
            window = window[-60:]
            if len(window) > 1:
                self.fps_measured = (len(window) - 1) / (window[-1] - window[0])
            if window[-1] - last_stats > 1.0:
                last_stats = window[-1]
                with self.world.lock:  # what the environment message says (a turning ground with where it turns from)
                    env = self.world.crowd.environment.describe(self.world.crowd.turning())
                st = json.dumps({**self.world.stats(), "fps": round(self.fps_measured, 1), "clients": len(self.clients),
                                 "environment": env})
                if self.world.stalls > last_behind:
                    log.warning("generation behind real time: %d stalled frames so far", self.world.stalls)
                    last_behind = self.world.stalls
                for c in list(self.clients):
                    c.offer(st)
                    if c.dropped:  # told once a second, not once per message
                        c.tell(json.dumps({"type": "error", "id": None, "error": (
                            f"rate limit: {c.dropped} messages dropped in the last second (limit "
                            f"{self.rate:g} per second, bursts of {BURST})")}))
                        c.dropped = 0

    def run(self) -> None:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
        log.info("studio at http://%s:%d/  (WebSocket ws://%s:%d/ws)", self.host, self.port, self.host, self.port)
        web.run_app(self.app, host=self.host, port=self.port, print=None, handle_signals=True,
                    access_log_class=AccessLogger)

