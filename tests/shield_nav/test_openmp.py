"""The OpenMP spin limit: set where the user chose nothing, never over their choice, and before libgomp loads."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from shield_nav.openmp import SPINCOUNT, limit_spinning

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_sets_the_spin_count_where_nothing_is_chosen():
    env = {"PATH": "/bin"}
    assert limit_spinning(env) is True
    assert env == {"PATH": "/bin", "GOMP_SPINCOUNT": "10000"}
    assert SPINCOUNT == "10000"


@pytest.mark.parametrize("key,value", [("GOMP_SPINCOUNT", "300000"), ("OMP_WAIT_POLICY", "ACTIVE")])
def test_the_users_choice_stands(key, value):
    env = {key: value}
    assert limit_spinning(env) is False
    assert env == {key: value}  # nothing added, nothing changed


_PROBE = """
import os, runpy, sys
runpy.run_path({script!r}, run_name="probe")  # the module's top level, not its main()
maps = open("/proc/self/maps").read()
print(os.environ.get("GOMP_SPINCOUNT"), "libgomp" in maps, "torch" in sys.modules)
"""


def _probe(script: str, env: dict) -> list[str]:
    """GOMP_SPINCOUNT, whether libgomp is mapped, whether torch is imported, after ``script``'s top level ran."""
    out = subprocess.run(
        [sys.executable, "-c", _PROBE.format(script=os.path.join(REPO, script))],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    return out.stdout.split()


@pytest.mark.skipif(not os.path.exists("/proc/self/maps"), reason="needs /proc (Linux)")
@pytest.mark.parametrize("script", ["train.py", "eval.py"])
def test_entry_points_set_it_before_libgomp_loads(script):
    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    # Set, and no OpenMP runtime loaded yet: torch and numba read it when they load.
    assert _probe(script, env) == ["10000", "False", "False"]
    assert _probe(script, {**env, "GOMP_SPINCOUNT": "300000"})[0] == "300000"


_TOOL_PROBE = """
import os, runpy, sys
sys.argv = [{module!r}, "--help"]
try:
    runpy.run_module({module!r}, run_name={run_name!r}, alter_sys=True)
except SystemExit as e:  # argparse's --help
    assert e.code == 0, e.code
print(os.environ.get("GOMP_SPINCOUNT"))
"""


@pytest.mark.parametrize(
    "module", ["shield_nav.tools.imitation", "shield_nav.tools.route_view", "shield_nav.tools.speed_budget"]
)
def test_analysis_tools_set_it_only_when_run_as_tools(module):
    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}

    def probe(run_name: str) -> str:
        code = _TOOL_PROBE.format(module=module, run_name=run_name)
        out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                             timeout=120, check=True)  # fmt: skip
        return out.stdout.split()[-1]

    assert probe("__main__") == "10000"  # python -m: set, as train.py and eval.py do
    assert probe("imported") == "None"  # imported as a library: the environment is the caller's
