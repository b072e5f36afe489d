"""What the dashboard reads besides the robot API: robot types with URDF and meshes, a
recording's joints for a plot, and the page itself (public, while the API keeps its keys)."""

from __future__ import annotations

import math
import shutil
import xml.etree.ElementTree as ET
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from arena.recording.analysis import joint_series, thin
from arena.recording.mcap_file import read_recording
from arena.robot.model import BUILTIN_TYPES_DIR, TYPES_PATH_ENV
from arena.server import dashboard
from tests.conftest import RunningServer
from tests.golden import GOLDEN

Start = Callable[..., Awaitable[RunningServer]]


async def test_robot_types_give_joints_urdf_and_every_mesh(server: RunningServer) -> None:
    async with server.client() as http:
        types = (await http.get("/api/robot-types")).json()
        arm = (await http.get("/api/robot-types/so-arm100")).json()
        urdf = await http.get(arm["urdf"])
        assert [t["id"] for t in types] == ["koch", "so-101", "so-arm100"]
        assert types[2] == arm
        assert [j["name"] for j in arm["joints"]] == [
            "Rotation", "Pitch", "Elbow", "Wrist_Pitch", "Wrist_Roll", "Jaw",
        ]  # fmt: skip
        robot = (await http.get("/api/robots/demo-arm")).json()
        assert urdf.status_code == 200
        assert urdf.headers["content-type"].startswith("application/xml")
        document = ET.fromstring(urdf.text)
        urdf_limits = {
            str(joint.get("name")): joint.find("limit") for joint in document.iter("joint")
        }
        for spec, state in zip(arm["joints"], robot["joints"], strict=True):
            # The same limits as the robot's joint states; neutral (no robot.toml override
            # here) is the middle of the URDF range, and the wire limits are measured from it.
            assert spec["lower"] == pytest.approx(state["limits"]["lower"], abs=1e-6)
            assert spec["upper"] == pytest.approx(state["limits"]["upper"], abs=1e-6)
            limit = urdf_limits[spec["name"]]
            assert limit is not None
            lower, upper = float(limit.get("lower", 0)), float(limit.get("upper", 0))
            assert spec["neutral"] == pytest.approx((lower + upper) / 2)
            assert spec["lower"] == pytest.approx(math.degrees(lower - spec["neutral"]))
        meshes = [m.get("filename") for m in document.iter("mesh")]
        assert len(meshes) == 13
        for name in meshes:
            mesh = await http.get(arm["files"] + str(name))
            assert mesh.status_code == 200, name
            # A binary STL: 80-byte header, triangle count, 50 bytes a triangle.
            triangles = int.from_bytes(mesh.content[80:84], "little")
            assert len(mesh.content) == 84 + 50 * triangles > 84


