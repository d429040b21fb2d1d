"""``<omg4-player>`` on a plain page of one's own (one module import, one element): it renders the model as
``omg4 render`` does, answers its JS API and raises its events, plays a predicted sequence, and meets a hostile file
with its error event — one line — leaving the page alive."""

from __future__ import annotations

import json

import numpy as np
import pytest
from omg4.testing.browser import data_url_image, served
from PIL import Image

from omg4.app.cli import main
from omg4.errors import CorruptFileError
from omg4.metrics import psnr
from omg4.testing import forge

PAGE = """<!doctype html><html><head><meta charset="utf-8"><link rel="icon" href="data:,">
<script>
  // the page's own count of the WebGL objects alive (made and not yet deleted), by kind
  window.glLive = {};
  for (const kind of ["Buffer", "Texture", "Program", "VertexArray", "Framebuffer"]) {
    const proto = WebGL2RenderingContext.prototype, make = proto["create" + kind], drop = proto["delete" + kind];
    window.glLive[kind] = 0;
    proto["create" + kind] = function () { window.glLive[kind]++; return make.call(this); };
    proto["delete" + kind] = function (o) { if (o) window.glLive[kind]--; return drop.call(this, o); };
  }
</script></head>
<body style="margin: 0">
<p>Someone's own page.</p>
<script type="module" src="player/element.js"></script>
<omg4-player id="scene" ATTRIBUTES style="width: 320px; height: 200px"></omg4-player>
<script>
  window.events = [];
  const scene = document.getElementById("scene");
  for (const name of ["ready", "timechange", "error"]) scene.addEventListener(name, (e) => window.events.push([name, e.detail]));
</script>
</body></html>"""

SETTLED = """customElements.whenDefined('omg4-player').then(() => document.getElementById('scene').ready)
  .then((ready) => ({ready}), (err) => ({error: err.name, message: err.message}))"""


def page(folder, attributes: str) -> None:
    (folder / "page.html").write_text(PAGE.replace("ATTRIBUTES", attributes))


VISITS = iter(range(10**6))


def opened(browser, url: str) -> dict:
    """Navigate to ``url`` (made unique, so the wait below is the new page's) and wait for the element to settle."""
    url = f"{url}{'&' if '?' in url else '?'}visit={next(VISITS)}"
    browser.call("Page.navigate", url=url)
    for _ in range(300):
        if browser.evaluate(f"location.href === {json.dumps(url)} && !!document.getElementById('scene')"):
            break
    return browser.evaluate(SETTLED, timeout=120)


def canvas(browser) -> np.ndarray:
    url = browser.evaluate("document.getElementById('scene').canvas.toDataURL('image/png')")
    return data_url_image(url)


def rendered(tmp_path, model, scene_dir, time: float) -> np.ndarray:
    assert main(["render", "--model", str(model), "--data", str(scene_dir), "--time", str(time), "--out",
                 str(tmp_path / "ref.png")]) == 0
    return np.asarray(Image.open(tmp_path / "ref.png").convert("RGB"), np.float64)


@pytest.fixture(scope="module")
def site(tmp_path_factory, tiny_scene_dir):
    """A site holding an export's folder as ``player/`` and a page of its own beside it."""
    root = tmp_path_factory.mktemp("site")
    model = root / "m.omg4"
    forge.valid_file(model, 1200, codec="compact", seed=7, codebook_scale=0.25)
    assert main(["export", str(model), "--format", "web", "--data", str(tiny_scene_dir), "--out",
                 str(root / "player")]) == 0
    return root, model


def test_the_element_on_a_plain_page_renders_as_omg4_render(chromium, site, tiny_scene_dir, tmp_path):
    root, model = site
    page(root, 'src="player/model.omg4" cameras="player/cameras.json" camera="cam00" time="0.45" width="64" '
               'height="48"')
    with served(root) as url:
        result = opened(chromium, f"{url}/page.html")
        assert result["ready"]["camera"] == "cam00" and result["ready"]["gaussians"] == 1200
        reference = rendered(tmp_path, model, tiny_scene_dir, 0.45)
        image = canvas(chromium)
        assert image.shape == reference.shape and reference.std() > 10
        assert psnr(image / 255, reference / 255) >= 30
        api = chromium.evaluate("""(() => { const s = document.getElementById('scene');
          return {time: s.time, playing: s.playing, range: s.timeRange, names: s.cameraNames,
                  controls: !s.shadowRoot.querySelector('.panel').hidden}; })()""")
        assert api["time"] == 0.45 and not api["playing"] and api["range"] == [0.0, 1.0]
        assert api["names"][0] == "cam00" and not api["controls"]
        # seek: the element draws the new time, says so, and shows what omg4 render shows there
        assert chromium.evaluate("new Promise((done) => { const s = document.getElementById('scene');"
                                 " s.addEventListener('timechange', (e) => e.detail.time === 0.8 && done(true));"
                                 " s.seek(0.8); })")
        assert psnr(canvas(chromium) / 255, rendered(tmp_path, model, tiny_scene_dir, 0.8) / 255) >= 30
        # play, then pause: the time advances, then holds
        t1, t2 = chromium.evaluate("""(async () => {
          const s = document.getElementById('scene'), wait = (ms) => new Promise((r) => setTimeout(r, ms));
          s.seek(0); s.play();
          for (let i = 0; i < 400 && s.time === 0; i++) await wait(50);
          s.pause(); const paused = s.time; await wait(300); return [paused, s.time]; })()""")
        assert t1 > 0 and t2 == t1
        names = [name for name, _ in chromium.evaluate("window.events")]
        assert names[0] == "ready" and "timechange" in names and "error" not in names


