#!/usr/bin/env python3
"""The GPU check, on a machine with a GPU and no network, from the folder that
scripts/gpu-check/prepare.py packed and nothing else, at 1920x1080: crowdview makes its headless
context on the GPU (--require-gpu); figure 3 per representation (high, low, UV impostor, hybrid) for
the sample (crowdview --benchmark) and for the mixed crowd (bench_mixed_crowd.py --lod, LOD by
distance for hybrid); 100,000 characters of the mixed crowd: the whole frame to glFinish (crowdview
--crowd --headless --report, with GPU memory per archetype) and the frame's CPU build and upload
(crowdview_frame_bench, which draws nothing); two pictures of the mixed crowd.

    OUT=DIR scripts/gpu-check/run.py [FOLDER]        (FOLDER: default build/gpu-check)

A folder packed by `prepare.py --maps` (build/gpu-check-maps) runs the second mode instead: the GL
passes of the sample's impostor bake drawn on the GPU by the bake's own code under the folder's Python
wheels (scripts/gpu-check/maps.py compare, this checkout's crowdbake) and compared with what OSMesa drew
of the same plan (gpu-check-maps.json, log.txt; about a minute).

glvnd's loaders (the folder's Debian packages) and the bundles are unpacked into a scratch folder, and
LD_LIBRARY_PATH names them, the folder's libraries and the driver's /usr/local/nvidia/lib64.
Where the image has no EGL vendor file of its own, the driver's
/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json is named in
__EGL_VENDOR_LIBRARY_FILENAMES. Environment (the defaults take about 6 minutes on a GPU):
  GPU_CHECK_GL_DEVICE          crowdview's --gl-device (default auto). "software" rehearses the
                               check on Mesa's software EGL device, and drops --require-gpu
  GPU_CHECK_COUNT              characters in the pictures (default 20000)
  GPU_CHECK_LARGE_COUNT        characters of the frame figure (default 100000)
  GPU_CHECK_BENCHMARK_SECONDS  the sample's benchmark, its --max-seconds (default 90)
  GPU_CHECK_MIXED_SECONDS      the mixed crowd's search, each representation's (default 60)
Writes gpu-check.json (context, driver, the libraries' origins, each step's command, exit status and
seconds, the figures, and every step's report), log.txt (every step's output), view.png (overview)
and street.png. Prints one line per step. Exits 0 when every step succeeded, else 1; where no GPU
context is made it stops after that step.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
import zipfile
from pathlib import Path

SERVICES = Path(__file__).resolve().parents[2] / "services"  # this checkout's crowdbake, for the maps mode
NVIDIA_LIBRARIES = Path("/usr/local/nvidia/lib64")
NVIDIA_EGL_VENDOR = Path("/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json")
# Where glvnd's libEGL looks for vendor files when no variable names them.
SYSTEM_EGL_VENDOR_DIRS = (Path("/etc/glvnd/egl_vendor.d"), Path("/usr/share/glvnd/egl_vendor.d"))
STEP_TIMEOUT_S = 240  # any one step; the benchmarks keep to their --max-seconds well inside it
WIDTH, HEIGHT = "1920", "1080"
# Figure 3's representations as crowdview --benchmark names them, and bench_mixed_crowd.py's --lod for each.
FIGURE3_LODS = {"high_mesh": "high", "low_mesh": "low", "uv_impostor": "impostor", "hybrid": "auto"}


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


def unpack_bundles(packed: Path, root: Path) -> Path:
    """Unpacks every bundle tarball of `packed` (NAME.tar.xz holding NAME/) into root/bundles; returns root."""
    # tarfile's "data" filter (Python 3.12, and some 3.11 releases) refuses links and paths that leave the folder.
    safety = {"filter": "data"} if hasattr(tarfile, "data_filter") else {}
    for archive in sorted(packed.glob("*.tar.xz")):
        with tarfile.open(archive) as tar:
            tar.extractall(root / "bundles", **safety)
    return root


def crowd_of(folder: Path, bundles_root: Path, count: int, camera: str, path: Path) -> Path:
    """Writes the folder's crowd.json with `count` characters and `camera` to `path`, its bundles
    (bundles/NAME) named by absolute path below `bundles_root`; returns `path`."""
    description = json.loads((folder / "crowd.json").read_text())
    for archetype in description["archetypes"]:
        archetype["bundle"] = str(bundles_root / archetype["bundle"])
    path.write_text(json.dumps(dict(description, count=count, camera={"kind": camera})))
    return path


def read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def figures(benchmark: dict | None, mixed: dict[str, dict | None], large: dict | None, frame_bench: dict | None) -> dict:
    """The headline numbers of the steps' reports: N at 30 and 60 fps per representation, the large
    crowd's frame and GPU memory per archetype, the frame bench's CPU milliseconds."""
    def n_at(result: dict | None) -> dict | None:
        return None if result is None else {k: result.get(k) for k in ("n_at_30fps", "n_at_60fps", "converged_30", "converged_60")}

    sample = (benchmark or {}).get("results", {})
    return {
        "figure3_sample": {mode: n_at(sample.get(mode)) for mode in FIGURE3_LODS},
        "figure3_mixed": {mode: n_at((report or {}).get("results")) for mode, report in mixed.items()},
        "large_crowd": None if large is None else {
            "characters": {a["name"]: a.get("characters") for a in large.get("archetypes", [])},
            "frame_ms_median": large.get("frame_ms_median"), "gpu_draw_ms_median": large.get("gpu_draw_ms_median"),
            "cpu_build_ms_per_frame": large.get("cpu_build_ms_per_frame"), "draw_calls": large.get("draw_calls"), "triangles": large.get("triangles"),
            "gpu_memory_bytes": {a["name"]: a.get("gpu_memory_bytes") for a in large.get("archetypes", [])},
            "gpu_memory_bytes_total": large.get("gpu_memory_bytes_total")},
        "frame_bench_cpu": None if frame_bench is None else frame_bench.get("results"),
    }


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


def gl_environment(folder: Path, scratch: Path) -> tuple[dict[str, str], str]:
    """This process's environment with the folder's GL loaders (unpacked under scratch), its libraries and
    the driver's on LD_LIBRARY_PATH and the EGL vendor files chosen (egl_vendor_choice); and that choice."""
    env = dict(os.environ)
    loaders = unpack_gl_loaders(folder / "debs", scratch / "root")
    library_path = [loaders, folder / "lib"] + ([NVIDIA_LIBRARIES] if NVIDIA_LIBRARIES.is_dir() else [])
    env["LD_LIBRARY_PATH"] = ":".join([str(p) for p in library_path] + ([env["LD_LIBRARY_PATH"]] if env.get("LD_LIBRARY_PATH") else []))
    vendor = egl_vendor_choice(env)
    print(f"gpu-check: EGL vendor files: {vendor}", flush=True)
    return env, vendor


