#!/usr/bin/env python3
"""Packs the GPU check into one folder that a bare CUDA machine with no network runs alone
(scripts/gpu-check/run.py): crowdview and crowdview_frame_bench as built here, the shared
libraries they load that such an image lacks, glvnd's GL loaders as Debian packages, the shaders,
scripts/bench_mixed_crowd.py, four real bundles and a mixed crowd of them (crowd.json).

    scripts/gpu-check/prepare.py [--build build/runtime] [--out build/gpu-check] [--bundles-from DIR]
        [--work build/gpu-check-work] [--crowdbake PATH]
    scripts/gpu-check/prepare.py --maps [--out build/gpu-check-maps] [--python 3.12]

--maps packs the check's second mode instead (run.py tells them apart by prepared.json): the sample's
impostor plan and scene from a bake with its work folder kept, the maps OSMesa draws of them here
(scripts/gpu-check/maps.py draw), glvnd's loaders, and the Python packages the bake's GL passes import,
as wheels for --python (the GPU image's) at this environment's versions: about 40 MiB.

The bundles are scripts/demo.sh's archetypes: the sample in its loose and its tight garment (heavy
build), CesiumMan in the long skirt and the robot with its clips (../shared/assets, or
$CROWDBAKE_SHARED_ASSETS). --bundles-from takes them from a folder of baked bundles (NAME/VERSION,
as demo.sh's out/demo/bundles); else each is baked under --work with smaller impostors and textures
than the demo's, so that all four travel, and kept there: a second prepare with the same recipe bakes
nothing. bundles.json says where each came from, how it was baked and its size. The libraries are
read off `ldd`, less glibc and the C++ runtime, which a CUDA image has in newer versions. The folder
is refused over 60 MiB: a device run carries 64 MiB, the working tree included. Prints one line per
part and the folder's size.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PROGRAMS = ("crowdview", "crowdview_frame_bench")
# glvnd's loaders: libEGL.so.1 and libOpenGL.so.0 are what libepoxy opens; the rest keep glvnd whole.
GL_LOADER_PACKAGES = ("libegl1", "libglvnd0", "libopengl0", "libgl1", "libglx0", "libgles2")
# The C library and the C++ runtime: every CUDA image has them, newer than this build's.
IMAGE_LIBRARIES = re.compile(r"^(linux-vdso|ld-linux|libc|libm|libdl|libpthread|librt|libresolv|libutil|libstdc\+\+|libgcc_s)[.-]")
MAX_BYTES = 60 << 20
# What the bake's impostor maps import (crowdbake.stages.impostors under pyrender's EGL platform): carried as
# wheels at the versions installed here. trimesh works without scipy, which would not fit.
MAPS_PACKAGES = ("numpy", "PyOpenGL", "pyrender", "trimesh", "networkx", "pillow", "pyglet", "freetype-py", "imageio", "six")
ASSETS = Path(os.environ.get("CROWDBAKE_SHARED_ASSETS", ROOT.parent / "shared/assets"))
VERSION = "1.0.0"
# The demo bakes 88-texel tiles, 16 MiB of impostor maps a clip and the sample's textures at
# crowdbake's default size: its four bundles are about 160 MiB. These keep three elevations (azimuths
# fall to 12 before frames do) and bring the four to about 64 MiB, 20 packed.
TRAVEL_BAKE = ("--tile", "64", "--impostor-budget", "4", "--no-export")
TRAVEL_SAMPLE = ("--texture-size", "512")


@dataclass(frozen=True)
class Archetype:
    """One archetype of the mixed crowd: how its bundle is baked (crowdbake's arguments, run in its
    work folder) and what the crowd description says of it beside its name and bundle."""

    name: str  # the archetype's and its bundle's name
    demo_name: str  # its bundle's name in scripts/demo.sh, looked for in --bundles-from
    recipe: tuple[tuple[str, ...], ...]
    crowd: dict = field(default_factory=dict, hash=False)


def sample_recipe(name: str, *sample_args: str) -> tuple[tuple[str, ...], ...]:
    """`crowdbake sample` then its bake (the bake searches the cloth cycle itself)."""
    return (("sample", "sample", *sample_args, *TRAVEL_SAMPLE),
            ("bake", "sample/character.glb", "--cloth", "sample/cloth.pc2", "--cloth-mesh", "sample/cloth.obj",
             "--textures", "sample/textures", "--name", name, "--version", VERSION, *TRAVEL_BAKE, "--out", "bundles"))


def archetypes(assets: Path) -> list[Archetype]:
    """scripts/demo.sh's mixed crowd, less the sample playing three clips (the robot plays clips)."""
    walking = {"play_rate": [0.9, 1.1]}
    skirt, robot = assets / "long_skirt", assets / "robot_clips"
    return [
        Archetype("sample-loose", "sample-walker", sample_recipe("sample-loose", "--garment", "loose"), dict(share=3, **walking)),
        Archetype("sample-tight", "sample-tight",
                  sample_recipe("sample-tight", "--garment", "tight", "--build", "heavy", "--seed", "1"), dict(share=3, **walking)),
        Archetype("cesiumman", "cesiumman",
                  (("bake", str(assets / "CesiumMan.glb"), "--cloth", str(skirt / "long_skirt.pc2"), "--cloth-mesh",
                    str(skirt / "long_skirt.obj"), "--name", "cesiumman", "--version", VERSION, *TRAVEL_BAKE, "--out", "bundles"),),
                  dict(share=2)),
        # Its clips and transitions share one impostor budget (the others' 4 MiB a clip, 6 for all).
        Archetype("robot", "robot",
                  (("bake", str(robot / "robot.glb"), "--cloth", str(robot / "garment.pc2"), "--cloth-mesh", str(robot / "garment.obj"),
                    "--timeline", str(robot / "timeline.json"), "--name", "robot", "--version", VERSION, "--tile", "64",
                    "--impostor-archetype-budget", "6", "--no-export", "--out", "bundles"),),
                  dict(share=1, clips=[{"clip": "Walking", "weight": 2}, {"clip": "Running", "weight": 1}], switch_after_s=[0.5, 1.5])),
    ]


