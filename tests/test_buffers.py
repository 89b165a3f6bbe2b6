"""The engine's device memory plumbing: the de-duplicating hash set and the scratch that stages share."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import warp as wp

from badf.server.adf._buffers import DeviceBuffers, DeviceMemoryError, HostReadback, SharedScratch
from badf.server.adf._hashset import UNLISTED, HashSet, HashSetView, NarrowHashSetView, set_insert


@wp.kernel(enable_backward=False)
def _insert_keys(keys: wp.array(dtype=wp.int64), table: Any):
    set_insert(table, keys[wp.tid()])


@wp.kernel(enable_backward=False)
def _insert_keys_at(keys: wp.array(dtype=wp.int64), table: Any, slots: wp.array(dtype=wp.int32)):
    slots[wp.tid()] = set_insert(table, keys[wp.tid()])


for _view in (HashSetView, NarrowHashSetView):
    wp.overload(_insert_keys, {"table": _view})
    wp.overload(_insert_keys_at, {"table": _view})


def _hash_set(device: str, narrow: bool) -> HashSet:
    buffers = DeviceBuffers(wp.get_device(device))
    return HashSet("set", buffers, SharedScratch("scratch", buffers), HostReadback(buffers.device), label="t",
                   narrow=narrow)


@pytest.mark.parametrize("narrow", [False, True], ids=["64-bit", "32-bit"])
@pytest.mark.parametrize("distinct,expected", [(1, 1), (700, 700), (5000, 1200), (20011, 3), (150001, 3)])
def test_hash_set_lists_every_distinct_key_once(device, distinct, expected, narrow):
    # each key arrives 1 to 5 times in random order; an expected count below the distinct one makes the
    # measuring pass try again with a larger table, whose size is no power of two. Far below (150,001 keys
    # into a first table of 1,024 slots), each key past the full table probed every slot: a pass stops
    # early once the list has overflowed, and the passes after it find every key all the same. A narrow set
    # (keys below 2^31, its table in 32 bits) lists and sorts them alike, into the same int64 list
    rng = np.random.default_rng(distinct)
    unique = rng.choice(1 << (31 if narrow else 40), size=distinct, replace=False).astype(np.int64)
    if narrow and distinct > 1:
        unique[:2] = [0, (1 << 31) - 2]  # the narrow range's ends: the largest key sorts before UNLISTED
    keys = rng.permutation(np.repeat(unique, rng.integers(1, 6, size=distinct)))
    table = _hash_set(device, narrow)
    device_keys = wp.array(keys, dtype=wp.int64, device=device)
    count = table.insert_all(expected, lambda view: wp.launch(_insert_keys, dim=len(keys), inputs=[device_keys, view],
                                                               device=device), measure=True)
    assert count == distinct
    assert table.view.keys.dtype == (wp.int32 if narrow else wp.int64)
    listed, _ = table.sort_listed(0, 31 if narrow else 62)
    listed = listed.numpy()
    np.testing.assert_array_equal(listed[:distinct], np.sort(unique))
    assert np.all(listed[distinct : table.list_capacity] == UNLISTED)

    # a planned pass over the same keys, in the table sized for them with headroom, lists them all again
    assert table.planned > distinct
    table.insert_all(0, lambda view: wp.launch(_insert_keys, dim=len(keys), inputs=[device_keys, view], device=device),
                     measure=False)
    assert int(table.view.count.numpy()[0]) == distinct
    np.testing.assert_array_equal(np.sort(table.view.listed_keys.numpy()[:distinct]), np.sort(unique))


@pytest.mark.parametrize("narrow", [False, True], ids=["64-bit", "32-bit"])
@pytest.mark.parametrize("together", [True, False])
def test_a_key_inserted_by_many_threads_at_once_is_listed_once(device, together, narrow):
    """Each of 3,000 keys inserted 27 times, by neighbouring threads (which meet at the same slot in the same
    instant, as a halo cell's 27 neighbours or a corner's eight cells do) or spread over the launch: a thread may
    read its slot before another's compare-and-swap lands, and every key is still listed exactly once, in the slot
    every one of its inserts returns."""
    rng = np.random.default_rng(27)
    unique = rng.choice(1 << (31 if narrow else 40), size=3000, replace=False).astype(np.int64)
    keys = np.repeat(unique, 27) if together else rng.permutation(np.repeat(unique, 27))
    table = _hash_set(device, narrow)
    device_keys = wp.array(keys, dtype=wp.int64, device=device)
    slots = wp.zeros(len(keys), dtype=wp.int32, device=device)
    count = table.insert_all(len(unique), lambda view: wp.launch(_insert_keys_at, dim=len(keys),
                                                                  inputs=[device_keys, view, slots], device=device),
                             measure=True)
    assert count == len(unique)
    view = table.view
    listed = view.listed_keys.numpy()[:count]
    np.testing.assert_array_equal(np.sort(listed), np.sort(unique))
    table_keys, slots = view.keys.numpy(), slots.numpy()
    assert np.all(table_keys[slots] == keys)  # each insert's slot holds its key
    first = {}
    for key, slot in zip(keys.tolist(), slots.tolist()):
        assert first.setdefault(key, slot) == slot  # and every insert of a key returned the same slot
    np.testing.assert_array_equal(table_keys[view.listed_slots.numpy()[:count]], listed)
    # a narrow table takes 8 bytes a slot with its listed slots, against 12
    assert view.keys.capacity == view.capacity * (4 if narrow else 8)


def test_a_scratch_take_lays_its_arrays_apart_and_over_the_last_take(device, monkeypatch):
    buffers = DeviceBuffers(wp.get_device(device))
    scratch = SharedScratch("scratch", buffers)
    a, b, c = scratch.take((1000, wp.int64), (3, wp.int32), (10, wp.vec3))
    spans = [(x.ptr, x.ptr + x.capacity) for x in (a, b, c)]
    assert all((start - a.ptr) % 256 == 0 for start, _ in spans)  # from the allocation, itself aligned
    assert all(spans[i][1] <= spans[i + 1][0] for i in range(2))  # in order, none overlapping
    a.fill_(7)
    b.fill_(-1)
    c.fill_(wp.vec3(1.0, 2.0, 3.0))
    assert np.all(a.numpy() == 7) and np.all(b.numpy() == -1) and np.all(c.numpy() == [1.0, 2.0, 3.0])
    held = buffers.nbytes()
    assert held >= spans[-1][1] - spans[0][0]

    # the next stage starts at the front again, over the dead arrays, without allocating, nor waiting for the
    # device as growing does (which a graph capture refuses: planned frames fell back to eager launches when
    # the allocation's size was compared in the wrong unit)
    waits = []
    monkeypatch.setattr(wp, "synchronize_device", lambda *args: waits.append(args))
    (d,) = scratch.take((500, wp.int32))
    again = scratch.take((1000, wp.int64), (3, wp.int32), (10, wp.vec3))
    assert d.ptr == a.ptr and again[0].ptr == a.ptr and buffers.nbytes() == held and not waits
    # a stage that needs more grows the one allocation (counted once, as the buffers' scratch)
    e, f = scratch.take((4000, wp.int64), (4000, wp.int64))
    assert f.ptr + f.capacity - e.ptr > held and len(waits) == 1
    assert buffers.nbytes() == buffers.nbytes_by_role()["scratch"] >= 64000
    e.fill_(3)
    f.fill_(4)
    assert np.all(e.numpy() == 3) and np.all(f.numpy() == 4)


def test_a_scratch_reserved_for_several_stages_holds_the_largest_without_growing(device, monkeypatch):
    buffers = DeviceBuffers(wp.get_device(device))
    scratch = SharedScratch("scratch", buffers)
    small = ((100, wp.int32),)
    large = ((1000, wp.int64), (1000, wp.int32))
    scratch.reserve(small, large, ((10, wp.vec3),))
    held = buffers.nbytes()
    assert held == 8192 + 4096  # the largest stage: 8,000 and 4,000 bytes, each end aligned to 256
    waits = []
    monkeypatch.setattr(wp, "synchronize_device", lambda *args: waits.append(args))
    for layout in (small, large, small):
        arrays = scratch.take(*layout)
        assert arrays[0].ptr == scratch._backing.ptr
    assert buffers.nbytes() == held and not waits  # no stage grew it, so none waited for the device
    scratch.reserve(small)  # a smaller reservation keeps what is held
    assert buffers.nbytes() == held


def test_fitting_sets_each_array_by_its_first_request_of_the_frame(device):
    """Within `fit`, an array's first request makes it anew at that size if it held more, and later requests
    only grow it, so each ends at the frame's largest; requests with headroom (query batches) keep theirs.
    The scratch shrinks to its first take likewise. Outside `fit` nothing shrinks."""
    buffers = DeviceBuffers(wp.get_device(device))
    scratch = SharedScratch("scratch", buffers)
    big = buffers.ensure("keys", 1000, wp.int64)
    batch = buffers.ensure("query.points", 1000, wp.vec3, headroom=True)
    scratch.take((1000, wp.int64))
    assert buffers.ensure("keys", 10, wp.int64).ptr == big.ptr  # not fitting: kept
    with buffers.fit():
        small = buffers.ensure("keys", 10, wp.int64)
        assert small.shape[0] == 10
        grown = buffers.ensure("keys", 300, wp.int64)  # a later request of the frame grows it
        assert grown.shape[0] == 300
        assert buffers.ensure("keys", 20, wp.int64).ptr == grown.ptr  # and is not cut again
        assert buffers.ensure("query.points", 5, wp.vec3, headroom=True).ptr == batch.ptr
        (taken,) = scratch.take((100, wp.int64))
        assert scratch._backing.capacity == 1024  # 800 bytes, aligned to 256, from the first take's 8,000
        taken.fill_(5)
        assert np.all(taken.numpy() == 5)
    assert buffers.ensure("keys", 10, wp.int64).ptr == grown.ptr
    held = buffers.nbytes()
    buffers.release("query.")
    assert buffers.nbytes() == held - batch.capacity and "query.points" not in buffers._arrays


def test_a_buffer_past_warps_limits_is_a_clear_memory_error():
    """Warp's array shapes are int32: a request past them (a depth-10 octree of a large surface needed a
    2.5 GB scratch of bytes) is a DeviceMemoryError naming the buffer and what to change, before allocating."""
    buffers = DeviceBuffers(wp.get_device("cpu"))
    with pytest.raises(DeviceMemoryError, match=r"oct\.big needs 8192 MiB, more elements than a Warp array"):
        buffers.ensure("oct.big", 2**31, wp.int32)
    with pytest.raises(MemoryError, match="A lower depth"):
        buffers.array("oct.big", 2**31, wp.uint8)
    assert buffers.nbytes() == 0  # nothing was allocated or kept
