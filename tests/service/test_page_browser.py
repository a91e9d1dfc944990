"""The page at ``/``, ``/docs`` and ``/redoc`` in a real headless Chromium (Debian's ``chromium`` and
``chromium-driver``, which ``make test`` installs) against the main uvicorn server on 127.0.0.1.

Skips only when the browser or its driver is not installed. Selenium is given both paths, so Selenium
Manager never runs (nothing is downloaded).
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import plyfile
import pytest
from api_server import LIMITED, limited_server, synthetic_pair
from moved_files import coloured_ply

from service.pointcloud_io import read_points, write_points

SOURCE_RGB = (255, 140, 0)  # = COLORS in service/web/page.js
TARGET_RGB = (30, 144, 255)
MIN_PIXELS = 100  # of each cloud's colour in the view (700 points, 2x2 pixels each)
WAIT_S = 20


def _find(env: str, *names: str) -> str | None:
    if os.environ.get(env):
        return os.environ[env]
    for name in names:
        path = shutil.which(name) or (name if Path(name).is_file() else None)
        if path:
            return path
    return None


CHROMIUM = _find("MFGNET_CHROMIUM", "chromium", "chromium-browser", "google-chrome")
CHROMEDRIVER = _find("MFGNET_CHROMEDRIVER", "chromedriver", "/usr/lib/chromium/chromedriver")
# axe-core's browser bundle: `make install-browser` puts it in the venv (npm); MFGNET_AXE_JS names another copy
AXE_JS = Path(os.environ.get("MFGNET_AXE_JS") or Path(sys.prefix) / "node_modules" / "axe-core" / "axe.min.js")

pytestmark = pytest.mark.skipif(
    CHROMIUM is None or CHROMEDRIVER is None,
    reason="Chromium or chromedriver not installed (apt-get install chromium chromium-driver; `make test` does it)",
)


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    downloads = tmp_path_factory.mktemp("downloads")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in (
        "--headless=new",
        "--no-sandbox",  # CI runs as root
        "--disable-dev-shm-usage",
        "--window-size=1400,1000",
        "--use-angle=swiftshader",  # WebGL on the CPU where there is no GPU
        "--enable-unsafe-swiftshader",
        "--no-first-run",
        "--disable-background-networking",
    ):
        options.add_argument(arg)
    # network events: external_requests(); console messages and uncaught errors: console_errors()
    options.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    options.add_experimental_option("prefs", {"download.default_directory": str(downloads)})
    driver = webdriver.Chrome(options=options, service=Service(executable_path=CHROMEDRIVER))
    driver.set_page_load_timeout(WAIT_S)
    driver.downloads = downloads
    yield driver
    driver.quit()


def wait_for(driver, script: str, what: str, timeout: float = WAIT_S):
    """Until the JavaScript expression ``script`` is truthy; its value."""
    from selenium.webdriver.support.ui import WebDriverWait

    try:
        return WebDriverWait(driver, timeout, poll_frequency=0.05).until(lambda d: d.execute_script(f"return {script}"))
    except Exception as exc:
        status = driver.execute_script("const s = document.getElementById('status'); return s && s.textContent")
        raise AssertionError(f"timed out waiting for {what}; page status: {status!r}") from exc


def colour_pixels(png: bytes, rgb: tuple[int, int, int], tolerance: int = 12) -> int:
    from PIL import Image

    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)  # [H, W, 3]
    return int((np.abs(pixels - np.array(rgb)) <= tolerance).all(axis=-1).sum())


def external_requests(driver, server_url: str) -> list[str]:
    """URLs the browser sent to any host but the server since the last call (from Chrome's network log);
    requests the page's Content-Security-Policy blocked before they left the browser are not counted."""
    sent, blocked = {}, set()
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        params = message.get("params", {})
        if message["method"] == "Network.requestWillBeSent":
            sent[params["requestId"]] = params["request"]["url"]
        elif message["method"] == "Network.loadingFailed" and params.get("blockedReason"):
            blocked.add(params["requestId"])
    return [
        url
        for rid, url in sent.items()
        if rid not in blocked and re.match(r"(https?|wss?)://", url) and not url.startswith(server_url + "/")
    ]


def console_errors(driver) -> list[str]:
    """Errors the page's console showed since the last call: uncaught exceptions, ``console.error`` and failed loads
    (a 4xx answer to the page's own request is one too)."""
    return [entry["message"] for entry in driver.get_log("browser") if entry["level"] == "SEVERE"]


def register(driver, server_url: str, source: Path, target: Path, key: str | None = None) -> str:
    """Load the page, choose both files (and the API key), press Register; the final state (done / error)."""
    driver.get(f"{server_url}/")
    if key is not None:
        driver.find_element("id", "api_key").send_keys(key)
    driver.find_element("id", "source").send_keys(str(source))
    driver.find_element("id", "target").send_keys(str(target))
    driver.find_element("id", "register").click()
    return wait_for(
        driver, "document.body.dataset.state !== 'running' && document.body.dataset.state", "the registration"
    )


def register_a_broken_source(driver, folder: Path) -> str:
    """On the loaded page, choose a truncated PLY (``folder/broken.ply``) as the source and press Register again;
    the final state (error, for a 422)."""
    corrupt = folder / "broken.ply"
    corrupt.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n")
    driver.find_element("id", "source").send_keys(str(corrupt))
    driver.find_element("id", "register").click()
    return wait_for(
        driver, "document.body.dataset.state !== 'running' && document.body.dataset.state", "the failed registration"
    )


def downloaded(driver, name: str) -> Path:
    """Press "Download aligned source" and wait for the status to say so and for ``name`` to be complete in the
    download folder; its path."""
    driver.find_element("id", "download").click()
    wait_for(driver, "document.getElementById('status').textContent.includes('downloaded')", "the download")
    download = driver.downloads / name
    for _ in range(100):
        if download.is_file() and download.stat().st_size > 0 and not list(driver.downloads.glob("*.crdownload")):
            break
        time.sleep(0.05)
    return download


def status_text(driver) -> str:
    return driver.execute_script("return document.getElementById('status').textContent")


def shown_transform(driver) -> np.ndarray:
    return np.array(driver.find_element("id", "transform").text.split(), dtype=float).reshape(4, 4)  # every digit


def test_page_registers_with_no_console_errors(browser, server, ply_files):
    """First in the module, so the browser is fresh: Chrome asks a new page's server for /favicon.ico, and that
    404 was an error in every user's console."""
    _, source_file, target_file = ply_files
    console_errors(browser)
    assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
    assert console_errors(browser) == []
    assert browser.execute_script("return document.querySelector('link[rel=icon]').href") == "data:,"
    for button in ("show-before", "show-after", "reset-view"):
        browser.find_element("id", button).click()
    assert console_errors(browser) == []


def test_the_before_and_after_toggles_say_which_is_pressed(browser, server, ply_files):
    """Before / After showed their state only as a colour: a screen reader heard two plain buttons."""
    _, source_file, target_file = ply_files
    assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
    for button, after in (("show-before", False), ("show-after", True)):
        browser.find_element("id", button).click()
        pressed = [browser.find_element("id", b).get_attribute("aria-pressed") for b in ("show-before", "show-after")]
        assert pressed == [str(not after).lower(), str(after).lower()]


@pytest.fixture(scope="module")
def ply_files(tmp_path_factory):
    """A seeded partial-to-partial pair written as binary PLY by the project's writer."""
    pair = synthetic_pair(seed=3)
    folder = tmp_path_factory.mktemp("clouds")
    write_points(folder / "scan_ж.ply", pair.source)  # a name beyond ASCII: the download keeps it
    write_points(folder / "scan_b.ply", pair.target)
    return pair, folder / "scan_ж.ply", folder / "scan_b.ply"


@pytest.mark.parametrize("renderer", ["webgl", "2d"])
def test_page_registers_two_ply_files_and_draws_both_clouds(browser, server, ply_files, renderer, tmp_path):
    pair, source_file, target_file = ply_files
    external_requests(browser, server.url)  # drop earlier tests' events
    browser.get(f"{server.url}/?renderer={renderer}")
    assert browser.title == "MFGNet registration"
    shown = browser.execute_script("return document.body.dataset.renderer")
    if renderer == "2d":
        assert shown == "2D canvas"
    else:  # WebGL whenever the browser has it (SwiftShader gives it without a GPU), else the 2D fallback
        has_webgl = browser.execute_script("return !!document.createElement('canvas').getContext('webgl')")
        assert shown == ("WebGL" if has_webgl else "2D canvas"), (shown, has_webgl)

    browser.find_element("id", "source").send_keys(str(source_file))
    browser.find_element("id", "target").send_keys(str(target_file))
    browser.find_element("id", "register").click()
    state = wait_for(
        browser,
        "['done', 'error'].includes(document.body.dataset.state) && document.body.dataset.state",
        "the registration",
    )
    assert state == "done", browser.find_element("id", "status").text

    result = browser.find_element("id", "result")
    assert result.is_displayed()
    text = result.text
    assert "inlier ratio" in text and "total" in text and "reliable" in text
    rows = [[float(v) for v in line.split()] for line in browser.find_element("id", "transform").text.splitlines()]
    T = np.array(rows)  # [4, 4] as shown (5 significant digits)
    assert T.shape == (4, 4)
    assert np.abs(T[:3, :3] - pair.rotation).max() < 0.05  # the seeded pair's true pose
    assert np.abs(T[:3, 3] - pair.translation).max() < 0.05
    assert f"source {len(pair.source)} of {len(pair.source)} points" in browser.find_element("id", "shown").text

    browser.execute_script("return new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    canvas = browser.find_element("id", "canvas")
    png = canvas.screenshot_as_png
    (tmp_path / f"view-{renderer}.png").write_bytes(png)
    browser.save_screenshot(str(tmp_path / f"page-{renderer}.png"))
    source_px, target_px = colour_pixels(png, SOURCE_RGB), colour_pixels(png, TARGET_RGB)
    assert source_px >= MIN_PIXELS and target_px >= MIN_PIXELS, (source_px, target_px)

    browser.find_element("id", "show-before").click()  # the source as uploaded: still both colours
    browser.execute_script("return new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    before = canvas.screenshot_as_png
    assert colour_pixels(before, SOURCE_RGB) >= MIN_PIXELS and colour_pixels(before, TARGET_RGB) >= MIN_PIXELS
    assert before != png
    from selenium.webdriver.common.action_chains import ActionChains

    ActionChains(browser).move_to_element(canvas).click_and_hold().move_by_offset(80, 30).release().perform()
    browser.execute_script("return new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    assert canvas.screenshot_as_png != before  # dragging orbits the camera
    assert external_requests(browser, server.url) == []


def test_page_downloads_the_aligned_source_as_ply(browser, server, ply_files):
    pair, source_file, target_file = ply_files
    browser.get(f"{server.url}/")
    browser.find_element("id", "source").send_keys(str(source_file))
    browser.find_element("id", "target").send_keys(str(target_file))
    browser.find_element("id", "register").click()
    assert wait_for(browser, "document.body.dataset.state === 'done'", "the registration")
    transform = np.array(browser.find_element("id", "transform").text.split(), dtype=float).reshape(4, 4)
    browser.find_element("id", "download").click()
    target = browser.downloads / "scan_ж_aligned.ply"
    wait_for(browser, "document.getElementById('status').textContent.includes('downloaded')", "the download")
    for _ in range(100):
        if target.is_file() and target.stat().st_size > 0 and not list(browser.downloads.glob("*.crdownload")):
            break
        time.sleep(0.05)
    aligned = read_points(target)  # [N, 3] float32
    assert aligned.shape == pair.source.shape
    expected = pair.source.astype(np.float64) @ transform[:3, :3].T + transform[:3, 3]
    assert np.abs(aligned - expected).max() < 1e-4  # the page shows the pose to 5 significant digits


def test_page_downloads_a_coloured_ply_mesh_as_itself_moved(browser, server, tmp_path):
    """The download was x, y, z only: a coloured mesh came back without its colours, normals and faces."""
    pair = synthetic_pair(seed=3)
    source_file, target_file = tmp_path / "mesh.ply", tmp_path / "target.ply"
    vertex = coloured_ply(source_file, pair.source)
    write_points(target_file, pair.target)
    assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
    download = downloaded(browser, "mesh_aligned.ply")  # the name the answer's Content-Disposition gives
    written = plyfile.PlyData.read(str(download))
    rows = written["vertex"].data
    for name in ("red", "green", "blue", "quality"):
        assert rows[name].tobytes() == vertex[name].tobytes(), name
    assert len(written["face"].data) == 200
    T = shown_transform(browser)
    expected = pair.source.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    assert np.abs(np.stack([rows[a] for a in "xyz"], axis=1) - expected).max() < 1e-4


def test_the_pose_shown_is_the_answers_to_the_last_digit_for_a_map_in_utm(browser, server, ply_files, tmp_path):
    """A local scan registered into a map in UTM coordinates: the matrix shown is the server's (5 significant digits
    had moved the translation by metres, and every point by tens of metres)."""
    pair, source_file, _ = ply_files
    target_file = tmp_path / "map.npy"
    np.save(target_file, pair.target.astype(np.float64) + np.array([512_345.25, 5_412_345.5, 229.75]))
    assert register(browser, server.url, source_file, target_file) == "done"
    with open(source_file, "rb") as source, open(target_file, "rb") as target:
        answer = httpx.post(f"{server.url}/v1/register", files={"source": source, "target": target}, timeout=60).json()
    np.testing.assert_array_equal(shown_transform(browser), np.asarray(answer["transform"]))


def test_a_scan_registered_into_a_map_in_utm_is_drawn_with_the_map(browser, server, ply_files, tmp_path):
    """A local scan registered into a map in UTM coordinates: "After" frames the two clouds where the pose puts them,
    both drawn (the view had stayed on the uploaded clouds' box, thousands of kilometres across: one pixel)."""
    pair, source_file, _ = ply_files
    target_file = tmp_path / "map.npy"
    np.save(target_file, pair.target.astype(np.float64) + np.array([512_345.25, 5_412_345.5, 229.75]))
    assert register(browser, server.url, source_file, target_file) == "done"
    browser.execute_script("return new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    png = browser.find_element("id", "canvas").screenshot_as_png
    source_px, target_px = colour_pixels(png, SOURCE_RGB), colour_pixels(png, TARGET_RGB)
    assert source_px >= MIN_PIXELS and target_px >= MIN_PIXELS, (source_px, target_px)


@pytest.mark.parametrize(
    ("path", "ready"),
    [
        ("/docs", "document.querySelector('.swagger-ui .info .title')"),
        ("/redoc", "document.querySelector('.api-info h1, h1')"),
    ],
)
def test_api_docs_load_with_no_external_requests(browser, server, path, ready):
    page = httpx.get(server.url + path, timeout=10).text
    hosts = set(re.findall(r"https?://[^\s'\"<>]+", page))
    assert hosts == set(), hosts  # every asset URL is relative to this server
    external_requests(browser, server.url)
    console_errors(browser)
    browser.get(server.url + path)
    wait_for(browser, ready, f"{path} to render")
    title = wait_for(browser, f"{ready} && {ready}.textContent", f"{path} title")
    assert "MFGNet registration service" in title
    assert external_requests(browser, server.url) == []
    time.sleep(0.5)  # ReDoc's sidebar draws its logo after the title
    assert console_errors(browser) == []  # ReDoc's vendor logo, blocked by the policy, was a SEVERE line each visit


def test_every_control_is_labelled_and_reached_by_tab_in_order(browser, server):
    browser.get(f"{server.url}/")
    unlabelled = browser.execute_script(
        "return [...document.querySelectorAll('input, select, button')].filter(e => !(e.labels && e.labels.length)"
        " && !e.getAttribute('aria-label') && !e.textContent.trim()).map(e => e.id)"
    )
    assert unlabelled == []
    assert browser.find_element("id", "status").get_attribute("role") == "status"  # a polite live region
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    reached = []
    for _ in range(12):
        ActionChains(browser).send_keys(Keys.TAB).perform()
        reached.append(browser.execute_script("return document.activeElement.id"))
    order = ["source", "target", "refine", "rotation_search", "drop_isolated", "api_key", "register"]
    assert [i for i in reached if i in order][: len(order)] == order, reached


VIEW_JS = "JSON.parse(document.getElementById('canvas').dataset.view)"



# -- the pose's angles, a changed choice, the download's bytes, an unsendable key, the up axis ------------------------
def test_the_pose_is_shown_as_yaw_pitch_roll_and_extrinsic_zyx_to_9_digits(browser, server, ply_files):
    """The page showed only `euler_zyx_deg` (extrinsic, R = Rx(c) Ry(b) Rz(a)), labelled "Euler z-y-x", to 5 digits:
    read as yaw, pitch, roll (R = Rz Ry Rx) a 30 / 20 / 10 deg turn was 11 deg off in roll."""
    _, source_file, target_file = ply_files
    assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
    with open(source_file, "rb") as source, open(target_file, "rb") as target:
        answer = httpx.post(f"{server.url}/v1/register", files={"source": source, "target": target}, timeout=60).json()
    for element, key in (("ypr", "yaw_pitch_roll_deg"), ("euler", "euler_zyx_deg")):
        shown = [float(v) for v in browser.find_element("id", element).text.split(", ")]
        np.testing.assert_allclose(shown, answer[key], rtol=1e-8, atol=1e-6)
    assert "R = Rz(yaw) Ry(pitch) Rx(roll)" in browser.find_element("id", "result").text


def test_choosing_another_file_clears_the_last_pairs_result(browser, server, ply_files, tmp_path):
    """A new file under the old pair's pose, view and Download: the download moved the old source by the old pose."""
    pair, source_file, target_file = ply_files
    assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
    other = tmp_path / "other.ply"
    write_points(other, pair.target)
    browser.find_element("id", "source").send_keys(str(other))
    assert not browser.find_element("id", "result").is_displayed()
    assert "Files changed: press Register for this pair." in status_text(browser)


def test_the_download_moves_the_bytes_registered_not_the_file_as_it_is_now(browser, server, ply_files, tmp_path):
    """The file was read again at Download: overwritten on disk meanwhile, its new content came back moved by the
    old pose (and in its new format)."""
    pair, _, target_file = ply_files
    source_file = tmp_path / "work.ply"
    write_points(source_file, pair.source)
    assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
    T = shown_transform(browser)
    source_file.write_text("1 2 3\n4 5 6\n")  # re-exported meanwhile
    download = downloaded(browser, "work_aligned.ply")
    expected = pair.source.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    assert np.abs(read_points(download) - expected).max() < 1e-4


def test_an_api_key_that_cannot_be_sent_names_the_key_field(browser, server, ply_files):
    """fetch() refuses a header value beyond Latin-1 (a pasted em dash): the page said the server did not answer."""
    _, source_file, target_file = ply_files
    assert register(browser, server.url, source_file, target_file, key="abc\u2014def") == "error"
    assert "API key" in status_text(browser) and "No answer from the server" not in status_text(browser)
    assert browser.find_element("id", "api_key").get_attribute("aria-invalid") == "true"


def test_the_view_draws_z_up(browser, server, tmp_path):
    """Point clouds (LAS, E57, maps, LiDAR) are Z-up: a pole along +z was drawn lying down, the ground upright."""
    rng = np.random.default_rng(0)
    pole = rng.uniform([-0.2, -0.2, 0.0], [0.2, 0.2, 4.0], size=(700, 3))  # [N, 3] a tall box along z
    source_file, target_file = tmp_path / "pole_a.ply", tmp_path / "pole_b.ply"
    write_points(source_file, pole)
    write_points(target_file, pole + rng.normal(scale=0.01, size=pole.shape))
    register(browser, server.url, source_file, target_file)
    browser.execute_script("return new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    from PIL import Image

    png = browser.find_element("id", "canvas").screenshot_as_png
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)  # [H, W, 3]
    drawn = (np.abs(pixels - np.array(TARGET_RGB)) <= 12).all(axis=-1)  # [H, W]
    rows, cols = np.flatnonzero(drawn.any(axis=1)), np.flatnonzero(drawn.any(axis=0))
    assert len(rows) and rows[-1] - rows[0] > 2 * (cols[-1] - cols[0])  # taller than wide


def view_state(driver) -> dict[str, float]:
    """The camera the view last drew: ``{"yaw_deg", "pitch_deg", "distance"}`` (``canvas.dataset.view``)."""
    return driver.execute_script(f"return {VIEW_JS}")


def settled_scroll(driver, still_s: float = 0.3) -> int:
    """``window.scrollY`` once it has not moved for ``still_s`` (a smooth scroll, such as Page Down's, runs on after
    its first step)."""
    deadline = time.monotonic() + WAIT_S
    last, since = driver.execute_script("return window.scrollY"), time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.05)
        now = driver.execute_script("return window.scrollY")
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= still_s:
            return now
    raise AssertionError("the page kept scrolling")


def press(driver, *keys: str) -> None:
    """Send keys to the focused element and wait until the view has drawn them."""
    from selenium.webdriver.common.action_chains import ActionChains

    ActionChains(driver).send_keys(*keys).perform()
    driver.execute_script("return new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")


def test_the_view_turns_zooms_and_resets_from_the_keyboard_without_scrolling_the_page(browser, server, ply_files):
    """WCAG 2.1.1: the 3D view turned and zoomed only with a mouse, and Tab never reached it."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.wheel_input import ScrollOrigin
    from selenium.webdriver.common.keys import Keys

    _, source_file, target_file = ply_files
    browser.set_window_size(1400, 700)  # shorter than the page: a key that scrolled it would show
    try:
        assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
        canvas = browser.find_element("id", "canvas")
        assert canvas.get_attribute("role") == "application" and "3D view" in canvas.get_attribute("aria-label")
        keys_hint = browser.find_element("id", canvas.get_attribute("aria-describedby"))
        assert keys_hint.is_displayed()
        for words in ("arrow keys", "+", "-", "Home", "0", "zoom", "reset"):
            assert words in keys_hint.text, keys_hint.text

        browser.execute_script("document.getElementById('reset-view').focus()")
        press(browser, Keys.TAB)  # the view comes next in the tab order, with a visible outline
        assert browser.execute_script("return document.activeElement.id") == "canvas"
        outline = browser.execute_script(
            "const s = getComputedStyle(document.activeElement); return [s.outlineStyle, parseFloat(s.outlineWidth)]"
        )
        assert outline[0] != "none" and outline[1] >= 2, outline
        browser.execute_script("window.scrollTo(0, 60)")
        scroll_y = browser.execute_script("return window.scrollY")
        assert 0 < scroll_y < browser.execute_script("return document.documentElement.scrollHeight - innerHeight")

        start = view_state(browser)
        before = canvas.screenshot_as_png
        steps = [  # key, the change it makes to the view
            (Keys.ARROW_LEFT, {"yaw_deg": -5}),
            (Keys.ARROW_RIGHT, {"yaw_deg": 0}),
            (Keys.ARROW_RIGHT, {"yaw_deg": 5}),
            (Keys.ARROW_UP, {"yaw_deg": 5, "pitch_deg": -5}),
            (Keys.ARROW_DOWN, {"yaw_deg": 5, "pitch_deg": 0}),
            (Keys.ARROW_DOWN, {"yaw_deg": 5, "pitch_deg": 5}),
        ]
        for key, change in steps:
            press(browser, key)
            now = view_state(browser)
            for name in ("yaw_deg", "pitch_deg"):
                assert now[name] == pytest.approx(start[name] + change.get(name, 0), abs=0.02), (key, now, start)
            assert now["distance"] == start["distance"]
            assert browser.execute_script("return window.scrollY") == scroll_y, key
        assert canvas.screenshot_as_png != before  # the drawing follows the camera
        for key, factor in (("+", 1 / 1.2), ("=", 1 / 1.44), ("-", 1 / 1.2)):
            press(browser, key)
            assert view_state(browser)["distance"] == pytest.approx(start["distance"] * factor, rel=1e-4), key
        for key in (Keys.HOME, "0"):
            press(browser, Keys.ARROW_LEFT, "+")
            assert view_state(browser) != start
            press(browser, key)
            assert view_state(browser) == start, key
            assert browser.execute_script("return window.scrollY") == scroll_y, key

        ActionChains(browser).key_down(Keys.CONTROL).send_keys(Keys.ARROW_LEFT, "0").key_up(Keys.CONTROL).perform()
        assert view_state(browser) == start  # browser shortcuts are the browser's
        press(browser, Keys.PAGE_DOWN)  # a key the view does not handle keeps its default (a smooth scroll)
        wait_for(browser, f"window.scrollY > {scroll_y}", "Page Down to scroll the page")
        assert view_state(browser) == start

        api_key = browser.find_element("id", "api_key")  # keys typed in a form field leave the view alone
        settled_scroll(browser)  # Page Down's smooth scroll has ended: the click lands on the field
        api_key.click()
        for key in (Keys.ARROW_LEFT, Keys.ARROW_DOWN, "+", "-", "0", Keys.HOME):  # one at a time, each handled
            press(browser, key)
        assert api_key.get_attribute("value") == "+-0"
        assert view_state(browser) == start

        scroll_y = settled_scroll(browser)  # the mouse works as before (Page Down's smooth scroll has ended)
        ActionChains(browser).scroll_from_origin(ScrollOrigin.from_element(canvas), 0, 100).perform()
        wait_for(browser, f"{VIEW_JS}.distance !== {start['distance']}", "the wheel to zoom")
        assert view_state(browser)["distance"] == pytest.approx(start["distance"] * np.exp(0.1), rel=1e-4)
        assert browser.execute_script("return window.scrollY") == scroll_y
        ActionChains(browser).move_to_element(canvas).click_and_hold().move_by_offset(50, 0).release().perform()
        assert view_state(browser)["yaw_deg"] == pytest.approx(start["yaw_deg"] + np.degrees(0.5), abs=0.02)
    finally:
        browser.set_window_size(1400, 1000)


def test_a_failed_registration_shows_the_servers_message_and_hides_the_last_result(
    browser, server, ply_files, tmp_path
):
    """After a good pair, a bad file's error showed under the good pair's pose, view and download button."""
    _, source_file, target_file = ply_files
    assert register(browser, server.url, source_file, target_file) == "done"
    assert register_a_broken_source(browser, tmp_path) == "error"
    status = status_text(browser)
    assert status.startswith("422: ") and "broken.ply" in status and "undefined" not in status, status
    assert browser.execute_script("return document.getElementById('result').hidden")
    assert browser.find_element("id", "shown").text == ""
    assert not browser.find_element("id", "register").get_attribute("disabled")
    browser.find_element("id", "source").send_keys(str(source_file))  # the user picks the right file: it registers
    browser.find_element("id", "register").click()
    assert (
        wait_for(
            browser,
            "document.body.dataset.state !== 'running' && document.body.dataset.state",
            "the registration after an error",
        )
        == "done"
    ), status_text(browser)
    assert not browser.execute_script("return document.getElementById('result').hidden")


def test_a_slow_answer_shows_the_time_and_can_be_cancelled_and_no_answer_is_explained(browser, server, ply_files):
    """A slow answer showed a still "Uploading and registering…" with Register disabled and no way out but reloading;
    an unreachable server showed fetch's bare "Failed to fetch"."""
    _, source_file, target_file = ply_files
    browser.get(f"{server.url}/")
    browser.find_element("id", "source").send_keys(str(source_file))
    browser.find_element("id", "target").send_keys(str(target_file))
    slow = {"offline": False, "latency": 4000, "downloadThroughput": -1, "uploadThroughput": -1}
    browser.execute_cdp_cmd("Network.enable", {})
    try:
        browser.execute_cdp_cmd("Network.emulateNetworkConditions", slow)
        browser.find_element("id", "register").click()
        wait_for(browser, "document.getElementById('elapsed').textContent.includes('1 s')", "the elapsed time")
        assert browser.find_element("id", "cancel").is_displayed()
        browser.find_element("id", "cancel").click()
        assert (
            wait_for(browser, "document.body.dataset.state !== 'running' && document.body.dataset.state", "the cancel")
            == "cancelled"
        )
        assert status_text(browser) == "Cancelled."
        assert not browser.find_element("id", "cancel").is_displayed()
        assert not browser.find_element("id", "register").get_attribute("disabled")

        browser.execute_cdp_cmd("Network.emulateNetworkConditions", {**slow, "offline": True, "latency": 0})
        browser.find_element("id", "register").click()
        assert (
            wait_for(
                browser,
                "document.body.dataset.state !== 'running' && document.body.dataset.state",
                "the unreachable server",
            )
            == "error"
        )
        assert status_text(browser).startswith("No answer from the server"), status_text(browser)
    finally:
        browser.execute_cdp_cmd("Network.emulateNetworkConditions", {**slow, "latency": 0})
        browser.execute_cdp_cmd("Network.disable", {})
    browser.find_element("id", "register").click()  # the server answers again: so does the page
    assert (
        wait_for(
            browser,
            "document.body.dataset.state !== 'running' && document.body.dataset.state",
            "the registration after a cancel",
        )
        == "done"
    ), status_text(browser)


def test_with_an_api_key_the_page_explains_a_401_and_matches_the_json_api(browser, tmp_path):
    """The 401 said "send 'Authorization: Bearer <key>'", which a page user cannot; the key's field is named and
    focused. With the key: the pose and reliability the JSON API answers, the download, and a too large file's 413."""
    limited = limited_server()  # MFGNET_API_KEY and 400 points per file
    pair = synthetic_pair(seed=3, keep=300)
    source_file, target_file = tmp_path / "small_src.ply", tmp_path / "small_tgt.ply"
    write_points(source_file, pair.source)
    write_points(target_file, pair.target)
    assert register(browser, limited.url, source_file, target_file) == "error"
    status = status_text(browser)
    assert status.startswith("401: missing or invalid API key") and '"API key" field' in status, status
    assert browser.execute_script("return document.activeElement.id") == "api_key"
    api_key = browser.find_element("id", "api_key")  # the field in error, described by the message (WCAG 3.3.1)
    assert (api_key.get_attribute("aria-invalid"), api_key.get_attribute("aria-describedby")) == ("true", "status")
    api_key.send_keys("x")  # typing a key clears the mark
    assert (api_key.get_attribute("aria-invalid"), api_key.get_attribute("aria-describedby")) == (None, None)

    key = LIMITED["api_key"]
    assert register(browser, limited.url, source_file, target_file, key=key) == "done", status_text(browser)
    with limited.client(headers={"Authorization": f"Bearer {key}"}) as client:
        files = {
            "source": (source_file.name, source_file.read_bytes()),
            "target": (target_file.name, target_file.read_bytes()),
        }
        answer = client.post("/v1/register", files=files, data={"drop_isolated": "true"})  # the page's options
    assert answer.status_code == 200, answer.text
    api = answer.json()
    T = np.array(api["transform"])
    np.testing.assert_allclose(shown_transform(browser), T, rtol=1e-4, atol=1e-9)
    reliable = api["quality"]["reliable"]
    assert browser.find_element("id", "reliable").text == ("(reliable)" if reliable else "(not reliable)")

    download = downloaded(browser, "small_src_aligned.ply")  # with the key, as the registration
    expected = pair.source.astype(np.float64) @ T[:3, :3].T + T[:3, 3]  # the API's pose at full precision
    assert np.abs(read_points(download) - expected).max() < 1e-5

    big = tmp_path / "big.npy"
    np.save(big, np.tile(pair.source, (2, 1)))  # 600 points
    browser.find_element("id", "source").send_keys(str(big))
    browser.find_element("id", "register").click()
    assert (
        wait_for(
            browser, "document.body.dataset.state !== 'running' && document.body.dataset.state", "the too large file"
        )
        == "error"
    )
    status = status_text(browser)
    assert status.startswith("413: ") and "600 points" in status and "MFGNET_MAX_FILE_POINTS" in status, status


def narrow_screen(driver, width: int, height: int, scale: float = 1) -> None:
    """Show the page ``width`` x ``height`` CSS px large at ``scale`` device px per CSS px (what browser zoom does to
    the layout), until ``Emulation.clearDeviceMetricsOverride``."""
    driver.execute_cdp_cmd(
        "Emulation.setDeviceMetricsOverride",
        {"width": width, "height": height, "deviceScaleFactor": scale, "mobile": False},
    )


@pytest.mark.parametrize(
    ("width", "height", "scale"),
    [
        (360, 740, 1),  # a phone
        (320, 640, 1),  # WCAG 1.4.10 (reflow): 1280 CSS px at 400% zoom
        (640, 500, 2),  # 1280 at 200% zoom
    ],
)
def test_a_narrow_screen_shows_the_page_without_sideways_scrolling(browser, server, ply_files, width, height, scale):
    """Nothing but the pose matrix reaches past the screen's edge, and where the matrix scrolls sideways it is a tab
    stop: keys scroll only what has the focus, so at 320 px a keyboard user could not read its right-hand column."""
    _, source_file, target_file = ply_files
    narrow_screen(browser, width, height, scale)
    try:
        assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
        assert browser.execute_script("return innerWidth") == width
        assert browser.execute_script("return document.documentElement.scrollWidth") <= width
        past_the_edge = browser.execute_script(
            "return [...document.querySelectorAll('body *')].filter(e => e.getBoundingClientRect().right > innerWidth)"
            ".map(e => e.id || e.tagName)"
        )
        assert past_the_edge == []
        assert browser.find_element("id", "canvas").size["width"] <= width
        scrolls, tab_stop = browser.execute_script(
            "const t = document.getElementById('transform'); return [t.scrollWidth > t.clientWidth, t.tabIndex >= 0]"
        )
        assert tab_stop or not scrolls, "the pose matrix scrolls sideways but the keyboard cannot reach it"
    finally:
        browser.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})


def focus_is_shown(driver, element) -> bool:
    """Whether the focused ``element`` and the 6 px around it look different once it loses the focus (an outline,
    a ring, a colour change: any visible focus indicator, WCAG 2.4.7). Leaves the focus where it was."""
    x, y, width, height = driver.execute_script(
        "const r = arguments[0].getBoundingClientRect(); return [r.left + scrollX, r.top + scrollY, r.width, r.height]",
        element,
    )
    clip = {"x": x - 6, "y": y - 6, "width": width + 12, "height": height + 12, "scale": 1}

    def shot() -> str:
        return driver.execute_cdp_cmd("Page.captureScreenshot", {"format": "png", "clip": clip})["data"]

    focused = shot()
    driver.execute_script("arguments[0].blur()", element)
    blurred = shot()
    driver.execute_script("arguments[0].focus()", element)
    return focused != blurred


def test_the_page_registers_from_the_keyboard_alone_with_the_focus_shown_and_the_result_announced(
    browser, server, ply_files
):
    """WCAG 2.1.1, 2.4.3, 2.4.7 and 4.1.3 end to end: Tab reaches both file inputs, the options and Register, each
    with a visible focus indicator; keys set the options; Enter on Register registers (Enter again while it runs
    sends nothing more). Register was disabled while a pair ran, and a disabled button drops the focus to the page's
    start; the status line, the live region, said only "Done in N ms." and not what came."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    _, source_file, target_file = ply_files
    browser.get(f"{server.url}/")
    controls = ["source", "target", "refine", "rotation_search", "drop_isolated", "api_key", "register"]
    keys = {"refine": [Keys.ARROW_DOWN, Keys.ARROW_DOWN], "drop_isolated": [Keys.SPACE]}  # icp; keep isolated points
    reached, unshown = [], []
    for _ in range(12):
        press(browser, Keys.TAB)
        focused = browser.switch_to.active_element
        name = focused.get_attribute("id")
        reached.append(name)
        if name not in controls:
            continue
        if not focus_is_shown(browser, focused):
            unshown.append(name)
        if name in ("source", "target"):  # what a file chooser opened by Space would give
            focused.send_keys(str(source_file if name == "source" else target_file))
        press(browser, *keys.get(name, []))
        if name == "register":
            break
    assert [i for i in reached if i in controls] == controls, reached
    assert unshown == [], f"no visible focus indicator on {unshown}"
    assert browser.execute_script(
        "return [document.getElementById('refine').value, document.getElementById('drop_isolated').checked]"
    ) == ["icp", False]

    press(browser, Keys.ENTER, Keys.ENTER)
    state = wait_for(
        browser, "document.body.dataset.state !== 'running' && document.body.dataset.state", "the registration"
    )
    assert state == "done", status_text(browser)
    sent = "performance.getEntriesByType('resource').filter(e => e.name.endsWith('/v1/register/view')).length"
    assert browser.execute_script(f"return {sent}") == 1
    assert browser.execute_script("return document.activeElement.id") == "register", "the focus was lost"
    status = browser.find_element("id", "status")
    assert status.get_attribute("role") == "status"
    reliable = browser.find_element("id", "reliable").text  # "(reliable)" or "(not reliable)"
    assert re.fullmatch(rf"Done in \d+ ms: {reliable[1:-1]}, (no|\d+) warnings?\.", status.text), status.text

    after = []
    for _ in range(10):  # on from Register: the view, the pose matrix, the download
        ActionChains(browser).send_keys(Keys.TAB).perform()
        after.append(browser.execute_script("return document.activeElement.id"))
        if after[-1] == "download":
            break
    assert [i for i in after if i in ("canvas", "transform", "download")] == ["canvas", "transform", "download"], after


# the WCAG 2.1 A and AA rules, and axe's best practices (landmarks, heading order, one main, ...)
AXE_TAGS = ["wcag2a", "wcag2aa", "wcag21a", "wcag21aa", "best-practice"]


def axe_violations(driver) -> list[str]:
    """axe-core's violations of ``AXE_TAGS`` on the page as it is now: ``"rule-id: help (target, ...)"`` each."""
    if not driver.execute_script("return !!window.axe"):
        driver.execute_script(AXE_JS.read_text(encoding="utf-8"))
    return driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "axe.run(document, {runOnly: {type: 'tag', values: arguments[0]}, resultTypes: ['violations']})"
        ".then(r => done(r.violations.map(v => `${v.id}: ${v.help} (` +"
        " v.nodes.map(n => n.target.join(' ')).join(', ') + ')')), e => done(['axe failed: ' + e]))",
        AXE_TAGS,
    )


def skip_without_axe() -> None:
    if not AXE_JS.is_file():
        pytest.skip(f"axe-core not installed ({AXE_JS}; `make install-browser` installs it with npm)")


def test_axe_finds_no_violations_initially_while_running_with_a_result_and_with_an_error(
    browser, server, ply_files, tmp_path
):
    """axe-core's WCAG 2.1 A/AA rules and best practices on the page as loaded, while a registration runs, with a
    registration's view and result shown, and with a failed registration's error shown. The renderer's name (#777 on
    white) failed color-contrast."""
    skip_without_axe()
    _, source_file, target_file = ply_files
    browser.set_script_timeout(WAIT_S)
    browser.get(f"{server.url}/")
    found = {"initial": axe_violations(browser)}

    browser.find_element("id", "source").send_keys(str(source_file))
    browser.find_element("id", "target").send_keys(str(target_file))
    slow = {"offline": False, "latency": 3000, "downloadThroughput": -1, "uploadThroughput": -1}
    browser.execute_cdp_cmd("Network.enable", {})
    try:
        browser.execute_cdp_cmd("Network.emulateNetworkConditions", slow)  # the answer comes 3 s late
        browser.find_element("id", "register").click()
        found["running"] = axe_violations(browser)
        assert browser.execute_script("return document.body.dataset.state") == "running"  # axe saw that state
        # nothing moves while it runs (the seconds are text): nothing for prefers-reduced-motion to stop
        assert browser.execute_script("return document.getAnimations().length") == 0
        browser.find_element("id", "cancel").click()
    finally:
        browser.execute_cdp_cmd("Network.emulateNetworkConditions", {**slow, "latency": 0})
        browser.execute_cdp_cmd("Network.disable", {})

    assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
    assert not browser.execute_script("return document.getElementById('result').hidden")
    found["with a result"] = axe_violations(browser)
    assert register_a_broken_source(browser, tmp_path) == "error"
    assert status_text(browser).startswith("422: ")
    found["with an error"] = axe_violations(browser)
    failing = {state: violations for state, violations in found.items() if violations}
    assert not failing, json.dumps(failing, indent=1)


def test_axe_finds_no_violations_on_a_320_px_screen_and_on_a_401(browser, server, ply_files, tmp_path):
    """axe-core's rules (as above) with a result on a 320 CSS px wide screen (WCAG 1.4.10's reflow width), and with
    the 401 of a server that needs an API key. At 320 px the pose matrix scrolled sideways without being a tab stop
    (scrollable-region-focusable)."""
    skip_without_axe()
    _, source_file, target_file = ply_files
    browser.set_script_timeout(WAIT_S)
    found = {}
    narrow_screen(browser, 320, 640)
    try:
        assert register(browser, server.url, source_file, target_file) == "done", status_text(browser)
        found["320 px wide, with a result"] = axe_violations(browser)
    finally:
        browser.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})

    limited = limited_server()  # MFGNET_API_KEY set
    pair = synthetic_pair(seed=3, keep=300)
    write_points(tmp_path / "small_src.ply", pair.source)
    write_points(tmp_path / "small_tgt.ply", pair.target)
    assert register(browser, limited.url, tmp_path / "small_src.ply", tmp_path / "small_tgt.ply") == "error"
    assert status_text(browser).startswith("401: ")
    found["a 401 asking for the API key"] = axe_violations(browser)
    failing = {state: violations for state, violations in found.items() if violations}
    assert not failing, json.dumps(failing, indent=1)
