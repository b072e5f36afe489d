"""The dashboard in a real browser: Debian's chromium driven by Playwright, against a real
server on 127.0.0.1. Each test leaves a screenshot in tests/screenshots/.

`make test` builds the page and installs chromium first.
"""

from __future__ import annotations

import json
import queue
import re
import shutil
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import pytest
import trio
import websockets.sync.client

from arena.server import dashboard
from arena.server.config import ServerConfig
from arena.server.run import run_server
from tests.conftest import missing, need
from tests.golden import GOLDEN
from tests.hardware import running_sim
from tests.test_policy_server import CAMERA, tiny  # noqa: F401 (the fixture)

playwright_api = need("playwright.sync_api", "dev")
from playwright.sync_api import Browser, Page, expect  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
if not CHROMIUM.exists():
    missing("needs Debian's chromium: run `make test`")
if not dashboard.is_built():
    missing("the page is not built: run `make test`")
SCREENSHOTS = Path(__file__).resolve().parent / "screenshots"
# Flags for a headless, offline, root-run chromium; software WebGL for the 3D view.
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]
#: How long an expectation waits for the page (a bound only a broken page reaches: on a loaded
#: 2-core machine, chromium's software rendering and the server share the cores with everything
#: else, and 15 s was once not enough for a fault to show).
WAIT_MS = 60_000
expect.set_options(timeout=30_000)  # every other expectation (Playwright's own default: 5 s)


@dataclass
class LiveServer:
    """A real Arena server running in a thread of its own (the browser API here is blocking)."""

    url: str
    _stop: Any

    def http(self, key: str | None = None) -> httpx.Client:
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        return httpx.Client(base_url=self.url, timeout=10, headers=headers)

    def stop(self) -> None:
        self._stop()


@pytest.fixture
def start_live(tmp_path: Path) -> Iterator[Any]:
    """Start servers in threads; every one stops when the test ends."""
    stops = []

    def start(**settings: Any) -> LiveServer:
        settings.setdefault("recordings_dir", str(tmp_path / "recordings"))
        config = ServerConfig(port=0, shutdown_grace=0.2, **settings)
        ready: queue.Queue[Any] = queue.Queue()

        async def main() -> None:
            stop = trio.Event()
            async with trio.open_nursery() as nursery:
                try:
                    _, urls = await nursery.start(partial(run_server, config, stop=stop))
                except BaseException as error:
                    ready.put(error)
                    raise
                ready.put((urls[0], trio.lowlevel.current_trio_token(), stop))

        thread = threading.Thread(target=trio.run, args=(main,), daemon=True)
        thread.start()
        answer = ready.get(timeout=30)
        if isinstance(answer, BaseException):
            raise answer
        url, token, stop = answer

        def stop_server() -> None:
            trio.from_thread.run_sync(stop.set, trio_token=token)
            thread.join(timeout=15)

        stops.append(stop_server)
        return LiveServer(url, stop_server)

    yield start
    for stop in stops:
        stop()


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    with playwright_api.sync_playwright() as driver:
        launched = driver.chromium.launch(
            executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS
        )
        yield launched
        launched.close()


@contextmanager
def checked_page(browser: Browser, name: str, **options: Any) -> Iterator[Page]:
    """A page in a fresh browser context (`options` go to the context); page errors fail the
    test; a screenshot `name`.png is taken at the end."""
    options = {"viewport": {"width": 1280, "height": 900}, **options}
    context = browser.new_context(accept_downloads=True, **options)
    opened = context.new_page()
    errors: list[str] = []
    opened.on("pageerror", lambda error: errors.append(str(error)))
    try:
        yield opened
        SCREENSHOTS.mkdir(exist_ok=True)
        opened.screenshot(path=str(SCREENSHOTS / f"{name}.png"), full_page=True)
    finally:
        context.close()
    assert errors == [], f"the page threw: {errors}"


@pytest.fixture
def page(browser: Browser, request: pytest.FixtureRequest) -> Iterator[Page]:
    """A fresh page, checked as `checked_page` does."""
    with checked_page(browser, request.node.name) as opened:
        yield opened


def slider(page: Page, joint: str) -> Any:
    return page.locator(f'input[type=range][data-joint="{joint}"]')


def click_slider_at(page: Page, joint: str, fraction: float) -> float:
    """Click the slider's track like a hand would; returns the value the click gave it (the
    one the page commands). Read from the click's own `input` event: once the hand lets go the
    slider shows the robot's value again, which may still be on its way there."""
    return click_range_at(page, slider(page, joint), fraction)


def click_range_at(page: Page, handle: Any, fraction: float) -> float:
    """Click a range input's track at `fraction` of its width; the value the click gave it."""
    handle.evaluate("el => el.addEventListener('input', () => { el.dataset.clicked = el.value; })")
    handle.scroll_into_view_if_needed()  # (a card with more buttons puts the last below the fold)
    box = handle.bounding_box()
    assert box is not None
    page.mouse.click(box["x"] + box["width"] * fraction, box["y"] + box["height"] / 2)
    expect(handle).to_have_attribute("data-clicked", re.compile(r"."))
    return float(handle.get_attribute("data-clicked") or "nan")


def real_value(server: LiveServer, robot: str, joint: str) -> float:
    with server.http() as http:
        joints = http.get(f"/api/robots/{robot}/joints").json()
    return float(next(j["real_value"] for j in joints if j["name"] == joint))


def test_create_a_robot_attach_a_mock_slave_and_drive_it_with_a_slider(
    start_live: Any, page: Page
) -> None:
    server = start_live()
    page.goto(server.url + "/ui/")
    page.fill("#create-name", "Bench arm")
    page.fill("#create-id", "bench-arm")
    page.select_option("#create-slave", "")  # no slave: this test attaches one itself
    page.click("#create-robot button[type=submit]")
    expect(page).to_have_url(re.compile(r"#/robots/bench-arm$"))
    expect(page.locator("#robot-title")).to_have_text("Bench arm (bench-arm)")
    # the form offers the API's default type again after a robot is made (not the first listed)
    expect(page.locator("#create-type")).to_have_value("so-arm100")
    expect(page.locator("#robot-state")).to_have_text("idle")
    expect(page.locator('#robot-list li[data-robot="bench-arm"]')).to_be_visible()
    expect(page.locator("#peers")).to_have_text("nothing attached")

    page.click("#add-mock")
    expect(page.locator("#peers li").first).to_contain_text("mock-slave")
    expect(page.locator("#peers li .tag").first).to_have_text("connected")
    expect(page.locator('td[data-real="Rotation"]')).to_have_text("0.0")

    wanted = click_slider_at(page, "Rotation", 0.8)
    assert wanted > 20  # the right part of the track is well away from zero
    # The mock slave's measured value follows the slider, on the page and on the server.
    expect(page.locator('td[data-virtual="Rotation"]')).to_have_text(
        f"{wanted:.1f}", timeout=WAIT_MS
    )
    expect(page.locator('td[data-real="Rotation"]')).to_have_text(f"{wanted:.1f}", timeout=WAIT_MS)
    assert real_value(server, "bench-arm", "Rotation") == pytest.approx(wanted, abs=0.05)
    # The 3D view is drawn (software WebGL) and its ghost (the real pose) caught up too.
    expect(page.locator("#twin canvas")).to_have_count(1)
    twin = page.locator("#twin")
    expect(twin).to_have_attribute("data-ghost-tip", twin.get_attribute("data-tip") or "")

    # Detach the slave, then delete the robot (the second click confirms).
    page.locator("#peers li").first.get_by_role("button", name="Detach").click()
    expect(page.locator("#peers")).to_have_text("nothing attached")
    page.click("#delete-robot")
    expect(page.locator("#delete-robot")).to_have_text("Really delete?")
    with server.http() as http:
        assert http.get("/api/robots/bench-arm").status_code == 200  # one click deletes nothing
    page.click("#delete-robot")
    expect(page.locator("#robot-panel")).to_be_hidden()
    expect(page.locator("#robot-list")).to_have_text("no robots yet")
    with server.http() as http:
        assert http.get("/api/robots/bench-arm").json()["error"]["code"] == "UNKNOWN_ROBOT"


