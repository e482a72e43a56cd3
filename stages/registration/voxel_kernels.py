"""Numba kernels grouping rows by an int64 key (voxel keys) with a hash table, and summing rows per group.

The tables use open addressing with linear probing: ``table`` (2^b, 2) int64 holds in each slot a key
(-1: empty) and its group number; a key's first slot is given by Fibonacci hashing (the top b bits of
key * 2^64 / golden ratio).

Private kernels: contiguous arrays and scalars in, no validation. Use ``voxel.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetcal.pipeline.numba_flags import NJIT_FLAGS

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
"""Fibonacci hashing multiplier (2^64 / golden ratio)."""


@njit(**NJIT_FLAGS)
def voxel_keys_kernel(
    points: np.ndarray, voxel_size: float, valid: np.ndarray, offset: int, bits: int, keys_out: np.ndarray
) -> bool:
    """Voxel key of each point (N, 3) into ``keys_out`` (N,) int64: the cells floor(p / voxel_size)
    (in float64) shifted by ``offset`` and packed ``bits`` bits each (x highest); -1 outside ``valid``
    ((N,) bool, or empty: all valid). Returns False (keys unfinished) when a valid point's cell lies
    outside [-offset, offset) or is not finite."""
    check = valid.shape[0] > 0
    mask = (1 << bits) - 1
    for i in range(points.shape[0]):
        if check and not valid[i]:
            keys_out[i] = -1
            continue
        key = 0
        for c in range(3):
            cell = np.floor(np.float64(points[i, c]) / voxel_size)
            if not (cell >= -offset and cell < offset):
                return False
            key = (key << bits) | ((np.int64(cell) + offset) & mask)
        keys_out[i] = key
    return True


@njit(**NJIT_FLAGS)
def _shift_for(size: int) -> np.uint64:
    """The hash shift of a table of ``size`` (a power of two) slots: 64 - log2(size)."""
    bits = 0
    while (1 << bits) < size:
        bits += 1
    return np.uint64(64 - bits)


@njit(**NJIT_FLAGS)
def _slot_of(key: int, table: np.ndarray, shift: np.uint64) -> int:
    """Table slot holding ``key`` or the empty slot (-1 key) where it belongs (linear probing)."""
    mask = table.shape[0] - 1
    slot = np.int64((np.uint64(key) * _GOLDEN) >> shift)
    while table[slot, 0] != -1 and table[slot, 0] != key:
        slot = (slot + 1) & mask
    return slot


@njit(**NJIT_FLAGS)
def rehash_kernel(group_keys: np.ndarray, n_groups: int, table: np.ndarray) -> None:
    """Fill an empty table (all keys -1, 2^b slots over 2 * n_groups) with the keys of groups
    ``0:n_groups``."""
    shift = _shift_for(table.shape[0])
    for g in range(n_groups):
        slot = _slot_of(group_keys[g], table, shift)
        table[slot, 0] = group_keys[g]
        table[slot, 1] = g


@njit(**NJIT_FLAGS)
def group_kernel(keys: np.ndarray, group_out: np.ndarray, max_groups: int) -> tuple[np.ndarray, bool]:
    """Number the distinct non-negative keys in order of first appearance.

    Args:
        keys: (N,) int64; negative keys belong to no group.
        group_out: (N,) int64, written: the group of each row (-1 for negative keys).
        max_groups: stop once there are more distinct keys than this (-1: no limit); the table then
            holds at most 2 * max_groups slots.

    Returns:
        ((M,) int64 the distinct keys, group g's key at g; True when all rows were numbered, False when
        it stopped at max_groups + 1 distinct keys).
    """
    bits = 4
    while (1 << bits) < min(2 * keys.shape[0], 1 << 16):
        bits += 1
    table = np.full((1 << bits, 2), -1, dtype=np.int64)
    distinct = np.empty(max(16, keys.shape[0] // 8), dtype=np.int64)
    n_groups = 0
    for i in range(keys.shape[0]):
        key = keys[i]
        if key < 0:
            group_out[i] = -1
            continue
        slot = _slot_of(key, table, np.uint64(64 - bits))
        if table[slot, 0] == key:
            group_out[i] = table[slot, 1]
            continue
        if max_groups >= 0 and n_groups == max_groups:
            return distinct[:n_groups].copy(), False
        if 2 * (n_groups + 1) > table.shape[0]:  # keep the table at most half full
            bits += 1
            table = np.full((1 << bits, 2), -1, dtype=np.int64)
            rehash_kernel(distinct, n_groups, table)
            slot = _slot_of(key, table, np.uint64(64 - bits))
        if n_groups == distinct.shape[0]:
            distinct = np.concatenate((distinct, np.empty(distinct.shape[0], dtype=np.int64)))
        table[slot, 0] = key
        table[slot, 1] = n_groups
        distinct[n_groups] = key
        group_out[i] = n_groups
        n_groups += 1
    return distinct[:n_groups].copy(), True


@njit(**NJIT_FLAGS)
def sum_rows_kernel(
    group: np.ndarray, rank: np.ndarray, values: np.ndarray, sums_out: np.ndarray, counts_out: np.ndarray
) -> None:
    """Add each row of ``values`` (N, c) (as float64) to row ``rank[group[i]]`` of ``sums_out`` (M, c)
    and one to that row of ``counts_out`` (M,) int64, in row order; rows of group -1 are skipped."""
    for i in range(group.shape[0]):
        g = group[i]
        if g < 0:
            continue
        r = rank[g]
        counts_out[r] += 1
        for c in range(values.shape[1]):
            sums_out[r, c] += np.float64(values[i, c])


@njit(**NJIT_FLAGS)
def accumulate_kernel(
    table: np.ndarray,
    group_keys: np.ndarray,
    sums: np.ndarray,
    n_groups: int,
    keys: np.ndarray,
    values: np.ndarray,
    sign: int,
) -> int:
    """Add (``sign`` 1) or remove (-1) rows of ``values`` (N, c) to / from the running sums of their keys
    (``keys`` (N,) int64, negative: skipped); returns the new number of groups.

    ``sums`` (G, c + 1): the sums of each group's rows, its row count in the last column. A key not in
    the table gets the next group (its key into ``group_keys``); the caller leaves room (the table at
    most half full afterwards, ``sums`` and ``group_keys`` with n_groups + N rows). A group whose count
    drops to 0 has its sums reset to exactly 0.
    """
    shift = _shift_for(table.shape[0])
    c_count = values.shape[1]
    for i in range(keys.shape[0]):
        key = keys[i]
        if key < 0:
            continue
        slot = _slot_of(key, table, shift)
        if table[slot, 0] == key:
            g = table[slot, 1]
        else:
            g = n_groups
            n_groups += 1
            table[slot, 0] = key
            table[slot, 1] = g
            group_keys[g] = key
        sums[g, c_count] += sign
        if sums[g, c_count] == 0.0:
            sums[g, :] = 0.0
            continue
        for c in range(c_count):
            sums[g, c] += sign * np.float64(values[i, c])
    return n_groups


@njit(**NJIT_FLAGS)
def means_kernel(sums: np.ndarray, n_groups: int, group_keys: np.ndarray, keys_out: np.ndarray,
                 means_out: np.ndarray) -> int:
    """The occupied groups (count > 0) among the first ``n_groups`` of ``sums`` (G, c + 1): their keys
    into ``keys_out`` and their mean rows (sums / count) into ``means_out`` (G, c), in group order;
    returns how many."""
    c_count = means_out.shape[1]
    m = 0
    for g in range(n_groups):
        count = sums[g, c_count]
        if count > 0.0:
            keys_out[m] = group_keys[g]
            for c in range(c_count):
                means_out[m, c] = sums[g, c] / count
            m += 1
    return m
