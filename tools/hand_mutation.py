"""A pytest plugin that runs the tests against one hand-written mutant (`tools/mutants.py`,
`HAND_WRITTEN`), leaving the working tree as it is.

`tools/mutants.py` starts `python -m pytest -p tools.hand_mutation TESTS` with the mutant in the
environment (`ARENA_HAND_MUTANT`: JSON of file, original, mutated). Loaded before any test
module or conftest, the plugin puts an import hook first on `sys.meta_path`: the module whose
source is that file is compiled from its text with the one replacement made. A mutant whose
original text is not in the file exactly once stops the run (exit status 4, a usage error), so
that a stale entry is never counted as killed.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.util
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from types import CodeType, ModuleType

ENV = "ARENA_HAND_MUTANT"


def mutated_source(text: str, original: str, mutated: str, where: str) -> str:
    """`text` with `original` replaced by `mutated`; ValueError unless it occurs exactly once."""
    count = text.count(original)
    if count != 1:
        raise ValueError(f"{where}: {original!r} occurs {count} times (must be once)")
    return text.replace(original, mutated)


class _MutatedLoader(importlib.machinery.SourceFileLoader):
    """Loads one source file with the mutant's replacement made (never from a cached .pyc)."""

    def __init__(self, fullname: str, path: str, original: str, mutated: str) -> None:
        super().__init__(fullname, path)
        self.original = original
        self.mutated = mutated

    def get_code(self, fullname: str) -> CodeType:
        path = self.get_filename(fullname)
        text = Path(path).read_text(encoding="utf-8")
        source = mutated_source(text, self.original, self.mutated, path)
        return compile(source, path, "exec", dont_inherit=True)


class _Finder(importlib.abc.MetaPathFinder):
    """Finds modules as usual, but gives the mutated file its own loader."""

    def __init__(self, target: Path, original: str, mutated: str) -> None:
        self.target = target
        self.original = original
        self.mutated = mutated
        self.loaded = False

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is None or spec.origin is None or Path(spec.origin).resolve() != self.target:
            return None
        self.loaded = True
        loader = _MutatedLoader(fullname, spec.origin, self.original, self.mutated)
        return importlib.util.spec_from_file_location(fullname, spec.origin, loader=loader)


def _install() -> _Finder | None:
    raw = os.environ.get(ENV)
    if not raw:
        return None
    entry = json.loads(raw)
    target = Path(entry["file"]).resolve()
    # Checked now, so that a stale entry fails before any test runs.
    mutated_source(
        target.read_text(encoding="utf-8"), entry["original"], entry["mutated"], str(target)
    )
    if any(
        getattr(m, "__file__", None) and Path(m.__file__).resolve() == target
        for m in list(sys.modules.values())
    ):
        raise RuntimeError(f"{target} was imported before the mutant could be put in")
    finder = _Finder(target, entry["original"], entry["mutated"])
    sys.meta_path.insert(0, finder)
    return finder


_FINDER = _install()


def pytest_sessionfinish(session: object, exitstatus: int) -> None:
    """A mutant that no test imported was never tried: a usage error, not a survivor."""
    if _FINDER is not None and not _FINDER.loaded:
        print(f"\nhand mutant: no test imported {_FINDER.target}", file=sys.stderr)
        session.exitstatus = 4  # type: ignore[attr-defined]
