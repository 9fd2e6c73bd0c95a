#!/usr/bin/env bash
# One-shot, idempotent set-up for a fresh Debian 12 machine (CI runs it as root on a fresh clone):
#   1. apt packages for headless GL (EGL/llvmpipe) and Mitsuba's LLVM backend, only those missing;
#   2. .venv with the pinned packages (uv when available: ~20 s instead of ~2 min of pip);
#   3. the toolkit itself, editable, which installs the `dars` console script into .venv/bin.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=.venv
STAMP="$VENV/.installed-$(cat requirements.txt pyproject.toml tools/package-lock.json toolkit/csrc/*.cpp 2>/dev/null | sha256sum | cut -c1-16)"
[ -f "$STAMP" ] && exit 0

APT_PKGS="libgomp1 libatomic1 libx11-6 libgl1 libopengl0 libegl1 libegl-mesa0 libgl1-mesa-dri libllvm19 chromium xvfb"
missing=""
for p in $APT_PKGS; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing="$missing $p"
done
command -v node >/dev/null 2>&1 || missing="$missing nodejs npm"
if [ -n "$missing" ]; then
  echo "[setup] installing apt packages:$missing"
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing
fi

PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3
[ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip uv >/dev/null
# uv ignores pip.conf: hand it the wheel folder(s) pip is configured with (the CPU torch wheel lives there).
FIND_LINKS=""
for d in $("$VENV/bin/python" -m pip config list 2>/dev/null | sed -n "s/.*find-links='\(.*\)'/\1/p" | sort -u); do
  FIND_LINKS="$FIND_LINKS --find-links $d"
done
EXTRA=""
for u in $("$VENV/bin/python" -m pip config list 2>/dev/null | sed -n "s/.*extra-index-url='\(.*\)'/\1/p"); do
  EXTRA="$EXTRA --extra-index-url $u"
done
echo "[setup] installing Python packages into $VENV (torch==2.13.0 CPU)"
"$VENV/bin/uv" pip install -q --python "$VENV/bin/python" $FIND_LINKS $EXTRA --index-strategy unsafe-best-match -r requirements.txt
"$VENV/bin/uv" pip install -q --python "$VENV/bin/python" --no-deps -e .
"$VENV/bin/python" - <<'PY'
import torch
assert torch.__version__.startswith("2.13.0"), f"wrong torch {torch.__version__}: a CUDA build was pulled in"
import open3d, cv2, onnxruntime, kornia, pymeshlab, fast_simplification, moderngl  # noqa: F401
print(f"[setup] ok: torch {torch.__version__}, kornia {kornia.__version__}, open3d {open3d.__version__}")
PY
echo "[setup] building the CPU hash-grid kernel (once, ~1 min)"
"$VENV/bin/python" -c "from toolkit.encoding import hashgrid_kernel; import sys; sys.exit(0 if hashgrid_kernel() else 1)" \
  || echo "[setup] warning: kernel build failed; training falls back to the plain-torch encoding (slower)"
bash scripts/setup_node.sh || echo "[setup] warning: node packages (glTF validator, three.js) not installed"
rm -f "$VENV"/.installed-*
touch "$STAMP"
