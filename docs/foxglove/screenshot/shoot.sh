#!/usr/bin/env bash
# Screenshots of a twin run log (MCAP) in the Foxglove Studio web app, headless.
# App: the prebuilt webpack bundle shipped inside npm @foxglove/studio-base@1.48.0 (assets/index.js,
# UMD, externals react/react-dom 17), mounted by web/boot.js (stand-in for the unpublished studio-web).
# Usage: shoot.sh [RUN_MCAP] [LAYOUT_JSON] [OUTDIR]
# Needs: node/npm, /usr/bin/chromium (apt-get install -y chromium). Env: PORT (8765), TIMES, PLAY_TIMES,
#        PATCHED=1 for a second pass with Foxglove's later JSON-schema fix applied to the bundle.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
RUN="${1:?usage: shoot.sh RUN_MCAP [LAYOUT_JSON] [OUTDIR]}"
LAYOUT="${2:-$HERE/../ball_drop.json}"
OUT="${3:-$HERE/shots}"
PORT="${PORT:-8765}"
mkdir -p "$OUT"
RUN="$(realpath "$RUN")"; LAYOUT="$(realpath "$LAYOUT")"; OUT="$(realpath "$OUT")"
cd "$HERE"

# 1. node deps (puppeteer-core, http-server with Range support, react 17 UMD, @mcap/core)
[ -d node_modules/puppeteer-core ] || npm install --no-audit --no-fund
# 2. the Studio web bundle from npm
if [ ! -f web/studio-base/index.js ]; then
  tmp=$(mktemp -d)
  (cd "$tmp" && npm pack @foxglove/studio-base@1.48.0 >/dev/null && tar xzf foxglove-studio-base-1.48.0.tgz package/assets)
  mkdir -p web && rm -rf web/studio-base && mv "$tmp/package/assets" web/studio-base && rm -rf "$tmp"
fi
cp node_modules/react/umd/react.production.min.js node_modules/react-dom/umd/react-dom.production.min.js web/
# 2b. the same bundle with Foxglove's later fix (studio PR #7100, "Tolerate missing properties key in
#     JSON schema", also in Lichtblick) applied, to see what a current app makes of the JSON channels
if [ ! -f web/studio-base-patched/index.js ]; then
  mkdir -p web/studio-base-patched
  for f in web/studio-base/*; do ln -sf "../studio-base/$(basename "$f")" web/studio-base-patched/; done
  # parseJsonSchema is in the main bundle and in the MCAP-reading worker chunk
  for f in $(grep -l 'Object\.entries(schema\.properties)' web/studio-base/*.js); do
    rm -f "web/studio-base-patched/$(basename "$f")"
    sed 's/Object\.entries(schema\.properties)/Object.entries(schema.properties ?? {})/' "$f" > "web/studio-base-patched/$(basename "$f")"
  done
fi
sed 's#studio-base/index.js#studio-base-patched/index.js#' web/index.html > web/index-patched.html
# 3. inputs
mkdir -p web/data "$OUT"
cp "$RUN" web/data/run.mcap
cp "$LAYOUT" web/data/layout.json
export LOG_START_NS=$(node logstart.js web/data/run.mcap)
# 4. serve (http-server answers Range requests, which the remote-file data source needs)
node_modules/.bin/http-server web -p "$PORT" -a 127.0.0.1 -c-1 -s & SRV=$!
trap 'kill $SRV 2>/dev/null || true' EXIT
for i in $(seq 50); do curl -sf -o /dev/null "http://127.0.0.1:$PORT/index.html" && break; sleep 0.2; done
export STUDIO_BASE="http://127.0.0.1:$PORT"
# 5. shoot: stock app, then the patched one
PAGE=index.html node shoot.js "$OUT" ""
if [ "${PATCHED:-0}" = 1 ]; then
  PAGE=index-patched.html TIMES="${PATCHED_TIMES:-5}" PLAY_TIMES="${PATCHED_PLAY_TIMES:-9.7}" node shoot.js "$OUT" "patched_"
fi
ls -la "$OUT"
