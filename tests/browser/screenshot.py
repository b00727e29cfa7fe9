"""Saves a screenshot of the web page with the baked terrain lit by a low sun (docs/ui.png).

    HORIZON_BIN=target/debug/horizon-bake python tests/browser/screenshot.py [OUT.png]

It starts the server binary on 127.0.0.1 with a temporary data directory, uploads
docs/corpus/jacksboro_128.png through the page's file input at the terrain's true scale
(height_scale 728.2 = metres / 90 m per texel) with the exact kernel, waits for the WebGL2
viewer, sets a low sun, renders at the displayed size with the CPU preview (`size=`) beside it and
captures the 1280×800 viewport.
"""

from __future__ import annotations

import sys
from pathlib import Path

from playwright.sync_api import sync_playwright

from harness import CHROMIUM, ROOT, TERRAIN, launch, server

AZIMUTH, ELEVATION = 150.0, 12.0


def main() -> int:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs" / "ui.png"
    with server() as s, sync_playwright() as p:
        browser = launch(p, CHROMIUM)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(s.url + "/")
            page.wait_for_function("() => window.__horizon !== undefined")
            page.set_input_files("#file", str(TERRAIN))
            page.select_option("#p-method", "exact")
            page.select_option("#p-radius-mode", "unlimited")
            page.fill("#p-height_scale", "728.2")
            with page.expect_response(lambda r: r.request.method == "POST") as info:
                page.click("#bake")
            bake_id = info.value.header_value("location").rsplit("/", 1)[1]
            page.wait_for_function("id => window.__horizon.loadedId === id", arg=bake_id,
                                   timeout=600_000)
            page.select_option("#layout", "side")
            page.select_option("#resolution", "display")
            page.evaluate("l => window.__horizon.setLight(l)",
                          {"azimuth": AZIMUTH, "elevation": ELEVATION, "hardness": 8})
            # wait for the CPU preview beside the canvas to arrive for this light
            page.wait_for_function(
                "() => { const i = document.getElementById('cpu-image');"
                " return i.src.startsWith('blob:') && i.complete && i.naturalWidth > 0; }",
                timeout=120_000)
            page.evaluate("() => { document.activeElement.blur(); window.scrollTo(0, 0); }")
            page.wait_for_timeout(300)
            page.screenshot(path=str(out))
            if errors:
                print("page errors:", errors, file=sys.stderr)
                return 1
        finally:
            browser.close()
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