def test_estop_locks_the_sliders_and_reset_frees_them(start_live: Any, page: Page) -> None:
    server = start_live(demo=True)
    with server.http() as http:
        assert http.post("/api/robots", json={"robot_type": "so-arm100", "name": "Second"})
    page.goto(server.url + "/ui/#/robots/demo-arm")
    expect(page.locator("#robot-state")).to_have_text("idle")
    expect(slider(page, "Elbow")).to_be_enabled()
    expect(page.locator("#estop")).to_be_enabled()

    page.click("#estop")
    expect(page.locator("#robot-state")).to_have_text("E-STOPPED")
    for joint in ("Rotation", "Pitch", "Elbow", "Wrist_Pitch", "Wrist_Roll", "Jaw"):
        expect(slider(page, joint)).to_be_disabled()
    expect(page.locator("#master-line")).to_contain_text("e-stop from the dashboard")
    expect(page.locator("#events")).to_contain_text("now estopped")
    expect(page.locator("#reset")).to_be_enabled()
    with server.http() as http:
        status = http.get("/api/robots/demo-arm/status").json()
        assert status["state"] == "estopped"
        # A command now is refused by the server too, not just hidden by the page.
        refused = http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Elbow", "value": -5}]}
        )
        assert refused.json()["error"]["code"] == "ESTOPPED"

    page.click("#reset")
    expect(page.locator("#robot-state")).to_have_text("idle")
    expect(slider(page, "Elbow")).to_be_enabled()
    wanted = click_slider_at(page, "Elbow", 0.3)
    expect(page.locator('td[data-real="Elbow"]')).to_have_text(f"{wanted:.1f}", timeout=WAIT_MS)

    # Stop everything: every robot, the one on screen and the other.
    page.click("#stop-all")
    expect(page.locator("#robot-state")).to_have_text("E-STOPPED")
    with server.http() as http:
        states = {r["id"]: r["state"] for r in http.get("/api/robots").json()}
    assert set(states.values()) == {"estopped"} and len(states) == 2
    expect(page.locator("#robot-list .state.estopped")).to_have_count(2)


def test_a_sequence_takes_the_robot_and_moves_the_3d_twin(start_live: Any, page: Page) -> None:
    server = start_live(demo=True)
    page.goto(server.url + "/ui/#/robots/demo-arm")
    twin = page.locator("#twin")
    expect(twin).to_have_attribute("data-tip", re.compile(r"^-?\d"))
    rest = twin.get_attribute("data-tip")
    page.select_option("#sequence", "gentle-wave")
    page.click("#play")
    expect(page.locator("#robot-state")).to_have_text("mastered")
    expect(page.locator("#master-line")).to_contain_text("mock-sequence")
    expect(slider(page, "Rotation")).to_be_disabled()
    # The solid (commanded) arm's tip travels more than 2 cm from where it stood.
    page.wait_for_function(
        """rest => {
            const now = document.getElementById("twin").dataset.tip.split(",").map(Number);
            const was = rest.split(",").map(Number);
            return Math.hypot(...now.map((v, i) => v - was[i])) > 0.02;
        }""",
        arg=rest,
        timeout=WAIT_MS,
    )
    page.screenshot(path=str(SCREENSHOTS / "sequence-playing.png"))

    page.click("#stop-sequence")
    expect(page.locator("#robot-state")).to_have_text("idle")
    expect(slider(page, "Rotation")).to_be_enabled()
    expect(page.locator("#master-line")).to_have_text("No master: the sliders drive the robot.")


def demo_with_golden(start_live: Any, page: Page, tmp_path: Path) -> Any:
    """A demo server whose recordings folder holds the golden gentle-wave recording, with the
    page open on demo-arm."""
    folder = tmp_path / "recordings"
    folder.mkdir()
    shutil.copy(GOLDEN / "gentle-wave.mcap", folder)
    server = start_live(demo=True, recordings_dir=str(folder))
    page.goto(server.url + "/ui/#/robots/demo-arm")
    return server


def test_recordings_list_download_plot_replay_and_start_stop(
    start_live: Any, page: Page, tmp_path: Path
) -> None:
    server = demo_with_golden(start_live, page, tmp_path)
    expect(page.locator("#recorder-status")).to_contain_text("Recording")
    page.click("#record-stop")
    expect(page.locator("#recorder-status")).to_have_text("Not recording.")
    golden = page.locator('#recording-list li[data-recording="gentle-wave.mcap"]')
    expect(golden).to_be_visible()

    with page.expect_download() as download:
        golden.get_by_role("button", name="Download").click()
    saved = tmp_path / "downloaded.mcap"
    download.value.save_as(saved)
    assert saved.read_bytes() == (tmp_path / "recordings" / "gentle-wave.mcap").read_bytes()

    golden.get_by_role("button", name="Plot").click()
    plot = page.locator("#plot")
    expect(plot).to_be_visible()
    expect(plot).to_have_attribute("data-recording", "gentle-wave.mcap")
    assert int(plot.get_attribute("data-points") or 0) > 20
    expect(page.locator("#plot-legend")).to_contain_text("Rotation")
    page.get_by_role("button", name="Close").click()
    expect(plot).to_be_hidden()

    golden.get_by_role("button", name="Replay").click()
    expect(page.locator("#robot-state")).to_have_text("mastered")
    expect(page.locator("#master-line")).to_contain_text("replay")

    page.click("#record-start")
    expect(page.locator("#recorder-status")).to_contain_text("Recording")
    with server.http() as http:
        assert http.get("/api/recordings").json()["recorder"]["active"] is True


def test_with_keys_the_page_asks_for_one_and_a_viewer_key_may_stop_but_not_reset(
    start_live: Any, page: Page
) -> None:
    # Stopping is never gated behind more than seeing (specs/api.md): a viewer's e-stop works,
    # its reset is refused.
    server = start_live(demo=True, api_keys=("operator-key",), viewer_keys=("viewer-key",))
    page.goto(server.url + "/ui/")
    expect(page.locator("#key-dialog")).to_be_visible()
    expect(page.locator("#server-status")).to_contain_text("UNAUTHORIZED")
    page.fill("#key-input", "viewer-key")
    page.click("#key-save")
    page.goto(server.url + "/ui/#/robots/demo-arm")
    expect(page.locator("#robot-state")).to_have_text("idle")
    expect(page.locator("#watch-status")).to_have_text("live")
    page.click("#estop")
    expect(page.locator("#robot-state")).to_have_text("E-STOPPED")
    page.click("#reset")
    expect(page.locator("#events")).to_contain_text("FORBIDDEN")
    expect(page.locator("#robot-state")).to_have_text("E-STOPPED")

    page.click("#key-button")
    page.fill("#key-input", "operator-key")
    page.click("#key-save")
    expect(page.locator("#robot-state")).to_have_text("E-STOPPED")
    page.click("#reset")
    expect(page.locator("#robot-state")).to_have_text("idle")
    with server.http("operator-key") as http:
        assert http.get("/api/robots/demo-arm/status").json()["state"] == "idle"


def test_on_a_phone_the_stop_buttons_stay_in_view(start_live: Any, browser: Browser) -> None:
    server = start_live(demo=True)
    context = browser.new_context(viewport={"width": 390, "height": 844}, is_mobile=True)
    phone = context.new_page()
    try:
        phone.goto(server.url + "/ui/#/robots/demo-arm")
        expect(phone.locator("#robot-state")).to_have_text("idle")
        width = phone.evaluate("document.documentElement.scrollWidth")
        assert width <= 390  # one column, nothing wider than the screen
        phone.locator("#recordings-panel").scroll_into_view_if_needed()
        assert phone.evaluate("window.scrollY") > 300
        for button in ("#estop", "#stop-all"):
            box = phone.locator(button).bounding_box()
            assert box is not None and box["y"] >= 0 and box["y"] + box["height"] <= 844
        phone.click("#estop")
        expect(phone.locator("#robot-state")).to_have_text("E-STOPPED")
        SCREENSHOTS.mkdir(exist_ok=True)
        phone.screenshot(path=str(SCREENSHOTS / "phone.png"))
    finally:
        context.close()


