"""scripts/constraints.txt, the exact versions `make setup` installs: it has to satisfy pyproject.toml's ranges, and
the environment the tests run in (made by `make setup`) has to hold those versions."""

import re
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;]+)$")


def pinned_versions() -> dict[str, str]:
    pins = {}
    for number, line in enumerate((ROOT / "scripts" / "constraints.txt").read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        match = PIN.match(line.strip())
        assert match, f"scripts/constraints.txt line {number}: not 'name==version': {line!r}"
        name = canonicalize_name(match.group(1))
        assert name not in pins, f"scripts/constraints.txt line {number}: {name} pinned twice"
        pins[name] = match.group(2)
    return pins


def direct_requirements() -> list[Requirement]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = [r for group in project["optional-dependencies"].values() for r in group]
    return [Requirement(r) for r in project["dependencies"] + extras]


def test_every_dependency_of_pyproject_is_pinned_inside_its_range():
    pins = pinned_versions()
    for requirement in direct_requirements():
        name = canonicalize_name(requirement.name)
        assert name in pins, f"{requirement} (pyproject.toml) has no pin in scripts/constraints.txt"
        assert requirement.specifier.contains(pins[name], prereleases=True), \
            f"scripts/constraints.txt pins {name}=={pins[name]}, outside pyproject.toml's {requirement}"


def test_the_environment_holds_the_pinned_versions_of_the_direct_dependencies():
    pins = pinned_versions()
    for requirement in direct_requirements():
        name = canonicalize_name(requirement.name)
        assert metadata.version(name) == pins[name], \
            f"{name} {metadata.version(name)} installed, scripts/constraints.txt pins {pins[name]}: run make setup"
