"""What a recording's and a run's numbers depend on beyond code and seed: recorded, and compared."""

import copy

import numpy as np

from perception.numerics import numeric_environment, numerics_differences


def test_the_record_names_numpy_and_the_blas_kernels_numpy_chose():
    record = numeric_environment(("numpy", "no-such-distribution"))
    assert record["packages"] == {"numpy": np.__version__, "no-such-distribution": None}
    assert record["blas"] and all(b["architecture"] not in ("", "None") for b in record["blas"])
    assert record["machine"] and record["cpu"]
    assert numerics_differences(record, copy.deepcopy(record)) == []


def test_differences_name_what_changed_from_the_earlier_record():
    old = {"machine": "x86_64", "cpu": "Intel Xeon", "packages": {"numpy": "2.4.6", "scipy": "1.17.1"},
           "blas": [{"api": "openblas", "version": "0.3.31", "architecture": "SkylakeX"}], "env": {}}
    new = copy.deepcopy(old)
    new["cpu"] = "AMD EPYC"
    new["blas"][0]["architecture"] = "Haswell"
    new["env"] = {"OPENBLAS_CORETYPE": "Haswell"}
    assert numerics_differences(new, old) == ["cpu 'Intel Xeon' -> 'AMD EPYC'",
                                              "BLAS kernels openblas SkylakeX -> openblas Haswell",
                                              "environment {} -> {'OPENBLAS_CORETYPE': 'Haswell'}"]
    # what changes results by itself: the kernels, not the CPU's name or the variable that chose them
    assert numerics_differences(new, old, results_only=True) == ["BLAS kernels openblas SkylakeX -> openblas Haswell"]
    new["blas"] = old["blas"]
    assert numerics_differences(new, old, results_only=True) == []  # another CPU, the same kernels
    new["packages"] = {"numpy": "2.5.0", "torch": "2.13.0"}  # a package only one record names is not compared
    assert numerics_differences(new, old, results_only=True) == ["numpy 2.4.6 -> 2.5.0"]
    assert numerics_differences(new, None) == ["not recorded"]  # a manifest written before they were kept
