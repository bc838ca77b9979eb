#!/usr/bin/env bash
# The main job, end to end, with no server to start by hand:
#   1. set up (scripts/setup.sh)
#   2. generate the sample clothed character        -> out/demo/sample/
#   3. find its cloth cycle                          -> out/demo/cycle/ (report.html)
#   4. bake it into a bundle                         -> out/demo/bundles/sample-walker/1.0.0/
#   5. render a crowd from the bundle, headless      -> out/demo/crowd.png
#   6. a mixed crowd (runtime/README.md "Crowds of several archetypes"): the sample in a second garment on
#      the heavy build, the sample playing Idle, Walking and Running (one cloth simulation through all three,
#      baked with its timeline), and where ../shared/assets is present CesiumMan in the long skirt and the
#      robot with its cape                          -> out/demo/mixed/crowd.json, out/demo/mixed.png
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bash scripts/setup.sh
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-osmesa}"
out="out/demo"
rm -rf "$out"
mkdir -p "$out"
crowdbake=(.venv/bin/crowdbake)

echo "== 1/6 sample content =="
"${crowdbake[@]}" sample "$out/sample" --garment loose
echo "== 2/6 cycle search =="
"${crowdbake[@]}" cycle "$out/sample/cloth.pc2" --mesh "$out/sample/cloth.obj" \
  --character "$out/sample/character.glb" --out "$out/cycle"
echo "== 3/6 bake =="
"${crowdbake[@]}" bake "$out/sample/character.glb" --cloth "$out/sample/cloth.pc2" \
  --cloth-mesh "$out/sample/cloth.obj" --cycle "$out/cycle/cycle.json" --textures "$out/sample/textures" \
  --name sample-walker --version 1.0.0 --out "$out/bundles"
echo "== 4/6 crowd render =="
build/runtime/crowdview --bundle "$out/bundles/sample-walker/1.0.0" --count 200 --seed 1 \
  --camera street --headless --frames 30 --screenshot "$out/crowd.png"

echo "== 5/6 more archetypes =="
"${crowdbake[@]}" sample "$out/sample-tight" --garment tight --build heavy --seed 1
"${crowdbake[@]}" bake "$out/sample-tight/character.glb" --cloth "$out/sample-tight/cloth.pc2" \
  --cloth-mesh "$out/sample-tight/cloth.obj" --textures "$out/sample-tight/textures" \
  --name sample-tight --version 1.0.0 --out "$out/bundles"
# Idle -> Walking -> Running -> Walking -> Idle in one simulation (a coarser cloth and 512² textures keep it
# short); the bundle carries every clip's loop and the transitions where the bake publishes them, else the
# Walking loop.
"${crowdbake[@]}" sample "$out/sample-clips" --clips --garment loose --seed 2 --cloth-rows 20 --cloth-columns 48 --texture-size 512
"${crowdbake[@]}" bake "$out/sample-clips/character.glb" --cloth "$out/sample-clips/cloth.pc2" \
  --cloth-mesh "$out/sample-clips/cloth.obj" --textures "$out/sample-clips/textures" \
  --timeline "$out/sample-clips/timeline.json" --animation Walking --name sample-clips --version 1.0.0 --out "$out/bundles"
# A clip mix names clips of the bundle: only a bundle that holds the timeline's clips has them by name (one
# that fell back to the Walking loop holds one clip, named `cycle`).
# Its characters switch clip every 0.5 to 1.5 s, so the 3 s drawn below hold switches to measure.
clip_mix=""
if grep -q '"name": "Running"' "$out/bundles/sample-clips/1.0.0/manifest.json"; then
  clip_mix=', "clips": [{"clip": "Idle", "weight": 1}, {"clip": "Walking", "weight": 2}, {"clip": "Running", "weight": 1}],
     "switch_after_s": [0.5, 1.5]'
fi
archetypes='{"name": "sample-loose", "bundle": "../bundles/sample-walker/1.0.0", "share": 3, "play_rate": [0.9, 1.1]},
    {"name": "sample-tight", "bundle": "../bundles/sample-tight/1.0.0", "share": 3, "play_rate": [0.9, 1.1]},
    {"name": "sample-clips", "bundle": "../bundles/sample-clips/1.0.0", "share": 3, "play_rate": [0.9, 1.1]'"$clip_mix"'}'
assets="${CROWDBAKE_SHARED_ASSETS:-$root/../shared/assets}"
if [[ -f "$assets/CesiumMan.glb" && -f "$assets/long_skirt/long_skirt.pc2" && -f "$assets/robot_clips/robot.glb" ]]; then
  "${crowdbake[@]}" bake "$assets/CesiumMan.glb" --cloth "$assets/long_skirt/long_skirt.pc2" \
    --cloth-mesh "$assets/long_skirt/long_skirt.obj" --name cesiumman --version 1.0.0 --out "$out/bundles"
  # The robot's cape was simulated through Idle, Walking, Running and Walking: its timeline gives the bundle
  # every clip and the transitions between them.
  "${crowdbake[@]}" bake "$assets/robot_clips/robot.glb" --cloth "$assets/robot_clips/garment.pc2" \
    --cloth-mesh "$assets/robot_clips/garment.obj" --timeline "$assets/robot_clips/timeline.json" \
    --name robot --version 1.0.0 --out "$out/bundles"
  archetypes="$archetypes,
    {\"name\": \"cesiumman\", \"bundle\": \"../bundles/cesiumman/1.0.0\", \"share\": 2},
    {\"name\": \"robot\", \"bundle\": \"../bundles/robot/1.0.0\", \"share\": 1,
     \"clips\": [{\"clip\": \"Walking\", \"weight\": 2}, {\"clip\": \"Running\", \"weight\": 1}], \"switch_after_s\": [0.5, 1.5]}"
else
  echo "shared assets not found in $assets (CesiumMan.glb, long_skirt/, robot_clips/): the mixed crowd has the two sample archetypes"
fi
mkdir -p "$out/mixed"
cat > "$out/mixed/crowd.json" <<JSON
{
  "crowd_format_version": 1,
  "seed": 1,
  "count": 240,
  "archetypes": [
    $archetypes
  ],
  "layout": {"kind": "spot"},
  "camera": {"kind": "street"}
}
JSON
echo "== 6/6 mixed crowd render =="
build/runtime/crowdview --crowd "$out/mixed/crowd.json" --headless --frames 90 --impostor-blend off \
  --screenshot "$out/mixed.png" --report "$out/mixed/report.json"
echo "done: cycle report $out/cycle/report.html, bundle $out/bundles/sample-walker/1.0.0, crowd picture $out/crowd.png," \
  "mixed crowd $out/mixed.png (counts and memory per archetype: $out/mixed/report.json)"
