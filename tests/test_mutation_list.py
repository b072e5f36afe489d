"""The hand-written mutants `make mutants` runs beside mutmut's (tools/mutants.py,
`HAND_WRITTEN`) cannot rot: each one's text is still in its file exactly once, and the tests
expected to kill it still exist. Cheap: nothing is run against a mutant here."""

from __future__ import annotations

import ast
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


def load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(name, module)
    spec.loader.exec_module(module)
    return module


MUTANTS = load("mutants")
HOOK = load("hand_mutation")


def test_there_are_hand_written_mutants() -> None:
    assert MUTANTS.HAND_WRITTEN


@pytest.mark.parametrize("mutant", MUTANTS.HAND_WRITTEN, ids=lambda m: m.mutated)
def test_each_hand_written_mutant_still_applies_to_its_file(mutant: object) -> None:
    module, file = mutant.module, mutant.file  # type: ignore[attr-defined]
    assert MUTANTS.MODULES[module][0] == file, f"{file} is not the file of module {module}"
    text = (ROOT / file).read_text(encoding="utf-8")
    original, mutated = mutant.original, mutant.mutated  # type: ignore[attr-defined]
    assert text.count(original) == 1, f"{original!r} must occur once in {file}: update the list"
    changed = HOOK.mutated_source(text, original, mutated, file)
    assert changed != text
    ast.parse(changed)  # the mutant still compiles


@pytest.mark.parametrize("mutant", MUTANTS.HAND_WRITTEN, ids=lambda m: m.mutated)
def test_the_tests_that_kill_each_mutant_exist(mutant: object) -> None:
    for node in mutant.tests:  # type: ignore[attr-defined]
        path, _, name = node.partition("::")
        tree = ast.parse((ROOT / path).read_text(encoding="utf-8"))
        defined = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
        defined |= {n.name for n in ast.walk(tree) if isinstance(n, ast.AsyncFunctionDef)}
        assert not name or name.split("[")[0] in defined, f"{node} is gone"


def test_a_mutant_whose_text_is_gone_or_doubled_is_refused() -> None:
    with pytest.raises(ValueError, match="occurs 0 times"):
        HOOK.mutated_source("a = 1\n", "b = 2", "b = 3", "x.py")
    with pytest.raises(ValueError, match="occurs 2 times"):
        HOOK.mutated_source("a = 1\na = 1\n", "a = 1", "a = 2", "x.py")
