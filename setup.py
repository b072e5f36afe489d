"""Packaging hook: a wheel carries the built dashboard and the JSON schemas (pyproject.toml has
the rest). The dashboard is built by Node beforehand (`make ui`, or the Dockerfile's first
stage), so that the wheel, and the sdist it may be built from, install where there is no Node.
An editable install (`make run`) needs neither: it serves from the checkout."""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
DASHBOARD = ROOT / "arena" / "dashboard" / "dist" / "index.html"
SCHEMAS = ROOT / "specs" / "schemas"


class BuildWithAssets(build_py):
    """`build_py`, refusing to make a wheel without the dashboard, and adding the schemas."""

    def run(self) -> None:
        if not self.editable_mode and not DASHBOARD.is_file():
            raise SystemExit(
                f"{DASHBOARD.relative_to(ROOT)} is missing: build the dashboard first "
                "(`make ui`, which needs Node.js), so that the package serves /ui/."
            )
        super().run()
        if not self.editable_mode:
            target = Path(self.build_lib) / "arena" / "json_schemas"
            target.mkdir(parents=True, exist_ok=True)
            for schema in sorted(SCHEMAS.glob("*.json")):
                shutil.copyfile(schema, target / schema.name)


setup(cmdclass={"build_py": BuildWithAssets})
