"""Builds the compositor's C library (the rest of the package is configured in pyproject.toml).

Two builds of one source: a baseline one, and on x86-64 an AVX2 + FMA (x86-64-v3) one that
canonical_core.rendering.cpu_tiles loads where the CPU supports it. Needs a C compiler (gcc).
"""

import platform

from setuptools import Extension, setup

SOURCE_DIR = "canonical_core/rendering"
# -ffp-contract=fast: fused multiply-adds in the blend (GCC's default outside ISO mode, made explicit).
FLAGS = ["-O3", "-ffp-contract=fast", "-Wno-psabi"]


def compositor(name: str, extra_flags: list[str]) -> Extension:
    return Extension(
        f"canonical_core.rendering.{name}",
        [f"{SOURCE_DIR}/{name}.c"],
        depends=[f"{SOURCE_DIR}/_composite.c"],
        extra_compile_args=FLAGS + extra_flags,
    )


builds = [compositor("_composite", [])]
if platform.machine().lower() in ("x86_64", "amd64"):
    builds.append(compositor("_composite_x86_64_v3", ["-march=x86-64-v3"]))

setup(ext_modules=builds)
