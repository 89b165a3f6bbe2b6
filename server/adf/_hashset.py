"""A GPU hash set of non-negative int64 keys that lists each distinct key once, for de-duplication.

Open addressing with linear probing; a thread whose compare-and-swap claims an empty slot appends the key
(and the slot) to a compact list with an atomic counter, so the distinct keys come out without sorting all
the duplicates. The table holds twice the expected count (load at most 1/2), and the list the expected
count: sizes follow the count, not the next power of two, so the sorts and the radix tree that come after
run over no more entries than they need.

Two ways to run a pass (see `insert_all`): measuring, which reads the count back and, if more keys arrived
than the list holds, grows the table and runs the pass again; or planned, which reads nothing, so a frame
can run without waiting on the host (and be captured as a CUDA graph): the count stays on the device,
every later kernel clips it to the list's capacity, and the frame's owner checks it once at the end.
The list beyond the count holds UNLISTED, which sorts after every key, so the whole list can be sorted
without knowing the count.

A set whose keys all stay below 2^31 (the octree's corners up to depth 9) can keep its table in 32 bits
(`narrow`): the table, which is the largest of the octree's stages, takes a third less of the scratch, and the
list is sorted in 32 bits. Its listed keys are int64 all the same, so what reads them does not change.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import warp as wp

from badf.server.adf._buffers import DeviceBuffers, SharedScratch

EMPTY = wp.constant(wp.int64(-1))
UNLISTED = (1 << 62) - 1  # every bit a sorted key range can use (keys stay below 2^62) is set
NARROW_UNLISTED = (1 << 31) - 1  # UNLISTED in a narrow set's 32 bits (its keys stay below 2^31)
_NARROW_UNLISTED = wp.constant(wp.int32(NARROW_UNLISTED))
_UNLISTED = wp.constant(wp.int64(UNLISTED))
_MIN_CAPACITY = 1024


@wp.struct
class HashSetView:
    keys: wp.array(dtype=wp.int64)  # (capacity,) table, EMPTY where free
    capacity: int
    listed_keys: wp.array(dtype=wp.int64)  # distinct keys in arrival order
    listed_slots: wp.array(dtype=wp.int32)  # their table slots
    list_capacity: int
    count: wp.array(dtype=wp.int32)  # (1,) distinct keys seen (may exceed list_capacity on overflow)


@wp.struct
class NarrowHashSetView:
    """HashSetView whose table holds keys below 2^31 in 32 bits (its list is int64 like any set's)."""

    keys: wp.array(dtype=wp.int32)  # (capacity,) table, EMPTY where free
    capacity: int
    listed_keys: wp.array(dtype=wp.int64)
    listed_slots: wp.array(dtype=wp.int32)
    list_capacity: int
    count: wp.array(dtype=wp.int32)


@wp.func
def _in_table(table: HashSetView, key: wp.int64) -> wp.int64:
    """A key as the table holds it."""
    return key


@wp.func
def _in_table(table: NarrowHashSetView, key: wp.int64) -> wp.int32:
    return wp.int32(key)


@wp.func
def _hash(key: wp.int64) -> wp.uint64:
    # splitmix64's finaliser: every input bit moves every output bit
    x = wp.uint64(key)
    x = (x ^ (x >> wp.uint64(30))) * wp.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> wp.uint64(27))) * wp.uint64(0x94D049BB133111EB)
    return x ^ (x >> wp.uint64(31))


@wp.func
def listed_count(table: Any) -> int:
    """How many keys the list holds (the count clipped to the list's capacity)."""
    return wp.min(table.count[0], table.list_capacity)


@wp.func
def set_insert(table: Any, key: wp.int64) -> int:
    """Insert key; returns its table slot, or -1 when the table is full or the list has overflowed (more
    distinct keys than it holds: the pass is run again with a larger table, so this one may stop early).
    Without that stop, a table that keys overfill took each later key through every slot: a mesh of 4,000
    tiny parts, whose cells a first estimate from its area far undercounts, took 25 s to build on the CPU
    (twelfth outside check)."""
    slot = int(_hash(key) % wp.uint64(table.capacity))
    empty = _in_table(table, EMPTY)
    stored = _in_table(table, key)
    for probe in range(table.capacity):
        previous = wp.atomic_cas(table.keys, slot, empty, stored)
        if previous == empty:
            index = wp.atomic_add(table.count, 0, 1)
            if index < table.list_capacity:
                table.listed_keys[index] = key
                table.listed_slots[index] = slot
            return slot
        if previous == stored:
            return slot
        slot += 1
        if slot == table.capacity:
            slot = 0
        # a long probe at load 1/2 is rare; past the list's capacity the keys are counted, not kept
        if (probe & 31) == 31 and table.count[0] > table.list_capacity:
            return -1
    return -1


