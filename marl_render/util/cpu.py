"""Which CPU this is: the model and instruction-set flags every result records, for machines here differ
(Xeons with AMX and AVX-512 BF16, AMD EPYCs without) and figures compare only within one CPU model."""
from __future__ import annotations

import platform


def cpu_model_and_flags() -> tuple[str, set[str]]:
    """/proc/cpuinfo's 'model name' (else platform.processor(), else "unknown") and its flags (empty off Linux)."""
    fields: dict = {}
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:  # the first processor's block is enough: every core of a machine is alike
                key, _, value = line.partition(":")
                fields.setdefault(key.strip(), value.strip())
                if not line.strip():
                    break
    except OSError:  # no /proc (not Linux): the model from platform alone
        pass
    return fields.get("model name") or platform.processor() or "unknown", set(fields.get("flags", "").split())
