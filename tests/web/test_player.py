"""The .omg4 web player (``omg4 export --format web``) in headless Chromium: its decoder against the Python decoder
bit for bit, its WebGL2 renders against ``omg4 render``, forged files, and the export folder rule."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from omg4.testing.browser import DIGESTS, SEGMENT_DIGESTS, data_url_image, open_player, python_digests, served
from PIL import Image

from omg4.app.cli import main
from omg4.codec import coders
from omg4.codec.container import read_container
from omg4.codec.payload import CompactGrids, decode_payload
from omg4.codec.references import reference_sections
from omg4.errors import CorruptFileError
from omg4.io.web_player import MANIFEST, export_web
from omg4.metrics import psnr
from omg4.testing import forge

@pytest.mark.parametrize("backbone, codec, count, grids", [
    ("rt4dgs", "compact", 4000, CompactGrids()),  # the demo's size and coder
    ("freetimegs", "compact", 1500, CompactGrids()),
    ("rt4dgs", "compact", 300, CompactGrids(weights=4, rotations=12, exact=100)),  # n-bit weights, other grids
    ("rt4dgs", "ans", 600, CompactGrids()),  # fp16 Morton positions; LZMA floats rewritten for the browser
    ("rt4dgs", "paper", 300, CompactGrids()),  # Huffman+LZMA streams rewritten as ANS
], ids=["demo-size", "freetimegs", "other-grids", "ans-codec", "paper-codec"])
def test_the_page_decodes_every_value_as_the_python_decoder(chromium, tmp_path, backbone, codec, count, grids):
    model = tmp_path / "m.omg4"
    forge.valid_file(model, count, codec=codec, seed=count, codebook_scale=0.25, precision=grids, backbone=backbone)
    export_web(tmp_path / "web", model)
    expected = python_digests(model)
    with served(tmp_path / "web") as url:
        open_player(chromium, f"{url}/index.html?ui=0&time=0")  # paused: no frames compete with the decoding
        decoded = chromium.evaluate(DIGESTS)
    assert decoded == expected


def test_the_page_decodes_a_predicted_sequence_as_the_python_decoder(chromium, tmp_path):
    """Segments 1 and 2 predicted from the one before (key interval 3): the player's chain decodes every value of
    each as the Python decoder does, the values taken from the reference — codebooks, the MLPs' change and the
    carried Gaussians, put first — included."""
    from omg4.codec.container import read_versioned
    from omg4.codec.sequence import read_index, read_segment

    model = tmp_path / "seq.omg4"
    forge.valid_sequence(model, 3, 400, codec="compact", codebook_scale=0.25, key_interval=3)
    carried = [read_versioned(read_segment(model, e))[1].get("carried", 0) for e in read_index(model).segments]
    assert carried[0] == 0 and carried[1] > 0 and carried[2] > 0
    export_web(tmp_path / "web", model)
    listing = json.loads((tmp_path / "web" / "sequence.json").read_text())
    assert listing["key_interval"] == 3 and [s["reference"] for s in listing["segments"]] == [None, 0, 1]
    with served(tmp_path / "web") as url:
        open_player(chromium, f"{url}/index.html?ui=0&time=0")
        for k in (2, 1, 0):
            assert chromium.evaluate(SEGMENT_DIGESTS.replace("SEGMENT", str(k))) == python_digests(model, k), k



def test_the_page_refuses_forged_carried_gaussians_in_one_line(chromium, tmp_path):
    """A predicted segment whose carried Gaussians are forged (docs/file-format.md §8b): the page's message is the
    Python decoder's."""
    from omg4.codec.sequence import SegmentDecoder, read_index, read_segment

    model = tmp_path / "seq.omg4"
    forge.valid_sequence(model, 2, 300, codec="compact", codebook_scale=0.25, key_interval=2)
    export_web(tmp_path / "web", model)
    segment = tmp_path / "web" / json.loads((tmp_path / "web" / "sequence.json").read_text())["segments"][1]["file"]
    header, sections = forge.split_container(read_segment(model, read_index(model).segments[1]))
    reference = reference_sections(SegmentDecoder(model).payload(0))
    forgeries = {
        "count": forge.assemble_container({**header, "carried": header["carried"] + 1}, sections),
        "encoding": forge.assemble_container({**header, "encodings": {**header["encodings"], "carry": "ranks"}},
                                             sections),
        "truncated": forge.assemble_container(header, [(n, b[:-2] if n == "carry" else b) for n, b in sections]),
    }
    decode = SEGMENT_DIGESTS.replace("DIGEST_BODY", "").replace("SEGMENT", "1").replace(
        "const p = await", "try { await").replace("payload(1);", "payload(1); return 'ok'; } catch (e) { return e.message; }")
    with served(tmp_path / "web") as url:
        open_player(chromium, f"{url}/index.html?ui=0&time=0")
        for kind, data in forgeries.items():
            segment.write_bytes(data)
            with pytest.raises(CorruptFileError) as python:
                decode_payload(data, reference)
            message = chromium.evaluate(decode)
            assert message == str(python.value).removeprefix("data: ") and "\n" not in message, kind

