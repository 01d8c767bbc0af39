"""The install the README gives and CI runs: the reference environment in constraints.txt covers and satisfies
pyproject.toml's dependencies, and both the README and .ci/run install with it."""

import os
import re

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11; the reference environment is 3.11

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _pins() -> dict[str, str]:
    pins: dict[str, str] = {}
    with open(os.path.join(REPO, "constraints.txt")) as f:
        for line in f:
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            name, sep, version = line.partition("==")
            assert sep and version and ";" not in line, f"constraints.txt: {line!r} is not an exact pin NAME==VERSION"
            key = canonicalize_name(name)
            assert key not in pins, f"constraints.txt pins {name} twice"
            pins[key] = version
    return pins


def test_every_dependency_is_pinned_within_its_range():
    with open(os.path.join(REPO, "pyproject.toml"), "rb") as f:
        project = tomllib.load(f)["project"]
    pins = _pins()
    reqs = [Requirement(r) for r in [*project["dependencies"], *project["optional-dependencies"]["dev"]]]
    assert len(reqs) > 20
    for req in reqs:
        key = canonicalize_name(req.name)
        assert key in pins, f"{req.name} (pyproject.toml) has no pin in constraints.txt"
        assert req.specifier.contains(pins[key], prereleases=True), (
            f"constraints.txt pins {req.name}=={pins[key]}, outside pyproject.toml's {req.specifier}"
        )
        for extra in req.extras:  # qpsolvers[osqp]: the extra's solver is pinned too
            assert canonicalize_name(extra) in pins, f"{req.name}[{extra}]: {extra} has no pin"


def test_the_readme_and_ci_install_the_reference_environment():
    pins = _pins()
    with open(os.path.join(REPO, "README.md")) as f:
        readme = f.read()
    with open(os.path.join(REPO, ".ci", "run")) as f:
        ci = f.read()
    readme_install = re.search(r"^pip install torch==(\S+) && (pip install [^\n]*?)(?: && python eval.py)?$", readme,
                               re.M)  # fmt: skip
    assert readme_install, "README: the install command is not where this test looks for it"
    assert readme_install.group(1) == pins["torch"], "the README's torch differs from constraints.txt's"
    assert readme_install.group(2) == 'pip install -e ".[dev]" -c constraints.txt'
    assert f'pip install --quiet torch=={pins["torch"]} && pip install --quiet -e ".[dev]" -c constraints.txt' in ci
