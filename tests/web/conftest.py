"""The browser player's tests: an export folder served over HTTP and opened in headless Chromium (software WebGL2).
Skipped, with the reason, where Debian's ``chromium`` is missing (``.ci/run`` installs it)."""

from __future__ import annotations

import pytest
from omg4.testing.browser import CHROMIUM, Browser


@pytest.fixture(scope="module")
def chromium(tmp_path_factory):
    if CHROMIUM is None:
        pytest.skip("no Chromium to drive (Debian package 'chromium')")
    browser = Browser(tmp_path_factory.mktemp("profile"))
    yield browser
    browser.close()
