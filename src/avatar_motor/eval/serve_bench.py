"""`avatar-motor bench --serve`: a real `avatar-motor serve` subprocess measured through the
socket: input-to-visible-reaction latency, received frame rate, and the server's CPU use with
1 and 8 avatars."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import numpy as np


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def _start(model: str, avatars: int) -> tuple[subprocess.Popen, str]:
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "avatar_motor.cli", "serve", "--model", model, "--avatars", str(avatars),
                             "--port", str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"ws://127.0.0.1:{port}/ws"
    end = time.time() + 60
    while time.time() < end:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return proc, url
        except OSError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("the server did not start within 60 s")


def reaction_latency(url: str, trials: int = 10) -> list[float]:
    """Send the forward_run impulse and time until a received frame shows the pelvis leaving its
    course by more than 2 cm (relative to constant-velocity extrapolation of the last frames)."""
    from ..client import Client

    out = []
    with Client(url) as c:
        for k in range(trials):
            c.drain()
            hist = [f["avatars"][0]["positions"][0].copy() for f in c.frames(6)]
            c.drain()
            t0 = time.perf_counter()
            c.command({"type": "impulse", "avatar": 0, "preset": "forward_run"}, wait=False)
            last, prev = hist[-1], hist[-2]
            for f in c.frames(30):
                p = f["avatars"][0]["positions"][0]
                expect = last + (last - prev)
                if float(np.linalg.norm((p - expect)[[0, 2]])) > 0.02:
                    out.append(time.perf_counter() - t0)
                    break
                prev, last = last, p
            c.command({"type": "reset", "avatar": 0})
            time.sleep(1.0)
    return out


def serve_bench(model: str, seconds: float = 10.0) -> str:
    lines = [f"serve bench: `avatar-motor serve --model {model}` in a subprocess, measured through the socket"]
    for avatars in (1, 8):
        proc, url = _start(model, avatars)
        try:
            from ..client import Client
            time.sleep(2.0)
            with Client(url) as c:
                c.drain()
                cpu0, t0 = _cpu_seconds(proc.pid), time.time()
                n = sum(1 for _ in c.frames(int(seconds * 30)))
                dt = time.time() - t0
                cpu = (_cpu_seconds(proc.pid) - cpu0) / dt
            lines.append(f"  {avatars} avatar(s): {n / dt:.1f} frames/s received, server CPU {100 * cpu:.0f}% of one core "
                         f"({os.cpu_count()} cores here)")
            if avatars == 1:
                lat = reaction_latency(url)
                if lat:
                    a = np.array(lat) * 1000
                    lines.append(f"  input-to-visible-reaction latency through the socket: median {np.median(a):.0f} ms, "
                                 f"max {a.max():.0f} ms over {len(a)} pushes")
                else:
                    lines.append("  reaction latency: no reaction detected")
        finally:
            proc.terminate()
            proc.wait(10)
    return "\n".join(lines)