@pytest.fixture
def outside_mesh(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Robot type `tmp-arm` (a copy of so-arm100) in a folder that also holds `outside.stl`."""
    types = tmp_path / "types"
    shutil.copytree(BUILTIN_TYPES_DIR / "so-arm100", types / "tmp-arm")
    (types / "outside.stl").write_bytes(b"not the type's own")
    monkeypatch.setenv(TYPES_PATH_ENV, str(types))
    return types / "outside.stl"


@pytest.mark.parametrize(
    ("path", "status", "code"),
    [
        ("/api/robot-types/no-such-arm", 422, "UNKNOWN_ROBOT_TYPE"),
        ("/api/robot-types/no-such-arm/urdf", 422, "UNKNOWN_ROBOT_TYPE"),
        ("/api/robot-types/tmp-arm/files/robot.toml", 404, "NOT_FOUND"),
        ("/api/robot-types/tmp-arm/files/meshes/LICENSE", 404, "NOT_FOUND"),
        ("/api/robot-types/tmp-arm/files/meshes/Nothing.stl", 404, "NOT_FOUND"),
        # outside.stl exists, one folder up: only the folder check keeps it in
        ("/api/robot-types/tmp-arm/files/..%2Foutside.stl", 404, "NOT_FOUND"),
        ("/api/robot-types/tmp-arm/files/meshes%2F..%2F..%2Foutside.stl", 404, "NOT_FOUND"),
        ("/api/robot-types/tmp-arm/files/%2Fetc%2Fpasswd.stl", 404, "NOT_FOUND"),
    ],
)
async def test_robot_type_files_are_meshes_of_the_type_and_nothing_else(
    server: RunningServer, outside_mesh: Path, path: str, status: int, code: str
) -> None:
    async with server.client() as http:
        own = await http.get("/api/robot-types/tmp-arm/files/meshes/Base.stl")
        answer = await http.get(path, follow_redirects=True)  # "//" is first merged by a 308
    assert own.status_code == 200  # the type is found, so refusals below are the folder check
    assert answer.status_code == status
    assert answer.json()["error"]["code"] == code
    assert outside_mesh.read_bytes() not in answer.content


async def test_a_recordings_joints_come_thinned_for_a_plot(
    start_server: Start, tmp_path: Path
) -> None:
    folder = tmp_path / "recordings"
    folder.mkdir()
    shutil.copy(GOLDEN / "manual-estop-reset.mcap", folder)
    server = await start_server(recordings_dir=str(folder), record=False)
    recording = read_recording(folder / "manual-estop-reset.mcap")
    robot = sorted({m.robot_id for m in recording.messages if m.robot_id})[0]
    full = joint_series(recording, robot)
    async with server.client() as http:
        answer = (await http.get("/api/recordings/manual-estop-reset.mcap/joints")).json()
        few = (
            await http.get("/api/recordings/manual-estop-reset.mcap/joints", params={"points": 3})
        ).json()
        bad = [
            await http.get("/api/recordings/manual-estop-reset.mcap/joints", params=params)
            for params in (
                {"points": "1"},
                {"points": "x"},
                {"points": "5001"},
                {"points": "²"},  # a digit to str.isdigit(), not to int()
                {"points": "9" * 5000},  # beyond int()'s digit limit
            )
        ]
        stranger = await http.get(
            "/api/recordings/manual-estop-reset.mcap/joints", params={"robot": "stranger"}
        )
        missing = await http.get("/api/recordings/nothing.mcap/joints")
    assert answer["robot"] == robot
    assert [j["name"] for j in answer["joints"]] == full.joints
    first = answer["joints"][0]
    assert first["virtual"] == [list(p) for p in full.virtual[first["name"]]]  # short: all kept
    assert answer["estops"] == full.estops and len(full.estops) == 1
    for joint in few["joints"]:
        whole = full.virtual.get(joint["name"], [])
        assert len(joint["virtual"]) == min(3, len(whole))
        if whole:  # the ends are kept
            assert joint["virtual"][0] == list(whole[0])
            assert joint["virtual"][-1] == list(whole[-1])
    for answer_ in bad:
        assert answer_.status_code == 422
        assert answer_.json()["error"]["code"] == "INVALID_VALUE"
    assert stranger.status_code == 404
    assert stranger.json()["error"]["code"] == "UNKNOWN_ROBOT"
    assert missing.json()["error"]["code"] == "UNKNOWN_RECORDING"


def test_thin_keeps_the_ends_and_spreads_the_rest() -> None:
    points = [(float(i), float(i * i)) for i in range(101)]
    assert thin(points, 200) == points
    picked = thin(points, 5)
    assert picked == [points[0], points[25], points[50], points[75], points[100]]
    assert thin(points, 1) == [points[-1]]
    assert thin(points, 0) == []


async def test_the_page_is_public_but_the_api_keeps_its_keys(
    start_server: Start, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    built = tmp_path / "dist"
    built.mkdir()
    (tmp_path / "secret.txt").write_text("beside the page, not part of it")
    (built / "index.html").write_text("<!doctype html><title>Arena</title>")
    (built / "app.js").write_text("export {};")
    monkeypatch.setattr(dashboard, "BUILD_DIR", built)
    server = await start_server(api_keys=("sekret",), demo=True)
    async with server.client() as http:
        root = await http.get("/ui", follow_redirects=False)
        page = await http.get("/ui/")
        script = await http.get("/ui/app.js")
        escape = await http.get("/ui/..%2Fsecret.txt")
        absent = await http.get("/ui/nothing.js")
        types = await http.get("/api/robot-types")
        types_with_key = await http.get(
            "/api/robot-types", headers={"Authorization": "Bearer sekret"}
        )
        browser = await http.get("/", headers={"Accept": "text/html,*/*;q=0.8"})
        program = await http.get("/", headers={"Authorization": "Bearer sekret"})
    assert root.status_code in (301, 302) and root.headers["location"].endswith("/ui/")
    assert page.status_code == 200 and "<title>Arena</title>" in page.text
    assert script.status_code == 200
    assert escape.status_code == 404 and escape.json()["error"]["code"] == "NOT_FOUND"
    assert absent.status_code == 404 and absent.json()["error"]["code"] == "NOT_FOUND"
    assert types.status_code == 401 and types.json()["error"]["code"] == "UNAUTHORIZED"
    assert types_with_key.status_code == 200
    # A browser asking for / is shown the page; a program gets the JSON status with a link.
    assert browser.status_code in (301, 302) and browser.headers["location"].endswith("/ui/")
    assert program.json()["links"]["dashboard"] == "/ui/"


async def test_an_unbuilt_page_says_how_to_build_it(
    server: RunningServer, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(dashboard, "BUILD_DIR", tmp_path / "nothing")
    async with server.client() as http:
        page = await http.get("/ui/")
        browser = await http.get("/", headers={"Accept": "text/html"})
    assert page.status_code == 404
    assert page.json()["error"] == {"code": "NOT_FOUND", "message": dashboard.NOT_BUILT}
    assert browser.status_code == 200 and browser.json()["name"] == "Arena"


async def test_the_so101_type_serves_its_meshes_and_a_percent_gripper(
    server: RunningServer,
) -> None:
    async with server.client() as http:
        arm = (await http.get("/api/robot-types/so-101")).json()
        urdf = await http.get(arm["urdf"])
        gripper = arm["joints"][-1]
        assert (gripper["name"], gripper["unit"], gripper["lower"], gripper["upper"]) == (
            "gripper",
            "percent",
            0,
            100,
        )
        # 0 % is the URDF's lower limit, 100 % its upper: -10 to 100 degrees of jaw
        assert gripper["neutral"] == pytest.approx(-0.174533)
        assert gripper["radians_per_unit"] * 100 == pytest.approx(1.74533 + 0.174533)
        pan = arm["joints"][0]
        assert (pan["unit"], pan["neutral"]) == ("deg", 0)
        assert pan["radians_per_unit"] == pytest.approx(math.pi / 180)
        meshes = {m.get("filename") for m in ET.fromstring(urdf.text).iter("mesh")}
        assert len(meshes) == 13
        for name in meshes:
            mesh = await http.get(arm["files"] + str(name))
            assert mesh.status_code == 200, name