def baked_bundle(archetype: Archetype, work: Path, crowdbake: str) -> Path:
    """The archetype's bundle baked under work/NAME by its recipe; reused where recipe.json there is
    this recipe and the bake finished. Raises SystemExit naming the step that failed."""
    folder = work / archetype.name
    bundle = folder / "bundles" / archetype.name / VERSION
    recipe_file = folder / "recipe.json"
    recipe = [list(step) for step in archetype.recipe]
    if (bundle / "manifest.json").is_file() and recipe_file.is_file() and json.loads(recipe_file.read_text()) == recipe:
        print(f"prepare: {archetype.name}: baked before, in {bundle}")
        return bundle
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    env = dict(os.environ, PYOPENGL_PLATFORM=os.environ.get("PYOPENGL_PLATFORM", "osmesa"))
    for step in recipe:
        print(f"prepare: {archetype.name}: crowdbake {' '.join(step)}", flush=True)
        done = subprocess.run([crowdbake, *step], cwd=folder, env=env, capture_output=True, text=True)
        (folder / f"{step[0]}.log").write_text(done.stdout + done.stderr)
        if done.returncode != 0:
            raise SystemExit(f"prepare: {archetype.name}: crowdbake {step[0]} failed (exit {done.returncode}); see {folder / step[0]}.log")
    recipe_file.write_text(json.dumps(recipe, indent=1) + "\n")  # written last: it marks a finished bake
    return bundle


def packed(bundle: Path, name: str, archive: Path) -> Path:
    """`bundle`'s files as NAME/ in an xz tarball at `archive`: pose caches and block-compressed maps
    shrink to about a third, which is what lets the robot's clips travel."""
    with tarfile.open(archive, "w:xz", preset=6) as tar:
        tar.add(bundle.resolve(), arcname=name)  # a linked bundle folder is packed, not the link
    return archive


def packed_bake(archetype: Archetype, bundle: Path, work: Path) -> Path:
    """The baked bundle's tarball, kept beside its bake and made again only after a new bake."""
    archive = work / archetype.name / "bundle.tar.xz"
    if archive.is_file() and archive.stat().st_mtime >= (work / archetype.name / "recipe.json").stat().st_mtime:
        return archive
    return packed(bundle, archetype.name, archive)


def found_bundle(archetype: Archetype, bundles: Path) -> Path:
    """The newest version of the archetype's bundle in a NAME/VERSION folder, by its name or the demo's."""
    for name in (archetype.name, archetype.demo_name):
        versions = sorted(p.parent for p in (bundles / name).glob("*/manifest.json"))
        if versions:
            return versions[-1]
    raise SystemExit(f"prepare: {bundles} has no {archetype.name} (or {archetype.demo_name}) bundle as NAME/VERSION/manifest.json")


def crowd_entry(archetype: Archetype, manifest: dict) -> dict:
    """The archetype's line of crowd.json; a clip mix only where the bundle holds those clips by name
    (a bake that fell back to one loop holds one clip, `cycle`)."""
    entry = {"name": archetype.name, "bundle": f"bundles/{archetype.name}", **archetype.crowd}
    clips = {c.get("name") for c in manifest.get("clips", [])}
    if not all(c["clip"] in clips for c in entry.get("clips", [])):
        del entry["clips"]
        entry.pop("switch_after_s", None)
    return entry