def test_the_element_fills_its_box_with_controls_and_takes_a_camera(chromium, site):
    root, _ = site
    page(root, 'src="player/model.omg4" cameras="player/cameras.json" controls autoplay loop')
    with served(root) as url:
        assert "ready" in opened(chromium, f"{url}/page.html")
        size = chromium.evaluate("(() => { const s = document.getElementById('scene'); "
                                 "return [s.canvas.width, s.canvas.height, s.playing, "
                                 "s.shadowRoot.querySelector('.panel').hidden, s.stats]; })()")
        assert size[:2] == [320, 200] and size[2] is True and size[3] is False and "Gaussians" in size[4]
        name = chromium.evaluate("(() => { const s = document.getElementById('scene'); s.camera = s.cameraNames[1]; "
                                 "return s.camera.name; })()")
        assert name == chromium.evaluate("document.getElementById('scene').cameraNames[1]")
        wrong = chromium.evaluate("(() => { try { document.getElementById('scene').camera = 'nope'; } "
                                  "catch (e) { return e.message; } })()")
        assert wrong.startswith("no camera named 'nope'")
        # a new src: the file shown before is let go (its GL objects deleted), the new one loads and is ready again
        live = chromium.evaluate("({...window.glLive})")
        assert live["Buffer"] > 0 and live["Texture"] > 0 and live["Program"] > 0
        again = chromium.evaluate("""(async () => { const s = document.getElementById('scene');
          s.setAttribute('src', 'player/model.omg4?again'); const ready = await s.ready;
          await new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)));
          return [ready.gaussians, s.frames > 0, {...window.glLive}]; })()""")
        assert again[:2] == [1200, True]
        assert again[2] == live  # as many alive as one file needs: the old file's all deleted


def test_a_predicted_sequence_plays_through_the_element(chromium, tmp_path, tiny_scene_dir):
    sequence = tmp_path / "seq.omg4"
    forge.valid_sequence(sequence, 3, 600, codec="compact", codebook_scale=0.25, key_interval=2)
    assert main(["export", str(sequence), "--format", "web", "--data", str(tiny_scene_dir), "--out",
                 str(tmp_path / "player")]) == 0
    with served(tmp_path) as url:
        for time in (0.3, 0.9, 2.4):
            page(tmp_path, f'src="player/" cameras="player/cameras.json" time="{time}" width="64" height="48"')
            result = opened(chromium, f"{url}/page.html")
            assert result["ready"]["segments"] == 3
            assert psnr(canvas(chromium) / 255, rendered(tmp_path, sequence, tiny_scene_dir, time) / 255) >= 30, time


def test_a_hostile_file_raises_the_error_event_in_one_line_and_the_page_lives_on(chromium, tmp_path):
    base = forge.valid_file(tmp_path / "m.omg4", 300, codec="compact", seed=5, codebook_scale=0.25)
    folder = tmp_path / "player"
    assert main(["export", str(tmp_path / "m.omg4"), "--format", "web", "--out", str(folder)]) == 0
    verdicts = []
    with served(tmp_path) as url:
        for i, (kind, data) in enumerate(forge.forged_files(base, 12, seed=3)):
            (folder / "model.omg4").write_bytes(data)
            page(tmp_path, f'src="player/model.omg4?case={i}" time="0"')
            result = opened(chromium, f"{url}/page.html")
            # the reference: what omg4's own decoder makes of the same bytes
            try:
                python_refuses = forge.exercise(folder / "model.omg4") != "ok"
            except CorruptFileError:
                python_refuses = True
            verdicts.append((kind, "error" in result, python_refuses))
            if "error" not in result:
                assert result["ready"]["gaussians"] > 0, kind  # a file the element takes, it shows
                continue
            events = chromium.evaluate("window.events")
            (error,) = [detail for name, detail in events if name == "error"]
            assert error["message"] == result["message"] and error["message"] and "\n" not in error["message"], kind
            shown = chromium.evaluate("document.getElementById('scene').shadowRoot.querySelector('.message')"
                                      ".textContent")
            assert shown == error["message"]
            assert chromium.evaluate("document.querySelector('p').textContent") == "Someone's own page."
    assert [(kind, browser) for kind, browser, _ in verdicts] == [(kind, python) for kind, _, python in verdicts]
    assert sum(browser for _, browser, _ in verdicts) >= 6  # most forgeries are refusals: the error path is exercised
