#!/usr/bin/env python3
"""Packs the GPU check into one folder that a bare CUDA machine with no network runs alone
(scripts/gpu-check/run.py): crowdview and crowdview_frame_bench as built here, the shared
libraries they load that such an image lacks, glvnd's GL loaders as Debian packages, the shaders
and a bundle.

    scripts/gpu-check/prepare.py [--build build/runtime] [--out build/gpu-check] [--bundle DIR]

--bundle: a baked bundle folder (scripts/demo.sh bakes out/demo/bundles/sample-walker/1.0.0); by
default the synthetic test bundle (make_synthetic_bundle), which runs every step but is no
character worth measuring. The libraries are read off `ldd`, less glibc and the C++ runtime, which
a CUDA image has in newer versions. The folder is refused over 60 MiB: a device run carries 64 MiB,
the working tree included. Prints one line per part and the folder's size.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PROGRAMS = ("crowdview", "crowdview_frame_bench")
# glvnd's loaders: libEGL.so.1 and libOpenGL.so.0 are what libepoxy opens; the rest keep glvnd whole.
GL_LOADER_PACKAGES = ("libegl1", "libglvnd0", "libopengl0", "libgl1", "libglx0", "libgles2")
# The C library and the C++ runtime: every CUDA image has them, newer than this build's.
IMAGE_LIBRARIES = re.compile(r"^(linux-vdso|ld-linux|libc|libm|libdl|libpthread|librt|libresolv|libutil|libstdc\+\+|libgcc_s)[.-]")
MAX_BYTES = 60 << 20


def shared_libraries(program: Path) -> dict[str, Path]:
    """soname -> resolved path of every library `program` loads, by ldd; raises on a missing one."""
    out = subprocess.run(["ldd", str(program)], check=True, capture_output=True, text=True).stdout
    libraries = {}
    for line in out.splitlines():
        m = re.match(r"\s*(\S+) => (\S+|not found)", line)
        if not m:
            continue
        if m.group(2) == "not found":
            raise SystemExit(f"prepare: {program.name} needs {m.group(1)}, which ldd does not find here")
        libraries[m.group(1)] = Path(m.group(2))
    return libraries


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build", type=Path, default=ROOT / "build/runtime", help="crowdview's build folder")
    parser.add_argument("--out", type=Path, default=ROOT / "build/gpu-check", help="the folder to write (replaced)")
    parser.add_argument("--bundle", type=Path, help="a bundle folder to render and benchmark (default: a synthetic one)")
    args = parser.parse_args()
    programs = [args.build / name for name in PROGRAMS]
    for p in programs:
        if not p.is_file():
            raise SystemExit(f"prepare: {p} is missing; build crowdview first (scripts/setup.sh)")
    if args.bundle and not (args.bundle / "manifest.json").is_file():
        raise SystemExit(f"prepare: {args.bundle} has no manifest.json")

    if args.out.exists():
        shutil.rmtree(args.out)
    for sub in ("bin", "lib", "debs"):
        (args.out / sub).mkdir(parents=True)
    for p in programs:
        shutil.copy2(p, args.out / "bin" / p.name)

    carried: dict[str, str] = {}
    for p in programs:
        for soname, path in shared_libraries(p).items():
            if IMAGE_LIBRARIES.match(soname) or soname in carried:
                continue
            shutil.copy2(path, args.out / "lib" / soname)  # follows the soname link to the library itself
            carried[soname] = str(path)
    print(f"prepare: {len(carried)} shared libraries")

    subprocess.run(["apt-get", "download", *GL_LOADER_PACKAGES], cwd=args.out / "debs", check=True, capture_output=True, text=True)
    debs = sorted(p.name for p in (args.out / "debs").glob("*.deb"))
    if len(debs) != len(GL_LOADER_PACKAGES):
        raise SystemExit(f"prepare: apt-get download gave {debs} for {list(GL_LOADER_PACKAGES)}")
    print(f"prepare: GL loaders {', '.join(debs)}")

    # The shaders include "../config.h": they keep their place beside it.
    shutil.copytree(ROOT / "runtime/src/shaders", args.out / "src/shaders")
    shutil.copy2(ROOT / "runtime/src/config.h", args.out / "src/config.h")
    bundle = args.out / "bundle"
    if args.bundle:
        shutil.copytree(args.bundle, bundle)
    else:
        subprocess.run([str(args.build / "tests/make_synthetic_bundle"), str(bundle)], check=True, capture_output=True)
    name = json.loads((bundle / "manifest.json").read_text())["name"]
    print(f"prepare: bundle {name}")

    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    os_release = dict(re.findall(r'^(\w+)="?([^"\n]*)"?$', Path("/etc/os-release").read_text(), re.M))
    (args.out / "prepared.json").write_text(json.dumps({"commit": commit, "built_on": os_release.get("PRETTY_NAME", "?"),
                                                        "libraries": carried, "gl_loader_debs": debs, "bundle": name}, indent=2) + "\n")
    size = folder_bytes(args.out)
    if size > MAX_BYTES:
        raise SystemExit(f"prepare: {args.out} is {size / 2**20:.1f} MiB, over the {MAX_BYTES >> 20} MiB a device run can carry")
    print(f"prepare: wrote {args.out} ({size / 2**20:.1f} MiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
