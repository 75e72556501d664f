"""Which knobs change a training run's bits: the tiny golden run (marl_render/baselines/golden.py) in
the default and the reproducible mode, under environment settings that emulate another CPU's kernels.

    python tools/reproducible_knobs.py        # a markdown table (minutes: three processes per line)

Each line runs ``python -m marl_render.baselines.golden`` in a fresh process with one variable set (the
libraries read them when they load): ATEN_CPU_CAPABILITY picks ATen's AVX-512, AVX2 or baseline
kernels, ONEDNN_MAX_CPU_ISA caps oneDNN's, MKL_CBWR / MKL_ENABLE_INSTRUCTIONS / MKL_DEBUG_CPU_TYPE choose
MKL's branch, LP_NATIVE_VECTOR_WIDTH llvmpipe's vectors, and --threads torch's threads. The reproducible
mode sets its own pins (reproducible.ENVIRONMENT: ATEN_CPU_CAPABILITY, MKL_CBWR) over a line's, so such a
line shows that the mode overrides it; the other variables it leaves as given.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

PINNED = ("ATEN_CPU_CAPABILITY", "MKL_CBWR", "GALLIUM_OVERRIDE_CPU_CAPS")
VARIATIONS = ((), ("ATEN_CPU_CAPABILITY=avx2",), ("ATEN_CPU_CAPABILITY=default",), ("ONEDNN_MAX_CPU_ISA=AVX2",),
              ("ONEDNN_MAX_CPU_ISA=SSE41",), ("MKL_CBWR=AVX2",), ("MKL_CBWR=COMPATIBLE",),
              ("MKL_ENABLE_INSTRUCTIONS=AVX2",), ("MKL_DEBUG_CPU_TYPE=5",), ("LP_NATIVE_VECTOR_WIDTH=128",),
              ("--threads", "2"))


def hashes(variation: tuple, mode: str, precision: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k not in PINNED}
    argv = [sys.executable, "-m", "marl_render.baselines.golden", "--mode", mode]
    if variation[:1] == ("--threads",):
        if mode == "reproducible":
            return "refused (one thread)"
        argv += list(variation)
    else:
        env.update(item.split("=", 1) for item in variation)
    if precision and mode == "default":
        argv += ["--precision", precision]
    found = json.loads(subprocess.run(argv, env=env, capture_output=True, text=True, check=True).stdout)
    return f"`{found['actor_sha256'][:12]}` / `{found['losses_sha256'][:12]}`"


def main() -> int:
    print("| setting | default mode, bfloat16 | default mode, float32 | reproducible mode |\n|---|---|---|---|")
    for variation in VARIATIONS:
        cells = [hashes(variation, "default", "bfloat16"), hashes(variation, "default", "float32"),
                 hashes(variation, "reproducible", None)]
        print(f"| {' '.join(variation) or '(none)'} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
