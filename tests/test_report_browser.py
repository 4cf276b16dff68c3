"""A survey's report.html in a real browser: headless Chromium opens the smoke survey's page from the file,
every image on it decodes, and the screenshot shows maps (not a blank page). Skipped where Chromium is not
installed, unless RAGSPLAT_BROWSER=required (CI installs it and sets that)."""

import os
import re
import shutil
import subprocess

import numpy as np
import pytest
from test_survey import finished, survey  # noqa: F401 (the fixtures)

from ragsplat.dataset import layout

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
# the flags a closed network and a root user need (no sandbox, no background connections)
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars"]


@pytest.fixture
def chromium(tmp_path):
    if CHROMIUM is None:
        if os.environ.get("RAGSPLAT_BROWSER") == "required":
            pytest.fail("RAGSPLAT_BROWSER=required and no chromium on the PATH")
        pytest.skip("no Chromium (apt-get install chromium)")

    def run(*args):
        return subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", *args],
                              capture_output=True, text=True, timeout=120, check=True)
    return run


def test_the_report_opens_in_chromium_with_every_map_drawn(finished, chromium, tmp_path):  # noqa: F811
    out, _ = finished
    url = (out / "report.html").resolve().as_uri()
    dom = chromium("--virtual-time-budget=10000", "--dump-dom", url).stdout  # after the load event
    loaded = re.search(r'data-images="(\d+)/(\d+)"', dom)
    assert loaded, "the page's check did not run"
    done, total = map(int, loaded.groups())
    assert total >= 6 and done == total, f"{done} of {total} images decoded"
    shot = tmp_path / "report.png"
    chromium(f"--screenshot={shot}", "--window-size=1400,1800", url)
    image = layout.read_png(shot)
    inked = (image < 200).any(-1).mean()
    colours = len(np.unique(image.reshape(-1, 3), axis=0))
    # a page of text alone inks a few per cent in a few hundred colours
    assert inked > 0.05 and colours > 2000, f"{100 * inked:.0f} % inked, {colours} colours: a blank page?"
