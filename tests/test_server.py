"""The server end to end through the Python client: streaming rate, acks, fuzzing, two viewers."""
import asyncio
import json
import random
import socket
import threading
import time

import numpy as np
import pytest
import torch

from avatar_motor.body.motion_state import body_mismatch
from avatar_motor.body.rotations import quat_to_matrix
from avatar_motor.body.skeleton import SHAPE_DIM, forward_kinematics, rest_offsets
from avatar_motor.client import Client
from avatar_motor.runtime.crowd import RuntimeConfig
from avatar_motor.serve.server import BURST, RATE, Server
from avatar_motor.serve.world import World

from .conftest_models import SHIPPED, shipped_or_tiny, tiny_motor


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Running:
    """A server on a background thread with its own event loop."""

    def __init__(self, world: World, token=None, **limits):
        from aiohttp import web

        from avatar_motor.serve.server import AccessLogger
        self.port = free_port()
        self.server = Server(world, "127.0.0.1", self.port, token, **limits)
        self.loop = asyncio.new_event_loop()
        self.runner = web.AppRunner(self.server.app, access_log_class=AccessLogger)
        started = threading.Event()

        def run():
            asyncio.set_event_loop(self.loop)
            self.loop.run_until_complete(self.runner.setup())
            self.loop.run_until_complete(web.TCPSite(self.runner, "127.0.0.1", self.port).start())
            started.set()
            self.loop.run_forever()

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()
        assert started.wait(20)
        self.url = f"ws://127.0.0.1:{self.port}/ws"

    def stop(self):
        asyncio.run_coroutine_threadsafe(self.runner.cleanup(), self.loop).result(20)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    motor = shipped_or_tiny(tmp_path_factory.mktemp("m"))
    world = World(motor, RuntimeConfig(), seed=0)
    world.apply({"type": "spawn", "position": [0.0, 0.0]}, log=False)
    r = Running(world)
    # let generation get ahead before measuring
    time.sleep(1.0)
    yield r
    r.stop()


def test_stream_rate_acks_and_second_viewer(server):
    with Client(server.url) as a, Client(server.url) as b:
        assert a.welcome["version"] == 1 and len(a.welcome["joint_names"]) == 22
        a.drain()
        t0 = time.time()
        frames = list(a.frames(300))  # 10 s at 30 fps
        dt = time.time() - t0
        rate = len(frames) / dt
        print(f"received {len(frames)} frames in {dt:.2f} s = {rate:.1f} fps")
        assert rate >= 29.0
        idx = [f["frame"] for f in frames]
        assert idx == sorted(idx)
        # every command is acknowledged
        for cmd in ({"type": "goal", "avatar": 0, "velocity": [1.0, 0.0]}, {"type": "impulse", "avatar": 0, "preset": "left_kick"},
                    {"type": "push", "avatar": 0, "joint": "head", "velocity": [0, 0, 2.0]}, {"type": "target", "avatar": 0, "position": [3.0, 3.0]},
                    {"type": "target", "avatar": 0, "position": None}, {"type": "goal", "avatar": 0, "velocity": None},
                    {"type": "seed", "seed": 3}, {"type": "spawn", "position": [2.0, 0.0]}):
            r = a.command(cmd)
            assert r["type"] == "ack" and r["ok"], r
        new = r["avatar"]
        assert b.command({"type": "remove", "avatar": new})["ok"]
        # the second viewer sees the same avatars
        fb = next(b.frames(1))
        assert set(fb["avatars"]) == {0}


def test_every_client_is_told_the_environment(server):
    """An obstacle or a tilt from one client reaches every client as an `environment` message and
    is in the welcome of a client that connects later; a bad index is an error naming it."""
    with Client(server.url) as a, Client(server.url) as b:
        assert a.welcome["environment"]["obstacles"] == [] and a.welcome["environment"]["ground"]["tilt"] == [0.0, 0.0]
        r = a.command({"type": "obstacle", "centre": [5.0, 5.0], "size": [1.0, 0.3, 0.2], "yaw": 45.0})
        assert r["ok"] and r["obstacle"] == 0, r
        m = b._wait_message(lambda m: m.get("type") == "environment" and m["obstacles"])
        assert m["obstacles"] == [{"centre": [5.0, 5.0], "size": [1.0, 0.3, 0.2], "yaw": 45.0}]
        assert a.command({"type": "ground", "tilt": [5.0, 0.0], "pivot": [5.0, 5.0]})["ok"]
        with Client(server.url) as c:
            assert c.welcome["environment"]["ground"] == {"tilt": [5.0, 0.0], "pivot": [5.0, 5.0]}
            assert len(c.welcome["environment"]["obstacles"]) == 1
        r = a.command({"type": "remove_obstacle", "obstacle": 4})
        assert r["type"] == "error" and "no obstacle 4" in r["error"]
        r = a.command({"type": "ground", "tilt": [50.0, 0.0]})
        assert r["type"] == "error" and "tilt" in r["error"]
        r = a.command({"type": "ground", "tilt": [0.0, 0.0], "seconds": -1})
        assert r["type"] == "error" and "seconds" in r["error"]
        # turning (a tilting platform): the environment message and the stats say where it turns from
        assert a.command({"type": "ground", "tilt": [-5.0, 0.0], "pivot": [5.0, 5.0], "seconds": 30})["ok"]
        m = b._wait_message(lambda m: m.get("type") == "environment" and m["ground"]["tilt"] == [-5.0, 0.0])
        assert m["ground"]["from"]["tilt"] == [5.0, 0.0] and m["ground"]["from"]["frames"] == 900
        m = b._wait_message(lambda m: m.get("type") == "stats" and m["environment"]["ground"]["tilt"] == [-5.0, 0.0])
        assert m["environment"]["ground"]["from"]["frames"] == 900
        assert a.command({"type": "remove_obstacle"})["ok"] and a.command({"type": "ground", "tilt": [0.0, 0.0]})["ok"]
        m = b._wait_message(lambda m: m.get("type") == "environment" and not m["obstacles"] and m["ground"]["tilt"] == [0.0, 0.0])
        assert m["obstacles"] == []


