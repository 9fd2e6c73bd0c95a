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

step "2/8 priors from the photos alone (shipped networks; written to $OUT/priors, never into the sample)"
# labels + metal masks by the shipped segmenter (never trained on this sample; its labels are only scored),
# W maps from the photos and those predictions, SH light by the shipped light network
$DARS priors segment "$SAMPLE" --out "$OUT/priors/segment" --force
$DARS priors weights "$SAMPLE" --out "$OUT/priors/weights" --force
$DARS priors light "$SAMPLE" --out "$OUT/priors/light" --force
$DARS priors sh-probe "$SAMPLE/env.hdr" --out "$OUT/priors/env_sh.json" --force  # for reference; training does not read it

step "3/8 train (fast preset, $MINUTES min)"
rm -rf "$OUT/run"
$DARS train "$SAMPLE" --out "$OUT/run" --preset fast --minutes "$MINUTES" --priors "$OUT/priors"

step "4/8 render every test view (all decomposed outputs) and evaluate (writes $OUT/run/eval/report.md)"
$DARS render "$OUT/run" --out "$OUT/renders"
$DARS eval "$OUT/run"

step "5/8 asset: mesh -> UV atlas -> PBR textures -> GLB"
$DARS export-asset "$OUT/run" --out "$OUT/asset" --resolution 256 --faces 100000

step "6/8 ONNX: export with parity checks, then one view through ONNX Runtime (no torch)"
$DARS export-onnx "$OUT/run" --out "$OUT/onnx"
$DARS infer "$OUT/onnx" --camera "$SAMPLE:test:0" --out "$OUT/onnx_view.png"

step "7/8 previews: moderngl (headless) and the WebXR page"
$DARS view "$OUT/asset" --headless --out "$OUT/preview.png" --camera "$SAMPLE:test:0"
$DARS export-web "$OUT/asset" "$OUT/web"

step "8/8 done"
cat <<EON
  contact sheet   $OUT/contact_sheet.png
  priors          $OUT/priors/
  trained run     $OUT/run/   (log.jsonl, loss_curves.png, checkpoint.pt)
  test renders    $OUT/renders/   (rgb, albedo, roughness, metallic, normal, semantic, depth per view)
  evaluation      $OUT/run/eval/report.md  metrics.json
  glTF asset      $OUT/asset/scene.glb
  ONNX models     $OUT/onnx/   one view rendered by ONNX Runtime: $OUT/onnx_view.png
  preview         $OUT/preview.png
  WebXR page      $OUT/web/index.html  (serve with: python3 -m http.server -d $OUT/web)
EON
