"""The CPU back-end's launches over corners and query points shared out over the machine's cores.

Warp runs a CPU launch's threads one after another on the calling thread, and lets go of the GIL while it does,
so launches over disjoint ranges of items run side by side from a pool of threads. Only kernels whose every
write is to their own item's slots are shared out (the corner searches without a split, the winding numbers, the
signs, the point queries), and the look beside a closed mesh's faces for parts running into each other, which
only ever sets one flag; each chunk sees the same kernel over a slice of the per-item arrays, with its own
count, so each item's answer is computed exactly as in one launch. CUDA launches go through unchanged.
"""

from __future__ import annotations

import concurrent.futures
import os
import threading

import warp as wp

from badf.server._environment import cpu_threads_setting

# Items per chunk below which a launch is not shared out (a launch costs tens of microseconds), and chunks per
# thread, so that chunks of long walks (corners far from the surface) do not leave the other threads idle. An
# exact query's point walks the BVH (about 10 us for the bunny on this project's CPU, a winding walk included), so
# exact batches are shared out from chunks of MIN_EXACT_CHUNK points.
MIN_CHUNK = 2048
MIN_EXACT_CHUNK = 256
CHUNKS_PER_THREAD = 4
MAX_CHUNKS = 256
COUNTS_ROOM = MAX_CHUNKS + 1  # a count per chunk, and a zero


def cpu_threads() -> int:
    """Threads the CPU back-end's launches are shared out over: $BADF_CPU_THREADS if set (1 turns it off), else
    the cores this process may run on."""
    threads = cpu_threads_setting()
    if threads is not None:
        return threads
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


_pool: concurrent.futures.ThreadPoolExecutor | None = None
_pool_threads = 0
_pool_lock = threading.Lock()


def _forget_pool() -> None:
    """In a forked child the pool's threads are not there: it makes its own when it first needs one."""
    global _pool, _pool_threads, _pool_lock
    _pool, _pool_threads, _pool_lock = None, 0, threading.Lock()


os.register_at_fork(after_in_child=_forget_pool)


def shared_pool(threads: int) -> concurrent.futures.ThreadPoolExecutor:
    """The process's pool of `threads` threads for CPU launches side by side (made again for another count)."""
    global _pool, _pool_threads
    with _pool_lock:
        if _pool is None or _pool_threads != threads:
            if _pool is not None:
                _pool.shutdown(wait=False)
            _pool = concurrent.futures.ThreadPoolExecutor(max_workers=threads, thread_name_prefix="badf-cpu")
            _pool_threads = threads
        return _pool


def chunks_for(capacity: int, threads: int | None = None, min_chunk: int | None = None) -> int:
    """How many chunks a launch over `capacity` items is cut into on the CPU back-end (1: one launch), each of at
    least `min_chunk` items (default MIN_CHUNK)."""
    threads = cpu_threads() if threads is None else threads
    if threads <= 1:
        return 1
    return max(1, min(CHUNKS_PER_THREAD * threads, MAX_CHUNKS, capacity // (min_chunk or MIN_CHUNK)))


def _launch_threads(device: wp.Device, dim: int, sliced, min_chunk: int | None) -> int:
    """The threads a launch over `dim` items is shared out over: 1 on CUDA, for a kernel that is not to be shared
    out, and below two chunks' items, whatever the setting (so a small query need not read it)."""
    if not device.is_cpu or sliced is None or dim < 2 * (min_chunk or MIN_CHUNK):
        return 1
    return cpu_threads()


def shares_out(device, dim: int, *, min_chunk: int | None = None) -> bool:
    """Whether `launch_per_item` cuts a launch over `dim` items into chunks (else it is one `wp.launch`)."""
    device = wp.get_device(device)
    return chunks_for(dim, _launch_threads(device, dim, (), min_chunk), min_chunk) > 1


def launch_per_item(kernel, dim: int, inputs: list, outputs: list, *, sliced: tuple[wp.array, ...] | None,
                    counts: wp.array | None = None, offset_at: int | None = None, min_chunk: int | None = None,
                    device, **launch_options) -> None:
    """`wp.launch(kernel, dim=dim, inputs, outputs, device, **launch_options)` for a kernel whose thread i handles
    item i and writes only item i's slots, or a flag that every thread writing it sets to the same value. On the CPU
    back-end the items are cut into chunks launched from a pool of threads, with the arrays in `sliced` (those with
    a slot per item, wherever they are passed; None: not to be shared out, as the kernel writes elsewhere too)
    sliced to the chunk. With `counts` (a CPU int32 array of COUNTS_ROOM), the kernel's first three arguments are
    (items, count, capacity = dim), it handles the items below min(count[0], capacity), and each chunk gets its own
    count (written into `counts`) and capacity. With `offset_at`, the argument there (of inputs, then outputs) is
    an int that the kernel adds to its thread index to find its item, and each chunk gets it plus its first item.
    Chunks hold at least `min_chunk` items (default MIN_CHUNK). Returns once every chunk has run; a chunk's error is
    raised here."""
    device = wp.get_device(device)
    threads = _launch_threads(device, dim, sliced, min_chunk)
    chunks = chunks_for(dim, threads, min_chunk)
    if chunks <= 1:
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, **launch_options)
        return
    arguments = [*inputs, *outputs]
    listed = dim if counts is None else min(int(arguments[1].numpy()[0]), dim)
    bounds = [dim * j // chunks for j in range(chunks + 1)]
    chunk_counts = None if counts is None else counts.numpy()
    launches = []
    for j in range(chunks):
        start, end = bounds[j], bounds[j + 1]
        if start >= listed:
            break
        chunk = list(arguments)
        if counts is not None:
            chunk_counts[j] = min(listed, end) - start
            chunk[1], chunk[2] = counts[j : j + 1], end - start
        for at, argument in enumerate(arguments):
            if any(argument is array for array in sliced):
                chunk[at] = argument[start:end]
        if offset_at is not None:
            chunk[offset_at] = arguments[offset_at] + start
        launches.append((end - start, chunk))
    if not launches:
        return
    split = len(inputs)
    # one item first, here, loads the kernel's module (if it is not yet), which the threads then find loaded: with
    # a count of zero it does nothing else; without a count it answers the first item, as its chunk will again
    idle_dim, idle = 1, list(launches[0][1])
    if counts is not None:
        chunk_counts[MAX_CHUNKS] = 0
        idle[1] = counts[MAX_CHUNKS : MAX_CHUNKS + 1]
    wp.launch(kernel, dim=idle_dim, inputs=idle[:split], outputs=idle[split:], device=device, **launch_options)
    pool = shared_pool(threads)
    futures = [pool.submit(wp.launch, kernel, dim=chunk_dim, inputs=chunk[:split], outputs=chunk[split:],
                           device=device, **launch_options) for chunk_dim, chunk in launches]
    for future in futures:
        future.result()
