"""Probe, not part of the product: the registers and local-memory spills of the corners' kernels on a GPU
architecture, without a GPU. Warp compiles each kernel to PTX with its own NVRTC (ahead of time, no driver needed),
and `ptxas -v` from a CUDA toolkit reports what the kernel would use.

    python3 bench/probes/probe_spills.py [--variant NAME=FOLDER ...] [--arch 90] [--ptxas PATH] [--out F.json]

Each variant (a repository root or `.ab/NAME`, as `bench/interleave.py` takes them; default: this checkout) is
compiled in a process of its own. The kernels: the corners' winding numbers, their searches (whole, and split), the
sign kernel and the query kernel of a field signed by winding numbers (`SIGN_WINDING` = 2), which walk in float64
where float32 cancels. The winding kernel is capped at 48 registers (`SIGN_MAX_REGISTERS`) and the
searches at 64, so what grows is the spill traffic: bytes of spill stores and loads in the code (a static count,
not how often they run), and the stack frame (the walks' node stacks, and the spills' slots). PTX from Warp's NVRTC
may be newer than the toolkit's ptxas reads; its `.version` line is then lowered to the toolkit's (9.0 for CUDA
13.0), which these kernels' instructions do not need.
"""

import argparse
import glob
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile

sys.path.insert(0, __file__.rsplit("/", 3)[0])
from badf.bench.interleave import _package_root, variant_environment  # noqa: E402

_COMPILE = r"""
import json, sys, warp as wp
wp.config.quiet = True
wp.init()
from badf.server.adf import _distance
kernels = {"winding": _distance.winding_kernel(), "searches": _distance._corner_searches(False),
           "searches (split)": _distance._corner_searches(True), "sign (winding)": _distance.sign_kernel(2),
           "queries (winding)": _distance.query_kernel(2)}
out = {}
for name, kernel in kernels.items():
    folder = sys.argv[1] + "/" + name.replace(" ", "_").replace("(", "").replace(")", "")
    out[name] = [str(p) for p in wp.compile_aot_module(kernel.module, arch=int(sys.argv[2]), module_dir=folder,
                                                       use_ptx=True)]
print(json.dumps(out))
"""

_REPORT = re.compile(
    r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads.*?Used (\d+) registers", re.S)


def find_ptxas(given: str | None) -> str:
    found = given or shutil.which("ptxas") or next(iter(sorted(glob.glob("/usr/local/cuda*/bin/ptxas"))), None)
    if not found:
        raise SystemExit("probe_spills: no ptxas on the PATH or under /usr/local/cuda*/bin (give --ptxas)")
    return found


def toolkit_ptx_version(ptxas: str) -> str:
    """The newest PTX ISA this ptxas reads, from the error it gives for a newer one."""
    with tempfile.NamedTemporaryFile("w", suffix=".ptx", delete=False) as f:
        f.write(".version 99.0\n.target sm_90\n.address_size 64\n")
    result = subprocess.run([ptxas, "-arch=sm_90", f.name, "-o", os.devnull], capture_output=True, text=True)
    os.unlink(f.name)
    match = re.search(r"current version is '([\d.]+)'", result.stderr)
    return match.group(1) if match else "9.0"


def measure(ptx: pathlib.Path, ptxas: str, arch: int, version: str) -> dict:
    text = ptx.read_bytes().replace(b"\0", b"").decode()
    text = re.sub(r"^\.version [\d.]+", f".version {version}", text, count=1, flags=re.M)
    lowered = ptx.with_suffix(".lowered.ptx")
    lowered.write_text(text)
    result = subprocess.run([ptxas, f"-arch=sm_{arch}", "-v", str(lowered), "-o", os.devnull], capture_output=True,
                            text=True)
    match = _REPORT.search(result.stderr)
    if result.returncode != 0 or not match:
        raise SystemExit(f"probe_spills: ptxas failed on {ptx}:\n{result.stderr[-2000:]}")
    frame, stores, loads, registers = (int(g) for g in match.groups())
    return {"registers": registers, "stack_frame_bytes": frame, "spill_store_bytes": stores,
            "spill_load_bytes": loads}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", action="append", default=[], help="NAME=FOLDER (repeat); default: this checkout")
    parser.add_argument("--arch", type=int, default=90)
    parser.add_argument("--ptxas", default=None)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    ptxas = find_ptxas(args.ptxas)
    version = toolkit_ptx_version(ptxas)
    here = pathlib.Path(__file__).resolve().parents[2]
    variants = dict(v.split("=", 1) for v in args.variant) or {"tree": str(here)}
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for name, folder in variants.items():
            root = _package_root(pathlib.Path(folder), pathlib.Path(scratch), name)
            compiled = subprocess.run([sys.executable, "-c", _COMPILE, f"{scratch}/{name}-ptx", str(args.arch)],
                                      env=variant_environment(root), capture_output=True, text=True)
            if compiled.returncode != 0:
                raise SystemExit(f"probe_spills: {name} did not compile:\n{compiled.stderr[-3000:]}")
            for kernel, paths in json.loads(compiled.stdout.strip().splitlines()[-1]).items():
                rows.append({"variant": name, "kernel": kernel, **measure(pathlib.Path(paths[0]), ptxas, args.arch,
                                                                          version)})
    print(f"sm_{args.arch}, {ptxas} (PTX read as .version {version}):")
    print(f"{'variant':>10} {'kernel':>18} {'registers':>10} {'stack frame':>12} {'spill stores':>13} "
          f"{'spill loads':>12}")
    for r in rows:
        print(f"{r['variant']:>10} {r['kernel']:>18} {r['registers']:>10} {r['stack_frame_bytes']:>12} "
              f"{r['spill_store_bytes']:>13} {r['spill_load_bytes']:>12}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"arch": args.arch, "ptxas": ptxas, "ptx_version": version, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
