"""The shape of `arena/` (specs/architecture.md): layers, no import circles, no private names
across modules, no file over 600 lines. The checks are `tools/architecture.py`'s."""

from __future__ import annotations

import importlib.util
import sys
import textwrap
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parent.parent


def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "architecture", ROOT / "tools" / "architecture.py"
    )
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules["architecture"] = module
    spec.loader.exec_module(module)
    return module


arch = _tool()


def test_arena_keeps_its_shape() -> None:
    shape = arch.read(ROOT)
    assert len(shape.files) > 100
    assert arch.layer_breaks(shape) == []
    assert arch.circles(shape) == []
    assert shape.private == []
    assert arch.long_files(shape) == []


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = tmp_path / "arena" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return tmp_path


def test_every_kind_of_import_counts_toward_a_circle(tmp_path: Path) -> None:
    root = _tree(
        tmp_path,
        {
            "__init__.py": "",
            "robot/__init__.py": "",
            "robot/a.py": "from arena.robot import b\n",
            "robot/b.py": """\
                from typing import TYPE_CHECKING
                if TYPE_CHECKING:
                    from arena.robot.c import Thing
                """,
            "robot/c.py": """\
                def late():
                    from . import a
                """,
        },
    )
    assert arch.circles(arch.read(root)) == [["arena.robot.a", "arena.robot.b", "arena.robot.c"]]


def test_a_folder_may_not_import_upward_or_a_private_name(tmp_path: Path) -> None:
    root = _tree(
        tmp_path,
        {
            "__init__.py": "",
            "protocol/__init__.py": "",
            "protocol/wire.py": "from arena.robot.core import step\n",
            "robot/__init__.py": "",
            "robot/core.py": "from arena.protocol.wire import _secret\n\ndef step(): ...\n",
            "server/__init__.py": "",
            "server/app.py": "import arena.robot.core\n" + "x = 1\n" * 601,
        },
    )
    shape = arch.read(root)
    assert arch.layer_breaks(shape) == [
        "arena.protocol.wire -> arena.robot.core: protocol may not import robot"
    ]
    assert shape.private == [("arena.robot.core", "arena.protocol.wire._secret")]
    assert arch.long_files(shape) == [("arena.server.app", 602)]
