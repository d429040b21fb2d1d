"""The player as an npm package (``src/omg4/web/package.json``): ``npm pack`` makes a tarball of the element, the
decoder and the Spark adapter; installed from it into an empty folder, a plain page imports the element from
``node_modules`` and plays a file as ``omg4 render`` draws it."""

from __future__ import annotations

import json
import posixpath
import re
import shutil
import subprocess
import tarfile

import pytest
from test_element import canvas, opened, rendered

import omg4
from omg4.app.cli import main
from omg4.io.web_player import PLAYER_ROOT
from omg4.metrics import psnr
from omg4.testing import forge
from omg4.testing.browser import served

PAGE = """<!doctype html><html><head><meta charset="utf-8"><link rel="icon" href="data:,"></head><body>
<script type="module">import "./node_modules/omg4-player/element.js";</script>
<omg4-player id="scene" src="model.omg4" cameras="cameras.json" camera="cam00" time="0.45" width="64" height="48"
  style="width: 320px; height: 200px"></omg4-player>
</body></html>"""


def npm(*args, cwd) -> str:
    if shutil.which("npm") is None:
        pytest.fail("npm is needed (.ci/run installs the tests' npm packages with it)")
    return subprocess.run(["npm", *args, "--no-audit", "--no-fund"], cwd=cwd, check=True, capture_output=True,
                          text=True, timeout=120).stdout


@pytest.fixture(scope="module")
def tarball(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pack")
    packed = json.loads(npm("pack", str(PLAYER_ROOT), "--pack-destination", str(folder), "--json", cwd=folder))[0]
    return folder / packed["filename"], {f["path"] for f in packed["files"]}


def test_the_package_is_the_player_at_omgs_version(tarball):
    path, files = tarball
    meta = json.loads((PLAYER_ROOT / "package.json").read_text())
    assert meta["version"] == omg4.__version__ and path.name == f"omg4-player-{omg4.__version__}.tgz"
    assert meta["type"] == "module" and meta["exports"]["."] == "./element.js"
    for module in ("element.js", "spark.js", "decoder/payload.js", "decoder/codecs.js", "render/renderer.js",
                   "sequence.js", "player.css", "package.json", "README.md"):
        assert module in files, module
    assert not {"index.html", "spark.html", "spark-page.js"} & files  # the pages of an export, not the package's
    with tarfile.open(path) as tar:
        assert {m.name.removeprefix("package/") for m in tar.getmembers()} == files
    for module in (f for f in files if f.endswith(".js")):  # what the package's modules import, it holds
        source = re.sub(r"^\s*//.*$", "", (PLAYER_ROOT / module).read_text(), flags=re.M)  # not the comments
        for target in re.findall(r'(?:from|import)\s*"(\.{1,2}/[^"]+)"', source):
            assert posixpath.normpath(posixpath.join(posixpath.dirname(module), target)) in files, (module, target)


def test_installed_from_its_tarball_a_plain_page_plays_a_file(tarball, chromium, tiny_scene_dir, tmp_path):
    app = tmp_path / "app"
    app.mkdir()
    npm("install", "--offline", "--ignore-scripts", str(tarball[0]), cwd=app)  # nothing fetched: no dependencies
    resolved = subprocess.run(["node", "--input-type=module", "-e", "console.log(import.meta.resolve('omg4-player'))"],
                              cwd=app, check=True, capture_output=True, text=True).stdout.strip()
    assert resolved == (app / "node_modules" / "omg4-player" / "element.js").as_uri()  # what a bundler imports
    model = app / "model.omg4"
    forge.valid_file(model, 1200, codec="compact", seed=7, codebook_scale=0.25)
    assert main(["export", str(model), "--format", "web", "--data", str(tiny_scene_dir), "--out",
                 str(tmp_path / "export")]) == 0
    shutil.copy(tmp_path / "export" / "cameras.json", app / "cameras.json")
    (app / "page.html").write_text(PAGE)
    with served(app) as url:
        result = opened(chromium, f"{url}/page.html")
        assert result["ready"]["gaussians"] == 1200
        reference = rendered(tmp_path, model, tiny_scene_dir, 0.45)
        image = canvas(chromium)
        assert image.shape == reference.shape and reference.std() > 10
        assert psnr(image / 255, reference / 255) >= 30
