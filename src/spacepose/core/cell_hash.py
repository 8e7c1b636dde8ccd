"""Open-addressing hash tables of occupied grid cells, compiled with numba.

A cell key packs a cell's three indices into one int64 (:func:`spacepose.core.voxel.cell_keys`).
The occupied cells are numbered in order of first appearance (their *rank*), and a table maps a
key's slot to its rank, probing linearly from a Fibonacci hash of the key: the voxel grids of
:mod:`spacepose.core.voxel` and the neighbour searches of :mod:`spacepose.core.grid` share it.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

_FIBONACCI = np.uint64(0x9E3779B97F4A7C15)


def hash_bits(n_keys: int) -> int:
    """Bits of an open-addressing table with room for ``n_keys`` keys at most half full."""
    return max(4, int(np.ceil(np.log2(2 * max(n_keys, 1)))))


def group_cells(
    keys: NDArray[np.int64],
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], int]:
    """Number the occupied cells in order of first appearance and hash them.

    Parameters
    ----------
    keys
        (N,) cell keys (:func:`spacepose.core.voxel.cell_keys`).

    Returns
    -------
    cell, unique, table, bits
        (N,) rank of each point's cell, (M,) the keys of the occupied cells by rank, and the
        open-addressing table (size ``2**bits``) mapping a key's slot to its rank (-1: empty),
        searched with :func:`find_cell`.
    """
    bits = hash_bits(len(keys))
    cell = np.empty(len(keys), dtype=np.int64)
    unique = np.empty(len(keys), dtype=np.int64)
    table = np.full(1 << bits, -1, dtype=np.int64)
    count = _group(keys, bits, cell, unique, table)
    return cell, unique[:count], table, bits


@numba.njit(cache=True, inline="always")
def hash_slot(key, bits):
    """Slot of ``key`` in a table of ``2**bits`` slots."""
    # Fibonacci hashing: the top bits of key × 2⁶⁴/φ spread neighbouring keys apart.
    return np.int64((np.uint64(key) * _FIBONACCI) >> np.uint64(64 - bits))


@numba.njit(cache=True, inline="always")
def find_cell(table, unique, bits, key):
    """Rank of the cell ``key`` (-1: no point in it) in a :func:`group_cells` table; with
    ``bits`` 0, ``table`` is a direct table indexed by the key itself."""
    if bits == 0:
        return table[key]
    mask = (1 << bits) - 1
    s = hash_slot(key, bits)
    while True:
        rank = table[s]
        if rank == -1 or unique[rank] == key:
            return rank
        s = (s + 1) & mask


@numba.njit(cache=True)
def _group(keys, bits, cell, unique, table):
    mask = (1 << bits) - 1
    count = 0
    for i in range(len(keys)):
        key = keys[i]
        s = hash_slot(key, bits)
        while True:
            rank = table[s]
            if rank == -1:
                table[s] = count
                unique[count] = key
                cell[i] = count
                count += 1
                break
            if unique[rank] == key:
                cell[i] = rank
                break
            s = (s + 1) & mask
    return count
