"""What the numbers of a recording or a training run depend on beyond the code and the seed.

The same command with the same seed gives the same strokes and the same networks bit for bit on one machine, but
not always on another: NumPy's matrix products go to OpenBLAS, which picks its kernels by the CPU it finds (the
``architecture`` of :func:`numeric_environment`), and kernels that sum in another order round differently. That
is enough to change every shard of a data set (session 33: recorded on an AMD EPYC whose environment sets
``OPENBLAS_CORETYPE=Haswell``, with the same code and library versions, all 42 shards of ``data/clean`` and of
``data/fire`` differed from the earlier sessions'; with ``OPENBLAS_CORETYPE=SkylakeX`` every shard came out as
before). Torch's CPU kernels round by the CPU as well, so a network trained again elsewhere can differ too. The recorder writes this
record into the data set's manifest and the evaluation into its provenance, so a recording that no longer
matches can be explained, and matched again, from the files alone.

Only package metadata and the BLAS libraries already loaded are read: importing this module imports no
simulator and no torch.
"""

from __future__ import annotations

import importlib.metadata
import os
import platform
from typing import Any

import threadpoolctl

ENV_VARS = ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES", "MKL_CBWR", "ATEN_CPU_CAPABILITY")
"""Environment variables that choose the CPU code paths of those packages (recorded when set)."""


def numeric_environment(packages: tuple[str, ...]) -> dict[str, Any]:
    """A JSON-ready record of what the floating-point results depend on here: the machine, the CPU's model,
    the versions of ``packages`` (distribution names; ``None`` where one is not installed), each loaded BLAS
    library with the kernel family it chose (``architecture``), and whichever of :data:`ENV_VARS` is set."""
    import numpy  # noqa: F401  (loads NumPy's OpenBLAS, so threadpoolctl can report it)

    versions: dict[str, str | None] = {}
    for name in packages:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    blas = sorted(({"api": str(pool.get("internal_api")), "version": str(pool.get("version")),
                    "architecture": str(pool.get("architecture"))}
                   for pool in threadpoolctl.threadpool_info() if pool.get("user_api") == "blas"),
                  key=lambda entry: (entry["api"], entry["version"], entry["architecture"]))
    return {"machine": platform.machine(), "cpu": cpu_model(), "packages": versions, "blas": blas,
            "env": {name: os.environ[name] for name in ENV_VARS if name in os.environ}}


def cpu_model() -> str:
    """The CPU's model name as the kernel reports it (``/proc/cpuinfo``), else :func:`platform.processor`."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as handle:
            for line in handle:
                key, _, value = line.partition(":")
                if key.strip() == "model name":
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def numerics_differences(here: dict[str, Any] | None, there: dict[str, Any] | None,
                         results_only: bool = False) -> list[str]:
    """What differs from ``there`` (an earlier :func:`numeric_environment` record) to ``here``, one short
    phrase each (``[]`` when they agree); a record that is missing (a manifest written before they were kept)
    gives ``["not recorded"]``. ``results_only`` leaves out what does not change a result by itself: the CPU's
    name and the environment variables (the BLAS kernels they lead to are compared)."""
    if not isinstance(here, dict) or not isinstance(there, dict):
        return ["not recorded"]
    out = []
    for key in ("machine",) if results_only else ("machine", "cpu"):
        if here.get(key) != there.get(key):
            out.append(f"{key} {there.get(key)!r} -> {here.get(key)!r}")
    packages_here, packages_there = here.get("packages") or {}, there.get("packages") or {}
    for name in sorted(set(packages_here) & set(packages_there)):  # the packages both records name
        if packages_here.get(name) != packages_there.get(name):
            out.append(f"{name} {packages_there.get(name)} -> {packages_here.get(name)}")
    if here.get("blas") != there.get("blas"):
        def kernels(record: dict[str, Any]) -> str:
            return ", ".join(f"{b.get('api')} {b.get('architecture')}" for b in record.get("blas") or []) or "none"
        out.append(f"BLAS kernels {kernels(there)} -> {kernels(here)}")
    if not results_only and (here.get("env") or {}) != (there.get("env") or {}):
        out.append(f"environment {there.get('env') or {}} -> {here.get('env') or {}}")
    return out
