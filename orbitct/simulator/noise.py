"""Counter-based random numbers for per-pixel noise: parallel, and reproducible from one seed."""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_S16, _S32, _S48 = np.uint64(16), np.uint64(32), np.uint64(48)
_LO16, _LO32 = np.uint64(0xFFFF), np.uint64(0xFFFFFFFF)


@nb.njit(cache=True, nogil=True, inline="always")
def stream(seed: np.uint64, index: int) -> np.uint64:
    """Start state of the stream of pixel ``index``."""
    return seed ^ (np.uint64(index) * _M2)


@nb.njit(cache=True, nogil=True, inline="always")
def _bits(state: np.uint64) -> tuple[np.uint64, np.uint64]:
    """SplitMix64 step: new state and 64 random bits."""
    state = state + _GOLDEN
    z = state
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return state, z ^ (z >> _S31)


@nb.njit(cache=True, nogil=True, inline="always")
def uniform(state: np.uint64) -> tuple[np.uint64, float]:
    """New state and a uniform number in (0, 1) (53 bits)."""
    state, z = _bits(state)
    return state, (float(z >> _S11) + 0.5) * (1.0 / 9007199254740992.0)


@nb.njit(cache=True, nogil=True, inline="always")
def uniform_pair(state: np.uint64) -> tuple[np.uint64, float, float]:
    """New state and two uniform numbers in (0, 1) (32 bits each) from one step."""
    state, z = _bits(state)
    return state, (float(z & _LO32) + 0.5) * (1.0 / 4294967296.0), (float(z >> _S32) + 0.5) * (1.0 / 4294967296.0)


@nb.njit(cache=True, nogil=True, inline="always")
def normal_fast(state: np.uint64) -> tuple[np.uint64, float]:
    """Near-normal number (mean 0, variance 1, tails cut at 3.46): sum of four 16-bit uniforms (read noise)."""
    state, z = _bits(state)
    s = float(z & _LO16) + float((z >> _S16) & _LO16) + float((z >> _S32) & _LO16) + float(z >> _S48)
    return state, ((s + 2.0) * (1.0 / 65536.0) - 2.0) * 1.7320508075688772


@nb.njit(cache=True, nogil=True, inline="always")
def poisson(state: np.uint64, lam: float) -> tuple[np.uint64, float]:
    """An exact Poisson draw: multiplication method below 12, Hormann's PTRS above."""
    if lam <= 0.0:
        return state, 0.0
    if lam < 12.0:
        limit = math.exp(-lam)
        k = 0
        state, p = uniform(state)
        while p > limit:
            k += 1
            state, u = uniform(state)
            p *= u
        return state, float(k)
    slam = math.sqrt(lam)
    b = 0.931 + 2.53 * slam
    a = -0.059 + 0.02483 * b
    vr = 0.9277 - 3.6224 / (b - 2.0)
    loglam = -1.0
    while True:
        state, U, V = uniform_pair(state)
        U -= 0.5
        us = 0.5 - abs(U)
        k = math.floor((2.0 * a / us + b) * U + lam + 0.43)
        if us >= 0.07 and vr >= V:
            return state, k
        if k < 0.0 or (us < 0.013 and us < V):
            continue
        if loglam < 0.0:
            loglam = math.log(lam)
        invalpha = 1.1239 + 1.1328 / (b - 3.4)
        if math.log(V * invalpha / (a / (us * us) + b)) <= -lam + k * loglam - log_factorial(k):
            return state, k


@nb.njit(cache=True, nogil=True, inline="always")
def log_factorial(k: float) -> float:
    """``log(k!)`` for integer-valued ``k >= 0`` (table below 10, Stirling series above)."""
    if k < 10.0:
        return math.lgamma(k + 1.0)
    x = k + 1.0
    x2 = 1.0 / (x * x)
    return (x - 0.5) * math.log(x) - x + 0.9189385332046728 + (1.0 / 12.0 - x2 * (1.0 / 360.0 - x2 / 1260.0)) / x


def seed_from(rng: np.random.Generator) -> np.uint64:
    """A 64-bit kernel seed drawn from a numpy generator."""
    return np.uint64(int(rng.integers(0, 2**63 - 1)))


@nb.njit(cache=True, nogil=True)
def poisson_array(lam: NDArray[np.float64], seed: np.uint64) -> NDArray[np.float64]:
    """Independent Poisson draws, one per entry of ``lam`` (pixel streams 0, 1, 2, ...)."""
    out = np.empty(lam.shape[0])
    for k in range(lam.shape[0]):
        _, out[k] = poisson(stream(seed, k), lam[k])
    return out
