"""A Zenoh router for badf workers and clients (`badf serve --router-only`, and the router in front of
`badf serve --gpus`): it routes every request to the worker that declared the object's keys, and logs
workers joining and leaving, as their liveliness tokens come and go."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from typing import Sequence

import zenoh

from badf.protocol import DEFAULT_ENDPOINT, KeySpace, config_file_names, zenoh_config

log = logging.getLogger("badf.server")


@dataclass(frozen=True)
class RouterSettings:
    """Where a router listens and which routers it joins. `listen` None means: with a config file whose text
    names `listen`, the file's endpoints; otherwise tcp/127.0.0.1:7447 when it connects to nothing, else no
    endpoint."""

    namespace: str = "badf"
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] = ()
    config_file: str | None = None

    def __post_init__(self) -> None:
        KeySpace(self.namespace)
        self.zenoh_config()  # InvalidOptionError now, naming a malformed endpoint or config file

    def zenoh_config(self, *, extra_listen: Sequence[str] = ()) -> zenoh.Config:
        """The router's configuration; `extra_listen` endpoints are added to the others (the private
        loopback endpoint of the workers that `badf serve --gpus` starts)."""
        listen = self.listen
        if listen is None and not config_file_names(self.config_file, "listen"):
            listen = () if self.connect else (DEFAULT_ENDPOINT,)
        config = zenoh_config(mode="router", listen=listen, connect=self.connect, config_file=self.config_file)
        if extra_listen:
            current = json.loads(config.get_json("listen/endpoints"))
            if isinstance(current, dict):  # Zenoh's per-mode default
                current = current.get("router", [])
            config.insert_json5("listen/endpoints", json.dumps([*current, *extra_listen]))
        return config


def configured_endpoints(config: zenoh.Config, which: str) -> list[str]:
    """The endpoints a configuration listens on (`which` = "listen") or connects to ("connect"), for its
    mode where the file gives them per mode."""
    endpoints = json.loads(config.get_json(f"{which}/endpoints"))
    if not isinstance(endpoints, dict):
        return list(endpoints or [])
    mode = json.loads(config.get_json("mode")) or "peer"  # Zenoh's own default mode
    return list(endpoints.get(mode, []))


def log_worker_changes(session: zenoh.Session, namespace: str) -> zenoh.Subscriber:
    """Log each worker of `namespace` that joins or leaves (its liveliness token appears or goes)."""
    keys = KeySpace(namespace)

    def on_change(sample: zenoh.Sample) -> None:
        worker = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == zenoh.SampleKind.DELETE:
            log.warning("worker %s left: its objects are unavailable until clients register them again", worker)
        else:
            log.info("worker %s joined", worker)

    return session.liveliness().declare_subscriber(keys.every_worker_token, on_change, history=True)
