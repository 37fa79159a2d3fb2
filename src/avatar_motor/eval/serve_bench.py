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


def _start(model: str, avatars: int, serve_args: list[str] | None = None) -> tuple[subprocess.Popen, str]:
    """A `serve` subprocess; serve_args: runtime options passed on (e.g. ["--backend", "torch"])."""
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "avatar_motor.cli", "serve", "--model", model, "--avatars", str(avatars),
                             "--port", str(port), *(serve_args or [])], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
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


def serve_bench(model: str, seconds: float = 10.0, serve_args: list[str] | None = None) -> str:
    lines = [f"serve bench: `avatar-motor serve --model {model}` in a subprocess, measured through the socket"]
    for avatars in (1, 8):
        proc, url = _start(model, avatars, serve_args)
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


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def soak(model: str, seconds: float, avatars: int = 8, clients: int = 4, window: float = 60.0,
         png: str | None = None, serve_args: list[str] | None = None, magnet: float = 0.0) -> str:
    """`bench --soak`: a real `serve` subprocess with `avatars` idle avatars watched by `clients`
    clients for `seconds`. Per window: frames per second each client received, the server's
    resident memory, stalled ticks; over the run: frames with non-finite values and how far each
    idle avatar's pelvis wandered. magnet > 0: every `magnet` seconds each avatar is sent a new
    target 3 m from where it stood at the start (the studio's magnet moved about; the served
    model's reaching adaptor follows it), so the avatars are not idle."""
    import threading

    from ..client import Client
    proc, url = _start(model, avatars, serve_args)
    rows, lock = [], threading.Lock()
    counts = [0] * clients
    nonfinite = [0]
    first: dict[int, np.ndarray] = {}
    last: dict[int, np.ndarray] = {}
    stop = threading.Event()

    def watch(k: int, c) -> None:
        while not stop.is_set():
            try:
                f = c.frames_q.get(timeout=1.0)
            except Exception:  # noqa: BLE001 - a quiet second; the window shows it
                continue
            with lock:
                counts[k] += 1
                if k == 0:
                    for i, a in f["avatars"].items():
                        p = a["positions"]
                        if not (np.isfinite(p).all() and np.isfinite(a["rotations"]).all()):
                            nonfinite[0] += 1
                            continue
                        first.setdefault(i, p[0, [0, 2]].copy())
                        last[i] = p[0, [0, 2]].copy()

    try:
        time.sleep(2.0)
        cs = [Client(url, timeout=30).__enter__() for _ in range(clients)]
        threads = [threading.Thread(target=watch, args=(k, c), daemon=True) for k, c in enumerate(cs)]
        for t in threads:
            t.start()
        t0 = time.time()
        stalls0 = None
        sent = [0]

        def move_targets() -> None:  # on its own thread, so the windows keep their time
            k = 0
            while not stop.wait(magnet):
                with lock:
                    starts = dict(first)
                for i, p in starts.items():
                    a = 1.3 * k + i
                    cs[0].command({"type": "target", "avatar": i, "position": [float(p[0] + 3 * np.cos(a)),
                                                                               float(p[1] + 3 * np.sin(a))]}, wait=False)
                    sent[0] += 1
                k += 1
        if magnet > 0:
            threading.Thread(target=move_targets, daemon=True).start()
        while time.time() - t0 < seconds:
            with lock:
                before = list(counts)
            w0 = time.time()
            time.sleep(min(window, seconds - (w0 - t0)))
            dt = time.time() - w0
            with lock:
                fps = [(a - b) / dt for a, b in zip(counts, before)]
            stats = [m for m in _drain_messages(cs[0]) if m.get("type") == "stats"]
            stalls = stats[-1]["stalls"] if stats else (rows[-1]["stalls"] if rows else 0)
            stalls0 = stalls if stalls0 is None else stalls0
            rows.append({"t": time.time() - t0, "fps": fps, "rss": _rss_mb(proc.pid), "stalls": stalls})
        stop.set()
        for c in cs:
            c.close()
    finally:
        proc.terminate()
        proc.wait(10)
    drift = {i: float(np.linalg.norm(last[i] - first[i])) for i in sorted(first)}
    lines = [f"soak: `avatar-motor serve --model {model} --avatars {avatars}`, {clients} clients, {seconds:.0f} s "
             f"({os.cpu_count()} cores)",
             "  time (s)  frames/s per client" + " " * max(0, 8 * clients - 19) + "  server RSS (MB)  stalled ticks so far"]
    for r in rows:
        lines.append(f"  {r['t']:8.0f}  " + " ".join(f"{x:7.1f}" for x in r["fps"]) + f"  {r['rss']:15.0f}  {r['stalls']:20d}")
    all_fps = [x for r in rows for x in r["fps"]]
    after = [r["rss"] for r in rows if r["t"] > 60.0] or [r["rss"] for r in rows]
    lines.append(f"  frames/s per client: min {min(all_fps):.1f}, mean {np.mean(all_fps):.1f} (per {window:.0f}-s window)")
    lines.append(f"  server memory {'after the first minute' if rows and rows[-1]['t'] > 60 else 'over the run'}: "
                 f"{min(after):.0f}-{max(after):.0f} MB "
                 f"(growth {after[-1] - after[0]:+.0f} MB)")
    lines.append(f"  stalled ticks: {rows[-1]['stalls'] if rows else 0} of {int(seconds * 30)}; frames with NaN/inf: {nonfinite[0]}")
    where = ", ".join(f"{i}: {d:.2f}" for i, d in drift.items())
    if magnet > 0:
        lines.append(f"  magnet: a new target for every avatar every {magnet:g} s ({sent[0]} targets sent); "
                     f"each avatar's pelvis at the end from its start (m): {where}")
    else:
        lines.append(f"  idle drift of each avatar's pelvis (m): {where}")
    if png:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, (a1, a2, a3) = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
        ts = [r["t"] / 60 for r in rows]
        for k in range(clients):
            a1.plot(ts, [r["fps"][k] for r in rows], label=f"client {k}")
        a1.set_ylabel("frames/s received")
        a1.set_ylim(0, 35)
        a1.legend(loc="lower right")
        a2.plot(ts, [r["rss"] for r in rows])
        a2.set_ylabel("server RSS (MB)")
        a3.bar(ts, np.diff([0] + [r["stalls"] for r in rows]), width=0.8 * (ts[1] - ts[0]) if len(ts) > 1 else 0.5)
        a3.set_ylabel("stalled ticks per window")
        a3.set_xlabel("minutes")
        fig.suptitle(f"soak: {avatars} avatars, {clients} clients")
        fig.savefig(png, dpi=80)
        lines.append(f"  plot: {png}")
    return "\n".join(lines)


def _drain_messages(c) -> list[dict]:
    out = []
    while True:
        try:
            out.append(c.messages.get_nowait())
        except Exception:  # noqa: BLE001 - empty
            return out