def _canvas(browser) -> np.ndarray:
    url = browser.evaluate("document.querySelector('omg4-player').canvas.toDataURL('image/png')")
    return data_url_image(url)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return psnr(a / 255.0, b / 255.0)


@pytest.mark.parametrize("backbone", ["rt4dgs", "freetimegs"])
def test_the_page_renders_the_test_camera_as_omg4_render(chromium, tmp_path, tiny_scene_dir, backbone):
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 1200, codec="compact", seed=7, codebook_scale=0.25, backbone=backbone)
    assert main(["export", str(model), "--format", "web", "--data", str(tiny_scene_dir), "--out",
                 str(tmp_path / "web")]) == 0
    with served(tmp_path / "web") as url:
        for time in (0.0, 0.45, 1.0):
            assert main(["render", "--model", str(model), "--data", str(tiny_scene_dir), "--time", str(time), "--out",
                         str(tmp_path / "ref.png")]) == 0
            reference = np.asarray(Image.open(tmp_path / "ref.png").convert("RGB"), np.float64)
            result = open_player(chromium, f"{url}/index.html?ui=0&width=64&height=48&time={time}")
            assert result["ready"]["camera"] == "cam00"  # the first test camera, as omg4 render --data picks
            page = _canvas(chromium)
            assert page.shape == reference.shape and reference.std() > 10  # a picture, not an empty frame
            assert _psnr(page, reference) >= 30, time


def test_forged_files_end_as_a_one_line_message_and_the_page_stays_responsive(chromium, tmp_path):
    base = forge.valid_file(tmp_path / "m.omg4", 300, codec="compact", seed=5, codebook_scale=0.25)
    export_web(tmp_path / "web", tmp_path / "m.omg4")
    refused = 0
    with served(tmp_path / "web") as url:
        for i, (kind, data) in enumerate(forge.forged_files(base, 24, seed=11)):
            (tmp_path / "web" / "model.omg4").write_bytes(data)
            result = open_player(chromium, f"{url}/index.html?ui=0&time=0&case={i}")
            if "error" in result:
                refused += 1
                message = result["message"]
                assert result["error"] in ("CorruptFileError", "Error") and message and "\n" not in message, kind
            assert chromium.evaluate("1 + 1") == 2
    assert refused >= 12


