"""Access control: workers started from the example configuration (examples/secure/*.json5: TLS only, users
and passwords, rules by user and key expression), pointed at throwaway certificates made with openssl in a
temporary folder, and clients connecting with the example client configuration.

Shown: by default a worker listens on 127.0.0.1 only; a client without a user, with a wrong password, in
plain TCP, or without the CA is refused while connecting; a read-only user queries, slices and reads info
but can neither register, update, stream nor delete; two tenants (namespaces, each with its own worker)
share a router and an object name, and neither can see or reach the other's objects.
"""

from __future__ import annotations

import json
import pathlib
import secrets
import shutil
import subprocess
from contextlib import ExitStack
from dataclasses import dataclass

import pytest
import zenoh
from conftest import free_endpoint, wait_until

from badf.bench.soak import PROBE, cube, expected_probe_distance, frame_vertices
from badf.client import Client
from badf.protocol import AccessDeniedError, BadfError, WorkerUnavailableError, zenoh_config
from badf.server import WorkerSettings, worker_process

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples" / "secure"
USERS = ("alice", "carol", "bob", "worker-b")  # tenant A's user and reader, tenant B's user and worker
BASE, FACES = cube(8)
BIG, _ = cube(8)
BIG *= 2  # tenant B's object of the same name is twice the size: its probe distance is 1 - offset(F)

def make_certificates(folder: pathlib.Path) -> None:
    """A throwaway CA and a server certificate for localhost / 127.0.0.1 signed by it (valid one day)."""
    folder.mkdir(parents=True)

    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True, timeout=60)

    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "1",
            "-subj", "/CN=badf test CA")  # fmt: skip
    openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "server.key", "-out", "server.csr",
            "-subj", "/CN=localhost")  # fmt: skip
    (folder / "san.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    openssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", "server.pem", "-days", "1", "-extfile", "san.cnf")  # fmt: skip


def from_example(name: str, folder: pathlib.Path, replacements: dict[str, str], *, saved_as: str | None = None) -> str:
    """An example config with its /etc/badf/ paths moved into `folder` and the given texts replaced."""
    text = (EXAMPLES / name).read_text()
    for old, new in replacements.items():
        assert old in text, f"{old!r} is not in {name}: the example and this test have drifted apart"
        text = text.replace(old, new)
    text = text.replace("/etc/badf/", f"{folder}/")
    path = folder / (saved_as or name)
    path.write_text(text)
    return str(path)


