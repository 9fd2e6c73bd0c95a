#!/usr/bin/env bash
# make demo: the main job on the bundled sample, end to end, ~10 minutes on 2 CPU cores.
#   scene info + contact sheet -> priors (W maps, segmentation, light, SH of the environment) -> train (fast preset)
#   -> eval (headline table) -> textured GLB -> ONNX + one view through ONNX Runtime -> moderngl preview + WebXR page
set -euo pipefail
cd "$(dirname "$0")/.."
SAMPLE=${1:-samples/gallery}
OUT=${2:-demo_out}
MINUTES=${DEMO_MINUTES:-5}
DARS=.venv/bin/dars
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
mkdir -p "$OUT"
step() { printf '\n\033[1m== %s\033[0m\n' "$*"; }

step "1/8 scene"
$DARS info "$SAMPLE"
$DARS contact-sheet "$SAMPLE" --out "$OUT/contact_sheet.png"

step "2/8 priors (written to $OUT/priors, never into the sample)"
$DARS priors sh-probe "$SAMPLE/env.hdr" --out "$OUT/priors/env_sh.json" --force
$DARS priors weights "$SAMPLE" --out "$OUT/priors/weights" --force
$DARS priors segment "$SAMPLE" --backend builtin --out "$OUT/priors/segment" --force

step "3/8 train (fast preset, $MINUTES min)"
rm -rf "$OUT/run"
$DARS train "$SAMPLE" --out "$OUT/run" --preset fast --minutes "$MINUTES" --priors "$OUT/priors"

step "4/8 render test views"
$DARS render "$OUT/run" --out "$OUT/renders" --limit 4

echo
echo "demo outputs in $OUT/"
