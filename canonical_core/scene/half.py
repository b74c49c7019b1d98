"""IEEE half precision in numba kernels: float32 <-> float16 bit patterns held as uint16.

numba has no float16 type on the CPU, so the voxel map keeps its half-precision columns as uint16
and the kernels convert with `to_half` and `from_half`. Where the CPU numba compiles for converts
half precision itself (x86 with F16C, arm64) they are its instructions, which LLVM emits for its
``half`` type;
elsewhere LLVM would call runtime functions that numba's JIT does not provide, and the integer
conversions below (`half_bits`, `float_bits`) stand in. Both round as numpy's
``astype(np.float16)`` does (to nearest, ties to even; subnormals, infinities and NaN kept), so an
array converted in a kernel and one converted by numpy hold the same bits, and numpy reads the
columns back through a zero-copy ``.view(np.float16)``.

Example:
    >>> import numpy as np
    >>> x = np.array([1.0, -0.1, 65504.0, 1e-6], np.float32)
    >>> h = np.empty(4, np.uint16)
    >>> halves_of(x, h)
    >>> bool((h == x.astype(np.float16).view(np.uint16)).all())
    True
"""

from __future__ import annotations

import platform

import numba
import numpy as np
from llvmlite import binding as llvm_binding
from llvmlite import ir
from numba import types
from numba.extending import intrinsic


@intrinsic
def _bits_of(typingctx, x):
    """A float32's bits as a uint32 (a bit cast: no view of memory, so nothing for the compiler to reorder)."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return types.uint32(types.float32), codegen


@intrinsic
def _float_of(typingctx, bits):
    """The float32 whose bits are the uint32 ``bits``."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.uint32), codegen


@intrinsic
def _half_of(typingctx, x):
    """The float16 nearest the float32 ``x``, as bits: LLVM's conversion to ``half``."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(builder.fptrunc(args[0], ir.HalfType()), ir.IntType(16))

    return types.uint16(types.float32), codegen


@intrinsic
def _float_of_half(typingctx, bits):
    """The float32 equal to the float16 whose bits are ``bits``: LLVM's conversion from ``half``."""

    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())

    return types.float32(types.uint16), codegen


def converts_in_hardware(machine: str | None = None, features: str | None = None) -> bool:
    """Whether LLVM converts half precision with instructions on the CPU numba compiles for
    (``machine`` as `platform.machine` names it, ``features`` as LLVM lists them: ``+f16c,...``).
    By default the host's features, or those numba is told to target (``NUMBA_CPU_NAME`` other than
    ``host``, e.g. ``generic`` for a cache shared between machines: then only ``NUMBA_CPU_FEATURES``)."""
    machine = (machine or platform.machine()).lower()
    if machine in ("x86_64", "amd64"):
        if features is None:
            targeted = numba.config.CPU_NAME not in (None, "host")
            features = (numba.config.CPU_FEATURES or "") if targeted else llvm_binding.get_host_cpu_features().flatten()
        return "+f16c" in features.split(",")
    return machine in ("arm64", "aarch64")


HARDWARE = converts_in_hardware()


@numba.njit(inline="always")
def integer_to_half(x):  # float32 -> float16's bits (uint16)
    """`to_half` in integer operations (any CPU)."""
    return half_bits(_bits_of(np.float32(x)))


@numba.njit(inline="always")
def integer_from_half(h):  # float16's bits (uint16) -> float32
    """`from_half` in integer operations (any CPU)."""
    return _float_of(float_bits(h))


@numba.njit(inline="always")
def _hardware_to_half(x):
    return _half_of(np.float32(x))


@numba.njit(inline="always")
def _hardware_from_half(h):
    return _float_of_half(np.uint16(h))


# float32 -> float16's bits (uint16): the float16 nearest x (ties to even), as bits
to_half = _hardware_to_half if HARDWARE else integer_to_half
# float16's bits (uint16) -> float32: the float32 equal to the float16 (exact: every half is a float32)
from_half = _hardware_from_half if HARDWARE else integer_from_half


@numba.njit(inline="always")
def half_bits(f):  # float32's bits (uint32) -> float16's bits (uint16)
    """The float16 nearest the float32 whose bits are ``f`` (ties to even), as bits."""
    f = np.uint32(f)
    sign = np.uint16((f >> np.uint32(16)) & np.uint32(0x8000))
    f &= np.uint32(0x7FFFFFFF)
    if f > np.uint32(0x7F800000):  # NaN: stays a (quiet) NaN
        return sign | np.uint16(0x7E00)
    if f >= np.uint32(0x477FF000):  # 65520 and up round past the largest half: infinity
        return sign | np.uint16(0x7C00)
    if f >= np.uint32(0x38800000):  # a normal half: rebias the exponent, round off 13 bits
        base = f - np.uint32(0x38000000)
        q = base >> np.uint32(13)
        rest = base & np.uint32(0x1FFF)
        if rest > np.uint32(0x1000) or (rest == np.uint32(0x1000) and q & np.uint32(1)):
            q += np.uint32(1)  # a carry into the exponent is the right rounding too
        return sign | np.uint16(q)
    if f < np.uint32(0x33000000):  # below half the smallest subnormal (2^-25): zero
        return sign
    # a subnormal half: the value in units of 2^-24, rounded
    shift = np.uint32(126) - (f >> np.uint32(23))
    m = (f & np.uint32(0x7FFFFF)) | np.uint32(0x800000)
    q = m >> shift
    rest = m & ((np.uint32(1) << shift) - np.uint32(1))
    halfway = np.uint32(1) << (shift - np.uint32(1))
    if rest > halfway or (rest == halfway and q & np.uint32(1)):
        q += np.uint32(1)
    return sign | np.uint16(q)


@numba.njit(inline="always")
def float_bits(h):  # float16's bits (uint16) -> float32's bits (uint32)
    """The float32 equal to the float16 whose bits are ``h`` (exact: every half is a float32), as bits."""
    h = np.uint32(h)
    sign = (h & np.uint32(0x8000)) << np.uint32(16)
    exponent = (h >> np.uint32(10)) & np.uint32(0x1F)
    mantissa = h & np.uint32(0x3FF)
    if exponent == np.uint32(0x1F):  # infinity or NaN
        return sign | np.uint32(0x7F800000) | (mantissa << np.uint32(13))
    if exponent:
        return sign | ((exponent + np.uint32(112)) << np.uint32(23)) | (mantissa << np.uint32(13))
    if not mantissa:
        return sign
    e = np.uint32(113)  # a subnormal: shift its leading bit up to the implicit one
    while not mantissa & np.uint32(0x400):
        mantissa <<= np.uint32(1)
        e -= np.uint32(1)
    return sign | (e << np.uint32(23)) | ((mantissa & np.uint32(0x3FF)) << np.uint32(13))


@numba.njit(cache=True)
def halves_of(
    x: np.ndarray,  # [N] float32, contiguous
    out: np.ndarray,  # [N] uint16: the float16 bits of each
) -> None:
    """``x.astype(np.float16)`` as bits, by `to_half` (what the tests check it against)."""
    for i in range(x.shape[0]):
        out[i] = to_half(x[i])


@numba.njit(cache=True)
def floats_of(
    h: np.ndarray,  # [N] uint16 float16 bits
    out: np.ndarray,  # [N] float32, contiguous
) -> None:
    """``h.view(np.float16).astype(np.float32)``, by `from_half`."""
    for i in range(h.shape[0]):
        out[i] = from_half(h[i])
