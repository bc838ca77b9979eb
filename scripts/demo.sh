#!/usr/bin/env bash
# The main job, end to end, with no server to start by hand:
#   1. set up (scripts/setup.sh)
#   2. generate the sample clothed character        -> out/demo/sample/
#   3. find its cloth cycle                          -> out/demo/cycle/ (report.html)
#   4. bake it into a bundle                         -> out/demo/bundles/sample-walker/1.0.0/
#   5. render a crowd from the bundle, headless      -> out/demo/crowd.png
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bash scripts/setup.sh
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-osmesa}"
out="out/demo"
rm -rf "$out"
mkdir -p "$out"
crowdbake=(.venv/bin/crowdbake)

echo "== 1/4 sample content =="
"${crowdbake[@]}" sample "$out/sample" --garment loose
echo "== 2/4 cycle search =="
"${crowdbake[@]}" cycle "$out/sample/cloth.pc2" --mesh "$out/sample/cloth.obj" \
  --character "$out/sample/character.glb" --out "$out/cycle"
echo "== 3/4 bake =="
"${crowdbake[@]}" bake "$out/sample/character.glb" --cloth "$out/sample/cloth.pc2" \
  --cloth-mesh "$out/sample/cloth.obj" --cycle "$out/cycle/cycle.json" --textures "$out/sample/textures" \
  --name sample-walker --version 1.0.0 --out "$out/bundles"
echo "== 4/4 crowd render =="
build/runtime/crowdview --bundle "$out/bundles/sample-walker/1.0.0" --count 200 --seed 1 \
  --camera street --headless --frames 30 --screenshot "$out/crowd.png"
echo "done: cycle report $out/cycle/report.html, bundle $out/bundles/sample-walker/1.0.0, crowd picture $out/crowd.png"