def test_fuzzed_messages_leave_the_server_alive_at_30fps(server):
    rng = random.Random(0)
    samples = ['{"type": "goal", "avatar": 0, "velocity": [1e309, 0]}', '{"type": "push"}', "[]", "null", "{",
               '{"type": "impulse", "avatar": 0, "preset": "moonwalk"}', '{"type": "spawn", "shape": [9,9,9,9,9,9]}',
               '{"type": "goal", "avatar": 99, "velocity": [0, 1]}', '{"type": "push", "avatar": 0, "joint": "tail", "velocity": [0,0,1]}',
               '{"type": "reset", "avatar": "0"}', '{"type": "goal", "avatar": 0, "extra": 1}', "x" * 20000,
               '{"type": "seed", "seed": -1}', json.dumps({"type": "label", "avatar": 0, "label": "wave"})]
    with Client(server.url) as c:
        errors = 0
        for k in range(1000):
            r = rng.random()
            if r < 0.3:
                msg = rng.choice(samples)
            elif r < 0.5:
                msg = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 64)))
            elif r < 0.7:
                msg = json.dumps({"type": rng.choice(["goal", "push", "impulse", "spawn", "bogus", 3, None]),
                                  "avatar": rng.choice([0, -1, "a", 1.5, None]), "velocity": rng.choice([[1, 2], "fast", [None, 1], []])})
            elif r < 0.8:
                msg = "".join(chr(rng.randint(32, 0x2FF)) for _ in range(rng.randint(0, 200)))
            else:  # flood of valid but rapid commands
                msg = json.dumps({"type": "goal", "avatar": 0, "velocity": [rng.uniform(-2, 2), rng.uniform(-2, 2)]})
            c.send_raw(msg)
        # every message got a reply, or was dropped over the rate limit and counted in a notice
        end = time.time() + 30
        replies = dropped = 0
        while replies + dropped < 1000 and time.time() < end:
            try:
                m = c.messages.get(timeout=1)
            except Exception:
                continue
            if m.get("type") == "error" and m["error"].startswith("rate limit:"):
                dropped += int(m["error"].split()[2])
            elif m.get("type") in ("ack", "error"):
                replies += 1
                errors += m["type"] == "error"
        assert replies + dropped == 1000 and replies >= 240 and errors > 70, (replies, dropped, errors)
        time.sleep(BURST / RATE)  # the flood emptied the client's bucket: commands sent now may be dropped
        c.command({"type": "goal", "avatar": 0, "velocity": None})
        c.command({"type": "reset", "avatar": 0})
        c.drain()
        t0 = time.time()
        frames = list(c.frames(90))
        assert len(frames) / (time.time() - t0) >= 29.0
    with Client(server.url) as d:  # and a new client still connects
        assert d.welcome["avatars"] == [0]


def test_a_command_dropped_over_the_rate_limit_is_named_in_the_client_error(tmp_path):
    """A command the server dropped over the rate limit gets no reply: the client's error says so
    (the server's notice) rather than only timing out."""
    world = World(shipped_or_tiny(tmp_path))
    world.apply({"type": "spawn"}, log=False)
    r = Running(world, rate=0.5)
    try:
        with Client(r.url, timeout=3.0) as c:
            for _ in range(BURST):  # the whole burst, then one more over the limit
                c.send_raw(json.dumps({"type": "goal", "avatar": 0, "velocity": [1.0, 0.0]}))
            with pytest.raises(TimeoutError, match="rate limit: .* dropped"):
                c.command({"type": "reset", "avatar": 0})
    finally:
        r.stop()


def test_token_required_beyond_loopback(tmp_path):
    motor = shipped_or_tiny(tmp_path)
    with pytest.raises(ValueError, match="--token"):
        Server(World(motor), host="0.0.0.0")
    world = World(motor)
    world.apply({"type": "spawn"}, log=False)
    r = Running(world, token="s3cret")
    try:
        with Client(r.url) as c:
            assert c.command({"type": "goal", "avatar": 0, "velocity": [1, 0]})["type"] == "error"
            assert c.command({"type": "hello", "token": "s3cret"})["ok"]
            assert c.command({"type": "goal", "avatar": 0, "velocity": [1, 0]})["ok"]
    finally:
        r.stop()


def test_headless_replay_is_reproducible(tmp_path):
    motor = shipped_or_tiny(tmp_path)
    script = [{"frame": 10, "cmd": {"type": "impulse", "avatar": 0, "preset": "forward_run"}},
              {"frame": 40, "cmd": {"type": "goal", "avatar": 0, "velocity": [0.0, 1.0]}}]
    runs = []
    for _ in range(2):
        w = World(motor, seed=4)
        w.apply({"type": "spawn"}, log=False)
        w.run_offline(80, script)
        runs.append(w.recording(0))
        assert [e["frame"] for e in w.events] == [10, 40]
    assert (runs[0] - runs[1]).abs().max() == 0


