"""The server's limits and guards under abuse (issue #26): continuous goal streams, floods, the
token, the avatar cap. Each test runs its own server (none shares the machine with another)."""
import asyncio
import random
import time

import pytest

from avatar_motor.client import Client
from avatar_motor.runtime.crowd import RuntimeConfig
from avatar_motor.serve.world import World

from .conftest_models import SHIPPED, shipped_or_tiny, tiny_motor
from .test_server import Running


@pytest.fixture
def server(tmp_path):
    world = World(shipped_or_tiny(tmp_path), RuntimeConfig(), seed=0)
    world.apply({"type": "spawn", "position": [0.0, 0.0]}, log=False)
    r = Running(world)
    time.sleep(1.0)
    yield r
    r.stop()


@pytest.mark.parametrize("hz", [10, 60])
def test_a_jittered_goal_stream_keeps_the_avatar_walking(tmp_path, hz):
    """A gamepad stick's stream (1.2 m/s forward, +-0.05 m/s jitter, at 10 or 60 Hz) once froze the
    avatar (0.00 m in 5 s: every goal cut the queue and nothing new was shown). Now goals within
    the recut tolerance only update the controls: it walks (after the first 2 s at 0.8-1.0 m/s
    here; this model's speed from an idle start tops out near there, see the card), the clock shows
    a new frame at (almost) every tick and the queue is cut once."""
    world = World(shipped_or_tiny(tmp_path), RuntimeConfig(), seed=0)
    world.apply({"type": "spawn"}, log=False)
    r = Running(world)
    rng = random.Random(hz)
    try:
        with Client(r.url) as c:
            time.sleep(0.5)
            with world.lock:
                start, s0, f0 = world.crowd.state(0)[[0, 2]].clone(), world.stalls, world.frame
            t0 = time.time()
            mid = None
            while time.time() - t0 < 6.0:
                c.command({"type": "goal", "avatar": 0, "velocity": [rng.uniform(-0.05, 0.05), 1.2 + rng.uniform(-0.05, 0.05)]},
                          wait=False)
                time.sleep(1.0 / hz)
                if mid is None and time.time() - t0 >= 2.0:
                    with world.lock:
                        mid, t_mid = world.crowd.state(0)[[0, 2]].clone(), time.time()
            with world.lock:
                end, t_end = world.crowd.state(0)[[0, 2]].clone(), time.time()
                stalls, ticks, cuts = world.stalls - s0, world.frame - f0, world.crowd.avatars[0].epoch
        moved = float((end - start).norm())
        speed = float((end - mid)[1]) / (t_end - t_mid)  # along the goal (+Z), after the start
        print(f"{hz} Hz: moved {moved:.2f} m in 6 s, {speed:.2f} m/s after 2 s, {stalls} stalled of {ticks} ticks, {cuts} cut(s)")
        assert stalls <= 0.01 * ticks and cuts <= 2
        if SHIPPED.joinpath("model.safetensors").exists():
            assert speed > 0.6  # half the goal speed: walking, not frozen (0.00 m) or shuffling (0.3 m/s)
    finally:
        r.stop()


FLOOD = """
import asyncio, json, sys, time
import aiohttp
msgs = ["{", '{"type": "goal", "avatar": 0, "velocity": [0.5, 0.0]}', '{"type": "push"}', "[]"]
async def main():
    async with aiohttp.ClientSession() as s, s.ws_connect(sys.argv[1], max_msg_size=0) as ws:
        for k in range(50000):
            await ws.send_str(msgs[k % len(msgs)])
        print("sent", time.time(), flush=True)
        end = time.time() + 3
        while time.time() < end:
            try:
                m = await ws.receive(timeout=0.5)
            except asyncio.TimeoutError:
                continue
            if m.type == aiohttp.WSMsgType.TEXT and "rate limit" in m.data:
                print(json.loads(m.data)["error"], flush=True)
            elif m.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING):
                print("closed", ws.close_code, (m.extra or "").replace(chr(10), " "), flush=True)
                break
asyncio.run(main())
"""


VIEW = """
import json, sys, time
from avatar_motor.client import Client
with Client(sys.argv[1]) as v:
    v.drain()
    next(iter(v.frames(1)))
    print("receiving", flush=True)
    end = time.time() + float(sys.argv[2])
    arrivals = []
    while time.time() < end:
        for _ in v.frames(1):
            arrivals.append(time.time())
print(json.dumps(arrivals))
"""


