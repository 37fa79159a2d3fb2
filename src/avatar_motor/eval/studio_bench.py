"""`avatar-motor bench --studio`: the studio as a user's browser gets it. A real `avatar-motor
serve` subprocess with N avatars, opened in headless Chromium (Debian's, software GL: no GPU) and
watched for a while: frames received per second (the stream), frames drawn per second, and the
server's stalled ticks (a tick at which some avatar had no frame ready), as the studio's HUD shows
them; then a screenshot. The figures are averages over the window, from the page's counters."""
from __future__ import annotations

import shutil
import time

from .serve_bench import _start

ARGS = ["--no-sandbox", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
COUNTERS = "[performance.now(), window.studio.received, window.studio.drawn, window.studio.stalls]"


def studio_bench(model: str, avatars: int = 8, seconds: float = 20.0, quality: str = "low", png: str | None = None,
                 serve_args: list[str] | None = None, size: tuple[int, int] = (1100, 700)) -> str:
    chromium = shutil.which("chromium")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        sync_playwright = None
    if chromium is None or sync_playwright is None:
        raise RuntimeError("bench --studio needs Debian's chromium (make chromium) and playwright "
                           "(pip install 'avatar-motor[test]')")
    if quality not in ("low", "high"):
        raise ValueError(f"--quality must be low or high, got {quality!r}")
    # the cap raised to the crowd asked for (serve's own measured cap may be lower on a busy host)
    proc, url = _start(model, avatars, ["--max-avatars", str(avatars), "--avatars-per-client", str(avatars),
                                        *(serve_args or [])])
    page_url = url.replace("ws://", "http://").replace("/ws", f"/?quality={quality}")
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, headless=True, args=ARGS)
            page = browser.new_page(viewport={"width": size[0], "height": size[1]})
            page.goto(page_url)
            page.wait_for_function(f"window.studio && window.studio.received > 30 && window.studio.lastStats "
                                   f"&& window.studio.lastStats.avatars >= {avatars}", timeout=120000)
            # the studio draws the first few as skinned humans (16; 8 in low quality), the rest as capsules
            humans = page.evaluate(f"Math.min({avatars}, window.studio.maxHumans)")
            page.wait_for_function(f"window.studio.humans().length >= {humans}", timeout=180000)
            time.sleep(3.0)  # past the meshes' first uploads
            t0, r0, d0, s0 = page.evaluate(COUNTERS)
            per_second = []
            end = time.time() + seconds
            while time.time() < end:
                time.sleep(1.0)
                per_second.append(page.evaluate("[window.studio.fpsTimes.length, window.studio.renderTimes.length]"))
            t1, r1, d1, s1 = page.evaluate(COUNTERS)
            if png:
                page.screenshot(path=png)
            errors = page.evaluate("window.studio.errors")
            browser.close()
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    dt = (t1 - t0) / 1000.0
    stream = [s for s, _ in per_second]
    drawn = [d for _, d in per_second]
    lines = [f"studio bench: `avatar-motor serve --model {model}` with {avatars} avatars, the studio at ?quality={quality} "
             f"in headless Chromium (software GL, {size[0]}x{size[1]}), watched {dt:.0f} s",
             f"  stream: {(r1 - r0) / dt:5.1f} frames/s received (each second: {min(stream)}-{max(stream)})",
             f"  drawn:  {(d1 - d0) / dt:5.1f} frames/s (each second: {min(drawn)}-{max(drawn)})",
             f"  stalled ticks at the server: {s1 - s0} in the window ({s1} since start)",
             f"  drawn as skinned humans: {humans}, as capsules: {avatars - humans}"]
    if errors:
        lines.append(f"  page errors: {errors[:3]}")
    if png:
        lines.append(f"  screenshot: {png}")
    return "\n".join(lines)
