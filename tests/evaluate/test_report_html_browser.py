"""report.html in a real browser: headless Chromium (Debian's ``chromium`` package).

Chromium is run as a command, no DevTools client (the environment has no WebSocket
package):

- ``--dump-dom`` prints the DOM after the page has loaded and ``--virtual-time-budget``
  ms of (virtual) time have passed;
- ``--enable-logging=stderr --v=0`` makes Chromium write every console message of the
  page, uncaught exceptions included, to stderr as ``...:CONSOLE:<line>] "<message>"``
  (the CONSOLE line format has changed between versions, hence the loose pattern);
- whether each ``<img>`` loaded is not in the DOM, so a test-only wrapper page next to
  the report loads it in an iframe and writes ``complete && naturalWidth > 0`` of every
  image into its own DOM. file:// pages are cross-origin to each other unless
  ``--allow-file-access-from-files`` is given, so the wrapper's Chromium gets that flag;
- ``--host-resolver-rules`` maps every host name to nothing, so the page cannot reach
  the network even if it tried (the report must not need it).

- the page's layout (how wide its content is, whether a table overflows its box, which
  links it has) is measured the same way, by a wrapper whose iframe is as wide as a
  laptop's window (``LAPTOP_WIDTHS``).

``test_checks_detect_planted_faults`` proves every check can fail.
"""

from __future__ import annotations

import html
import json
import os
import re
import signal
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import OpenImageIO as oiio
import pytest

CHROMIUM = Path("/usr/bin/chromium")

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="/usr/bin/chromium not installed (Debian packages: chromium chromium-driver)",
)

#: Flags for a quiet, offline, headless run as root in a container.
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",  # the test may run as root, where the sandbox refuses to start
    "--disable-gpu",
    "--disable-dev-shm-usage",  # containers often have a tiny /dev/shm
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--host-resolver-rules=MAP * ~NOTFOUND",
    "--enable-logging=stderr",
    "--v=0",
)
#: Virtual time the page gets after loading before the DOM is dumped (ms).
VIRTUAL_TIME_BUDGET_MS = 5000
#: Wall-clock limit of one Chromium run (s); a normal run takes about one second.
CHROMIUM_TIMEOUT_S = 60
#: Console messages as logged by Chromium to stderr with --enable-logging=stderr.
CONSOLE_LINE = re.compile(r":CONSOLE[:(]\d*\)?\]\s*(.*)")
WRAPPER_RESULT_ID = "phrt-img-check"

#: Loads ``{page}`` in an iframe; once it (and therefore every image in it) has loaded,
#: writes [{src, ok}] for every <img> into <pre id=WRAPPER_RESULT_ID>.
WRAPPER_HTML = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>image check</title></head><body>
<pre id="{result_id}">pending</pre>
<iframe id="page" src="{page}" width="1200" height="800"></iframe>
<script>
const frame = document.getElementById("page");
frame.addEventListener("load", () => {{
  let result;
  try {{
    result = Array.from(frame.contentDocument.images).map(img => ({{
      src: img.getAttribute("src"),
      ok: img.complete && img.naturalWidth > 0,
    }}));
  }} catch (error) {{
    result = {{error: String(error)}};
  }}
  document.getElementById("{result_id}").textContent = JSON.stringify(result);
}});
</script></body></html>
"""


#: Window widths the page must fit without scrolling sideways (px): a 1280 px laptop
#: screen, and a narrower window on one.
LAPTOP_WIDTHS = (1280, 1024)
#: The data files the page must link (relative links to files next to it).
DATA_LINKS = ("sweep.csv", "summary.csv")

#: Loads ``{page}`` in an iframe ``{width}`` px wide; once loaded, writes the page's
#: layout into <pre id=WRAPPER_RESULT_ID>: its content width (scrollWidth) against its
#: window (clientWidth), each ``div.table`` box's, and every link's href.
LAYOUT_WRAPPER_HTML = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>layout check</title></head><body style="margin:0">
<pre id="{result_id}">pending</pre>
<iframe id="page" src="{page}" width="{width}" height="900" style="border:0"></iframe>
<script>
const frame = document.getElementById("page");
frame.addEventListener("load", () => {{
  let result;
  try {{
    const doc = frame.contentDocument;
    result = {{
      content: doc.documentElement.scrollWidth,
      window: doc.documentElement.clientWidth,
      tables: Array.from(doc.querySelectorAll("div.table")).map(box => ({{
        content: box.scrollWidth, box: box.clientWidth,
      }})),
      links: Array.from(doc.querySelectorAll("a[href]")).map(a => a.getAttribute("href")),
    }};
  }} catch (error) {{
    result = {{error: String(error)}};
  }}
  document.getElementById("{result_id}").textContent = JSON.stringify(result);
}});
</script></body></html>
"""


