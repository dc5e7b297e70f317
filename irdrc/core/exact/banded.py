"""Exact stationary distributions of the chains the aggregation rounds solve
(``irdrc.core.exact.stationary``): a chain on the queue lengths 0 … n − 1 whose jumps stay in a
band, by the GTH algorithm, and the product of such chains over one period of a periodic policy.
NumPy and SciPy, on the CPU."""

from __future__ import annotations

from typing import Any


def banded_stationary(src: Any, dst: Any, vals: Any, n: int) -> Any:
    """The stationary distribution of a chain on 0 … n − 1 whose jumps stay in a band (the
    aggregated queue), from its transitions ``src`` → ``dst`` with probabilities ``vals`` (NumPy;
    repeats are summed): the GTH algorithm (Grassmann, Taksar and Heyman), which eliminates the
    states from the top and never subtracts, so it is exact to rounding however many orders of
    magnitude the distribution spans — where a linear solve pinned at one state is not (a queue
    that fills gave entries of −10¹³ there). Eliminating a state keeps the band, so it costs
    O(n·band²). A state the ones below it cannot be reached from ends the elimination: below it
    every state is transient (mass 0). The back substitution rescales as it grows, so nothing
    overflows."""
    import numpy as np
    from numpy.lib.stride_tricks import as_strided

    off = dst - src
    bl, bu = max(1, -int(off.min())), max(1, int(off.max()))
    pad = bu  # rows above state 0, so that every block update has its full shape
    W = bl + bu + 1
    # B[pad + i, j − i + bl] = P[i, j], repeats summed in their order
    B = np.bincount((src + pad) * W + off + bl, vals, (n + pad) * W).reshape(n + pad, W)
    B[pad + np.arange(n), bl] = 0.0  # staying put does not enter GTH
    # strided views of B, one entry per state k (no copy, no fancy indexing in the loop):
    flat, item = B.reshape(-1), B.itemsize
    # blocks[k][a, b] = P[k − bu + a, k − bl + b], the entries eliminating k updates
    blocks = as_strided(flat[bu:], (n, bu, bl), (W * item, (W - 1) * item, item), writeable=True)
    ups = as_strided(flat[bu + bl :], (n, bu), (W * item, (W - 1) * item))  # P[k − bu + a, k]
    downs = B[pad:, :bl]  # downs[k][b] = P[k, k − bl + b]
    s = np.zeros(n)
    w, outer = np.empty(bl), np.empty((bu, bl))
    base = 0
    for k in range(n - 1, 0, -1):
        down = downs[k]
        if k < bl:
            down = down.copy()
            down[: bl - k] = 0.0
        total = np.add.reduce(down)
        if total <= 0.0:
            base = k
            break
        s[k] = total
        np.divide(down, total, out=w)
        np.multiply(ups[k][:, None], w, out=outer)
        block = blocks[k]
        np.add(block, outer, out=block)
    up_all = np.ascontiguousarray(ups)
    pi = np.zeros(n)
    pi[base] = 1.0
    for k in range(base + 1, n):
        lo = k - bu
        pi[k] = float(pi[max(lo, base) : k] @ up_all[k][max(0, base - lo) :]) / s[k]
        if pi[k] > 1e150:
            pi[base : k + 1] *= 1e-150
    return pi / pi.sum()


def product_stationary(src: Any, dst: Any, kernels: list[Any], n: int) -> Any:
    """The stationary distribution of the product of the chains on 0 … n − 1 whose transitions
    ``src`` → ``dst`` have the probabilities ``kernels[j]`` (one period of a periodic policy; the
    product's jumps stay in the sum of the bands)."""
    from scipy import sparse

    product = None
    for vals in kernels:
        A = sparse.csr_matrix((vals, (src, dst)), shape=(n, n))
        product = A if product is None else product @ A
    coo = sparse.coo_matrix(product)
    return banded_stationary(coo.row, coo.col, coo.data, n)