class HashSet:
    """Device buffers of one hash set, reused from frame to frame."""

    def __init__(self, name: str, buffers: DeviceBuffers, scratch: SharedScratch, host_counts, *, label: str,
                 narrow: bool = False):
        """`name` names the listed keys' buffer, which sets alive at different times may share; `label`
        names this set's count, which is read at the end of the frame. The table and the listed slots,
        which live only while keys go in and are sorted, are taken from `scratch`; `narrow`: every key is below
        2^31, and the table holds them in 32 bits (its view is a NarrowHashSetView)."""
        self.name = name
        self.narrow = narrow
        self.scratch = scratch
        self.label = label
        self.buffers = buffers
        self.device = buffers.device
        self.host = host_counts
        self.planned = 0  # the expected count of planned passes
        self._view: HashSetView | None = None

    def insert_all(self, expected: int, launch: Callable[..., None], *, measure: bool,
                   beside: tuple[tuple[int, type], ...] = ()) -> int | None:
        """Clear and run `launch(view, *arrays)`, which inserts; `arrays` are what it needs while keys go in,
        laid out as `beside` says ((count, dtype) each) in the scratch after the table, contents undefined.

        Measuring: `expected` sizes the first try; the count is read back, and the pass repeated with a
        larger table until the list held every distinct key; returns the count and plans later passes
        for it with headroom. Planned: the table is sized for the plan, nothing is read, returns None.
        """
        if not measure:
            view, arrays = self._reset(self.planned, beside)
            launch(view, *arrays)
            return None
        expected = max(expected, 1)
        while True:
            view, arrays = self._reset(expected, beside)
            launch(view, *arrays)
            count = self.host.read(view.count, 0)
            if count <= view.list_capacity:
                self.planned = with_headroom(count)
                return count
            expected = 2 * max(count, expected)

    def scratch_layout(self, expected: int, beside: tuple[tuple[int, type], ...] = ()) -> tuple[tuple[int, type], ...]:
        """What this set expecting that many keys takes from the scratch: its table, and the listed slots, which hold
        twice the list, as radix_sort_pairs needs (the listed keys are sorted in the spent table, which is as
        long: sort_listed); then the arrays `beside` (insert_all)."""
        capacity = max(2 * expected, _MIN_CAPACITY)
        return ((capacity, wp.int32 if self.narrow else wp.int64), (capacity, wp.int32), *beside)

    @staticmethod
    def list_capacity_for(expected: int) -> int:
        """The list's capacity of a set expecting that many keys: half its table (`scratch_layout`)."""
        return max(2 * expected, _MIN_CAPACITY) // 2

    def _reset(self, expected: int, beside: tuple[tuple[int, type], ...] = ()) -> tuple[HashSetView, list]:
        layout = self.scratch_layout(expected, beside)
        capacity = layout[0][0]
        b = self.buffers
        view = NarrowHashSetView() if self.narrow else HashSetView()
        view.keys, view.listed_slots, *arrays = self.scratch.take(*layout)
        view.keys.fill_(-1)
        view.capacity = capacity
        view.list_capacity = capacity // 2
        view.listed_keys = b.ensure(self.name + ".keys", view.list_capacity, wp.int64)
        view.listed_keys.fill_(UNLISTED)
        view.count = b.ensure(f"{self.name}.count.{self.label}", 1, wp.int32)
        view.count.zero_()
        self._view = view
        return view, arrays

    @property
    def view(self) -> HashSetView | NarrowHashSetView:
        return self._view

    @property
    def list_capacity(self) -> int:
        return self._view.list_capacity

    def spent_table(self) -> wp.array:
        """The table's memory as (capacity,) int32, for a caller done inserting (the table is not read
        again, and the listed keys and slots are elsewhere)."""
        table = self._view.keys
        return table if self.narrow else wp.array(ptr=table.ptr, dtype=wp.int32, shape=table.shape, device=self.device)

    def sort_listed(self, begin_bit: int, end_bit: int) -> tuple[wp.array, wp.array]:
        """Sort the whole list (with the slots): the listed keys in order, then UNLISTED; (keys, slots).

        The table is spent once every key is in, and it is twice the list's length, the room radix_sort_pairs
        needs: the keys are sorted there and copied back, so the list, which outlives the frame (the corners'
        keys are the next frame's coherence), holds no room of its own (2 MB for the bunny's corners). A narrow
        set's keys are sorted in 32 bits there, UNLISTED as NARROW_UNLISTED, whose bits of the range are all set
        as well."""
        v = self._view
        if self.narrow:
            wp.launch(_narrow_keys, dim=v.list_capacity, inputs=[v.listed_keys], outputs=[v.keys], device=self.device)
        else:
            wp.copy(v.keys, v.listed_keys, count=v.list_capacity)
        wp.utils.radix_sort_pairs(v.keys, v.listed_slots, v.list_capacity, begin_bit=begin_bit, end_bit=end_bit)
        if self.narrow:
            wp.launch(_widen_keys, dim=v.list_capacity, inputs=[v.keys], outputs=[v.listed_keys], device=self.device)
        else:
            wp.copy(v.listed_keys, v.keys, count=v.list_capacity)
        return v.listed_keys, v.listed_slots


@wp.kernel(enable_backward=False)
def _narrow_keys(keys: wp.array(dtype=wp.int64), narrow: wp.array(dtype=wp.int32)):
    i = wp.tid()
    key = keys[i]
    narrow[i] = wp.where(key == _UNLISTED, _NARROW_UNLISTED, wp.int32(key))


@wp.kernel(enable_backward=False)
def _widen_keys(narrow: wp.array(dtype=wp.int32), keys: wp.array(dtype=wp.int64)):
    i = wp.tid()
    key = narrow[i]
    keys[i] = wp.where(key == _NARROW_UNLISTED, _UNLISTED, wp.int64(key))


def with_headroom(count: int) -> int:
    """The capacity planned for a count measured once, so frames that grow a little still fit."""
    return count + count // 4 + 16