def test_a_physics_session_replays_bit_for_bit(tmp_path):
    """Physics mode through the World's commands (a force, a spring held then released, a ball, an
    obstacle and a tilted ground): the event log replayed headless gives the same frames, bit for
    bit, and the same balls and environment."""
    motor = shipped_or_tiny(tmp_path)
    script = [{"frame": 5, "cmd": {"type": "physics", "avatar": 0, "on": True}},
              {"frame": 8, "cmd": {"type": "obstacle", "centre": [0.0, 0.6], "size": [2.0, 0.2, 0.15], "yaw": 10.0}},
              {"frame": 9, "cmd": {"type": "ground", "tilt": [6.0, -3.0], "pivot": [0.0, 0.0]}},
              {"frame": 12, "cmd": {"type": "force", "avatar": 0, "joint": "pelvis", "force": [300.0, 0.0, 0.0], "seconds": 0.2}},
              {"frame": 20, "cmd": {"type": "spring", "avatar": 0, "joint": "left_wrist", "target": [0.5, 1.5, 0.5]}},
              {"frame": 30, "cmd": {"type": "spring", "avatar": 0, "joint": "left_wrist", "target": None}},
              {"frame": 34, "cmd": {"type": "ball", "avatar": 0, "position": [0.0, 1.2, 1.5], "velocity": [0.0, 0.5, -10.0],
                                    "mass": 3.0}}]
    runs, balls = [], []
    for _ in range(2):
        w = World(motor, seed=2)
        w.apply({"type": "spawn"}, log=False)
        w.run_offline(60, script)
        runs.append(w.recording(0))
        balls.append(w.balls_payload())
        assert [e["frame"] for e in w.events] == [5, 8, 9, 12, 20, 30, 34]
    assert (runs[0] - runs[1]).abs().max() == 0 and balls[0] == balls[1]
    env = w.environment_payload()
    assert env["ground"]["tilt"] == [6.0, -3.0] and len(env["obstacles"]) == 1
    # the replay of the first world's own event log (as /api/events serves it) too
    r = World(motor, seed=2)
    r.apply({"type": "spawn"}, log=False)
    r.run_offline(60, list(w.events))
    assert (r.recording(0) - runs[1]).abs().max() == 0


def test_fit_draws_cuts_the_largest_down_to_one_each():
    from avatar_motor.runtime.crowd import fit_draws
    assert fit_draws([4, 1, 4], None) == [4, 1, 4]  # no budget
    assert fit_draws([4, 1, 4], 9) == [4, 1, 4]  # fits
    assert fit_draws([4, 1, 4], 8) == [4, 1, 3]  # a tie: the later avatar first
    assert fit_draws([4, 1, 4], 5) == [2, 1, 2]
    assert fit_draws([4, 1, 4], 2) == [1, 1, 1]  # never below one draw: the sum stays above
    assert fit_draws([], -3) == []  # every avatar simulated: its physics rows alone exceed the budget
    for counts in ([4, 4, 1, 2], [1], [3, 8], []):
        for rows in range(-2, 17):
            cut = fit_draws(counts, rows)
            assert all(1 <= c <= k for c, k in zip(cut, counts))
            assert sum(cut) == max(min(sum(counts), rows), len(counts))


def test_stats_name_the_avatars_simulated_near_a_low_obstacle(tmp_path):
    """An avatar near a low obstacle is simulated without a command (RuntimeConfig.step_over):
    the stats say so (the studio shows it), and not once the obstacle is gone."""
    w = World(tiny_motor(tmp_path), seed=0)
    w.apply({"type": "spawn"}, log=False)
    w.apply({"type": "spawn", "position": [5.0, 0.0]}, log=False)
    assert w.stats()["simulated"] == []
    w.apply({"type": "obstacle", "centre": [0.0, 0.5], "size": [2.0, 0.2, 0.15]})
    w.run_offline(20)
    assert w.stats()["simulated"] == [0]
    w.apply({"type": "remove_obstacle"})
    w.run_offline(40)
    assert w.stats()["simulated"] == []


def test_a_body_stepping_over_a_bar_is_cut_to_the_served_row_budget(tmp_path):
    """Simulated only to step over a low bar (nothing acting on it), an avatar's candidates are cut
    with the plain draws when a batch would be late; a pushed one's are not."""
    w = World(tiny_motor(tmp_path), seed=0)
    w.apply({"type": "spawn"}, log=False)
    w.apply({"type": "obstacle", "centre": [0.0, 0.5], "size": [2.0, 0.2, 0.15]})
    w.run_offline(20)
    assert w.stats()["simulated"] == [0] and w.crowd.timings["rows"] == w.config.physics.candidates
    w.row_cost = 10.0  # a row takes longer than the queue lasts: one draw each
    w.run_offline(20)
    assert w.stats()["simulated"] == [0] and w.crowd.timings["rows"] == 1
    w.apply({"type": "push", "avatar": 0, "joint": "head", "velocity": [0.0, 0.0, 2.0]})
    w.run_offline(3)
    assert w.crowd.timings["rows"] == w.config.physics.candidates


def test_rows_within_the_budget():
    from avatar_motor.serve.world import rows_within
    assert rows_within(0.05, 0.0, 15) is None  # budget 0: never cut
    assert rows_within(0.05, 0.6, 15) == 6  # 0.3 s of a 0.5-s segment at 50 ms a row
    assert rows_within(0.2, 0.6, 15) == 1
    assert rows_within(10.0, 0.6, 15) == 1  # at least one
    assert rows_within(0.0, 0.6, 15) >= 10**4


