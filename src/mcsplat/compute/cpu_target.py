"""The CPU that the kernels are compiled for.

By default every CPU kernel is built for this host (`-march=native`: AVX-512 where the host has it, AVX2 or NEON
elsewhere). MCSPLAT_CPU_TARGET names another CPU to build for instead, an LLVM CPU name such as `znver3` (an AMD EPYC
with AVX2 and no AVX-512) or `haswell`: the build a laptop without AVX-512 runs can then be measured beside the host's
own on one machine (`benchmarks/train_speed.py --cpu-target`). Warp keys its kernel cache by the flags, so the builds
never mix. Warp's compiler takes the target as the front end's `-target-cpu` (it refuses `-march=` with anything but
`native`).
"""

from __future__ import annotations

import os
import re

from ..errors import MCSplatError

TARGET_VARIABLE = "MCSPLAT_CPU_TARGET"
NATIVE = "-march=native"


def target_flag() -> str:
    """The compiler flag that names the CPU the kernels are built for."""
    name = os.environ.get(TARGET_VARIABLE, "").strip()
    if not name or name == "native":
        return NATIVE
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
        raise MCSplatError(f"{TARGET_VARIABLE}={name!r} is not a CPU name; give an LLVM CPU name such as znver3 or "
                           f"haswell, or unset it to build for this machine")
    return f"-target-cpu {name}"


def kernel_flags(extra: str = "") -> str:
    """A kernel module's compiler flags: the target CPU, then `extra` (e.g. `-ffp-contract=fast`)."""
    return f"{target_flag()} {extra}".strip()


def with_target(flags: str | None) -> str | None:
    """Warp's default flags for modules without their own (`wp.config.cpu_compiler_flags`), on the target CPU."""
    if flags is None or target_flag() == NATIVE:
        return flags
    return flags.replace(NATIVE, target_flag()) if NATIVE in flags else f"{target_flag()} {flags}".strip()
