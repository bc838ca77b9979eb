#!/usr/bin/env python3
"""The GPU check, on a machine with a GPU and no network, from the folder that
scripts/gpu-check/prepare.py packed and nothing else: crowdview makes its headless context on the
GPU (--require-gpu), renders a crowd, runs its benchmark, and crowdview_frame_bench times a frame's
CPU side; the figures and pictures go to $OUT.

    OUT=DIR scripts/gpu-check/run.py [FOLDER]        (FOLDER: default build/gpu-check)

glvnd's loaders (the folder's Debian packages) are unpacked into a scratch folder, and
LD_LIBRARY_PATH names them, the folder's libraries and the driver's /usr/local/nvidia/lib64.
Where the image has no EGL vendor file of its own, the driver's
/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json is named in
__EGL_VENDOR_LIBRARY_FILENAMES. Environment:
  GPU_CHECK_GL_DEVICE          crowdview's --gl-device (default auto). "software" rehearses the
                               check on Mesa's software EGL device, and drops --require-gpu
  GPU_CHECK_COUNT              characters in the rendered crowd (default 20000)
  GPU_CHECK_BENCHMARK_SECONDS  the benchmark's --max-seconds (default 120)
Writes gpu-check.json (context, driver, the libraries' origins, each step's command, exit status
and seconds), log.txt (every step's output), view.json and view.png (overview), street.png,
benchmark.json and frame_bench.json. Prints one line per step. Exits 0 when every step succeeded,
else 1; where no GPU context is made it stops after that step.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NVIDIA_LIBRARIES = Path("/usr/local/nvidia/lib64")
NVIDIA_EGL_VENDOR = Path("/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json")
# Where glvnd's libEGL looks for vendor files when no variable names them.
SYSTEM_EGL_VENDOR_DIRS = (Path("/etc/glvnd/egl_vendor.d"), Path("/usr/share/glvnd/egl_vendor.d"))
STEP_TIMEOUT_S = 240  # any one step; the benchmark keeps to its --max-seconds well inside it


def unpack_gl_loaders(debs: Path, root: Path) -> Path:
    """Unpacks every .deb of `debs` into `root`; returns the folder holding their libraries."""
    for deb in sorted(debs.glob("*.deb")):
        subprocess.run(["dpkg", "-x", str(deb), str(root)], check=True)
    return root / "usr/lib/x86_64-linux-gnu"


def egl_vendor_choice(env: dict[str, str]) -> str:
    """Where nothing names the EGL vendor files and none of the image's own is NVIDIA's, sets
    __EGL_VENDOR_LIBRARY_FILENAMES to the driver's file first, then the image's (Mesa's, say);
    returns what libEGL will read, in words."""
    for name in ("__EGL_VENDOR_LIBRARY_FILENAMES", "__EGL_VENDOR_LIBRARY_DIRS"):
        if env.get(name):
            return f"{name}={env[name]} (given)"
    found = [p for d in SYSTEM_EGL_VENDOR_DIRS if d.is_dir() for p in sorted(d.glob("*.json"))]
    if NVIDIA_EGL_VENDOR.is_file() and not any("nvidia" in p.read_text().lower() for p in found):
        env["__EGL_VENDOR_LIBRARY_FILENAMES"] = ":".join(str(p) for p in [NVIDIA_EGL_VENDOR, *found])
        return f"__EGL_VENDOR_LIBRARY_FILENAMES={env['__EGL_VENDOR_LIBRARY_FILENAMES']} (the image names no NVIDIA library)"
    if found:
        return "the image's: " + ", ".join(map(str, found))
    return "none: no vendor file here, so EGL will list no device"


def library_origins(program: Path, env: dict[str, str], carried: list[Path]) -> dict[str, list[str]]:
    """ldd of `program` under `env`: the libraries from the carried folders, and those from the image."""
    out = subprocess.run(["ldd", str(program)], env=env, capture_output=True, text=True).stdout
    origins: dict[str, list[str]] = {"carried": [], "image": [], "missing": []}
    for name, path in re.findall(r"^\s*(\S+) => (\S+)", out, re.M):
        if path == "not":
            origins["missing"].append(name)
        else:
            origins["carried" if any(Path(path).is_relative_to(c) for c in carried) else "image"].append(f"{name} {path}")
    return origins


def nvidia_smi() -> str | None:
    if not shutil.which("nvidia-smi"):
        return None
    done = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                          capture_output=True, text=True)
    return (done.stdout or done.stderr).strip()


class Steps:
    """Runs the check's commands one after another, logging each and recording how it went."""

    def __init__(self, env: dict[str, str], log: Path):
        self.env, self.log, self.done = env, log, []

    def run(self, name: str, command: list[str]) -> bool:
        start = time.monotonic()
        try:
            result = subprocess.run(command, env=self.env, capture_output=True, text=True, timeout=STEP_TIMEOUT_S)
            status, output = result.returncode, result.stdout + result.stderr
        except subprocess.TimeoutExpired as e:
            status, output = "timeout", f"{e.stdout or ''}{e.stderr or ''}"
        seconds = round(time.monotonic() - start, 2)
        with self.log.open("a") as f:
            f.write(f"$ {' '.join(command)}\n{output}[{name}: exit {status}, {seconds} s]\n\n")
        last = output.strip().splitlines()[-1] if output.strip() else ""
        print(f"gpu-check: {name}: exit {status} in {seconds} s" + ("" if status == 0 else f": {last}"), flush=True)
        self.done.append({"name": name, "command": command, "exit": status, "seconds": seconds})
        return status == 0


def main() -> int:
    folder = Path(sys.argv[1] if len(sys.argv) > 1 else "build/gpu-check").resolve()
    out = Path(os.environ.get("OUT", "")).resolve() if os.environ.get("OUT") else None
    if out is None or not out.is_dir():
        raise SystemExit("gpu-check: set OUT to the folder for the results")
    if not (folder / "prepared.json").is_file():
        raise SystemExit(f"gpu-check: {folder} is not a folder scripts/gpu-check/prepare.py wrote")
    device = os.environ.get("GPU_CHECK_GL_DEVICE", "auto")
    count = os.environ.get("GPU_CHECK_COUNT", "20000")
    benchmark_seconds = os.environ.get("GPU_CHECK_BENCHMARK_SECONDS", "120")
    scratch = Path(tempfile.mkdtemp(prefix="gpu-check-"))

    env = dict(os.environ)
    loaders = unpack_gl_loaders(folder / "debs", scratch / "root")
    library_path = [loaders, folder / "lib"] + ([NVIDIA_LIBRARIES] if NVIDIA_LIBRARIES.is_dir() else [])
    env["LD_LIBRARY_PATH"] = ":".join([str(p) for p in library_path] + ([env["LD_LIBRARY_PATH"]] if env.get("LD_LIBRARY_PATH") else []))
    env["CROWDVIEW_SHADERS"] = str(folder / "src/shaders")
    vendor = egl_vendor_choice(env)
    print(f"gpu-check: EGL vendor files: {vendor}", flush=True)

    crowdview, frame_bench, bundle = str(folder / "bin/crowdview"), str(folder / "bin/crowdview_frame_bench"), str(folder / "bundle")
    # A rehearsal on Mesa's software device draws on llvmpipe by intent; anything else must reach the GPU.
    context = ["--gl-device", device] + ([] if device == "software" else ["--require-gpu"])
    steps = Steps(env, out / "log.txt")
    context_report = scratch / "context.json"
    ok = steps.run("context", [crowdview, "--bundle", bundle, "--headless", "--frames", "1", "--count", "1", "--width", "64",
                               "--height", "64", "--report", str(context_report), *context])
    if ok:
        view = [crowdview, "--bundle", bundle, "--headless", "--count", count, "--width", "1920", "--height", "1080", *context]
        steps.run("view", view + ["--frames", "60", "--report", str(out / "view.json"), "--screenshot", str(out / "view.png")])
        steps.run("street", view + ["--frames", "30", "--camera", "street", "--screenshot", str(out / "street.png")])
        steps.run("benchmark", [crowdview, "--bundle", bundle, "--benchmark", "--max-seconds", benchmark_seconds, "--report",
                                str(out / "benchmark.json"), *context])
        steps.run("frame_bench", [frame_bench, "--count", "100000", "--frames", "60", "--report", str(out / "frame_bench.json"), *context])

    summary = {
        "ok": ok and all(s["exit"] == 0 for s in steps.done),
        "gl": json.loads(context_report.read_text())["gl"] if context_report.is_file() else None,
        "gpu": nvidia_smi(),
        "egl_vendor_files": vendor,
        "gl_device": device,
        "prepared": json.loads((folder / "prepared.json").read_text()),
        "libraries": library_origins(folder / "bin/crowdview", env, [folder, scratch]),
        "steps": steps.done,
    }
    (out / "gpu-check.json").write_text(json.dumps(summary, indent=2) + "\n")
    shutil.rmtree(scratch)
    gl = summary["gl"] or {}
    print(f"gpu-check: {'ok' if summary['ok'] else 'FAILED'}: {gl.get('renderer', 'no context')} ({gl.get('context', '-')}); "
          f"results in {out}", flush=True)
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