def test_a_served_row_budget_cuts_the_draws_and_replays(tmp_path):
    """A served world whose rows take long (World.row_cost, as the generation worker reports
    them) draws fewer best-of-K candidates in its next batches; the budget is recorded with its
    frame (script()'s budgets) and a headless replay draws as it did: the same frames, bit for bit."""
    motor = tiny_motor(tmp_path)
    cfg = RuntimeConfig(goal_candidates=4, trajectory_halflife=0.2)
    script = [{"frame": 0, "cmd": {"type": "goal", "avatar": 0, "velocity": [0.0, 1.0]}}]

    def world():
        w = World(motor, cfg, seed=5)
        w.apply({"type": "spawn"}, log=False)
        return w

    w, rows = world(), []
    for f in range(70):
        if f == 30:
            w.row_cost = 0.15  # 0.7 of the ~14 frames queued: 2 rows
        w.run_offline(1, script if f == 0 else None)
        rows.append(w.crowd.timings.get("rows"))
    assert 4 in rows[:30] and rows[-1] == 2
    assert w.stats()["max_rows"] == 2
    rec = w.script()
    assert rec["budgets"] and rec["budgets"][0]["max_rows"] == 2 and rec["budgets"][0]["frame"] >= 30
    r = world()
    r.run_offline(70, rec["events"], rec["budgets"])
    assert torch.equal(r.recording(0), w.recording(0))
    plain = world()  # without the budget the frames differ: it was applied
    plain.run_offline(70, rec["events"])
    assert not torch.equal(plain.recording(0), w.recording(0))

    # under a budget a batch of simulated avatars only (a pushed one's candidates exceed it; no
    # plain draws to cut) still generates
    sim = world()
    sim.row_cost = 0.15
    sim.run_offline(40, [{"frame": 0, "cmd": {"type": "physics", "avatar": 0, "on": True}},
                         {"frame": 2, "cmd": {"type": "push", "avatar": 0, "joint": "head", "velocity": [0.0, 0.0, 2.0]}}])
    assert sim.stats()["max_rows"] is not None and sim.recording(0).shape[0] == 40


def test_a_command_keeps_the_frames_the_clock_shows_before_its_segment(tmp_path):
    """Served, a command's cut keeps as many queued frames as ticks pass before the new segment
    can be ready (the batch in flight first): none when it is ready before the next tick, so a
    command shows at that tick. The frames kept are in the event, and a replay cuts the same."""
    from avatar_motor.serve.world import CUT_MARGIN, MAX_KEEP
    w = World(tiny_motor(tmp_path), seed=0)
    w.apply({"type": "spawn"}, log=False)
    w.run_offline(5)
    now, period = 100.0, 1 / 30
    w.segment_seconds = 0.010
    ready = 0.010 * (1 + CUT_MARGIN[0]) + CUT_MARGIN[1]  # after now
    w.next_tick = now + ready + 0.001
    assert w.frames_to_keep_now(now) == 0  # ready before the next tick
    w.next_tick = now + ready - 0.001
    assert w.frames_to_keep_now(now) == 1  # one tick passes first
    w.generating_since = now - 0.002  # a batch in flight: 8 ms more
    w.next_tick = now + ready + 0.004
    assert w.frames_to_keep_now(now) == 1
    w.generating_since = None
    w.segment_seconds = 1.0  # a slow machine: at most MAX_KEEP
    assert w.frames_to_keep_now(now) == MAX_KEEP
    w.segment_seconds, w.next_tick = 0.010, now + ready + 2.5 * period
    assert w.frames_to_keep_now(now) == 0
    # the clock may tick later (Pacer.allowance): a segment ready within it keeps none
    w.next_tick, w.tick_allowance = now + ready - 0.001, 0.002
    assert w.frames_to_keep_now(now) == 0
    w.tick_allowance = 0.0

    # through apply: the clock's next tick far ahead keeps none, just passed keeps one
    import time as _time
    for ahead, keep in ((10.0, 0), (-0.001, 1)):
        w.run_offline(20)  # queues full again
        w.next_tick = _time.perf_counter() + ahead
        w.apply({"type": "impulse", "avatar": 0, "preset": "forward_run"})
        assert w.events[-1]["keep"] == keep and len(w.crowd.avatars[0].queue) == keep
        assert w.cut_pending == (keep == 0)  # an emptied queue: the clock ticks when it refills
        w.tick()
        assert not w.cut_pending
    # a replay takes each event's keep
    script = [dict(e, frame=e["frame"] + 5) for e in w.events]
    r = World(tiny_motor(tmp_path), seed=0)
    r.apply({"type": "spawn"}, log=False)
    r.crowd.keep_on_cut = 3
    r.run_offline(script[0]["frame"] + 1, script[:1])
    assert r.events[-1]["keep"] == 0


def _run_pacer(pacer, events, until, ready_at=lambda t: True, cut_at=()):
    """Drive a Pacer on a virtual clock: wake at each `events` time (segment commits) or when its
    wait ends; returns the tick times. cut_at: times at which a command empties a queue."""
    now, ticks, cut = pacer.next_t, [], False
    pending_cuts, wakes = sorted(cut_at), sorted(events)
    while now < until:
        while pending_cuts and pending_cuts[0] <= now:
            pending_cuts.pop(0)
            cut = True
        w = pacer.wait(now, ready_at(now), cut)
        if w <= 0:
            ticks.append(now)
            pacer.ticked(now)
            cut = False
            continue
        later = [t for t in wakes + pending_cuts if t > now]
        now = min([now + w] + later)
    return ticks


