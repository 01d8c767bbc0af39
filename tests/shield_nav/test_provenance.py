"""Package versions recorded with every evaluation and checkpoint (shield_nav.provenance)."""

import os
import platform

import mujoco
import numpy as np
import scipy
import torch

from shield_nav.provenance import (
    PACKAGES,
    SIMD_FLAGS,
    cpu_model,
    cpu_simd,
    format_differences,
    manifest_record,
    package_versions,
    version_differences,
)


def test_package_versions_are_the_imported_modules_own():
    v = package_versions()
    assert set(v) == {"python", *PACKAGES}
    assert v["python"] == platform.python_version()
    # Each module's own version attribute, read independently of the installed distribution's metadata.
    assert v["numpy"] == np.__version__ and v["scipy"] == scipy.__version__
    assert v["torch"] == torch.__version__ and v["mujoco"] == mujoco.__version__


def test_a_package_that_is_not_installed_is_none():
    assert package_versions(("numpy", "no-such-distribution-shield-nav")) == {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "no-such-distribution-shield-nav": None,
    }


def test_version_differences_by_hand():
    a = {"python": "3.11.7", "numpy": "2.4.6", "scipy": "1.17.1", "daqp": None}
    b = {"python": "3.12.3", "numpy": "2.4.6", "scipy": "1.18.1", "daqp": "0.11.0", "extra": "1"}
    diff = version_differences(a, b)
    # Only names both hold; None against a version is a difference; "extra" is on one side only.
    assert diff == {"daqp": [None, "0.11.0"], "python": ["3.11.7", "3.12.3"], "scipy": ["1.17.1", "1.18.1"]}
    assert format_differences(diff) == "daqp None / 0.11.0, python 3.11.7 / 3.12.3, scipy 1.17.1 / 1.18.1"
    assert version_differences(a, a) == {} and format_differences({}) == ""
    # An output written before versions were recorded: unknown is not reported as different.
    assert version_differences(None, b) == {} and version_differences(a, None) == {}


def test_cpu_model_is_the_first_model_name_of_proc_cpuinfo():
    try:
        with open("/proc/cpuinfo") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
    except OSError:
        names = []
    if names:
        assert cpu_model() == names[0] != ""
    else:  # not Linux: whatever the platform module says, a string
        assert cpu_model() == platform.processor()


def test_cpu_simd_is_the_known_flags_of_proc_cpuinfo_in_order():
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((ln.split(":", 1)[1].split() for ln in f if ln.startswith(("flags", "Features"))), None)
    except OSError:
        flags = None
    if flags is None:
        assert cpu_simd() is None
        return
    got = cpu_simd().split()
    assert got == [f for f in SIMD_FLAGS if f in flags]  # the recorded order, only known flags
    assert set(got) <= set(flags)


def test_manifest_record_adds_simd_only_where_recorded():
    pk = {"python": "3.11.7", "numpy": "2.4.6"}
    assert manifest_record({"packages": pk, "cpu_simd": "avx avx2 fma"}) == {**pk, "cpu_simd": "avx avx2 fma"}
    old = manifest_record({"packages": pk})  # written before cpu_simd was recorded
    assert old == pk and manifest_record({}) is None
    # Unknown is not different; a known other processor is.
    assert version_differences(old, {**pk, "cpu_simd": "avx avx2"}) == {}
    new = {**pk, "cpu_simd": "avx avx2 fma avx512f"}
    assert version_differences(manifest_record({"packages": pk, "cpu_simd": "avx avx2 fma"}), new) == {
        "cpu_simd": ["avx avx2 fma", "avx avx2 fma avx512f"]
    }


def test_bench_machine_facts_name_the_processor():
    """Every bench JSON carries the processor beside the timings (machines named alike differ in SIMD)."""
    from shield_nav.bench.common import machine

    facts = machine()
    assert facts["cpu_model"] == cpu_model() and facts["cpu_simd"] == cpu_simd()
    assert facts["cpu_count"] == os.cpu_count() and facts["machine"] == platform.machine()