def run_chromium(page: Path, profile: Path, *extra: str) -> tuple[str, list[str]]:
    """Load ``page`` headless; return (dumped DOM, console messages)."""
    command = [
        str(CHROMIUM),
        *CHROMIUM_FLAGS,
        f"--user-data-dir={profile}",
        f"--virtual-time-budget={VIRTUAL_TIME_BUDGET_MS}",
        *extra,
        "--dump-dom",
        page.resolve().as_uri(),
    ]
    # Own process group, so that a hung run is ended with every helper process it started.
    process = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        dom, log = process.communicate(timeout=CHROMIUM_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate()
        pytest.fail(f"chromium did not finish within {CHROMIUM_TIMEOUT_S} s: {command}")
    assert process.returncode == 0, f"chromium exit {process.returncode}:\n{log[-3000:]}"
    assert dom.strip(), f"chromium dumped no DOM:\n{log[-3000:]}"
    messages = [m.group(1) for line in log.splitlines() if (m := CONSOLE_LINE.search(line))]
    return dom, messages


def image_load_states(page: Path, profile: Path) -> tuple[list[dict], list[str]]:
    """[{src, ok}] of every <img> of ``page`` as loaded by Chromium, and console messages."""
    wrapper = page.with_name(f"_image_check_{page.stem}.html")
    wrapper.write_text(WRAPPER_HTML.format(result_id=WRAPPER_RESULT_ID, page=page.name))
    dom, messages = run_chromium(wrapper, profile, "--allow-file-access-from-files")
    found = re.search(rf'<pre id="{WRAPPER_RESULT_ID}">(.*?)</pre>', dom, re.S)
    assert found, f"wrapper result missing from DOM:\n{dom[:2000]}"
    text = html.unescape(found.group(1))
    assert text != "pending", "the page in the iframe never finished loading"
    result = json.loads(text)
    assert isinstance(result, list), f"wrapper could not read the page: {result}"
    return result, messages


def page_layout(page: Path, profile: Path, width: int) -> dict:
    """The layout of ``page`` in a window ``width`` px wide (see LAYOUT_WRAPPER_HTML)."""
    wrapper = page.with_name(f"_layout_check_{page.stem}_{width}.html")
    wrapper.write_text(
        LAYOUT_WRAPPER_HTML.format(result_id=WRAPPER_RESULT_ID, page=page.name, width=width)
    )
    dom, messages = run_chromium(
        wrapper, profile, "--allow-file-access-from-files", f"--window-size={width + 100},1000"
    )
    assert messages == [], f"console messages: {messages}"
    found = re.search(rf'<pre id="{WRAPPER_RESULT_ID}">(.*?)</pre>', dom, re.S)
    assert found, f"wrapper result missing from DOM:\n{dom[:2000]}"
    text = html.unescape(found.group(1))
    assert text != "pending", "the page in the iframe never finished loading"
    layout = json.loads(text)
    assert "error" not in layout, f"wrapper could not read the page: {layout}"
    return layout


def layout_problems(page: Path, layout: dict, width: int) -> list[str]:
    """What is wrong with ``layout`` at ``width``: content wider than the window (the page
    scrolls sideways), a window wider than ``width`` (not measured where asked), a
    missing or broken link to a data file."""
    problems = []
    if layout["window"] > width:
        problems.append(f"measured in a {layout['window']} px window, not {width} px")
    if layout["content"] > layout["window"]:
        problems.append(f"content {layout['content']} px wide in a {layout['window']} px window")
    for name in DATA_LINKS:
        if name not in layout["links"]:
            problems.append(f"no link to {name}")
        elif not (page.parent / name).is_file():
            problems.append(f"link to {name}, which does not exist")
    return problems


class _ImgCounter(HTMLParser):
    def __init__(self):
        super().__init__()
        self.srcs = []

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.srcs.append(dict(attrs).get("src"))


def _img_srcs(page: Path) -> list[str]:
    counter = _ImgCounter()
    counter.feed(page.read_text())
    return counter.srcs


@pytest.fixture(scope="module")
def report(report_dir) -> Path:
    return report_dir / "report.html"


@pytest.mark.slow
def test_report_renders_without_console_errors(report, tmp_path):
    screenshot = tmp_path / "report.png"
    dom, messages = run_chromium(
        report, tmp_path / "profile", "--window-size=1280,2000", f"--screenshot={screenshot}"
    )
    assert messages == [], f"console messages: {messages}"
    assert "<title>phrt sweep: error against run time</title>" in dom
    # Four tables per stage (sweep_tables.TABLES), two stages.
    assert dom.count("<table>") == 8 and "heu1@20000rays" in dom
    # The page was laid out and painted: the screenshot is the window size, not blank.
    image = oiio.ImageInput.open(str(screenshot))
    assert image is not None, f"no screenshot: {oiio.geterror()}"
    spec, pixels = image.spec(), image.read_image(oiio.UINT8)
    image.close()
    assert (spec.width, spec.height) == (1280, 2000)
    assert pixels.std() > 10.0, f"screenshot looks blank: {screenshot}"


@pytest.mark.slow
def test_every_report_image_loads(report, tmp_path):
    states, messages = image_load_states(report, tmp_path / "profile")
    assert messages == [], f"console messages: {messages}"
    srcs = _img_srcs(report)
    assert len(srcs) >= 10  # plots, timelines, previews, FLIP maps
    assert [s["src"] for s in states] == srcs
    failed = [s["src"] for s in states if not s["ok"]]
    assert failed == [], f"images that did not load: {failed}"


@pytest.mark.slow
@pytest.mark.parametrize("width", LAPTOP_WIDTHS)
def test_report_fits_a_laptop_screen_and_links_its_csvs(report, tmp_path, width):
    """At a laptop's window width the page never scrolls sideways and links its CSVs; at
    1280 px every table also fits its own box (config first, no sideways scroll inside)."""
    layout = page_layout(report, tmp_path / "profile", width)
    assert layout_problems(report, layout, width) == []
    # Four tables per stage (sweep_tables.TABLES), two stages.
    assert len(layout["tables"]) == 8
    if width == max(LAPTOP_WIDTHS):
        wide = [t for t in layout["tables"] if t["content"] > t["box"]]
        assert wide == [], f"tables wider than their box at {width} px: {wide}"


@pytest.mark.slow
def test_checks_detect_planted_faults(report, tmp_path):
    """A page with a console error, an uncaught exception and a missing image fails both;
    a page wider than the window and without CSV links fails the layout check."""
    bad = report.with_name("planted_faults.html")
    bad.write_text(
        "<!DOCTYPE html><html><head><title>bad</title></head><body>"
        '<img src="error_vs_time.png"><img src="no_such_image.png">'
        '<script>console.error("planted console error"); '
        'throw new Error("planted exception");</script></body></html>'
    )
    _dom, messages = run_chromium(bad, tmp_path / "profile")
    assert any("planted console error" in m for m in messages), messages
    assert any("planted exception" in m for m in messages), messages

    states, _messages = image_load_states(bad, tmp_path / "profile")
    assert {s["src"]: s["ok"] for s in states} == {
        "error_vs_time.png": True,
        "no_such_image.png": False,
    }

    wide = report.with_name("planted_wide.html")
    wide.write_text(
        '<!DOCTYPE html><html><head><title>wide</title></head><body>'
        '<div style="width: 2000px">a table too wide</div>'
        '<a href="sweep.csv">sweep.csv</a><a href="elsewhere.csv">summary</a></body></html>'
    )
    problems = layout_problems(wide, page_layout(wide, tmp_path / "profile", 1280), 1280)
    assert any(p.startswith("content ") and "px wide in a" in p for p in problems), problems
    assert "no link to summary.csv" in problems, problems
