"""The studio in headless Chromium (Debian's): it loads, the avatar moves by itself, and reacts
to a push and to the keyboard. Saves a screenshot to test-artifacts/studio.png."""
import shutil
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from avatar_motor.runtime.crowd import RuntimeConfig
from avatar_motor.serve.server import STATIC
from avatar_motor.serve.world import World

from .conftest_models import shipped_or_tiny
from .test_server import Running

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
needs_chromium = pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="Debian chromium not installed (make test installs it)")


@contextmanager
def studio_page(world: World, ready: str):
    """The studio of a served `world` open in headless Chromium, once the page's `ready` JS holds."""
    if not (STATIC / "dist" / "studio.js").exists():
        pytest.fail("studio not built: run 'make web'")
    from playwright.sync_api import sync_playwright
    world.apply({"type": "spawn"}, log=False)
    srv = Running(world)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
            page = browser.new_page(viewport={"width": 1100, "height": 700})
            page.goto(f"http://127.0.0.1:{srv.port}/")
            page.wait_for_function(ready, timeout=30000)
            yield page
            assert page.evaluate("window.studio.errors.length") == 0
            browser.close()
    finally:
        srv.stop()


@needs_chromium
def test_studio_in_chromium(tmp_path, artifacts):
    world = World(shipped_or_tiny(tmp_path), RuntimeConfig(), seed=0)
    with studio_page(world, "window.studio && window.studio.frame > 20 && window.studio.joints(0)") as page:
        f0, j0 = page.evaluate("[window.studio.frame, window.studio.joints(0)]")
        time.sleep(1.0)
        f1, j1 = page.evaluate("[window.studio.frame, window.studio.joints(0)]")
        assert f1 > f0 + 15  # the stream runs
        # the HUD shows frames received and frames drawn, and the server's stalls
        hud = page.evaluate("['fps', 'drawn', 'stalls'].map((k) => Number(document.getElementById(k).textContent))")
        assert hud[0] >= 25 and hud[1] > 0 and hud[2] >= 0, hud
        assert max(abs(a - b) for a, b in zip(j0, j1)) > 1e-3  # the avatar moves by itself
        # a push through the page's own socket: the head is thrown backwards
        ack = page.evaluate("window.studio.send({type: 'push', avatar: 0, joint: 'head', velocity: [0, 0, -4]})")
        assert ack["ok"]
        # and one with the mouse: drag the pelvis sideways
        x, y = page.evaluate("window.studio.screenOf(0, 0)")
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x + 80, y, steps=5)
        page.mouse.up()
        deadline = time.time() + 5
        while time.time() < deadline and not any(e["cmd"]["type"] == "push" and e["cmd"]["joint"] != "head" for e in world.events):
            time.sleep(0.1)
        drag = [e["cmd"] for e in world.events if e["cmd"]["type"] == "push" and e["cmd"]["joint"] != "head"]
        assert drag and abs(drag[-1]["velocity"][0]) + abs(drag[-1]["velocity"][2]) > 0.1, world.events
        # steering from the keyboard: hold D (camera-relative right) and watch the pelvis travel
        p0 = page.evaluate("window.studio.pelvis(0)")
        page.keyboard.down("KeyW")
        time.sleep(2.5)
        p1 = page.evaluate("window.studio.pelvis(0)")
        page.keyboard.up("KeyW")
        moved = ((p1[0] - p0[0]) ** 2 + (p1[2] - p0[2]) ** 2) ** 0.5
        assert moved > 0.3, f"pelvis moved only {moved:.2f} m while steering"
        assert world.events[-1]["cmd"]["type"] == "goal" or any(e["cmd"]["type"] == "goal" for e in world.events)
        page.screenshot(path=str(artifacts / "studio.png"))


@needs_chromium
def test_studio_offers_the_labels_of_its_adaptors(tmp_path):
    from avatar_motor.model.adaptor import AdaptedDenoiser, AdaptorConfig
    motor = shipped_or_tiny(tmp_path)
    # untrained: the mechanics (the shipped adaptors' own test is test_shipped_family)
    adaptors = [AdaptedDenoiser(motor.net, AdaptorConfig(labels=["bow", "wave"])).eval(),
                AdaptedDenoiser(motor.net, AdaptorConfig(labels=["tired"])).eval(),
                AdaptedDenoiser(motor.net, AdaptorConfig(control="target")).eval()]
    for ad, name in zip(adaptors, ("actions", "styles", "reach")):
        ad.name = name
    world = World(motor, RuntimeConfig(), seed=0, adaptors=adaptors)
    with studio_page(world, "window.studio && window.studio.frame > 5") as page:
        buttons = page.eval_on_selector_all("#labels button", "bs => bs.map(b => b.textContent)")
        assert buttons == ["bow", "wave", "tired", "none"]
        groups = page.eval_on_selector_all("#labels .group", "gs => gs.map(g => g.dataset.adaptor)")
        assert groups == ["actions", "styles"]
        assert "reaching adaptor (reach)" in page.text_content("#magnet-mode")
        page.fill("#scale", "2")
        page.click("#labels button[data-label='wave']")
        deadline = time.time() + 5
        while time.time() < deadline and world.crowd.avatars[0].label is None:
            time.sleep(0.05)
        assert world.crowd.avatars[0].label == 1 and world.crowd.avatars[0].control_scale == 2.0
        page.click("#labels button[data-label='']")
        deadline = time.time() + 5
        while time.time() < deadline and world.crowd.avatars[0].label is not None:
            time.sleep(0.05)
        assert world.crowd.avatars[0].label is None
