"""Device arrays of one object, by name: allocated once, grown geometrically when a size needs it, counted."""

from __future__ import annotations

import contextlib

import numpy as np
import warp as wp

# A buffer asked to grow with headroom gets this much, so sizes that creep up do not reallocate each call.
_GROWTH = 1.5


class DeviceMemoryError(MemoryError):
    """A buffer that the device could not hold (or that is larger than a Warp array may be)."""


class DeviceBuffers:
    def __init__(self, device: wp.Device):
        self.device = device
        self._arrays: dict[str, wp.array] = {}
        # while fitting (`fit`), the names asked for so far: an array's first request then sets its size
        self._fitted: set[str] | None = None

    def array(self, name: str, count: int, dtype) -> wp.array:
        """A zeroed array of exactly `count` elements (at least one), replacing any of that name."""
        arr = self._allocate(name, count, dtype, zeroed=True)
        self._arrays[name] = arr
        return arr

    def ensure(self, name: str, count: int, dtype, *, headroom: bool = False) -> wp.array:
        """The array of that name if it holds `count` elements, else a new one (contents not kept): of
        exactly `count` elements for sizes planned with their own headroom (`with_headroom`), or with
        `headroom` of at least half again the old size, for sizes that creep up call by call."""
        arr = self._arrays.get(name)
        shrink = not headroom and self._shrinks(name, count)
        if self._fitted is not None:
            self._fitted.add(name)
        if arr is None or arr.shape[0] < count or shrink:
            grown = count if arr is None or not headroom else max(count, int(arr.shape[0] * _GROWTH))
            arr = self._allocate(name, grown, dtype, zeroed=False)
            self._arrays[name] = arr
        return arr

    def holds(self, name: str, count: int) -> bool:
        """Whether `ensure(name, count)` would hand back the array as it is (neither grown nor, while fitting, made
        anew smaller)."""
        arr = self._arrays.get(name)
        return arr is not None and arr.shape[0] >= count and not self._shrinks(name, count)

    def release(self, prefix: str) -> bool:
        """Give back every array whose name starts with `prefix` (freed once nothing else holds it); whether any."""
        names = [name for name in self._arrays if name.startswith(prefix)]
        for name in names:
            del self._arrays[name]
        return bool(names)

    @contextlib.contextmanager
    def fit(self):
        """Within it, a planned size's first request makes its array anew if the array holds more (later
        requests of the frame only grow it, so each ends at the frame's largest): for the frame after one
        planned from an estimate, so that the estimate's room is given back. Allocated arrays are freed in
        stream order, as when an array grows."""
        self._fitted = set()
        try:
            yield
        finally:
            self._fitted = None

    def _shrinks(self, name: str, count: int) -> bool:
        """Whether a request of a planned size makes its array anew at that smaller size (`fit`)."""
        arr = self._arrays.get(name)
        return (self._fitted is not None and name not in self._fitted and arr is not None
                and arr.shape[0] > max(int(count), 1))

    def _allocate(self, name: str, count: int, dtype, *, zeroed: bool) -> wp.array:
        """An array from Warp, or DeviceMemoryError naming what did not fit and how much the object holds."""
        count = max(int(count), 1)
        size = count * wp.types.type_size_in_bytes(dtype)
        if count >= 2**31:  # Warp's shapes are int32
            raise DeviceMemoryError(self._too_large(name, size, "more elements than a Warp array may hold (2^31)"))
        try:
            return (wp.zeros if zeroed else wp.empty)(count, dtype=dtype, device=self.device)
        except RuntimeError as error:
            if "alloc" not in str(error).lower():
                raise
            raise DeviceMemoryError(self._too_large(name, size, f"which the device could not allocate ({error})")) from None

    def _too_large(self, name: str, size: int, why: str) -> str:
        return (f"the field does not fit on {self.device}: {name} needs {size / 2**20:.0f} MiB, {why}; the object "
                f"already holds {self.nbytes() / 2**20:.0f} MiB. A lower depth, halo=0, refine='centroid' or a band "
                "makes the octree smaller")

    def nbytes(self) -> int:
        return sum(arr.capacity for arr in self._arrays.values())

    def nbytes_by_role(self) -> dict[str, int]:
        """Bytes by what they hold: the field a query reads (octree links, corner table and values), the BVH,
        the mesh and its sign data, coherence state, query batches, what only a BVH build uses ("rebuild": held
        from a frame that moves the domain to the next one that keeps it, Bvh.give_back_build), and frame
        scratch (the rest)."""
        roles = {"field": 0, "bvh": 0, "mesh": 0, "coherence": 0, "queries": 0, "rebuild": 0, "scratch": 0}
        for name, arr in self._arrays.items():
            roles[_role(name)] += arr.capacity
        return roles


_FIELD = {"corner.value", "corner.leaf", "oct.corner_slot", "oct.child_mask", "oct.first_child"}