def test_the_pacer_shows_a_ready_segment_at_once_and_keeps_the_rate():
    """The served clock (Pacer): undisturbed it ticks every period; a command whose segment is ready
    before its tick shows early (never sooner than min_interval after the last), one not ready when
    due waits for it, each within max_drift of the nominal schedule; the moved phase drifts back,
    so over time the rate is the clock's whatever the commands do."""
    from avatar_motor.serve.world import Pacer
    period = 1 / 30
    p = Pacer.start(0.0, period)
    ticks = _run_pacer(p, [], 0.99)
    assert len(ticks) == 30 and max(abs(t - k * period) for k, t in enumerate(ticks)) < 1e-9

    # a command at 0.501 s, its segment committed 20 ms later: shown then, not at 0.5333
    p = Pacer.start(0.0, period)
    ready = lambda t: not (0.501 <= t < 0.521)  # the queue is empty from the cut until the commit
    ticks = _run_pacer(p, [0.521], 3.0, ready, cut_at=[0.501])
    assert any(abs(t - 0.521) < 1e-9 for t in ticks)
    gaps = [b - a for a, b in zip(ticks, ticks[1:])]
    assert min(gaps) >= p.min_interval - 1e-9 and max(gaps) <= period + p.correction + 1e-9
    assert abs(ticks[-1] - 90 * period) < 0.002 and abs(len(ticks) - 90) <= 1  # back on schedule

    # a segment committed 30 ms after a command just before a tick: that tick waits for it
    p = Pacer.start(0.0, period)
    ready = lambda t: not (0.53 <= t < 0.56)
    ticks = _run_pacer(p, [0.56], 3.0, ready, cut_at=[0.53])
    assert any(abs(t - 0.56) < 1e-9 for t in ticks) and not any(0.5334 < t < 0.56 for t in ticks)
    assert abs(len(ticks) - 90) <= 1

    # frames never ready (generation behind): ticks come late by max_drift at most, at the rate
    p = Pacer.start(0.0, period)
    ticks = _run_pacer(p, [], 2.0, lambda t: False)
    assert all(t - k * period <= p.max_drift + 1e-9 for k, t in enumerate(ticks))
    assert abs(len(ticks) - 60) <= 1

    # a command every tick, each ready at once: the rate holds, and a tick moves at most once in
    # `calm` ticks (a steady stream stays steady under a 60-Hz stick)
    p = Pacer.start(0.0, period)
    cuts = [k * period + 0.001 for k in range(90)]
    ticks = _run_pacer(p, [], 3.0, cut_at=cuts)
    assert abs(len(ticks) - 90) <= 2 and all(t - k * period >= -p.max_drift - 1e-9 for k, t in enumerate(ticks))
    moved = [k for k, (a, b) in enumerate(zip(ticks, ticks[1:])) if abs(b - a - period) > p.correction + 1e-9]
    assert 3 <= len(moved) <= 90 // p.calm + 1 and min(b - a for a, b in zip(moved, moved[1:])) >= p.calm

    p = Pacer.start(0.0, period)  # a machine pause: start over instead of racing to catch up
    p.ticked(0.0)
    p.ticked(5.0)
    assert p.wait(5.01, True, False) > 0 and p.next_t > 5.0


def test_record_and_events_downloads(server):
    import urllib.request
    base = f"http://127.0.0.1:{server.port}"
    for fmt, magic in (("bvh", b"HIERARCHY"), ("glb", b"glTF"), ("npz", b"PK")):
        with urllib.request.urlopen(f"{base}/api/record?avatar=0&seconds=2&format={fmt}", timeout=30) as r:
            body = r.read()
            assert body.startswith(magic) and "attachment" in r.headers["Content-Disposition"]
    with urllib.request.urlopen(f"{base}/api/events", timeout=10) as r:
        ev = json.loads(r.read())
    assert ev["version"] == 1 and isinstance(ev["events"], list)
    with urllib.request.urlopen(f"{base}/api/human?avatar=0", timeout=30) as r:  # the studio's skinned human
        full = r.read()
        assert full.startswith(b"glTF") and r.headers["Content-Type"] == "model/gltf-binary"
    with urllib.request.urlopen(f"{base}/api/human?avatar=0&detail=low", timeout=30) as r:  # its low quality's
        low = r.read()
        assert low.startswith(b"glTF") and len(low) < len(full) / 4
    with urllib.request.urlopen(f"{base}/api/record?avatar=0&seconds=1&format=bvh&skeleton=ue5", timeout=30) as r:
        assert b"JOINT thigh_l" in r.read()  # Unreal's names
    import urllib.error
    for bad in ("record?avatar=0&format=fbx&seconds=0", "record?avatar=0&format=obj", "record?avatar=0&skeleton=maya",
                "human?avatar=99", "human?avatar=x", "human?avatar=0&detail=medium"):  # each named in a 400, the server goes on
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(f"{base}/api/{bad}", timeout=10)
        assert e.value.code == 400


