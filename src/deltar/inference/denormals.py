"""Subnormal floats flushed to zero around the colorization fill's LU.

The fill factors a banded system in float32 (:mod:`deltar.inference.colorization`). Its
fill-in decays geometrically away from the diagonal, and on a 60 x 80 grid thousands of
the factors' entries fall below float32's smallest normal number (1.2e-38). x86 cores
compute with such subnormal numbers through a slow microcode path, which slows the
factorisation several times over (benchmarks/RESULTS.md). Entries that
small change nothing the refinement with float64 residuals does not correct, so the
solve turns on the processor's flush-to-zero modes for its own duration and thread
(x86-64: MXCSR's FTZ and DAZ bits; AArch64: FPCR's FZ bit), through glibc's
``fegetenv`` / ``fesetenv``, and restores the previous mode after. Elsewhere (another C
library or processor) :func:`flush_denormals` does nothing and the solve is as exact,
only slower.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import platform
from collections.abc import Iterator

#: x86-64 MXCSR bits: FTZ (results) and DAZ (inputs).
_MXCSR_FLUSH = 0x8000 | 0x0040
#: AArch64 FPCR bit FZ.
_FPCR_FLUSH = 1 << 24


@functools.cache
def _fenv() -> tuple[ctypes.CDLL, type[ctypes.Structure], int] | None:
    """(libm, glibc's fenv_t layout with its mode register as ``control``, the flush
    bits), or None where this process cannot set the mode (not glibc on x86-64 /
    AArch64)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    machine = platform.machine().lower()
    if machine in ("x86_64", "amd64"):
        # glibc's x86-64 fenv_t: the 28-byte x87 environment, then MXCSR (32 bytes).
        fields = [("x87", ctypes.c_uint8 * 28), ("control", ctypes.c_uint32)]
        bits = _MXCSR_FLUSH
    elif machine in ("aarch64", "arm64"):
        fields = [("control", ctypes.c_uint32), ("status", ctypes.c_uint32)]
        bits = _FPCR_FLUSH
    else:
        return None
    name = ctypes.util.find_library("m")
    if name is None:
        return None
    try:
        libm = ctypes.CDLL(name)
        get, put = libm.fegetenv, libm.fesetenv
    except (OSError, AttributeError):
        return None
    get.argtypes = put.argtypes = [ctypes.c_void_p]
    layout = type("FloatEnvironment", (ctypes.Structure,), {"_fields_": fields})
    return libm, layout, bits


def flush_supported() -> bool:
    """True where :func:`flush_denormals` changes the floating-point mode."""
    return _fenv() is not None


@contextlib.contextmanager
def flush_denormals() -> Iterator[None]:
    """Within the block the calling thread reads and writes subnormal floats as zero.

    The thread's previous floating-point environment is restored on exit (also on an
    exception). Other threads are not affected. A no-op where not supported
    (:func:`flush_supported`).
    """
    found = _fenv()
    if found is None:
        yield
        return
    libm, layout, bits = found
    saved = layout()
    if libm.fegetenv(ctypes.byref(saved)) != 0:
        yield
        return
    flushing = layout.from_buffer_copy(saved)
    flushing.control |= bits
    libm.fesetenv(ctypes.byref(flushing))
    try:
        yield
    finally:
        libm.fesetenv(ctypes.byref(saved))
