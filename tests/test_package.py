"""The package: an sdist and a wheel that install where there is no checkout and no Node, and
serve the dashboard, the docs and the demo robot from what they carry."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from arena.server import dashboard
from tests.conftest import missing
from tests.serve_process import serving

ROOT = Path(__file__).resolve().parent.parent
#: Extras' modules: the server must start without importing any of them.
EXTRA_MODULES = ("mujoco", "lerobot", "torch", "zenoh", "matplotlib")


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """`python -m build`: the sdist, then the wheel built from that sdist (so both carry it all)."""
    try:
        import build  # noqa: F401
    except ImportError:
        missing("needs build (the `dev` extra): pip install build")
    if not dashboard.is_built():
        missing("the dashboard is not built: make ui")
    out = tmp_path_factory.mktemp("dist")
    subprocess.run(
        [sys.executable, "-m", "build", "--no-isolation", "--outdir", str(out), str(ROOT)],
        check=True,
        capture_output=True,
        timeout=300,
    )
    yield out


def without_checkout() -> dict[str, str]:
    """This process's environment without the checkout on the path."""
    return {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}


def wheel_of(folder: Path) -> Path:
    (wheel,) = folder.glob("arena-*.whl")
    return wheel


def test_the_sdist_and_the_wheel_carry_dashboard_robot_types_and_schemas(built: Path) -> None:
    names = set(zipfile.ZipFile(wheel_of(built)).namelist())
    (sdist,) = built.glob("arena-*.tar.gz")
    with tarfile.open(sdist) as archive:
        in_sdist = {name.split("/", 1)[1] for name in archive.getnames() if "/" in name}
    for tree in (ROOT / "arena" / "dashboard" / "dist", ROOT / "arena" / "robot_types"):
        for file in tree.rglob("*"):
            if file.is_file():
                relative = file.relative_to(ROOT).as_posix()
                assert relative in names, relative
                assert relative in in_sdist, relative
    schemas = sorted((ROOT / "specs" / "schemas").glob("*.json"))
    assert len(schemas) > 20
    for schema in schemas:
        assert f"arena/json_schemas/{schema.name}" in names
        assert f"specs/schemas/{schema.name}" in in_sdist
    assert not any("node_modules" in name for name in names | in_sdist)


@pytest.fixture(scope="module")
def installed(built: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh virtualenv with the wheel installed (no Node, no checkout). Its dependencies come
    from this test run's environment, appended to its path by a `.pth` line (which, unlike a
    site directory, runs none of that environment's `.pth` files: not its editable `arena`)."""
    venv = tmp_path_factory.mktemp("venv")
    base = getattr(sys, "_base_executable", sys.executable)
    subprocess.run([base, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    pip = [sys.executable, "-m", "pip", "--python", str(python)]
    subprocess.run(
        [*pip, "install", "--quiet", "--no-deps", str(wheel_of(built))],
        check=True,
        timeout=300,
        env=without_checkout(),
    )
    site = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    (Path(site) / "zz_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return python


def test_the_installed_wheel_serves_ui_docs_and_the_demo_robot_without_the_checkout(
    installed: Path, tmp_path: Path
) -> None:
    env = without_checkout()
    where = subprocess.run(
        [installed, "-c", "import arena, json, sys; print(json.dumps([arena.__file__, sys.path]))"],
        capture_output=True,
        text=True,
        check=True,
        cwd=tmp_path,
        env=env,
    ).stdout
    module, path = json.loads(where)
    assert module.startswith(str(installed.parent.parent)), module  # the wheel's copy
    # No other entry of its path holds an `arena` (the checkouts' `.pth` files are not run).
    holding = [entry for entry in path if (Path(entry or tmp_path) / "arena").exists()]
    assert holding == [str(Path(module).parent.parent)], path
    with serving(
        ["--demo", "--port", "0"],
        cwd=tmp_path,
        env=env,
        python=str(installed),
    ) as served:
        ui = httpx.get(f"{served.url}/ui/", timeout=10)
        assert ui.status_code == 200 and ui.text == (dashboard.BUILD_DIR / "index.html").read_text()
        script = httpx.get(f"{served.url}/ui/app.js", timeout=10)
        assert script.content == (dashboard.BUILD_DIR / "app.js").read_bytes()
        assert "Arena API" in httpx.get(f"{served.url}/docs", timeout=10).text
        robots = httpx.get(f"{served.url}/api/robots", timeout=10).json()
        assert [robot["id"] for robot in robots] == ["demo-arm"]
        mesh = httpx.get(
            f"{served.url}/api/robot-types/so-arm100/files/meshes/Base.stl", timeout=10
        )
        source = ROOT / "arena" / "robot_types" / "so-arm100" / "meshes" / "Base.stl"
        assert mesh.content == source.read_bytes()
        assert httpx.get(f"{served.url}/readyz", timeout=10).status_code == 200
        # Recorded where it was started: the first batch (within a quarter second) opens the
        # file; the server is killed at the end of this block, so wait for it here.
        deadline = time.monotonic() + 60
        while not list((tmp_path / "recordings").glob("*.mcap")):
            assert time.monotonic() < deadline, "no recording in the folder it was started in"
            time.sleep(0.05)


def test_arena_serve_starts_without_importing_any_extra(installed: Path, tmp_path: Path) -> None:
    """Everything `arena serve` imports before it listens (the extras are importable here)."""
    code = (
        "import sys, arena.cli, arena.server.run, arena.server.app\n"
        f"print([m for m in {EXTRA_MODULES!r} if m in sys.modules])\n"
    )
    env = without_checkout()
    done = subprocess.run(
        [installed, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path, env=env
    )
    assert done.stdout.strip() == "[]"


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_a_wheel_without_the_built_dashboard_is_refused(tmp_path: Path) -> None:
    """A checkout where `make ui` has not run: no wheel that would answer /ui/ with 404."""
    try:
        import build  # noqa: F401
    except ImportError:
        missing("needs build (the `dev` extra): pip install build")
    tracked = subprocess.run(
        ["git", "-C", str(ROOT), "ls-files", "-z"], capture_output=True, check=True, text=True
    ).stdout.split("\0")
    source = tmp_path / "source"
    for name in filter(None, tracked):  # the files git has, as they are now (no dist/)
        if (ROOT / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(ROOT / name, source / name)
    done = subprocess.run(
        [sys.executable, "-m", "build", "--no-isolation", "--wheel", "--outdir", "out", "."],
        capture_output=True,
        text=True,
        cwd=source,
        timeout=300,
    )
    assert done.returncode != 0
    assert "arena/dashboard/dist/index.html is missing: build the dashboard first" in (
        done.stdout + done.stderr
    )
    assert not list((source / "out").glob("*.whl"))
