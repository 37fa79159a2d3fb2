"""A small client for the avatar-motor stream (docs/protocol.md): connect, send commands, read
frames. Both an example for engine integrations and the server's test driver.

    from avatar_motor.client import Client
    with Client("ws://127.0.0.1:8765/ws") as c:
        c.command({"type": "goal", "avatar": 0, "velocity": [1.2, 0.0]})
        for frame in c.frames(60):
            print(frame["frame"], frame["avatars"][0]["positions"][0])
"""
from __future__ import annotations

import asyncio
import json
import threading
import time
from queue import Empty, Queue

import aiohttp
import numpy as np

from .serve.protocol import decode_frame_binary


def _frame_from_json(m: dict) -> dict:
    """A JSON frame in the form binary frames decode to, so both formats read alike."""
    return {"frame": m["frame"], "avatars": {a["id"]: {"positions": np.asarray(a["positions"], dtype=np.float32),
                                                       "rotations": np.asarray(a["rotations"], dtype=np.float32)}
                                             for a in m["avatars"]}}


class Client:
    """Blocking wrapper around one WebSocket connection (runs its own event loop thread)."""

    def __init__(self, url: str = "ws://127.0.0.1:8765/ws", format: str = "binary", token: str | None = None,
                 timeout: float = 10.0):
        self.url, self.format, self.token, self.timeout = url, format, token, timeout
        self.frames_q: Queue = Queue()
        self.messages: Queue = Queue()
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._next_id = 1
        self.welcome: dict | None = None
        self.error: BaseException | None = None

    # ------------------------------------------------------------ lifecycle
    def __enter__(self) -> "Client":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def connect(self) -> None:
        self._thread.start()
        if not self._ready.wait(self.timeout):
            raise TimeoutError(f"could not connect to {self.url}")
        if self.error:
            raise ConnectionError(f"could not connect to {self.url}: {self.error}")
        self.welcome = self._wait_message(lambda m: m.get("type") == "welcome")
        if self.format != "binary" or self.token:
            hello = {"type": "hello", "version": 1, "format": self.format}
            if self.token:
                hello["token"] = self.token
            reply = self.command(hello)
            if reply.get("type") == "error":
                self.close()
                raise ConnectionError(f"{self.url}: {reply['error']}")
            if "auth" in self.welcome:  # the server describes its world once the token is given
                self.welcome = self._wait_message(lambda m: m.get("type") == "welcome" and "auth" not in m)

    def close(self) -> None:
        if self._loop.is_running():
            asyncio.run_coroutine_threadsafe(self._close(), self._loop).result(5)
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        self._loop.create_task(self._reader())
        self._loop.run_forever()

    async def _reader(self) -> None:
        try:
            self._session = aiohttp.ClientSession()
            self._ws = await self._session.ws_connect(self.url, max_msg_size=0)
        except Exception as e:  # noqa: BLE001 - reported to the caller
            self.error = e
            self._ready.set()
            return
        self._ready.set()
        async for msg in self._ws:
            if msg.type == aiohttp.WSMsgType.BINARY:
                self.frames_q.put(decode_frame_binary(msg.data))
            elif msg.type == aiohttp.WSMsgType.TEXT:
                m = json.loads(msg.data)
                if m.get("type") == "frame":
                    self.frames_q.put(_frame_from_json(m))
                else:
                    self.messages.put(m)

    async def _close(self) -> None:
        await self._ws.close()
        await self._session.close()

    # ------------------------------------------------------------ use
    def send_raw(self, data: str | bytes) -> None:
        """Send anything (tests use this to send malformed messages)."""
        coro = self._ws.send_bytes(data) if isinstance(data, bytes) else self._ws.send_str(data)
        asyncio.run_coroutine_threadsafe(coro, self._loop).result(self.timeout)

    def command(self, cmd: dict, wait: bool = True) -> dict | None:
        """Send a command; with wait, return its ack (or error) reply."""
        cid = self._next_id
        self._next_id += 1
        self.send_raw(json.dumps({**cmd, "id": cid}))
        if not wait:
            return None
        return self._wait_message(lambda m: m.get("id") == cid and m.get("type") in ("ack", "error"))

    def _wait_message(self, pred) -> dict:
        end = time.time() + self.timeout
        skipped, limited = [], None
        try:
            while time.time() < end:
                try:
                    m = self.messages.get(timeout=max(0.01, end - time.time()))
                except Empty:
                    break
                if pred(m):
                    return m
                if m.get("type") == "error" and m.get("id") is None and str(m.get("error", "")).startswith("rate limit:"):
                    limited = m["error"]
                skipped.append(m)
        finally:
            for m in skipped:
                self.messages.put(m)
        if limited:  # the command was most likely among those dropped
            raise TimeoutError(f"no reply from the server, which said: {limited}; send fewer commands, or wait "
                               "for the limit's bucket to refill and send again")
        raise TimeoutError("no reply from the server")

    def frames(self, n: int):
        """Yield the next n frames, binary or JSON alike: {'frame': k, 'avatars': {id: {'positions':
        (22, 3) float32 array, 'rotations': (22, 4) float32 array x, y, z, w}}}."""
        for _ in range(n):
            yield self.frames_q.get(timeout=self.timeout)

    def drain(self) -> int:
        k = 0
        while True:
            try:
                self.frames_q.get_nowait()
                k += 1
            except Empty:
                return k
