#!/usr/bin/env bash
# Install the pinned Node tools (tools/package.json + tools/package-lock.json: the Khronos glTF validator) into
# tools/node_modules. Idempotent: does nothing when the installed tree matches the lock file. Without node/npm it
# prints a note and exits 0 (the tests that need the validator then skip with that reason).
set -euo pipefail
cd "$(dirname "$0")/../tools"
if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
  echo "[setup_node] node/npm not found: skipping the glTF validator (tests/test_gltf.py will skip its check)"
  exit 0
fi
STAMP="node_modules/.installed-$(sha256sum package-lock.json | cut -c1-16)"
[ -f "$STAMP" ] && exit 0
echo "[setup_node] installing pinned npm packages into tools/node_modules (npm ci)"
npm ci --no-audit --no-fund --loglevel=error
rm -f node_modules/.installed-*
touch "$STAMP"
