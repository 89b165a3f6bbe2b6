"""The one place where badf turns its options into a Zenoh configuration."""

from __future__ import annotations

import json
import re
import socket
from typing import Literal, Sequence

import zenoh

from badf.protocol._errors import InvalidOptionError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"

ZenohMode = Literal["router", "peer", "client"]


def zenoh_config(
    *,
    mode: ZenohMode,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] = (),
    config_file: str | None = None,
    connect_timeout_s: float | None = None,
) -> zenoh.Config:
    """A Zenoh configuration for a badf worker or client.

    It starts from Zenoh's defaults with multicast scouting off (only the endpoints given are used) and shared
    memory off: Zenoh's SHM transport was seen to lose queries and replies on a starved CPU
    (eclipse-zenoh/zenoh#2628). With `config_file` (JSON5: TLS, authentication, access control), that file is
    the base, and these two stay off unless its text names them ("scouting", "shared_memory"): a file that only
    sets the lease turned both on (thirty-sixth outside check). In both cases `mode` and the endpoints given
    here override the base: `listen` None keeps the base's (Zenoh's default for a router is every interface's
    port 7447, for a peer a random port), while an empty `listen` means listen nowhere. `connect_timeout_s`
    bounds how long opening the session waits for `connect`.

    Raises InvalidOptionError naming the endpoint or the config file that Zenoh does not accept. Zenoh checks
    an endpoint's form here (PROTOCOL/ADDRESS); whether it can be reached is known only when a session opens.
    """
    if config_file is None:
        config = zenoh.Config()
    else:
        try:
            config = zenoh.Config.from_file(config_file)
        except zenoh.ZError as error:
            raise InvalidOptionError(f"cannot use the Zenoh config file {config_file!r}: {zenoh_message(error)}") from None
    if not config_file_names(config_file, "scouting"):
        config.insert_json5("scouting/multicast/enabled", "false")
    if not config_file_names(config_file, "shared_memory"):
        config.insert_json5("transport/shared_memory/enabled", "false")
    config.insert_json5("mode", json.dumps(mode))
    if listen is not None:
        config.insert_json5("listen/endpoints", _endpoints_json(listen, "listen"))
    if connect:
        config.insert_json5("connect/endpoints", _endpoints_json(connect, "connect"))
    if connect_timeout_s is not None:
        config.insert_json5("connect/timeout_ms", json.dumps(max(1, round(connect_timeout_s * 1000))))
    return config


def config_file_names(config_file: str | None, word: str) -> bool:
    """Whether a Zenoh config file's text names `word` (a section or key, or in a comment); False without a file.
    Zenoh's parsed config cannot tell a value the file set from its own default."""
    if config_file is None:
        return False
    try:
        with open(config_file, encoding="utf-8", errors="replace") as file:
            return word in file.read()
    except OSError as error:
        raise InvalidOptionError(f"cannot read the Zenoh config file {config_file!r}: {error}") from None


def _endpoints_json(endpoints: Sequence[str], role: str) -> str:
    """The endpoints as JSON, each checked by Zenoh's own parser so that an error names the one at fault."""
    if isinstance(endpoints, str):
        endpoints = [endpoints]
    probe = zenoh.Config()
    for endpoint in endpoints:
        if not isinstance(endpoint, str):
            raise InvalidOptionError(f"a {role} endpoint must be a string like {DEFAULT_ENDPOINT}, got {endpoint!r}")
        try:
            probe.insert_json5(f"{role}/endpoints", json.dumps([endpoint]))
        except zenoh.ZError:
            raise InvalidOptionError(
                f"{role} endpoint {endpoint!r} is not a Zenoh endpoint: expected PROTOCOL/ADDRESS, "
                f"for instance {DEFAULT_ENDPOINT}"
            ) from None
        if endpoint.partition("/")[0].lower() in _LOSSY_PROTOCOLS:
            raise InvalidOptionError(
                f"{role} endpoint {endpoint!r}: Zenoh's UDP links may drop messages, and badf's requests and "
                "frames must not be lost; use tcp/, tls/ or quic/"
            )
        problem = _address_problem(endpoint)
        if problem is not None:
            raise InvalidOptionError(f"{role} endpoint {endpoint!r} {problem}")
    return json.dumps(list(endpoints))


_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_LOSSY_PROTOCOLS = ("udp",)  # best effort: a request or a registration sent on it can vanish without a word


def _address_problem(endpoint: str) -> str | None:
    """What is wrong with an IP endpoint's HOST:PORT (metadata after '?' or '#' aside), or None. Zenoh's parser
    takes any text there, and a port of -1 or "abc", or no port, failed only when the session opened, as
    "is a port taken?" and exit status 1 (sixteenth outside check)."""
    protocol, _, address = endpoint.partition("/")
    if protocol.lower() not in _IP_PROTOCOLS:
        return None
    address = re.split(r"[?#]", address, maxsplit=1)[0]
    if address.startswith("["):  # [IPv6]:PORT
        host, bracket, rest = address[1:].partition("]")
        colon, port = rest[:1], rest[1:]
        if not bracket or rest[:1] not in ("", ":"):
            return "is not [IPv6]:PORT, for instance tcp/[::1]:7447"
    else:
        host, colon, port = address.rpartition(":")
    if not colon or not port:
        return f"names no port: expected {protocol}/HOST:PORT, for instance {DEFAULT_ENDPOINT}"
    if not host:
        return f"names no host: expected {protocol}/HOST:PORT, for instance {DEFAULT_ENDPOINT}"
    if not port.isascii() or not port.isdigit():
        return f"names port {port!r}: a port is a number, 0 to 65535"
    if not 0 <= int(port) <= 65535:
        return f"names port {int(port)}: a port is 0 to 65535"
    octets = host.split(".")
    if len(octets) == 4 and all(o.isascii() and o.isdigit() for o in octets) and any(int(o) > 255 for o in octets):
        return f"names host {host!r}: each part of an IPv4 address is 0 to 255"
    return None


def with_a_free_port(endpoint: str) -> str:
    """A TCP endpoint that names port 0 with that port replaced by one free on its host a moment ago; any other
    endpoint as it came. Zenoh binds port 0 to a port of its own and tells nobody which (a router on
    tcp/127.0.0.1:0 logged that it listened on port 0), so the port is chosen before the session opens and
    logged as it is. Endpoints are checked by `zenoh_config` first."""
    protocol, _, address = endpoint.partition("/")
    if protocol.lower() != "tcp":
        return endpoint
    split = re.split(r"([?#])", address, maxsplit=1)
    host_port, rest = split[0], "".join(split[1:])
    host, colon, port = host_port.rpartition(":")
    if not colon or port != "0":
        return endpoint
    bare = host[1:-1] if host.startswith("[") else host
    family = socket.AF_INET6 if ":" in bare else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.bind((bare, 0))
            free = probe.getsockname()[1]
    except OSError as error:
        raise InvalidOptionError(f"listen endpoint {endpoint!r}: no port can be bound on {host} ({error})") from None
    return f"{protocol}/{host}:{free}{rest}"


def zenoh_message(error: Exception) -> str:
    """Zenoh's message without the Rust source locations it appends (" at /root/.cargo/.../x.rs:388.")."""
    return _SOURCE_LOCATION.sub("", str(error)).strip()


_SOURCE_LOCATION = re.compile(r"\s+at /\S+\.rs:\d+\.?")