def bundle_record(archetype: Archetype, bundle: Path, archive: Path, source: str, manifest: dict) -> dict:
    """bundles.json's line for one bundle: where it came from, its recipe and what it holds."""
    impostor = manifest.get("impostor", {})
    return {"bundle": f"bundles/{archetype.name}.tar.xz", "name": manifest["name"], "version": manifest["version"],
            "format_version": manifest.get("format_version"), "source": source,
            "crowdbake": [["crowdbake", *step] for step in archetype.recipe] if source == "baked here" else None,
            "bytes": folder_bytes(bundle), "packed_bytes": archive.stat().st_size, "clips": [c.get("name") for c in manifest.get("clips", [])],
            "impostor_views": {"azimuths": len(impostor.get("azimuths_deg", [])), "elevations": len(impostor.get("elevations_deg", [])),
                               "frames": len(impostor.get("frame_indices", [])), "tile_crop": impostor.get("crop")}}


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


def gl_loader_debs(folder: Path) -> list[str]:
    """glvnd's loader packages downloaded into `folder` (apt-get download); their file names."""
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(["apt-get", "download", *GL_LOADER_PACKAGES], cwd=folder, check=True, capture_output=True, text=True)
    debs = sorted(p.name for p in folder.glob("*.deb"))
    if len(debs) != len(GL_LOADER_PACKAGES):
        raise SystemExit(f"prepare: apt-get download gave {debs} for {list(GL_LOADER_PACKAGES)}")
    print(f"prepare: GL loaders {', '.join(debs)}")
    return debs


def maps_archetype() -> Archetype:
    """The sample in its loose garment as the mixed crowd's, baked with its work folder kept."""
    steps = sample_recipe("maps-sample", "--garment", "loose")
    return Archetype("maps-sample", "sample-walker", (steps[0], (*steps[1], "--work", "work")))


def python_wheels(python: str, folder: Path, environment_python: str) -> list[str]:
    """MAPS_PACKAGES as wheels for CPython `python` on x86-64 Linux, at environment_python's versions."""
    versions = json.loads(subprocess.run(
        [environment_python, "-c", "import importlib.metadata as m, json, sys; print(json.dumps([m.version(p) for p in sys.argv[1:]]))",
         *MAPS_PACKAGES], check=True, capture_output=True, text=True).stdout)
    abi = "cp" + python.replace(".", "")
    platforms = [arg for tag in ("manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64", "any") for arg in ("--platform", tag)]
    done = subprocess.run([environment_python, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:", "--python-version",
                           python, "--implementation", "cp", "--abi", abi, *platforms, "--dest", str(folder),
                           *(f"{p}=={v}" for p, v in zip(MAPS_PACKAGES, versions))], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"prepare: pip download of the maps' wheels for Python {python} failed: {done.stderr.strip().splitlines()[-1:]}")
    wheels = sorted(p.name for p in folder.glob("*.whl"))
    print(f"prepare: {len(wheels)} wheels for Python {python}: {', '.join(wheels)}")
    return wheels


def prepare_maps(args: argparse.Namespace) -> int:
    """The --maps folder (module docstring)."""
    if args.out.exists():
        shutil.rmtree(args.out)
    args.out.mkdir(parents=True)
    archetype = maps_archetype()
    bundle = baked_bundle(archetype, args.work, args.crowdbake)
    work = args.work / archetype.name / "work"
    with tarfile.open(args.out / "work.tar.xz", "w:xz", preset=6) as tar:
        for name in ("stage.json", "record.json", "scene.npz"):  # the plan and its scene: what draw_task reads
            tar.add(work / "impostor" / name, arcname=f"work/impostor/{name}")
    environment_python = str(Path(args.crowdbake).with_name("python"))
    drawn = subprocess.run([environment_python, str(ROOT / "scripts/gpu-check/maps.py"), "draw", str(work), str(args.out / "maps.npz")],
                           env=dict(os.environ, PYOPENGL_PLATFORM="osmesa", PYTHONPATH=str(ROOT / "services")), capture_output=True, text=True)
    if drawn.returncode != 0:
        raise SystemExit(f"prepare: drawing the maps under OSMesa failed: {(drawn.stderr.strip().splitlines() or ['?'])[-1]}")
    print(f"prepare: {drawn.stdout.strip()}")
    debs = gl_loader_debs(args.out / "debs")
    wheels = python_wheels(args.python, args.out / "wheels", environment_python)
    manifest = json.loads((bundle / "manifest.json").read_text())
    (args.out / "prepared.json").write_text(json.dumps({
        "mode": "maps", "commit": git_commit(), "python": args.python, "wheels": wheels, "gl_loader_debs": debs,
        "bake": [["crowdbake", *step] for step in archetype.recipe], "bundle": {"name": manifest["name"], "version": manifest["version"]},
    }, indent=2) + "\n")
    return finished(args.out)