def test_a_flood_from_one_client_leaves_other_viewers_at_30fps(server):
    """50k messages sent as fast as a socket takes them (malformed and valid mixed) by one process
    while another watches: the viewer keeps >= 28 fps, the flooder is cut off once far over the
    rate limit, the event history stays bounded and the server log gets a summary, not a line per
    message."""
    import json
    import subprocess
    import sys
    world = server.server.world
    events_before = world.events_total
    viewer = subprocess.Popen([sys.executable, "-c", VIEW, server.url, "8"], stdout=subprocess.PIPE, text=True)
    # the viewer is connected and receiving (a fixed wait was too short on a loaded host: the flood
    # was over before the viewer's first frame)
    assert viewer.stdout.readline().strip() == "receiving"
    t0 = time.time()
    out = subprocess.run([sys.executable, "-c", FLOOD, server.url], capture_output=True, text=True, timeout=60).stdout.splitlines()
    arrivals = json.loads(viewer.communicate(timeout=60)[0])
    sent = float(next(line for line in out if line.startswith("sent")).split()[1])
    # the flood and 2 s after: the admitted burst (pushes among it) may make a tick late, and the
    # clock makes up a late tick's time at 2 ms a tick (world.Pacer.correction: 100 ms in 1.7 s),
    # so the rate it keeps is an average over that long (over flood + 1 s, one tick 90 ms late on
    # a loaded CI host read 27.8 fps)
    during = [t for t in arrivals if t0 <= t <= sent + 2.0]
    fps = (len(during) - 1) / (during[-1] - during[0])
    gap = max(b - a for a, b in zip(arrivals, arrivals[1:]))
    told = [line for line in out if not line.startswith("sent")]
    closed = [line for line in told if line.startswith("closed")]
    print(f"viewer: {len(during)} frames in the {sent - t0:.1f} s of the flood and 2 s after = {fps:.1f} fps, "
          f"longest gap {1e3 * gap:.0f} ms; told {told[:2]}")
    assert fps >= 28.0 and gap < 0.2
    # the flooder is cut off (1008, policy violation) once it is far over the limit
    assert closed and closed[0].startswith("closed 1008 rate limit:"), told
    from avatar_motor.serve.server import BURST, RATE
    accepted = world.events_total - events_before
    assert accepted <= BURST + RATE * (time.time() - t0)  # the rate limit took the rest
    with Client(server.url) as c:
        assert c.command({"type": "goal", "avatar": 0, "velocity": None})["ok"]


def test_the_token_guards_every_route_is_never_logged_and_guesses_are_limited(tmp_path, caplog):
    import logging

    import aiohttp
    from avatar_motor.serve import server as S
    world = World(tiny_motor(tmp_path), seed=0)
    world.apply({"type": "spawn"}, log=False)
    r = Running(world, token="s3cret")
    base = f"http://127.0.0.1:{r.port}"

    async def get(path):
        async with aiohttp.ClientSession() as s, s.get(base + path) as resp:
            return resp.status

    def status(path):
        return asyncio.run(get(path))

    try:
        with caplog.at_level(logging.INFO):
            for path in ("/", "/api/info", "/api/events", "/api/record?avatar=0&seconds=1"):
                assert status(path) == 401, path
                assert status(path + ("&" if "?" in path else "?") + "token=s3cret") in (200, 503), path
            with Client(r.url) as c:  # no token yet: a welcome that says so, nothing about the world
                assert "auth" in c.welcome and "avatars" not in c.welcome and "model" not in c.welcome
                assert c.command({"type": "hello", "token": "s3cret"})["ok"]
                assert c._wait_message(lambda m: m.get("type") == "welcome" and "avatars" in m)["avatars"] == [0]
            with Client(r.url, token="s3cret") as c:  # the client gives it and gets the full welcome
                assert c.welcome["avatars"] == [0]
            with pytest.raises(ConnectionError, match="token required"):
                Client(r.url, token="wrong").connect()
        assert not any("s3cret" in rec.getMessage() for rec in caplog.records)
        for k in range(S.GUESSES - 1):  # one wrong token was sent above
            assert status(f"/api/info?token=guess{k}") == 401
        assert status("/api/info?token=s3cret") == 429  # locked out, even with the right one, for a while
    finally:
        r.stop()