def test_target_command_drives_a_served_reaching_adaptor_at_its_scale(tmp_path):
    from avatar_motor.model.adaptor import AdaptedDenoiser, AdaptorConfig
    from avatar_motor.serve.protocol import ProtocolError, validate_command
    from .conftest_models import tiny_motor
    motor = tiny_motor(tmp_path)
    world = World(motor, adaptors=[AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval()])
    i = world.apply({"type": "spawn"})["avatar"]
    world.apply(validate_command({"type": "target", "avatar": i, "position": [2.0, 1.0], "scale": 0.7}))
    a = world.crowd.avatars[i]
    assert a.target.tolist() == [2.0, 1.0] and a.control_scale == pytest.approx(0.7)
    assert i not in world.targets  # the adaptor walks there, not the velocity magnet
    with pytest.raises(ProtocolError, match="scale"):
        validate_command({"type": "target", "avatar": i, "position": [2.0, 1.0], "scale": 11})
    world.apply(validate_command({"type": "target", "avatar": i, "position": None}))
    assert a.target is None


SHAPE = [1.5, -1.0, 0.8, -0.5, 1.2, -1.4]  # a tall, short-legged, broad body: far from the average one


def fk_error(positions, rotations, shape) -> float:
    """Metres between streamed joint positions (22, 3) and forward kinematics of the streamed
    quaternions (22, 4) x, y, z, w on the bones of `shape`."""
    J = torch.from_numpy(np.array(positions, dtype=np.float64))
    R = quat_to_matrix(torch.from_numpy(np.array(rotations, dtype=np.float64))[:, [3, 0, 1, 2]])  # w, x, y, z
    fk, _ = forward_kinematics(J[0], R[0], R[1:], rest_offsets(shape, torch.float64))
    return float((fk - J).norm(dim=-1).max())


def test_streamed_frames_are_one_body_on_each_avatars_bones(tmp_path):
    world = World(shipped_or_tiny(tmp_path), seed=2)
    r = Running(world)
    try:
        with Client(r.url, format="json") as cj, Client(r.url) as cb:
            ids = [cj.command({"type": "spawn", "position": [0.0, 0.0], "shape": SHAPE})["avatar"],
                   cj.command({"type": "spawn", "position": [2.0, 0.0]})["avatar"]]
            shapes = {ids[0]: torch.tensor(SHAPE), ids[1]: None}
            for cmd in ({"type": "push", "avatar": ids[0], "joint": "head", "velocity": [0.0, 0.0, 2.0]},
                        {"type": "goal", "avatar": ids[0], "velocity": [0.0, 1.0]},
                        {"type": "goal", "avatar": ids[1], "velocity": [-1.0, 0.0]}):
                assert cj.command(cmd)["ok"]
            cj.drain(), cb.drain()
            json_frames, binary_frames = list(cj.frames(60)), list(cb.frames(60))
    finally:
        r.stop()
    for f in (json_frames[0], binary_frames[0]):  # the client gives both formats the same form
        a = f["avatars"][ids[0]]
        assert a["positions"].shape == (22, 3) and a["rotations"].shape == (22, 4) and a["positions"].dtype == np.float32
    worst = {"json": 0.0, "binary": 0.0}
    for fmt, frames in (("json", json_frames), ("binary", binary_frames)):
        for f in frames:
            avs = f["avatars"]  # both formats read alike
            assert set(avs) == set(ids)
            for i in ids:
                worst[fmt] = max(worst[fmt], fk_error(avs[i]["positions"], avs[i]["rotations"], shapes[i]))
    print(f"streamed FK mismatch: {worst}")
    assert worst["json"] < 1e-3 and worst["binary"] < 1e-3
    # the check sees the bones: the shaped avatar is not the average body
    shaped = json_frames[-1]["avatars"][ids[0]]
    assert fk_error(shaped["positions"], shaped["rotations"], None) > 0.01


def test_headless_export_is_one_body_on_the_avatars_bones(tmp_path, capsys):
    from avatar_motor.cli import main
    model = SHIPPED
    if not (SHIPPED / "model.safetensors").exists():
        tiny_motor(tmp_path)
        model = tmp_path / "tiny"
    script = tmp_path / "events.json"
    script.write_text(json.dumps({"events": [
        {"frame": 0, "cmd": {"type": "spawn", "position": [1.0, 0.0], "shape": SHAPE}},
        {"frame": 5, "cmd": {"type": "push", "avatar": 1, "joint": "left_wrist", "velocity": [0.0, 2.0, 1.0]}},
        {"frame": 10, "cmd": {"type": "goal", "avatar": 1, "velocity": [1.0, 0.5]}},
        {"frame": 20, "cmd": {"type": "impulse", "avatar": 0, "preset": "left_kick"}}]}))
    out = tmp_path / "out"
    assert main(["serve", "--model", str(model), "--headless", "--seconds", "2", "--script", str(script),
                 "--export", str(out)]) == 0
    bad = tmp_path / "bad.json"  # a malformed row budget is named, not half replayed
    bad.write_text(json.dumps({"events": [], "budgets": [{"frame": 3, "max_rows": 0}]}))
    assert main(["serve", "--model", str(model), "--headless", "--seconds", "1", "--script", str(bad)]) == 2
    assert "budgets must be" in capsys.readouterr().err
    for i, shape in ((0, None), (1, torch.tensor(SHAPE))):
        with np.load(out / f"avatar{i}.npz") as z:
            states, betas = torch.from_numpy(z["states"]).double(), torch.from_numpy(z["betas"])
        assert len(states) == 60 and torch.equal(betas, shape if shape is not None else torch.zeros(SHAPE_DIM))
        assert float(body_mismatch(states, rest_offsets(shape, torch.float64)).max()) < 1e-3