@dataclass
class Deployment:
    endpoint: str  # the router's TLS endpoint
    configs: dict[str, str]  # client config file per user, and "anonymous", "wrong password", "no CA"


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    """Worker "a" (the router, tenant A) from worker.json5 and worker "b" (tenant B, behind it) from
    worker-behind-router.json5, both in their own processes; client configs from client.json5."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl makes the throwaway certificates")
    folder = tmp_path_factory.mktemp("secure")
    make_certificates(folder / "tls")
    passwords = {user: secrets.token_urlsafe(16) for user in USERS}
    (folder / "users.txt").write_text("".join(f"{user}:{password}\n" for user, password in passwords.items()))
    endpoint = "tls/127.0.0.1:" + free_endpoint().rsplit(":", 1)[1]
    router_config = from_example("worker.json5", folder, {"tls/0.0.0.0:7447": endpoint})
    alice = 'user: "alice", password: "REPLACE-WITH-ALICES-PASSWORD"'
    configs = {
        user: from_example("client.json5", folder, {alice: f"user: {json.dumps(user)}, password: {json.dumps(pw)}"},
                           saved_as=f"{user}.json5")
        for user, pw in passwords.items() if user != "worker-b"
    }  # fmt: skip
    configs["anonymous"] = from_example("client.json5", folder, {alice: ""}, saved_as="anonymous.json5")
    configs["wrong password"] = from_example(
        "client.json5", folder, {"REPLACE-WITH-ALICES-PASSWORD": "not-her-password"}, saved_as="wrong.json5"
    )
    configs["no CA"] = from_example(
        "client.json5", folder,
        {'tls: { root_ca_certificate: "/etc/badf/tls/ca.pem" },': "",
         "REPLACE-WITH-ALICES-PASSWORD": passwords["alice"]},
        saved_as="no-ca.json5",
    )  # fmt: skip
    worker_b_config = from_example(
        "worker-behind-router.json5", folder, {"REPLACE-WITH-WORKER-B-PASSWORD": passwords["worker-b"]}
    )
    tenant_a = WorkerSettings(worker_id="a", namespace="tenant-a", config_file=router_config, device="cpu")
    tenant_b = WorkerSettings(
        worker_id="b", namespace="tenant-b", mode="client", connect=(endpoint,), config_file=worker_b_config,
        device="cpu",
    )  # fmt: skip
    with worker_process(tenant_a, start_timeout_s=300.0), worker_process(tenant_b, start_timeout_s=300.0):
        yield Deployment(endpoint, configs)


def connect(deployment: Deployment, who: str, namespace: str, timeout: float = 30.0) -> Client:
    return Client(deployment.endpoint, namespace=namespace, config_file=deployment.configs[who], timeout=timeout)


def assert_answers(obj, frame: int, *, half_size: float) -> None:
    reply = obj.query(PROBE, mode="exact")
    assert reply.frame == frame
    assert abs(float(reply.distance[0]) - (expected_probe_distance(frame) + 0.5 - half_size)) <= 1e-4


def test_a_worker_listens_on_loopback_only_by_default() -> None:
    """`badf serve` without --listen or --config: its router socket is bound to 127.0.0.1 (read back from
    /proc/net/tcp and tcp6), so no other machine can reach it."""
    settings = WorkerSettings()
    assert json.loads(settings.zenoh_config().get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    try:
        session = zenoh.open(settings.zenoh_config())
    except zenoh.ZError:
        pytest.skip("port 7447 is taken on this machine")
    with session:
        listening = _listening_addresses(7447)
    assert listening == {"127.0.0.1"}, listening


def _listening_addresses(port: int) -> set[str]:
    addresses = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            rows = pathlib.Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            local, state = row.split()[1], row.split()[3]
            address, hex_port = local.rsplit(":", 1)
            if state == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                addresses.add(_address(address))
    return addresses


def _address(hex_address: str) -> str:
    raw = bytes.fromhex(hex_address)
    if len(raw) == 4:
        return ".".join(str(b) for b in raw[::-1])
    words = [raw[i : i + 4][::-1] for i in range(0, 16, 4)]  # tcp6: four little-endian 32-bit words
    import ipaddress

    return str(ipaddress.IPv6Address(b"".join(words)))


@pytest.mark.parametrize("who", ["anonymous", "wrong password", "no CA", "plain TCP"])
def test_unauthenticated_clients_are_refused(deployment: Deployment, who: str) -> None:
    if who == "plain TCP":
        endpoint = deployment.endpoint.replace("tls/", "tcp/")
        with pytest.raises(WorkerUnavailableError, match="cannot reach"):
            Client(endpoint, namespace="tenant-a", timeout=3)
        return
    with pytest.raises(WorkerUnavailableError, match="cannot reach"):
        connect(deployment, who, "tenant-a", timeout=3)


def test_a_reader_queries_but_cannot_register_update_stream_or_delete(deployment: Deployment) -> None:
    with ExitStack() as stack:
        alice = stack.enter_context(connect(deployment, "alice", "tenant-a"))
        carol = stack.enter_context(connect(deployment, "carol", "tenant-a", timeout=5))
        owned = alice.register("reader-test", BASE, FACES, depth=4)
        assert owned.update(frame_vertices(BASE, 1)) == 1
        seen = carol.object("reader-test")
        assert [info.name for info in carol.objects()] == ["reader-test"]
        assert [info.worker for info in carol.workers()] == ["a"]
        assert_answers(seen, 1, half_size=0.5)
        assert seen.slice("z", 0.0, resolution=16).frame == 1
        assert seen.info().frame == 1
        with pytest.raises(AccessDeniedError, match="tenant-a/worker/a/register"):
            carol.register("carols-own", BASE, FACES, depth=4)
        with pytest.raises(AccessDeniedError, match="tenant-a/obj/reader-test/frame"):
            seen.update(frame_vertices(BASE, 2))
        for _ in range(20):  # never delivered: denied at the router
            seen.stream(frame_vertices(BASE, seen.frame + 1))
        with pytest.raises(AccessDeniedError, match="tenant-a/obj/reader-test/delete"):
            seen.delete()
        for _ in range(2):
            seen.info()  # round trips of carol's session after her puts
        assert owned.update(frame_vertices(BASE, 2)) == 2  # had her frames 3.. arrived, this would be stale
        info = owned.info()
        assert (info.frame, info.frames_applied, info.frames_dropped, info.frames_rejected) == (2, 2, 0, 0)
        assert [info.name for info in alice.objects()] == ["reader-test"]
        owned.delete()


def test_two_tenants_cannot_see_each_other(deployment: Deployment) -> None:
    with ExitStack() as stack:
        alice = stack.enter_context(connect(deployment, "alice", "tenant-a"))
        bob = stack.enter_context(connect(deployment, "bob", "tenant-b"))
        wait_until(lambda: [w.worker for w in bob.workers(timeout=5)] == ["b"], timeout=60, what="tenant B's worker")
        mine = alice.register("shared-name", BASE, FACES, depth=4)
        theirs = bob.register("shared-name", BIG, FACES, depth=4)
        assert (mine.worker, theirs.worker) == ("a", "b")
        assert [(i.name, i.worker) for i in alice.objects()] == [("shared-name", "a")]
        assert [(i.name, i.worker) for i in bob.objects()] == [("shared-name", "b")]
        assert_answers(alice.object("shared-name"), 0, half_size=0.5)
        assert_answers(bob.object("shared-name"), 0, half_size=1.0)
        for user, other in (("alice", "tenant-b"), ("bob", "tenant-a")):  # a user in the other's namespace
            with connect(deployment, user, other, timeout=5) as intruder:
                assert intruder.workers(timeout=5) == [] and intruder.objects(timeout=5) == []
                with pytest.raises(BadfError):
                    intruder.object("shared-name", timeout=5)
                with pytest.raises(BadfError):
                    intruder.register("planted", BASE, FACES, worker="a" if other == "tenant-a" else "b", timeout=5)
        config = zenoh_config(mode="client", connect=[deployment.endpoint], config_file=deployment.configs["alice"])
        with zenoh.open(config) as session:  # every namespace at once: nothing of tenant B comes back
            keys = [str(reply.ok.key_expr) for reply in session.get("*/obj/*/info", timeout=5) if reply.ok]
            keys += [str(reply.ok.key_expr) for reply in session.liveliness().get("*/worker/*", timeout=5) if reply.ok]
        assert not any(key.startswith("tenant-b") for key in keys), keys
        assert [i.name for i in bob.objects()] == [i.name for i in alice.objects()] == ["shared-name"]
        mine.delete()
        theirs.delete()


def test_the_sdist_holds_the_examples_and_the_tests_whole(tmp_path) -> None:
    """The source distribution held tests/test_*.py but not the helpers they import (conftest.py, meshes.py,
    oracle.py, ...) nor tests/data, and not the example configurations above (eleventh outside check):
    MANIFEST.in adds tests/, examples/ and docs/. Built from a copy of the checkout, without build isolation."""
    import sys
    import tarfile

    root = EXAMPLES.parents[1]
    source = tmp_path / "source"
    shutil.copytree(root, source, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", "*.pyc", ".pytest_cache", ".gpu*", ".whl",
        "test-artifacts", "bench-out"))  # fmt: skip
    subprocess.run([sys.executable, "-c", "import sys; from setuptools import build_meta; "
                    "build_meta.build_sdist(sys.argv[1])", str(tmp_path / "dist")],
                   cwd=source, check=True, capture_output=True, timeout=300)  # fmt: skip
    [sdist] = (tmp_path / "dist").glob("badf-*.tar.gz")
    with tarfile.open(sdist) as archive:
        shipped = {name.split("/", 1)[1] for name in archive.getnames() if "/" in name}
    wanted = {str(path.relative_to(source)) for folder in ("tests", "examples") for path in (source / folder).rglob("*")
              if path.is_file()}
    assert {"tests/conftest.py", "tests/meshes.py", "tests/data/README.md", "examples/secure/worker.json5"} <= wanted
    assert sorted(wanted - shipped) == []