def _role(name: str) -> str:
    if name in _FIELD:
        return "field"
    if name.startswith("bvh.build."):
        return "rebuild"
    if name.startswith("bvh."):
        return "bvh"
    if name.startswith(("mesh.", "sign.")):
        return "mesh"
    if name.startswith(("corner.prev", "corner.next")):
        return "coherence"
    if name.startswith("query."):
        return "queries"
    return "scratch"


_SCRATCH_ELEMENT = 16  # bytes: a shared scratch is an array of wp.vec4


class SharedScratch:
    """One allocation that the stages of a frame lay their short-lived arrays over, one stage after another.

    `take` lays the arrays it is asked for out from the front, so they overlap what the previous `take`
    returned: the caller takes a stage's arrays only once no queued work will read the last stage's (all
    run in order on one stream). The allocation is one of the object's named buffers (counted as scratch);
    it grows when a stage needs more, and shrinks only to the first stage's needs in a frame that fits
    the object's buffers (`DeviceBuffers.fit`). Growing waits for the device first, so no kernel
    still queued reads the old allocation when it is freed: a measured frame or the first planned frame
    of new sizes may grow it, never a frame being captured as a graph, which repeats an eager one.
    """

    _ALIGN = 256  # bytes; every array starts on a multiple, as the allocator's own do

    def __init__(self, name: str, buffers: DeviceBuffers):
        self.name = name
        self.buffers = buffers
        self.device = buffers.device
        self._backing: wp.array | None = None

    def take(self, *layout: tuple[int, type]) -> list[wp.array]:
        """Arrays of (count, dtype) each (at least one element), contents undefined, valid until the next take."""
        offsets = self._offsets(layout)
        self._hold(offsets[-1] // _SCRATCH_ELEMENT)
        base = self._backing.ptr
        return [wp.array(ptr=base + offset, dtype=dtype, shape=(max(int(count), 1),), device=self.device)
                for offset, (count, dtype) in zip(offsets, layout)]

    def reserve(self, *layouts: tuple[tuple[int, type], ...]) -> None:
        """Hold room for the largest of these stages' layouts (each as `take` gets it) at once, so that a frame
        whose sizes are all planned grows the scratch, and waits for the device, once at most rather than at
        each stage that needs more than the last."""
        self._hold(max(self._offsets(layout)[-1] for layout in layouts) // _SCRATCH_ELEMENT)

    def give_back(self) -> bool:
        """Free the allocation, for an object whose frames need none for a while (a later `take` or `reserve`
        allocates it anew); whether there was one. Nothing queued may still read it: the device is waited for, and
        the owner drops any captured graph that lays its arrays over it."""
        if self._backing is None:
            return False
        wp.synchronize_device(self.device)
        self._backing = None
        return self.buffers.release(self.name)

    def _offsets(self, layout) -> list[int]:
        """Each array's byte offset in the allocation, and the end of the last."""
        offsets = [0]
        for count, dtype in layout:
            offsets.append(offsets[-1] + -(-max(int(count), 1) * wp.types.type_size_in_bytes(dtype) // self._ALIGN)
                           * self._ALIGN)
        return offsets

    def _hold(self, elements: int) -> None:
        # 16-byte elements, so the allocation may pass 2 GiB within Warp's int32 shapes (ends are aligned)
        grows = self._backing is not None and self._backing.shape[0] < elements
        if grows and self.device.is_cuda and self.device.is_capturing:
            raise RuntimeError(f"{self.name}: a stage outgrew its scratch while a graph was captured")
        # every request is one of the named buffer, so `DeviceBuffers.fit` treats the scratch as any other
        backing = self.buffers.ensure(self.name, elements, wp.vec4)
        if backing is not self._backing:
            if self._backing is not None:
                wp.synchronize_device(self.device)  # before the old allocation's last reference goes
            self._backing = backing


class SideStream:
    """A second stream of one object on CUDA, for work that runs beside what its frame's stream queues
    next: `fork` makes it wait for everything queued so far on the current stream, `join` makes the current
    stream wait for what was queued on it. Inside a graph capture the two waits become the graph's edges.
    On the CPU back-end there is none: `fork` gives None, and the work runs in order on the one stream."""

    # False: every object's work queued in order on its one stream (for `badf bench engine` to compare)
    allowed = True

    def __init__(self, device: wp.Device):
        self.device = device
        self.enabled = device.is_cuda and SideStream.allowed
        self._stream: wp.Stream | None = None

    def fork(self) -> wp.Stream | None:
        if not self.enabled:
            return None
        if self._stream is None:
            self._stream = wp.Stream(self.device)
            self._forked, self._joined = wp.Event(self.device), wp.Event(self.device)
        self._stream.wait_stream(wp.get_stream(self.device), self._forked)
        return self._stream

    def join(self, stream: wp.Stream | None) -> None:
        if stream is not None:
            wp.get_stream(self.device).wait_stream(stream, self._joined)


class HostStaged:
    """A small device array the host writes before each frame and the frame copies up: on CUDA through a pinned
    twin, so the copy is asynchronous and can be part of a captured graph; on the CPU the array itself, which the
    host writes in place and `upload` leaves alone."""

    def __init__(self, array: wp.array):
        self.array = array
        self._host = (wp.zeros(array.shape[0], dtype=array.dtype, device="cpu", pinned=True) if array.device.is_cuda
                      else array)

    def host(self) -> np.ndarray:
        """Where the host writes the next frame's values."""
        return self._host.numpy()

    def upload(self) -> None:
        """Queue the copy of what the host wrote into the device array (nothing on the CPU)."""
        if self._host is not self.array:
            wp.copy(self.array, self._host)


class HostReadback:
    """Reads a few integers back from the device through one small pinned buffer (no allocation per frame)."""

    def __init__(self, device: wp.Device):
        self.device = device
        self._host = wp.empty(64, dtype=wp.int32, device="cpu", pinned=device.is_cuda)

    def read(self, arr: wp.array, index: int) -> int:
        wp.copy(self._host, arr, dest_offset=0, src_offset=index, count=1)
        self._wait()
        return int(self._host.numpy()[0])

    def read_floats(self, arr: wp.array, count: int) -> tuple[float, ...]:
        """The first `count` float32 values of arr."""
        raw = wp.array(ptr=self._host.ptr, dtype=wp.float32, shape=(count,), device="cpu")
        wp.copy(raw, arr, count=count)
        self._wait()
        return tuple(float(x) for x in raw.numpy())

    def read_array(self, arr: wp.array, count: int) -> np.ndarray:
        wp.copy(self._host, arr, count=count)
        self._wait()
        return self._host.numpy()[:count].copy()

    def _wait(self) -> None:
        if self.device.is_cuda:
            wp.synchronize_stream(wp.get_stream(self.device))


class KeptViews:
    """Kernel views (Warp structs) kept for as long as what they are made of stays the same: each array by identity,
    each number by value. Setting a struct's fields goes through Warp's Python, about 50 us for a query's three
    views on this project's CPU, where a query of one point takes about 130 us besides; a kept view is handed back
    while every field is the one it was made with. A kept view holds its arrays, so an array replaced since stays
    alive until its slot's next view is made: `clear` (a trim) lets go of all of them."""

    # False: every view made anew (for bench/probes/probe_small_queries.py to compare)
    keep = True

    def __init__(self, struct):
        self._struct = struct
        self._kept: dict[int, tuple[tuple, object]] = {}

    def view(self, fields: dict[str, object], slot: int = 0):
        """The struct with these field values, kept in `slot` (a view per slot: the frame's and the queries')."""
        values = tuple(fields.values())
        kept = self._kept.get(slot)
        if kept is not None and kept[0] == values and KeptViews.keep:
            return kept[1]
        view = self._struct()
        for name, value in fields.items():
            setattr(view, name, value)
        self._kept[slot] = (values, view)
        return view

    def clear(self) -> None:
        self._kept.clear()


class KeptLaunch:
    """A kernel launch recorded once (Warp's `record_cmd`) and replayed while its arguments stay the same: each
    array and struct by identity, each number by value. Packing a launch's arguments goes through Warp's Python for
    each of them, a fifth of a one-point query's time on this project's CPU; a replay hands Warp the packed ones. A
    kept launch holds its arguments, so an array replaced since stays alive until the next launch is recorded:
    `clear` (a trim) lets go of them."""

    # False: every launch packed anew (for bench/probes/probe_small_queries.py to compare)
    keep = True

    def __init__(self):
        self._kept: tuple[tuple, object] | None = None
        self.replays = 0

    def launch(self, kernel, dim: int, inputs: list, outputs: list, device) -> None:
        """`wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device)`, replayed where the last one
        had the same kernel, dimension and arguments."""
        arguments = (kernel, dim, device, *inputs, *outputs)
        kept = self._kept
        if kept is not None and KeptLaunch.keep and _same_arguments(kept[0], arguments):
            kept[1].launch()
            self.replays += 1
            return
        self._kept = None  # let go of the old arguments first
        recorded = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, record_cmd=True)
        recorded.launch()
        self._kept = (arguments, recorded)

    def let_go_unless(self, arguments: tuple) -> None:
        """Let go of the kept launch unless each of these objects is among its arguments."""
        if self._kept is not None and not all(any(a is b for b in self._kept[0]) for a in arguments):
            self._kept = None

    def clear(self) -> None:
        self._kept = None


def _same_arguments(before: tuple, now: tuple) -> bool:
    """Each argument the same object, or a number of the same type and value."""
    if len(before) != len(now):
        return False
    for a, b in zip(before, now):
        if a is b:
            continue
        if type(a) is not type(b) or not isinstance(a, (int, float, np.number)) or a != b:
            return False
    return True