def test_a_foreign_web_page_cannot_drive_the_server(tmp_path):
    """Cross-site WebSocket hijacking and DNS rebinding: a page of another site (its Origin) or
    reached under a foreign Host name is refused; the studio's own page, programs that send no
    Origin, and a foreign page that knows the token are let in."""
    import aiohttp
    world = World(tiny_motor(tmp_path), seed=0)
    r = Running(world)
    base = f"http://127.0.0.1:{r.port}"

    async def probe(path, headers, token=None):
        url = f"{r.url if path == '/ws' else base + path}" + (f"?token={token}" if token else "")
        async with aiohttp.ClientSession() as s:
            if path == "/ws":
                try:
                    async with s.ws_connect(url, headers=headers) as ws:
                        await ws.send_str(json.dumps({"type": "spawn"}))
                        return 101
                except aiohttp.WSServerHandshakeError as e:
                    return e.status
            async with s.get(url, headers=headers) as resp:
                return resp.status

    def status(path, headers, token=None):
        return asyncio.run(probe(path, headers, token))

    try:
        before = len(world.crowd)
        assert status("/ws", {"Origin": "http://evil.example"}) == 403
        assert status("/api/events", {"Origin": "http://evil.example"}) == 403
        assert status("/api/info", {"Host": "evil.example"}) == 403  # DNS rebinding: a foreign name for our address
        assert status("/ws", {"Host": f"attacker.example:{r.port}"}) == 403
        assert len(world.crowd) == before  # nothing was applied
        assert status("/ws", {"Origin": base}) == 101  # the studio's own page
        assert status("/ws", {"Origin": f"http://localhost:{r.port}", "Host": f"localhost:{r.port}"}) == 101
        assert status("/ws", {}) == 101 and status("/api/info", {}) == 200  # programs send no Origin
    finally:
        r.stop()
    with_token = Running(World(tiny_motor(tmp_path), seed=0), token="s3cret")
    try:
        r = with_token
        assert status("/ws", {"Origin": "http://evil.example"}) == 403
        assert status("/ws", {"Origin": "http://evil.example"}, token="s3cret") == 101
    finally:
        with_token.stop()


def _fuzz_variants(kind: str, rng: random.Random) -> list[dict]:
    """Malformed messages of one command type: each required field missing, each field of a wrong
    type or out of range, an unknown field."""
    from avatar_motor.serve import protocol as P
    required, optional = P._FIELDS[kind]
    good = {"avatar": 0, "preset": "left_kick", "joint": "head", "velocity": [0.0, 0.0, 1.0], "label": "wave",
            "seed": 1, "on": True, "force": [0.0, 0.0, 100.0], "seconds": 0.5, "target": [0.0, 1.0, 1.0],
            "position": [0.0, 1.0, 3.0], "description": "a weary old man", "tilt": [5.0, 0.0], "centre": [0.0, 2.0],
            "size": [1.0, 0.2, 0.2]}
    base = {"type": kind, **{k: good[k] for k in required}}
    bad_values = [None, True, "x" * 300, -1, 1e309, [1e6, 1e6, 1e6], {"a": 1}, [None], ["spawn"], 2**40]
    out = [{**{k: v for k, v in base.items() if k != field}} for field in required]
    for field in [*required, *optional]:
        for v in rng.sample(bad_values, 4):
            out.append({**base, field: v})
    out.append({**base, "bogus": 1})
    out.append({**base, "type": [kind]})
    return out


def test_every_message_class_is_fuzzed_and_errors_carry_the_id(server):
    """docs/protocol.md's commands, each fuzzed; every error reply carries the command's id (a
    client waiting for it gets it) and the server stays up."""
    from avatar_motor.serve import protocol as P
    rng = random.Random(1)
    with Client(server.url) as c:
        for kind in P.COMMANDS:
            for k, msg in enumerate(_fuzz_variants(kind, rng)):
                r = c.command(msg)  # the Client adds an id and waits for the reply with that id
                if r["type"] == "ack":  # null releases a goal, target or label: valid, so acknowledged
                    P.validate_command(msg)
                else:
                    assert r["error"], (msg, r)
            time.sleep(0.3)  # stay within the rate limit
        # the reply's id also when the message is not a valid command at all
        c.send_raw(json.dumps({"type": ["spawn"], "id": "abc"}))
        assert c._wait_message(lambda m: m.get("id") == "abc")["type"] == "error"
        c.send_raw(json.dumps({"type": "goal", "avatar": 0, "id": 77, "pad": "x" * 20000}))  # over 16 KiB
        assert "exceeds" in c._wait_message(lambda m: m.get("id") == 77)["error"]
        c.send_raw("x" * 70000)  # over 64 KiB and under the socket's 1 MiB: an error reply, not a closed socket
        assert "exceeds" in c._wait_message(lambda m: m.get("type") == "error" and "exceeds" in m["error"])["error"]
        c.command({"type": "reset"})
        c.command({"type": "physics", "avatar": 0, "on": False})  # a fuzzed variant may have turned it on
        assert c.command({"type": "goal", "avatar": 0, "velocity": None})["ok"]


def _failing_in_physics(world: World) -> None:
    """Make world's batches fail while one of their avatars is in physics mode (a bug stand-in)."""
    compute = world.crowd.compute

    def bad(job, **kw):
        if any(world.crowd.avatars[i].physics for i in job.avatars if i in world.crowd.avatars):
            raise RuntimeError("a solver bug")
        return compute(job, **kw)

    world.crowd.compute = bad