def test_a_world_refuses_more_avatars_than_it_keeps_in_real_time(tmp_path):
    """The cap is measured at start-up (serve --max-avatars overrides it) and one client may take
    only its share."""
    world = World(tiny_motor(tmp_path), seed=0)
    r = Running(world)
    try:
        from avatar_motor.serve.world import MAX_AVATARS, MAX_KEEP
        assert 1 <= world.max_avatars <= MAX_AVATARS and 1 <= world.crowd.keep_on_cut <= MAX_KEEP
        assert r.server.per_client == max(1, (world.max_avatars + 1) // 2)
    finally:
        r.stop()
    world = World(tiny_motor(tmp_path), seed=0)
    r = Running(world, max_avatars=3, per_client=2)
    try:
        with Client(r.url) as a, Client(r.url) as b:
            assert a.welcome["limits"]["avatars"] == 3 and a.welcome["limits"]["avatars_per_client"] == 2
            assert a.command({"type": "spawn"})["ok"] and a.command({"type": "spawn"})["ok"]
            assert "at most 2" in a.command({"type": "spawn"})["error"]
            assert b.command({"type": "spawn"})["ok"]
            assert "at most 3" in b.command({"type": "spawn"})["error"]
            assert a.command({"type": "remove", "avatar": 0})["ok"] and a.command({"type": "spawn"})["ok"]
    finally:
        r.stop()


def test_bench_soak_reports_rate_memory_stalls_nan_and_drift(tmp_path):
    """`avatar-motor bench --soak` on a short run: its table and plot (the hour-long run is in the README)."""
    from avatar_motor.eval.serve_bench import soak
    model = SHIPPED if (SHIPPED / "model.safetensors").exists() else tiny_motor(tmp_path).path
    report = soak(str(model), 8.0, avatars=2, clients=2, window=4.0, png=str(tmp_path / "soak.png"))
    print(report)
    rows = [line.split() for line in report.splitlines() if line.strip() and line.split()[0].replace(".", "").isdigit()]
    assert len(rows) == 2 and all(len(r) == 5 for r in rows)  # time, 2 clients' frames/s, memory, stalls
    assert all(float(r[1]) > 20 and float(r[2]) > 20 and float(r[3]) > 50 for r in rows)
    assert "frames with NaN/inf: 0" in report and "idle drift" in report and (tmp_path / "soak.png").stat().st_size > 1000


def test_bench_soak_with_the_magnet_moves_the_avatars(tmp_path):
    """`bench --soak --magnet S`: the served model's reaching adaptor (the shipped family's) is sent
    a new target every S seconds, and the avatar walks off its start."""
    from avatar_motor.eval.serve_bench import soak
    if not (SHIPPED / "model.safetensors").exists():
        pytest.skip("needs the shipped family (its reaching adaptor)")
    report = soak(str(SHIPPED), 8.0, avatars=1, clients=1, window=4.0, magnet=1.5)
    print(report)
    line = next(x for x in report.splitlines() if "magnet:" in x)
    assert int(line.split("(")[1].split()[0]) >= 3  # targets sent
    assert float(line.rsplit(":", 1)[1]) > 0.5  # the pelvis left its start for the targets 3 m off
    assert "frames with NaN/inf: 0" in report


def test_a_notice_is_not_lost_behind_frames_a_slow_client_has_not_taken():
    """Frames queue two deep and a slow reader loses the oldest; a notice (the rate limit's) used
    to go through the same queue and could be lost with them, so the client's error could not
    name it. Notices go ahead of the next frame, never dropped for a newer one."""
    from avatar_motor.serve.server import Client as Link, Server

    class SlowSocket:
        def __init__(self):
            self.sent = []

        async def send_str(self, text):
            self.sent.append(text)

        async def send_bytes(self, data):
            self.sent.append(data)

    async def run():
        ws = SlowSocket()
        link = Link(ws, "test", needs_token=False)
        link.offer(b"frame 1")
        link.tell("notice")
        for k in range(2, 6):  # the reader is away: frames 1-3 are dropped for newer ones
            link.offer(f"frame {k}".encode())
        sender = asyncio.create_task(Server._sender(None, link))
        await asyncio.sleep(0.05)
        sender.cancel()
        return ws.sent

    assert asyncio.run(run()) == ["notice", b"frame 4", b"frame 5"]
