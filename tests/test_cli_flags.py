"""Malformed command lines end with one line on stderr and exit status 2, before anything starts."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from conftest import free_endpoint

CASES = [
    (["serve", "--listen", "notanendpoint"], "listen endpoint 'notanendpoint' is not a Zenoh endpoint"),
    (["serve", "--listen", "<free>", "--connect", "garbage"], "connect endpoint 'garbage' is not a Zenoh endpoint"),
    (["serve", "--router-only", "--listen", "nowhere"], "listen endpoint 'nowhere' is not a Zenoh endpoint"),
    (["serve", "--listen", "tcp/127.0.0.1:99999"], "names port 99999: a port is 0 to 65535"),
    # ports and hosts that Zenoh's parser took and only the session's opening refused, as "is a port taken?"
    # with exit status 1 (sixteenth outside check)
    (["serve", "--listen", "tcp/127.0.0.1:-1"], "names port '-1': a port is a number, 0 to 65535"),
    (["serve", "--listen", "tcp/127.0.0.1:abc"], "names port 'abc': a port is a number"),
    (["serve", "--listen", "tcp/127.0.0.1"], "'tcp/127.0.0.1' names no port: expected tcp/HOST:PORT"),
    (["serve", "--listen", "tcp/127.0.0.1:"], "names no port"),
    (["serve", "--listen", "tcp/999.0.0.1:17479"], "names host '999.0.0.1': each part of an IPv4 address is 0 to 255"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "tcp/127.0.0.1:-1"], "--listen: listen endpoint"),
    (["serve", "--listen", "<free>", "--connect", "tcp/127.0.0.1:70000?iface=lo"], "names port 70000"),
    (["serve", "--listen", "<free>", "--config", "/nonexistent/badf.json5"], "cannot use the Zenoh config file"),
    (["serve", "--mode", "client"], "give the router to connect to (--connect tcp/HOST:7447)"),
    (["serve", "--mode", "client", "--connect", "<free>", "--listen", "<free>"], "client mode listens on nothing"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--mesh", "<nan-vertex>"],
     "nan.npz: vertex 2 is [0.0, nan, 0.0]"),
    (["view", "--port", "0", "--connect", "<free>", "--timeout", "1e300"], "timeout must be a positive number"),
    (["view", "--port", "0", "--connect", "<free>", "--namespace", "a//b"], "namespace chunk of 'a//b'"),
    (["serve", "--listen", "udp/127.0.0.1:7447"], "UDP links may drop messages"),
    (["view", "--connect", "notanendpoint"], "connect endpoint 'notanendpoint' is not a Zenoh endpoint"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--depth", "0"], "--depth must be in 1..10, got 0"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--depth", "11"], "--depth must be in 1..10, got 11"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--mesh", "/nonexistent/m.obj"],
     "/nonexistent/m.obj: no such file"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--sequence", "<not-npz>"], "not an .npz archive"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--port", "-3"], "--port must be in 0..65535, got -3"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "garbage"], "listen endpoint 'garbage' is not a Zenoh endpoint"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--points", "5000000"],
     "--points must be in 1..4194304, got 5000000"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--device", "gpu9"], "--device 'gpu9' is not a device"),
    (["demo", "--frames", "1", "--listen", "<free>", "--host", "999.9.9.9"], "--host: cannot serve the page on host"),
    (["serve", "--listen", "<free>", "--worker-id", ""], "--worker-id must be 1 to 100 characters"),
    (["serve", "--listen", "<free>", "--stats-interval", "-5"], "--stats-interval must be a positive"),
    # an endpoint twice (exit 1, 'is a port taken?'), and a worker joining itself (raw Zenoh errors each second)
    (["serve", "--listen", "tcp/127.0.0.1:9", "--listen", "tcp/127.0.0.1:9"], "--listen names tcp/127.0.0.1:9 twice"),
    (["serve", "--listen", "tcp/127.0.0.1:9", "--connect", "tcp/127.0.0.1:9"], "is this process's own --listen endpoint"),
    (["serve", "--router-only", "--listen", "tcp/127.0.0.1:9", "--connect", "tcp/127.0.0.1:9"], "own --listen endpoint"),
    # a router prints no stats lines: the flag was taken and ignored (eighteenth outside check)
    (["serve", "--router-only", "--listen", "<free>", "--stats-interval", "5"], "--stats-interval does not apply to --router-only"),
    (["serve", "--listen", "<free>", "--stats-interval", "nan"], "--stats-interval must be a positive finite number"),
    (["serve", "--listen", "<free>", "--stats-interval", "inf"], "--stats-interval must be a positive finite number"),
    (["serve", "--listen", "<free>", "--stats-interval", "1e-9"], "in 0.1..1e6, got 1e-09"),
    (["serve", "--listen", "<free>", "--stats-interval", "1e300"], "in 0.1..1e6, got 1e+300"),
    (["bench", "engine", "--quick", "--mesh", "<no-faces>", "--out", "/tmp"], "--out: '/tmp' is a folder"),
    (["bench", "engine", "--quick", "--mesh", "<no-faces>"], "no faces array (it holds vertices)"),
    (["bench", "service", "--small", "--mesh", "/nonexistent/m.npz"], "badf bench service: /nonexistent/m.npz"),
    # bench flags that no run could use: refused before anything starts (they were tracebacks after the run,
    # or runs that measured nothing and exited 0)
    (["bench", "engine", "--quick", "--mesh", "<no-faces>", "--depth", "0"], "--depth must be in 1..10, got 0"),
    (["bench", "engine", "--quick", "--mesh", "<no-faces>", "--out", "/nonexistent-dir/x.json"],
     "--out: the folder of '/nonexistent-dir/x.json' does not exist"),
    (["bench", "service", "--small", "--mesh", "<no-faces>", "--batches", "abc"], "--batches takes integers"),
    (["bench", "viewer", "--small", "--mesh", "<no-faces>", "--stream-fps", "0"], "--stream-fps must be a positive"),
    (["bench", "soak", "--clients", "0"], "--clients must be at least 1, got 0"),
    (["bench", "soak", "--grid", "100000"], "--grid must be at most 1,289"),
    (["bench", "service", "--small", "--mesh", "<no-faces>", "--points", "100000000"], "--points must be at most 4,194,304"),
    (["bench", "service", "--small", "--mesh", "<no-faces>", "--batches", "1024,8000000"], "--batches must be at most"),
    (["bench", "scaleout", "--small", "--mesh", "<no-faces>", "--seconds", "nan"], "--seconds must be a positive"),
    (["bench", "soak", "--device", "gpu3"], "--device 'gpu3' is not a device here"),
    (["bench", "accuracy", "--meshes", "nosuchmesh"], "--meshes nosuchmesh: not a mesh file here, nor a mesh in"),
    # a named mesh that is not there was skipped with exit status 0, and a stray --switch-meshes ignored, and
    # empty values ran as if absent (thirty-first outside check)
    (["bench", "accuracy", "--meshes", "spot,stanford-bunyy"], "--meshes stanford-bunyy: not a mesh file here"),
    (["bench", "accuracy", "--meshes", "spot", "--switch-meshes", "nothere"], "--switch-meshes nothere: not among"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--mesh", ""],
     "an empty name where a mesh file was expected"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--sequence", ""],
     "an empty name where a mesh file was expected"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--device", ""], "--device '' is not a device"),
    (["bench", "accuracy", "--render", "<not-npz>"], "not a results JSON file"),
    # refused after minutes of running, with a traceback (outside check, 2026-11-22)
    (["bench", "viewer", "--small", "--mesh", "<no-faces>", "--resolution", "100"],
     "--resolution must be one of 64, 128, 256, 512, 1024, got 100"),
    (["bench", "accuracy", "--out-dir", "<not-npz>"], "is a file; name a folder"),
    (["bench", "accuracy", "--render", "<engine-json>"], "not the results of `badf bench accuracy` (they are of"),
    (["bench", "scaleout", "--small", "--device", "cpu", "--mesh", "<no-faces>", "--workers", "200"],
     "--workers must be 1 to"),
    # flags run as if absent (outside check, 2026-11-22)
    (["bench", "engine", "--quick", "--mesh", "<no-faces>", "--block-sweep"], "--block-sweep and --register-sweep go with"),
    (["bench", "engine", "--device", "cpu", "--mesh", "<no-faces>", "--kernels"], "--kernels profiles CUDA activity"),
    (["bench", "soak", "--seconds", "10", "--warm-up", "100"], "--warm-up (100 s) must be shorter than --seconds (10)"),
    (["demo", "cloth", "--no-viewer", "--frames", "1", "--listen", "<free>", "--mesh", "m.obj"],
     "badf demo cloth: --mesh is for the morph scene"),
    (["demo", "cloth", "--no-viewer", "--frames", "1", "--listen", "<free>", "--points", "10"], "--points is for the morph"),
    (["demo", "--no-viewer", "--frames", "1", "--listen", "<free>", "--stiff"], "badf demo morph: --stiff is for the cloth"),
    # errors named the settings' fields (stats_interval_s, max_slice_hz), not the flags (eleventh outside check)
    (["serve", "--listen", "<free>", "--stats-interval", "0"], "badf serve: --stats-interval must be a positive"),
    (["serve", "--listen", "<free>", "--trim-after", "nan"], "badf serve: --trim-after must be 0 (never) or a finite"),
    (["serve", "--listen", "<free>", "--trim-after", "0.01"], "--trim-after must be 0 (never) or a finite number of "
     "seconds in 0.1..1e6, got 0.01"),
    (["serve", "--router-only", "--listen", "<free>", "--trim-after", "5"], "--trim-after does not apply to --router-only"),
    (["view", "--connect", "<free>", "--max-slice-hz", "0"], "badf view: --max-slice-hz must be a finite positive"),
    (["view", "--connect", "<free>", "--max-mesh-hz", "-1"], "badf view: --max-mesh-hz must be a finite positive"),
    (["view", "--connect", "<free>", "--max-info-hz", "nan"], "badf view: --max-info-hz must be a finite positive"),
    # a rate past any use was taken (1e300: no limit at all; 1e-300: never a poll; nineteenth outside check)
    (["view", "--connect", "<free>", "--max-info-hz", "1e300"], "--max-info-hz must be a finite positive number in 0.01..1000"),
    (["view", "--connect", "<free>", "--max-slice-hz", "1e-300"], "in 0.01..1000 per second, got 1e-300"),
    (["view", "--connect", "<free>", "--port", "70000"], "badf view: --port must be an integer in 0..65535"),
    (["view", "--connect", "<free>", "--timeout", "0"], "badf view: --timeout must be a positive number"),
    (["view", "--connect", "<free>", "--object", "a/b"], "badf view: --object must be 1 to 100 characters"),
    # counts and times past any use ended in tracebacks, some after the worker had started, and a folder that
    # cannot be written lost the run's results at its end (seventeenth outside check)
    (["bench", "service", "--small", "--mesh", "<no-faces>", "--round-trips", "10000000000"],
     "--round-trips must be at most 1,000,000 (a bound on what a run can use), got 10000000000"),
    (["bench", "soak", "--seconds", "99999999999999999999"], "--seconds must be at most 604,800 (a week), got 1e+20"),
    (["bench", "accuracy", "--workers", "99999999999999999999"], "--workers must be at most 256"),
    (["bench", "scaleout", "--small", "--mesh", "<no-faces>", "--workers", "100000"], "--workers must be at most 256"),
    (["bench", "engine", "--mesh", "<no-faces>", "--out", "/proc/badf-bench.json"], "--out: cannot write in '/proc'"),
    (["bench", "accuracy", "--out-dir", "/proc/badf-bench"], "--out-dir: cannot make '/proc/badf-bench'"),
    # serve named no devices for an unknown one, and died in a traceback for "cuda" where there is no CUDA
    # (seventeenth outside check; that case is the test below, as it needs a machine without CUDA)
    (["serve", "--listen", "<free>", "--device", "cuda:9"], "badf serve: --device 'cuda:9' is not a device here"),
]


@pytest.mark.parametrize(("args", "message"), CASES, ids=[" ".join(args) for args, _ in CASES])
def test_a_malformed_command_line_is_one_clear_line(args: list[str], message: str, tmp_path) -> None:
    (tmp_path / "not.npz").write_bytes(b"not a zip archive")
    np.savez(tmp_path / "no-faces.npz", vertices=np.zeros((3, 3), np.float32))
    np.savez(tmp_path / "nan.npz", vertices=np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], np.float32),
             faces=np.array([[0, 1, 2]]))
    (tmp_path / "engine.json").write_text('{"benchmark": "engine", "rows": []}')
    stand_ins = {"<free>": free_endpoint, "<not-npz>": lambda: str(tmp_path / "not.npz"),
                 "<engine-json>": lambda: str(tmp_path / "engine.json"),
                 "<no-faces>": lambda: str(tmp_path / "no-faces.npz"), "<nan-vertex>": lambda: str(tmp_path / "nan.npz")}
    args = [stand_ins[arg]() if arg in stand_ins else arg for arg in args]
    done = subprocess.run([sys.executable, "-m", "badf.cli", *args], capture_output=True, text=True, timeout=120)
    _assert_one_clear_line(done, message)


def test_serve_on_cuda_where_there_is_none_is_one_clear_line(endpoint: str) -> None:
    import warp as wp

    if wp.get_cuda_device_count() > 0:
        pytest.skip("this machine has CUDA")
    done = subprocess.run([sys.executable, "-m", "badf.cli", "serve", "--listen", endpoint, "--device", "cuda"],
                          capture_output=True, text=True, timeout=120)
    _assert_one_clear_line(done, "badf serve: --device 'cuda' is not a device here")


@pytest.mark.parametrize("value", ["abc", "0"])
@pytest.mark.parametrize("args", [["serve", "--listen", "<free>"], ["demo", "--no-viewer", "--frames", "1", "--listen",
                                  "<free>"], ["bench", "engine", "--quick"], ["bench", "random-check", "--cases", "2"]],
                         ids=lambda args: " ".join(args[:2]) if isinstance(args, list) else args)
def test_a_bad_cpu_threads_setting_is_one_line_before_anything_starts(args: list[str], value: str) -> None:
    """BADF_CPU_THREADS that is not a whole number of at least 1: serve logged the engine's failure with a
    traceback, demo's worker died in one, bench engine ended in one, and random-check counted it as an engine
    problem in every case (twenty-eighth outside check)."""
    args = [free_endpoint() if arg == "<free>" else arg for arg in args]
    done = subprocess.run([sys.executable, "-m", "badf.cli", *args], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "BADF_CPU_THREADS": value})
    _assert_one_clear_line(done, f"badf {args[0]}: BADF_CPU_THREADS must be")


def _assert_one_clear_line(done: subprocess.CompletedProcess, message: str) -> None:
    lines = [line for line in done.stderr.splitlines() if not line.startswith(("Warp ", "   "))]
    assert done.returncode == 2, done.stderr
    assert message in done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    assert len(lines) == 1, done.stderr


# A command run where an optional dependency is not installed (in a process that sees the module as absent:
# `import` raises ModuleNotFoundError, `importlib.util.find_spec` gives None). They died in a traceback, the
# demo's after it had started the worker, and the accuracy benchmark's after the whole run (eleventh outside
# check).
MISSING_EXTRAS = [
    ("warp", ["serve", "--listen", "<free>"],
     "badf serve needs 'warp', which is not installed; install it with: pip install 'badf[server]'"),
    ("warp", ["demo", "--no-viewer", "--frames", "1", "--listen", "<free>"],
     "badf demo needs 'warp', which is not installed; install it with: pip install 'badf[server]'"),
    ("viser", ["demo", "--frames", "1", "--listen", "<free>", "--port", "0"],
     "badf demo needs 'viser', which is not installed; install it with: pip install 'badf[viewer]', or pass "
     "--no-viewer"),
    ("warp", ["bench", "soak", "--seconds", "1"],
     "badf bench soak needs 'warp', which is not installed; install it with: pip install 'badf[bench]'"),
    ("trimesh", ["bench", "engine", "--quick", "--mesh", "<no-faces>"], "badf bench engine needs 'trimesh'"),
    ("matplotlib", ["bench", "accuracy", "--device", "cpu", "--meshes", "spot", "--depths", "3", "--dense-max-depth",
                    "3", "--switch-depth", "3", "--points", "60", "--near-points", "40", "--query-batch", "2000",
                    "--repeat", "1", "--switch-meshes", "spot", "--no-stability", "--workers", "1", "--out-dir",
                    "<out>"],
     "badf bench accuracy needs 'matplotlib', which is not installed; install it with: pip install 'badf[bench]'"),
]


@pytest.mark.parametrize(("absent", "args", "message"), MISSING_EXTRAS,
                         ids=[f"{absent}: {' '.join(args[:2])}" for absent, args, _ in MISSING_EXTRAS])
def test_a_missing_extra_is_one_line_naming_it(absent: str, args: list[str], message: str, tmp_path) -> None:
    (tmp_path / "sitecustomize.py").write_text(f"import sys\n\nsys.modules[{absent!r}] = None  # not installed\n")
    np.savez(tmp_path / "no-faces.npz", vertices=np.zeros((3, 3), np.float32))
    stand_ins = {"<free>": free_endpoint, "<out>": lambda: str(tmp_path / "out"),
                 "<no-faces>": lambda: str(tmp_path / "no-faces.npz")}
    args = [stand_ins[arg]() if arg in stand_ins else arg for arg in args]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run([sys.executable, "-m", "badf.cli", *args], capture_output=True, text=True, env=env,
                          timeout=300)
    _assert_one_clear_line(done, message)


# `python -m badf.bench.NAME`, documented as `badf bench NAME`, parsed its flags and ran on its own: no flag
# checks, a traceback for a missing file, no SIGTERM handling (eleventh outside check).
PYTHON_M_BENCH = [
    ("soak", ["--seconds", "0"], "badf bench soak: --seconds must be a positive finite number, got 0.0"),
    ("service", ["--small", "--mesh", "/nonexistent/nothere.npz"], "badf bench service: /nonexistent/nothere.npz"),
    ("engine", ["--quick", "--mesh", "<no-faces>", "--depth", "0"], "--depth must be in 1..10, got 0"),
    ("viewer", ["--small", "--mesh", "<no-faces>", "--stream-fps", "0"], "--stream-fps must be a positive"),
    ("scaleout", ["--small", "--mesh", "<no-faces>", "--seconds", "nan"], "--seconds must be a positive"),
    ("accuracy", ["--no-stability", "--meshes", "spot", "--depths", "0"], "--depths must be in 1..10"),
]


@pytest.mark.parametrize(("name", "args", "message"), PYTHON_M_BENCH, ids=[name for name, _, _ in PYTHON_M_BENCH])
def test_python_m_bench_runs_as_badf_bench(name: str, args: list[str], message: str, tmp_path) -> None:
    np.savez(tmp_path / "no-faces.npz", vertices=np.zeros((3, 3), np.float32))
    args = [str(tmp_path / "no-faces.npz") if arg == "<no-faces>" else arg for arg in args]
    done = subprocess.run([sys.executable, "-m", f"badf.bench.{name}", *args], capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    _assert_one_clear_line(done, message)


def test_a_worker_that_cannot_reach_its_router_says_where_it_looked() -> None:
    """A worker joining a router nobody runs was told "is the port taken?", which pointed at a port it
    does not take; it now names the router it could not reach."""
    nobody = free_endpoint()
    done = subprocess.run([sys.executable, "-m", "badf.cli", "serve", "--device", "cpu", "--mode", "client",
                           "--connect", nobody], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert f"is a router listening at {nobody}?" in done.stderr
    assert "taken" not in done.stderr


def test_a_router_on_port_0_says_the_port_it_took() -> None:
    """`--listen tcp/127.0.0.1:0` logged "router listening on tcp/127.0.0.1:0" while Zenoh took a port of its own,
    which nobody could then find (twenty-eighth outside check). The port is now chosen before the session opens,
    and the logged endpoint is one a client reaches."""
    import re
    import selectors
    import socket
    import time

    router = subprocess.Popen([sys.executable, "-m", "badf.cli", "serve", "--router-only", "--listen",
                               "tcp/127.0.0.1:0"], stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        watch = selectors.DefaultSelector()
        watch.register(router.stderr, selectors.EVENT_READ)
        deadline, said = time.monotonic() + 60.0, ""
        while "router listening on" not in said and time.monotonic() < deadline and router.poll() is None:
            if watch.select(timeout=1.0):
                said += router.stderr.readline()
        found = re.search(r"router listening on tcp/127\.0\.0\.1:(\d+)", said)
        assert found, said
        port = int(found.group(1))
        assert port != 0
        with socket.create_connection(("127.0.0.1", port), timeout=10.0):
            pass  # the router took the port it named
    finally:
        router.send_signal(signal.SIGINT)
        try:
            router.wait(timeout=30)
        except subprocess.TimeoutExpired:
            router.kill()
            router.wait()


def test_view_heeds_ctrl_c_while_it_waits_for_a_router() -> None:
    """With no router at --connect, opening the session blocks in Zenoh's native code for the whole
    --timeout, and SIGINT went unheeded until then (17.6 s of 20). The viewer now starts on a thread of its
    own, and the main thread ends the process on the signal."""
    nobody = free_endpoint()  # a port nobody listens on
    view = subprocess.Popen([sys.executable, "-m", "badf.cli", "view", "--connect", nobody, "--port", "0",
                             "--timeout", "120"], stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        for line in view.stderr:  # the line printed once the signal handlers are in place
            if line.startswith("badf view: connecting to"):
                break
        view.send_signal(signal.SIGINT)
        assert view.wait(timeout=30) == 0  # a liveness bound: it ends at once
        assert "stopped while starting" in view.stderr.read()
    finally:
        if view.poll() is None:
            view.kill()
            view.wait(30)


def test_serve_stops_at_once_on_sigterm_while_its_kernels_compile(tmp_path) -> None:
    """With Warp's kernel cache empty, a worker spends tens of seconds compiling before it serves. SIGTERM then
    either waited for the whole compile (33 to 35 s) or crashed the worker (SIGSEGV, in faulthandler's report of
    the stacks 10 s after the signal): 2 of 4 stops in an outside check of 2026-12-02. It now leaves at once,
    with status 0. Here the cache is a new folder, so the signal comes while the first modules compile."""
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "empty-warp-cache"))
    serve = subprocess.Popen([sys.executable, "-m", "badf.cli", "serve", "--device", "cpu", "--listen",
                              free_endpoint()], stderr=subprocess.PIPE, text=True, env=env)  # fmt: skip
    try:
        for line in serve.stderr:  # logged just before the kernels load
            if "loading the engine's kernels" in line:
                break
        serve.send_signal(signal.SIGTERM)
        assert serve.wait(timeout=60) == 0  # a liveness bound: one module's compile at most
        rest = serve.stderr.read()
        assert "stopped while loading the engine's kernels" in rest, rest[-2000:]
        assert "engine kernels ready" not in rest and "still running" not in rest
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.wait(30)


@pytest.mark.parametrize(("file_name", "name"), [("my frames+v2", "my_frames_v2"), ("café", "caf_"), ("x" * 120, "x" * 100)])
def test_demo_names_its_object_after_any_file(file_name: str, name: str) -> None:
    """`badf demo --mesh/--sequence` names the object after the file: a sequence's name was not cleaned up,
    and non-ASCII letters or a long name were kept, so the worker refused the registration after starting."""
    from badf.protocol import check_name
    from badf.server._demo import _key_safe

    assert check_name(_key_safe(file_name)) == name


def test_the_shutdown_report_names_every_thread_and_only_once(capsys) -> None:
    """A process still running SHUTDOWN_REPORT_AFTER_S after its stop signal writes where each thread is. The
    report reads the stacks holding the interpreter's lock (faulthandler's, which does not, crashed a worker),
    and a process that ends in time (exit_now sets the flag) writes none."""
    import threading

    from badf.server import _run

    parked = threading.Event()
    waiter = threading.Thread(target=parked.wait, name="badf-test-parked", daemon=True)
    waiter.start()
    try:
        _run._SHUTDOWN_REPORTED.clear()
        _run._report_if_still_running(0.01)
        report = capsys.readouterr().err
        assert report.startswith("badf: still running 0 s after the stop signal")
        assert "thread badf-test-parked:" in report and "thread MainThread:" in report
        assert "in _report_if_still_running" in report  # the reporting thread's own stack, read live
        _run._report_if_still_running(0.01)  # reported already: once is enough
        assert capsys.readouterr().err == ""
    finally:
        parked.set()
        waiter.join(10)
