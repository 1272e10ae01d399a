"""What CPU this is: absolute timings depend on it (one development CPU has AVX-512 with bf16,
another only AVX2), so every benchmark names it beside its figures."""

from __future__ import annotations

import os
import platform


def _cpuinfo() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return f.read()
    except OSError:  # not Linux
        return ""


def cpu_model() -> str:
    for line in _cpuinfo().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "cpu"


def cpu_flags() -> set[str]:
    for line in _cpuinfo().splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


def cpu_has_native_bf16() -> bool:
    """AVX512-BF16 or AMX: there bf16 3D convolutions are ~10x faster than fp32 (measured, 2-core EPYC)."""
    return bool({"avx512_bf16", "amx_bf16"} & cpu_flags())


def cpu_description() -> dict:
    """The CPU's name, cores and the instruction sets absolute timings depend on (for a JSON line)."""
    flags = cpu_flags()
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "avx512": "avx512f" in flags, "bf16": cpu_has_native_bf16()}
