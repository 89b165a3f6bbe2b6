"""A GPU hash set of non-negative int64 keys that lists each distinct key once, for de-duplication.

Open addressing with linear probing; a thread whose compare-and-swap claims an empty slot appends the key
(and the slot) to a compact list with an atomic counter, so the distinct keys come out without sorting all
the duplicates. The table is sized from an expected count (last frame's, for a deforming mesh) at load at
most 1/2; if more keys arrive than the list holds, `insert_all` grows the table and runs the pass again.
"""

from __future__ import annotations

from collections.abc import Callable

import warp as wp

from badf.server.adf._buffers import DeviceBuffers

EMPTY = wp.constant(wp.int64(-1))
_MIN_CAPACITY = 1024


@wp.struct
class HashSetView:
    keys: wp.array(dtype=wp.int64)  # (capacity,) table, EMPTY where free
    mask: int  # capacity - 1 (capacity is a power of two)
    listed_keys: wp.array(dtype=wp.int64)  # distinct keys in arrival order
    listed_slots: wp.array(dtype=wp.int32)  # their table slots
    list_capacity: int
    count: wp.array(dtype=wp.int32)  # (1,) distinct keys seen (may exceed list_capacity on overflow)


@wp.func
def _hash(key: wp.int64) -> wp.uint64:
    # splitmix64's finaliser: every input bit moves every output bit
    x = wp.uint64(key)
    x = (x ^ (x >> wp.uint64(30))) * wp.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> wp.uint64(27))) * wp.uint64(0x94D049BB133111EB)
    return x ^ (x >> wp.uint64(31))


@wp.func
def set_insert(table: HashSetView, key: wp.int64) -> int:
    """Insert key; returns its table slot, or -1 when the table is full."""
    slot = int(_hash(key) & wp.uint64(table.mask))
    for _probe in range(table.mask + 1):
        previous = wp.atomic_cas(table.keys, slot, EMPTY, key)
        if previous == EMPTY:
            index = wp.atomic_add(table.count, 0, 1)
            if index < table.list_capacity:
                table.listed_keys[index] = key
                table.listed_slots[index] = slot
            return slot
        if previous == key:
            return slot
        slot = (slot + 1) & table.mask
    return -1


class HashSet:
    """Device buffers of one hash set, reused from frame to frame."""

    def __init__(self, name: str, buffers: DeviceBuffers, host_counts):
        self.name = name
        self.buffers = buffers
        self.device = buffers.device
        self.host = host_counts
        self.expected = 0
        self.count = 0
        self._view: HashSetView | None = None

    def insert_all(self, expected: int, launch: Callable[[HashSetView], None]) -> int:
        """Clear, run `launch(view)` (which inserts), and repeat with a larger table until the list held
        every distinct key; returns how many there are. `expected` sizes the first try."""
        expected = max(expected, self.expected, 1)
        while True:
            view = self._reset(expected)
            launch(view)
            count = self.host.read(view.count, 0)
            if count <= view.list_capacity:
                self.count = count
                # the next frame starts from this size, shrinking slowly if it falls
                self.expected = max(count, self.expected // 2)
                return count
            expected = 2 * max(count, expected)

    def _reset(self, expected: int) -> HashSetView:
        capacity = _MIN_CAPACITY
        while capacity < 2 * expected:
            capacity *= 2
        b = self.buffers
        view = HashSetView()
        view.keys = b.ensure(self.name + ".table", capacity, wp.int64)
        view.keys.fill_(-1)
        view.mask = capacity - 1
        view.list_capacity = capacity // 2
        # listed keys and slots are sorted afterwards: radix_sort_pairs needs twice the room
        view.listed_keys = b.ensure(self.name + ".keys", capacity, wp.int64)
        view.listed_slots = b.ensure(self.name + ".slots", capacity, wp.int32)
        view.count = b.ensure(self.name + ".count", 1, wp.int32)
        view.count.zero_()
        self._view = view
        return view

    @property
    def view(self) -> HashSetView:
        return self._view

    def sort_listed(self, begin_bit: int, end_bit: int) -> tuple[wp.array, wp.array]:
        """Sort the listed keys (with their slots); returns (keys, slots), `count` long."""
        v = self._view
        wp.utils.radix_sort_pairs(v.listed_keys, v.listed_slots, self.count, begin_bit=begin_bit, end_bit=end_bit)
        return v.listed_keys, v.listed_slots