def test_the_page_says_when_recording_stopped_and_why(
    start_live: Any, page: Page, tmp_path: Path
) -> None:
    folder = tmp_path / "recordings"
    server = start_live(demo=True, recordings_dir=str(folder))
    page.goto(server.url + "/ui/#/robots/demo-arm")
    expect(page.locator("#recorder-status")).to_contain_text("Recording")
    page.click("#record-stop")
    expect(page.locator("#recorder-status")).to_have_text("Not recording.")
    # The disk goes bad: the folder becomes a file, and recording is switched on again.
    shutil.rmtree(folder)
    folder.write_text("not a folder")
    page.click("#record-start")
    with server.http() as http:  # something to record
        http.put("/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 3}]})
    status = page.locator("#recorder-status")
    expect(status).to_contain_text("Recording stopped", timeout=30_000)
    expect(status).to_have_class(re.compile("failing"))
    expect(page.locator("#server-status")).to_contain_text("recording FAILING", timeout=30_000)
    page.screenshot(path=str(SCREENSHOTS / "recording-failing.png"))


def test_the_twin_draws_the_workspace_and_what_a_refused_move_would_hit(
    start_live: Any, page: Page
) -> None:
    server = start_live(demo=True)
    box = {"name": "camera", "min": [0.15, -0.1, 0.0], "max": [0.25, 0.0, 0.2]}
    with server.http() as http:
        placed = http.put("/api/robots/demo-arm/workspace", json={"floor": 0.0, "keep_out": [box]})
        assert placed.status_code == 200
    page.goto(server.url + "/ui/#/robots/demo-arm")
    twin = page.locator("#twin")
    expect(twin).to_have_attribute("data-workspace", "floor,camera", timeout=WAIT_MS)
    click_slider_at(page, "Pitch", 0.97)  # the arm folded down into its table: refused
    expect(twin).to_have_attribute("data-hit", re.compile(r"^\w+,floor$"), timeout=WAIT_MS)
    expect(page.locator("#events")).to_contain_text("COLLISION")
    with server.http() as http:
        pitch = next(
            j for j in http.get("/api/robots/demo-arm/joints").json() if j["name"] == "Pitch"
        )
    assert pitch["virtual_value"] < 60  # nothing of the refused move went out
    # ...and the slider says so: back on the robot's value, not where the hand left it
    page.wait_for_function(
        "limit => Number(document.querySelector('input[data-joint=Pitch]').value) < limit",
        arg=60,
    )


def test_a_camera_streams_beside_the_twin_and_episodes_are_marked(
    start_live: Any, page: Page
) -> None:
    server = start_live(demo=True, api_keys=("operator-key",))
    page.goto(server.url + "/ui/")
    page.fill("#key-input", "operator-key")
    page.click("#key-save")
    page.goto(server.url + "/ui/#/robots/demo-arm")
    expect(page.locator("#robot-state")).to_have_text("idle")
    page.fill("#camera-source", "test-pattern")
    page.click("#add-camera")
    # the stream (asked with the key in its query, as an <img> cannot send headers) shows
    image = page.locator('#cameras [data-camera="front"] img')
    expect(image).to_be_visible()
    page.wait_for_function(
        "() => document.querySelector('#cameras img').naturalWidth === 640", timeout=WAIT_MS
    )
    caption = page.locator('#cameras [data-camera="front"] figcaption')
    expect(caption).to_contain_text("640\u00d7480")

    page.fill("#episode-task", "pick up the cube")
    page.click("#episode-start")
    status = page.locator("#episode-status")
    expect(status).to_contain_text("episode 0 recording")
    expect(status).to_contain_text("pick up the cube")
    expect(page.locator("#episode-stop")).to_be_enabled()
    page.screenshot(path=str(SCREENSHOTS / "camera-and-episode.png"))
    page.click("#episode-stop")
    expect(status).to_have_text("1 kept, 0 discarded")
    page.click("#episode-discard")
    expect(status).to_have_text("0 kept, 1 discarded")
    with server.http("operator-key") as http:
        assert http.get("/api/robots/demo-arm/episodes").json()["discarded"] == 1
    page.click('#cameras [data-camera="front"] button')
    expect(page.locator("#cameras figure")).to_have_count(0)


def test_the_dashboard_of_one_node_lists_and_drives_a_robot_of_another(
    start_live: Any, page: Page
) -> None:
    need("zenoh", "fleet")
    hub = start_live(demo=True, node="hub", fleet_listen=("tcp/127.0.0.1:0",))
    with hub.http() as http:
        nodes = http.get("/api/fleet/nodes").json()["nodes"]
    (locator,) = next(node for node in nodes if node["name"] == "hub")["locators"]
    edge = start_live(node="edge", fleet_listen=("tcp/127.0.0.1:0",), fleet_connect=(locator,))
    page.goto(edge.url + "/ui/")
    listed = page.locator('#robot-list li[data-robot="demo-arm"]')
    expect(listed).to_contain_text("@hub", timeout=WAIT_MS)  # the robot of the other node
    listed.locator("a").click()
    # its details come through the edge node, its state over a WebSocket carried to the hub
    expect(page.locator("#robot-title")).to_have_text("Demo arm (demo-arm)")
    expect(page.locator("#watch-status")).to_have_text("live")
    expect(page.locator("#robot-state")).to_have_text("idle")
    expect(page.locator("#peers li").first).to_contain_text("demo-mock-slave")
    wanted = click_slider_at(page, "Rotation", 0.75)
    expect(page.locator('td[data-real="Rotation"]')).to_have_text(f"{wanted:.1f}", timeout=WAIT_MS)
    assert real_value(hub, "demo-arm", "Rotation") == pytest.approx(wanted, abs=0.05)


@pytest.mark.parametrize("demo", [False, True], ids=["fresh-server", "with-the-demo-robot"])
def test_robot_creation_and_control(
    start_live: Any, browser: Browser, request: pytest.FixtureRequest, demo: bool
) -> None:
    """The seed's own integration test ("Integration Tests" in its README), in Python's
    Playwright: its four lines, then what they must mean on the server."""
    server = start_live(demo=demo)
    with checked_page(browser, request.node.name, base_url=server.url) as page:
        page.goto("/")
        page.click('[data-testid="create-robot"]')
        page.click('[data-testid="connect-demo-sequences"]')
        expect(page.locator('[data-testid="robot-status"]')).to_contain_text("Master + Slaves")

        # `/` took the browser to the dashboard; the new robot is the one on screen.
        expect(page).to_have_url(re.compile(r"/ui/#/robots/robot-[0-9a-f]+$"))
        robot_id = page.url.rsplit("/", 1)[1]
        with server.http() as http:
            robot = http.get(f"/api/robots/{robot_id}").json()
            others = [r for r in http.get("/api/robots").json() if r["id"] != robot_id]
        assert robot["name"] == "My Robot"
        assert [slave["type"] for slave in robot["slaves"]] == ["mock-slave"]
        assert robot["master"]["type"] == "mock-sequence"
        assert robot["state"] == "mastered"
        # The demo robot the page showed first was left alone.
        assert [(r["id"], r["master"]) for r in others] == ([("demo-arm", None)] if demo else [])
        # Its 3D view shows the slave's measured pose, and the master line what plays.
        expect(page.locator("#twin-legend")).to_contain_text("measured")
        expect(page.locator("#twin-legend")).not_to_contain_text("no slave")
        expect(page.locator("#master-line")).to_contain_text(
            "Playing sequences 'gentle-wave', 'small-scan', 'tiny-flex' in a loop"
        )


def test_the_only_robot_opens_at_once_and_ids_tell_robots_apart(
    start_live: Any, page: Page
) -> None:
    server = start_live()
    with server.http() as http:
        for robot_id in ("first", "second", "third"):
            body = {"robot_type": "so-arm100", "name": "My Robot", "id": robot_id}
            assert http.post("/api/robots", json=body).status_code == 201
            if robot_id == "first":
                # The server's only robot: the page opens it, ready to stop.
                page.goto(server.url + "/ui/")
                expect(page.locator("#robot-title")).to_have_text("My Robot (first)")
                expect(page).to_have_url(re.compile(r"/ui/#/robots/first$"))
                expect(page.locator("#estop")).to_be_enabled()
    # Three robots of one name: each shows its id beside its name.
    page.goto(server.url + "/ui/#")
    items = page.locator("#robot-list li")
    for robot_id in ("first", "second", "third"):
        expect(page.locator(f'#robot-list li[data-robot="{robot_id}"]')).to_contain_text(
            f"My Robot {robot_id}"
        )
    expect(items).to_have_count(3)
    # None of three is chosen for you: the page says to choose.
    expect(page.locator("#notice")).to_contain_text("Choose a robot")
    expect(page.locator("#robot-panel")).to_be_hidden()
    expect(page.locator("#estop")).to_be_disabled()


def test_the_demo_robot_opens_at_once_among_others(start_live: Any, page: Page) -> None:
    server = start_live(demo=True)
    with server.http() as http:
        for _ in range(2):
            body = {"robot_type": "so-arm100", "name": "My Robot"}
            assert http.post("/api/robots", json=body).status_code == 201
    page.goto(server.url + "/ui/")
    expect(page.locator("#robot-title")).to_have_text("Demo arm (demo-arm)")
    expect(page.locator("#estop")).to_be_enabled()
    expect(page.locator("#robot-list li")).to_have_count(3)
    texts = page.locator("#robot-list li a").all_inner_texts()
    assert len(set(texts)) == 3, texts  # the two "My Robot" differ by their ids


# Pixels of the 3D view with the hue of `swatch` (a legend entry's colour): the hue within
# 12 degrees, saturated and not dark, so that the lit solid arm counts whatever its shading.
COUNT_HUE = """swatch => {
    const [r0, g0, b0] = getComputedStyle(document.querySelector(swatch))
        .borderTopColor.match(/\\d+/g).map(Number);
    const hsv = (r, g, b) => {
        const max = Math.max(r, g, b), min = Math.min(r, g, b), span = max - min;
        if (!span) return [0, 0, max / 255];
        let hue = max === r ? (g - b) / span : max === g ? 2 + (b - r) / span : 4 + (r - g) / span;
        return [(hue * 60 + 360) % 360, span / max, max / 255];
    };
    const [want] = hsv(r0, g0, b0);
    const source = document.querySelector("#twin canvas");
    if (!source) return 0; // not drawn yet
    const copy = document.createElement("canvas");
    copy.width = source.width;
    copy.height = source.height;
    const context = copy.getContext("2d");
    context.drawImage(source, 0, 0);
    const pixels = context.getImageData(0, 0, copy.width, copy.height).data;
    let count = 0;
    for (let i = 0; i < pixels.length; i += 4) {
        const [hue, saturation, value] = hsv(pixels[i], pixels[i + 1], pixels[i + 2]);
        const off = Math.min(Math.abs(hue - want), 360 - Math.abs(hue - want));
        if (off <= 12 && saturation > 0.35 && value > 0.3) count++;
    }
    return count;
}"""
COMMANDED = '#twin-legend [data-part="commanded"] .swatch'
MEASURED = '#twin-legend [data-part="measured"] .swatch'


def hue_pixels(page: Page, swatch: str) -> int:
    return int(page.evaluate(COUNT_HUE, swatch))


def test_the_twin_tells_the_measured_arm_from_the_commanded_one(
    start_live: Any, page: Page
) -> None:
    server = start_live()
    with server.http() as http:
        body = {"robot_type": "so-arm100", "name": "Bare", "id": "bare"}
        assert http.post("/api/robots", json=body).status_code == 201
    page.goto(server.url + "/ui/#/robots/bare")
    legend = page.locator("#twin-legend")
    expect(legend.locator('[data-part="commanded"]')).to_contain_text("commanded")
    # No slave: nothing is measured, and no ghost stands at a pose nobody measured.
    expect(legend.locator('[data-part="measured"]')).to_contain_text("measured: no slave")
    page.wait_for_function(f"() => ({COUNT_HUE})({COMMANDED!r}) > 2000", timeout=WAIT_MS)
    assert hue_pixels(page, MEASURED) == 0

    # A mock slave: it stands where it was commanded, the two arms in one place, and still the
    # measured one shows, in its own colour, over the commanded one.
    page.click("#add-mock")
    expect(legend.locator('[data-part="measured"]')).not_to_contain_text("no slave")
    twin = page.locator("#twin")
    expect(twin).to_have_attribute("data-ghost-tip", twin.get_attribute("data-tip") or "")
    page.wait_for_function(f"() => ({COUNT_HUE})({MEASURED!r}) > 500", timeout=WAIT_MS)
    # (Under the outline: some 1,700 pixels in a view that leaves room for the arm's reach.)
    assert hue_pixels(page, COMMANDED) > 1000

    # The slave goes: the robot keeps its last real values, but no ghost stands for them.
    page.locator("#peers li").first.get_by_role("button", name="Detach").click()
    expect(legend.locator('[data-part="measured"]')).to_contain_text("measured: no slave")
    page.wait_for_function(f"() => ({COUNT_HUE})({MEASURED!r}) === 0", timeout=WAIT_MS)
    assert hue_pixels(page, COMMANDED) > 2000


def test_the_page_says_which_sequence_plays(start_live: Any, page: Page) -> None:
    server = start_live(demo=True)
    page.goto(server.url + "/ui/#/robots/demo-arm")
    page.select_option("#sequence", "small-scan")
    page.click("#play")
    line = page.locator("#master-line")
    expect(line).to_contain_text("Playing sequence 'small-scan' (master 'master-")
    expect(line).to_contain_text(", mock-sequence): the sliders are locked.")
    expect(page.locator('[data-testid="robot-status"]')).to_contain_text("Master + Slaves")
    # The rest plays it in a loop (the page's 8 s play may end on a loaded machine before the
    # reload and the two clicks are done).
    with server.http() as http:
        body = {
            "type": "mock-sequence",
            "sequences": ["small-scan"],
            "loop": True,
            "takeover": True,
        }
        assert http.post("/api/robots/demo-arm/master", json=body).is_success
    # Reloaded, the page still knows what plays: the server says.
    page.reload()
    expect(line).to_contain_text("Playing sequence 'small-scan' in a loop")
    # The demo sequences take over only when asked twice: the first click is refused, and the
    # page says who holds the robot.
    connect = page.locator('[data-testid="connect-demo-sequences"]')
    connect.click()
    # (the second click at once: the page keeps a refusal armed for 4 s, which a loaded
    # machine's checks in between could outlast; the refusal's words are checked after)
    expect(connect).to_have_text("Take over with the demo sequences?")
    connect.click()
    events = page.locator("#events")
    expect(events).to_contain_text("MASTER_ACTIVE")
    expect(events).to_contain_text("It is held by sequence 'small-scan' in a loop (master 'master-")
    expect(line).to_contain_text(
        "Playing sequences 'gentle-wave', 'small-scan', 'tiny-flex' in a loop"
    )
    expect(connect).to_have_text("Connect demo sequences")
    page.click("#stop-sequence")
    expect(line).to_have_text("No master: the sliders drive the robot.")
    expect(page.locator('[data-testid="robot-status"]')).to_have_text("Slaves, no master")


def test_the_page_says_what_plays_when_another_client_started_it(
    start_live: Any, page: Page, tmp_path: Path
) -> None:
    server = demo_with_golden(start_live, page, tmp_path)
    line = page.locator("#master-line")
    expect(line).to_have_text("No master: the sliders drive the robot.")
    with server.http() as http:  # another client, not this page
        body = {"type": "mock-sequence", "sequences": ["tiny-flex"], "loop": True}
        sequence = http.post("/api/robots/demo-arm/master", json=body).json()["id"]
        expect(line).to_have_text(
            f"Playing sequence 'tiny-flex' in a loop (master '{sequence}', mock-sequence): "
            "the sliders are locked."
        )
        body = {"recording": "gentle-wave.mcap", "loop": True, "takeover": True}
        replay = http.post("/api/robots/demo-arm/replay", json=body).json()["master"]
        expect(line).to_have_text(
            f"Playing replay of 'gentle-wave.mcap' in a loop (master '{replay}', replay): "
            "the sliders are locked."
        )
    ws_url = server.url.replace("http://", "ws://") + "/ws/master/demo-arm?id=alice&takeover=1"
    with websockets.sync.client.connect(ws_url):
        expect(line).to_have_text(
            "Held by WebSocket client (master 'alice', websocket): the sliders are locked."
        )
        expect(page.locator("#robot-status")).to_have_attribute(
            "title", re.compile(r"^WebSocket client \(master 'alice', websocket\)")
        )
    # Its socket closed without a release: the robot e-stops, and the page says why.
    expect(line).to_contain_text("E-stopped: master 'alice' lost")


def test_a_replay_onto_a_held_robot_takes_over_on_a_second_click(
    start_live: Any, page: Page, tmp_path: Path
) -> None:
    server = demo_with_golden(start_live, page, tmp_path)
    line = page.locator("#master-line")
    ws_url = server.url.replace("http://", "ws://") + "/ws/master/demo-arm?id=alice"
    with websockets.sync.client.connect(ws_url) as alice:
        expect(line).to_contain_text("Held by WebSocket client (master 'alice'")
        golden = page.locator('#recording-list li[data-recording="gentle-wave.mcap"]')
        replay = golden.locator("button[data-replay]")
        expect(replay).to_have_text("Replay")
        # The first click is refused: the page says why and who holds the robot. The second
        # takes over (at once: the refusal stays armed for 4 s, which a loaded machine's
        # checks in between could outlast); alice is told who did.
        replay.click()
        expect(replay).to_have_text("Take over with this replay?")
        replay.click()
        events = page.locator("#events")
        expect(events).to_contain_text("MASTER_ACTIVE")
        expect(events).to_contain_text("It is held by WebSocket client (master 'alice', websocket)")
        expect(line).to_contain_text("Playing replay of 'gentle-wave.mcap' (master '")
        expect(replay).to_have_text("Replay")
        told = json.loads(alice.recv(timeout=WAIT_MS / 1000))
        while told["type"] != "detached":
            told = json.loads(alice.recv(timeout=WAIT_MS / 1000))
    assert told["data"]["code"] == "TAKEN_OVER"
    assert told["data"]["by"]["description"] == "replay of 'gentle-wave.mcap'"


def test_a_plot_opens_large_enough_to_read(start_live: Any, page: Page, tmp_path: Path) -> None:
    demo_with_golden(start_live, page, tmp_path)
    golden = page.locator('#recording-list li[data-recording="gentle-wave.mcap"]')
    golden.get_by_role("button", name="Plot").click()
    plot = page.locator("#plot")
    expect(plot).to_have_attribute("data-recording", "gentle-wave.mcap")
    box = plot.bounding_box()
    assert box is not None and box["width"] >= 800 and box["height"] >= 360
    # Drawn at the size it shows (not a small drawing stretched or shrunk), with axes labelled.
    assert plot.evaluate("c => c.width / c.getBoundingClientRect().width") >= 1
    ticks = (plot.get_attribute("data-ticks") or "").split(";")
    assert len(ticks) == 2 and all(len(axis.split(",")) >= 4 for axis in ticks), ticks
    page.screenshot(path=str(SCREENSHOTS / "plot-open.png"))
    # The plot covers the page, not the stop buttons: E-STOP works with it open.
    page.click("#estop")
    expect(page.locator("#robot-state")).to_have_text("E-STOPPED")
    expect(plot).to_be_visible()
    page.keyboard.press("Escape")
    expect(plot).to_be_hidden()


def test_a_double_click_on_create_robot_makes_one_robot(start_live: Any, page: Page) -> None:
    server = start_live()
    page.goto(server.url + "/ui/")
    page.dblclick('[data-testid="create-robot"]')
    expect(page.locator("#robot-title")).to_contain_text("My Robot (robot-")
    expect(page.locator("#peers li").first).to_contain_text("mock-slave")
    with server.http() as http:
        robots = http.get("/api/robots").json()
    assert len(robots) == 1, robots
    expect(page.locator("#robot-list li")).to_have_count(1)


def test_the_arm_stays_in_view_wherever_it_moves(start_live: Any, browser: Browser) -> None:
    """On a phone the view is narrow: the arm turned to its side and stretched out stays in
    it, and a view a hand turned stays as the hand left it."""
    server = start_live(demo=True)
    phone = {"viewport": {"width": 400, "height": 900}, "is_mobile": True}
    with checked_page(browser, "arm-in-view-phone", **phone) as page:
        page.goto(server.url + "/ui/#/robots/demo-arm")
        twin = page.locator("#twin")
        expect(twin).to_have_attribute("data-in-view", re.compile(r"^0\.\d+$"))
        poses = [
            {"Rotation": 100, "Pitch": 90, "Elbow": -90},  # out to the side, towards the viewer
            {"Rotation": -100, "Pitch": 90, "Elbow": -90},  # out to the other side
            {"Rotation": 0, "Pitch": 0, "Elbow": -90, "Wrist_Pitch": -90},  # up
        ]
        for pose in poses:
            move_and_wait(server, page, pose)
            # 1 is the view's edge: every joint and the tip are well inside it.
            assert float(twin.get_attribute("data-in-view") or "nan") < 0.9, pose
    # A hand turns the view (a mouse drag on a desktop): the arm moving does not turn it back.
    with checked_page(browser, "arm-in-view-orbit") as page:
        page.goto(server.url + "/ui/#/robots/demo-arm")
        canvas = page.locator("#twin canvas")
        twin = page.locator("#twin")
        expect(twin).to_have_attribute("data-camera", re.compile(r"."))
        aimed = twin.get_attribute("data-camera")
        box = canvas.bounding_box()
        assert box is not None
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.mouse.down()
        page.mouse.move(box["x"] + box["width"] / 4, box["y"] + box["height"] / 3, steps=5)
        page.mouse.up()
        expect(twin).not_to_have_attribute("data-camera", aimed or "")
        turned = twin.get_attribute("data-camera")
        move_and_wait(server, page, {"Rotation": 100, "Pitch": 90, "Elbow": -90})
        expect(twin).to_have_attribute("data-camera", turned or "")
        assert float(twin.get_attribute("data-in-view") or "nan") < 1


def move_and_wait(server: LiveServer, page: Page, pose: dict[str, float]) -> None:
    """Command `pose` (the joint limits may clamp it) and wait until the page shows the arm
    there: its Virtual column reads what the server says the robot commands."""
    with server.http() as http:
        joints = [{"name": name, "value": value} for name, value in pose.items()]
        answer = http.put("/api/robots/demo-arm/joints", json={"joints": joints})
        assert answer.status_code == 200, answer.text
        goal = {c["joint"]: c["applied"] for c in answer.json()["clamped"]}
        goal = {name: goal.get(name, value) for name, value in pose.items()}
    for name, value in goal.items():
        expect(page.locator(f'[data-virtual="{name}"]')).to_have_text(f"{value:.1f}")


def test_a_slaves_fault_shows_on_it_while_it_lasts(start_live: Any, page: Page) -> None:
    # A fault comes over the viewer socket: logged, and listed on its slave until it is over.
    server = start_live(demo=True)
    page.goto(server.url + "/ui/#/robots/demo-arm")
    expect(page.locator("#robot-state")).to_have_text("idle")
    expect(page.locator("#watch-status")).to_have_text("live")  # its viewer socket is open
    # (named: an unnamed one's number counts the slaves of every server this process ran)
    ws_url = "ws" + server.url[len("http") :] + "/ws/slave/demo-arm?id=ws-slave-1"
    with websockets.sync.client.connect(ws_url) as arm:
        fault = {"code": "SERVO_HOT", "message": "Elbow is warm", "severity": "warning"}
        arm.send(json.dumps({"type": "error", "data": fault | {"joint": "Elbow"}}))
        shown = page.locator('#peers li[data-peer="ws-slave-1"] li.fault')
        expect(shown).to_have_text("SERVO_HOT (Elbow): Elbow is warm", timeout=WAIT_MS)
        expect(page.locator("#events")).to_contain_text("ws-slave-1: warning SERVO_HOT (Elbow)")
        # A status saying it is not connected is a fault of its own; one saying it is again
        # ends that one (and only that one).
        status = {"isConnected": False, "error": "cable loose"}
        arm.send(json.dumps({"type": "status_update", "data": status}))
        expect(page.locator('#peers li[data-peer="ws-slave-1"] li.fault')).to_have_count(
            2, timeout=WAIT_MS
        )
        status = {"isConnected": True}
        arm.send(json.dumps({"type": "status_update", "data": status}))
        expect(page.locator("#events")).to_contain_text("SLAVE_STATUS over", timeout=WAIT_MS)
        expect(page.locator('#peers li[data-peer="ws-slave-1"] li.fault')).to_have_count(
            1, timeout=WAIT_MS
        )


def test_the_so101_gripper_slider_is_in_percent(start_live: Any, page: Page) -> None:
    # One unit everywhere the robot type says: the so-101's gripper runs 0 (closed) to 100.
    server = start_live()
    with server.http() as http:
        created = http.post("/api/robots", json={"robot_type": "so-101", "id": "follower"})
        assert created.status_code == 201
        http.post("/api/robots/follower/slaves", json={"type": "mock-slave"})
    page.goto(server.url + "/ui/#/robots/follower")
    row = page.locator("#joints tbody tr").filter(has=slider(page, "gripper"))
    expect(row.locator("td").first).to_have_text("gripper (%)", timeout=WAIT_MS)
    expect(page.locator("#joints tbody tr").first.locator("td").first).to_have_text(
        "shoulder_pan (°)"
    )
    expect(slider(page, "gripper")).to_have_attribute("min", "0")
    expect(slider(page, "gripper")).to_have_attribute("max", "100")
    wanted = click_slider_at(page, "gripper", 0.5)
    assert 40 <= wanted <= 60
    expect(page.locator('td[data-real="gripper"]')).to_have_text(f"{wanted:.1f}", timeout=WAIT_MS)
    assert real_value(server, "follower", "gripper") == pytest.approx(wanted, abs=0.1)


def test_pause_resume_intervene_and_hand_back_from_the_page(start_live: Any, page: Page) -> None:
    server = start_live(demo=True)
    with server.http() as http:
        sequence = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
        assert http.post("/api/robots/demo-arm/master", json=sequence).status_code == 201
    page.goto(server.url + "/ui/#/robots/demo-arm")
    state = page.locator("#robot-state")
    line = page.locator("#master-line")
    expect(state).to_have_text("mastered")
    expect(slider(page, "Rotation")).to_be_disabled()
    page.click("#master-pause")
    expect(state).to_have_text("paused")
    expect(line).to_contain_text("Paused: sequence 'gentle-wave'")
    expect(page.locator("#master-pause")).to_be_disabled()
    # Space resumes (and pauses) for whoever has the page focused.
    page.locator("#robot-title").click()
    page.keyboard.press(" ")
    expect(state).to_have_text("mastered")
    page.keyboard.press(" ")
    expect(state).to_have_text("paused")
    page.click("#master-resume")
    expect(state).to_have_text("mastered")
    # Intervene: the sequence waits, paused, and the sliders drive the robot.
    page.click("#intervene")
    expect(state).to_have_text("intervened")
    expect(line).to_contain_text("You intervene")
    expect(slider(page, "Rotation")).to_be_enabled()
    with server.http() as http:
        shown = http.get("/api/robots/demo-arm").json()
        assert shown["paused_master"]["kind"] == "mock-sequence"
        assert shown["master"]["kind"] == "operator"
    wanted = click_slider_at(page, "Rotation", 0.8)
    expect(page.locator('td[data-virtual="Rotation"]')).to_have_text(
        f"{wanted:.1f}", timeout=WAIT_MS
    )
    page.click("#hand-back")
    expect(state).to_have_text("mastered")
    expect(slider(page, "Rotation")).to_be_disabled()
    expect(line).to_contain_text("Playing sequence 'gentle-wave'")
    with server.http() as http:
        shown = http.get("/api/robots/demo-arm").json()
        assert shown["paused_master"] is None and not shown["master"]["paused"]


def hand_position(server: LiveServer, robot: str) -> list[float]:
    """The hand's commanded tool point (metres), as the API says it."""
    with server.http() as http:
        pose = http.get(f"/api/robots/{robot}/pose").json()
    return [float(v) for v in pose["commanded"]["position"]]


def moved_along(server: LiveServer, start: list[float], axis: int, sign: int) -> float:
    """How far the hand has gone from `start` along `axis` (`sign`: the way it should), once
    that is over 1 cm (or the wait's bound has passed)."""
    ends = time.monotonic() + WAIT_MS / 1000
    moved = 0.0
    while time.monotonic() < ends:
        moved = sign * (hand_position(server, "demo-arm")[axis] - start[axis])
        if moved > 0.01:
            break
        time.sleep(0.05)
    return moved


def test_the_keyboard_drives_the_hand_over_the_master_websocket(
    start_live: Any, page: Page
) -> None:
    server = start_live(demo=True)
    page.goto(server.url + "/ui/#/robots/demo-arm")
    expect(page.locator("#robot-state")).to_have_text("idle")
    page.click("#drive-hand")
    expect(page.locator("#drive-status")).to_contain_text("driving")
    expect(page.locator("#robot-state")).to_have_text("mastered")
    start = hand_position(server, "demo-arm")
    for key, axis, sign in [("w", 2, 1), ("ArrowUp", 0, 1), ("ArrowLeft", 1, 1)]:
        page.keyboard.down(key)  # held: the hand goes at 5 cm/s along the key's axis
        moved = moved_along(server, start, axis, sign)
        page.keyboard.up(key)
        assert moved > 0.01, (key, moved)
        # Let go: the hand stops (within the dead-man time); the other axes stayed put.
        time.sleep(1.0)
        stopped = hand_position(server, "demo-arm")
        time.sleep(0.5)
        assert hand_position(server, "demo-arm") == pytest.approx(stopped, abs=1e-4)
        for other in {0, 1, 2} - {axis}:
            assert stopped[other] == pytest.approx(start[other], abs=0.003), (key, other)
        start = stopped
    page.click("#drive-hand")  # stop driving: the master lets go of the robot
    expect(page.locator("#robot-state")).to_have_text("idle")


def test_a_websocket_master_s_link_shows_beside_it_green_then_red_when_commands_come_late(
    start_live: Any, page: Page
) -> None:
    server = start_live(demo=True, command_max_age=0.05)
    page.goto(server.url + "/ui/#/robots/demo-arm")
    ws_url = server.url.replace("http://", "ws://") + "/ws/master/demo-arm?id=alice"
    first = time.time() * 1000

    def command(stamp: float) -> str:
        data = {"timestamp": stamp, "joints": [{"name": "Rotation", "value": 1}]}
        return json.dumps({"type": "command", "data": data})

    with websockets.sync.client.connect(ws_url) as alice:  # (it answers the server's pings)
        alice.send(command(first))
        tag = page.locator('#peers li[data-peer="alice"] .tag.link')
        expect(tag).to_have_class(re.compile(r"\bgood\b"), timeout=WAIT_MS)  # loopback
        expect(tag).to_contain_text("ms")
        # Stamps a millisecond apart sent at least 0.3 s apart: each arrives later than the
        # 50 ms allowed, is dropped and counted, and the link shows red.
        stop = threading.Event()

        def late() -> None:
            stamp = first
            while not stop.wait(0.3):
                stamp += 1
                alice.send(command(stamp))

        sender = threading.Thread(target=late, daemon=True)
        sender.start()
        try:
            expect(tag).to_have_class(re.compile(r"\bpoor\b"), timeout=WAIT_MS)
            expect(tag).to_contain_text("stale")
        finally:
            stop.set()
            sender.join()


def test_driving_the_hand_while_a_master_runs_intervenes_and_hands_back(
    start_live: Any, page: Page
) -> None:
    server = start_live(demo=True)
    with server.http() as http:
        sequence = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
        assert http.post("/api/robots/demo-arm/master", json=sequence).status_code == 201
    page.goto(server.url + "/ui/#/robots/demo-arm")
    state = page.locator("#robot-state")
    expect(state).to_have_text("mastered")
    expect(page.locator("#who-drives")).to_have_text(
        "drives: sequence 'gentle-wave' in a loop (master 'master-1', mock-sequence)"
    )
    page.click("#episode-start")
    corrections = page.locator("#corrections")
    expect(corrections).to_have_text("0 corrections in this episode (0 in all)")
    page.click("#drive-hand")
    # The keyboard corrects the sequence: it waits, paused, while the hand is driven.
    expect(state).to_have_text("intervened")
    expect(page.locator("#drive-status")).to_contain_text("correcting")
    expect(page.locator("#who-drives")).to_have_text(
        "drives: WebSocket client (master 'dashboard-hand', websocket); "
        "waits: sequence 'gentle-wave' in a loop (master 'master-1', mock-sequence)"
    )
    expect(corrections).to_have_text("1 correction in this episode (1 in all)")
    with server.http() as http:
        shown = http.get("/api/robots/demo-arm").json()
    assert shown["master"]["id"] == "dashboard-hand"
    assert shown["paused_master"]["kind"] == "mock-sequence"
    start = hand_position(server, "demo-arm")
    page.keyboard.down("w")
    moved = moved_along(server, start, 2, 1)
    page.keyboard.up("w")
    assert moved > 0.01
    # Stop driving: the correction ends and the sequence plays again.
    page.click("#drive-hand")
    expect(state).to_have_text("mastered")
    expect(page.locator("#master-line")).to_contain_text("Playing sequence 'gentle-wave'")
    with server.http() as http:
        shown = http.get("/api/robots/demo-arm").json()
    assert shown["paused_master"] is None and shown["master"]["kind"] == "mock-sequence"


#: A gamepad the page sees through `navigator.getGamepads` (the standard mapping), set from the
#: test with `window.testPad(axes, triggers)`.
SYNTHETIC_GAMEPAD = """
window.testPad = (axes, triggers = [0, 0]) => {
  const buttons = Array.from({ length: 17 }, () => ({ value: 0, pressed: false }));
  buttons[6] = { value: triggers[0], pressed: triggers[0] > 0.5 };
  buttons[7] = { value: triggers[1], pressed: triggers[1] > 0.5 };
  window.pad = { id: "Test pad", index: 0, connected: true, mapping: "standard", axes, buttons };
};
window.pad = null;
navigator.getGamepads = () => [window.pad, null, null, null];
"""


def held_still(server: LiveServer, seconds: float = 1.0) -> list[float]:
    """The hand's position after `seconds` in which it must not have moved."""
    before = hand_position(server, "demo-arm")
    time.sleep(seconds)
    after = hand_position(server, "demo-arm")
    assert after == pytest.approx(before, abs=1e-4)
    return after


def assert_along(start: list[float], stopped: list[float], axis: int, what: object) -> None:
    """The hand went from `start` to `stopped` along `axis`: the other two axes moved at most
    3 mm, or a quarter of the way it went (the test lets go only once it has seen 1 cm: on a
    loaded machine the hand may go further meanwhile, the inverse kinematics drifting with it)."""
    bound = max(0.003, 0.25 * abs(stopped[axis] - start[axis]))
    for other in {0, 1, 2} - {axis}:
        assert stopped[other] == pytest.approx(start[other], abs=bound), (what, other)


def test_a_gamepad_drives_the_hand_with_a_dead_zone(start_live: Any, page: Page) -> None:
    server = start_live(demo=True)
    page.add_init_script(SYNTHETIC_GAMEPAD)
    page.goto(server.url + "/ui/#/robots/demo-arm")
    expect(page.locator("#robot-state")).to_have_text("idle")
    page.click("#drive-hand")
    expect(page.locator("#drive-status")).to_contain_text("driving")
    page.evaluate("testPad([0, 0, 0, 0])")
    expect(page.locator("#drive-status")).to_contain_text("gamepad: Test pad")
    # A stick resting a little off its centre moves nothing.
    page.evaluate("testPad([0.1, -0.1, 0, 0.12])")
    start = held_still(server)
    # Right stick up: up (z); left stick up: forward (x); left: to the left (y).
    for axes, axis in [([0, 0, 0, -1], 2), ([0, -1, 0, 0], 0), ([-1, 0, 0, 0], 1)]:
        page.evaluate(f"testPad({axes})")
        moved = moved_along(server, start, axis, 1)
        page.evaluate("testPad([0, 0, 0, 0])")
        assert moved > 0.01, (axes, moved)
        stopped = held_still(server)
        assert_along(start, stopped, axis, axes)
        start = stopped
    # The right trigger closes the gripper.
    with server.http() as http:
        before = http.get("/api/robots/demo-arm/pose").json()["commanded"]["gripper"]
    page.evaluate("testPad([0, 0, 0, 0], [0, 1])")
    ends = time.monotonic() + WAIT_MS / 1000
    closed = before
    while time.monotonic() < ends and closed > before - 5:
        with server.http() as http:
            closed = http.get("/api/robots/demo-arm/pose").json()["commanded"]["gripper"]
        time.sleep(0.05)
    page.evaluate("testPad([0, 0, 0, 0])")
    assert closed <= before - 5
    page.click("#drive-hand")
    expect(page.locator("#robot-state")).to_have_text("idle")


def orient(page: Page, beta: float, gamma: float) -> None:
    """A DeviceOrientation event, as a phone's sensor sends it."""
    page.evaluate(
        "([beta, gamma]) => window.dispatchEvent(new DeviceOrientationEvent("
        "'deviceorientation', { alpha: 0, beta, gamma, absolute: false }))",
        [beta, gamma],
    )


def test_a_phone_s_tilt_drives_the_hand_while_a_clutch_is_held(
    start_live: Any, browser: Browser
) -> None:
    server = start_live(demo=True)
    phone = {"viewport": {"width": 390, "height": 844}, "is_mobile": True, "has_touch": True}
    with checked_page(browser, "phone_tilt", **phone) as page:
        page.goto(server.url + "/ui/#/robots/demo-arm")
        expect(page.locator("#robot-state")).to_have_text("idle")
        expect(page.locator("#tilt-row")).to_be_hidden()
        page.click("#drive-hand")
        expect(page.locator("#drive-status")).to_contain_text("driving")
        expect(page.locator("#tilt-move")).to_be_visible()
        orient(page, 40, 0)  # held at 40 degrees, as one reads a phone
        start = hand_position(server, "demo-arm")
        orient(page, 10, 0)  # tipped without the clutch: nothing moves
        start = held_still(server)
        # Held at 40 degrees, a clutch pressed, the phone tipped: the hand goes its way.
        # (in the keyboard test's order: the arm's reach keeps each way within its bounds)
        for button, beta, gamma, axis, sign in [
            ("#tilt-lift", 70, 0, 2, 1),  # the top back toward the face: up
            ("#tilt-move", 10, 0, 0, 1),
            ("#tilt-move", 40, 30, 1, -1),  # the right edge down: to the right
        ]:
            orient(page, 40, 0)
            page.locator(button).dispatch_event("pointerdown", {"pointerId": 1})
            orient(page, beta, gamma)
            moved = moved_along(server, start, axis, sign)
            page.locator(button).dispatch_event("pointerup", {"pointerId": 1})
            assert moved > 0.01, (button, beta, gamma, moved)
            stopped = held_still(server)  # let go: it stops, however the phone is held
            assert_along(start, stopped, axis, button)
            start = stopped
        page.click("#drive-hand")
        expect(page.locator("#robot-state")).to_have_text("idle")
        expect(page.locator("#tilt-row")).to_be_hidden()


def test_a_leader_arm_attaches_from_the_card_and_corrects_a_running_master(
    start_live: Any, page: Page, tmp_path: Path
) -> None:
    sims = running_sim(tmp_path / "leader")
    sim = next(sims)
    try:
        server = start_live(demo=True, calibration_dir=str(tmp_path / "calibrations"))
        page.goto(server.url + "/ui/#/robots/demo-arm")
        expect(page.locator("#robot-state")).to_have_text("idle")
        expect(page.locator("#attach-leader")).to_have_text("Attach leader arm")
        page.fill("#leader-port", str(sim.link))
        page.click("#attach-leader")
        expect(page.locator("#robot-state")).to_have_text("mastered", timeout=WAIT_MS)
        with server.http() as http:
            shown = http.get("/api/robots/demo-arm").json()
            assert shown["master"]["kind"] == "usb-master"
            assert http.delete("/api/robots/demo-arm/master").status_code == 200
            sequence = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
            assert http.post("/api/robots/demo-arm/master", json=sequence).status_code == 201
        # While a master runs, the leader arm corrects it (actuated: no jerk at the handover).
        expect(page.locator("#attach-leader")).to_have_text("Correct with the leader arm")
        page.check("#leader-actuated")
        page.click("#attach-leader")
        expect(page.locator("#robot-state")).to_have_text("intervened", timeout=WAIT_MS)
        expect(page.locator("#attach-status")).to_contain_text("leader arm corrects")
        with server.http() as http:
            shown = http.get("/api/robots/demo-arm").json()
        assert shown["master"]["kind"] == "usb-master"
        assert shown["paused_master"]["kind"] == "mock-sequence"
        page.click("#hand-back")
        expect(page.locator("#robot-state")).to_have_text("mastered")
    finally:
        sims.close()


def click_leader_at(page: Page, joint: str, fraction: float) -> float:
    """Click the simulated leader's slider of `joint` like a hand would; the value it took."""
    handle = page.locator(f'input[type=range][data-leader-joint="{joint}"]')
    return click_range_at(page, handle, fraction)


def wait_for_real(page: Page, joint: str, wanted: float) -> None:
    """Until the robot's measured `joint` on the page is within a degree and a half of `wanted`."""
    page.wait_for_function(
        """([joint, wanted]) => {
            const cell = document.querySelector(`td[data-real="${joint}"]`);
            return cell && Math.abs(parseFloat(cell.textContent) - wanted) < 1.5;
        }""",
        arg=[joint, wanted],
        timeout=WAIT_MS,
    )


def test_a_simulated_leader_moves_from_the_card_and_the_robot_follows(
    start_live: Any, page: Page, tmp_path: Path
) -> None:
    """Issue 61: with `--sim-leader` (make run) the card offers the server's simulated leader,
    attaches it, and moves its joints with sliders of its own; the robot follows, as its
    master and as a correction of a running one."""
    server = start_live(
        demo=True, sim_leader="so-arm100", calibration_dir=str(tmp_path / "calibrations")
    )
    with server.http() as http:
        (simulated,) = http.get("/api/robots/demo-arm/leader").json()["simulated"]
    page.goto(server.url + "/ui/#/robots/demo-arm")
    expect(page.locator("#robot-state")).to_have_text("idle")
    expect(page.locator("#leader-port")).to_have_value(simulated["port"])
    expect(page.locator("#sim-leader")).to_be_hidden()  # no leader attached yet
    page.click("#attach-leader")
    expect(page.locator("#robot-state")).to_have_text("mastered", timeout=WAIT_MS)
    expect(page.locator("#sim-leader")).to_be_visible()
    expect(page.locator("#sim-leader-note")).to_contain_text("it drives the robot")
    expect(slider(page, "Rotation")).to_be_disabled()  # the robot's own: the leader drives
    wanted = click_leader_at(page, "Rotation", 0.8)
    assert wanted > 20
    wait_for_real(page, "Rotation", wanted)
    assert real_value(server, "demo-arm", "Rotation") == pytest.approx(wanted, abs=1.5)
    # A correction: a sequence runs, the simulated leader intervenes from the card and drives.
    with server.http() as http:
        assert http.delete("/api/robots/demo-arm/master").status_code == 200
        sequence = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
        assert http.post("/api/robots/demo-arm/master", json=sequence).status_code == 201
    expect(page.locator("#attach-leader")).to_have_text("Correct with the leader arm")
    page.click("#attach-leader")
    expect(page.locator("#robot-state")).to_have_text("intervened", timeout=WAIT_MS)
    expect(page.locator("#sim-leader")).to_be_visible()
    wanted = click_leader_at(page, "Elbow", 0.25)
    wait_for_real(page, "Elbow", wanted)
    page.click("#hand-back")
    expect(page.locator("#robot-state")).to_have_text("mastered")
    expect(page.locator("#sim-leader")).to_be_hidden()  # the leader is gone with the correction


def test_a_policy_of_the_tenant_s_folder_attaches_from_the_card(
    start_live: Any,
    page: Page,
    tiny: Path,  # noqa: F811
    tmp_path: Path,
) -> None:
    policies = tmp_path / "policies"
    shutil.copytree(tiny, policies / "tiny-act")
    (policies / "notes").mkdir()  # not a policy: not offered
    server = start_live(demo=True, policy_dir=str(policies))
    with server.http() as http:
        assert http.post("/api/robots/demo-arm/cameras", json=CAMERA).status_code == 201
    page.goto(server.url + "/ui/#/robots/demo-arm")
    options = page.locator("#policy option")
    expect(options).to_have_text(["tiny-act (act)"])
    page.fill("#policy-task", "wave")
    page.click("#attach-policy")
    expect(page.locator("#robot-state")).to_have_text("mastered", timeout=2 * WAIT_MS)
    expect(page.locator("#attach-status")).to_contain_text("running policy:act:")
    expect(page.locator("#master-line")).to_contain_text("policy:act:")
    # Its live figures on the card, and on /metrics.
    figures = page.locator("#policy-figures")
    expect(figures).to_have_text(
        re.compile(r"^policy: inference \d+ ms, chunk 10, \d+ stalls?, [1-9]\d* inferences$"),
        timeout=WAIT_MS,
    )
    with server.http() as http:
        text = http.get("/metrics").text
    assert 'arena_policy_chunk_actions{robot="demo-arm"} 10' in text
    assert re.search(r'arena_policy_inferences_total\{robot="demo-arm"\} [1-9]', text)
    # (a loaded machine may make a stall: the series is there, whatever it counts)
    assert re.search(r'arena_policy_stalls_total\{robot="demo-arm"\} \d+\n', text)
    # Corrected from the keyboard, the policy waits and its figures stay in view.
    page.click("#drive-hand")
    expect(page.locator("#robot-state")).to_have_text("intervened")
    expect(page.locator("#who-drives")).to_contain_text("waits: policy:act:")
    expect(figures).to_be_visible()
    expect(page.locator("#corrections")).to_have_text("1 correction in all (no episode running)")
    page.click("#drive-hand")
    expect(page.locator("#robot-state")).to_have_text("mastered")
    with server.http() as http:
        shown = http.get("/api/robots/demo-arm").json()
    assert shown["master"]["kind"] == "policy"
    assert "'wave'" in shown["master"]["description"]


def test_a_new_arm_is_calibrated_from_the_card_step_by_step(
    start_live: Any, page: Page, tmp_path: Path
) -> None:
    sims = running_sim(tmp_path / "arm")
    sim = next(sims)
    try:
        server = start_live(calibration_dir=str(tmp_path / "calibrations"))
        with server.http() as http:
            assert http.post("/api/robots", json={"id": "arm"}).status_code == 201
            slave = {"type": "usb-slave", "port": str(sim.link)}
            assert http.post("/api/robots/arm/slaves", json=slave).status_code == 201
        page.goto(server.url + "/ui/#/robots/arm")
        step = page.locator("#calibration-step")
        expect(step).to_contain_text("not calibrated", timeout=WAIT_MS)
        page.click("#calibrate-start")
        expect(step).to_contain_text("1 of 2. Torque is off")
        expect(page.locator("#calibrate-start")).to_be_disabled()
        # Posed like the twin (every joint at 0): the horns sit at arbitrary raw steps.
        rest_raw = {1: 3000, 2: 1100, 3: 2500, 4: 700, 5: 3900, 6: 2048}
        with sim.paused() as bus:
            for sid, raw in rest_raw.items():
                bus.servo(sid).move_by_hand(raw)
        page.click("#calibrate-capture")
        expect(step).to_contain_text("2 of 2. Move each joint")
        # The base through its range: the twin's measured arm follows live, the range grows.
        rotation = page.locator('#calibration-ranges li[data-joint="Rotation"]')
        for delta in (-400, 300):
            with sim.paused() as bus:
                bus.servo(1).move_by_hand(rest_raw[1] + delta)
            expect(page.locator('td[data-real="Rotation"]')).to_have_text(
                f"{delta * 360 / 4096:.1f}", timeout=WAIT_MS
            )
        expect(rotation).to_contain_text("Rotation: -35.2 to 26.4", timeout=WAIT_MS)
        assert float(rotation.locator("meter").get_attribute("value") or 0) > 0
        page.click("#calibrate-finish")
        expect(step).to_contain_text("calibrated (", timeout=WAIT_MS)
        expect(page.locator("#calibration-ranges li")).to_have_count(0)
        with server.http() as http:
            stored = http.get("/api/robots/arm/calibration").json()
        assert stored["calibrated"] is True and stored["session"] is None
        joint = stored["calibration"]["joints"]["Rotation"]
        assert joint["min_degrees"] == pytest.approx(-400 * 360 / 4096, abs=0.01)
        assert joint["max_degrees"] == pytest.approx(300 * 360 / 4096, abs=0.01)
        assert (tmp_path / "calibrations" / "arm.json").is_file()
        # Started again and cancelled: the calibration in use stays.
        page.click("#calibrate-start")
        expect(step).to_contain_text("1 of 2")
        page.click("#calibrate-cancel")
        expect(step).to_contain_text("calibrated (")
        with server.http() as http:
            again = http.get("/api/robots/arm/calibration").json()
        assert again["session"] is None and again["calibration"] == stored["calibration"]
    finally:
        sims.close()


def test_the_calibration_flow_shows_only_for_a_hardware_arm(start_live: Any, page: Page) -> None:
    server = start_live(demo=True)  # the demo robot's slave is a mock
    page.goto(server.url + "/ui/#/robots/demo-arm")
    expect(page.locator("#robot-state")).to_have_text("idle")
    expect(page.locator("#peers li").first).to_contain_text("mock-slave")
    expect(page.locator("#calibration")).to_be_attached()
    expect(page.locator("#calibration")).to_be_hidden()
