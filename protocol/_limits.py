"""Size limits a decoder enforces from a message's header, before it allocates anything."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Limits:
    """Upper bounds on what one message may carry. The defaults fit a 1M-point query and a 10M-vertex mesh.

    Zenoh's own receive limit (`transport/link/rx/max_message_size`, 1 GiB by default) must stay above
    `max_message_bytes`, or larger messages are dropped silently instead of answered with an error.
    """

    max_vertices: int = 10_000_000
    max_faces: int = 20_000_000
    max_points: int = 4_194_304
    max_cells: int = 4_194_304
    max_slice_resolution: int = 2048
    max_message_bytes: int = 512 * 1024 * 1024
    max_metadata_bytes: int = 64 * 1024

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"Limits.{name} must be a positive integer, got {value!r}")

    def to_json(self) -> dict[str, int]:
        return asdict(self)


DEFAULT_LIMITS = Limits()