def test_export_replaces_only_an_earlier_export(tmp_path, capsys):
    model = tmp_path / "m.omg4"
    forge.valid_file(model, 300, codec="compact", seed=2)
    out = tmp_path / "web"
    assert main(["export", str(model), "--format", "web", "--out", str(out)]) == 0
    written = json.loads((out / MANIFEST).read_text())["files"]
    assert {"index.html", "player.js", "model.omg4"} <= set(written)
    assert (out / "model.omg4").read_bytes() == model.read_bytes()  # a compact file needs no rewrite
    assert main(["export", str(model), "--format", "web", "--out", str(out)]) == 0  # over an earlier export
    capsys.readouterr()
    (out / "notes.txt").write_text("mine")
    assert main(["export", str(model), "--format", "web", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "notes.txt" in err and err.count("\n") == 1
    assert (out / "notes.txt").read_text() == "mine"
    other = tmp_path / "other"
    other.mkdir()
    (other / "photo.png").write_bytes(b"x")
    assert main(["export", str(model), "--format", "web", "--out", str(other)]) == 2
    assert sorted(p.name for p in other.iterdir()) == ["photo.png"]
    assert main(["export", str(model), "--format", "web", "--out", str(model)]) == 2  # the input itself


def test_export_web_refuses_what_the_player_cannot_play(tmp_path, capsys):
    checkpoint = tmp_path / "model.safetensors"
    checkpoint.write_bytes(b"not a model")
    assert main(["export", str(checkpoint), "--format", "web", "--out", str(tmp_path / "web")]) == 2
    assert "not an .omg4 file" in capsys.readouterr().err
    assert not (tmp_path / "web").exists()


@pytest.mark.parametrize("key_interval", [1, 2], ids=["key-segments", "predicted"])
def test_a_sequence_plays_segment_by_segment_crossfading_at_boundaries(chromium, tmp_path, tiny_scene_dir,
                                                                       key_interval):
    """Three segments of 1 s sharing 0.2 s (forge.valid_sequence): each fetched as playback reaches it; inside a
    shared range both drawn and crossfaded as omg4's renderer blends them (omg4 render of the sequence file). With
    a key interval of 2 segment 1 is predicted from segment 0 and segment 2 is a key segment again."""
    sequence = tmp_path / "seq.omg4"
    forge.valid_sequence(sequence, 3, 600, codec="compact", codebook_scale=0.25, key_interval=key_interval)
    assert main(["export", str(sequence), "--format", "web", "--data", str(tiny_scene_dir), "--out",
                 str(tmp_path / "web")]) == 0
    index = json.loads((tmp_path / "web" / "sequence.json").read_text())
    assert [s["time_range"] for s in index["segments"]] == [[0.0, 1.0], [0.8, 1.8], [1.6, 2.6]]
    assert not (tmp_path / "web" / "model.omg4").exists()
    fetched = "performance.getEntriesByType('resource').map((e) => e.name.split('/').pop()).filter((n) => n.endsWith('.omg4'))"
    with served(tmp_path / "web") as url:
        for time, shown in ((0.3, {"000.omg4", "001.omg4"}), (0.9, {"000.omg4", "001.omg4", "002.omg4"}),
                            (2.4, {"000.omg4", "002.omg4"})):
            assert main(["render", "--model", str(sequence), "--data", str(tiny_scene_dir), "--time", str(time),
                         "--out", str(tmp_path / "ref.png")]) == 0
            reference = np.asarray(Image.open(tmp_path / "ref.png").convert("RGB"), np.float64)
            result = open_player(chromium, f"{url}/index.html?ui=0&width=64&height=48&time={time}")
            assert result["ready"]["segments"] == 3
            assert _psnr(_canvas(chromium), reference) >= 30, time
            assert set(chromium.evaluate(fetched)) <= shown, time  # the first, those shown and the next one only


def test_the_pages_header_bounds_are_the_python_decoders(chromium, tmp_path):
    """docs/file-format.md §5, one byte either side of each bound: the declared values (8N, 8N per quaternion
    rotation, Σ K·s + N·slots + N·Σ s per attribute, the MLP elements) against 64·B + 2²⁰, and N against B/4 beyond
    4,096 Gaussians — the same refusals as the Python decoder's (tests/codec/test_compact.py)."""
    forge.valid_file(tmp_path / "m.omg4", 300, codec="compact")
    export_web(tmp_path / "web", tmp_path / "m.omg4")
    header, _ = read_container(tmp_path / "m.omg4")
    header["mlp"]["declared.w"] = [1 << 21]
    n, quats = header["num_gaussians"], header["quaternions"]
    declared = 8 * n + 8 * n * len(quats) + sum(int(np.prod(s)) for s in header["mlp"].values())
    for shapes in header["attributes"].values():
        declared += sum(k * s for k, s in shapes) + n * len(shapes) + n * sum(s for _, s in shapes)
    enough = -(-(declared - (1 << 20)) // 64)
    many = {**header, "num_gaussians": 5000}
    check = """(h, bytes) => import('./decoder/payload.js').then(({ checkHeader }) => {
      try { checkHeader(h, bytes); return 'ok'; } catch (e) { return e.message; } })"""
    with served(tmp_path / "web") as url:
        open_player(chromium, f"{url}/index.html?ui=0&time=0")
        results = [chromium.evaluate(f"({check})({json.dumps(h)}, {b})")
                   for h, b in ((header, enough), (header, enough - 1), (many, 20000 + 10**7), (many, 19999))]
    assert results[0] == "ok" and results[1] == f"header declares {declared} values, more than {enough - 1} data bytes can encode"
    assert results[2] == "ok" and results[3].startswith("header claims 5000 Gaussians")


def test_the_bare_page_fills_the_window_with_the_cameras_view_and_more(chromium, tmp_path, tiny_scene_dir):
    """?ui=0 without a size: the canvas is the window; the test camera's view sits centred at the largest scale
    that keeps it whole, the margins show more of the scene — as omg4 render draws that framed camera."""
    from omg4.data import load_scene

    model = tmp_path / "m.omg4"
    forge.valid_file(model, 1200, codec="compact", seed=7, codebook_scale=0.25)
    assert main(["export", str(model), "--format", "web", "--data", str(tiny_scene_dir), "--out",
                 str(tmp_path / "web")]) == 0
    with served(tmp_path / "web") as url:
        open_player(chromium, f"{url}/index.html?ui=0&time=0.45")
        width, height = chromium.evaluate("[window.innerWidth, window.innerHeight]")
        page = _canvas(chromium)
    assert page.shape == (height, width, 3) and width > 64 and height > 48
    camera = load_scene(tiny_scene_dir, decode=False, progress=False).test_cameras()[0]
    s = min(width / camera.width, height / camera.height)
    K = camera.K * np.array([[s, s, s], [s, s, s], [1, 1, 1]])
    K[0, 2] += (width - camera.width * s) / 2
    K[1, 2] += (height - camera.height * s) / 2
    (tmp_path / "framed.json").write_text(json.dumps({"K": K.tolist(), "viewmat": camera.viewmat.tolist(),
                                                      "width": width, "height": height}))
    assert main(["render", "--model", str(model), "--camera", str(tmp_path / "framed.json"), "--time", "0.45",
                 "--out", str(tmp_path / "ref.png")]) == 0
    reference = np.asarray(Image.open(tmp_path / "ref.png").convert("RGB"), np.float64)
    assert reference.std() > 10 and _psnr(page, reference) >= 30


@pytest.mark.parametrize("sequence", [False, True], ids=["one-model", "sequence"])
def test_loading_asks_only_for_files_the_export_wrote(chromium, tmp_path, sequence):
    """No 404 on load: the page reads the export's list (omg4-web.json) before asking for sequence.json or
    cameras.json; every request it makes succeeds, and the stats show no rate before the clock advances."""
    model = tmp_path / "m.omg4"
    if sequence:
        forge.valid_sequence(model, 2, 300, codec="compact", codebook_scale=0.25)
    else:
        forge.valid_file(model, 300, codec="compact", seed=3, codebook_scale=0.25)
    export_web(tmp_path / "web", model)  # no dataset: no cameras.json
    requests = []
    with served(tmp_path / "web", requests) as url:
        result = open_player(chromium, f"{url}/index.html?ui=0&time=0")
        stats = chromium.evaluate("document.querySelector('omg4-player').stats")
    assert "ready" in result
    assert requests and all(status == 200 for _, status in requests), [r for r in requests if r[1] != 200]
    asked = {path.split("?")[0].rsplit("/", 1)[-1] for path, _ in requests}
    assert ("sequence.json" in asked) == sequence and "cameras.json" not in asked
    assert "– FPS" in stats and "Infinity" not in stats


def test_a_page_opened_from_disk_says_how_to_open_it(chromium, tmp_path):
    forge.valid_file(tmp_path / "m.omg4", 300, codec="compact", seed=4)
    export_web(tmp_path / "web", tmp_path / "m.omg4")
    url = (tmp_path / "web" / "index.html").resolve().as_uri()
    chromium.call("Page.navigate", url=url)
    shown = "(() => { const m = document.getElementById('message'); return m && !m.hidden ? m.textContent : null; })()"
    for _ in range(100):
        message = chromium.evaluate(shown)
        if message:
            break
        time.sleep(0.05)
    assert message and "http.server" in message and "http://localhost:8000" in message


def test_the_players_codec_table_is_the_codecs_table():
    from omg4.io.web_player import CODECS_MODULE, PLAYER_ROOT

    assert (PLAYER_ROOT / CODECS_MODULE).read_text() == coders.browser_module()  # regenerate after a codec change