def unpack_wheels(wheels: Path, site: Path) -> Path:
    """Every wheel of `wheels` unzipped into `site`, which then imports them as pip would have installed them."""
    for wheel in sorted(wheels.glob("*.whl")):
        with zipfile.ZipFile(wheel) as archive:
            archive.extractall(site)
    return site


def run_maps(folder: Path, out: Path, device: str, prepared: dict) -> int:
    """The second mode (module docstring): one step, scripts/gpu-check/maps.py, and its report."""
    running = f"{sys.version_info.major}.{sys.version_info.minor}"
    if prepared.get("python") != running:
        raise SystemExit(f"gpu-check: {folder} carries wheels for Python {prepared.get('python')}, this is {running} "
                         f"(prepare.py --maps --python {running})")
    scratch = Path(tempfile.mkdtemp(prefix="gpu-check-maps-"))
    env, vendor = gl_environment(folder, scratch)
    with tarfile.open(folder / "work.tar.xz") as tar:
        tar.extractall(scratch, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    site = unpack_wheels(folder / "wheels", scratch / "site")
    env.update(PYOPENGL_PLATFORM="egl", PYTHONPATH=f"{site}:{SERVICES}", PYTHONNOUSERSITE="1")
    steps = Steps(env, out / "log.txt")
    report = scratch / "maps.json"
    steps.run("maps", [sys.executable, "-s", str(Path(__file__).with_name("maps.py")), "compare", str(scratch / "work"),
                       str(folder / "maps.npz"), str(report), "--gl-device", device])
    summary = {"ok": all(s["exit"] == 0 for s in steps.done), "mode": "maps", "gpu": nvidia_smi(), "egl_vendor_files": vendor,
               "gl_device": device, "prepared": prepared, "steps": steps.done, "maps": read_json(report)}
    (out / "gpu-check-maps.json").write_text(json.dumps(summary, indent=2) + "\n")
    shutil.rmtree(scratch)
    print(f"gpu-check: {'ok' if summary['ok'] else 'FAILED'}: maps; results in {out}", flush=True)
    return 0 if summary["ok"] else 1


def main() -> int:
    folder = Path(sys.argv[1] if len(sys.argv) > 1 else "build/gpu-check").resolve()
    out = Path(os.environ.get("OUT", "")).resolve() if os.environ.get("OUT") else None
    if out is None or not out.is_dir():
        raise SystemExit("gpu-check: set OUT to the folder for the results")
    if not (folder / "prepared.json").is_file():
        raise SystemExit(f"gpu-check: {folder} is not a folder scripts/gpu-check/prepare.py wrote")
    device = os.environ.get("GPU_CHECK_GL_DEVICE", "auto")
    prepared = json.loads((folder / "prepared.json").read_text())
    if prepared.get("mode") == "maps":
        return run_maps(folder, out, device, prepared)
    count = int(os.environ.get("GPU_CHECK_COUNT", "20000"))
    large_count = int(os.environ.get("GPU_CHECK_LARGE_COUNT", "100000"))
    benchmark_seconds = os.environ.get("GPU_CHECK_BENCHMARK_SECONDS", "90")
    mixed_seconds = os.environ.get("GPU_CHECK_MIXED_SECONDS", "60")
    scratch = Path(tempfile.mkdtemp(prefix="gpu-check-"))

    env, vendor = gl_environment(folder, scratch)
    env["CROWDVIEW_SHADERS"] = str(folder / "src/shaders")

    crowdview, frame_bench = str(folder / "bin/crowdview"), str(folder / "bin/crowdview_frame_bench")
    unpacked = unpack_bundles(folder / "bundles", scratch)
    sample = str(unpacked / "bundles/sample-loose")
    # A rehearsal on Mesa's software device draws on llvmpipe by intent; anything else must reach the GPU.
    context = ["--gl-device", device] + ([] if device == "software" else ["--require-gpu"])
    size = ["--width", WIDTH, "--height", HEIGHT]
    steps = Steps(env, out / "log.txt")
    reports = scratch / "reports"
    reports.mkdir()
    ok = steps.run("context", [crowdview, "--bundle", sample, "--headless", "--frames", "1", "--width", "64",
                               "--height", "64", "--report", str(reports / "context.json"), *context])
    mixed_lods = {}
    if ok:
        for camera, frames in (("overview", "60"), ("street", "30")):
            steps.run(camera, [crowdview, "--crowd", str(crowd_of(folder, unpacked, count, camera, scratch / f"{camera}.json")), "--headless",
                               "--frames", frames, *size, "--screenshot", str(out / ("view.png" if camera == "overview" else "street.png")), *context])
        steps.run("large_crowd", [crowdview, "--crowd", str(crowd_of(folder, unpacked, large_count, "overview", scratch / "large.json")),
                                  "--headless", "--frames", "30", *size, "--report", str(reports / "large_crowd.json"), *context])
        steps.run("frame_bench", [frame_bench, "--count", str(large_count), "--archetypes", "4", "--frames", "60",
                                  "--report", str(reports / "frame_bench.json"), *context])
        steps.run("figure3_sample", [crowdview, "--bundle", sample, "--benchmark", "--modes", ",".join(FIGURE3_LODS), *size,
                                     "--max-seconds", benchmark_seconds, "--report", str(reports / "figure3_sample.json"), *context])
        # The whole crowd on screen, as crowdview --benchmark draws it.
        mixed_crowd = crowd_of(folder, unpacked, 240, "overview", scratch / "mixed.json")
        for mode, lod in FIGURE3_LODS.items():
            mixed_lods[mode] = reports / f"figure3_mixed_{mode}.json"
            steps.run(f"figure3_mixed_{mode}", [sys.executable, str(folder / "bench_mixed_crowd.py"), str(mixed_crowd),
                                                "--crowdview", crowdview, "--lod", lod, "--gl-device", device, "--width", WIDTH,
                                                "--height", HEIGHT, "--max-seconds", mixed_seconds, "--out", str(mixed_lods[mode])])

    step_reports = {p.stem: read_json(p) for p in sorted(reports.glob("*.json"))}
    summary = {
        "ok": ok and all(s["exit"] == 0 for s in steps.done),
        "gl": (step_reports.get("context") or {}).get("gl"),
        "gpu": nvidia_smi(),
        "egl_vendor_files": vendor,
        "gl_device": device,
        "prepared": prepared,
        "libraries": library_origins(folder / "bin/crowdview", env, [folder, scratch]),
        "steps": steps.done,
        "figures": figures(step_reports.get("figure3_sample"), {m: step_reports.get(p.stem) for m, p in mixed_lods.items()},
                           step_reports.get("large_crowd"), step_reports.get("frame_bench")),
        "bundles": read_json(folder / "bundles.json"),
        "reports": step_reports,
    }
    (out / "gpu-check.json").write_text(json.dumps(summary, indent=2) + "\n")
    shutil.rmtree(scratch)
    gl = summary["gl"] or {}
    print(f"gpu-check: {'ok' if summary['ok'] else 'FAILED'}: {gl.get('renderer', 'no context')} ({gl.get('context', '-')}); "
          f"results in {out}", flush=True)
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
