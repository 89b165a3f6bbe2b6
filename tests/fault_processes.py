"""Client processes that the fault tests start (with `spawn`) and then kill or abandon.

Each works on the cube of the soak benchmark, whose frame F is moved by offset(F) along x, so whoever
looks afterwards can tell from one exact query which frame an object holds and that it is whole.
"""

from __future__ import annotations

import time

import numpy as np

from badf.bench.soak import cube, frame_vertices
from badf.client import Client
from badf.protocol import InfoRequest, KeySpace, SliceRequest, encode, zenoh_config

BIG_FRAME_VERTICES = 1_000_000  # 12 MB per frame on the wire


def big_cube() -> tuple[np.ndarray, np.ndarray]:
    """The soak cube plus a million unreferenced copies of its first vertex: frames of 12 MB that the
    engine applies cheaply (it refits 768 triangles), so the sender spends its time sending."""
    vertices, faces = cube(8)
    padding = np.repeat(vertices[:1], BIG_FRAME_VERTICES - len(vertices), axis=0)
    return np.concatenate([vertices, padding]), faces


def send_big_frames_until_killed(endpoint: str, name: str, acknowledged, sending) -> None:
    """Register `name` (12 MB frames), apply three frames with `update` (the last acknowledged number goes
    into `acknowledged`), set `sending`, then send frames back to back (two streamed, one update) until
    killed; bounded at 10,000 frames in case nobody kills it."""
    base, faces = big_cube()
    with Client(endpoint, timeout=120) as client:
        obj = client.register(name, base, faces, depth=3)
        for _ in range(3):
            acknowledged.value = obj.update(frame_vertices(base, obj.frame + 1))
        sending.set()
        for count in range(10_000):
            if count % 3 == 2:
                acknowledged.value = obj.update(frame_vertices(base, obj.frame + 1))
            else:
                obj.stream(frame_vertices(base, obj.frame + 1))


def ask_for_slices(endpoint: str, name: str, count: int, resolution: int, sent) -> None:
    """A viewer: ask for `count` slices of `name` at once, then for the object's info (answered at once, so
    its reply says the slice requests, sent before it on the same link, have arrived), and set `sent`; the
    test then stops this process (SIGSTOP), so nothing reads the replies. Bounded: it exits after 10
    minutes if nobody ends it."""
    import zenoh

    keys = KeySpace()
    session = zenoh.open(zenoh_config(mode="client", connect=[endpoint]))
    payload = encode(SliceRequest(name, "z", 0.0, resolution=resolution))
    for _ in range(count):
        session.get(keys.object_slice(name), lambda _reply: None, payload=payload, timeout=600)
    for reply in session.get(keys.object_info(name), payload=encode(InfoRequest(name)), timeout=60):
        if reply.ok is not None:
            sent.set()
    time.sleep(600)