def test_a_batch_that_keeps_failing_is_given_up_and_the_world_goes_on(tmp_path):
    """A batch that fails FAILURES_BEFORE_RESET times in a row stands its avatars up with physics
    off, logged as commands (a replay does the same), with a notice naming them; before, it was
    retried forever and those avatars stood frozen."""
    from avatar_motor.serve.world import FAILURES_BEFORE_RESET
    w = World(tiny_motor(tmp_path), seed=0)
    w.apply({"type": "spawn"}, log=False)
    w.run_offline(20)
    _failing_in_physics(w)
    w.apply({"type": "physics", "avatar": 0, "on": True})
    calls = []
    compute = w.crowd.compute
    w.crowd.compute = lambda job, **kw: (calls.append(job.avatars), compute(job, **kw))[1]
    w.run_offline(60)
    assert not w.crowd.avatars[0].physics
    assert len(calls) >= FAILURES_BEFORE_RESET + 1  # failed, given up, then generated again
    assert len(w.history[0]) == 80 and w.stalls == 0
    [n] = w.notices
    assert n["type"] == "error" and n["avatars"] == [0] and "a solver bug" in n["error"] and "physics off" in n["error"]
    kinds = [e["cmd"]["type"] for e in w.events]
    assert kinds[-2:] == ["physics", "reset"] and w.failures == 0
    # a failure that giving up does not cure is raised, not looped on
    w.crowd.compute = lambda job, **kw: (_ for _ in ()).throw(RuntimeError("always"))
    with pytest.raises(RuntimeError, match="always"):
        w.run_offline(5)


def test_only_the_avatar_that_fails_a_batch_is_given_up(tmp_path):
    """A batch of several that fails is tried one avatar at a time: the avatar that fails alone is
    given up, the others keep their motion (no reset, physics as it was); before, an avatar that only
    shared the batch was stood up too. A replay of the commands shows the same motion."""
    w = World(tiny_motor(tmp_path), seed=0)
    for _ in range(3):
        w.apply({"type": "spawn"})
    w.run_offline(20)
    _failing_in_physics(w)
    w.apply({"type": "physics", "avatar": 1, "on": True})
    batches = []
    compute = w.crowd.compute
    w.crowd.compute = lambda job, **kw: (batches.append(list(job.avatars)), compute(job, **kw))[1]
    w.run_offline(60)
    [n] = w.notices
    assert n["avatars"] == [1] and "a solver bug" in n["error"]
    assert batches[:6] == [[0, 1, 2], [0], [1], [1], [1], [2]]  # failed together, then each alone, the culprit 3 times
    assert [0, 1, 2] in batches[6:] and not w.searched and not w.suspects  # together again after
    resets = [e["cmd"].get("avatar") for e in w.events if e["cmd"]["type"] == "reset"]
    assert resets == [1] and not w.crowd.avatars[1].physics
    assert all(len(w.history[i]) == 80 for i in range(3))
    # the replay, with the same bug: the give-up's commands come at the frame of the failed batch,
    # before it, so the replay never meets the failure, and its motion is the recorded one
    r = World(tiny_motor(tmp_path), seed=0)
    _failing_in_physics(r)
    r.run_offline(80, w.script()["events"])
    assert not r.notices
    for i in range(3):
        assert torch.equal(torch.stack(list(r.history[i])), torch.stack(list(w.history[i])))


def test_a_batch_that_fails_only_whole_is_given_up_whole(tmp_path):
    """Every avatar of the failing batch goes through alone, and the batch fails again together:
    it is given up whole, once, and the world goes on."""
    w = World(tiny_motor(tmp_path), seed=0)
    for _ in range(2):
        w.apply({"type": "spawn"}, log=False)
    w.run_offline(20)
    compute, failed = w.crowd.compute, []

    def together(job, **kw):
        if len(job.avatars) > 1 and len(failed) < 4:
            failed.append(list(job.avatars))
            raise RuntimeError("a batching bug")
        return compute(job, **kw)

    w.crowd.compute = together
    w.run_offline(60)
    [n] = w.notices
    assert n["avatars"] == [0, 1] and "a batching bug" in n["error"] and len(failed) == 4
    assert all(len(w.history[i]) == 80 for i in range(2)) and not w.searched


def test_a_served_batch_that_keeps_failing_tells_the_clients(tmp_path):
    """Served: the world's other avatars keep moving while the failing one is retried, and every
    client gets the notice once its avatars are stood up; the avatar that only shared its batch is not."""
    world = World(tiny_motor(tmp_path), seed=0)
    world.apply({"type": "spawn"}, log=False)
    world.apply({"type": "spawn"}, log=False)
    _failing_in_physics(world)
    r = Running(world)
    try:
        with Client(r.url, timeout=10.0) as c:
            assert c.command({"type": "physics", "avatar": 0, "on": True})["type"] == "ack"
            n = c._wait_message(lambda m: m.get("type") == "error" and "avatars" in m)
            assert n["avatars"] == [0] and "generation failed" in n["error"]
            assert [e["cmd"].get("avatar") for e in world.events if e["cmd"]["type"] == "reset"] == [0]
            c.drain()
            frames = [f["avatars"][0]["positions"] for f in c.frames(40)]
            assert not world.crowd.avatars[0].physics
            assert np.abs(frames[-1] - frames[0]).max() > 0  # it moves again
    finally:
        r.stop()
