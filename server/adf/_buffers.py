"""Device arrays of one object, by name: allocated once, grown geometrically when a size needs it, counted."""

from __future__ import annotations

import warp as wp

# A buffer that must grow gets this much headroom, so a slowly growing octree does not reallocate each frame.
_GROWTH = 1.5


class DeviceBuffers:
    def __init__(self, device: wp.Device):
        self.device = device
        self._arrays: dict[str, wp.array] = {}

    def array(self, name: str, count: int, dtype) -> wp.array:
        """A zeroed array of exactly `count` elements (at least one), replacing any of that name."""
        arr = wp.zeros(max(int(count), 1), dtype=dtype, device=self.device)
        self._arrays[name] = arr
        return arr

    def ensure(self, name: str, count: int, dtype) -> wp.array:
        """The array of that name if it holds `count` elements, else a larger one (contents not kept)."""
        arr = self._arrays.get(name)
        if arr is None or arr.shape[0] < count:
            grown = count if arr is None else max(count, int(arr.shape[0] * _GROWTH))
            arr = wp.empty(max(grown, 1), dtype=dtype, device=self.device)
            self._arrays[name] = arr
        return arr

    def nbytes(self) -> int:
        return sum(arr.capacity for arr in self._arrays.values())