def git_commit() -> str:
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()


def finished(folder: Path) -> int:
    """Refuses a folder over MAX_BYTES; else prints its size."""
    size = folder_bytes(folder)
    if size > MAX_BYTES:
        raise SystemExit(f"prepare: {folder} is {size / 2**20:.1f} MiB, over the {MAX_BYTES >> 20} MiB a device run can carry")
    print(f"prepare: wrote {folder} ({size / 2**20:.1f} MiB)")
    return 0


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build", type=Path, default=ROOT / "build/runtime", help="crowdview's build folder")
    parser.add_argument("--out", type=Path, help="the folder to write (replaced; default build/gpu-check, --maps build/gpu-check-maps)")
    parser.add_argument("--bundles-from", type=Path, help="a folder of baked bundles, NAME/VERSION (default: bake them under --work)")
    parser.add_argument("--work", type=Path, default=ROOT / "build/gpu-check-work", help="where bakes are made and kept")
    parser.add_argument("--crowdbake", default=str(ROOT / ".venv/bin/crowdbake"), help="the crowdbake command")
    parser.add_argument("--maps", action="store_true", help="pack the second mode: the bake's maps on the GPU against OSMesa's")
    parser.add_argument("--python", default="3.12", help="--maps: the GPU image's Python, for its wheels (default 3.12)")
    args = parser.parse_args()
    args.out = args.out or ROOT / ("build/gpu-check-maps" if args.maps else "build/gpu-check")
    if args.maps:
        return prepare_maps(args)
    programs = [args.build / name for name in PROGRAMS]
    for p in programs:
        if not p.is_file():
            raise SystemExit(f"prepare: {p} is missing; build crowdview first (scripts/setup.sh)")
    crowd = archetypes(ASSETS)
    if args.bundles_from:
        sources = {a.name: (found_bundle(a, args.bundles_from), str(args.bundles_from)) for a in crowd}
    else:
        if not ASSETS.is_dir():
            raise SystemExit(f"prepare: no shared assets in {ASSETS} (CesiumMan, long_skirt, robot_clips); set CROWDBAKE_SHARED_ASSETS")
        sources = {a.name: (baked_bundle(a, args.work, args.crowdbake), "baked here") for a in crowd}

    if args.out.exists():
        shutil.rmtree(args.out)
    for sub in ("bin", "lib", "debs", "bundles"):
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

    debs = gl_loader_debs(args.out / "debs")

    # The shaders include "../config.h": they keep their place beside it.
    shutil.copytree(ROOT / "runtime/src/shaders", args.out / "src/shaders")
    shutil.copy2(ROOT / "runtime/src/config.h", args.out / "src/config.h")
    shutil.copy2(ROOT / "scripts/bench_mixed_crowd.py", args.out / "bench_mixed_crowd.py")
    records, entries = {}, []
    for archetype in crowd:
        bundle, source = sources[archetype.name]
        archive = args.out / "bundles" / f"{archetype.name}.tar.xz"
        if args.bundles_from:
            packed(bundle, archetype.name, archive)
        else:
            shutil.copy2(packed_bake(archetype, bundle, args.work), archive)
        manifest = json.loads((bundle / "manifest.json").read_text())
        record = records[archetype.name] = bundle_record(archetype, bundle, archive, source, manifest)
        entries.append(crowd_entry(archetype, manifest))
        print(f"prepare: bundle {archetype.name} ({record['bytes'] / 2**20:.1f} MiB, packed {record['packed_bytes'] / 2**20:.1f}; {source})")
    description = {"crowd_format_version": 1, "seed": 1, "count": 240, "archetypes": entries,
                   "layout": {"kind": "spot"}, "camera": {"kind": "street"}}
    (args.out / "crowd.json").write_text(json.dumps(description, indent=2) + "\n")
    (args.out / "bundles.json").write_text(json.dumps(
        {"baked_smaller_than_the_demo": " ".join(("crowdbake bake", *TRAVEL_BAKE, "(the robot: --impostor-archetype-budget 6),",
                                                   "crowdbake sample", *TRAVEL_SAMPLE)),
         "bundles": records}, indent=2) + "\n")

    commit = git_commit()
    os_release = dict(re.findall(r'^(\w+)="?([^"\n]*)"?$', Path("/etc/os-release").read_text(), re.M))
    (args.out / "prepared.json").write_text(json.dumps({"mode": "crowdview", "commit": commit, "built_on": os_release.get("PRETTY_NAME", "?"),
                                                        "libraries": carried, "gl_loader_debs": debs, "bundles": list(records)}, indent=2) + "\n")
    return finished(args.out)


if __name__ == "__main__":
    sys.exit(main())
