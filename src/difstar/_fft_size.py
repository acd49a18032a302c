"""Fast FFT sizes: one place decides which lengths the transforms use."""

from __future__ import annotations

_FAST_RADICES = (2, 3, 5, 7)


def fast_length(n: int) -> int:
    """Smallest m ≥ n whose prime factors are all in {2, 3, 5, 7} (fast FFT sizes).

    Enumerates the 7-smooth candidates (O(log³ n) steps, never a scan), so it returns at
    once for any size; sizes beyond 2⁶² raise ValueError."""
    n = max(int(n), 1)
    if n > 2**62:
        raise ValueError(f"fast_length: n = {n} is beyond any grid that could be allocated.")
    best = 1 << (n - 1).bit_length()  # the power of two ≥ n
    p7 = 1
    while p7 < best:
        p5 = p7
        while p5 < best:
            p3 = p5
            while p3 < best:
                m = p3
                if m < n:  # the smallest m · 2^k ≥ n
                    m <<= (-(-n // m) - 1).bit_length()
                best = min(best, m)
                p3 *= 3
            p5 *= 5
        p7 *= 7
    return best


#: complex (side × side) arrays certainly held at once: a lower bound on the memory a
#: grid needs (the pruned paths hold little more), used to refuse, before anything is
#: allocated, a grid that cannot fit
